"""The engine's per-block post-processing and the run's merge, per trial, against another revision (issue 31).

Run:  OPENBLAS_NUM_THREADS=1 python benchmarks/bench_merge.py [--before REV] [--rounds 3] [--trials 16384]

What it times (CPU of the process, ``time.process_time``), in a fresh interpreter per arm, the arms (this tree and
``--before REV``, that revision's ``mtbudget`` and built-in plugins unpacked into a temporary directory) alternated
in each of ``--rounds`` rounds: ``runner.execute`` of the built-in paper configuration, ``--trials`` trials,
``attribution_trials=0``, inline, logged to an MCAP file in a temporary directory, as ``mtbudget run`` does (after a
1024-trial warm-up run keeping every value and one histogramming them, so that numba's kernels are loaded or
compiled before the clock).  The functions are timed
by wrappers installed in both trees alike:

* ``post``: ``Engine.run_blocks`` minus its ``simulate`` and ``identify`` calls: the compensated field at the mesh,
  the per-block results (and the identified field at the mesh, ``sc.evaluate`` of the identification's points);
* ``merge``: ``runner.accumulate_block``: a block's moments, co-moments and histogram, merged into the run's;
* ``log``: ``RunLogWriter.blocks``, ``checkpoint``, ``points`` and ``finish``: what the run log costs;
* ``total``: the whole ``execute`` call.

Every figure is us per trial; the ratios (before / now) are per round, then their median.  The machine is shared:
only the ratios of arms measured in the same round mean something (the load average is printed with each round).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, os, sys, tempfile, time
from pathlib import Path
import mtbudget
from mtbudget import engine as E, runner, runlog
trials = int(sys.argv[1])
spent = {"post": 0.0, "sim_id": 0.0, "merge": 0.0, "log": 0.0}

def timed(owner, name, key, sign=1.0):
    f = getattr(owner, name)
    def wrapper(*a, **k):
        t = time.process_time()
        try:
            return f(*a, **k)
        finally:
            spent[key] += sign * (time.process_time() - t)
    setattr(owner, name, wrapper)

timed(E.Engine, "run_blocks", "post")
timed(E.Engine, "simulate", "sim_id")
timed(E, "identify", "sim_id")
timed(runner, "accumulate_block", "merge")
for name in ("blocks", "checkpoint", "points", "finish"):
    timed(runlog.RunLogWriter, name, "log")
with tempfile.TemporaryDirectory() as tmp:
    for keep in (True, False):  # both paths (every value kept, histograms): every kernel loaded before the clock
        runner.execute(None, trials=1024, attribution_trials=0, log_path=Path(tmp) / f"warm{keep}.mcap", progress=False,
                       keep_samples=keep)
    for k in spent:
        spent[k] = 0.0
    t = time.process_time()
    runner.execute(None, trials=trials, attribution_trials=0, log_path=Path(tmp) / "run.mcap", progress=False)
    total = time.process_time() - t
spent["post"] -= spent["sim_id"]
print(json.dumps({"tree": os.path.dirname(os.path.dirname(mtbudget.__file__)), "total": total,
                  **{k: v for k, v in spent.items() if k != "sim_id"}}))
"""


def arm(trials: int, path: str | None) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    if path:
        env["PYTHONPATH"] = path
    out = subprocess.run([sys.executable, "-c", CHILD, str(trials)], env=env, capture_output=True, text=True,
                         cwd=tempfile.gettempdir())
    if out.returncode:
        raise SystemExit(out.stderr)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    return {k: (v / trials * 1e6 if k != "tree" else v) for k, v in r.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", metavar="REV", help="also git revision REV, alternated with this tree")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--trials", type=int, default=16384)
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_engine_floor import unpacked

    import contextlib

    with contextlib.ExitStack() as stack:
        arms = {"now": None}
        if args.before:
            arms[args.before] = stack.enter_context(unpacked(args.before))
            arm(64, arms[args.before])  # its kernels compiled into its temporary tree, not in a timed arm
        keys = ("post", "merge", "log", "total")
        rows = {a: [] for a in arms}
        for r in range(args.rounds):
            order = list(arms) if r % 2 == 0 else list(arms)[::-1]
            for a in order:
                rows[a].append(arm(args.trials, arms[a]))
            load = open("/proc/loadavg").read().split()[:3]
            print(f"round {r + 1} (load {' '.join(load)}), us of CPU per trial, {args.trials} trials:", flush=True)
            for a in arms:
                x = rows[a][-1]
                print(f"  {a:>10}: " + ", ".join(f"{k} {x[k]:.2f}" for k in keys)
                      + f"; post + merge + log {x['post'] + x['merge'] + x['log']:.2f}", flush=True)
        print("medians, us of CPU per trial:")
        for a in arms:
            med = {k: statistics.median(x[k] for x in rows[a]) for k in keys}
            print(f"  {a:>10}: " + ", ".join(f"{k} {med[k]:.2f}" for k in keys)
                  + f"; post + merge + log {med['post'] + med['merge'] + med['log']:.2f}")
        if args.before:
            def three(x):
                return x["post"] + x["merge"] + x["log"]
            ratios = [three(b) / three(n) for b, n in zip(rows[args.before], rows["now"])]
            totals = [b["total"] / n["total"] for b, n in zip(rows[args.before], rows["now"])]
            print(f"before / now, post + merge + log: {', '.join(f'{x:.2f}' for x in ratios)} "
                  f"(median {statistics.median(ratios):.2f}x); whole run: {', '.join(f'{x:.3f}' for x in totals)} "
                  f"(median {statistics.median(totals):.3f}x)")


if __name__ == "__main__":
    main()
