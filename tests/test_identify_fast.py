"""The chord solver (the fast path) against the Gauss-Newton reference and scipy, trial by trial.

Trials are simulated here, independently of the engine: a machine drawn from the paper's generation
functions under the *free* straightness convention (the identification uses ISO 230-1), a tracker pose
perturbed per trial, the tracker's spherical noise and the machine's repeatability.  Every trial must
agree with Gauss-Newton (per-trial weights, fresh Jacobians) to 1e-6 mm in the tracker points and in the
identified (compensated) field; a sample agrees with scipy.optimize.least_squares.
"""

import gc

import numpy as np
import pytest
from scipy import optimize

from mtbudget import identify as identify_module
from mtbudget import tracker as lt
from mtbudget.config import load_config
from mtbudget.errors import IdentificationError
from mtbudget.identify import Noise, Strategy, identify, scale_vector
from mtbudget.model import MeasurementModel
from mtbudget.plan import build_plan, mesh

# the paper's tracker (mtbudget/data/paper_xfyz.toml, [tracker]) and its stated uncertainties, written out
# by hand: the tests check the solver, not the configuration reader
POSE = np.array([-563.52, 194.37, 677.78, np.radians(0.0339), np.radians(0.0343), np.radians(59.4652)])
NOISE = Noise(angular=20e-6, distance=4e-3, distance_per_length=0.8e-6, repeatability=1.5e-3)
TOL_MM = 1e-6


def paper_plan():
    plan = load_config().plan()  # the built-in default: the paper's 75 points, one tool at z -150 mm
    assert len(plan) == 75 and np.allclose(np.unique(plan.tool, axis=0), [[0, 0, -150]])
    return plan


def two_tools_three_passes():
    pts = mesh({"x": (800, 1200), "y": (100, 500), "z": (200, 400)}, 100)
    return build_plan(pts, [[0, 0, -150], [0, 0, -300]], runs=3)


def simulate(plan, N, rng, scale=1.0):
    """N simulated verifications of one machine: (identification model, measured points (N, M, 3))."""
    truth = MeasurementModel.for_plan("XFYZ", plan, straightness_convention="free")
    std = {"mm": [8e-3, 3e-3, 1.5e-3], "rad": [10e-6, 5e-6, 2.5e-6]}  # the paper's generation functions
    theta = np.array([rng.normal(0, 30e-6) if p.is_squareness else rng.normal(0, std[p.unit][min(p.order, 3) - 1])
                      for p in truth.errors.params]) * scale
    pose = POSE + rng.normal(0, 1, (N, 6)) * [0.2, 0.2, 0.2, 20e-6, 20e-6, 20e-6]  # the tracker set up anew
    clean = truth.predict(np.broadcast_to(theta, (N, truth.n_params)), pose)
    r = np.linalg.norm(clean, axis=-1)
    sph = np.empty(clean.shape)
    sph[..., 0] = rng.standard_normal(r.shape) * (NOISE.distance + NOISE.distance_per_length * r)
    sph[..., 1:] = rng.standard_normal(r.shape + (2,)) * NOISE.angular
    pert = {"spherical_noise": sph}
    for a in "xyz":
        pert[f"axis_offset.{a}"] = rng.standard_normal(r.shape) * NOISE.repeatability
    meas = truth.predict(np.broadcast_to(theta, (N, truth.n_params)), pose, pert)
    return MeasurementModel.for_plan("XFYZ", plan), meas


def assert_same_solution(model, a, b, tol=TOL_MM):
    """Trial by trial: the same tracker points and the same identified field (mm)."""
    dp = np.abs(model.predict(a.theta, a.pose) - model.predict(b.theta, b.pose)).max(axis=(1, 2))
    df = np.abs(model.machine_points(a.theta) - model.machine_points(b.theta)).max(axis=(1, 2))
    assert dp.max() < tol, (dp.max(), np.argmax(dp))
    assert df.max() < tol, (df.max(), np.argmax(df))
    return dp.max(), df.max()


def scipy_residual(model, meas, Q):
    """One trial with scipy over the same identifiable directions theta = Q x / scale, same weights."""
    sv = scale_vector(model)
    C = model.covariance(meas[None], NOISE.angular, NOISE.distance, NOISE.distance_per_length, NOISE.repeatability)[0]
    Wh = np.linalg.inv(np.linalg.cholesky(C))

    def fun(x):
        r = meas - model.predict((Q @ x[6:]) / sv, x[:6])[0]
        return np.einsum("mij,mj->mi", Wh, r).ravel()

    pose0 = lt.register(model.machine_points(np.zeros(model.n_params)), meas[None])[0]
    x0 = np.concatenate([pose0, np.zeros(Q.shape[1])])
    # 3-point differences with a relative step of 1e-3: with the default step scipy stops ~1e-6 mm short of the
    # minimum (its cost is higher than the solvers'), its finite differences drowned in round-off
    sol = optimize.least_squares(fun, x0, method="trf", x_scale="jac", jac="3-point", diff_step=1e-3, ftol=1e-15,
                                 xtol=1e-15, gtol=1e-15, max_nfev=20000)
    return meas - model.predict((Q @ sol.x[6:]) / sv, sol.x[:6])[0]


@pytest.mark.parametrize("plan_of, N, sample", [(paper_plan, 64, (0, 63)), (two_tools_three_passes, 8, (5,))],
                         ids=["paper", "2tools-3passes"])
def test_chord_agrees_with_gauss_newton_and_scipy_on_every_trial(plan_of, N, sample, rng):
    model, meas = simulate(plan_of(), N, rng)
    ref = identify(model, meas, NOISE, Strategy(solver="gauss-newton"))
    fast = identify(model, meas, NOISE)
    assert fast.solver == "chord" and ref.solver == "gauss-newton" and ref.n_fallback == 0
    assert fast.converged.all() and ref.converged.all()
    assert fast.n_fallback == int(fast.fallback.sum()) == 0  # these trials are in the linear range
    assert_same_solution(model, fast, ref)
    # Eq. 27 before compensation: the same weighted pose-only registration
    assert np.abs(fast.initial_error - ref.initial_error).max() < TOL_MM
    # everything the result holds is consistent with its own solution, exactly
    assert np.abs(fast.residual - (meas - model.predict(fast.theta, fast.pose))).max() < 1e-12
    Rm = lt.rotation(fast.pose[:, 3], fast.pose[:, 4], fast.pose[:, 5])
    assert np.abs(fast.residual_machine - np.einsum("nij,nmj->nmi", Rm, fast.residual)).max() < 1e-12
    assert np.abs(fast.whitened - np.einsum("nmij,nmj->nmi", fast.whitener, fast.residual)).max() < 1e-12
    assert np.allclose(fast.chi2, (fast.whitened**2).sum(axis=(1, 2)), rtol=1e-12)
    assert np.allclose(fast.chi2, ref.chi2, rtol=1e-6) and fast.dof == ref.dof
    assert np.abs(fast.whitener - ref.whitener).max() < 1e-12 * np.abs(ref.whitener).max()
    # design and covariances at the solution: the same as the reference's (computed from the exact Jacobian)
    assert np.allclose(fast.design, ref.design, rtol=1e-6, atol=1e-9 * np.abs(ref.design).max())
    for key in ("cov_theta", "cov_pose"):
        a, b = getattr(fast, key), getattr(ref, key)
        assert np.abs(a - b).max() < 1e-6 * np.abs(b).max(), key
    # an independent solver on a sample
    Q = fast.basis
    for n in sample:
        assert np.abs(scipy_residual(model, meas[n], Q) - fast.residual[n]).max() < TOL_MM


def test_a_shared_iteration_matrix_reaches_the_same_minimum(rng):
    """iteration_pose (what the engine passes): one iteration matrix from the nominal points seen from the nominal
    pose, for every trial; the solution is Gauss-Newton's and does not depend on that matrix: a pose 0.05 rad and
    10 mm off reaches it in a few more iterations; 0.3 rad off, the chord contracts too slowly and every trial is
    handed to Gauss-Newton, counted."""
    model, meas = simulate(paper_plan(), 32, rng)
    ref = identify(model, meas, NOISE, Strategy(solver="gauss-newton"))
    labels = np.repeat(np.arange(4), 8)
    for off, fallbacks in ((0.0, 0), (0.05, 0), (0.3, 32)):
        pose = POSE + np.array([200, -100, 50, 1, -1, 1]) * off
        shared = identify(model, meas, NOISE, iteration_pose=pose, groups=labels)
        assert shared.n_fallback == fallbacks
        assert_same_solution(model, shared, ref)
    multi = identify(model, meas, NOISE, Strategy.multi_phase(), iteration_pose=POSE)
    assert_same_solution(model, multi, identify(model, meas, NOISE, Strategy.multi_phase(solver="gauss-newton")))


def test_multi_phase_and_given_starts_reach_the_same_minimum(rng):
    model, meas = simulate(paper_plan(), 16, rng)
    ref = identify(model, meas, NOISE, Strategy.multi_phase(solver="gauss-newton"))
    assert_same_solution(model, identify(model, meas, NOISE, Strategy.multi_phase()), ref)
    # a given start (the reference's own solution moved a little) converges to the same minimum
    start = identify(model, meas, NOISE, Strategy(solver="gauss-newton"))
    moved = identify(model, meas, NOISE, theta0=start.theta * 1.01, pose0=start.pose + [0.05, 0, 0, 0, 0, 1e-5])
    assert moved.n_fallback == 0
    assert_same_solution(model, moved, ref)


def test_fixed_perturbations_as_diagnosis_asserts_them(rng):
    """A thermal scale and a tracker-frame offset taken as known: both solvers see the same model."""
    model, meas = simulate(paper_plan(), 8, rng)
    M = model.n_points
    fixed = {"axis_scale.x": np.full((1, M), 12e-6), "point_offset": rng.normal(0, 2e-3, (8, M, 3)),
             "tracker_offset": np.full((1, M, 3), 1e-3)}
    ref = identify(model, meas, NOISE, Strategy(solver="gauss-newton"), fixed=fixed)
    fast = identify(model, meas, NOISE, fixed=fixed)
    assert fast.n_fallback == 0
    dp = np.abs(ref.residual - fast.residual).max()
    assert dp < TOL_MM
    df = np.abs(model.machine_points(ref.theta) - model.machine_points(fast.theta)).max()
    assert df < TOL_MM


def test_one_recording_as_diagnosis_identifies_it(null_recording):
    rec = null_recording
    model = MeasurementModel.for_plan(rec.machine, rec.plan)
    ref = identify(model, rec.lt, Noise.of(rec), Strategy(solver="gauss-newton"))
    fast = identify(model, rec.lt, Noise.of(rec))
    assert fast.n_fallback == 0
    assert_same_solution(model, fast, ref)
    assert np.allclose(fast.design, ref.design, rtol=1e-6, atol=1e-9 * np.abs(ref.design).max())


def test_a_trial_outside_the_linear_range_falls_back_and_is_counted(rng):
    model, meas = simulate(paper_plan(), 6, rng)
    # trial 2: a machine 300 times the paper's (errors of millimetres and milliradians)
    _, big = simulate(paper_plan(), 1, np.random.default_rng(7), scale=300.0)
    meas[2] = big[0]
    ref = identify(model, meas, NOISE, Strategy(solver="gauss-newton"))
    fast = identify(model, meas, NOISE)
    assert fast.fallback.tolist() == [False, False, True, False, False, False]
    assert fast.n_fallback == 1 and fast.converged.all()
    assert_same_solution(model, fast, ref)  # the fallback is the reference itself
    # a trial the chord cannot finish in its iteration limit falls back too, and is counted
    few = identify(model, meas, NOISE, Strategy(chord_iter=1))
    assert few.n_fallback == 6 and few.converged.all()
    assert_same_solution(model, few, ref)


def test_bias_guard_sends_what_it_cannot_vouch_for_to_gauss_newton(rng):
    """With the guard at 0, every trial goes to Gauss-Newton; the default keeps the paper's trials on the chord."""
    model, meas = simulate(paper_plan(), 4, rng)
    strict = identify(model, meas, NOISE, Strategy(chord_bias=0.0))
    assert strict.n_fallback == 4
    assert identify(model, meas, NOISE).n_fallback == 0


def test_solver_is_validated(rng):
    model, meas = simulate(paper_plan(), 1, rng)
    with pytest.raises(IdentificationError, match="unknown solver 'newton'"):
        identify(model, meas, NOISE, Strategy(solver="newton"))


def test_identifiability_is_computed_once_per_model_and_mask(rng, monkeypatch):
    calls = []
    real = identify_module.analyse
    monkeypatch.setattr(identify_module, "analyse", lambda *a, **k: calls.append(1) or real(*a, **k))
    model, meas = simulate(paper_plan(), 2, rng)
    first = identify(model, meas, NOISE)
    identify(model, meas, NOISE)
    identify(model, meas[:1], NOISE, Strategy(solver="gauss-newton"))
    assert len(calls) == 1
    identify(model, meas, NOISE, Strategy.multi_phase())  # two more masks: pose alone, pose + translational
    assert len(calls) == 3
    # the cached results cannot be changed through a result
    with pytest.raises(ValueError):
        first.basis[0, 0] = 1.0
    # a model changed in place is analysed again; a model that is gone leaves the cache
    model.plan.tool[:] = model.plan.tool + [0.0, 0.0, -10.0]
    identify(model, model.predict(np.zeros(model.n_params), POSE), NOISE)
    assert len(calls) == 4
    key = id(model)
    assert key in identify_module._PLAN_CACHE
    del model, first
    gc.collect()
    assert key not in identify_module._PLAN_CACHE


def test_multi_phase_reports_its_parameters_on_the_one_phase_datum(rng):
    """The earlier phases of a multi-phase identification move the parameters along directions the last phase
    cannot see (on the paper's plan up to 3 urad in ex(z)/ey(z) and dx(z)/dy(z) of degree 2); the result is put on
    the last phase's datum with the rigid motion those directions carry moved to the tracker pose: the same
    parameters as the one-phase identification (minimum norm), the same residuals and chi2, by both solvers."""
    model, meas = simulate(paper_plan(), 12, rng)
    sv = scale_vector(model)
    one = identify(model, meas, NOISE, Strategy.one_phase(solver="gauss-newton"))
    N = one.identifiability.null_space
    assert N.shape[1] > 0
    for solver in ("chord", "gauss-newton"):
        multi = identify(model, meas, NOISE, Strategy.multi_phase(solver=solver), iteration_pose=POSE)
        assert not multi.n_fallback
        assert np.abs((multi.theta * sv) @ N).max() < 1e-9  # nothing left in the null space
        assert np.abs((multi.theta - one.theta) * sv).max() < 1e-3  # um, urad: the one-phase parameters
        assert np.abs(multi.residual - one.residual).max() < 1e-7  # mm
        assert np.abs(multi.chi2 / one.chi2 - 1).max() < 1e-8


def test_multi_phase_on_a_five_axis_datum_holds_its_parameters_at_zero():
    """A machine with rotary axes: the datum rule's held parameters are zero after several phases too (its phases
    never move them; the datum move must keep them there: a wrong solve for the held set would not)."""
    from mtbudget.config import bundled_config
    from mtbudget.engine import Engine
    from mtbudget.scenario import build_scenario

    sc = build_scenario(load_config(bundled_config("five_axis_cafxyz")))
    meas = Engine(sc, block=6).simulate(0)[0]
    one = identify(sc.id_model, meas, sc.noise, Strategy.one_phase(), iteration_pose=sc.pose)
    held = one.identifiability.held
    assert held
    multi = identify(sc.id_model, meas, sc.noise, Strategy.multi_phase(), iteration_pose=sc.pose)
    assert np.abs(multi.theta[:, held]).max() < 1e-15
    sv = scale_vector(sc.id_model)
    assert np.abs((multi.theta - one.theta) * sv).max() < 1e-2
    assert np.abs(multi.chi2 / one.chi2 - 1).max() < 1e-8
