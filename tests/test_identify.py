"""Identification against independent numbers: exact recovery, the example's truth, scipy, closed forms."""

import json

import numpy as np
import pytest
from scipy import optimize, stats

from mtbudget import tracker as lt
from mtbudget.config import example_recording
from mtbudget.errors import IdentificationError
from mtbudget.identify import Noise, Strategy, analyse, identify, range_basis, scale_vector
from mtbudget.model import MeasurementModel
from mtbudget.plan import build_plan, mesh
from mtbudget.simulate import parameters_from_truth, truth_error_model

NOISE = Noise(angular=5e-6, distance=4e-3, distance_per_length=0.8e-6, repeatability=1.5e-3)
POSE = np.array([-700.0, 250.0, 650.0, 0.002, -0.001, 0.3])
# unit factors written out by hand on purpose: the tests check mtbudget's conversions, they do not reuse them
UM_PER_MM, URAD_PER_RAD = 1e3, 1e6
POSE_SCALE_BY_HAND = np.array([UM_PER_MM] * 3 + [URAD_PER_RAD] * 3)


def paper_plan(tools=((0, 0, -150), (0, 0, -300)), runs=2):
    pts = mesh({"x": (800, 1200), "y": (100, 500), "z": (200, 400)}, 100)
    return build_plan(pts, [list(t) for t in tools], runs=runs)


def identifiable_truth(model, rng):
    """Random parameters with no component in the plan's non-identifiable directions."""
    ident = analyse(model)
    sv = scale_vector(model)
    theta_s = np.array([rng.normal(0, 8.0) for _ in model.errors.params])  # ~8 um / 8 urad
    Q = range_basis(np.ones(model.n_params, bool), ident.null_space)
    return (Q @ (Q.T @ theta_s)) / sv


def test_noise_free_verification_is_recovered_to_1e_9_mm(rng):
    model = MeasurementModel.for_plan("XFYZ", paper_plan())
    theta = identifiable_truth(model, rng)
    meas = model.predict(theta, POSE)[0]
    res = identify(model, meas, NOISE)
    assert res.converged.all()
    err_mm = np.abs(res.theta[0] - theta) * np.where(np.array(model.errors.units) == "mm", 1.0, 1000.0)  # rad on 1 m
    assert err_mm.max() < 1e-9
    assert np.abs(res.pose[0, :3] - POSE[:3]).max() < 1e-9
    assert np.abs(res.pose[0, 3:] - POSE[3:]).max() * 2000 < 1e-9
    assert np.abs(res.residual).max() < 1e-9


@pytest.mark.parametrize("code", ["FXYZ", "XYFZ", "ZFXY"])
def test_noise_free_recovery_in_other_configurations(code, rng):
    model = MeasurementModel.for_plan(code, paper_plan())
    theta = identifiable_truth(model, rng)
    res = identify(model, model.predict(theta, POSE)[0], NOISE)
    assert np.abs(res.residual).max() < 1e-9
    assert np.abs(model.machine_points(res.theta) - model.machine_points(theta)).max() < 1e-9


def test_null_example_chi_square_per_dof(null_recording):
    model = MeasurementModel.for_plan(null_recording.machine, null_recording.plan)
    res = identify(model, null_recording.lt, Noise.of(null_recording))
    assert 0.8 <= res.chi2_per_dof[0] <= 1.25
    # and under the chi-square distribution with its dof, not an outlier either way
    p = stats.chi2.sf(res.chi2[0], res.dof)
    assert 0.001 < p < 0.999


def _rigid_projector(P):
    """Projector onto the rigid motions (translations, small rotations) of points P (M, 3): (3M, 3M)."""
    M = len(P)
    A = np.zeros((M, 3, 6))
    A[:, :, :3] = np.eye(3)
    c = P - P.mean(0)
    A[:, 0, 4], A[:, 0, 5] = c[:, 2], -c[:, 1]
    A[:, 1, 3], A[:, 1, 5] = -c[:, 2], c[:, 0]
    A[:, 2, 3], A[:, 2, 4] = c[:, 1], -c[:, 0]
    A = A.reshape(3 * M, 6)
    return A @ np.linalg.pinv(A)


def test_null_example_field_agrees_with_truth_within_its_uncertainty(null_recording):
    rec = null_recording
    truth = json.loads((example_recording("null") / "truth.json").read_text())
    model = MeasurementModel.for_plan(rec.machine, rec.plan)
    res = identify(model, rec.lt, Noise.of(rec))
    tmodel = MeasurementModel(model.config, truth_error_model(rec.plan, truth["geometric_errors"]["coefficients"]), rec.plan)
    theta_t, _, _ = parameters_from_truth(truth, tmodel)
    F_t = tmodel.machine_points(theta_t)[0].reshape(-1)
    P_i, J = model.machine_points(res.theta, jacobian=True)
    F_i = P_i[0].reshape(-1)
    J = J[0].reshape(-1, model.n_params)
    H = np.eye(len(F_i)) - _rigid_projector(P_i[0])
    d = H @ (F_i - F_t)
    cov = H @ J @ res.cov_theta[0] @ J.T @ H.T
    w, V = np.linalg.eigh(cov)
    keep = w > w.max() * 1e-10
    z = (V[:, keep].T @ d) / np.sqrt(w[keep])
    chi2, dof = float(z @ z), int(keep.sum())
    assert stats.chi2.sf(chi2, dof) > 1e-3, (chi2, dof)
    # and the identified field is much closer to the truth than no compensation at all
    d0 = H @ (P_i[0].reshape(-1) - F_i + (model.plan.nominal + model.plan.tool).reshape(-1) - F_t)
    assert np.linalg.norm(d) < 0.5 * np.linalg.norm(H @ ((model.plan.nominal + model.plan.tool).reshape(-1) - F_t))
    del d0


def scipy_identify(model, meas, noise, pose0, free):
    """Second implementation: scipy.optimize.least_squares on the whitened residuals of the exact chain.

    ``free`` selects the geometric parameters it may move (the others stay 0).
    """
    C = model.covariance(meas[None], noise.angular, noise.distance, noise.distance_per_length, noise.repeatability)[0]
    Wh = np.linalg.inv(np.linalg.cholesky(C))
    p = model.n_params

    def params(x):
        theta = np.zeros(p)
        theta[free] = x[6:]
        return x[:6], theta

    def fun(x):
        pose, theta = params(x)
        r = meas - model.predict(theta, pose)[0]
        return np.einsum("mij,mj->mi", Wh, r).ravel()

    x0 = np.concatenate([pose0, np.zeros(free.sum())])
    scale = np.concatenate([[1, 1, 1, 1e-3, 1e-3, 1e-3], 1e-3 * np.ones(free.sum())])
    # 3-point differences: 2-point ones stop short of the minimum by ~1e-4 mm on this problem
    sol = optimize.least_squares(fun, x0, method="trf", x_scale=scale, jac="3-point", ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=20000)
    pose, theta = params(sol.x)
    return meas - model.predict(theta, pose)[0]


def test_batched_solver_agrees_with_scipy_trial_by_trial(rng):
    model = MeasurementModel.for_plan("XFYZ", paper_plan(runs=1))
    theta = identifiable_truth(model, rng)
    clean = model.predict(theta, POSE)
    N = 3
    clean = np.broadcast_to(clean, (N,) + clean.shape[1:])
    # one draw of the tracker's spherical noise (range, azimuth, elevation), no machine repeatability
    r = np.linalg.norm(clean, axis=-1)
    sph = np.empty(clean.shape)
    sph[..., 0] = rng.standard_normal(r.shape) * (NOISE.distance + NOISE.distance_per_length * r)
    sph[..., 1:] = rng.standard_normal(r.shape + (2,)) * NOISE.angular
    noise = {"spherical_noise": sph}
    meas = model.predict(np.broadcast_to(theta, (N, model.n_params)), POSE, noise)
    res = identify(model, meas, NOISE)
    ident = res.identifiability
    # this plan's non-identifiable directions are single parameters (roll of Y and Z), so scipy can
    # solve the same problem by leaving exactly those parameters out
    assert all(len(c) == 1 for c in ident.combinations())
    free = np.array([n not in ident.unidentifiable_parameters() for n in model.errors.names])
    for n in range(N):
        pose0 = lt.register(model.machine_points(np.zeros(model.n_params)), meas[n:n + 1])[0]
        assert np.abs(res.residual[n] - scipy_identify(model, meas[n], NOISE, pose0, free)).max() < 1e-6


def test_two_tool_offsets_make_pitch_and_roll_observable():
    one = analyse(MeasurementModel.for_plan("XFYZ", paper_plan(tools=((0, 0, -150),))))
    two = analyse(MeasurementModel.for_plan("XFYZ", paper_plan()))
    lost_one = set(one.unidentifiable_parameters())
    lost_two = set(two.unidentifiable_parameters())
    # with one tool length, pitch and roll of Z act like a translation of Z: lost
    assert {"ex(z)[P1]", "ey(z)[P1]", "ex(z)[P2]", "ey(z)[P2]"} <= lost_one
    assert not any(n.startswith(("ex(", "ey(")) for n in lost_two)
    assert two.identifiable > one.identifiable
    # roll of Z and Y about the tool axis needs a lateral tool offset: still lost with offsets along z only
    assert {"ez(y)[P1]", "ez(z)[P1]"} <= lost_two
    three = analyse(MeasurementModel.for_plan("XFYZ", paper_plan(tools=((0, 0, -150), (0, 0, -300), (100, 0, -150)))))
    assert not any(n.startswith("ez(z)") for n in three.unidentifiable_parameters())


def test_multi_phase_reaches_the_same_minimum(null_recording):
    model = MeasurementModel.for_plan(null_recording.machine, null_recording.plan)
    a = identify(model, null_recording.lt, Noise.of(null_recording), Strategy.one_phase())
    b = identify(model, null_recording.lt, Noise.of(null_recording), Strategy.multi_phase())
    assert np.abs(a.residual - b.residual).max() < 1e-9


def test_eq27_before_and_after(null_recording):
    model = MeasurementModel.for_plan(null_recording.machine, null_recording.plan)
    res = identify(model, null_recording.lt, Noise.of(null_recording))
    assert res.mean_error_after[0] == pytest.approx(np.linalg.norm(res.residual[0], axis=1).mean())
    assert res.mean_error_after[0] < res.mean_error_before[0]


def test_tracker_far_from_any_guess_converges(rng):
    model = MeasurementModel.for_plan("XFYZ", paper_plan())
    theta = identifiable_truth(model, rng)
    pose = np.array([3000.0, -2500.0, 1800.0, 0.4, -0.6, 2.9])
    res = identify(model, model.predict(theta, pose)[0], NOISE)
    assert np.abs(res.residual).max() < 1e-9


def test_bad_input_gives_clear_errors(rng):
    model = MeasurementModel.for_plan("XFYZ", paper_plan())
    meas = model.predict(np.zeros(model.n_params), POSE)[0]
    bad = meas.copy()
    bad[17, 1] = np.nan
    with pytest.raises(IdentificationError, match=r"NaN.*\[17\]"):
        identify(model, bad, NOISE)
    # too few points for the requested degrees
    pts = mesh({"x": (800, 1200), "y": (100, 500), "z": (200, 400)}, 100)
    few = pts[np.random.default_rng(0).choice(75, 8, replace=False)]  # 24 coordinates for ~40 parameters
    small = build_plan(few, [[0, 0, -150]], runs=1)
    m2 = MeasurementModel.for_plan("XFYZ", small)
    with pytest.raises(IdentificationError, match="too few points: 8 points"):
        identify(m2, m2.predict(np.zeros(m2.n_params), POSE)[0], NOISE)
    # all points on one line
    line = build_plan(np.column_stack([np.linspace(800, 1200, 9), np.full(9, 300.0), np.full(9, 300.0)]), [[0, 0, 0]], runs=1)
    m3 = MeasurementModel.for_plan("XFYZ", line, max_degree=1)
    with pytest.raises(IdentificationError, match="line"):
        identify(m3, m3.predict(np.zeros(m3.n_params), POSE)[0], NOISE)
    # a degree the plan cannot support
    from mtbudget.machine import ErrorModel
    em = ErrorModel.default(model.plan.nominal)
    em = ErrorModel(ranges=em.ranges, degrees={**em.degrees, "dz(z)": 4})
    with pytest.raises(IdentificationError, match="dz\\(z\\).*3 distinct"):
        identify(MeasurementModel(model.config, em, model.plan), meas, NOISE)


def test_planar_mesh_identifies_with_lower_degrees():
    pts = mesh({"x": (800, 1200), "y": (100, 500), "z": (300, 300)}, 100)
    plan = build_plan(pts, [[0, 0, -150], [0, 0, -300]], runs=1)
    model = MeasurementModel.for_plan("XFYZ", plan)
    meas = model.predict(np.zeros(model.n_params), POSE)[0]
    res = identify(model, meas, NOISE)
    assert np.abs(res.residual).max() < 1e-9
    assert res.identifiability.null_space.shape[1] > 0


def test_iso230_convention_spans_the_free_model_space(rng):
    """Any machine of the recordings' (free) convention is represented exactly under ISO 230-1 straightness.

    Linear straightness trades against squareness and the tracker rotation, but a rotation also turns the
    tool offsets; the constant tilt terms of the tool-carrying axis make up for that.
    """
    plan = paper_plan()
    free = MeasurementModel.for_plan("XFYZ", plan, straightness_convention="free")
    iso = MeasurementModel.for_plan("XFYZ", plan)
    assert "dy(x)[P1]" in free.errors.names and "dy(x)[P1]" not in iso.errors.names
    assert "ex(z)[P0]" in iso.errors.names
    theta = np.array([rng.normal(0, 10e-3 if p.unit == "mm" else 20e-6) for p in free.errors.params])
    meas = free.predict(theta, POSE)[0]
    res = identify(iso, meas, NOISE)
    assert np.abs(res.residual).max() < 1e-6  # 1 nm: what remains are second-order differences of the chains


# --------------------------------------------------------------------------- what the result exposes
def test_result_exposes_whitener_design_and_basis_at_the_solution(null_recording):
    """The public fields against their definitions, recomputed independently (finite differences of the model)."""
    rec = null_recording
    model = MeasurementModel.for_plan(rec.machine, rec.plan)
    res = identify(model, rec.lt, Noise.of(rec))
    M, p = model.n_points, model.n_params
    # whitener: L^-1 of each point's covariance, so that Wh C Wh^T = I
    C = lt.covariance(rec.lt, rec.angular, rec.distance, rec.distance_per_length) + rec.repeatability**2 * np.eye(3)
    Wh = res.whitener[0]
    assert Wh.shape == (M, 3, 3)
    assert np.abs(Wh @ C @ np.swapaxes(Wh, 1, 2) - np.eye(3)).max() < 1e-9
    assert np.abs(np.einsum("mij,mj->mi", Wh, res.residual[0]) - res.whitened[0]).max() < 1e-12
    # basis: orthonormal, and orthogonal to the non-identifiable directions; scale: um per mm, urad per rad
    Q = res.basis
    r = Q.shape[1]
    assert Q.shape == (p, r) and r == res.identifiability.identifiable
    assert np.abs(Q.T @ Q - np.eye(r)).max() < 1e-10
    assert np.abs(Q.T @ res.identifiability.null_space).max() < 1e-10
    assert np.array_equal(res.scale, np.where(np.array(model.errors.units) == "mm", UM_PER_MM, URAD_PER_RAD))
    # design: d(whitened residual)/dz = -design, z = (pose in um / urad, Q^T theta in um / urad)
    A = res.design[0]
    assert A.shape == (3 * M, 6 + r)

    def whitened(z):
        pose = res.pose[0] + z[:6] / POSE_SCALE_BY_HAND
        theta = res.theta[0] + (Q @ z[6:]) / res.scale
        return np.einsum("mij,mj->mi", Wh, rec.lt - model.predict(theta, pose)[0]).ravel()

    h = 0.1  # um / urad: round-off (~1e-11 of coordinates in the thousands) stays far below the test; central
    #          differences leave third-order terms only
    for k in range(6 + r):
        e = np.zeros(6 + r)
        e[k] = h
        fd = -(whitened(e) - whitened(-e)) / (2 * h)
        assert np.abs(fd - A[:, k]).max() < 1e-6 * np.abs(A[:, k]).max(), k
    # the covariances are the inverse normal matrix mapped back to mm and rad
    T = np.zeros((6 + p, 6 + r))
    T[:6, :6] = np.diag(1 / POSE_SCALE_BY_HAND)
    T[6:, 6:] = Q / res.scale[:, None]
    cov = T @ np.linalg.inv(A.T @ A) @ T.T
    assert np.allclose(res.cov_theta[0], cov[6:, 6:], rtol=1e-8, atol=1e-30)
    assert np.allclose(res.cov_pose[0], cov[:6, :6], rtol=1e-8, atol=1e-30)


def test_trials_that_did_not_converge_are_counted(rng):
    model = MeasurementModel.for_plan("XFYZ", paper_plan(runs=1))
    theta = identifiable_truth(model, rng)
    meas = model.predict(theta, POSE)[0]
    far = np.stack([meas, model.predict(theta, np.array([3000.0, -2500.0, 1800.0, 0.4, -0.6, 2.9]))[0]])
    done = identify(model, far, NOISE)
    assert done.n_trials == 2 and done.n_not_converged == 0
    # one Gauss-Newton step from the registration is not enough to call a trial converged
    one = identify(model, far, NOISE, Strategy(max_iter=1, solver="gauss-newton"))
    assert one.n_not_converged == int((~one.converged).sum()) >= 1
    # the chord solver hands what it cannot finish to Gauss-Newton: counted as fallbacks, and with the
    # same iteration limit not converged either
    chord = identify(model, far, NOISE, Strategy(max_iter=1, chord_iter=1))
    assert chord.n_fallback == 2 and chord.n_not_converged == int((~chord.converged).sum()) >= 1
