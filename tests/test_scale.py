"""Speed and scale (issue 31): the rigid-motion removal as a rank-6 correction, large meshes."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from mtbudget.budget import point_lpu
from mtbudget.config import default_config_path, load_config
from mtbudget.engine import Engine
from mtbudget.scenario import build_scenario, rigid_projector as _rigid_projector

from conftest import rigid_free as dense_rigid_free


def _rigid_fit_residual(P, d):
    """d minus its least-squares rigid motion (translation t and small rotation w about the origin: t + w x p),
    fitted by lstsq on a matrix assembled from skew-symmetric matrices (not the code's construction)."""
    M = len(P)
    rows = []
    for p in P:
        skew = np.array([[0.0, p[2], -p[1]], [-p[2], 0.0, p[0]], [p[1], -p[0], 0.0]])  # w x p = skew @ w
        rows.append(np.hstack([np.eye(3), skew]))
    A = np.vstack(rows)
    sol, *_ = np.linalg.lstsq(A, d.reshape(M * 3, -1), rcond=None)
    return d.reshape(M * 3, -1) - A @ sol


@pytest.mark.parametrize("shape", ["grid", "random", "line"])
def test_rank6_removal_equals_the_dense_projector_and_a_rigid_fit(shape):
    rng = np.random.default_rng(3)
    if shape == "grid":
        g = np.stack(np.meshgrid(np.linspace(800, 1200, 5), np.linspace(100, 500, 5), np.linspace(200, 400, 3),
                                 indexing="ij"), -1).reshape(-1, 3)
    elif shape == "random":
        g = rng.uniform(-500, 500, (40, 3)) + [1000, 300, 300]
    else:  # points on a line: the rotation about the line moves nothing (rank 5)
        g = np.outer(np.linspace(0, 400, 9), [1.0, 0.5, 0.2]) + [800, 100, 200]
    P = _rigid_projector(g)
    D = dense_rigid_free(g)
    X = rng.normal(size=(7, 3 * len(g)))
    assert np.abs(X @ P.T - X @ D.T).max() < 1e-12
    assert np.abs(P @ X.T - D @ X.T).max() < 1e-12
    assert np.abs(P @ X[0] - D @ X[0]).max() < 1e-12
    assert np.abs(np.asarray(P) - D).max() < 1e-12
    assert np.abs(P @ X.T - _rigid_fit_residual(g, X.T)).max() < 1e-9
    # a finite rotation and translation of the points is removed to second order in the angle
    a = 1e-6
    R = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    moved = (g @ R.T + [0.3, -0.2, 0.1] - g).ravel()
    assert np.abs(P @ moved).max() < 1e-9


def test_the_engine_and_the_guf_give_the_same_numbers_with_the_dense_projector():
    sc = build_scenario(load_config())
    fast = Engine(sc, block=16, seed=5).run_blocks([0, 1])
    lpu = point_lpu(sc)
    sc.rigid_free = dense_rigid_free(sc.mesh_points)  # the dense (3 M0)^2 projector of the code before
    dense = Engine(sc, block=16, seed=5).run_blocks([0, 1])
    lpu_dense = point_lpu(sc)
    for a, b in zip(fast, dense):
        assert np.abs(a.components - b.components).max() < 1e-9  # um
        for k in a.scalars:
            assert np.allclose(a.scalars[k], b.scalars[k], rtol=1e-12, atol=1e-9), k
    assert np.abs(lpu["estimate"] - lpu_dense["estimate"]).max() < 1e-9
    # the GUF's per-point blocks against the full dense covariance, formed independently
    M0 = len(sc.mesh_rows)
    assert lpu["cov"].shape == (M0, 3, 3)
    assert np.abs(lpu["cov"] - lpu_dense["cov"]).max() < 1e-9 * np.abs(lpu_dense["cov"]).max()


def _paper_with_step(tmp_path, step):
    text = default_config_path().read_text()
    text, n = re.subn(r'(?m)^step = "100 mm"', f'step = "{step} mm"', text)
    assert n == 1
    path = tmp_path / f"step{step}.toml"
    path.write_text(text)
    return path


def test_a_4851_point_mesh_runs_and_its_removal_is_linear(tmp_path):
    from mtbudget.runner import run

    cfg = load_config(_paper_with_step(tmp_path, 20))  # paper ranges, 21 x 21 x 11 points
    sc = build_scenario(cfg)
    assert len(sc.mesh_rows) == 4851
    # the removal on a block of 64 trials: a few 3M x 6 products, never the 14553^2 matrix (1.7 GB)
    X = np.random.default_rng(1).normal(size=(64, 3 * 4851))
    t = time.process_time()
    Y = X @ sc.rigid_free.T
    assert time.process_time() - t < 0.5
    for j in range(6):  # what is left has no rigid part: orthogonal to every rigid motion
        assert np.abs(Y @ sc.rigid_free.Q[:, j]).max() < 1e-9
    res = run(sc, trials=4, block=4, attribution_trials=0)
    assert res.trials == 4 and res.not_converged == 0
    assert 0 < res.summary()["mean"] < 100  # um
    pts = res.points()
    assert len(pts) == 4851 and all(np.all(np.isfinite(p["u"]["value"])) for p in pts)


def test_the_mesh_cap_names_the_key(tmp_path):
    from mtbudget.errors import ConfigError

    path = _paper_with_step(tmp_path, 100)
    path.write_text(path.read_text().replace('step = "100 mm"', 'step_x = "4 mm"\nstep_y = "4 mm"\nstep_z = "200 mm"'))
    with pytest.raises(ConfigError, match=r"mesh.*20402 mesh points; at most 10000"):
        load_config(path)


def test_a_whole_run_imports_neither_scipy_stats_nor_matplotlib(tmp_path):
    """`mtbudget run` (table and JSON, with its budget) never loads scipy.stats (~0.35 s of CPU) nor matplotlib."""
    import subprocess
    import sys

    code = """
import sys
from click.testing import CliRunner
from mtbudget.cli import main
from mtbudget.config import default_config_path
for extra in ([], ["--json"]):
    r = CliRunner().invoke(main, ["run", str(default_config_path()), "--trials", "4", "--attribution-trials", "2",
                                  "--quiet", "--log", "r.mcap", "--force", *extra])
    assert r.exit_code == 0, r.output
print("loaded:" + ",".join(m for m in ("matplotlib", "scipy.stats") if m in sys.modules))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "loaded:", out.stdout[-500:]


def test_per_point_intervals_stream_from_about_ten_thousand_trials_and_say_their_method():
    """Below the limit every per-point value is kept (exact order statistics); beyond it they are histogrammed as
    they come (nothing per trial is kept), the intervals agree with the exact ones within the histogram's resolution,
    and the statement says which method it used."""
    from pathlib import Path

    from mtbudget import runner
    from mtbudget.report import budget_text
    from mtbudget.runner import RunSettings, keep_vector_samples, run

    assert keep_vector_samples(RunSettings(trials=10_000), 75)  # the paper's 75 points: exact up to ~11 000 trials
    assert not keep_vector_samples(RunSettings(trials=12_000), 75)
    assert not keep_vector_samples(RunSettings(trials=256), 4851)
    sc = build_scenario(load_config(Path(__file__).parent / "data" / "small.toml"))
    exact = run(sc, trials=1024, block=64, attribution_trials=0)
    assert exact.acc.vector_samples and not exact.acc.vector_hist
    limit = runner.VECTOR_SAMPLE_LIMIT
    runner.VECTOR_SAMPLE_LIMIT = 100  # this run streams
    try:
        streamed = run(sc, trials=1024, block=64, attribution_trials=0)
    finally:
        runner.VECTOR_SAMPLE_LIMIT = limit
    assert not streamed.acc.vector_samples and streamed.acc.vector_hist
    pe, ps = exact.points(), streamed.points()
    assert pe[0]["interval"]["method"].startswith("order statistics")
    assert ps[0]["interval"]["method"].startswith("quantiles of a 4000-bin histogram")
    assert pe[0]["shortest_interval"]["method"].startswith("order statistics")
    assert "piecewise-linear CDF of a 4000-bin histogram" in ps[0]["shortest_interval"]["method"]
    h = streamed.acc.vector_hist["components"]
    width = (h.high - h.low) / h.bins  # one bin, per component
    for a, b in zip(pe, ps):
        assert np.allclose(a["u"]["value"], b["u"]["value"], rtol=1e-12)  # moments are exact in both
        for end in ("low", "high"):
            # 1024 trials: the exact ends are order statistics, the histogram's interpolate between the same values;
            # they differ by at most the gap between neighbouring order statistics plus a bin
            gap = np.abs(np.asarray(a["interval"][end]) - np.asarray(b["interval"][end]))
            assert np.all(gap <= 0.02 * np.asarray(a["u"]["value"]) + width[3 * a["point"]:3 * a["point"] + 3]), gap
        # the shortest interval: its length near the trials' own (its ends slide where the distribution is nearly
        # symmetric), and it holds about p of the trials' own values (binomial scatter of 1024 trials, 3 sigma)
        w = width[3 * a["point"]:3 * a["point"] + 3]
        length = [np.subtract(x["shortest_interval"]["high"], x["shortest_interval"]["low"]) for x in (a, b)]
        assert np.all(np.abs(length[0] - length[1]) <= 0.06 * np.asarray(a["u"]["value"]) + 2 * w)
        values = np.concatenate(exact.acc.vector_samples["components"])[:, 3 * a["point"]:3 * a["point"] + 3]
        inside = ((values >= b["shortest_interval"]["low"]) & (values <= b["shortest_interval"]["high"])).mean(axis=0)
        assert np.all(np.abs(inside - 0.95) <= 3 * np.sqrt(0.95 * 0.05 / len(values)) + 2 / len(values)), inside
    assert "quantiles of a 4000-bin histogram" in budget_text(streamed)
    assert "order statistics of every trial" in budget_text(exact)


def test_histograms_of_large_meshes_are_bounded():
    from mtbudget.stats import HIST_COUNTS, VectorHistogram

    h = VectorHistogram(np.random.default_rng(0).normal(size=(4, 3 * 4851)))
    assert h.counts.size <= HIST_COUNTS and h.bins >= 500
    assert VectorHistogram(np.zeros((4, 225))).bins == 4000


# One laser tracker alone is no longer a case of this chord: the engine identifies it as [tracker]
# (Scenario.one_tracker, identify.identify), held to identify_stations by the one-tracker chord's own accuracy (1e-6 mm,
# tests/test_stations_mc.py, test_one_laser_tracker_station_agrees_with_identify_stations), not to this chord's 1e-7 um.
@pytest.mark.parametrize("stations", [slice(None), slice(1, None)])
def test_several_stations_with_one_shared_matrix_agree_with_identify_stations(stations):
    """The engine's identification over several stations (one iteration matrix shared by every trial, no Jacobian
    formed per trial: multistation._batch_chord) gives every trial's result as identify_stations, the reference
    (Gauss-Newton with each trial's exact Jacobian), one trial at a time: the compensated field to 1e-7 um, every
    unknown to 1e-5 of a scaled unknown (um, urad), chi2 to 1e-9; none falls back (measured: 7e-9 um, 1.3e-7).  Four stations, one tracker
    with two interferometers."""
    import tomllib

    from mtbudget.config import bundled_config, parse_config
    from mtbudget.engine import _station_basis
    from mtbudget.multistation import _scales, identify_stations, identify_stations_batch

    d = tomllib.loads(bundled_config("four_stations").read_text())
    d["stations"] = d["stations"][stations]
    sc = build_scenario(parse_config(d))
    sim = Engine(sc, block=12, seed=11).simulate(0)
    model, hold = sc.id_model, sc.unidentifiable(sc.id_model)
    basis = _station_basis(sc, model, None, hold)
    assert len(basis) == 5  # the chord's shared matrices
    b = identify_stations_batch(model, sc.stations, sc.row_station, sim[0], sim.ranges, sc.noise.repeatability,
                                hold=hold, basis=basis)
    assert b["converged"].all() and not b["failed"].any()
    scale, p = _scales(model, sc.stations), model.n_params
    for i in range(12):
        r = identify_stations(model, sc.stations, sc.row_station, sim[0][i], sim.ranges[i], sc.noise.repeatability,
                              hold=hold)
        assert np.abs((b["x"][i] - r.x) * scale).max() < 1e-5, i
        F = sc.evaluate(model, np.stack([b["theta"][i], r.x[:p]]))
        assert np.abs(sc.rigid_free @ (F[0] - F[1]).ravel()).max() * 1e3 < 1e-7  # um
        assert abs(b["chi2"][i] / r.chi2 - 1) < 1e-9


def test_a_tracker_step_is_an_exact_rigid_motion_about_the_centre():
    """kernels_stations.rigid_step against scipy's rotation of a rotation vector (a second implementation): the new
    rotation is Rot(w) R, the new position Rot(w) (T - c) + c + t, for rotations of 1e-9 to 0.3 rad (the series
    below 1e-6 rad and Rodrigues above), to 1e-15 and 1e-12 mm."""
    from scipy.spatial.transform import Rotation

    from mtbudget import tracker as lt
    from mtbudget.kernels_stations import rigid_step

    rng = np.random.default_rng(8)
    k = 8
    angles = rng.normal(0, 0.5, (k, 3))
    R = np.ascontiguousarray(lt.rotation(angles[:, 0], angles[:, 1], angles[:, 2]))
    x = rng.normal(0, 1000, (k, 9))  # the pose's translation at columns 2..4
    om = rng.normal(size=(k, 3))
    om *= (np.logspace(-9, np.log10(0.3), k) / np.linalg.norm(om, axis=1))[:, None]
    z = np.ascontiguousarray(np.concatenate([rng.normal(0, 0.01, (k, 3)), om], axis=1))
    cen = np.array([1000.0, 300.0, 300.0])
    R1, x1 = R.copy(), x.copy()
    zx = np.zeros((k, 9))  # the steps of every unknown, the pose's at columns 2..7
    zx[:, 2:8] = z
    t = np.arange(k)[::-1].copy()  # trial t[j] moved by row j of the steps
    rigid_step(R1, x1, zx[::-1].copy(), 2, cen, t)
    Rot = Rotation.from_rotvec(om).as_matrix()
    assert np.abs(R1 - Rot @ R).max() < 1e-15
    T = (Rot @ (x[:, 2:5] - cen)[:, :, None])[:, :, 0] + cen + z[:, :3]
    assert np.abs(x1[:, 2:5] - T).max() < 1e-12
    assert np.array_equal(np.delete(x1, [2, 3, 4], axis=1), np.delete(x, [2, 3, 4], axis=1))  # the rest untouched


def test_the_several_station_chord_in_pieces_gives_the_same_bits(monkeypatch):
    """More trials than multistation.CHORD_CHUNK are iterated in pieces (the working set kept in cache): every result
    equals that of one call over all of them, bit for bit (a piece of one trial included: 301 = 3 x 100 + 1)."""
    import tomllib

    import mtbudget.multistation as ms
    from mtbudget.config import bundled_config, parse_config
    from mtbudget.engine import _station_basis

    d = tomllib.loads(bundled_config("four_stations").read_text())
    d["stations"] = d["stations"][:1] + d["stations"][2:3]  # a tracker and an interferometer
    sc = build_scenario(parse_config(d))
    sim = Engine(sc, block=301, seed=5).simulate(0)
    model, hold = sc.id_model, sc.unidentifiable(sc.id_model)
    basis = _station_basis(sc, model, None, hold)

    def batch():
        return ms.identify_stations_batch(model, sc.stations, sc.row_station, sim[0], sim.ranges,
                                          sc.noise.repeatability, hold=hold, basis=basis)

    monkeypatch.setattr(ms, "CHORD_CHUNK", 100)
    pieces = batch()
    monkeypatch.setattr(ms, "CHORD_CHUNK", 10**6)
    whole = batch()
    assert sorted(pieces) == sorted(whole) and pieces["dof"] == whole["dof"]
    for k, v in whole.items():
        if isinstance(v, np.ndarray):
            assert v.shape[0] == 301 and np.array_equal(pieces[k], v, equal_nan=True), k


def test_one_station_poses_the_one_tracker_identification_problem():
    """A [[stations]] list of one laser tracker states the identification [tracker] states: the same unknowns (its
    pose and the geometric parameters), weights, datum (what one tracker cannot identify held at zero) and degrees of
    freedom.  The one-tracker identification (identify.identify, Gauss-Newton) and the several-station reference
    (multistation.identify_stations) of the same trials agree to their tolerance (measured: 5e-9 in the unknowns,
    6e-10 um in the compensated field, 9e-12 in chi2).  Which is why the engine identifies such a run as [tracker]
    (Scenario.one_tracker; its chord stops within 6e-6 um of this minimum in the field: tests/test_stations_mc.py)."""
    import tomllib

    from mtbudget.config import bundled_config, parse_config
    from mtbudget.identify import Noise, Strategy, identify, scale_vector
    from mtbudget.multistation import _scales, identify_stations

    d = tomllib.loads(bundled_config("four_stations").read_text())
    d["stations"] = d["stations"][:1]
    sc = build_scenario(parse_config(d))
    sim = Engine(sc, block=6, seed=11).simulate(0)
    model, hold = sc.id_model, sc.unidentifiable(sc.id_model)
    st = sc.stations[0]
    noise = Noise(st.angular, st.distance, st.distance_per_length, sc.noise.repeatability)
    one = identify(model, sim[0], noise, Strategy.one_phase(solver="gauss-newton", xtol=1e-9, max_iter=50))
    assert one.converged.all()
    sv, p = _scales(model, sc.stations), model.n_params
    for i in range(6):
        r = identify_stations(model, sc.stations, sc.row_station, sim[0][i], sim.ranges[i], sc.noise.repeatability,
                              hold=hold)
        assert np.abs((np.concatenate([one.theta[i], one.pose[i]]) - r.x) * sv).max() < 1e-6  # um, urad
        F = sc.evaluate(model, np.stack([one.theta[i], r.x[:p]]))
        assert np.abs(sc.rigid_free @ (F[0] - F[1]).ravel()).max() * 1e3 < 1e-8  # um
        assert abs(one.chi2[i] / r.chi2 - 1) < 1e-9 and one.dof == r.dof
    assert np.abs(scale_vector(model) * one.theta).max() > 10.0  # the parameters identified are not zeros


def test_the_station_kernels_equal_the_numpy_residuals_and_the_exact_gradient(monkeypatch):
    """kernels_stations against the batch's numpy residuals (``evaluate``) and A^T w from its exact Jacobian."""
    from mtbudget import kernels_stations as ks
    from mtbudget import multistation as ms
    from mtbudget import tracker as lt
    from mtbudget.config import bundled_config
    from mtbudget.engine import _station_basis
    from mtbudget.machine import chain_adjoint

    sc = build_scenario(load_config(bundled_config("four_stations")))
    sim = Engine(sc, block=5, seed=2).simulate(0)
    model, hold = sc.id_model, sc.unidentifiable(sc.id_model)
    got = {}
    monkeypatch.setattr(ms, "_batch_chord", lambda model, blocks, x, evaluate, *a: got.update(
        blocks=blocks, x=x.copy(), evaluate=evaluate) or {})
    ms.identify_stations_batch(model, sc.stations, sc.row_station, sim[0], sim.ranges, sc.noise.repeatability,
                               hold=hold, basis=_station_basis(sc, model, None, hold))
    rng = np.random.default_rng(4)
    sv, p = ms._scales(model, sc.stations), model.n_params
    x = got["x"] + rng.normal(0, 1, got["x"].shape) / sv  # off the start by about 1 um or urad in every unknown
    t = np.array([4, 1, 3])  # trials out of order, a subset
    w_ref, raw_ref, A = got["evaluate"](x[t], t, jacobian=True)
    P = model.machine_points(x[t][:, :p])  # the trials' points, row j for trial t[j]
    P0 = model.machine_points(np.zeros((1, p)))[0]
    ahead, centre = {}, {}  # a tracker's part of the next gradient, left by its residuals; its centre of rotation
    xt = np.ascontiguousarray(x[t])
    x = np.ascontiguousarray(x)
    w = np.full((len(x), w_ref.shape[1]), np.nan)  # written at rows t only
    v, g = np.zeros((3, model.n_points, 3)), np.zeros_like(xt)
    _, adjoint = chain_adjoint(model.config, model.errors, xt[:, :p], model.inputs, B=model.B)
    off = 0
    for (st, idx, W, sl), e_ref in zip(got["blocks"], raw_ref):
        idx = np.ascontiguousarray(idx, np.int64)
        meas = np.ascontiguousarray(sim[0][:, idx] if st.kind == "xyz" else sim.ranges[:, idx])
        W = np.ascontiguousarray(W)
        e = np.full((len(x),) + e_ref.shape[1:], np.nan)
        if st.kind == "xyz":
            R = np.ascontiguousarray(lt.rotation(x[:, sl.start + 3], x[:, sl.start + 4], x[:, sl.start + 5]))
            centre[sl.start] = cen = np.ascontiguousarray(P0[idx].mean(axis=0))
            ahead[sl.start] = (np.full((len(x), len(idx), 3), np.nan), np.full((len(x), 6), np.nan))
            ks.xyz_residual(P, idx, x, sl.start, R, meas, W, t, off, w, e, cen, *ahead[sl.start])
        else:
            ks.range_residual(P, idx, x, sl.start, meas, W, t, off, w, e)
        assert np.abs(e[t] - e_ref).max() < 1e-12  # mm
        assert np.isnan(e[0]).all()  # a trial not asked for is not written
        off += e[0].size
    assert np.abs(w[t] - w_ref).max() < 1e-9 * np.abs(w_ref).max()
    # the gradient: the chain's part against A^T w from the exact Jacobian; a laser tracker's pose, moved by a small
    # rigid motion of the station (the chord's coordinates), against central differences of the numpy residuals
    # along ks.rigid_step
    off = 0
    for st, idx, W, sl in got["blocks"]:
        idx = np.ascontiguousarray(idx, np.int64)
        W, pos = np.ascontiguousarray(W), np.arange(3)
        if st.kind == "xyz":
            ks.xyz_gradient(*ahead[sl.start], t, idx, sl.start, v, g)
            off += 3 * len(idx)
        else:
            d = P[:, idx] - xt[:, None, sl.start:sl.start + 3]
            U = np.ascontiguousarray(d / np.sqrt((d * d).sum(-1))[..., None])
            ks.range_gradient(w, off, W, t, U, pos, idx, sl.start, v, g)
            off += len(idx)
    g[:, :p] = adjoint(v)
    ref = np.einsum("kri,kr->ki", A, w[t])  # A^T w from the exact whitened Jacobian (scaled unknowns)
    rigid = np.zeros(g.shape[1], bool)
    for c0 in centre:
        rigid[c0:c0 + 6] = True
    assert np.abs((g / sv - ref)[:, ~rigid]).max() < 1e-9 * np.abs(ref).max()
    for c0, cen in centre.items():
        for k in range(6):
            h = 1e-4 if k < 3 else 1e-7  # mm, rad
            diff = []
            for sign in (1, -1):
                xk = xt.copy()
                Rk = np.ascontiguousarray(lt.rotation(xk[:, c0 + 3], xk[:, c0 + 4], xk[:, c0 + 5]))
                z = np.zeros(xk.shape)
                z[:, c0 + k] = sign * h
                ks.rigid_step(Rk, xk, z, c0, cen, np.arange(3))
                xk[:, c0 + 3:c0 + 6] = lt.euler_from_rotation(Rk)
                diff.append(got["evaluate"](xk, t, jacobian=False)[0])
            dw = (diff[0] - diff[1]) / (2 * h)  # d(whitened residual) = -d(whitened prediction)
            fd = -(dw * w[t]).sum(axis=1)
            assert np.abs(g[:, c0 + k] - fd).max() < 1e-6 * np.abs(fd).max(), (c0, k)


def test_the_chord_evaluates_the_chain_once_per_distinct_row():
    """multistation._distinct_rows_chain (the several-station chord's chain: each of the plan's distinct rows once)
    against the model's own chain at every row, bit for bit, with random parameters: four stations measuring the same
    75 poses (300 rows, 75 distinct), and a five-axis plan whose rows are all distinct."""
    from mtbudget.config import bundled_config
    from mtbudget.identify import scale_vector
    from mtbudget.multistation import _distinct_rows_chain

    rng = np.random.default_rng(8)
    for name, distinct in (("four_stations", 75), ("five_axis_cafxyz", None)):
        model = build_scenario(load_config(bundled_config(name))).id_model
        plan = model.plan
        rows = np.column_stack([plan.nominal, plan.tool] + [plan.angles[a] for a in sorted(plan.angles)])
        assert distinct is None or len(np.unique(rows, axis=0)) == distinct
        chain_at, inv = _distinct_rows_chain(model)
        theta = rng.normal(0, 1, (5, model.n_params)) / scale_vector(model)  # about 1 um or urad each
        P, ref = chain_at(theta), model.machine_points(theta)
        assert P.shape == (5, len(np.unique(rows, axis=0)), 3) and inv.shape == (model.n_points,)
        assert np.array_equal(P[:, inv], ref) and np.abs(ref).max() > 100.0  # mm: points, not zeros


def test_tracker_whiteners_equal_numpys_covariance_and_whitener():
    """kernels_stations.tracker_whiteners against tracker.covariance + repeatability^2 I, then identify.whitener (the
    numpy passes it replaces), bit for bit on random points from 1 um to metres; a covariance that is not positive
    definite (a point at the tracker, no repeatability) is left to numpy, which raises."""
    from mtbudget import tracker as lt
    from mtbudget.identify import whitener
    from mtbudget.kernels_stations import tracker_whiteners
    from mtbudget.multistation import _tracker_whiteners
    from mtbudget.recording import Station

    rng = np.random.default_rng(5)
    for scale in (1e-3, 1.0, 3e3):
        P = rng.normal(0, scale, (40, 60, 3))
        P[0, :2] = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]  # on the tracker's axes: the angles' conventions
        for ang, dist, dpl, rep in ((5e-6, 4e-3, 0.8e-6, 1.5e-3), (2e-5, 1e-3, 0.0, 1e-4)):
            out = np.empty(P.shape + (3,))
            assert tracker_whiteners(P, ang, dist, dpl, float(rep**2), out)
            ref = whitener(lt.covariance(P, ang, dist, dpl) + rep**2 * np.eye(3))
            assert np.array_equal(out.view(np.uint64), ref.view(np.uint64)), (scale, ang)
    P[0, 0] = 0.0
    assert not tracker_whiteners(P, 5e-6, 4e-3, 0.0, 0.0, np.empty(P.shape + (3,)))
    st = Station(id=1, kind="xyz", angular=5e-6, distance=4e-3, distance_per_length=0.0)
    with pytest.raises(np.linalg.LinAlgError):
        _tracker_whiteners(P, st, 0.0)


def test_several_stations_with_stated_scales_take_the_reference_batch():
    """With [scales] the identification has fixed inputs, which the compiled J^T v does not take: the engine's
    several-station batch then iterates by Gauss-Newton (the basis's chord matrices unused), and a block runs."""
    import tomllib

    from mtbudget.config import bundled_config, parse_config

    d = tomllib.loads(bundled_config("four_stations").read_text())
    d["scales"] = {"x": {"cte": "11.5 um/(m*K)", "fixed_point": "800 mm"}}
    d["machine_tool"].pop("cte", None)
    d["sources"]["disable"] = d["sources"].get("disable", []) + ["temperature_drift"]
    sc = build_scenario(parse_config(d))
    assert sc.correction  # fixed inputs: the reference batch
    res = Engine(sc, block=4, seed=1).run_block(0)
    assert res.not_converged == 0 and np.all(np.isfinite(res.components))


def test_registered_distances_equal_register_then_to_tracker():
    """kernels_stations.registered_distances (the Eq. 27 error before compensation of a tracker's rows) against
    tracker.register and tracker.to_tracker trial by trial, for a tracker pose of the paper and a reflected fit."""
    from mtbudget import tracker as lt
    from mtbudget.kernels_stations import registered_distances

    rng = np.random.default_rng(1)
    P0 = rng.uniform(0, 500, (75, 3)) + [800, 100, 200]
    for pose in ([-563.5, 194.4, 677.8, 0.0006, 0.0006, 1.03], [2563.5, 194.4, 677.8, 0.0, 0.0, np.pi]):
        meas = lt.to_tracker(P0[None], np.array([pose])) + rng.normal(0, 0.02, (6, 75, 3))
        out = np.empty((6, 75))
        registered_distances(P0, meas, out)
        for i in range(6):
            ref = np.linalg.norm(meas[i] - lt.to_tracker(P0[None], lt.register(P0[None], meas[i][None]))[0], axis=1)
            assert np.abs(out[i] - ref).max() < 1e-9  # mm
        assert 0.01 < out.mean() < 0.05  # the noise, not a wrong fit
