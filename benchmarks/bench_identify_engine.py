"""The one-tracker identification as the engine calls it, per trial: this tree against git revision REV, in one run.

Run:  python benchmarks/bench_identify_engine.py [--before REV] [--blocks 16] [--rounds 5] [--repeat 3]
          [--config NAME]

What is timed: the calls of ``identify()`` the engine makes while it runs blocks 0 .. B-1 of the built-in default
configuration (the paper's: 75 points, 48 geometric + 6 pose parameters, every source; ``--config``: a bundled
example instead, e.g. ``five_axis_cafxyz``) in one chunk (as the runner
does for long runs: 16 blocks of 64 trials): the same measured points, noise, strategies (one-phase and multi-phase,
as the optimisation-strategy sources drew them), labels and nominal tracker pose.  Each arm records its own calls
(the simulation is the same code in both arms, checked below: the same measured points) and replays them: CPU seconds
of the identification per trial, the best of ``--repeat`` replays.  The arms run in subprocesses, alternated round
by round (the machine is shared: the figures are the medians of the rounds and the ratio of the medians).

Each arm also prints a digest of what the identification returned (theta, pose, residuals, chi2, points): equal
digests mean the two revisions give the same numbers, bit for bit.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import hashlib, json, sys, time
import numpy as np
from mtbudget import engine as E
from mtbudget.config import bundled_config, load_config
from mtbudget.engine import Engine
from mtbudget.executors import one_blas_thread
from mtbudget.scenario import build_scenario

blocks, repeat = int(sys.argv[1]), int(sys.argv[2])
config = None if sys.argv[3] == "-" else bundled_config(sys.argv[3])
calls = []
real = E.identify

def record(*a, **k):
    calls.append((a, k))
    return real(*a, **k)

with one_blas_thread():
    eng = Engine(build_scenario(load_config(config)), block=64)
    eng.run_blocks(list(range(2)))  # the plan's caches and the compiled kernels, before anything is timed
    E.identify = record
    eng.run_blocks(list(range(blocks)))
    E.identify = real
    n = sum(len(a[1]) for a, _ in calls)
    h_in, h_out = hashlib.sha256(), hashlib.sha256()
    for a, k in calls:
        h_in.update(np.ascontiguousarray(a[1]).tobytes())
        r = real(*a, **k)
        for x in (r.theta, r.pose, r.residual, r.residual_machine, r.chi2, r.whitened, r.initial_error, r.points):
            h_out.update(np.ascontiguousarray(x).tobytes())
    best = float("inf")
    for _ in range(repeat):
        c = time.process_time()
        for a, k in calls:
            real(*a, **k)
        best = min(best, time.process_time() - c)
print(json.dumps({"per_trial": best / n, "trials": n, "calls": len(calls), "in": h_in.hexdigest()[:16],
                  "out": h_out.hexdigest()[:16]}))
"""


def arm(pythonpath: str | None, blocks: int, repeat: int, config: str | None = None) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    out = subprocess.run([sys.executable, "-c", _CHILD, str(blocks), str(repeat), config or "-"], check=True, env=env,
                         capture_output=True, text=True, cwd=pythonpath or ROOT).stdout
    return json.loads(out.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", metavar="REV", help="also time the identification of git revision REV")
    ap.add_argument("--blocks", type=int, default=16, help="blocks of 64 trials in the engine's chunk (default 16)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3, help="replays per round, the best counts")
    ap.add_argument("--config", help="a bundled example instead of the built-in configuration")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_engine_floor import unpacked  # noqa: E402

    print(f"load before: {os.getloadavg()[0]:.1f}")
    now, before = [], []
    import contextlib

    with (unpacked(args.before) if args.before else contextlib.nullcontext()) as tmp:
        for r in range(args.rounds):
            now.append(arm(None, args.blocks, args.repeat, args.config))
            if args.before:
                before.append(arm(tmp, args.blocks, args.repeat, args.config))
            print(f"round {r + 1}: this tree {now[-1]['per_trial'] * 1e6:.1f} us/trial"
                  + (f", {args.before} {before[-1]['per_trial'] * 1e6:.1f} us/trial" if args.before else ""),
                  flush=True)
    med = lambda xs: sorted(x["per_trial"] for x in xs)[len(xs) // 2]  # noqa: E731
    x = now[0]
    print(f"\nidentify() as the engine calls it: {x['calls']} calls, {x['trials']} trials "
          f"({args.blocks} blocks of 64{', ' + args.config if args.config else ''}), CPU per trial, median of {args.rounds} rounds (best of {args.repeat} each):")
    print(f"  this tree: {med(now) * 1e6:.1f} us/trial   (digest of the results {x['out']})")
    if args.before:
        b = before[0]
        print(f"  {args.before}: {med(before) * 1e6:.1f} us/trial   (digest of the results {b['out']})")
        print(f"  ratio {args.before} / this tree: {med(before) / med(now):.2f}; per round: "
              + ", ".join(f"{p['per_trial'] / q['per_trial']:.2f}" for p, q in zip(before, now)))
        print("  the same measured points in both arms: " + ("yes" if b["in"] == x["in"] else "NO"))
        print("  the same results, bit for bit: " + ("yes" if b["out"] == x["out"] else "no (numbers changed)"))
    print(f"load after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
