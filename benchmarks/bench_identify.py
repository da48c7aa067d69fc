"""Batched identification vs scipy.optimize.least_squares trial by trial (issue: identification speed).

Run:  python benchmarks/bench_identify.py [--quick]

Both solve the same problem (same plan, weights, identifiable parameter
directions) on the same simulated trials.  Before any time is reported, every
trial's residuals must agree with the reference solver (Gauss-Newton, exact
Jacobian) to 1e-6 mm, and the sample solved with scipy must agree too: to
2e-6 mm, because scipy with 3-point differences itself stops up to ~1.4e-6 mm
from the minimum (its distance from Gauss-Newton is printed beside ours; a
round-off change of its start moves its end point by ~1e-6 mm).  Times are
measured in this run, on this machine, and reported as ratios.
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np
from scipy import optimize

from mtbudget import tracker as lt
from mtbudget.identify import Noise, Strategy, analyse, identify, range_basis, scale_vector
from mtbudget.model import MeasurementModel
from mtbudget.plan import build_plan, mesh

NOISE = Noise(angular=5e-6, distance=4e-3, distance_per_length=0.8e-6, repeatability=1.5e-3)
POSE = np.array([-700.0, 250.0, 650.0, 0.002, -0.001, 0.3])


def make_model(tools=((0, 0, -150),), runs=1):
    pts = mesh({"x": (800, 1200), "y": (100, 500), "z": (200, 400)}, 100)
    return MeasurementModel.for_plan("XFYZ", build_plan(pts, [list(t) for t in tools], runs=runs))


def trials(model, N, seed=1):
    rng = np.random.default_rng(seed)
    sv = scale_vector(model)
    Q = range_basis(np.ones(model.n_params, bool), analyse(model).null_space)
    theta = (Q @ (Q.T @ rng.normal(0, 8.0, model.n_params))) / sv
    clean = np.broadcast_to(model.predict(theta, POSE), (N, model.n_points, 3))
    return model.predict(np.broadcast_to(theta, (N, model.n_params)), POSE, draw_noise(clean, rng))


def draw_noise(P_LT, rng):
    """Tracker noise (range and both angles) and machine repeatability, drawn here for the benchmark alone."""
    N, M = P_LT.shape[:2]
    r = np.linalg.norm(P_LT, axis=-1)
    sph = np.empty((N, M, 3))
    sph[..., 0] = rng.standard_normal((N, M)) * (NOISE.distance + NOISE.distance_per_length * r)
    sph[..., 1:] = rng.standard_normal((N, M, 2)) * NOISE.angular
    out = {"spherical_noise": sph}
    for a in "xyz":
        out[f"axis_offset.{a}"] = rng.standard_normal((N, M)) * NOISE.repeatability
    return out


def scipy_one(model, meas, Q, sv):
    """One trial with scipy, over the same identifiable directions theta = Q phi / sv."""
    C = model.covariance(meas[None], NOISE.angular, NOISE.distance, NOISE.distance_per_length, NOISE.repeatability)[0]
    Wh = np.linalg.inv(np.linalg.cholesky(C))

    def fun(x):
        r = meas - model.predict((Q @ x[6:]) / sv, x[:6])[0]
        return np.einsum("mij,mj->mi", Wh, r).ravel()

    pose0 = lt.register(model.machine_points(np.zeros(model.n_params)), meas[None])[0]
    x0 = np.concatenate([pose0, np.zeros(Q.shape[1])])
    sol = optimize.least_squares(fun, x0, method="trf", x_scale="jac", jac="3-point",
                                 ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=10000)
    return meas - model.predict((Q @ sol.x[6:]) / sv, sol.x[:6])[0]


def time_batched(model, meas, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        res = identify(model, meas, NOISE)
        best = min(best, time.perf_counter() - t)
    return best, res


def peak_memory(model, meas):
    tracemalloc.start()
    identify(model, meas, NOISE)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="smaller runs (no 1e5 point of the scaling curve)")
    ap.add_argument("--scipy-trials", type=int, default=30, help="trials solved one by one with scipy")
    args = ap.parse_args()
    model = make_model()
    N = 1000
    meas = trials(model, N)
    t_batch, res = time_batched(model, meas)
    sv = scale_vector(model)
    Q = range_basis(np.ones(model.n_params, bool), res.identifiability.null_space)
    gn = identify(model, meas, NOISE, Strategy(solver="gauss-newton"))
    worst_gn = np.abs(gn.residual - res.residual).max()
    assert worst_gn < 1e-6, f"the batched results differ from Gauss-Newton by {worst_gn:.3g} mm"
    K = args.scipy_trials
    t = time.perf_counter()
    sols = [scipy_one(model, meas[n], Q, sv) for n in range(K)]
    t_scipy = (time.perf_counter() - t) / K
    worst = max(np.abs(sols[n] - res.residual[n]).max() for n in range(K))
    scipy_gn = max(np.abs(sols[n] - gn.residual[n]).max() for n in range(K))
    assert worst < 2e-6, f"results differ from scipy's by {worst:.3g} mm"
    per_trial = t_batch / N
    print(f"plan: {model.n_points} points, {model.n_params} geometric parameters ({res.identifiability.identifiable} identifiable)")
    print(f"batched:   N={N} in {t_batch:.3f} s = {per_trial * 1e3:.3f} ms/trial = {N / t_batch:.0f} trials/s")
    print(f"scipy:     {t_scipy * 1e3:.1f} ms/trial (mean of {K} trials, same inputs)")
    print(f"ratio:     {t_scipy / per_trial:.0f}x   (largest residual difference {worst:.2e} mm; Gauss-Newton's from "
          f"scipy's {scipy_gn:.2e} mm; ours from Gauss-Newton's, all {N} trials, {worst_gn:.2e} mm)")
    print(f"peak traced memory, N=1000: {peak_memory(model, meas) / 2**20:.0f} MiB")
    print("\nscaling with N (75 points):")
    for n in (1000, 10000) + (() if args.quick else (100000,)):
        m = trials(model, n, seed=2)
        t = time.perf_counter()
        identify(model, m, NOISE)
        dt = time.perf_counter() - t
        print(f"  N={n:>6}: {dt:8.2f} s  {n / dt:7.0f} trials/s  (x{dt / t_batch:.1f} the N=1000 time)")
    print("\nscaling with points (N=1000):")
    for tools, runs in (((0, 0, -150),), 1), (((0, 0, -150), (0, 0, -300)), 1), (((0, 0, -150), (0, 0, -300)), 2):
        mm = make_model(tools, runs)
        m = trials(mm, 1000, seed=3)
        dt, _ = time_batched(mm, m, repeat=1)
        print(f"  M={mm.n_points:>4}: {dt:7.2f} s  {1000 / dt:6.0f} trials/s  (x{dt / t_batch:.2f} the 75-point time)")


if __name__ == "__main__":
    main()
