"""Calibration of `mtbudget diagnose` on concealed, simulated recordings: the detection table of docs/diagnose.md.

Run:  python benchmarks/calibrate_diagnose.py [--cases 100] [--only new|library|noise|families|stations|five_axis]

Each case: a machine with random geometric errors larger than the effect, a
tracker at a random pose, drifting and cycling temperatures, the example
recordings' noise, and zero, one or two hidden effects at a multiple of the
point noise. Written and read back as a recording (some in inch, minutes and
degF). The concealed effects are drawn by the opt-in sources of the plugins,
written independently of the candidates' refit.

Rows of issue 16: misstated noise (range 4x, transverse 2x, repeatability 3x,
nothing hidden), effects outside the library (an x error in x*y*z; and the
new families against the original eight-family library), and the new
families in the library.  Reported per row (the counting rule is in
:func:`row` and docs/diagnose.md): wrong named effects, right (the hidden
effect named, and named alone), findings declared confounded with an
explanation outside the library, any finding, and "explained" while the
misfit is significant (never allowed).

Rows of issue 30 (``--only physics [--set 2]``): recordings of tests/physics_generator.py (a lead-screw periodic
error of X, an ADM cyclic error, a range scale of 10-30 um/m, a local backlash of X, a tracker azimuth zero
turning in time, nulls), the physics put into the measured points by plain numpy independent of the candidates;
``--set 2`` draws other seeds and magnitudes.

Rows of issue 20 (``--only stations``): recordings of four stations (two laser trackers, two tracking
interferometers), drawn by the independent numpy generator of tests/test_diagnose_stations.py (its own chain,
rotation and spherical noise; not mtbudget's simulator, nor any candidate's columns), each case its own machine
and station poses (jittered by 100 mm and 0.05 rad about the test's), with a range offset of 25-30 um (random
sign) on one tracker station chosen at random, or none.

Rows of the rotary candidates (``--only five_axis``): recordings of examples/five_axis_cafxyz.toml drawn by mtbudget's
simulator with its own options (``--set``; the mesh 2 x 2 x 2 instead of 3 x 3 x 3, the 5 A x 4 C angles and two
tools kept: 320 points), each case its own seed (every source of the example drawn anew, the machine's geometric
errors per trial too): nulls (rotary_reversal and rotary_encoder off, every other source at the example's values),
a reversal of C in [0, 150] urad (C's encoder error off), an encoder error of C with amplitudes in [0, 100] urad
(C's reversal off).  Counted: a rotary candidate the trial did not draw named as a finding (false naming), or as a
partial effect of a recording left NOT EXPLAINED (not a finding, counted apart), the drawn one named, and
z = (estimate - truth) / u per term.
``--full-mesh`` keeps the example's 3 x 3 x 3 mesh (1080 points, about a minute a case); ``--rows 0`` the nulls only.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from mtbudget.plugins import default_host
from mtbudget.testing import (
    declared_outside,
    expected,
    named,
    named_alone,
    named_or_confounded,
    run_case,
    wrong_named,
)

SINGLE = [("thermal_expansion", "x"), ("thermal_expansion", "y"), ("thermal_expansion", "z"), ("reversal", "x"),
          ("reversal", "y"), ("reversal", "z"), ("tracker_drift", None), ("axis_coupling", "xy"),
          ("air_temperature_drift", None), ("tracker_range_offset", None)]
NEW = [("spindle_growth", None), ("column_tilt", "x"), ("tool_length", None), ("axis_polynomial", "xy2")]
NOISE = [{"range": 4.0}, {"range": 3.0}, {"transverse": 2.0}, {"repeatability": 3.0}]
PAIRS = [(("thermal_expansion", "x"), ("reversal", "y")), (("tracker_drift", None), ("reversal", "x")),
         (("thermal_expansion", "y"), ("axis_coupling", "xy"))]
ORIGINAL = {"thermal_expansion", "reversal", "tracker_drift", "tracker_range_offset", "tracker_range_scale",
            "air_temperature_drift", "approximation_degree", "axis_coupling"}


def label(e):
    return e[0] + (f"[{e[1]}]" if e[1] else "")


def row(title, n, seed0, effects, cands, multiple=2.5, noise=None, imperial_every=4):
    """One row over n cases; the counting rule (docs/diagnose.md, "Calibration beyond the library"):

    * wrong named effect: a case with a finding that is not the hidden effect, not declared confounded with it, and
      not declared confounded with an explanation outside the library (``mtbudget.testing.wrong_named``);
      "before" applies the same rule without the declarations outside the library (the findings themselves are
      unchanged by them, so both come from the same run);
    * right: every hidden effect is named (alone or with a declared confounder) or declared confounded with a
      named one (another candidate the data fit as well); then in parentheses "named": every hidden effect is itself
      a finding, and "named alone": a finding with no confounder, neither in the library nor outside it;
    * declared outside: a case with a finding declared confounded with an explanation outside the library;
    * any finding: a case with a finding of any kind (in a row with nothing hidden, every one is a false claim).
    """
    want = {expected(e) for e in effects} - {None}
    wrong = wrong_before = right = right_named = alone = outside = claims = bad_explained = unexpl = 0
    what, what_before = Counter(), Counter()
    for k in range(n):
        d, _ = run_case(seed0 + k, effects, multiple, imperial=k % imperial_every == 0, candidates=cands, noise=noise)
        nm = named(d)
        bad = wrong_named(d, want)
        conf = named_or_confounded(d)
        bad_before = {e for e in nm - want if not (want and want <= conf)}
        wrong += bool(bad)
        wrong_before += bool(bad_before)
        what.update(label(e) for e in bad)
        what_before.update(label(e) for e in bad_before)
        right += bool(want) and want <= conf
        right_named += bool(want) and want <= nm
        alone += bool(want) and want <= named_alone(d)
        outside += bool(declared_outside(d))
        claims += bool(nm)
        unexpl += d.unexplained is not None
        # explained with a clearly significant misfit against the noise the gate used (stated or estimated)
        if d.unexplained is None and d.noise["used"] == "stated" and d.final["chi2_per_dof"] > 1.3:
            bad_explained += 1
    in_library = want <= {(c.effect, c.axis) for c in cands}
    right_txt = f"{right / n:.0%} ({right_named / n:.0%} / {alone / n:.0%})" if want and in_library else "-"
    print(f"| {title} | {n} | {wrong / n:.0%} | {right_txt} | {outside / n:.0%} | {claims / n:.0%} | {unexpl / n:.0%} | "
          f"{bad_explained} | {', '.join(f'{k} {v}' for k, v in what.most_common(3)) or '-'} | "
          f"{wrong_before / n:.0%} ({', '.join(f'{k} {v}' for k, v in what_before.most_common(3)) or '-'}) |",
          flush=True)


def _stations_generator():
    """tests/test_diagnose_stations.py's independent generator, loaded from its file."""
    path = Path(__file__).resolve().parents[1] / "tests" / "test_diagnose_stations.py"
    if str(path.parent) not in sys.path:  # it imports tests/stations_generator.py
        sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location("_four_station_generator", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def stations_row(title, n, seed0, offset, cands, far=False, both=False):
    """One row of four-station cases: (wrong named, right, unexplained, explained-while-significant)."""
    from mtbudget.diagnose import diagnose

    gen = _stations_generator()
    stations = gen.STATIONS
    if far:  # the bundled example's trackers, about 2 m from the points
        stations = [(1, "xyz", np.array([-900.0, 250.0, 700.0, -0.002, 0.0004, -0.30])),
                    (2, "xyz", np.array([2900.0, 320.0, 650.0, 0.001, -0.0005, 2.80]))] + gen.STATIONS[2:]
    wrong = right = unexpl = bad_explained = alone = 0
    what, z = Counter(), []
    for k in range(n):
        rng = np.random.default_rng(seed0 + k)
        value = float(rng.uniform(25e-3, 30e-3) * rng.choice([-1.0, 1.0]))  # mm
        sid = int(rng.choice([1, 2]))
        offsets = {1: value, 2: value} if both else ({sid: value} if offset else {})
        want = ({"tracker_range_offset"} if both else {f"station_range_offset[{sid}]"}) if offset or both else set()
        d = diagnose(gen.four_stations(seed0 + k, offsets, jitter=1.0, stations=stations), cands)
        nm = {f.candidate.label for f in d.findings}
        conf = nm | {c["effect"] + (f"[{c['axis']}]" if c["axis"] else "") for f in d.findings for c in f.confounded_with}
        out_decl = {f.candidate.label for f in d.findings if f.outside}
        wrong += bool(nm - want - out_decl) and not (want and want <= conf)
        right += bool(want) and want <= conf
        alone += bool(want) and nm == want and all(f.named_alone for f in d.findings)
        what.update(nm - want)
        unexpl += d.unexplained is not None
        if d.unexplained is None and d.noise["used"] == "stated" and d.final["chi2_per_dof"] > 1.3:
            bad_explained += 1
        for f in d.findings:
            if want and f.candidate.label in want:
                z.append((f.estimate[0] - value * 1e3) / f.uncertainty[0])
    zt = f"; (estimate - truth)/u: mean {np.mean(z):+.2f}, sd {np.std(z, ddof=1):.2f}" if len(z) > 1 else ""
    right_txt = f"{right / n:.0%} (named alone {alone / n:.0%})" if want_any(offset, both) else "-"
    print(f"| {title} | {n} | {wrong / n:.0%} | {right_txt} | {unexpl / n:.0%} | {bad_explained} | "
          f"{', '.join(f'{k} {v}' for k, v in what.most_common(3)) or '-'}{zt} |", flush=True)


def _physics_generator():
    """tests/physics_generator.py (issue 30), loaded from its file."""
    path = Path(__file__).resolve().parents[1] / "tests" / "physics_generator.py"
    spec = importlib.util.spec_from_file_location("_physics_generator", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


#: what a diagnosis should name for each kind of tests/physics_generator.py
PHYSICS_EXPECTED = {"none": None, "screw": ("periodic_error", "x"), "adm": ("periodic_error", "range"),
                    "range_scale": ("tracker_range_scale", None), "local_backlash": ("reversal", "x"),
                    "rotation": ("tracker_rotation_drift", None)}


def physics_case(gen, kind, seed, variant=1):
    """Diagnose one recording of tests/physics_generator.py: (outcome, z-scores, diagnosis).  Outcomes: "right" (the
    effect named, or declared confounded with a finding, with the right period, region and size: every z within 3),
    "right name, wrong size", "not explained" (no finding, NOT EXPLAINED), "missed" (explained without it),
    "wrong" (a finding that is not the effect nor declared confounded with it), "claim" (a finding on a null)."""
    from mtbudget.diagnose import diagnose

    rng = np.random.default_rng(np.random.SeedSequence([seed, variant, 30]))
    eff = gen.draw(kind, rng, variant)
    d = diagnose(gen.recording(seed, eff))
    want = PHYSICS_EXPECTED[kind]
    if want is None:
        return ("claim" if d.findings else "no claim"), {}, d
    z = {}
    hit = None
    for f in d.findings:
        key = (f.candidate.effect, f.candidate.axis)
        conf = {(c["effect"], c["axis"]) for c in f.confounded_with}
        if key == want:
            hit = f
        elif want not in conf and not f.outside:
            return "wrong", z, d
    if hit is None:
        if any(want in {(c["effect"], c["axis"]) for c in f.confounded_with} for f in d.findings):
            return "right (declared confounded)", z, d
        return ("not explained" if d.unexplained is not None else "missed"), z, d
    x = hit.details
    if kind in ("screw", "adm"):
        z["period"] = (x["period"]["value"] - eff["period"]) / x["period_uncertainty"]["value"]
        z["amplitude"] = (hit.estimate[0] - eff["amplitude"] * 1e3) / hit.uncertainty[0]
    elif kind == "range_scale":
        z["scale"] = (hit.estimate[0] - eff["scale"] * 1e6) / hit.uncertainty[0]
    elif kind == "local_backlash":
        if x.get("kind") != "local":
            return "right name, said uniform", z, d
        z["boundary_mm"] = x["boundary"]["value"] - eff["above"]
        z["B"] = (hit.estimate[1] - eff["B"] * 1e3) / hit.uncertainty[1]
        z["B elsewhere"] = hit.estimate[0] / hit.uncertainty[0]
    elif kind == "rotation":
        z["azimuth rate"] = (hit.estimate[0] - eff["rate"] * 3.6e9) / hit.uncertainty[0]
    ok = all(abs(v) <= 3 for k, v in z.items() if k != "boundary_mm") and abs(z.get("boundary_mm", 0.0)) <= 25.0
    return ("right" if ok else "right name, wrong size"), z, d


def physics_rows(n, seed0, variant=1):
    """The rows of issue 30: each kind of tests/physics_generator.py over n recordings."""
    gen = _physics_generator()
    for kind in gen.KINDS:
        out, zs, t0 = Counter(), {}, time.time()
        for k in range(n):
            o, z, _ = physics_case(gen, kind, seed0 + k, variant)
            out[o] += 1
            for key, v in z.items():
                zs.setdefault(key, []).append(v)
        ztxt = "; ".join(f"{k} mean {np.mean(v):+.2f} sd {np.std(v, ddof=1) if len(v) > 1 else 0:.2f}"
                         for k, v in zs.items()) or "-"
        print(f"| {kind} (set {variant}) | {n} | " + ", ".join(f"{k} {v}" for k, v in out.most_common())
              + f" | {ztxt} | {(time.time() - t0) / n:.1f} s |", flush=True)


FIVE_AXIS = Path(__file__).resolve().parents[1] / "examples" / "five_axis_cafxyz.toml"
FIVE_AXIS_SMALL = ("mesh.step_x=400 mm", "mesh.step_y=400 mm", "mesh.step_z=300 mm")
FIVE_AXIS_ROWS = (
    ("five-axis null: rotary_reversal and rotary_encoder off", None,
     ("sources.rotary_reversal.B_max=0 urad", "sources.rotary_encoder.E_max=0 urad")),
    ("five-axis: rotary_reversal of C, B in [0, 150] urad (C's encoder off)", "rotary_reversal[c]",
     ("sources.rotary_reversal.B_max=150 urad", "sources.rotary_reversal.axes=c", "sources.rotary_encoder.axes=a")),
    ("five-axis: rotary_encoder of C, amplitudes in [0, 100] urad (C's reversal off)", "rotary_periodic_error[c]",
     ("sources.rotary_encoder.E_max=100 urad", "sources.rotary_encoder.axes=c", "sources.rotary_reversal.axes=a")),
)


def five_axis_rows(n, seed0=80_000, full_mesh=False, rows=None):
    """The rows of the rotary candidates: each over n recordings of the five-axis example (see the module doc);
    ``full_mesh``: the example's own 3 x 3 x 3 mesh (1080 points, about a minute per case); ``rows``: their indices."""
    import tempfile

    from mtbudget.config import load_config
    from mtbudget.diagnose import diagnose
    from mtbudget.recording import read_recording, write_recording
    from mtbudget.scenario import build_scenario
    from mtbudget.simulate import simulate_recording

    rotary = ("rotary_reversal", "rotary_periodic_error")
    for title, hidden, sets in [r for j, r in enumerate(FIVE_AXIS_ROWS) if rows is None or j in rows]:
        sc = build_scenario(load_config(FIVE_AXIS, list(() if full_mesh else FIVE_AXIS_SMALL) + list(sets)))
        title += ", the example's mesh" if full_mesh else ""
        out, zs, others, t0 = Counter(), [], Counter(), time.time()
        for k in range(n):
            rec, truth = simulate_recording(sc, seed0 + k, 0)
            with tempfile.TemporaryDirectory() as tmp:
                write_recording(rec, Path(tmp) / "r", truth=truth)
                d = diagnose(read_recording(Path(tmp) / "r"), data_driven=False)
            drawn = truth["diagnosable"]
            names = [f.candidate.label for f in d.findings]
            partial = [p["effect"] + (f"[{p['axis']}]" if p.get("axis") else "")
                       for p in ((d.unexplained or {}).get("partial") or [])]

            def was_drawn(lb):
                v = (drawn.get(lb) or {}).get("value")
                vals = [x for x in (v if isinstance(v, list) else [v]) if x is not None]
                return any(abs(x) > 1.0 for x in vals)  # urad

            out["false rotary finding"] += any(lb.startswith(rotary) and not was_drawn(lb) for lb in names)
            out["false rotary partial"] += any(lb.startswith(rotary) and not was_drawn(lb) for lb in partial)
            out["unexplained"] += d.unexplained is not None
            out["any finding"] += bool(names)
            for lb in names:
                others[lb] += 1
            if hidden:
                f = next((f for f in d.findings if f.candidate.label == hidden), None)
                out["hidden named"] += f is not None
                if f is not None:
                    v = drawn[hidden]["value"]
                    v = v if isinstance(v, list) else [v]
                    kept = getattr(f.candidate, "kept", None)
                    v = [v[["c1", "s1", "c2", "s2"].index(t)] for t in kept] if kept else v
                    zs += [(e - t) / u for e, u, t in zip(f.estimate, f.uncertainty, v) if u > 0 and t is not None]
        ztxt = f"z mean {np.mean(zs):+.2f}, sd {np.std(zs, ddof=1):.2f} ({len(zs)} terms)" if len(zs) > 1 else "-"
        print(f"| {title} | {n} | {out['false rotary finding'] / n:.0%} | {out['false rotary partial'] / n:.0%} | "
              + (f"{out['hidden named'] / n:.0%}" if hidden else "-")
              + f" | {out['any finding'] / n:.0%} | {out['unexplained'] / n:.0%} | {ztxt} | "
              + (", ".join(f"{k} {v}" for k, v in others.most_common()) or "-")
              + f" | {(time.time() - t0) / n:.1f} s |", flush=True)


def want_any(offset, both):
    return bool(offset or both)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--multiple", type=float, default=2.5)
    ap.add_argument("--only", choices=("all", "new", "library", "noise", "families", "stations", "physics",
                                       "five_axis"),
                    default="all")
    ap.add_argument("--set", type=int, default=1, choices=(1, 2),
                    help="--only physics: the first set of recordings, or the second (other seeds and magnitudes)")
    ap.add_argument("--full-mesh", action="store_true",
                    help="--only five_axis: the example's own mesh (1080 points, about a minute a case), not 2 x 2 x 2")
    ap.add_argument("--rows", default=None,
                    help="--only five_axis: which rows, e.g. 0 (the nulls) or 0,2; default all")
    args = ap.parse_args()
    cands = default_host().candidates()
    original = [c for c in cands if c.effect in ORIGINAL]
    n = args.cases
    t0 = time.time()
    if args.only == "physics":
        print("| case | recordings | outcomes | (estimate - truth)/u (boundary: estimate - truth, mm) | per case |")
        print("| --- | --- | --- | --- | --- |")
        physics_rows(n, 60_000 if args.set == 1 else 970_000, args.set)
        print(f"\n({time.time() - t0:.0f} s)")
        return
    if args.only == "five_axis":
        print("| case | recordings | false rotary finding | false rotary partial | drawn effect named | any finding | "
              "unexplained | z = (estimate - truth)/u where named | findings (count) | per case |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        five_axis_rows(n, full_mesh=args.full_mesh,
                       rows=None if args.rows is None else {int(x) for x in args.rows.split(",")})
        print(f"\n({time.time() - t0:.0f} s)")
        return
    if args.only != "stations":
        print("| case | cases | wrong named effect | right (named / named alone) | declared confounded outside the library "
              "| any finding | unexplained | explained with chi2/dof > 1.3 | wrong named | before: wrong named effect "
              "(what) |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    else:
        print("| case | cases | wrong named effect | right (named alone) | unexplained | explained with chi2/dof > 1.3 "
              "| wrong claims; z |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
    if args.only in ("all", "new", "noise"):
        row("none", n, 20_000, (), cands)
        for nz in NOISE:
            row("none, noise " + ", ".join(f"{k} {v:g}x" for k, v in nz.items()), n, 21_000, (), cands, noise=nz)
    if args.only in ("all", "new", "families"):
        row("x error in x*y*z (outside the library)", n, 22_000, (("axis_polynomial", "xyz"),), cands, 4.0)
        for eff in NEW:
            row(f"{label(eff)} against the original library", n, 23_000, (eff,), original, 3.0)
        for eff in NEW:
            row(f"{label(eff)}", n, 24_000, (eff,), cands, args.multiple)
    if args.only in ("all", "library"):
        for eff in SINGLE:
            row(f"{label(eff)}", n, 30_000, (eff,), cands, args.multiple)
        for pair in PAIRS:
            row(" + ".join(label(e) for e in pair), n // 2, 40_000, pair, cands, 3.0, imperial_every=2)
    if args.only in ("all", "stations"):
        row_title = "four stations (trackers 0.9-1.8 m from the points): "
        stations_row(row_title + "none", n, 50_000, False, cands)
        stations_row(row_title + "station_range_offset, 25-30 um on one tracker", n, 51_000, True, cands)
        stations_row(row_title + "the same offset on both trackers (tracker_range_offset)", n, 52_000, False, cands,
                     both=True)
        stations_row("four stations, trackers 1.75-2.25 m from the points: station_range_offset, 25-30 um", n, 53_000,
                     True, cands, far=True)
    print(f"\n({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
