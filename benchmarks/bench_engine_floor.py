"""The verification Monte Carlo against a plain numpy floor of the same size (issue 12, first bullet).

Run:  python benchmarks/bench_engine_floor.py [--trials 640] [--before REV [--before-paths P ...]] [--chunk-blocks K]

1. Accuracy, before any time: simulated verifications of the built-in default configuration
   (the engine's own trials) identified with the chord solver and with Gauss-Newton; the largest
   difference in the tracker points and in the compensated field, and how many trials fell back;
   beside it, how far a whitener shared by all trials would move the result.  Then identify()
   alone, chord against Gauss-Newton.
2. The floor, in plain numpy, of the same size (75 points, 48 geometric + 6 pose parameters):
   simulate (the model linearised at the nominal, plus the tracker's correlated noise), identify
   with one shared pseudo-inverse and two chord iterations, evaluate the compensated field at the
   mesh (rigid motions removed, as the engine does).
3. The engine: ``mtbudget.runner.run`` on the built-in default configuration, attribution_trials=0,
   with the chord solver, with Gauss-Newton and (``--before REV``) the whole engine as it was at git
   revision REV (its ``mtbudget`` and built-in plugins unpacked into a temporary directory, run in a
   subprocess), all in this run.  ``--before-paths``: only these files from REV, everything else from the
   working tree (a change of those files alone, while other files change too).  ``--chunk-blocks K``: the
   runner's blocks identified together, in every arm (default: the runner's own choice, 4 blocks for runs
   this short; runs of 65 536 trials or more use 16).  Wall and CPU time (the machines are shared: the wall clock also
   counts other processes).  Per-trial time is the slope between two run lengths
   (best of 3 each), so the run's one-off work (scenario, GUF, first identifiability analysis) does
   not count; the all-in time of the longer run is printed beside it.

Times are ratios to what is measured in the same run; the machines are shared.
"""

from __future__ import annotations

import argparse
import contextlib
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from mtbudget import tracker as lt
from mtbudget.config import load_config
from mtbudget.engine import Engine
from mtbudget.identify import Strategy, identify, whitener
from mtbudget.runner import run
from mtbudget.scenario import build_scenario

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- 1. accuracy
def accuracy(scenario, blocks=4):
    eng = Engine(scenario)
    model = scenario.id_model
    worst_p = worst_f = 0.0
    fallbacks = trials = 0
    for b in range(blocks):
        meas, _, _ = eng.simulate(b)
        for phases in (Strategy.one_phase, Strategy.multi_phase):
            ref = identify(model, meas, scenario.noise, phases(solver="gauss-newton"))
            fast = identify(model, meas, scenario.noise, phases())
            worst_p = max(worst_p, np.abs(model.predict(ref.theta, ref.pose) - model.predict(fast.theta, fast.pose)).max())
            F = lambda th: model.machine_points(th)[:, scenario.mesh_rows]  # noqa: E731
            worst_f = max(worst_f, np.abs(F(ref.theta) - F(fast.theta)).max())
            fallbacks += fast.n_fallback
            trials += len(meas)
    return worst_p, worst_f, fallbacks, trials


def shared_whitener_effect(scenario, blocks=4):
    """How far one whitener for all trials (at the nominal points) moves Gauss-Newton's result (mm)."""
    import mtbudget.identify as identify_module

    eng = Engine(scenario)
    model, n = scenario.id_model, scenario.noise
    nominal = model.predict(np.zeros(model.n_params), scenario.pose)
    Wh0 = whitener(model.covariance(nominal, n.angular, n.distance, n.distance_per_length, n.repeatability))
    real = identify_module._weights
    worst_p = worst_f = 0.0
    for b in range(blocks):
        meas, _, _ = eng.simulate(b)
        ref = identify(model, meas, n, Strategy(solver="gauss-newton"))
        identify_module._weights = lambda model, meas, noise, strategy: np.repeat(Wh0, len(meas), axis=0)
        try:
            shared = identify(model, meas, n, Strategy(solver="gauss-newton"))
        finally:
            identify_module._weights = real
        worst_p = max(worst_p, np.abs(model.predict(ref.theta, ref.pose) - model.predict(shared.theta, shared.pose)).max())
        F = lambda th: model.machine_points(th)[:, scenario.mesh_rows]  # noqa: E731
        worst_f = max(worst_f, np.abs(F(ref.theta) - F(shared.theta)).max())
    return worst_p, worst_f


def identification_per_trial(scenario, blocks=4, group=16):
    """ms per trial of identify() alone on the engine's trials, in groups as the engine forms them."""
    eng = Engine(scenario)
    meas = [eng.simulate(b)[0] for b in range(blocks)]
    out = {}
    for solver in ("chord", "gauss-newton"):
        for phases in (Strategy.one_phase, Strategy.multi_phase):
            identify(scenario.id_model, meas[0][:group], scenario.noise, phases(solver=solver))  # the plan's cache
            best = np.inf
            for _ in range(3):
                t = time.perf_counter()
                for m in meas:
                    for lo in range(0, len(m), group):
                        identify(scenario.id_model, m[lo:lo + group], scenario.noise, phases(solver=solver))
                best = min(best, (time.perf_counter() - t) / (blocks * len(meas[0])))
            out[solver, phases.__name__] = best
    return out


# ----------------------------------------------------------------------------- 2. the floor
class Floor:
    """Plain numpy, linearised at the nominal: the least work a trial of this size can take.

    draws: the standard normal numbers a trial draws in all (default: what the floor itself needs, p + 6 + 3M,
    279 for the paper).  A larger number (:func:`engine_draws`, the engine's sources: 1115 for the paper) draws the
    rest in the same block and otherwise does the same: the floor of the same size *and the same random numbers*,
    a second reference beside the issue's."""

    def __init__(self, scenario, seed=1, draws=None):
        model = scenario.id_model
        p = model.n_params
        P0, Jg = model.machine_points(np.zeros((1, p)), jacobian=True)
        P0, Jg = P0[0], Jg[0]  # (M, 3), (M, 3, p) machine frame
        pose = np.asarray(scenario.pose, float)[None]
        R = lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5])[0]
        self.y0 = lt.to_tracker(P0[None], pose)[0].reshape(-1)  # (3M,)
        Jt = np.concatenate([np.einsum("ji,mjk->mik", R, Jg), lt.pose_jacobian(P0[None], pose)[0]], axis=2)
        self.J = Jt.reshape(-1, p + 6)  # (3M, 54): tracker frame, geometric then pose
        n = scenario.noise
        C = model.covariance(self.y0.reshape(1, -1, 3), n.angular, n.distance, n.distance_per_length, n.repeatability)[0]
        self.L = np.linalg.cholesky(C)  # (M, 3, 3): the simulated noise
        W = np.zeros((self.J.shape[0],) * 2)  # block-diagonal whitener, shared
        for m, w in enumerate(whitener(C)):
            W[3 * m:3 * m + 3, 3 * m:3 * m + 3] = w
        self.G = np.linalg.pinv(W @ self.J) @ W  # (54, 3M): the one shared pseudo-inverse
        rows = np.asarray(scenario.mesh_rows)
        self.Jf = Jg[rows].reshape(-1, p)  # (3 mesh, p): the compensated field, machine frame
        self.H = scenario.rigid_free  # removes what the tracker pose absorbs
        self.sd = np.concatenate([np.where(np.array(model.errors.units) == "mm", 8e-3, 10e-6), [0.2] * 3, [2e-5] * 3])
        self.rng = np.random.default_rng(seed)
        self.p = p
        own = p + 6 + self.J.shape[0]
        self.extra = 0 if draws is None else max(int(draws) - own, 0)

    def block(self, N):
        rng = self.rng
        x = rng.standard_normal((N, self.p + 6)) * self.sd  # geometric errors and pose
        e = np.einsum("mij,nmj->nmi", self.L, rng.standard_normal((N, len(self.L), 3))).reshape(N, -1)
        if self.extra:  # the engine's other random numbers (draws=): drawn, as its sources draw them
            rng.standard_normal((N, self.extra))
        y = self.y0 + x @ self.J.T + e  # simulate
        xh = np.zeros_like(x)
        for _ in range(2):  # two chord iterations on the (here linear) residuals with the shared pseudo-inverse
            xh += (y - self.y0 - xh @ self.J.T) @ self.G.T
        D = ((x - xh)[:, :self.p] @ self.Jf.T) @ self.H.T  # compensated field, rigid motions removed
        return np.linalg.norm(D.reshape(N, -1, 3), axis=2)

    def per_trial(self, N=20000, block=10000):
        """(wall, CPU) seconds per trial, best of 3."""
        self.block(block)
        best = (np.inf, np.inf)
        for _ in range(3):
            w, c = time.perf_counter(), time.process_time()
            for _ in range(N // block):
                self.block(block)
            best = min(best, ((time.perf_counter() - w) / N, (time.process_time() - c) / N))
        return best


def engine_draws(scenario, block=64) -> dict:
    """The random numbers one trial of ``scenario`` draws, counted on one simulated block of the engine: by the
    Generator method the sources call (``standard_normal`` and ``normal``: normal numbers; ``uniform``, ``integers``,
    ...), each source's generator wrapped in a counter."""
    import mtbudget.simulate as simulate

    counts: dict = {}

    class Counting:
        def __init__(self, rng):
            self._rng = rng

        def __getattr__(self, name):
            f = getattr(self._rng, name)
            if not callable(f):
                return f

            def counted(*a, **kw):
                r = f(*a, **kw)
                counts[name] = counts.get(name, 0) + (kw["out"].size if kw.get("out") is not None else np.size(r))
                return r

            return counted

    real = simulate.sample_source

    def sample_source(scenario, src, n, rng, *a, **kw):
        return real(scenario, src, n, Counting(rng), *a, **kw)

    simulate.sample_source = sample_source
    try:
        Engine(scenario, block=block).simulate(0)
    finally:
        simulate.sample_source = real
    return {k: v / block for k, v in counts.items()}


def normal_draws(counts: dict) -> int:
    """The normal numbers of :func:`engine_draws`' count."""
    return int(round(counts.get("standard_normal", 0) + counts.get("normal", 0)))


# ----------------------------------------------------------------------------- 3. the engine
_BEFORE = r"""
import sys, time
from mtbudget.config import load_config
from mtbudget.runner import run
short, long = int(sys.argv[1]), int(sys.argv[2])
kw = {} if sys.argv[3] == "-" else {"chunk_blocks": int(sys.argv[3])}
cfg = load_config()
out = {}
for n in (short, long):
    best = (float("inf"), float("inf"))
    for _ in range(3):
        w, c = time.perf_counter(), time.process_time()
        run(cfg, trials=n, block=64, attribution_trials=0, **kw)
        best = min(best, (time.perf_counter() - w, time.process_time() - c))
    out[n] = best
print((out[long][0] - out[short][0]) / (long - short), (out[long][1] - out[short][1]) / (long - short))
"""


def engine_at(rev: str, short: int, long: int, paths=None, chunk_blocks=None):
    """(wall, CPU) seconds per trial of the engine of git revision ``rev`` (its mtbudget and built-in plugins,
    unpacked into a temporary directory and run in a subprocess), by the same slope as :func:`engine_per_trial`.
    paths: only these files (repository paths) from ``rev``, the rest from the working tree."""
    import os

    with unpacked(rev, paths) as tmp:
        env = dict(os.environ, PYTHONPATH=tmp)
        out = subprocess.run([sys.executable, "-c", _BEFORE, str(short), str(long),
                              "-" if chunk_blocks is None else str(chunk_blocks)], check=True, env=env,
                             capture_output=True, text=True, cwd=tmp).stdout
    wall, cpu = map(float, out.split())
    return wall, cpu


@contextlib.contextmanager
def unpacked(rev: str, paths=None):
    """A temporary directory holding ``mtbudget`` and its built-in plugins (as ``mtbudget_plugins``) of git revision
    ``rev``: a Python path under which that revision runs (``PYTHONPATH`` comes before the editable install).
    paths: only these files (repository paths) from ``rev``, the rest from the working tree."""
    import io
    import os
    import shutil
    import tarfile
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        if paths:
            shutil.copytree(ROOT / "mtbudget", Path(tmp) / "mtbudget", ignore=shutil.ignore_patterns("__pycache__"))
            shutil.copytree(ROOT / "plugins", Path(tmp) / "plugins", ignore=shutil.ignore_patterns("__pycache__"))
            for path in paths:
                text = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"], check=True,
                                      capture_output=True).stdout
                (Path(tmp) / path).write_bytes(text)
        else:
            tar = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "mtbudget", "plugins"], check=True,
                                 capture_output=True).stdout
            tarfile.open(fileobj=io.BytesIO(tar)).extractall(tmp)
        os.rename(Path(tmp) / "plugins", Path(tmp) / "mtbudget_plugins")
        yield tmp


def engine_per_trial(arm, short, long, chunk_blocks=None):
    """Slope of run() time between two run lengths: (wall, CPU) seconds per trial, the run's one-off work excluded.

    CPU time (this process) beside wall time: on a shared machine the wall clock also counts the time other
    processes hold the cores."""
    real_setup = Engine._identification_setup

    def setup(self, settings):
        model, strategy = real_setup(self, settings)
        strategy.solver = "gauss-newton" if arm == "gauss-newton" else "chord"
        return model, strategy

    Engine._identification_setup = setup
    try:
        cfg = load_config()
        times = {}
        for n in (short, long):
            best = (np.inf, np.inf)
            for _ in range(3):
                w, c = time.perf_counter(), time.process_time()
                run(cfg, trials=n, block=64, attribution_trials=0,
                    **({} if chunk_blocks is None else {"chunk_blocks": chunk_blocks}))
                best = min(best, (time.perf_counter() - w, time.process_time() - c))
            times[n] = best
    finally:
        Engine._identification_setup = real_setup
    return ((times[long][0] - times[short][0]) / (long - short), (times[long][1] - times[short][1]) / (long - short),
            times)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=640, help="the longer run (the shorter is a fifth of it)")
    ap.add_argument("--before", metavar="REV", help="also run the engine of git revision REV (in a subprocess)")
    ap.add_argument("--before-paths", nargs="+", metavar="PATH",
                    help="with --before: only these files from REV (e.g. mtbudget/identify.py), the rest from the "
                         "working tree")
    ap.add_argument("--chunk-blocks", type=int, help="blocks identified together, in every engine arm")
    args = ap.parse_args()
    scenario = build_scenario(load_config())
    model = scenario.id_model

    dp, df, fb, n = accuracy(scenario)
    print(f"accuracy, chord vs Gauss-Newton, {n} identifications of the default configuration's trials "
          f"(one-phase and multi-phase):")
    print(f"  largest difference: tracker points {dp:.1e} mm, compensated field {df:.1e} mm; "
          f"fallbacks to Gauss-Newton: {fb} of {n}")
    assert dp < 1e-6 and df < 1e-6, "the chord solver does not reproduce Gauss-Newton to 1e-6 mm"
    sp, sf = shared_whitener_effect(scenario)
    print(f"  (for comparison, one whitener for all trials, at the nominal points, would move Gauss-Newton's "
          f"result by {sp:.1e} mm in the tracker points and {sf:.1e} mm in the field: the chord keeps each "
          f"trial's own)")

    ident = identification_per_trial(scenario)
    print("\nidentification alone, the engine's trials in groups of 16 (as its strategy sources split a 64-trial block):")
    for phases in ("one_phase", "multi_phase"):
        c, g = ident["chord", phases], ident["gauss-newton", phases]
        print(f"  {phases:11s}: chord {c * 1e3:.3f} ms/trial, Gauss-Newton {g * 1e3:.3f} ms/trial, {g / c:.1f}x")

    floor = Floor(scenario)
    t_floor, c_floor = floor.per_trial()
    print(f"\nfloor (plain numpy, {model.n_points} points, {model.n_params} + 6 parameters, linearised, shared "
          f"pseudo-inverse, 2 chord iterations): {t_floor * 1e6:.1f} us/trial wall, {c_floor * 1e6:.1f} us/trial CPU, "
          f"{1 / t_floor:,.0f} trials/s")

    short, long = max(64, args.trials // 5 // 64 * 64), args.trials
    chunk = "the runner's default" if args.chunk_blocks is None else args.chunk_blocks
    print(f"\nengine, mtbudget.runner.run(default config, block=64, attribution_trials=0, chunk_blocks: {chunk}), slope "
          f"{short} -> {long} trials (wall / CPU of this process):")
    res = {}
    for name in ("chord", "gauss-newton"):
        per, cpu, times = engine_per_trial(name, short, long, args.chunk_blocks)
        res[name] = per, cpu
        print(f"  {name:22s} {per * 1e3:7.3f} / {cpu * 1e3:7.3f} ms/trial  {1 / per:7.0f} trials/s  "
              f"{per / t_floor:5.1f}x / {cpu / c_floor:5.1f}x the floor   (best of 3 runs: {short} trials "
              f"{times[short][0]:.2f} s, {long} trials {times[long][0]:.2f} s, {times[long][0] / long * 1e3:.2f} "
              "ms/trial all in)")
    if args.before:
        per, cpu = engine_at(args.before, short, long, args.before_paths, args.chunk_blocks)
        res[f"before ({args.before})"] = per, cpu
        print(f"  {'before (' + args.before + ')':22s} {per * 1e3:7.3f} / {cpu * 1e3:7.3f} ms/trial  {1 / per:7.0f} "
              f"trials/s  {per / t_floor:5.1f}x / {cpu / c_floor:5.1f}x the floor   (its mtbudget and plugins, "
              "in a subprocess)")
    for name in res:
        if name != "chord":
            print(f"  chord vs {name}: {res[name][0] / res['chord'][0]:.1f}x faster (wall), "
                  f"{res[name][1] / res['chord'][1]:.1f}x (CPU)")

if __name__ == "__main__":
    main()
