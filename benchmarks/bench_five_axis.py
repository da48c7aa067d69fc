"""Five-axis speed (issue 26): the Monte Carlo of a five-axis verification per measured row, against the three-axis
path on a plan of the same number of rows, both measured in this run (the machines here are shared: ratios, not
seconds, are the figures).

Run:  python benchmarks/bench_five_axis.py [--short 128] [--long 640] [--rounds 3] [--before REV]

Arms (each the slope of ``runner.run`` CPU time between two run lengths, so the run's one-off work is left out;
median of ``--rounds`` alternating rounds):

* ``five-axis``: the bundled ``five_axis_cafxyz`` example (CAFXYZ, 540 poses x 2 tools = 1080 rows, every source
  of its configuration, the rotary ones among them);
* ``three-axis``: the same configuration as an XFYZ machine (no [rotary]) on a 9 x 10 x 6 mesh, 2 tools: 1080 rows,
  the same sources but the rotary ones, the same degrees;
* ``five-axis before``, ``three-axis before`` (``--before REV``): both configurations on git revision REV, in one
  subprocess per round (what a change cost or saved each arm).

Each arm's scenario is built once and its GUF beside the Monte Carlo (``budget.point_guf``, which ``run`` computes
at the start of every run: 6-8 s of CPU for these 540-point meshes, against about 1 ms a trial) is computed once
and reused: the slope is then the trials' own cost.  Before this (issue 31), every run built the scenario and the
GUF again and the slope over 1024 trials (about 1 s of CPU) was the difference of two 8-9 s totals: rounds of the
same tree scattered from 0.08 to 0.83 us/row.

Prints CPU seconds per trial and per measured row, and five-axis / three-axis.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from mtbudget import runner  # noqa: E402
from mtbudget.budget import point_guf  # noqa: E402
from mtbudget.config import bundled_config, load_config  # noqa: E402
from mtbudget.runner import run  # noqa: E402
from mtbudget.scenario import build_scenario  # noqa: E402

THREE_AXIS_TOML = """
format = "mtbudget-config/1"
name = "three_axis_1080_rows"
machine = "XFYZ"
seed = 2026
[mesh]
x = ["-200 mm", "200 mm"]
y = ["-225 mm", "225 mm"]
z = ["-100 mm", "150 mm"]
step_x = "50 mm"
step_y = "50 mm"
step_z = "50 mm"
[plan]
runs = 1
tools = [["0 mm", "0 mm", "-100 mm"], ["0 mm", "0 mm", "-200 mm"]]
stop_time = "8 s"
[tracker]
D = "-1500 mm"
L = "200 mm"
H = "300 mm"
a = "0.5 deg"
b = "-1 deg"
d = "17 deg"
angular = "5 urad"
[machine_tool]
max_degree = 2
[geometric_errors]
seed = 11
translational = ["8 um", "3 um"]
angular = ["20 urad", "8 urad"]
squareness = "30 urad"
[sources]
disable = ["approximation_degree"]
[sources.tracker_noise]
angular_mean = "5 urad"
angular_sd = "0.75 urad"
"""

_CHILD = r"""
import sys, time
from mtbudget import runner
from mtbudget.config import bundled_config, load_config
from mtbudget.scenario import build_scenario
if hasattr(runner, "point_guf"):  # the GUF once per scenario (see the module's docstring)
    _guf, _memo = runner.point_guf, {}
    runner.point_guf = lambda sc, *a, **k: _memo[id(sc)] if id(sc) in _memo else _memo.setdefault(id(sc), _guf(sc, *a, **k))
short, long = int(sys.argv[1]), int(sys.argv[2])
out = []
for path in sys.argv[3:]:
    sc = build_scenario(load_config(bundled_config("five_axis_cafxyz") if path == "five" else path))
    # warm-up: this copy compiles its kernels first (a fresh cache: the merge's kernels too, which a run of one block
    # does not call; compiled inside the short run, they made its slope about half the engine's own cost)
    runner.run(sc, trials=short, block=64, attribution_trials=0)
    t = {}
    for n in (short, long):
        c = time.process_time()
        runner.run(sc, trials=n, block=64, attribution_trials=0)
        t[n] = time.process_time() - c
    out.append((t[long] - t[short]) / (long - short))
print(*out)
"""

_GUF = {}


def _guf_once(scenario, *args, **kwargs):
    """``budget.point_guf`` once per scenario (this benchmark runs one scenario many times)."""
    if id(scenario) not in _GUF:
        _GUF[id(scenario)] = (scenario, point_guf(scenario, *args, **kwargs))
    return _GUF[id(scenario)][1]


def slope(sc, short: int, long: int) -> float:
    """CPU seconds per trial of ``run`` of scenario ``sc`` (this process), between two run lengths."""
    t = {}
    for n in (short, long):
        c = time.process_time()
        run(sc, trials=n, block=64, attribution_trials=0)
        t[n] = time.process_time() - c
    return (t[long] - t[short]) / (long - short)


def before(rev: str, cfg_path: Path, short: int, long: int) -> tuple:
    """(five-axis, three-axis) CPU seconds per trial on git revision ``rev``, in one subprocess."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_engine_floor import unpacked  # noqa: PLC0415

    with unpacked(rev) as tmp:
        out = subprocess.run([sys.executable, "-c", _CHILD, str(short), str(long), "five", str(cfg_path)], check=True,
                             env=dict(os.environ, PYTHONPATH=tmp), capture_output=True, text=True, cwd=tmp).stdout
    five, three = out.split()[-2:]
    return float(five), float(three)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--short", type=int, default=128)
    ap.add_argument("--long", type=int, default=640)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--before", metavar="REV", help="also both arms on git revision REV (subprocess)")
    args = ap.parse_args()
    runner.point_guf = _guf_once
    five = build_scenario(load_config(bundled_config("five_axis_cafxyz")))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "three.toml"
        path.write_text(THREE_AXIS_TOML)
        three = build_scenario(load_config(path))
        rows5, rows3 = len(five.plan), len(three.plan)
        print(f"rows per verification: five-axis {rows5}, three-axis {rows3}; load {os.getloadavg()[0]:.1f}")
        res = {"five-axis": [], "three-axis": [], "five-axis before": [], "three-axis before": []}
        slope(five, 64, 128)  # warm-up: compiled kernels, caches
        slope(three, 64, 128)
        for r in range(args.rounds):
            res["five-axis"].append(slope(five, args.short, args.long) / rows5)
            res["three-axis"].append(slope(three, args.short, args.long) / rows3)
            if args.before:
                b5, b3 = before(args.before, path, args.short, args.long)
                res["five-axis before"].append(b5 / rows5)
                res["three-axis before"].append(b3 / rows3)
            print(f"  round {r + 1}: " + ", ".join(f"{k} {v[-1] * 1e6:.3f} us/row" for k, v in res.items() if v))
    med = {k: statistics.median(v) for k, v in res.items() if v}
    print("\nCPU per trial and measured row (median of rounds):")
    for k, v in med.items():
        print(f"  {k:20s} {v * 1e6:8.3f} us/row")
    print(f"  five-axis / three-axis: {med['five-axis'] / med['three-axis']:.2f}  (issue 26: at most 2)")
    if "three-axis before" in med:
        print(f"  five-axis / three-axis on {args.before}: {med['five-axis before'] / med['three-axis before']:.2f}")
        for arm in ("five-axis", "three-axis"):
            r = [b / n for n, b in zip(res[arm], res[arm + " before"])]
            print(f"  {arm} before ({args.before}) / now: {statistics.median(r):.2f}  (rounds: "
                  + ", ".join(f"{x:.2f}" for x in r) + ")")


if __name__ == "__main__":
    main()
