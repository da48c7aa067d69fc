"""Coverage of five-axis features' 95 % intervals (examples/five_axis_features.toml), the way ISO/TS 15530-4 validates
a task-specific uncertainty: bench_features_coverage.py's method on the CAFXYZ trunnion machine.

Run:  python benchmarks/bench_features_coverage_fiveaxis.py [--machines 4] [--parts 512] [--trials 2048]

For each of ``--machines`` simulated machines (the example with geometric_errors.seed = 11, 12, ...), mtbudget states
each feature's 95 % interval of its error (``--trials``, seed 1, 2, ...).  Then ``--parts`` parts at nominal are
measured on that machine, each after its own verification (the engine's simulator and identification, another seed),
and the part's true error is computed HERE, apart from mtbudget/features.py: the truth and the identification model
at a plan of the probed poses built here (commanded positions and angles), the part's nominal points from the chain
at zero errors, the in-use errors drawn by this script: the probing error along the line or radius in the table frame,
the linear axes' repeatability turned into the table frame by R_C(c)^T R_A(a)^T written with scipy's rotations, and
the rotary axes' repeatability by evaluating the nominal chain at the angles plus the drawn turns (exactly, where
mtbudget linearises), one turn per axis and positioning: a run of consecutive points at one commanded angle of an
axis is probed with the axis held, so they share its turn; the associations are bench_features_coverage.py's (scipy
least squares, numpy lstsq).

``--repeatability`` sets ``repeatability = true`` on every feature (the example has it on the tilted face only), so
the rotary axes' held turns act on the distance across C, the bores and the face alike.
"""

from __future__ import annotations

import argparse
import os
import sys
import tomllib
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_features_coverage import coverage_by_machine, points_of, q, value  # noqa: E402

from mtbudget.config import bundled_config  # noqa: E402
from mtbudget.identify import scale_vector  # noqa: E402
from mtbudget.model import MeasurementModel  # noqa: E402
from mtbudget.plan import Plan  # noqa: E402


def angles_of(f, n):
    out = {}
    for k, v in f["angles"].items():
        vals = v if isinstance(v, list) else [v] * n
        out[k.lower()] = np.array([q(x, "rad") for x in vals])
    return out


def positioning_runs(v):
    """(N,) int: the positioning each point of one axis' commanded angles v is probed at, a new one where the angle
    changes from the previous point (the axis held over a run of equal angles)."""
    return np.cumsum(np.r_[True, v[1:] != v[:-1]]) - 1


def table_rotation(ang):
    """(N, 3, 3) R with v_machine = R v_table for CAFXYZ (A on the bed about +X, C on A about +Z): R_A(a) R_C(c)."""
    return np.array([Rotation.from_euler("x", a).as_matrix() @ Rotation.from_euler("z", c).as_matrix()
                     for a, c in zip(ang["a"], ang["c"])])


def part_errors(sc, eng, features, blocks, rng, rotary_R):
    truth, model = sc.truth, sc.id_model
    scale = scale_vector(model)
    tool = np.asarray(sc.tool, float)
    rep = sc.config.repeatability
    out = []
    for b in blocks:
        theta_hat = eng.run_blocks([b])[0].parameters / scale
        theta_true = eng.simulate(b)[1]
        n = len(theta_hat)
        rows = np.empty((n, len(features)))
        for k, f in enumerate(features):
            P = points_of(f)
            N = len(P)
            ang = angles_of(f, N)

            def chain(m, theta, angles):
                plan = Plan(np.arange(N), np.ones(N, int), np.zeros(N), P, np.ones((N, 3)), np.tile(tool, (N, 1)),
                            angles=angles, rotary=dict(sc.plan.rotary))
                return MeasurementModel(m.config, m.errors, plan).machine_points(theta)

            zero = np.zeros((1, truth.n_params))
            S = chain(truth, zero, ang)[0]
            e = chain(truth, theta_true, ang) - chain(model, theta_hat, ang)
            M = S[None] - e
            c = S.mean(axis=0)
            if f["kind"] == "distance":
                u = (S[1] - S[0]) / np.linalg.norm(S[1] - S[0])
                dirs = np.array([-u, u])
            else:
                dirs = (S - c) / np.linalg.norm(S - c, axis=1, keepdims=True)
            if "probing_error" in f:
                M = M + rng.normal(0, q(f["probing_error"], "mm") / 3.931, (n, N, 1)) * dirs[None]
            if f.get("repeatability"):
                R = table_rotation(ang)
                M = M + np.einsum("mji,nmj->nmi", R, rng.normal(0, rep, (n, N, 3)))
                runs = {a: positioning_runs(v) for a, v in ang.items()}
                for i in range(n):  # the rotary axes turned by their repeatability, one turn per axis and positioning:
                    turned = {a: v + rng.normal(0, rotary_R, runs[a][-1] + 1)[runs[a]] for a, v in ang.items()}
                    M[i] += chain(truth, zero, turned)[0] - S  # the nominal chain at the turned angles
            rows[:, k] = [value(f, S, M[i]) for i in range(n)]
        out.append(rows)
    return np.concatenate(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=4)
    ap.add_argument("--parts", type=int, default=512)
    ap.add_argument("--trials", type=int, default=2048)
    ap.add_argument("--repeatability", action="store_true", help="repeatability = true on every feature")
    args = ap.parse_args(argv)
    text = bundled_config("five_axis_features").read_text()
    base = tomllib.loads(bundled_config("five_axis_cafxyz").read_text())
    base.update({k: v for k, v in tomllib.loads(text).items() if k not in ("extends",)})
    features = base["features"]
    if args.repeatability:
        for f in features:
            f["repeatability"] = True
    rotary_R = q(base["sources"]["rotary_repeatability"]["R"], "rad")
    rng = np.random.default_rng(20261126)
    return coverage_by_machine(base, "five_axis_features", 11, args,
                               lambda sc, eng, blocks: part_errors(sc, eng, features, blocks, rng, rotary_R), width=16)


if __name__ == "__main__":
    sys.exit(main())
