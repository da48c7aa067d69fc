"""Identification over four stations (2 xyz, 2 range) x 75 points vs scipy.optimize.least_squares (issue 20).

Run:  python benchmarks/bench_multistation.py [--repeat N] [--seeds K]   (then the Monte Carlo's batched
identification against identify_stations trial by trial, 64 trials of the bundled four_stations configuration)

Data: the bundled generator benchmarks/make_four_stations.py (K noise draws, seeds 2020, 2021, ...).
Reference: scipy.optimize.least_squares (trust region, 2-point finite-difference Jacobian, ftol = xtol =
gtol = 1e-12) on the same whitened residuals, from the same start, over the identifiable unknowns only
(the non-identifiable ones that mtbudget.multistation names are held at zero in both).  The two must agree
(every identifiable unknown within 1e-3 of its standard uncertainty, chi2 to 1e-9 relative) before any time
is reported.  Times are the median of N runs, measured in this run, on this machine, one BLAS thread.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import optimize
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))

import make_four_stations  # noqa: E402

from mtbudget import tracker as lt  # noqa: E402
from mtbudget.model import MeasurementModel  # noqa: E402
from mtbudget.multistation import identify_stations, multilaterate  # noqa: E402
from mtbudget.identify import whitener  # noqa: E402
from mtbudget.recording import read_recording  # noqa: E402


def reference(rec, model, fixed_zero):
    """scipy.optimize.least_squares on the whitened residuals of all stations (an independent assembly)."""
    p = model.n_params
    stations = rec.station_list()
    sid = rec.station_ids()
    P0 = model.machine_points(np.zeros((1, p)))[0]
    x0, blocks = [np.zeros(p)], []
    for st in stations:
        rows = np.flatnonzero(sid == st.id)
        if st.kind == "xyz":
            meas = rec.lt[rows]
            C = lt.covariance(meas, st.angular, st.distance, st.distance_per_length)
            W = whitener(C + rec.repeatability**2 * np.eye(3))
            x0.append(lt.register(P0[rows], meas[None])[0])
        else:
            meas = rec.lt_range[rows]
            S, o = multilaterate(P0[rows], meas)
            r = np.linalg.norm(P0[rows] - S, axis=1)
            W = 1.0 / np.sqrt((st.distance + st.distance_per_length * r) ** 2 + rec.repeatability**2)
            x0.append(np.r_[S, o])
        blocks.append((st.kind, rows, meas, W))
    x0 = np.concatenate(x0)
    free = np.ones(len(x0), bool)
    free[fixed_zero] = False

    def residuals(xf):
        x = x0.copy()
        x[free] = xf
        x[fixed_zero] = 0.0
        P = model.machine_points(x[:p][None])[0]
        out, k = [], p
        for kind, rows, meas, W in blocks:
            if kind == "xyz":
                pred = lt.to_tracker(P[rows][None], x[k:k + 6][None])[0]
                out.append(np.einsum("nij,nj->ni", W, meas - pred).ravel())
                k += 6
            else:
                out.append(W * (meas - np.linalg.norm(P[rows] - x[k:k + 3], axis=1) - x[k + 3]))
                k += 4
        return np.concatenate(out)

    sol = optimize.least_squares(residuals, x0[free], method="trf", x_scale="jac", ftol=1e-12, xtol=1e-12, gtol=1e-12)
    x = x0.copy()
    x[free] = sol.x
    x[fixed_zero] = 0.0
    return x, float(sol.fun @ sol.fun), sol.nfev


def median_time(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    rows = []
    with threadpool_limits(limits=1, user_api="blas"), tempfile.TemporaryDirectory() as tmp:
        for k in range(args.seeds):
            make_four_stations.SEED = 2020 + k
            folder = make_four_stations.main(Path(tmp) / f"s{k}")
            rec = read_recording(folder, several_stations=True)
            model = MeasurementModel.for_plan(rec.machine, rec.plan)
            call = (lambda: identify_stations(model, rec.station_list(), rec.station_ids(), rec.lt, rec.lt_range,
                                              rec.repeatability))
            res = call()
            fixed_zero = np.flatnonzero(~res.identifiable())
            ref_x, ref_chi2, nfev = reference(rec, model, fixed_zero)
            ok = res.identifiable()
            dev = np.abs(res.x - ref_x)[ok] / res.u[ok]
            assert dev.max() < 1e-3, f"seed {2020 + k}: the two solutions differ by {dev.max():.2e} u"
            assert abs(res.chi2 - ref_chi2) <= 1e-9 * ref_chi2, (res.chi2, ref_chi2)
            t_ms = median_time(call, args.repeat)
            t_ref = median_time(lambda: reference(rec, model, fixed_zero), max(1, args.repeat // 2))
            rows.append((2020 + k, len(rec), res.n_unknowns, res.rank, res.chi2_per_dof, dev.max(), res.iterations,
                         nfev, t_ms, t_ref))
    print("four stations (2 xyz, 2 range) x 75 points; accuracy checked before timing; one BLAS thread")
    print(f"{'seed':>5} {'rows':>5} {'unknowns':>8} {'rank':>5} {'chi2/dof':>9} {'max|dx|/u':>10} "
          f"{'GN iter':>7} {'ref nfev':>8} {'multistation s':>14} {'least_squares s':>15} {'ratio':>6}")
    for seed, m, n, r, c, d, it, nfev, a, b in rows:
        print(f"{seed:>5} {m:>5} {n:>8} {r:>5} {c:>9.3f} {d:>10.1e} {it:>7} {nfev:>8} {a:>14.4f} {b:>15.3f} "
              f"{b / a:>6.1f}")


def engine_trials(trials: int, repeat: int):
    """The Monte Carlo's identification of several stations: identify_stations_batch (vectorised over trials) against
    identify_stations one trial at a time, on the same simulated trials of the bundled four_stations configuration
    (the paper's machine, 2 trackers + 2 interferometers, 300 rows); the compensated fields must agree to 1e-6 um
    before any time is printed."""
    from mtbudget.config import bundled_config, load_config
    from mtbudget.engine import Engine
    from mtbudget.multistation import identify_stations_batch
    from mtbudget.scenario import build_scenario

    sc = build_scenario(load_config(bundled_config("four_stations")))
    model, hold = sc.id_model, sc.unidentifiable(sc.id_model)
    sim = Engine(sc, block=trials).simulate(0)
    args = (model, sc.stations, sc.row_station)

    def batch():
        return identify_stations_batch(*args, sim[0], sim.ranges, sc.noise.repeatability, hold=hold)["theta"]

    def one_by_one():
        return np.array([identify_stations(*args, sim[0][i], sim.ranges[i], sc.noise.repeatability, hold=hold).x[
            :model.n_params] for i in range(trials)])

    with threadpool_limits(limits=1, user_api="blas"):
        a, b = batch(), one_by_one()
        F = sc.evaluate(model, np.concatenate([a, b]))
        diff = np.abs((F[:trials] - F[trials:]).reshape(trials, -1) @ sc.rigid_free.T).max() * 1e3
        assert diff < 1e-6, f"batched and trial-by-trial identification differ by {diff:.2e} um"
        t_batch = median_time(batch, repeat)
        t_one = median_time(one_by_one, max(1, repeat // 2))
    print(f"\nthe Monte Carlo's identification, four stations x 75 points, {trials} trials, one BLAS thread "
          f"(compensated fields agree to {diff:.1e} um):")
    print(f"  identify_stations_batch   {t_batch / trials * 1e3:7.2f} ms per trial")
    print(f"  identify_stations, a loop {t_one / trials * 1e3:7.2f} ms per trial   ratio {t_one / t_batch:.1f}x")


if __name__ == "__main__":
    main()
    engine_trials(64, 3)
