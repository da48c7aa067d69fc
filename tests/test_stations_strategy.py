"""The optimisation strategy acts on the identification over several stations ([[stations]], two or more): its
phases (the stations' unknowns, then the translational errors with them, then all) and its convergence criteria
(xtol, max_iter) with the one-tracker meaning (multistation.strategy_settings).

Independent references: scipy.optimize.least_squares on weighted residuals written here (scipy's rotation for Eq. 22,
the whitener a Cholesky factor's inverse, the datum the complement of the held directions built by scipy), and a
plain Gauss-Newton loop on the same residuals, differenced by scipy's own finite differences, for a given number of
steps.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import linalg, optimize
from scipy.spatial.transform import Rotation

from mtbudget import tracker as lt
from mtbudget.config import bundled_config, load_config
from mtbudget.engine import Engine, _station_basis
from mtbudget.identify import Strategy, scale_vector
from mtbudget.scenario import build_scenario

FOUR = bundled_config("four_stations")


@pytest.fixture(scope="module")
def four():
    """The bundled four stations (two trackers, two interferometers): the scenario, 3 simulated trials, the
    identification model and what one tracker cannot identify (held at zero by every solver)."""
    sc = build_scenario(load_config(FOUR))
    sim = Engine(sc, block=3, seed=23).simulate(0)
    model = sc.id_model
    return sc, sim, model, sc.unidentifiable(model)


def weighted_residuals(sc, model, hold, xyz, ranges):
    """(fun, u0, unpack): the weighted residuals of one trial as a function of u = (the geometric parameters in the
    complement of ``hold``, scaled; then every station's unknowns: T (mm) and a, b, d (rad) of a tracker, S (mm) and
    dead path (mm) of an interferometer), written here from the stated noise; u0 the closed-form start (theta = 0,
    Kabsch, multilateration); unpack(u) -> (theta (p,), station unknowns)."""
    from mtbudget.multistation import multilaterate

    p = model.n_params
    sv = scale_vector(model)
    N = linalg.null_space(hold.T) if hold.size else np.eye(p)  # the geometric directions the solvers move along
    P0 = model.machine_points(np.zeros((1, p)))[0]
    rep = sc.noise.repeatability
    parts, u0 = [], [np.zeros(N.shape[1])]
    for st in sc.stations:
        idx = np.flatnonzero(sc.row_station == st.id)
        if st.kind == "xyz":
            C = lt.covariance(xyz[idx], st.angular, st.distance, st.distance_per_length) + rep**2 * np.eye(3)
            W = np.linalg.inv(np.linalg.cholesky(C))  # W^T W = C^-1
            parts.append(("xyz", idx, W))
            u0.append(lt.register(P0[idx], xyz[idx][None])[0])
        else:
            S, o = multilaterate(P0[idx], ranges[idx])
            sigma = np.sqrt((st.distance + st.distance_per_length * np.linalg.norm(P0[idx] - S, axis=1))**2 + rep**2)
            parts.append(("range", idx, 1.0 / sigma))
            u0.append(np.concatenate([S, [o]]))
    u0 = np.concatenate(u0)

    def unpack(u):
        return (N @ u[:N.shape[1]]) / sv, u[N.shape[1]:]

    def fun(u):
        theta, st_u = unpack(u)
        P = model.machine_points(theta[None])[0]
        out, k = [], 0
        for kind, idx, W in parts:
            if kind == "xyz":
                T, ang = st_u[k:k + 3], st_u[k + 3:k + 6]
                R = Rotation.from_euler("XYZ", ang).as_matrix()  # Rx(a) Ry(b) Rz(d), Eq. 22
                e = xyz[idx] - (P[idx] - T) @ R
                out.append(np.einsum("mij,mj->mi", W, e).ravel())
                k += 6
            else:
                S, o = st_u[k:k + 3], st_u[k + 3]
                out.append(W * (ranges[idx] - np.linalg.norm(P[idx] - S, axis=1) - o))
                k += 4
        return np.concatenate(out)

    return fun, u0, unpack


def x_scale(model, hold, sc):
    """Each of u's unknowns' size of a step of 1 um or 1 urad (scipy's x_scale)."""
    N = model.n_params - hold.shape[1]
    return np.concatenate([np.ones(N)] + [np.r_[1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6] if st.kind == "xyz"
                                          else np.full(4, 1e-3) for st in sc.stations])


def jacobian(fun, model, hold, sc):
    """scipy's central differences with a step of 0.01 um or urad in every unknown: a relative step (scipy's default)
    is 1e-5 um on a parameter of 10 um, whose change of the residuals drowns in their round-off (a point 1000 mm
    away measured to 5 um: 2e-11 whitened), which left scipy 1e-4 um short of the minimum in the field."""
    from scipy.optimize._numdiff import approx_derivative

    h = 1e-2 * x_scale(model, hold, sc)
    return lambda u: approx_derivative(fun, u, method="3-point", abs_step=h)


def field_um(sc, model, a, b):
    """The largest difference of two identified parameter sets' compensated fields at the mesh (rigid motions
    removed), um."""
    F = sc.evaluate(model, np.stack([a, b]))
    return float(np.abs(sc.rigid_free @ (F[0] - F[1]).ravel()).max() * 1e3)


def test_multi_phase_and_one_phase_reach_the_minimum_scipy_finds(four):
    """Four stations: the engine's batched chord and the Gauss-Newton reference, one phase and multi-phase (the
    stations' unknowns, then with the translational errors, then all), all reach the minimum scipy's least_squares
    finds on the weighted residuals written here: the compensated field within 1e-5 um and chi2 (evaluated by the
    function written here) within 1e-10 relative (measured: 3-6e-6 um, 1e-11); one phase and multi-phase within 1e-7
    um of each other (the minimum is the minimum, whichever way it is approached).  The multi-phase runs iterated
    more (their earlier phases)."""
    from mtbudget.multistation import identify_stations, identify_stations_batch, phase_masks

    sc, sim, model, hold = four
    p = model.n_params
    multi = phase_masks(model, Strategy.multi_phase().phases)
    assert len(multi) == 3 and not multi[0].any() and multi[2].all() and 0 < multi[1].sum() < p
    assert phase_masks(model, Strategy.one_phase().phases) is None
    basis = _station_basis(sc, model, None, hold)
    args = (model, sc.stations, sc.row_station, sim[0], sim.ranges, sc.noise.repeatability)
    one_b = identify_stations_batch(*args, hold=hold, basis=basis)
    multi_b = identify_stations_batch(*args, hold=hold, basis=basis, phases=multi)
    assert one_b["converged"].all() and multi_b["converged"].all() and not multi_b["failed"].any()
    assert (multi_b["iterations"] > one_b["iterations"]).all()  # the earlier phases' steps
    for i in (0, 2):
        ref_args = (model, sc.stations, sc.row_station, sim[0][i], sim.ranges[i], sc.noise.repeatability)
        one_r = identify_stations(*ref_args, hold=hold)
        multi_r = identify_stations(*ref_args, hold=hold, phases=multi)
        assert one_r.converged and multi_r.converged and multi_r.iterations > one_r.iterations
        fun, u0, unpack = weighted_residuals(sc, model, hold, sim[0][i], sim.ranges[i])
        sol = optimize.least_squares(fun, u0, method="trf", x_scale=x_scale(model, hold, sc),
                                     jac=jacobian(fun, model, hold, sc), ftol=1e-15, xtol=1e-15, gtol=1e-15,
                                     max_nfev=200)
        assert sol.status > 0
        theta_s = unpack(sol.x)[0]
        chi2_s = float(sol.fun @ sol.fun)
        N, sv = linalg.null_space(hold.T), scale_vector(model)
        for name, x in (("batch, one phase", one_b["x"][i]), ("batch, multi-phase", multi_b["x"][i]),
                        ("reference, one phase", one_r.x), ("reference, multi-phase", multi_r.x)):
            assert field_um(sc, model, x[:p], theta_s) < 1e-5, (name, i)
            u = np.concatenate([N.T @ (x[:p] * sv), x[p:]])  # the solver's unknowns in scipy's coordinates
            assert np.abs(N @ u[:N.shape[1]] - x[:p] * sv).max() < 1e-9  # on the datum: nothing along hold
            f = fun(u)
            assert abs(f @ f / chi2_s - 1) < 1e-10, (name, i, f @ f, chi2_s)
        # a phase moves what it frees only: the stations' unknowns alone leave the geometry at zero, at a higher chi2
        pose_b = identify_stations_batch(*args, hold=hold, basis=basis, phases=phase_masks(model, [["pose"]]))
        pose_r = identify_stations(*ref_args, hold=hold, phases=phase_masks(model, [["pose"]]))
        assert np.abs(pose_b["theta"][i] * sv).max() < 1e-9 and np.abs(pose_r.theta * sv).max() < 1e-9
        assert pose_b["chi2"][i] > 2 * chi2_s and abs(pose_b["chi2"][i] / pose_r.chi2 - 1) < 1e-9
        # one phase and multi-phase agree far closer with each other than with scipy's finite differences
        assert field_um(sc, model, one_b["theta"][i], multi_b["theta"][i]) < 1e-7
        assert field_um(sc, model, one_r.theta, multi_r.theta) < 1e-7


def gauss_newton_steps(fun, jac, u0, steps):
    """A plain Gauss-Newton of ``steps`` full steps (no halving) on fun, Jacobians by scipy's finite differences."""
    u = u0.copy()
    for _ in range(steps):
        r = fun(u)
        J = jac(u)
        u = u - np.linalg.lstsq(J, r, rcond=None)[0]
    return u


def test_the_loose_criterion_stops_the_reference_after_max_iter_steps(four):
    """convergence_criteria's loose option (xtol 0.5 um, max_iter 2) stops the Gauss-Newton reference after 2
    iterations (not converged: its second step is above 0.5 um), where a plain Gauss-Newton of 2 steps on the residuals
    written here stops: within 2e-5 um in the field (measured 4-7e-6; after 1 step 4e-5 of a 0.1 um move), and what
    it leaves against the minimum is what those two steps leave, within 20 % (measured 4-10e-5 um: Gauss-Newton
    converges quadratically from the closed-form start); the tight option converges.  The batch (the engine's chord)
    iterates to min(xtol, 1e-7) whatever the criterion, as the one-tracker chord iterates to min(xtol, chord_tol):
    loose and tight give it the same bits."""
    from mtbudget.multistation import identify_stations, identify_stations_batch, strategy_settings

    sc, sim, model, hold = four
    loose = strategy_settings(model, Strategy.one_phase(xtol=0.5, max_iter=2))
    tight = strategy_settings(model, Strategy.one_phase())
    assert loose["reference"] == {"xtol": 0.5, "max_iter": 2, "phases": None}
    assert tight["reference"] == {"xtol": 1e-4, "max_iter": 30, "phases": None}
    assert loose["batch"] == tight["batch"] == {"xtol": 1e-7, "phases": None}
    for i in range(3):
        ref_args = (model, sc.stations, sc.row_station, sim[0][i], sim.ranges[i], sc.noise.repeatability)
        r_loose = identify_stations(*ref_args, hold=hold, **loose["reference"])
        r_tight = identify_stations(*ref_args, hold=hold, **tight["reference"])
        assert r_loose.iterations == 2 and not r_loose.converged
        assert r_tight.converged and r_tight.iterations > 2
        fun, u0, unpack = weighted_residuals(sc, model, hold, sim[0][i], sim.ranges[i])
        jac = jacobian(fun, model, hold, sc)
        one, two, converged = (unpack(gauss_newton_steps(fun, jac, u0, k))[0] for k in (1, 2, 8))
        assert field_um(sc, model, converged, r_tight.theta) < 1e-5
        assert field_um(sc, model, one, converged) > 0.05  # one step is far from it, two are near
        left = field_um(sc, model, r_loose.theta, r_tight.theta)
        expected = field_um(sc, model, two, converged)
        assert field_um(sc, model, r_loose.theta, two) < 2e-5
        assert left > 1e-5 and 0.8 < left / expected < 1.2, (i, left, expected)
    basis = _station_basis(sc, model, None, hold)
    args = (model, sc.stations, sc.row_station, sim[0], sim.ranges, sc.noise.repeatability)
    b_loose = identify_stations_batch(*args, hold=hold, basis=basis, **loose["batch"])
    b_tight = identify_stations_batch(*args, hold=hold, basis=basis, **tight["batch"])
    assert np.array_equal(b_loose["x"], b_tight["x"])


def test_phases_are_checked_as_the_one_tracker_checks_them(four):
    from mtbudget.errors import IdentificationError
    from mtbudget.multistation import phase_masks

    model = four[2]
    with pytest.raises(IdentificationError, match="pose"):
        phase_masks(model, [["translational"]])
    with pytest.raises(IdentificationError, match="unknown parameter group"):
        phase_masks(model, [["pose", "thermal"]])


def test_the_strategy_sources_contribute_to_a_four_station_budget(tmp_path):
    """An engine run of four stations with a small budget: convergence_criteria and phase_sequence are rows like the
    others (no 'does not act' note), finite, and about nothing (the minimum is the minimum: multi-phase ends where
    one phase does, and the chord is not loosened by a loose xtol), as with one tracker."""
    from mtbudget.report import budget_text
    from mtbudget.runner import run

    res = run(load_config(FOUR), trials=16, block=8, attribution_trials=16)
    text = budget_text(res)
    assert "does not act" not in text
    pb = {r["source"]: r for r in res.budget["points"]["rows"]}
    for src in ("convergence_criteria", "phase_sequence"):
        u = np.asarray(pb[src]["u_rms_over_mesh"], float)
        assert np.isfinite(u).all() and u.max() < 0.01, (src, u)  # um
        assert np.isfinite(res.budget["compensation_rms"]["rows"][[r["source"] for r in res.budget[
            "compensation_rms"]["rows"]].index(src)]["contribution"])


def test_with_stated_scales_the_batch_runs_the_phases_by_gauss_newton_to_the_same_minimum():
    """With [scales] the several-station batch has fixed inputs and iterates by Gauss-Newton (not the chord): its
    multi-phase trials end where its one-phase trials and the reference (identify_stations, the same fixed inputs)
    end, within 1e-7 um in the compensated field and 1e-9 in chi2, after more iterations."""
    import tomllib

    from mtbudget.config import parse_config
    from mtbudget.multistation import identify_stations, identify_stations_batch, phase_masks

    d = tomllib.loads(FOUR.read_text())
    d["scales"] = {"x": {"cte": "11.5 um/(m*K)", "fixed_point": "800 mm"}}
    d["machine_tool"].pop("cte", None)
    d["sources"]["disable"] = d["sources"].get("disable", []) + ["temperature_drift"]
    sc = build_scenario(parse_config(d))
    sim = Engine(sc, block=2, seed=5).simulate(0)
    model, hold, fixed = sc.id_model, sc.unidentifiable(sc.id_model), sc.correction
    assert fixed
    multi = phase_masks(model, Strategy.multi_phase().phases)
    args = (model, sc.stations, sc.row_station, sim[0], sim.ranges, sc.noise.repeatability)
    basis = _station_basis(sc, model, fixed, hold)
    one = identify_stations_batch(*args, fixed=fixed, hold=hold, basis=basis)
    mul = identify_stations_batch(*args, fixed=fixed, hold=hold, basis=basis, phases=multi)
    assert one["converged"].all() and mul["converged"].all() and (mul["iterations"] > one["iterations"]).all()
    for i in range(2):
        r = identify_stations(model, sc.stations, sc.row_station, sim[0][i], sim.ranges[i], sc.noise.repeatability,
                              fixed=fixed, hold=hold, phases=multi)
        for theta, chi2 in ((one["theta"][i], one["chi2"][i]), (mul["theta"][i], mul["chi2"][i])):
            assert field_um(sc, model, theta, r.theta) < 1e-7 and abs(chi2 / r.chi2 - 1) < 1e-9


def test_identify_of_a_four_station_recording_takes_the_strategy():
    """`mtbudget identify --strategy multi-phase` on a recording of several stations runs the phases (more iterations)
    and reaches the minimum one phase reaches: the same parameters within 1e-6 um or urad and the same chi2 within
    1e-9 (measured 9e-10 and 5e-13 on the bundled four-station recording)."""
    import json

    from click.testing import CliRunner

    from mtbudget.cli import main
    from mtbudget.config import example_recording
    from mtbudget.multistation import identify_recording_any

    rec = example_recording("four_stations")
    _, one = identify_recording_any(rec)
    _, mul = identify_recording_any(rec, strategy=Strategy.multi_phase())
    assert one.converged and mul.converged and mul.iterations > one.iterations
    out = {}
    for st in ("one-phase", "multi-phase"):
        res = CliRunner().invoke(main, ["identify", "--example", "four_stations", "--strategy", st, "--json"])
        assert res.exit_code == 0, res.output
        out[st] = json.loads(res.stdout)
    a, b = out["one-phase"], out["multi-phase"]
    assert abs(a["chi2_per_dof"] / b["chi2_per_dof"] - 1) < 1e-9
    assert max(abs(x["value"] - y["value"]) for x, y in zip(a["parameters"], b["parameters"])) < 1e-6
