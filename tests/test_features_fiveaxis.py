"""Features probed on a five-axis machine ([[features]] with `angles`, docs/features.md "Five-axis machines").

A distance probed across a quarter turn of the C table against the closed form of a pivot offset (the nominal points
and the error written here from FORMAT-3's equations with scipy's rotations); the engine's feature errors against a
computation written here from the truth and the identified parameters of the same verifications, trial by trial;
an in-use source acting along the machine's axes against its closed form in the workpiece frame; missing or wrong
angles refused in one line (exit 2); the example run printing the features with measurand, unit, k and coverage.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from mtbudget.cli import main
from mtbudget.config import bundled_config, parse_config
from mtbudget.errors import ConfigError

P_COMMANDED = [150.0, 0.0, 50.0]  # mm, the example's volume: x, y in [-200, 200], z in [-100, 200]
LENGTH_ACROSS_C = {"name": "length across C", "kind": "distance",
                   "points": [["150 mm", "0 mm", "50 mm"], ["150 mm", "0 mm", "50 mm"]],
                   "angles": {"A": "0 deg", "C": ["0 deg", "90 deg"]}}


def five(**extra) -> dict:
    data = tomllib.loads(bundled_config("five_axis_cafxyz").read_text())
    data.update(extra)
    return data


def scenario(data):
    from mtbudget.scenario import build_scenario

    return build_scenario(parse_config(data, "five.toml"))


def rz(deg) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


# ------------------------------------------------------------------ closed form: a C pivot offset
def test_a_distance_across_a_table_turn_sees_the_pivot_offset_as_its_closed_form():
    """C's location errors EXOC, EYOC = delta and nothing else: the tool point in the table frame is
    p + R_C(c)^T (P + T - p - delta) (FORMAT-3 with A at 0), so the compensated machine (identified as nominal) reports
    S_i + R_C(c_i)^T delta, and the distance between (150, 0, 50) mm probed at c = 0 and c = 90 deg changes by
    u . (R_C(90)^T - I) delta = 24.96 um (u the unit vector between the nominal points (150, 0, -50) and (70, -120,
    -50) mm)."""
    from mtbudget.features import FeatureSet

    sc = scenario(five(features=[LENGTH_ACROSS_C]))
    fs = FeatureSet.of(sc)
    truth = sc.truth
    pivot = np.array([50.0, -20.0, 0.0])  # [rotary.C] pivot
    tool = np.array([0.0, 0.0, -100.0])  # the verification's first tool
    S = np.array([pivot + rz(c).T @ (np.array(P_COMMANDED) + tool - pivot) for c in (0, 90)])
    assert np.allclose(fs.tool_points, S, atol=1e-9)  # the part, in the table frame
    assert np.allclose(S, [[150, 0, -50], [70, -120, -50]])
    delta = np.array([0.020, -0.010, 0.0])  # mm
    theta = np.zeros((1, truth.n_params))
    names = truth.errors.names
    theta[0, names.index("dx(c)[O]")], theta[0, names.index("dy(c)[O]")] = delta[:2]
    e = fs.evaluate(truth, theta) - fs.evaluate(truth, np.zeros_like(theta))  # true minus identified (nominal)
    assert np.allclose(e[0], [-rz(c).T @ delta for c in (0, 90)], atol=1e-12)
    got = fs.block_values(e, seed=1, block=0)[0, 0, 0]
    M = S + np.array([rz(c).T @ delta for c in (0, 90)])
    exact = (np.linalg.norm(M[1] - M[0]) - np.linalg.norm(S[1] - S[0])) * 1e3
    u = (S[1] - S[0]) / np.linalg.norm(S[1] - S[0])
    assert got == pytest.approx(exact, abs=1e-9)
    assert got == pytest.approx(u @ (rz(90).T - np.eye(3)) @ delta * 1e3, rel=1e-4)
    assert got == pytest.approx(24.96, abs=0.01)


# ------------------------------------------------------------------ the engine against a computation written here
def test_engine_five_axis_features_equal_a_computation_from_the_parameters():
    """One block: each trial's feature errors (a distance across C, a diameter probed by turning C, a position at
    c = 90 deg) from the truth's and the identified parameters, the chain at a plan of the probed points with their
    angles built here, and the associations written here (numpy norm, scipy least squares in the table's xy plane)."""
    from scipy import optimize

    from mtbudget.engine import Engine
    from mtbudget.identify import scale_vector
    from mtbudget.model import MeasurementModel
    from mtbudget.plan import Plan

    bore = {"name": "bore by C", "kind": "diameter", "points": [["150 mm", "-20 mm", "50 mm"]] * 4,
            "angles": {"A": "0 deg", "C": ["0 deg", "90 deg", "180 deg", "270 deg"]}}
    at90 = {"name": "bore at C 90", "kind": "position",
            "points": [["100 mm", "0 mm", "50 mm"], ["0 mm", "100 mm", "50 mm"], ["-100 mm", "0 mm", "50 mm"],
                       ["0 mm", "-100 mm", "50 mm"]], "angles": {"A": "0 deg", "C": "90 deg"}}
    sc = scenario(five(features=[LENGTH_ACROSS_C, bore, at90]))
    eng = Engine(sc, block=8, seed=4)
    got = eng.run_blocks([0])[0].features[:, :, 0]
    theta_true = eng.simulate(0)[1]
    model = sc.id_model
    theta_hat = eng.run_blocks([0])[0].parameters / scale_vector(model)
    plans = {"length across C": ([P_COMMANDED] * 2, {"a": [0, 0], "c": [0, 90]}),
             "bore by C": ([[150, -20, 50]] * 4, {"a": [0] * 4, "c": [0, 90, 180, 270]}),
             "bore at C 90": ([[100, 0, 50], [0, 100, 50], [-100, 0, 50], [0, -100, 50]], {"a": [0] * 4, "c": [90] * 4})}

    def circle(X):  # geometric least-squares circle in the plane z = const (the table's xy plane at A = 0)
        r = optimize.least_squares(lambda p: np.hypot(X[:, 0] - p[0], X[:, 1] - p[1]) - p[2],
                                   [X[:, 0].mean(), X[:, 1].mean(), np.ptp(X[:, 0]) / 2], xtol=1e-15, ftol=1e-15)
        return r.x

    want = np.empty_like(got)
    for k, (P, ang) in enumerate(plans.values()):
        P = np.array(P, float)
        N = len(P)
        plan = Plan(np.arange(N), np.ones(N, int), np.zeros(N), P, np.ones((N, 3)), np.tile([0.0, 0.0, -100.0], (N, 1)),
                    angles={a: np.radians(np.array(v, float)) for a, v in ang.items()}, rotary=dict(sc.plan.rotary))
        true = MeasurementModel(sc.truth.config, sc.truth.errors, plan)
        S = true.machine_points(np.zeros((1, sc.truth.n_params)))[0]
        e = true.machine_points(theta_true) - MeasurementModel(model.config, model.errors, plan).machine_points(theta_hat)
        for i in range(len(got)):
            M = S - e[i]
            if k == 0:
                want[i, k] = (np.linalg.norm(M[1] - M[0]) - np.linalg.norm(S[1] - S[0])) * 1e3
            else:
                a, b = circle(M), circle(S)
                want[i, k] = 2 * (a[2] - b[2]) * 1e3 if k == 1 else 2 * np.hypot(a[0] - b[0], a[1] - b[1]) * 1e3
    assert np.allclose(got, want, rtol=0, atol=1e-4), np.abs(got - want).max(axis=0)
    assert np.abs(want).max(axis=0).min() > 0.1  # every feature moves by more than 0.1 um: not vacuous


# ------------------------------------------------------------------ an in-use source along the machine's axes
def test_machine_thermal_drift_acts_along_the_machine_axes_turned_into_the_table_frame():
    """The axes' temperature change alone (no verification source): each point moves by alpha dT_a p_a along the
    machine's axes; at one commanded position probed at c = 0 and 90 deg the same machine-frame displacement d is
    R^T d in the table frame at each, so the distance changes by ((R_C(90) - I) u) . d, u = 0.832 x 150 mm alpha
    u(dT) ... : u = alpha u(dT) |((R_C(90) - I) u)_x| 150 mm = 0.718 um (alpha 11.5 um/(m K), u(dT) 0.3 K).  Without
    the turn, the same displacement at both ends would leave the distance unchanged."""
    from mtbudget.report import result_json
    from mtbudget.runner import RunSettings, run

    f = dict(LENGTH_ACROSS_C, machine_temperature_change="0.3 K")
    res = run(parse_config(five(sources={"enable": []}, features=[f]), "five.toml"),
              RunSettings(trials=512, attribution_trials=0, seed=5))
    out = result_json(res)["features"][0]
    S = np.array([[150, 0, -50], [70, -120, -50]], float)
    u = (S[1] - S[0]) / np.linalg.norm(S[1] - S[0])
    c = (rz(90) - np.eye(3)) @ u * np.array(P_COMMANDED)
    expected = 11.5e-6 * 0.3 * np.linalg.norm(c) * 1e3
    assert expected == pytest.approx(0.718, abs=0.001)
    assert out["u"] == pytest.approx(expected, rel=0.1)  # 512 trials: the relative u of u is 3.1 %
    assert "workpiece (table) frame" in out["frame"] and out["points"]["angles"]["value"]["C"] == [0.0, 90.0]


PIVOT_A, PIVOT_C = np.array([0.0, -20.0, -80.0]), np.array([50.0, -20.0, 0.0])  # [rotary.A], [rotary.C] pivot
TOOL = np.array([0.0, 0.0, -100.0])  # the verification's first tool


def turn_rates_at_a0(P, c_deg):
    """FORMAT-3's chain with A at 0, differentiated here: a turn dA of A (pivot p_A, about +X) and dC of C (pivot p_C,
    about +Z) move the table-frame tool point S = p_C + R_C^T (p_A + R_A^T (v - p_A) - p_C), v = P + T, by
    -dC e_z x (S - p_C) and -dA R_C^T (e_x x (v - p_A)) (A at 0 leaves v where it is): (N, 3) S and the rates."""
    v = np.asarray(P, float) + TOOL
    S = np.array([PIVOT_C + rz(c).T @ (vi - PIVOT_C) for vi, c in zip(v, c_deg)])
    rate_c = np.array([-np.cross([0, 0, 1.0], s - PIVOT_C) for s in S])
    rate_a = np.array([-rz(c).T @ np.cross([1.0, 0, 0], vi - PIVOT_A) for vi, c in zip(v, c_deg)])
    return S, rate_a, rate_c


def rotary_alone(features, trials=16384, seed=3):
    """(trials, K) the rotary axes' in-use repeatability alone on ``features`` (no verification error)."""
    from mtbudget.features import IN_USE, FeatureSet

    fs = FeatureSet.of(scenario(five(features=features)))
    vals = fs.block_values(np.zeros((trials, len(fs.points), 3)), seed=seed, block=0)
    return fs, vals[:, :, 2 + IN_USE.index("rotary_repeatability_in_use")]


def test_rotary_repeatability_in_use_against_the_turn_of_each_axis_written_here():
    """The rotary axes' repeatability alone on the distance across C (A held at 0 for both ends, C turned from 0 to
    90 deg): the distance changes by u . (d_1 - d_0), d_i = dA_i rate_A,i + dC_i rate_C,i with the rates of
    FORMAT-3 written here.  C is positioned twice (two draws), A once (ONE draw, held while both ends are probed):
    u^2 = u_R^2 [(u . rC_0)^2 + (u . rC_1)^2 + (u . (rA_1 - rA_0))^2] = (0.1023 um/urad x u_R)^2; with
    `reposition = true` A is positioned at each point too, its two draws independent: (u . rA_0)^2 + (u . rA_1)^2,
    0.1063 um/urad.  The stated 20 urad and `repeatability = true` with the run's rotary_repeatability source
    (R = 10 urad) each.  The distance is linear in the draws (the chain's turn rates): normal, so 16384 draws give
    u's relative standard uncertainty 1/sqrt(2 x 16383) = 0.55 %; the tolerance 2.2 % (4 of them) is well inside
    the 3.9 % between the held and re-positioned A."""
    S, ra, rc = turn_rates_at_a0([P_COMMANDED] * 2, (0, 90))
    u = (S[1] - S[0]) / np.linalg.norm(S[1] - S[0])
    # u . rate: C 72.12 and 72.11 mm/rad at the two points, A -24.96 and -16.64 mm/rad
    held = np.sqrt((u @ rc[0]) ** 2 + (u @ rc[1]) ** 2 + (u @ (ra[1] - ra[0])) ** 2) * 1e-3  # um per urad
    each = np.sqrt((u @ rc[0]) ** 2 + (u @ rc[1]) ** 2 + (u @ ra[0]) ** 2 + (u @ ra[1]) ** 2) * 1e-3
    assert held == pytest.approx(0.1023, abs=1e-4) and each == pytest.approx(0.1063, abs=1e-4)

    fs, vals = rotary_alone([dict(LENGTH_ACROSS_C, rotary_repeatability="20 urad"),
                             dict(LENGTH_ACROSS_C, name="with the run's R", repeatability=True),
                             dict(LENGTH_ACROSS_C, name="re-positioned", rotary_repeatability="20 urad",
                                  reposition=True)])
    for a, rate in (("a", ra), ("c", rc)):  # the chain's turn rates equal those written here
        assert np.allclose(fs.turn[a][:2], rate, atol=1e-6)
    assert vals[:, 0].std(ddof=1) == pytest.approx(20 * held, rel=0.022)
    assert fs.specs[1].rotary_repeatability == pytest.approx(10e-6)  # [sources.rotary_repeatability] R
    assert vals[:, 1].std(ddof=1) == pytest.approx(10 * held, rel=0.022)
    assert vals[:, 2].std(ddof=1) == pytest.approx(20 * each, rel=0.022)
    assert fs.specs[0].in_use() == ["rotary_repeatability_in_use"]
    assert "drawn once per positioning" in fs.specs[0].measurand()
    assert "reposition = true" in fs.specs[2].measurand()


def test_a_held_rotary_turn_leaves_a_flatness_probed_at_one_pose_unchanged():
    """The face probed at one pose (A = -45 deg, C = 0 for all five points): each rotary axis is positioned once and
    held, its repeatability one small turn of the table for every point, a rigid motion: the measured points stay
    in one plane and the flatness from this source is 0 (to round-off).  Re-positioned at every point
    (`reposition = true`) the five turns differ and the face looks unflat."""
    face = tomllib.loads(bundled_config("five_axis_features").read_text())["features"][3]
    assert face["name"] == "tilted face" and face["angles"] == {"A": "-45 deg", "C": "0 deg"}
    face = {k: v for k, v in face.items() if k != "repeatability"}
    _, vals = rotary_alone([dict(face, rotary_repeatability="10 urad"),
                            dict(face, name="re-positioned", rotary_repeatability="10 urad", reposition=True)], 4096)
    assert np.abs(vals[:, 0]).max() < 1e-6  # um
    assert vals[:, 1].mean() > 0.3


def test_a_held_rotary_turn_moves_a_bore_at_one_pose_rigidly_about_the_axes():
    """The bore at C 90 (four points probed by the linear axes, A = 0 and C = 90 deg held): one turn dC about the C
    axis and one dA about the A axis move its four table-frame points rigidly, the centre c by dC a + dA b in the
    bore's plane, a = -(e_z x (c - p_C)) (|a| = r = |c - p_C| in the plane, 53.85 mm) and b = -R_C^T (e_x x
    (v_c - p_A)) (the tool point at the centre, 30 mm in the plane): the position (twice the centre's offset) is
    2 |dC a + dA b|, E[position^2] = 4 u_R^2 (|a|^2 + |b|^2) = (1.231 um)^2 at 10 urad.  Its relative standard
    uncertainty over n draws is sqrt(2 (l1^2 + l2^2)) / ((l1 + l2) sqrt(n)), l the eigenvalues of [a b][a b]^T,
    here 1.0 % at n = 16384; the tolerance 4 %.  The std of the position against numpy's own 10^6 draws of
    2 |dC a + dA b|: 0.713 um (per-point draws, the earlier rule, gave 0.469 um)."""
    bore = {"name": "bore at C 90", "kind": "position", "rotary_repeatability": "10 urad",
            "points": [["100 mm", "0 mm", "50 mm"], ["0 mm", "100 mm", "50 mm"], ["-100 mm", "0 mm", "50 mm"],
                       ["0 mm", "-100 mm", "50 mm"]], "angles": {"A": "0 deg", "C": "90 deg"}}
    P = np.array([[100, 0, 50], [0, 100, 50], [-100, 0, 50], [0, -100, 50]], float)
    S = turn_rates_at_a0(P, [90] * 4)[0]
    c = S.mean(axis=0)  # the four points are symmetric about the circle's centre
    vc = P.mean(axis=0) + TOOL
    a = -np.cross([0, 0, 1.0], c - PIVOT_C)[:2]
    b = -(rz(90).T @ np.cross([1.0, 0, 0], vc - PIVOT_A))[:2]
    assert np.linalg.norm(a) == pytest.approx(np.hypot(*(c - PIVOT_C)[:2])) == pytest.approx(53.85, abs=0.01)
    R = 10e-6
    mean_sq = 4 * R ** 2 * (a @ a + b @ b) * 1e6  # um^2
    lam = np.linalg.eigvalsh(np.outer(a, a) + np.outer(b, b))
    n = 16384
    rel = np.sqrt(2 * (lam ** 2).sum()) / lam.sum() / np.sqrt(n)
    assert rel < 0.011
    _, vals = rotary_alone([bore], n)
    assert (vals[:, 0] ** 2).mean() == pytest.approx(mean_sq, rel=4 * rel)
    z = np.random.default_rng(0).standard_normal((10 ** 6, 2))
    std = (2 * np.linalg.norm(z[:, :1] * a + z[:, 1:] * b, axis=1) * R * 1e3).std()
    assert std == pytest.approx(0.713, abs=0.002)
    assert vals[:, 0].std(ddof=1) == pytest.approx(std, rel=0.03)


def table_point(v, a_deg, c_deg):
    """FORMAT-3's chain at zero errors written with scipy: the table-frame point the tool at machine point v touches
    with A at a (about +X through p_A, on the bed) and C at c (about +Z through p_C, on A)."""
    Ra = Rotation.from_euler("x", a_deg, degrees=True).as_matrix()
    Rc = Rotation.from_euler("z", c_deg, degrees=True).as_matrix()
    return PIVOT_C + Rc.T @ (PIVOT_A + Ra.T @ (np.asarray(v, float) - PIVOT_A) - PIVOT_C)


def test_a_distance_probed_at_two_tilts_of_A_against_the_rotary_geometry_written_here():
    """(0, 0, 100) mm probed at A = 0 and at A = -45 deg, C = 0 both: on the part (the table frame) the ends are the
    scipy chain's points S_0 = (0, 0, 0) and S_1 = p_A + R_A(-45)^T (v - p_A).  Two in-use sources alone, 16384
    draws each, against their propagation written here (both linear in the draws: the distance's error is normal,
    the relative standard uncertainty of its u 1/sqrt(2 x 16383) = 0.55 %, the tolerance 2.2 %):
    * the axes' temperature change (u 0.3 K): the same commanded point, the same machine-frame displacement
      d = alpha dT_z 100 mm e_z at both ends, turned into the table frame at each pose (R = R_A(a) R_C(c),
      v_machine = R v_table): the distance changes by u . (R_1^T - R_0^T) d, u = alpha 0.3 K 100 mm
      |u . (R_1^T - I) e_z|;
    * the rotary axes' repeatability (R = 10 urad): A positioned twice (two draws), C held at 0 for both ends (one
      draw): u^2 = R^2 [(u . rA_0)^2 + (u . rA_1)^2 + (u . (rC_1 - rC_0))^2], the turn rates dS/da, dS/dc by
      central differences of the scipy chain (step 1e-4 deg: the second-order error 1e-12 of the rate): 1.077 um
      (u . rA = -76.19 mm/rad at both ends, u . rC = -49.46 at both: C's held turn cancels); `reposition = true`
      (every draw independent) 1.285 um.  Thermal 0.256 um."""
    P = [0.0, 0.0, 100.0]
    v = np.array(P) + TOOL
    S = np.array([table_point(v, a, 0) for a in (0, -45)])
    assert np.allclose(S[0], 0) and np.allclose(S[1], [0, -20 - 60 * np.sqrt(0.5), -80 + 100 * np.sqrt(0.5)])
    u = (S[1] - S[0]) / np.linalg.norm(S[1] - S[0])
    R1 = Rotation.from_euler("x", -45, degrees=True).as_matrix()  # R_A(-45) R_C(0)
    thermal = 11.5e-6 * 0.3 * 100 * abs(u @ (R1.T - np.eye(3)) @ [0, 0, 1.0]) * 1e3  # um
    h = 1e-4  # deg
    rate = {ax: np.array([(table_point(v, a + h * (ax == "a"), h * (ax == "c"))
                           - table_point(v, a - h * (ax == "a"), -h * (ax == "c"))) / np.radians(2 * h)
                          for a in (0, -45)]) for ax in "ac"}
    rotary = 10e-6 * np.sqrt((u @ rate["a"][0]) ** 2 + (u @ rate["a"][1]) ** 2
                             + (u @ (rate["c"][1] - rate["c"][0])) ** 2) * 1e3  # um
    each = 10e-6 * np.sqrt(sum((u @ rate[ax][i]) ** 2 for ax in "ac" for i in (0, 1))) * 1e3  # reposition = true
    # u . rate: A -76.19 mm/rad at both ends; C -49.46 at both: C's one held turn leaves the distance unchanged
    assert thermal == pytest.approx(0.2562, abs=1e-4) and rotary == pytest.approx(1.0774, abs=1e-4)
    assert each == pytest.approx(1.285, abs=0.001)

    from mtbudget.features import IN_USE, FeatureSet

    f = {"name": "across A", "kind": "distance", "points": [["0 mm", "0 mm", "100 mm"]] * 2,
         "angles": {"A": ["0 deg", "-45 deg"], "C": "0 deg"}}
    fs = FeatureSet.of(scenario(five(features=[dict(f, machine_temperature_change="0.3 K"),
                                               dict(f, name="rotary", rotary_repeatability="10 urad"),
                                               dict(f, name="re-positioned", rotary_repeatability="10 urad",
                                                    reposition=True)])))
    assert np.allclose(fs.tool_points[:2], S, atol=1e-9)
    for ax in "ac":  # the chain's own turn rates at the tilted pose equal the scipy chain's
        assert np.allclose(fs.turn[ax][2:4], rate[ax], atol=1e-6)
    vals = fs.block_values(np.zeros((16384, len(fs.points), 3)), seed=7, block=0)
    assert vals[:, 0, 2 + IN_USE.index("machine_thermal_drift")].std(ddof=1) == pytest.approx(thermal, rel=0.022)
    col = 2 + IN_USE.index("rotary_repeatability_in_use")
    assert vals[:, 1, col].std(ddof=1) == pytest.approx(rotary, rel=0.022)
    assert vals[:, 2, col].std(ddof=1) == pytest.approx(each, rel=0.022)


def test_repeatability_on_five_axes_without_the_rotary_source_asks_for_it():
    from mtbudget.features import FeatureSet

    sc = scenario(five(sources={"enable": ["tracker_noise"]}, features=[dict(LENGTH_ACROSS_C, repeatability=True)]))
    with pytest.raises(ConfigError) as exc:
        FeatureSet.of(sc)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("five.toml: features[0].repeatability: ")
    assert "features[0].repeatability" in msg and "state the feature's rotary_repeatability" in msg, msg


def test_a_rotary_repeatability_in_the_next_unit_up_is_refused():
    """The rule of every stated uncertainty (docs/configuration.md): 1 mrad for 1 urad is refused in one line."""
    from mtbudget.features import FeatureSet

    with pytest.raises(ConfigError, match=r"^five.toml: features\[0\]\.rotary_repeatability: 1000 urad is not "
                                          r"plausible; expected 0 to 500 urad$"):
        FeatureSet.of(scenario(five(features=[dict(LENGTH_ACROSS_C, rotary_repeatability="1 mrad")])))


def test_a_three_axis_feature_takes_no_rotary_repeatability():
    from mtbudget.features import FeatureSet
    from mtbudget.scenario import build_scenario

    data = tomllib.loads(bundled_config("paper_xfyz").read_text())
    data["features"] = [{"name": "x", "kind": "distance", "rotary_repeatability": "10 urad",
                         "points": [["800 mm", "100 mm", "200 mm"], ["1200 mm", "100 mm", "200 mm"]]}]
    with pytest.raises(ConfigError, match=r"^paper.toml: features\[0\]\.rotary_repeatability: machine 'XFYZ' has no "
                                          r"rotary axis"):
        FeatureSet.of(build_scenario(parse_config(data, "paper.toml")))


@pytest.mark.parametrize("machine, value, words", [
    ("five", "yes", "features[0].reposition: expected true or false"),
    ("paper", True, "features[0].reposition: machine 'XFYZ' has no rotary axis"),
])
def test_a_bad_reposition_is_refused_in_one_line(machine, value, words):
    from mtbudget.features import FeatureSet
    from mtbudget.scenario import build_scenario

    if machine == "five":
        data = five(features=[dict(LENGTH_ACROSS_C, reposition=value)])
    else:
        data = tomllib.loads(bundled_config("paper_xfyz").read_text())
        data["features"] = [{"name": "x", "kind": "distance", "reposition": value,
                             "points": [["800 mm", "100 mm", "200 mm"], ["1200 mm", "100 mm", "200 mm"]]}]
    with pytest.raises(ConfigError) as exc:
        FeatureSet.of(build_scenario(parse_config(data, "f.toml")))
    assert str(exc.value).startswith("f.toml: " + words) and "\n" not in str(exc.value), str(exc.value)


def test_a_wrong_datum_on_five_axes_names_the_table_frame_and_the_normal_expected_there():
    """The tilted face is commanded in the machine's plane z = 100 mm at A = -45 deg: on the part (the table frame)
    its normal is R_A(-45 deg)^T e_z = (0, -0.7071, 0.7071) (A about +X, FORMAT-3's sense, written with scipy); a
    datum [0, 0, 1] (the commanded plane's normal) is refused in one line that names the nominal points in the
    workpiece (table) frame and prints that normal, not 'the commanded points'."""
    from mtbudget.features import FeatureSet

    face = tomllib.loads(bundled_config("five_axis_features").read_text())["features"][3]
    normal = Rotation.from_euler("x", -45, degrees=True).as_matrix().T @ [0, 0, 1.0]
    assert np.allclose(normal, [0, -np.sqrt(0.5), np.sqrt(0.5)])
    with pytest.raises(ConfigError) as exc:
        FeatureSet.of(scenario(five(features=[dict(face, datum=[0, 0, 1])])))
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("five.toml: features[0].datum: is not the normal of the plane of the "
                                              "nominal points in the workpiece (table) frame"), msg
    shown = np.array([float(v) for v in msg.split("which is [")[1].split("]")[0].split(",")])
    assert np.allclose(np.abs(shown @ normal), 1, atol=1e-4), msg
    FeatureSet.of(scenario(five(features=[dict(face, datum=list(normal))])))  # the table frame's normal is taken


def test_coinciding_poses_on_five_axes_are_named_in_the_table_frame():
    """Two probed poses that put the tool at one point of the part: (150, 0, 50) mm at C = 0 and, turned a quarter,
    the commanded point the table's turn brings to the same table point (p_C + R_C(90) (S - p_C) - T, S = (150, 0,
    -50) mm): distinct commanded points, one point on the part."""
    S = np.array([150.0, 0.0, -50.0])
    P2 = PIVOT_C + rz(90) @ (S - PIVOT_C) - TOOL
    assert np.allclose(turn_rates_at_a0([P2], [90])[0], S)
    f = dict(LENGTH_ACROSS_C, points=[["150 mm", "0 mm", "50 mm"], [f"{v:.9f} mm" for v in P2]])
    with pytest.raises(ConfigError) as exc:
        scenario_features(f)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("five.toml: features[0].points: the nominal points in the workpiece "
                                              "(table) frame (the tool at the commanded poses) coincide, at (150, 0, "
                                              "-50) mm"), msg


def scenario_features(*features):
    from mtbudget.features import FeatureSet

    return FeatureSet.of(scenario(five(features=list(features))))


# ------------------------------------------------------------------ bad angles: one line, exit 2
BASE = str(bundled_config("five_axis_cafxyz"))
PAPER = str(bundled_config("paper_xfyz"))


@pytest.mark.parametrize("base, angles, words", [
    (BASE, None, "features[0].angles: missing: machine 'CAFXYZ' has rotary axes A, C"),
    (BASE, '{C = ["0 deg", "90 deg"]}', "features[0].angles.A: missing"),
    (BASE, '{A = "0 deg", C = ["0 deg"]}', "features[0].angles.C: 1 angles for 2 probed points"),
    (BASE, '{A = "0 deg", B = "0 deg", C = "0 deg"}', "features[0].angles.B: machine 'CAFXYZ' has no rotary axis B"),
    (BASE, '{A = "0 deg", C = ["0 deg", "300 deg"]}', "features[0].angles.C[1]: 300 deg lies outside the angles the "
                                                       "verification visited, [0, 270] deg"),
    (BASE, '{A = "120 deg", C = "0 deg"}', "features[0].angles.A: 120 deg lies outside"),
    (BASE, '{A = "0 deg", C = ["0 deg", "36090 deg"]}', "features[0].angles.C[1]: 36090 deg is more than 100 turns "
                                                        "from zero; state the commanded angle (within +-36000 deg)"),
    (BASE, '{A = "0 deg", C = ["0 deg", "-35700 deg"]}', "features[0].angles.C[1]: -35700 deg lies outside the angles "
                                                         "the verification visited"),
    (BASE, '{A = "0 mm", C = "0 deg"}', "features[0].angles.A"),
    (BASE, '{A = "0 deg", C = "0 deg", c = "90 deg"}', "features[0].angles.c: rotary axis C is stated twice (as C "
                                                       "and c)"),
    (BASE, '"0 deg"', "features[0].angles: expected a table of the rotary axes' angles"),
    (PAPER, '{C = "0 deg"}', "features[0].angles: machine 'XFYZ' has no rotary axis; a feature's points take no angles"),
])
def test_missing_or_wrong_angles_are_refused_in_one_line(tmp_path, base, angles, words):
    pts = ('[["150 mm", "0 mm", "50 mm"], ["150 mm", "0 mm", "100 mm"]]' if base == BASE else
           '[["800 mm", "100 mm", "200 mm"], ["1200 mm", "100 mm", "200 mm"]]')
    path = tmp_path / "feat.toml"
    path.write_text(f'extends = "{base}"\n\n[[features]]\nname = "d"\nkind = "distance"\npoints = {pts}\n'
                    + (f"angles = {angles}\n" if angles else ""))
    res = CliRunner().invoke(main, ["run", str(path), "--trials", "2", "--log", str(tmp_path / "r.mcap"), "--quiet"])
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert "\n" not in line and "Traceback" not in line and str(path) in line and words in line, line


def test_a_minus_90_deg_c_angle_is_the_visited_270_deg():
    """The chain is periodic in a rotary angle: -90 deg is 270 deg, inside the visited [0, 270] deg."""
    from mtbudget.features import FeatureSet

    f = dict(LENGTH_ACROSS_C, angles={"A": "0 deg", "C": ["-90 deg", "270 deg"]},
             points=[["150 mm", "0 mm", "50 mm"], ["150 mm", "0 mm", "100 mm"]])
    fs = FeatureSet.of(scenario(five(features=[f])))
    assert np.allclose(fs.tool_points[0, :2], fs.tool_points[1, :2], atol=1e-9)


# ------------------------------------------------------------------ the example run, its JSON, report and DCC
@pytest.fixture(scope="module")
def example_run(tmp_path_factory):
    """`mtbudget run examples/five_axis_features.toml` (32 trials, a 16-trial budget): its output and its log."""
    log = tmp_path_factory.mktemp("five_axis_features") / "f.mcap"
    res = CliRunner().invoke(main, ["run", str(bundled_config("five_axis_features")), "--trials", "32", "--block",
                                    "16", "--attribution-trials", "16", "--quiet", "--log", str(log)])
    assert res.exit_code == 0, res.output
    return res, log


def test_the_five_axis_example_states_its_features_with_measurand_unit_k_coverage_and_frame(tmp_path, example_run):
    """`mtbudget run examples/five_axis_features.toml` prints every feature with its unit, u (k = 1), the interval's
    coverage, its measurand and the frame; the log's JSON, report and DCC say the same."""
    from mtbudget.report import result_json, run_report
    from mtbudget.report_dcc import write_dcc
    from mtbudget.runner import replay

    res, log = example_run
    table = res.output[res.output.index("Features probed on the compensated machine"):]
    assert "in the workpiece (table) frame" in table.splitlines()[0]
    assert "u (k=1)" in table and "95 % coverage" in table
    for name, kind in (("length across C", "distance"), ("bore by C", "diameter"), ("bore at C 90", "position"),
                       ("tilted face", "flatness")):
        row = next(line for line in table.splitlines() if line.strip().startswith(name + " ") and kind in line)
        assert "µm" in row
        assert f"{name}: " in table  # its measurand sentence
    assert "each point probed at its commanded rotary angles (A, C)" in table

    again = replay(log)
    j = result_json(again)["features"][0]
    assert j["name"] == "length across C" and j["unit"] == "um" and j["k"] == 1 and j["interval"]["coverage"] == 0.95
    assert j["points"]["angles"] == {"value": {"A": [0.0, 0.0], "C": [0.0, 90.0]}, "unit": "deg"}
    assert "workpiece (table) frame" in j["frame"] and "workpiece (table) frame" in j["measurand"]
    md = run_report(again, tmp_path / "rep")["markdown"].read_text()
    assert "| length across C | distance |" in md and "in the workpiece (table) frame" in md
    xml = write_dcc(again, tmp_path / "c.xml").read_text()
    assert "length across C" in xml and "in the workpiece (table) frame" in xml


def test_the_report_and_the_dcc_list_each_features_commanded_points_angles_and_points_on_the_part(tmp_path,
                                                                                                    example_run):
    """The pose is part of the measurand: report.md and the DCC list every probed point of every feature, its
    commanded position (mm), its commanded angles (deg) and the nominal point on the part in the table frame, the
    values of the configuration (read here from the example's TOML) and of the closed form (the length across C's
    ends on the part at (150, 0, -50) and (70, -120, -50) mm, the first test); the JSON labels its points as
    commanded machine positions and gives the part's nominal points.  The DCC keeps the schema's structure."""
    import xml.etree.ElementTree as ET

    from test_report_dcc import NS, follows_the_schema_structure

    from mtbudget.report import result_json, run_report
    from mtbudget.report_dcc import write_dcc
    from mtbudget.runner import replay

    again = replay(example_run[1])
    feats = tomllib.loads(bundled_config("five_axis_features").read_text())["features"]

    def mm(v):
        return float(v.split()[0])

    def deg(f, a, j):
        v = f["angles"][a]
        return mm(v[j] if isinstance(v, list) else v)

    j = result_json(again)["features"][0]
    assert "commanded machine positions" in j["points"]["quantity"]
    assert np.allclose(j["nominal_points"]["value"], [[150, 0, -50], [70, -120, -50]], atol=1e-9)
    assert "workpiece (table) frame" in j["nominal_points"]["frame"]

    md = run_report(again, tmp_path / "rep")["markdown"].read_text()
    lines = {ln.split("**")[1]: md.splitlines()[i + 1] for i, ln in enumerate(md.splitlines())
             if ln.startswith("* **")}
    assert "2: (150, 0, 50) mm, A = 0°, C = 90° → (70, -120, -50) mm on the part" in lines["length across C"]
    for f in feats:
        line = lines[f["name"]]
        assert line.startswith("  Probed points (commanded position of the linear axes and commanded rotary angles")
        for k, p in enumerate(f["points"]):
            at = f"{k + 1}: ({', '.join(f'{mm(v):g}' for v in p)}) mm, A = {deg(f, 'A', k):g}°, C = {deg(f, 'C', k):g}°"
            assert at in line, (at, line)

    root = ET.parse(write_dcc(again, tmp_path / "c.xml")).getroot()
    follows_the_schema_structure(root)
    result = next(r for r in root.iter(f"{{{NS['dcc']}}}result")
                  if r.find("dcc:name/dcc:content", NS).text.startswith("probed points of each feature"))
    lists = result.findall("dcc:data/dcc:list", NS)
    assert len(lists) == len(feats)
    for f, fl in zip(feats, lists):
        assert fl.find("dcc:name/dcc:content", NS).text.startswith(f["name"])
        pts = fl.findall("dcc:list", NS)
        assert len(pts) == len(f["points"])
        for k, (p, pl) in enumerate(zip(f["points"], pts)):
            got = {q.find("si:real/si:label", NS).text: (float(q.find("si:real/si:value", NS).text),
                                                          q.find("si:real/si:unit", NS).text)
                   for q in pl.findall("dcc:quantity", NS)}
            want = {"commanded_X": (mm(p[0]), r"\milli\metre"), "commanded_Y": (mm(p[1]), r"\milli\metre"),
                    "commanded_Z": (mm(p[2]), r"\milli\metre"), "commanded_A": (deg(f, "A", k), r"\degree"),
                    "commanded_C": (deg(f, "C", k), r"\degree")}
            assert {key: got[key] for key in want} == want
            assert set(got) == set(want) | {"nominal_x", "nominal_y", "nominal_z"}
    first = [{q.find("si:real/si:label", NS).text: float(q.find("si:real/si:value", NS).text)
              for q in pl.findall("dcc:quantity", NS)} for pl in lists[0].findall("dcc:list", NS)]
    assert [[p[f"nominal_{a}"] for a in "xyz"] for p in first] == [[150, 0, -50], [70, -120, -50]]


def test_a_head_side_machine_states_its_features_points_in_the_machine_frame(tmp_path):
    """YFXZAC: the rotary axes carry the tool, the part stays in the machine frame; the report and the DCC must not
    call its nominal points the workpiece (table) frame (they did, from a fixed label)."""
    from mtbudget.report import result_json, run_report
    from mtbudget.report_dcc import write_dcc
    from mtbudget.runner import replay

    log = tmp_path / "h.mcap"
    res = CliRunner().invoke(main, ["run", str(bundled_config("five_axis_features")), "--set", "machine=YFXZAC",
                                    "--trials", "16", "--block", "16", "--attribution-trials", "0", "--quiet",
                                    "--log", str(log)])
    assert res.exit_code == 0, res.output
    again = replay(log)
    j = result_json(again)["features"][0]
    assert j["frame"] == "machine frame" == j["nominal_points"]["frame"]
    md = run_report(again, tmp_path / "rep")["markdown"].read_text()
    xml = write_dcc(again, tmp_path / "c.xml").read_text()
    assert "nominal point on the part in the machine frame" in md and "workpiece (table) frame" not in md
    assert "of the point on the part, machine frame" in xml and "of the point on the part, workpiece" not in xml
