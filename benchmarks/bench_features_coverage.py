"""Coverage of the features' 95 % intervals, the way ISO/TS 15530-4 validates a task-specific uncertainty (issue 28).

Run:  python benchmarks/bench_features_coverage.py [--machines 4] [--parts 512] [--trials 4096]

For each of ``--machines`` simulated machines (the example configuration examples/paper_features.toml with
geometric_errors.seed = 7, 8, ...), mtbudget states each feature's 95 % coverage interval of its error from a Monte
Carlo run (``--trials``, seed 1, 2, ... one per machine).  Then ``--parts`` parts at nominal are measured on that machine, each after its own
verification, simulated and identified independently of the statement (another seed: the engine's simulator and
identification, block by block), and the part's true error is computed HERE, by code written apart from
mtbudget/features.py: the true and the identified machine at the probed points (truth model at the simulated
parameters, identification model at the identified ones), the in-use errors drawn from this script's own generator
by the formulas of docs/features.md, and the feature associated by scipy.optimize.least_squares (circles) and
numpy.linalg.lstsq (planes: z = a x + b y + c), the minimum zone by scipy.optimize.linprog on all the zone's
constraints (written again here).  The empirical coverage is the share of parts whose true error lies in the
stated interval; with n part-features it has a binomial standard deviation sqrt(0.95 x 0.05 / n) (0.48 % for 2048),
so the acceptance band [93.6, 96.4] % is about +-2.9 of them.
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
from scipy import optimize

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mtbudget.config import bundled_config, parse_config  # noqa: E402
from mtbudget.engine import Engine  # noqa: E402
from mtbudget.identify import scale_vector  # noqa: E402
from mtbudget.model import MeasurementModel  # noqa: E402
from mtbudget.plan import Plan  # noqa: E402
from mtbudget.report import result_json  # noqa: E402
from mtbudget.runner import RunSettings, run  # noqa: E402
from mtbudget.scenario import build_scenario  # noqa: E402
from mtbudget.units import to_internal  # noqa: E402

BAND = (93.6, 96.4)


def q(text, unit):
    return to_internal(text, unit)


def points_of(f):
    return np.array([[q(v, "mm") for v in p] for p in f["points"]])


def part_errors(sc, eng, features, blocks, rng):
    """(parts, K) the true error of each feature of parts measured after the verifications of ``blocks``."""
    truth, model = sc.truth, sc.id_model
    scale = scale_vector(model)
    tool = np.asarray(sc.tool, float)
    rep = sc.config.repeatability
    cte_m = sc.config.cte
    out = []
    for b in blocks:
        res = eng.run_blocks([b])[0]
        theta_hat = res.parameters / scale  # the identified parameters (unscaled; a lower degree leaves zeros)
        theta_true = eng.simulate(b)[1]
        n = len(theta_hat)
        rows = np.empty((n, len(features)))
        for k, f in enumerate(features):
            P = points_of(f)
            N = len(P)
            plan = Plan(np.arange(N), np.ones(N, int), np.zeros(N), P, np.ones((N, 3)), np.tile(tool, (N, 1)))
            S = MeasurementModel(truth.config, truth.errors, plan).machine_points(np.zeros((1, truth.n_params)))[0]
            e = (MeasurementModel(truth.config, truth.errors, plan).machine_points(theta_true)
                 - MeasurementModel(model.config, model.errors, plan).machine_points(theta_hat))
            M = S[None] - e  # the controller reports S - e where the tool touches S
            c = P.mean(axis=0)
            if f["kind"] == "distance":
                u = (P[1] - P[0]) / np.linalg.norm(P[1] - P[0])
                dirs = np.array([-u, u])
            elif f["kind"] in ("diameter", "position"):
                dirs = (P - c) / np.linalg.norm(P - c, axis=1, keepdims=True)
            else:
                dirs = np.tile([0.0, 0.0, 1.0], (N, 1))  # the example's planes are horizontal
            if "probing_error" in f:
                M = M + rng.normal(0, q(f["probing_error"], "mm") / 3.931, (n, N, 1)) * dirs[None]
            if f.get("repeatability"):
                M = M + rng.normal(0, rep, (n, N, 3))
            if "machine_temperature_change" in f:
                dT = rng.normal(0, q(f["machine_temperature_change"], "K"), (n, 1, 3))
                M = M + cte_m * dT * P[None]
            if "part_temperature_u" in f:
                a = q(f.get("part_cte", "11.5 um/(m*K)"), "1/K")
                M = M + (a * rng.normal(0, q(f["part_temperature_u"], "K"), (n, 1, 1))) * (P - c)[None]
            if "part_cte_u" in f:
                dt = to_internal(f["part_temperature"], "K", absolute_temperature=True) - 293.15
                M = M + (rng.normal(0, q(f["part_cte_u"], "1/K"), (n, 1, 1)) * dt) * (P - c)[None]
            rows[:, k] = [value(f, S, M[i]) for i in range(n)]
        out.append(rows)
    return np.concatenate(out)


def value(f, S, M):
    """The feature's error (um; urad for orientation) from the measured points M of the part at nominal S."""
    kind = f["kind"]
    if kind == "distance":
        return (np.linalg.norm(M[1] - M[0]) - np.linalg.norm(S[1] - S[0])) * 1e3
    if kind in ("diameter", "position"):
        def fit(X):  # geometric least-squares circle in the plane z = const (the example's circles)
            r = optimize.least_squares(lambda p: np.hypot(X[:, 0] - p[0], X[:, 1] - p[1]) - p[2],
                                       [X[:, 0].mean(), X[:, 1].mean(), np.ptp(X[:, 0]) / 2], xtol=1e-15, ftol=1e-15)
            return r.x
        a, b = fit(M), fit(S)
        return 2 * (a[2] - b[2]) * 1e3 if kind == "diameter" else 2 * np.hypot(a[0] - b[0], a[1] - b[1]) * 1e3
    if kind == "flatness":
        if f.get("association") == "minimum zone":  # min w s.t. |z - (a x + b y + c)| <= w
            A = np.column_stack([M[:, 0], M[:, 1], np.ones(len(M))])
            A_ub = np.vstack([np.column_stack([-A, -np.ones(len(M))]), np.column_stack([A, -np.ones(len(M))])])
            r = optimize.linprog([0, 0, 0, 1], A_ub=A_ub, b_ub=np.r_[-M[:, 2], M[:, 2]],
                                 bounds=[(None, None)] * 3 + [(0, None)], method="highs")
            return 2 * r.x[3] * 1e3
        A = np.column_stack([M[:, 0], M[:, 1], np.ones(len(M))])
        coef = np.linalg.lstsq(A, M[:, 2], rcond=None)[0]
        n = np.array([-coef[0], -coef[1], 1.0]) / np.linalg.norm([-coef[0], -coef[1], 1.0])
        h = M @ n
        return (h.max() - h.min()) * 1e3
    A = np.column_stack([M[:, 0] - M[:, 0].mean(), M[:, 1] - M[:, 1].mean(), np.ones(len(M))])
    coef = np.linalg.lstsq(A, M[:, 2], rcond=None)[0]
    return float(np.arctan(np.hypot(coef[0], coef[1]))) * 1e6


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=4)
    ap.add_argument("--parts", type=int, default=512)
    ap.add_argument("--trials", type=int, default=4096)
    args = ap.parse_args(argv)
    base = tomllib.loads(bundled_config("paper_features").read_text())
    features = base["features"]
    rng = np.random.default_rng(20261125)
    return coverage_by_machine(base, "paper_features", 7, args,
                               lambda sc, eng, blocks: part_errors(sc, eng, features, blocks, rng), width=22)


def coverage_by_machine(base: dict, name: str, seed0: int, args, errors_of, width: int) -> int:
    """For each of ``args.machines`` machines (geometric error seeds seed0, seed0 + 1, ...): its statement of
    ``base``'s features (``args.trials`` trials), the true errors of ``args.parts`` parts measured on it
    (``errors_of(scenario, engine, blocks)``, the benchmark's own code), and how many fall in the stated intervals;
    then :func:`coverage_summary` (both benchmarks)."""
    features = base["features"]
    hits: dict = {}
    t0 = time.perf_counter()
    for m in range(args.machines):
        data = copy.deepcopy(base)
        data["geometric_errors"]["seed"] = seed0 + m
        sc = build_scenario(parse_config(data, f"{name} (machine seed {seed0 + m})"))
        # each machine's statement from its own seed: statements drawn from one seed share their noise draws, and a
        # feature that hardly depends on the machine (a flatness) would get the same u, by the same chance, on all
        stated = result_json(run(sc, RunSettings(trials=args.trials, attribution_trials=0, seed=1 + m)))["features"]
        eng = Engine(sc, block=64, seed=1000 + m)  # the parts' verifications: another seed, independent draws
        E = errors_of(sc, eng, list(range(-(-args.parts // 64))))[: args.parts]
        for k, (f, s) in enumerate(zip(features, stated)):
            inside = (E[:, k] >= s["interval"]["low"]) & (E[:, k] <= s["interval"]["high"])
            hits.setdefault(f["kind"], []).append(inside)
            print(f"machine {m + 1} ({seed0 + m}): {f['name']:<{width}} stated u {s['u']:8.3f} {s['unit']:<4}, part "
                  f"errors' std {E[:, k].std(ddof=1):8.3f}, coverage {inside.mean():6.1%}", flush=True)
    return coverage_summary(hits, args, t0)


def coverage_summary(hits: dict, args, t0: float) -> int:
    """Print each feature kind's empirical coverage against BAND; 0 when every kind is inside it (both benchmarks)."""
    print(f"\nEmpirical coverage of the stated 95 % intervals per feature kind ({args.machines} machines x {args.parts} "
          f"parts, {args.trials} trials per statement; {time.perf_counter() - t0:.0f} s, load {os.getloadavg()[0]:.1f}):")
    ok = True
    for kind, h in hits.items():
        h = np.concatenate(h)
        c = 100 * h.mean()
        good = BAND[0] <= c <= BAND[1]
        ok &= good
        print(f"  {kind:<12} {c:5.1f} %  of {len(h)} part-features  {'in' if good else 'OUTSIDE'} [{BAND[0]}, {BAND[1]}] %")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
