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
  this process in the same run, alternating, ``--rounds`` rounds; beside it, the same floor drawing as many normal
  numbers a trial as the engine's sources do (``bench_engine_floor.engine_draws``: 1115 for the paper, the floor's own
  279), a second reference: the floor of the same size and the same random numbers.
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
* ``executors``: the command on the built-in configuration with ``--executor inline``, ``process --workers 2`` and
  ``thread --workers 2`` (``--executors`` to choose), ``--attribution-trials 0``, alternated in each of ``--rounds``
  rounds: CPU (every process of the command, workers included) and wall per trial, each the slope between
  ``--short`` and ``--exec-long`` trials, and the peak of the memory summed over the command's processes, sampled
  every ``--every`` s while the longer run runs: resident (RSS, a page shared by forked processes counted in each)
  and proportional (PSS, from ``/proc/PID/smaps_rollup``: a shared page split between its processes, so the sum
  counts it once).  Linux only.
* ``engine-threads``: in process, without the command's start-up: the same ``--thread-chunks`` chunks of 16 blocks
  of 64 trials (the built-in configuration, all sources) run by ``Engine.run_blocks`` on one thread, then on
  ``--workers`` threads (each its own engine, as the thread executor has), alternated, ``--rounds`` rounds: the
  wall-clock speed-up and the CPU the threads spend against one thread.  What the GIL costs, without the noise
  of start-up; run it on an idle machine (the other arms' load is printed too).
* ``engine-executors``: in process, the same chunks through ``executors.Executor`` of each of ``--executors``
  (``--workers`` workers, started before the clock), alternated, ``--rounds`` rounds: wall per trial and the cores
  the machine's other processes used meanwhile (a round they shared says nothing of scaling).
* ``start-methods``: the memory of a process pool of ``--workers`` workers started by fork, forkserver (with and
  without the engine's modules preloaded) and spawn, each in a fresh interpreter after 8 chunks of 4 blocks:
  summed RSS and PSS of the parent and its workers (each start method's pages shared or not).
* ``big``: the 10^6-trial run with its budget (issue 12's command: ``--big-trials`` trials, ``--attribution-trials
  10000``, ``--json --quiet --log``) on each of ``--big-executors`` (``--workers 2``), once each: wall, CPU, peak
  summed RSS and PSS, the main process's peak RSS, and the main result, to compare with the figures in
  docs/performance.md.

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


def descendants(pid: int) -> list:
    """``pid`` and every process below it (from /proc/*/stat)."""
    children: dict = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    st = f.read()
            except OSError:
                continue
            children.setdefault(int(st[st.rfind(")") + 2:].split()[1]), []).append(int(d))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def rss_pss(pids: list) -> tuple[float, float, float]:
    """(summed RSS, summed PSS, RSS of the first pid), MB (2^20 bytes), from /proc/PID/smaps_rollup."""
    rss = pss = first = 0
    for i, p in enumerate(pids):
        try:
            with open(f"/proc/{p}/smaps_rollup") as f:
                text = f.read()
        except OSError:
            continue
        for line in text.splitlines():
            if line.startswith("Rss:"):
                rss += int(line.split()[1])
                first = first or (int(line.split()[1]) if i == 0 else 0)
            elif line.startswith("Pss:"):
                pss += int(line.split()[1])
    return rss / 1024, pss / 1024, first / 1024


def machine_busy() -> float:
    """CPU seconds every core of the machine has been busy so far (user, nice, system, irq, softirq; /proc/stat)."""
    with open("/proc/stat") as f:
        v = f.readline().split()[1:]
    return (int(v[0]) + int(v[1]) + int(v[2]) + int(v[5]) + int(v[6])) / os.sysconf("SC_CLK_TCK")


def watched(argv: list, cwd: str, every: float = 0.25) -> dict:
    """Run ``argv``; its CPU (user + system of it and of every process it waited for: the growth of this process's
    RUSAGE_CHILDREN, the commands run one at a time), wall, and the peaks of the memory summed over its process
    tree, sampled every ``every`` s."""
    import resource  # noqa: PLC0415
    import threading  # noqa: PLC0415

    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    busy0 = machine_busy()
    t0 = time.perf_counter()
    p = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = {"rss": 0.0, "pss": 0.0, "main": 0.0, "procs": 0, "main_cpu": 0.0}
    done = threading.Event()
    tick = os.sysconf("SC_CLK_TCK")

    def sample():
        while not done.is_set():
            pids = descendants(p.pid)
            try:  # the command's own process (not its workers): user + system CPU so far, at the last sample
                with open(f"/proc/{p.pid}/stat") as f:
                    st = f.read()
                fields = st[st.rfind(")") + 2:].split()
                peak["main_cpu"] = (int(fields[11]) + int(fields[12])) / tick
            except (OSError, IndexError):
                pass
            r, s, m = rss_pss(pids)
            peak["rss"], peak["pss"], peak["main"] = max(peak["rss"], r), max(peak["pss"], s), max(peak["main"], m)
            peak["procs"] = max(peak["procs"], len(pids))
            done.wait(every)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    out, err = p.communicate()
    wall = time.perf_counter() - t0
    done.set()
    th.join()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{err[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    # what the machine's other processes used meanwhile, in cores: a round where they used one of two is no
    # measure of scaling
    others = max(0.0, (machine_busy() - busy0 - cpu) / wall)
    return {"cpu": cpu, "wall": wall, "out": out, "others": others, **peak}


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


def floor_cpu(same_draws: bool = False) -> float:
    """CPU s per trial of ``bench_engine_floor.Floor`` on the built-in configuration; same_draws: the floor drawing
    as many normal numbers a trial as the engine's sources do (the second reference)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_engine_floor import Floor, engine_draws, normal_draws  # noqa: PLC0415

    from mtbudget.config import load_config
    from mtbudget.scenario import build_scenario

    scenario = build_scenario(load_config())
    return Floor(scenario, draws=normal_draws(engine_draws(scenario)) if same_draws else None).per_trial()[1]


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
    ap.add_argument("--command-args", default="", help="command: more options of this tree's `mtbudget run`, e.g. "
                    "'--executor inline' (the default executor, auto, runs the longer run on threads: more CPU, less "
                    "wall time)")
    ap.add_argument("--before", metavar="REV", help="command: also the git revision REV (its mtbudget and plugins "
                    "unpacked into a temporary directory), alternating with this tree in every round, with "
                    "--before-args")
    ap.add_argument("--before-args", default=None, help="command: the options of REV's `mtbudget run` (default: "
                    "--command-args; a revision before --executor existed needs '')")
    ap.add_argument("--executors", default="inline,process,thread", help="the executors arm's executors")
    ap.add_argument("--workers", type=int, default=2, help="workers of the process and thread executors")
    ap.add_argument("--exec-long", type=int, default=20000, help="the executors arm's longer run (trials)")
    ap.add_argument("--every", type=float, default=0.25, help="memory sampling interval, s")
    ap.add_argument("--thread-chunks", type=int, default=12)
    ap.add_argument("--big-trials", type=int, nargs="+", default=[1_000_000])
    ap.add_argument("--big-executors", default="process,thread")
    ap.add_argument("--big-budget", type=int, default=10000, help="--attribution-trials of the big run")
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
            ratios, before, same = [], [], []
            for r in range(args.rounds):
                f = floor_cpu()
                f_same = floor_cpu(same_draws=True)
                c = slope(paper, args.short, args.long, *args.command_args.split())
                ratios.append(c / f)
                same.append(c / f_same)
                extra = ""
                if args.before:
                    bargs = args.command_args if args.before_args is None else args.before_args
                    cb = slope(paper, args.short, args.long, *bargs.split(), before=True)  # the same settings
                    before.append(cb / f)
                    extra = f"; {args.before}: {cb * 1e3:.4f} ms, {cb / f:.1f}x (this tree {cb / c:.2f}x faster)"
                print(f"command round {r + 1} ({load()}): mtbudget run {c * 1e3:.4f} ms CPU/trial "
                      f"({args.short} -> {args.long} trials), floor {f * 1e3:.4f} ms: {c / f:.1f}x; the floor with "
                      f"the engine's normal draws {f_same * 1e3:.4f} ms: {c / f_same:.1f}x{extra}", flush=True)
            print(f"command: median {statistics.median(ratios):.1f}x the floor"
                  + (f", {args.before} {statistics.median(before):.1f}x" if args.before else "")
                  + f"; {statistics.median(same):.1f}x the floor drawing the engine's normal numbers", flush=True)
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
        if "executors" in what:
            execs = args.executors.split(",")

            def arm(ex: str, n: int) -> dict:
                extra = ["--executor", ex] + (["--workers", str(args.workers)] if ex != "inline" else [])
                with tempfile.TemporaryDirectory() as cwd:
                    return watched([sys.executable, "-m", "mtbudget", "run", str(paper), "--trials", str(n), "--json",
                                    "--quiet", "--attribution-trials", "0", *extra], cwd, args.every)

            rows: dict = {e: [] for e in execs}
            for r in range(args.rounds):
                for ex in execs:
                    a, b = arm(ex, args.short), arm(ex, args.exec_long)
                    dn = args.exec_long - args.short
                    row = {"cpu": (b["cpu"] - a["cpu"]) / dn, "wall": (b["wall"] - a["wall"]) / dn, "rss": b["rss"],
                           "pss": b["pss"], "main": b["main"], "procs": b["procs"], "wall_long": b["wall"],
                           "cpu_long": b["cpu"], "others": max(a["others"], b["others"])}
                    rows[ex].append(row)
                    print(f"executors round {r + 1} ({load()}; other processes {row['others']:.2f} cores): {ex:<8} CPU {row['cpu'] * 1e3:.4f} ms/trial, wall "
                          f"{row['wall'] * 1e3:.4f} ms/trial ({args.short} -> {args.exec_long} trials); at "
                          f"{args.exec_long}: {b['wall']:.1f} s wall, {b['cpu']:.1f} s CPU, peak summed RSS "
                          f"{b['rss']:.0f} MB, PSS {b['pss']:.0f} MB over {b['procs']} processes (main RSS "
                          f"{b['main']:.0f} MB; its own CPU {b['main_cpu']:.1f} s)", flush=True)
            med = {e: {k: statistics.median(x[k] for x in v) for k in v[0]} for e, v in rows.items()}
            base = med[execs[0]]
            clean = [r for r in range(args.rounds) if all(rows[e][r]["others"] < 0.25 for e in execs)]
            if clean:  # the rounds in which no arm shared the cores with other work
                cm = {e: {k: statistics.median(rows[e][r][k] for r in clean) for k in ("cpu", "wall")} for e in execs}
                print(f"executors, the {len(clean)} rounds where other processes used < 0.25 cores in every arm: " +
                      ", ".join(f"{e} wall {cm[e]['wall'] * 1e3:.4f} ms/trial (speed {cm[execs[0]]['wall'] / cm[e]['wall']:.2f}x"
                                f"), CPU {cm[e]['cpu'] / cm[execs[0]]['cpu']:.2f}x" for e in execs), flush=True)
            for e, m in med.items():
                print(f"executors median: {e:<8} CPU {m['cpu'] * 1e3:.4f} ms/trial ({m['cpu'] / base['cpu']:.2f}x "
                      f"{execs[0]}), wall {m['wall'] * 1e3:.4f} ms/trial (speed {base['wall'] / m['wall']:.2f}x "
                      f"{execs[0]}), peak RSS {m['rss']:.0f} MB, PSS {m['pss']:.0f} MB", flush=True)
        if "engine-threads" in what:
            from concurrent.futures import ThreadPoolExecutor  # noqa: PLC0415

            from mtbudget.config import load_config  # noqa: PLC0415
            from mtbudget.engine import Engine  # noqa: PLC0415
            from mtbudget.executors import one_blas_thread  # noqa: PLC0415
            from mtbudget.scenario import build_scenario  # noqa: PLC0415

            with one_blas_thread():
                engs = [Engine(build_scenario(load_config()), block=64, seed=3) for _ in range(args.workers)]
                for e in engs:
                    e.run_blocks([0, 1])
                chunks = [list(range(16 * i, 16 * i + 16)) for i in range(args.thread_chunks)]
                trials = 64 * 16 * len(chunks)
                speed, cpu = [], []
                for r in range(args.rounds):
                    t, c = time.perf_counter(), time.process_time()
                    for ch in chunks:
                        engs[0].run_blocks(ch)
                    w1, c1 = time.perf_counter() - t, time.process_time() - c
                    import itertools  # noqa: PLC0415
                    import threading  # noqa: PLC0415

                    mine, ids = threading.local(), itertools.count()  # next() of a count is atomic under the GIL

                    def work(ch):
                        if not hasattr(mine, "engine"):
                            mine.engine = engs[next(ids)]
                        return mine.engine.run_blocks(ch)

                    t, c = time.perf_counter(), time.process_time()
                    with ThreadPoolExecutor(args.workers) as pool:
                        list(pool.map(work, chunks))
                    wn, cn = time.perf_counter() - t, time.process_time() - c
                    speed.append(w1 / wn)
                    cpu.append(cn / c1)
                    print(f"engine-threads round {r + 1} ({load()}): one thread {w1 / trials * 1e3:.4f} ms/trial wall "
                          f"({c1 / trials * 1e3:.4f} CPU), {args.workers} threads {wn / trials * 1e3:.4f} ms/trial wall "
                          f"({cn / trials * 1e3:.4f} CPU): speed-up {w1 / wn:.2f}x, CPU {cn / c1:.2f}x", flush=True)
            print(f"engine-threads: median speed-up {statistics.median(speed):.2f}x on {args.workers} threads, CPU "
                  f"{statistics.median(cpu):.2f}x one thread's", flush=True)
        if "engine-executors" in what:
            from mtbudget.config import load_config  # noqa: PLC0415
            from mtbudget.engine import Engine  # noqa: PLC0415
            from mtbudget.executors import Executor, one_blas_thread  # noqa: PLC0415
            from mtbudget.runner import RunSettings, make_spec  # noqa: PLC0415
            from mtbudget.scenario import build_scenario  # noqa: PLC0415

            execs = args.executors.split(",")
            with one_blas_thread():
                eng = Engine(build_scenario(load_config()), block=64, seed=3)
                eng.run_blocks([0, 1])
                spec = make_spec(eng.scenario, eng, RunSettings())
                chunks = [list(range(16 * i, 16 * i + 16)) for i in range(args.thread_chunks)]
                trials = 64 * 16 * len(chunks)
                res: dict = {e: [] for e in execs}
                for r in range(args.rounds):
                    row = []
                    for kind in execs:
                        with Executor(eng, spec, kind, args.workers) as ex:
                            for _ in ex.map([[10_000 + i] for i in range(args.workers)]):  # workers up, engines built
                                pass
                            def ours():  # CPU s of this process and of its worker processes so far
                                own = time.process_time()
                                for q in (getattr(ex.pool, "_processes", None) or {}):
                                    try:
                                        with open(f"/proc/{q}/stat") as f:
                                            st = f.read()
                                        v = st[st.rfind(")") + 2:].split()
                                        own += (int(v[11]) + int(v[12])) / os.sysconf("SC_CLK_TCK")
                                    except OSError:
                                        pass
                                return own

                            b0, t, c0 = machine_busy(), time.perf_counter(), ours()
                            for got in ex.map(chunks):
                                for blk in got:
                                    blk.vector_moments()  # as the run's merge does (computed already by workers)
                            w = time.perf_counter() - t
                            others = max(0.0, machine_busy() - b0 - (ours() - c0))
                        res[kind].append(w / trials)
                        row.append(f"{kind} {w / trials * 1e3:.4f} ms/trial (other processes {others / w:.2f} cores)")
                    print(f"engine-executors round {r + 1} ({load()}): " + ", ".join(row), flush=True)
            med = {e: statistics.median(v) for e, v in res.items()}
            print("engine-executors: median " + ", ".join(f"{e} {v * 1e3:.4f} ms/trial (speed {med[execs[0]] / v:.2f}x "
                                                           f"{execs[0]})" for e, v in med.items()), flush=True)
        if "start-methods" in what:
            for method in ("fork", "forkserver", "forkserver+preload", "spawn"):
                code = (
                    "import json, multiprocessing as mp, os, sys\n"
                    f"sys.path.insert(0, {str(ROOT / 'benchmarks')!r})\n"
                    "from concurrent.futures import ProcessPoolExecutor\n"
                    "from bench_scale import descendants, rss_pss\n"
                    "from mtbudget.config import load_config\n"
                    "from mtbudget.engine import Engine\n"
                    "from mtbudget.executors import one_blas_thread, run_blocks_from_spec\n"
                    "from mtbudget.runner import RunSettings, make_spec\n"
                    "from mtbudget.scenario import build_scenario\n"
                    "if __name__ == '__main__':\n"
                    "    with one_blas_thread():\n"
                    "        eng = Engine(build_scenario(load_config()), block=64, seed=1)\n"
                    "        eng.run_blocks([0, 1])\n"
                    "        spec = json.dumps(make_spec(eng.scenario, eng, RunSettings()), sort_keys=True, default=str)\n"
                    f"        ctx = mp.get_context({method.split('+')[0]!r})\n"
                    + ("        ctx.set_forkserver_preload(['mtbudget.engine', 'mtbudget.executors'])\n"
                       if method.endswith("preload") else "") +
                    f"        with ProcessPoolExecutor({args.workers}, mp_context=ctx) as pool:\n"
                    "            [f.result() for f in [pool.submit(run_blocks_from_spec, spec, list(range(4 * i, 4 * i + 4)))\n"
                    "                                  for i in range(8)]]\n"
                    "            pids = descendants(os.getpid())\n"
                    "            print(json.dumps([len(pids), *rss_pss(pids)[:2], [rss_pss([q])[:2] for q in pids]]))\n")
                with tempfile.TemporaryDirectory() as cwd:
                    f = Path(cwd) / "pool.py"
                    f.write_text(code)
                    out = subprocess.run([sys.executable, str(f)], capture_output=True, text=True, cwd=cwd,
                                         env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
                if out.returncode:
                    print(f"start-methods {method}: failed: {out.stderr[-500:]}", flush=True)
                    continue
                import json  # noqa: PLC0415

                n, rss, pss, each = json.loads(out.stdout.strip().splitlines()[-1])
                print(f"start-methods ({load()}): {method:<18} {n} processes, summed RSS {rss:.0f} MB, PSS {pss:.0f} MB; "
                      "each RSS/PSS " + ", ".join(f"{a:.0f}/{b:.0f}" for a, b in each), flush=True)
        if "big" in what:
            import json  # noqa: PLC0415

            for n in args.big_trials:
                for ex in args.big_executors.split(","):
                    extra = ["--executor", ex] + (["--workers", str(args.workers)] if ex != "inline" else [])
                    print(f"big: {n} trials, --executor {ex}, starting ({load()}; uptime: "
                          f"{subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()})", flush=True)
                    with tempfile.TemporaryDirectory() as cwd:
                        b = watched([sys.executable, "-m", "mtbudget", "run", str(paper), "--trials", str(n),
                                     "--attribution-trials", str(args.big_budget), "--json", "--quiet", "--log",
                                     "big.mcap", *extra], cwd, max(args.every, 0.5))
                    out = json.loads(b["out"])
                    o = out.get("outputs", {}).get("compensation_rms", {})
                    print(f"big: {n} trials + budget {args.big_budget}, {ex}: {b['wall']:.1f} s wall, {b['cpu']:.1f} s "
                          f"CPU, peak summed RSS {b['rss']:.0f} MB, PSS {b['pss']:.0f} MB over {b['procs']} processes, "
                          f"main process RSS {b['main']:.0f} MB, CPU {b['main_cpu']:.1f} s ({load()}; other processes used "
                          f"{b['others']:.2f} cores meanwhile); compensation_rms mean "
                          f"{o.get('mean')} std {o.get('std')}", flush=True)
        if "memory" in what:
            for n in args.memory_trials:
                t0 = time.time()
                cpu, wall, mb = command(paper, n, "--attribution-trials", "0")
                print(f"memory ({load()}): {n} trials, peak resident {mb:.0f} MB, {wall:.1f} s wall, {cpu:.1f} s CPU "
                      f"({(time.time() - t0):.0f} s)", flush=True)


if __name__ == "__main__":
    main()
