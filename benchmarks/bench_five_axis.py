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
* ``three-axis before`` (``--before REV``): that three-axis configuration on git revision REV, in a subprocess
  (what the rotary axes cost a three-axis machine: nothing, if the ratio is 1).

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

from mtbudget.config import bundled_config, load_config  # noqa: E402
from mtbudget.runner import run  # noqa: E402

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
from mtbudget.config import load_config
from mtbudget.runner import run
cfg = load_config(sys.argv[1])
short, long = int(sys.argv[2]), int(sys.argv[3])
run(cfg, trials=64, block=64, attribution_trials=0)  # warm-up: this copy compiles its kernels first
t = {}
for n in (short, long):
    c = time.process_time()
    run(cfg, trials=n, block=64, attribution_trials=0)
    t[n] = time.process_time() - c
print((t[long] - t[short]) / (long - short))
"""


def slope(cfg, short: int, long: int) -> float:
    """CPU seconds per trial of ``run`` (this process), between two run lengths."""
    t = {}
    for n in (short, long):
        c = time.process_time()
        run(cfg, trials=n, block=64, attribution_trials=0)
        t[n] = time.process_time() - c
    return (t[long] - t[short]) / (long - short)


def before(rev: str, cfg_path: Path, short: int, long: int) -> float:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_engine_floor import unpacked  # noqa: PLC0415

    with unpacked(rev) as tmp:
        out = subprocess.run([sys.executable, "-c", _CHILD, str(cfg_path), str(short), str(long)], check=True,
                             env=dict(os.environ, PYTHONPATH=tmp), capture_output=True, text=True, cwd=tmp).stdout
    return float(out.split()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--short", type=int, default=128)
    ap.add_argument("--long", type=int, default=640)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--before", metavar="REV", help="also the three-axis arm on git revision REV (subprocess)")
    args = ap.parse_args()
    five = load_config(bundled_config("five_axis_cafxyz"))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "three.toml"
        path.write_text(THREE_AXIS_TOML)
        three = load_config(path)
        from mtbudget.scenario import build_scenario

        rows5, rows3 = len(build_scenario(five).plan), len(build_scenario(three).plan)
        print(f"rows per verification: five-axis {rows5}, three-axis {rows3}; load {os.getloadavg()[0]:.1f}")
        res = {"five-axis": [], "three-axis": [], "three-axis before": []}
        slope(five, 64, 128)  # warm-up: compiled kernels, caches
        slope(three, 64, 128)
        for r in range(args.rounds):
            res["five-axis"].append(slope(five, args.short, args.long) / rows5)
            res["three-axis"].append(slope(three, args.short, args.long) / rows3)
            if args.before:
                res["three-axis before"].append(before(args.before, path, args.short, args.long) / rows3)
            print(f"  round {r + 1}: " + ", ".join(f"{k} {v[-1] * 1e6:.3f} us/row" for k, v in res.items() if v))
    med = {k: statistics.median(v) for k, v in res.items() if v}
    print("\nCPU per trial and measured row (median of rounds):")
    for k, v in med.items():
        print(f"  {k:20s} {v * 1e6:8.3f} us/row")
    print(f"  five-axis / three-axis: {med['five-axis'] / med['three-axis']:.2f}  (issue 26: at most 2)")
    if "three-axis before" in med:
        print(f"  three-axis now / before ({args.before}): {med['three-axis'] / med['three-axis before']:.2f}")


if __name__ == "__main__":
    main()
