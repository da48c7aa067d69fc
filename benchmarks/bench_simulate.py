"""The engine's simulation of a block (issue 31): CPU per trial, and how it scales on threads, against a revision.

Run:  OPENBLAS_NUM_THREADS=1 python benchmarks/bench_simulate.py [--before REV] [--rounds 5] [--blocks 150]
          [--what simulate,fixed,in-run,threads,parts,gil] [--workers 2] [--run-trials 8192]

* ``simulate``: ``Engine.simulate`` of ``--blocks`` blocks of 64 trials of the built-in configuration (the paper's,
  all sources), CPU time per trial (``time.process_time``; the best of 3 passes in each round: the least disturbed
  by the other processes of a shared machine).  What ``simulate.simulate_block`` does per block: each source's
  stream, its draws and their checks, the sums per model input, the truth model (chain and tracker).
* ``fixed``: the same with blocks of one trial, CPU per block: what a block costs whatever its size, nearly all of
  it Python holding the GIL (the sources' calls, the checks, the streams' seeding, the truth model's glue, the
  numpy calls on tiny arrays): the part of a block that two threads cannot run at once.
* ``in-run``: ``Engine.simulate`` timed (CPU) inside ``runner.run(None, trials=--run-trials,
  attribution_trials=0)`` (inline, the engine's chunks: the identification between the blocks takes the caches),
  per trial, and the whole run's CPU per trial beside it (start-up excluded: a run of 1024 trials first).
* ``threads``: the same blocks simulated on one thread, then on ``--workers`` threads (each its own engine, as the
  thread executor has), wall clock: the speed-up says how much of the simulation holds the GIL.  Only meaningful on
  an idle machine (the load average is printed with each round).
* ``gil`` (needs ``py-spy`` on the PATH): the blocks simulated under ``py-spy record`` twice, with and without
  ``--gil`` (200 samples a second); the samples inside ``simulate_block`` that hold the GIL against all of them:
  the share of the simulation two threads cannot run at once, measured on a busy machine as well as on an idle one
  (it does not depend on the cores the other processes leave).
* ``parts`` (this tree only): where a block's time goes: the streams, the sources (their draws and checks), the
  truth model (``from_targets``, ``truth_inputs``, ``predict``), per trial.

Each arm runs in a fresh interpreter; with ``--before REV`` the revision REV (its ``mtbudget`` and plugins, unpacked
into a temporary directory, :func:`bench_engine_floor.unpacked`) runs too, alternating with this tree in every
round, and the ratio is printed per round and as the median.  Only ratios measured in the same round mean
something on a shared machine.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load() -> str:
    return "load " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def worker(what: str, blocks: int, workers: int, run_trials: int = 8192) -> dict:
    """The measurement of one arm, in this interpreter (whichever mtbudget it imports)."""
    if what == "in-run":
        from mtbudget import engine, runner

        spent = [0.0, 0]
        simulate = engine.Engine.simulate

        def timed(self, *a, **k):
            c = time.process_time()
            out = simulate(self, *a, **k)
            spent[0] += time.process_time() - c
            spent[1] += self.block
            return out

        engine.Engine.simulate = timed
        runner.run(None, trials=1024, attribution_trials=0)
        spent[:] = [0.0, 0]
        c = time.process_time()
        runner.run(None, trials=run_trials, attribution_trials=0)
        total = time.process_time() - c
        return {"simulate_us_per_trial": spent[0] / spent[1] * 1e6, "run_us_per_trial": total / run_trials * 1e6}
    from mtbudget.config import load_config
    from mtbudget.engine import Engine
    from mtbudget.executors import one_blas_thread
    from mtbudget.scenario import build_scenario

    with one_blas_thread():
        engs = [Engine(build_scenario(load_config()), block=1 if what == "fixed" else 64, seed=3)
                for _ in range(max(workers, 1))]
        for e in engs:
            for b in range(4):
                e.simulate(b)  # the kernels compiled or loaded, the caches filled
        ids = list(range(10, 10 + blocks))
        trials = engs[0].block * blocks
        if what in ("fixed", "simulate"):  # the same loop: "fixed" on blocks of one trial (the Python of a block)
            best = float("inf")
            for _ in range(3):
                c = time.process_time()
                for b in ids:
                    engs[0].simulate(b)
                best = min(best, time.process_time() - c)
            return ({"cpu_us_per_block": best / blocks * 1e6} if what == "fixed"
                    else {"cpu_us_per_trial": best / trials * 1e6})
        if what == "plain":  # the gil arm's workload, sampled by py-spy from outside
            for b in ids:
                engs[0].simulate(b)
            return {}
        if what == "threads":
            from concurrent.futures import ThreadPoolExecutor

            t = time.perf_counter()
            for b in ids:
                engs[0].simulate(b)
            one = time.perf_counter() - t
            share = [ids[i::workers] for i in range(workers)]

            def run(k):
                for b in share[k]:
                    engs[k].simulate(b)

            with ThreadPoolExecutor(workers) as pool:
                t = time.perf_counter()
                list(pool.map(run, range(workers)))
                many = time.perf_counter() - t
            return {"one_us_per_trial": one / trials * 1e6, "many_us_per_trial": many / trials * 1e6,
                    "speed_up": one / many}
        if what == "parts":
            from mtbudget import simulate
            from mtbudget.model import from_targets

            eng = engs[0]
            sc, shapes = eng.scenario, eng.shapes
            n, seed = eng.block, eng.seed
            t_streams = t_sources = t_truth = 0.0
            pc = time.process_time
            for b in ids:
                a = pc()
                rngs = [simulate.stream(seed, b, s) for s in sc.sources] if not hasattr(simulate, "streams") else \
                    simulate.streams(seed, b, sc.sources)
                t_streams += pc() - a
                a = pc()
                targets = {}
                for src, rng in zip(sc.sources, rngs):
                    for k, v in simulate.sample_source(sc, src, n, rng, shapes, eng._options).items():
                        if k != "strategy":
                            targets[k] = targets[k] + v if k in targets else v
                t_sources += pc() - a
                a = pc()
                targets.pop("measurand_offset", None)
                pert = sc.truth_inputs(from_targets(targets))
                theta = sc.theta[None, :] + pert.pop("geometry", 0.0)
                sc.truth.predict(theta, sc.pose, pert)
                t_truth += pc() - a
            return {k: v / trials * 1e6 for k, v in
                    (("streams", t_streams), ("sources", t_sources), ("truth", t_truth))}
    raise SystemExit(f"unknown arm {what!r}")


def arm(what: str, args, path: str | None) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    if path:
        env["PYTHONPATH"] = path
    p = subprocess.run([sys.executable, __file__, "--worker", what, "--blocks", str(args.blocks), "--workers",
                        str(args.workers), "--run-trials", str(args.run_trials)], capture_output=True, text=True,
                       env=env, cwd=ROOT)
    if p.returncode != 0:
        raise SystemExit(f"arm {what} failed:\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def gil_share(args, path: str | None) -> tuple[int, int]:
    """(samples inside simulate_block holding the GIL, all samples inside it) of the ``plain`` workload under
    py-spy."""
    import shutil
    import tempfile

    spy = shutil.which("py-spy")
    if spy is None:
        raise SystemExit("the gil arm needs py-spy on the PATH (pip install py-spy)")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    if path:
        env["PYTHONPATH"] = path
    counts = []
    for flag in (["--gil"], []):
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "raw.txt"
            p = subprocess.run([spy, "record", *flag, "--rate", "200", "--format", "raw", "-o", str(out), "--",
                                sys.executable, __file__, "--worker", "plain", "--blocks", str(args.blocks)],
                               capture_output=True, text=True, env=env, cwd=ROOT)
            if p.returncode != 0 or not out.exists():
                raise SystemExit(f"py-spy failed:\n{p.stderr[-2000:]}")
            n = 0
            for line in out.read_text().splitlines():
                stack, _, count = line.rpartition(" ")
                if "simulate_block (" in stack:
                    n += int(count)
            counts.append(n)
    return counts[0], counts[1]



def _alternate(args, before, name: str, value, unit: str, text) -> None:
    """``--rounds`` rounds of the arm ``name``: this tree, then (``--before``) the revision before, alternated; each
    round's line is ``text(this tree's result, the revision's or None)``, then the medians of ``value`` and of the
    ratios (the revision's over this tree's)."""
    ours, theirs, ratios = [], [], []
    for r in range(args.rounds):
        a = arm(name, args, None)
        ours.append(value(a))
        b = None
        if before:
            b = arm(name, args, before)
            theirs.append(value(b))
            ratios.append(value(b) / value(a))
        print(f"{name} round {r + 1} ({load()}): " + text(a, b), flush=True)
    print(f"{name}: median this tree {statistics.median(ours):.2f} {unit}"
          + (f", {args.before} {statistics.median(theirs):.2f} {unit}, median ratio {statistics.median(ratios):.2f}x"
             if before else ""), flush=True)

def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--what", default="simulate,fixed,in-run,threads,parts")  # gil: asked for by name
    ap.add_argument("--run-trials", type=int, default=8192, help="trials of the in-run arm's run")
    ap.add_argument("--before", metavar="REV", help="also git revision REV, alternating with this tree")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--blocks", type=int, default=150, help="blocks of 64 trials per measurement")
    ap.add_argument("--workers", type=int, default=2, help="threads of the threads arm")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.blocks, args.workers, args.run_trials)))
        return
    what = [w.strip() for w in args.what.split(",") if w.strip()]
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} cores, {load()}; {args.blocks} blocks of 64 trials, "
          f"built-in configuration, all sources", flush=True)
    with contextlib.ExitStack() as stack:
        before = None
        if args.before:
            sys.path.insert(0, str(ROOT / "benchmarks"))
            from bench_engine_floor import unpacked  # noqa: PLC0415

            before = stack.enter_context(unpacked(args.before))
        B = args.before
        if "simulate" in what:
            _alternate(args, before, "simulate", lambda a: a["cpu_us_per_trial"], "us/trial",
                       lambda a, b: f"this tree {a['cpu_us_per_trial']:.2f} us/trial CPU" + (
                           f", {B} {b['cpu_us_per_trial']:.2f} us/trial: "
                           f"{b['cpu_us_per_trial'] / a['cpu_us_per_trial']:.2f}x faster" if b else ""))
        if "fixed" in what:
            _alternate(args, before, "fixed", lambda a: a["cpu_us_per_block"], "us per block",
                       lambda a, b: f"this tree {a['cpu_us_per_block']:.1f} us per block of one trial CPU" + (
                           f", {B} {b['cpu_us_per_block']:.1f} us: "
                           f"{b['cpu_us_per_block'] / a['cpu_us_per_block']:.2f}x less" if b else ""))
        if "in-run" in what:
            _alternate(args, before, "in-run", lambda a: a["simulate_us_per_trial"], "us/trial",
                       lambda a, b: f"this tree simulate {a['simulate_us_per_trial']:.2f} us/trial CPU (the run "
                                    f"{a['run_us_per_trial']:.1f})" + (
                           f", {B} {b['simulate_us_per_trial']:.2f} (the run {b['run_us_per_trial']:.1f}): "
                           f"{b['simulate_us_per_trial'] / a['simulate_us_per_trial']:.2f}x faster" if b else ""))
        if "threads" in what:
            ours, theirs = [], []
            for r in range(args.rounds):
                a = arm("threads", args, None)
                ours.append(a["speed_up"])
                line = (f"threads round {r + 1} ({load()}): this tree one thread {a['one_us_per_trial']:.2f} us/trial "
                        f"wall, {args.workers} threads {a['many_us_per_trial']:.2f}: speed-up {a['speed_up']:.2f}x")
                if before:
                    b = arm("threads", args, before)
                    theirs.append(b["speed_up"])
                    line += (f"; {args.before} one thread {b['one_us_per_trial']:.2f}, {args.workers} threads "
                             f"{b['many_us_per_trial']:.2f}: speed-up {b['speed_up']:.2f}x")
                print(line, flush=True)
            print(f"threads: median speed-up on {args.workers} threads, this tree {statistics.median(ours):.2f}x"
                  + (f", {args.before} {statistics.median(theirs):.2f}x" if before else ""), flush=True)
        if "gil" in what:
            for r in range(args.rounds):
                g, a = gil_share(args, None)
                line = (f"gil round {r + 1} ({load()}): this tree {g} of {a} samples in simulate_block hold the GIL "
                        f"({100 * g / max(a, 1):.0f} %)")
                if before:
                    gb, ab = gil_share(args, before)
                    line += (f"; {args.before} {gb} of {ab} ({100 * gb / max(ab, 1):.0f} %): for the same blocks "
                             f"{gb / max(g, 1):.2f}x the samples holding the GIL")
                print(line, flush=True)
        if "parts" in what:
            rows = [arm("parts", args, None) for _ in range(3)]
            parts = {k: min(r[k] for r in rows) for k in rows[0]}
            print("parts (this tree, best of 3, CPU us/trial): " + ", ".join(f"{k} {v:.2f}" for k, v in parts.items())
                  + f", total {sum(parts.values()):.2f}", flush=True)


if __name__ == "__main__":
    main()
