"""Speed and scale of the command a user runs (issue 31): CPU per trial against the numpy floor, large meshes,
several stations, memory.

Run:  OPENBLAS_NUM_THREADS=1 python benchmarks/bench_scale.py [--what floor,command,mesh,stations,memory]
          [--rounds 3] [--short 2000] [--long 32000] [--memory-trials 100000] [--before REV]

Every arm is ``python -m mtbudget run CONFIG --trials N --json --quiet`` in a subprocess, timed by
``/usr/bin/time`` (user + system CPU of the command, its peak resident memory); per-trial CPU is the slope
between two trial counts, so the run's one-off work (start-up, scenario, GUF, budget) does not count.
Configurations are the built-in ``paper_xfyz.toml`` with one thing changed:

* ``command``: as is (75 points), ``--short`` and ``--long`` trials (the issue: 2000 and 32000), default settings
  (all sources, the budget's 512 trials), against the floor of ``bench_engine_floor.Floor`` (plain numpy, one
  thread, 75 points, 48 + 6 parameters, linearised, one shared pseudo-inverse, 2 chord iterations) measured in
  this process in the same run, alternating, ``--rounds`` rounds.
* ``mesh``: ``[mesh] step`` 100 mm (75 points), 40 mm (726 points), 20 mm (4851 points), with
  ``--attribution-trials 0``; the slope between ``--slope`` trial counts (256 and 1280).  The ratio printed is the per-trial cost
  against 75 points, divided by the ratio of points (<= 1.5 is the issue's target).
* ``stations``: the bundled ``four_stations.toml`` (4 stations), its first station alone through
  ``[[stations]]``, and the paper configuration's ``[tracker]`` (the same station), 64 -> 320 trials,
  ``--attribution-trials 0``.
* ``engine-stations``: the same three configurations in process (``Engine.run_blocks`` of 4 blocks of 64 trials,
  CPU, the three alternated in each of ``--rounds`` rounds; each round's ratios, their median and the best times): the identification's cost without the command's fixed cost, which makes the slope of
  short runs noisy on a loaded machine.
* ``chunks``: in process, ``runner.run`` of the built-in configuration, 4096 trials, ``attribution_trials=0``,
  with ``chunk_blocks`` 4, 8, 16, 32 alternated, CPU per trial (the rule ``runner.auto_chunk_blocks`` is chosen
  from it).
* ``memory``: peak resident memory of the command at ``--memory-trials`` trials (``--attribution-trials 0``,
  inline).

The machines are shared: only ratios between arms measured in the same round mean something; the load
average is printed with every round.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "mtbudget" / "data"


#: a Python path under which the "before" arm's revision runs (``--before``), else None
BEFORE_PATH = None


def command(cfg: Path, trials: int, *extra: str, before: bool = False) -> tuple[float, float, float]:
    """(CPU s, wall s, peak RSS MB) of ``mtbudget run cfg --trials N`` in a subprocess (its log written in a
    temporary directory, as a user's run writes one); ``before``: the revision of ``--before``."""
    fmt = "%U %S %e %M"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    if before:
        env["PYTHONPATH"] = BEFORE_PATH
    with tempfile.TemporaryDirectory() as cwd:  # the run log goes where the command runs (its default mtbudget-run.mcap)
        p = subprocess.run(["/usr/bin/time", "-f", fmt, sys.executable, "-m", "mtbudget", "run", str(cfg), "--trials",
                            str(trials), "--json", "--quiet", *extra], capture_output=True, text=True, env=env, cwd=cwd)
    if p.returncode != 0:
        raise SystemExit(f"mtbudget run {cfg.name} --trials {trials} failed:\n{p.stderr[-2000:]}")
    u, s, e, m = p.stderr.strip().splitlines()[-1].split()
    return float(u) + float(s), float(e), float(m) / 1024


def slope(cfg: Path, short: int, long: int, *extra: str, before: bool = False) -> float:
    """CPU seconds per trial of the command between ``short`` and ``long`` trials."""
    a = command(cfg, short, *extra, before=before)[0]
    b = command(cfg, long, *extra, before=before)[0]
    return (b - a) / (long - short)


def load() -> str:
    return "load %.2f %.2f %.2f" % os.getloadavg()


def variant(tmp: Path, name: str, src: Path, edit) -> Path:
    text = edit(src.read_text())
    out = tmp / f"{name}.toml"
    out.write_text(text)
    return out


def with_step(step: int):
    def edit(text):
        new, n = re.subn(r'(?m)^step = "100 mm"', f'step = "{step} mm"', text)
        assert n == 1, "the built-in configuration's mesh step moved"
        return new
    return edit


def first_station(text: str) -> str:
    head, *stations = re.split(r"(?m)^(?=\[\[stations\]\])", text)
    return head + stations[0]


def floor_cpu() -> float:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_engine_floor import Floor  # noqa: PLC0415

    from mtbudget.config import load_config
    from mtbudget.scenario import build_scenario

    return Floor(build_scenario(load_config())).per_trial()[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--what", default="command,mesh,stations,memory")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--short", type=int, default=2000)
    ap.add_argument("--long", type=int, default=32000)
    ap.add_argument("--memory-trials", type=int, nargs="+", default=[100_000])
    ap.add_argument("--steps", type=int, nargs="+", default=[100, 40, 20])
    ap.add_argument("--slope", type=int, nargs=2, default=[256, 1280],
                    help="the two trial counts of the mesh and stations arms")
    ap.add_argument("--before", metavar="REV", help="command: also the git revision REV (its mtbudget and plugins "
                    "unpacked into a temporary directory), alternating with this tree in every round")
    args = ap.parse_args()
    what = set(args.what.split(","))
    paper = DATA / "paper_xfyz.toml"
    with contextlib.ExitStack() as stack:
        if args.before:
            global BEFORE_PATH
            sys.path.insert(0, str(ROOT / "benchmarks"))
            from bench_engine_floor import unpacked  # noqa: PLC0415

            BEFORE_PATH = stack.enter_context(unpacked(args.before))
            command(paper, 2, "--attribution-trials", "0", before=True)  # its kernels compiled, not in a timed arm
        measure(args, what, paper)


def measure(args, what, paper):
    command(paper, 2, "--attribution-trials", "0")  # compiles the kernels once (cached), not inside a timed arm
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        if "command" in what:
            ratios, before = [], []
            for r in range(args.rounds):
                f = floor_cpu()
                c = slope(paper, args.short, args.long)
                ratios.append(c / f)
                extra = ""
                if args.before:
                    cb = slope(paper, args.short, args.long, before=True)
                    before.append(cb / f)
                    extra = f"; {args.before}: {cb * 1e3:.4f} ms, {cb / f:.1f}x (this tree {cb / c:.2f}x faster)"
                print(f"command round {r + 1} ({load()}): mtbudget run {c * 1e3:.4f} ms CPU/trial "
                      f"({args.short} -> {args.long} trials), floor {f * 1e3:.4f} ms: {c / f:.1f}x{extra}", flush=True)
            print(f"command: median {statistics.median(ratios):.1f}x the floor"
                  + (f", {args.before} {statistics.median(before):.1f}x" if args.before else ""), flush=True)
        if "mesh" in what:
            cfgs = {s: variant(tmp, f"step{s}", paper, with_step(s)) for s in args.steps}
            from mtbudget.config import load_config  # noqa: PLC0415

            npts = {s: len(load_config(c).plan()) for s, c in cfgs.items()}
            for r in range(args.rounds):
                per = {s: slope(c, *args.slope, "--attribution-trials", "0") for s, c in cfgs.items()}
                base = args.steps[0]
                row = ", ".join(f"{npts[s]} points {per[s] * 1e3:.2f} ms/trial (x{per[s] / per[base]:.1f}, "
                                f"{per[s] / per[base] / (npts[s] / npts[base]):.2f} of linear)" for s in args.steps)
                print(f"mesh round {r + 1} ({load()}): {row}", flush=True)
        if "stations" in what:
            four = DATA / "four_stations.toml"
            cfgs = {"[tracker]": paper, "one [[stations]]": variant(tmp, "one", four, first_station), "four": four}
            for r in range(args.rounds):
                per = {k: slope(c, *args.slope, "--attribution-trials", "0") for k, c in cfgs.items()}
                row = ", ".join(f"{k} {v * 1e3:.3f} ms/trial" for k, v in per.items())
                print(f"stations round {r + 1} ({load()}): {row}; one [[stations]] / [tracker] "
                      f"{per['one [[stations]]'] / per['[tracker]']:.1f}x, four / one [[stations]] "
                      f"{per['four'] / per['one [[stations]]']:.1f}x, four / [tracker] "
                      f"{per['four'] / per['[tracker]']:.1f}x", flush=True)
        if "engine-stations" in what:
            from mtbudget.config import load_config  # noqa: PLC0415
            from mtbudget.engine import Engine  # noqa: PLC0415
            from mtbudget.scenario import build_scenario  # noqa: PLC0415

            four = DATA / "four_stations.toml"
            cfgs = {"[tracker]": paper, "one [[stations]]": variant(tmp, "one", four, first_station), "four": four}
            engs = {k: Engine(build_scenario(load_config(c)), block=64, seed=3) for k, c in cfgs.items()}
            for e in engs.values():
                e.run_blocks([0])
            per = {k: [] for k in engs}  # CPU per trial of every round, the arms alternated within a round
            for r in range(args.rounds):
                for k, e in engs.items():
                    c = time.process_time()
                    e.run_blocks([1, 2, 3, 4])
                    per[k].append((time.process_time() - c) / 256)
                print(f"engine-stations round {r + 1} ({load()}): " + ", ".join(f"{k} {v[-1] * 1e3:.3f} ms/trial"
                                                                               for k, v in per.items())
                      + f"; one [[stations]] / [tracker] {per['one [[stations]]'][-1] / per['[tracker]'][-1]:.2f}x, "
                      f"four / [tracker] {per['four'][-1] / per['[tracker]'][-1]:.2f}x", flush=True)
            best = {k: min(v) for k, v in per.items()}
            one = statistics.median(a / b for a, b in zip(per["one [[stations]]"], per["[tracker]"]))
            four_ = statistics.median(a / b for a, b in zip(per["four"], per["[tracker]"]))
            print(f"engine-stations ({load()}): best " + ", ".join(f"{k} {v * 1e3:.3f} ms/trial" for k, v in best.items())
                  + f"; median of the rounds' ratios: one [[stations]] / [tracker] {one:.2f}x, four / [tracker] "
                  f"{four_:.2f}x", flush=True)
        if "chunks" in what:
            from mtbudget.config import load_config  # noqa: PLC0415
            from mtbudget.runner import run  # noqa: PLC0415
            from mtbudget.scenario import build_scenario  # noqa: PLC0415

            sc = build_scenario(load_config())
            run(sc, trials=256, attribution_trials=0)
            res = {}
            for r in range(args.rounds):
                for cb in (4, 8, 16, 32):
                    c = time.process_time()
                    run(sc, trials=4096, chunk_blocks=cb, attribution_trials=0)
                    res.setdefault(cb, []).append((time.process_time() - c) / 4096)
                print(f"chunks round {r + 1} ({load()}): " + ", ".join(f"{cb} blocks {v[-1] * 1e3:.4f} ms/trial"
                                                                      for cb, v in res.items()), flush=True)
            med = {cb: statistics.median(v) for cb, v in res.items()}
            print("chunks: median " + ", ".join(f"{cb}: {med[4] / v:.2f}x the speed of 4" for cb, v in med.items()))
        if "memory" in what:
            for n in args.memory_trials:
                t0 = time.time()
                cpu, wall, mb = command(paper, n, "--attribution-trials", "0")
                print(f"memory ({load()}): {n} trials, peak resident {mb:.0f} MB, {wall:.1f} s wall, {cpu:.1f} s CPU "
                      f"({(time.time() - t0):.0f} s)", flush=True)


if __name__ == "__main__":
    main()
