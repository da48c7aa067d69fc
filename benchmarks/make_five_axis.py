"""Write five-axis recordings (format 3) for campaigns on data mtbudget has not seen (issue 26).

    python benchmarks/make_five_axis.py OUT [--n 8] [--kinds CAFXYZ,FXYZCB] [--seed 1] [--linear both]
                                          [--null 0.25] [--random] [--truth-dir DIR] [--check]

Each recording is a folder OUT/<kind>_<i>/ with recording.toml, points.csv and (unless --truth-dir puts it
elsewhere, for blind campaigns) truth.json, drawn by tests/fiveaxis_generator.py: numpy and scipy's exact
rotations only, no mtbudget code.  --random draws the machine and plan too (pivots, rotary angles, linear grid,
tool offsets, tracker pose, error magnitudes x 0.3..3); otherwise the presets of the generator (CAFXYZ 3x3x3 x A 5
x C 4 x 2 tools, 1080 rows; FXYZCB 3x3x3 x C 4 x B 5 x 2 tools, one lateral).  --null is the fraction of
recordings with perfect rotary axes.  OUT/manifest.json lists what each holds.

--check then runs `python -m mtbudget identify <folder> --json` on each and prints chi2 per dof and the largest
|z| of the rotary parameters (and at the end the rms of z over the parameters identifiable alone: a calibration
of identify's stated uncertainties) through their identifiable combinations (tests/fiveaxis_check.py; k = 1
uncertainties as identify states them), with the count beyond 3; the exit status is 1 if any recording fails
the issue's criteria (chi2/dof outside [0.8, 1.25], |z| > 3 or a non-identifiable parameter left unnamed) or if
not_identifiable is not the null space of the generator's own Jacobian for that plan.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import fiveaxis_generator as g  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--n", type=int, default=8, help="number of recordings (default 8)")
    ap.add_argument("--kinds", default=",".join(g.KINDS), help="comma-separated chain codes of the generator")
    ap.add_argument("--seed", type=int, default=1, help="master seed (default 1)")
    ap.add_argument("--linear", choices=("yes", "no", "both"), default="both",
                    help="linear-axis errors and squareness: in every recording, none, or alternating")
    ap.add_argument("--null", type=float, default=0.25, help="fraction of recordings with perfect rotary axes")
    ap.add_argument("--random", action="store_true", help="random machines and plans, not the presets")
    ap.add_argument("--truth-dir", type=Path, help="write truth.json here (<kind>_<i>.json), not in the recording")
    ap.add_argument("--check", action="store_true", help="identify each with mtbudget and compare with the truth")
    a = ap.parse_args(argv)
    kinds = a.kinds.split(",")
    for k in kinds:
        if k not in g.PRESETS:
            ap.error(f"--kinds: {k!r} is not one of {', '.join(g.PRESETS)}")
    rng = np.random.default_rng(a.seed)
    n_null = int(round(a.null * a.n))
    null_at = set(rng.choice(a.n, n_null, replace=False).tolist()) if n_null else set()
    a.out.mkdir(parents=True, exist_ok=True)
    manifest, failed, single = [], 0, []
    for i in range(a.n):
        kind = kinds[i % len(kinds)]
        seed = int(rng.integers(1 << 31))
        linear = {"yes": True, "no": False, "both": (i // len(kinds)) % 2 == 1}[a.linear]
        null = i in null_at
        over = g.random_overrides(np.random.default_rng(seed + 1), kind) if a.random else {}
        folder = a.out / f"{kind}_{i}"
        truth = g.make_recording(folder, kind, linear_errors=linear, null=null, seed=seed, **over)
        if a.truth_dir:
            a.truth_dir.mkdir(parents=True, exist_ok=True)
            (folder / "truth.json").replace(a.truth_dir / f"{kind}_{i}.json")
        entry = {"folder": folder.name, "kind": kind, "seed": seed, "linear_errors": linear, "null": null,
                 "random_machine": a.random, "rows": truth["plan"]["rows"], "plan": truth["plan"]["description"]}
        manifest.append(entry)
        print(f"{folder}: {kind}, seed {seed}, linear errors {linear}, null {null}, {truth['plan']['rows']} rows")
        if a.check:
            failed += not _check(folder, truth, entry, single)
    (a.out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    if a.check:
        print(f"{len(manifest) - failed} of {len(manifest)} recordings meet the criteria")
        if single:
            z = np.array(single)
            print(f"rotary parameters identifiable alone: {len(z)} z-values, rms {np.sqrt(np.mean(z ** 2)):.3f} "
                  f"(1 if identify's uncertainties are right), |z| > 2 in {np.mean(np.abs(z) > 2):.1%} (4.6 %), "
                  f"|z| > 3 in {np.mean(np.abs(z) > 3):.2%} (0.27 %)")
    return 1 if failed else 0


def _check(folder: Path, truth: dict, entry: dict, single: list) -> bool:
    from fiveaxis_check import compare, null_problems

    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "mtbudget", "identify", str(folder), "--json"],
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if run.returncode != 0:
        print(f"  identify exited {run.returncode}: {run.stderr.strip()[-300:]}")
        entry["check"] = {"exit": run.returncode}
        return False
    result = json.loads(run.stdout)
    rows = compare(result, truth, g.all_rotary_names(truth["kind"]))
    zs = [abs(z) for _, z, _ in rows if z is not None]
    single += [z for n, z, text in rows if z is not None and text.startswith(f"+1 {n}:")]  # exact, not a bound
    unnamed = [n for n, z, text in rows if z is None and text != "named in not_identifiable"]
    nulls = null_problems(result, truth)
    chi2 = result["chi2_per_dof"]
    ok = 0.8 <= chi2 <= 1.25 and max(zs, default=0) <= 3 and not unnamed and not nulls
    entry["check"] = {"chi2_per_dof": float(chi2), "max_abs_z": float(max(zs, default=0.0)), "beyond_3u": int(sum(z > 3 for z in zs)),
                      "unnamed": unnamed, "null_space": nulls, "wall_s": wall}
    print(f"  chi2/dof {chi2:.3f}, largest |z| {max(zs, default=0):.2f} of {len(zs)} rotary checks "
          f"({sum(z > 3 for z in zs)} beyond 3), {len(result.get('not_identifiable', []))} combinations named"
          f"{', unnamed: ' + ', '.join(unnamed) if unnamed else ''}"
          f"{', null space: ' + '; '.join(nulls) if nulls else ''}, identify {wall:.1f} s"
          f"  -> {'ok' if ok else 'FAIL'}")
    for name, z, text in rows:
        if z is not None and abs(z) > 3:
            print(f"    {name}: z = {z:+.2f}; {text}")
    return ok


if __name__ == "__main__":
    sys.exit(main())
