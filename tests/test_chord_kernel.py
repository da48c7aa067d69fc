"""The chord solver compiled (``kernels.chord_stage``, ``point_weights``, ``chord_final``) against its numpy
formulation (``identify._chord``, ``_weights``, ``_gram33``), a second implementation of the same iteration
written separately: every trial to round-off, whatever the trials are identified with.

test_identify_fast.py compares the compiled path with Gauss-Newton and scipy (independent solvers); here the
two formulations of the *same* iteration must agree far more closely (1e-9 mm, the same iteration counts and the
same fallbacks), and a trial's numbers must not depend on the trials identified with it, bit for bit.
"""

import numpy as np
import pytest

from mtbudget import identify as identify_module
from mtbudget.config import bundled_config, load_config
from mtbudget.engine import Engine
from mtbudget.identify import Strategy, identify
from mtbudget.scenario import build_scenario
from test_identify_fast import NOISE, POSE, paper_plan, simulate

TOL = 1e-9  # mm: round-off of two orders of summation, far below the solvers' own tolerance (1e-7 um)


def both(monkeypatch, *args, **kw):
    """identify() compiled and with the numpy formulation."""
    out = []
    for compiled in (True, False):
        monkeypatch.setattr(identify_module, "CHORD_KERNEL", compiled)
        out.append(identify(*args, **kw))
    return out


def assert_agree(model, a, b):
    assert a.n_fallback == b.n_fallback and a.iterations == b.iterations
    assert np.abs(model.predict(a.theta, a.pose) - model.predict(b.theta, b.pose)).max() < TOL
    assert np.abs(model.machine_points(a.theta) - model.machine_points(b.theta)).max() < TOL
    for key in ("residual", "residual_machine", "initial_error"):
        assert np.abs(getattr(a, key) - getattr(b, key)).max() < TOL, key
    assert np.abs(a.chi2 / b.chi2 - 1).max() < 1e-9
    np.testing.assert_allclose(a.whitener, b.whitener, rtol=1e-12, atol=0)


@pytest.mark.parametrize("phases", [Strategy.one_phase, Strategy.multi_phase])
def test_compiled_chord_equals_the_numpy_chord(monkeypatch, rng, phases):
    model, meas = simulate(paper_plan(), 24, rng)
    a, b = both(monkeypatch, model, meas, NOISE, phases())
    assert a.n_fallback == 0
    assert_agree(model, a, b)



def test_a_fixed_axis_input_per_trial_is_each_trial_s_own(monkeypatch, rng):
    """A known axis offset and scale given per trial ((N, M) arrays, as ``identify`` documents "broadcastable over
    trials"): identified together, each trial gets what it gets identified alone with its own (1, M) inputs (a
    reviewer found the nominal points built for one row only: a bare numpy error), compiled and numpy alike."""
    model, meas = simulate(paper_plan(), 4, rng)
    M = model.n_points
    fixed = {"axis_offset.x": rng.normal(0, 5e-3, (4, M)), "axis_scale.y": rng.normal(0, 2e-5, (4, M))}
    a, b = both(monkeypatch, model, meas, NOISE, Strategy(), fixed=fixed)
    assert a.n_fallback == 0 and a.converged.all()
    assert np.abs(a.theta - b.theta).max() < TOL
    for i in range(4):
        alone = identify(model, meas[i:i + 1], NOISE, Strategy(), fixed={k: v[i:i + 1] for k, v in fixed.items()})
        assert np.abs(alone.theta[0] - a.theta[i]).max() < TOL
        assert np.abs(alone.residual[0] - a.residual[i]).max() < TOL
        assert np.abs(alone.initial_error[0] - a.initial_error[i]).max() < TOL

def test_labels_with_their_own_iteration_matrices(monkeypatch, rng):
    """Without a shared iteration pose each label (block) iterates with its own mean information."""
    model, meas = simulate(paper_plan(), 24, rng)
    a, b = both(monkeypatch, model, meas, NOISE, Strategy(), chunk=24, groups=np.repeat([0, 1, 2], 8))
    assert_agree(model, a, b)


def test_fixed_perturbations_per_trial_and_shared(monkeypatch, rng):
    """Known inputs (a scale, per-trial point offsets, a geometry offset): stage 2 with each trial's formed
    Jacobian (the compiled path's mode 2) and the points moved as machine_points moves them."""
    model, meas = simulate(paper_plan(), 8, rng)
    M, p = model.n_points, model.n_params
    fixed = {"axis_scale.x": np.full((1, M), 12e-6), "point_offset": rng.normal(0, 2e-3, (8, M, 3)),
             "geometry": rng.normal(0, 1e-4, (8, p)) * (np.array(model.errors.units) == "mm")}
    a, b = both(monkeypatch, model, meas, NOISE, Strategy(), fixed=fixed)
    assert a.n_fallback == 0
    for key in ("residual", "residual_machine", "initial_error"):
        assert np.abs(getattr(a, key) - getattr(b, key)).max() < TOL, key
    assert np.abs(a.theta - b.theta).max() < TOL


def test_a_block_does_not_depend_on_the_blocks_identified_with_it(rng):
    """The engine's promise (one label per block, the shared nominal iteration matrix): a block identified alone
    or among others, in any order, gets the same bits."""
    model, meas = simulate(paper_plan(), 12, rng)
    labels = np.repeat([0, 1, 2], 4)
    kw = {"iteration_pose": POSE, "chunk": 12}
    whole = identify(model, meas, NOISE, Strategy.multi_phase(), groups=labels, **kw)
    order = np.r_[8:12, 0:4, 4:8]
    moved = identify(model, meas[order], NOISE, Strategy.multi_phase(), groups=labels, **kw)
    alone = identify(model, meas[4:8], NOISE, Strategy.multi_phase(), groups=np.zeros(4, int), **kw)
    for key in ("theta", "pose", "chi2", "residual", "initial_error"):
        np.testing.assert_array_equal(getattr(moved, key), getattr(whole, key)[order], key)
        np.testing.assert_array_equal(getattr(alone, key), getattr(whole, key)[4:8], key)


def test_five_axis_engine_trials(monkeypatch):
    """A CAFXYZ machine's trials (rotary axes in the chain: the compiled stage's J^T v through them)."""
    sc = build_scenario(load_config(bundled_config("five_axis_cafxyz")))
    meas = Engine(sc, block=8).simulate(0)[0]
    a, b = both(monkeypatch, sc.id_model, meas, sc.noise, Strategy(), iteration_pose=sc.pose)
    assert a.n_fallback == 0
    assert_agree(sc.id_model, a, b)


def test_the_engine_blocks_with_the_numpy_chord(monkeypatch):
    """The engine's numbers with either formulation: the paper default's per-point errors to 1e-9 um."""
    sc = build_scenario(load_config())
    out = []
    for compiled in (True, False):
        monkeypatch.setattr(identify_module, "CHORD_KERNEL", compiled)
        out.append(Engine(sc, block=16).run_blocks([0, 1]))
    for x, y in zip(*out):
        assert np.abs(x.components - y.components).max() < 1e-6  # um
        assert np.abs(x.parameters - y.parameters).max() < 1e-6  # um, urad
        for k, v in x.scalars.items():
            assert np.abs(v - y.scalars[k]).max() < 1e-6 * max(1.0, np.abs(v).max()), k


def test_a_tracker_far_from_the_nominal_pose_is_registered_first(rng):
    """The engine's identification starts the pose-only fit at the nominal pose (no Kabsch registration); a trial
    whose tracker stands elsewhere (here turned 0.5 rad about the machine's z) does not converge from there and is
    registered and fitted again: its Eq. 27 'before' errors and its solution are Gauss-Newton's (which always
    registers first), and nothing is lost."""
    from mtbudget import tracker as lt

    model, meas = simulate(paper_plan(), 8, rng)
    moved = POSE + [0, 0, 0, 0, 0, 0.5]
    P_W = lt.to_machine(meas[4:], np.broadcast_to(POSE, (4, 6)))  # the same readings, from a tracker turned
    meas = np.concatenate([meas[:4], lt.to_tracker(P_W, np.broadcast_to(moved, (4, 6)))])
    fast = identify(model, meas, NOISE, Strategy(), iteration_pose=POSE, groups=np.repeat([0, 1], 4))
    ref = identify(model, meas, NOISE, Strategy(solver="gauss-newton"))
    assert fast.n_fallback == 0  # registered and fitted again by the chord, not handed to Gauss-Newton
    assert np.abs(fast.initial_error - ref.initial_error).max() < 1e-6
    assert np.abs(fast.residual - ref.residual).max() < 1e-6
    assert np.abs(model.machine_points(fast.theta) - model.machine_points(ref.theta)).max() < 1e-6
    assert np.abs(fast.pose[4:, 5] - fast.pose[:4, 5] - 0.5).max() < 1e-3  # the turned trials found turned


def test_the_points_at_the_solution_are_the_chain_at_theta(rng):
    """Identification.points (what the engine takes for the compensated field instead of evaluating the chain
    again) is model.machine_points(theta) exactly, also for trials handed to Gauss-Newton; None where fixed
    perturbations move the points or with the Gauss-Newton solver."""
    model, meas = simulate(paper_plan(), 8, rng, scale=300.0)  # errors of millimetres: some trials fall back
    res = identify(model, meas, NOISE, Strategy(), iteration_pose=POSE)
    assert res.n_fallback > 0 and res.points is not None
    np.testing.assert_array_equal(res.points, model.machine_points(res.theta))
    assert identify(model, meas[:2], NOISE, Strategy(solver="gauss-newton")).points is None
    fixed = {"point_offset": np.full((1, model.n_points, 3), 1e-3)}
    assert identify(model, meas[:2], NOISE, Strategy(), fixed=fixed).points is None


def test_the_points_at_the_solution_are_machine_points_bit_for_bit(rng):
    """identify._chain_at (the chord's points at its solution, from the stages' chain inputs) gives
    model.machine_points(theta, fixed) exactly: without fixed inputs, and with a scale, a geometry offset and point
    offsets given per trial or shared."""
    model, _ = simulate(paper_plan(), 1, rng)
    M, p, N = model.n_points, model.n_params, 6
    theta = rng.normal(0, 1e-3, (N, p)) * np.where(np.array(model.errors.units) == "mm", 1.0, 1e-3)
    for fixed in ({}, {"axis_scale.x": np.full((1, M), 12e-6), "point_offset": rng.normal(0, 2e-3, (N, M, 3)),
                       "geometry": rng.normal(0, 1e-4, (N, p)) * (np.array(model.errors.units) == "mm")},
                  {"axis_offset.y": rng.normal(0, 1e-3, (N, M)), "point_offset": np.full((1, M, 3), 1e-3)}):
        got = identify_module._chain_at(identify_module._chord_chain(model, fixed, N), theta, fixed)
        np.testing.assert_array_equal(got, model.machine_points(theta, fixed))


def test_the_kept_chain_inputs_are_not_changed_by_identifying(rng):
    """The chain inputs of an unperturbed chunk are kept per model (the plan cache) and shared by every later call,
    whatever its number of trials: identifying must leave them as a fresh build makes them, and a chunk identified
    after others gets the numbers it gets first."""
    model, meas = simulate(paper_plan(), 6, rng)
    first = identify(model, meas[:2], NOISE, Strategy.multi_phase(), iteration_pose=POSE)
    identify(model, meas, NOISE, Strategy(), iteration_pose=POSE)
    kept = identify_module._plan_cache(model)["chord_chain"]
    fresh = identify_module._chord_chain(model, {}, 6)
    for key, value in fresh.items():
        np.testing.assert_array_equal(kept[key], value, err_msg=key)
    again = identify(model, meas[:2], NOISE, Strategy.multi_phase(), iteration_pose=POSE)
    for key in ("theta", "pose", "residual", "chi2"):
        np.testing.assert_array_equal(getattr(again, key), getattr(first, key), err_msg=key)
