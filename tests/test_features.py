"""Features probed on the compensated machine ([[features]], mtbudget/features.py, docs/features.md).

The uncertainty of two distances against a linear propagation of the identification covariance written here
(finite differences of the kinematic chain, the tracker covariance of Eq. 23 written from the spherical
coordinates, the weighted least-squares sandwich); the association functions against closed forms; every bad
input refused in one line that names file and key.
"""

from __future__ import annotations

import copy
import tomllib

import numpy as np
import pytest

from mtbudget.config import default_config_path, parse_config
from mtbudget.errors import ConfigError
from mtbudget.features import circle_fit, minimum_zone_flatness, plane_fit
from mtbudget.model import MeasurementModel
from mtbudget.plan import Plan


def paper(**extra) -> dict:
    data = tomllib.loads(default_config_path().read_text())
    data.update(copy.deepcopy(extra))
    return data


X_LENGTH = {"name": "x length", "kind": "distance", "points": [["800 mm", "100 mm", "200 mm"],
                                                                ["1200 mm", "100 mm", "200 mm"]], "tolerance": "20 um"}
DIAGONAL = {"name": "space diagonal", "kind": "distance", "points": [["800 mm", "100 mm", "200 mm"],
                                                                      ["1200 mm", "500 mm", "400 mm"]]}


# ------------------------------------------------------------------ the linear propagation, written here
def _tracker_cov(P, angular, distance, per_length, repeatability):
    """Cartesian covariance of tracker points P (M, 3): range and two angles in spherical coordinates."""
    x, y, z = P.T
    rho = np.hypot(x, y)
    r = np.hypot(rho, z)
    e_r = P / r[:, None]
    e_az = np.stack([-y / rho, x / rho, np.zeros_like(x)], axis=1)
    e_el = np.cross(e_r, e_az)
    u_r = distance + per_length * r
    C = (u_r**2)[:, None, None] * np.einsum("mi,mj->mij", e_r, e_r)
    C += ((rho * angular) ** 2)[:, None, None] * np.einsum("mi,mj->mij", e_az, e_az)
    C += ((r * angular) ** 2)[:, None, None] * np.einsum("mi,mj->mij", e_el, e_el)
    return C + repeatability**2 * np.eye(3)


def linear_u(sc, features) -> list:
    """u of each distance from the identification covariance: the weighted least squares over the geometric
    parameters and the tracker pose, linearised at the nominal machine, with the stated weights (20 urad,
    4 um + 0.8 um/m, repeatability) and the covariance the run draws (tracker noise only; the angular u drawn per
    trial from N(20, 3) urad, so its mean square is 20^2 + 3^2 urad^2)."""
    model = sc.id_model
    p = model.n_params
    x0 = np.concatenate([np.zeros(p), sc.pose])
    step = np.concatenate([np.full(p, 1e-4), np.full(3, 1e-3), np.full(3, 1e-6)])

    def meas(x):
        return model.predict(x[None, :p], x[p:])[0].reshape(-1)

    A = np.column_stack([(meas(x0 + np.eye(len(x0))[j] * step[j]) - meas(x0 - np.eye(len(x0))[j] * step[j]))
                         / (2 * step[j]) for j in range(len(x0))])
    P = meas(x0).reshape(-1, 3)
    n = sc.noise
    Cw = _tracker_cov(P, n.angular, n.distance, n.distance_per_length, n.repeatability)
    Ct = _tracker_cov(P, np.hypot(20e-6, 3e-6), n.distance, n.distance_per_length, 0.0)
    W = np.zeros((A.shape[0], A.shape[0]))
    S = np.zeros_like(W)
    for i in range(len(P)):
        W[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.linalg.inv(Cw[i])
        S[3 * i:3 * i + 3, 3 * i:3 * i + 3] = Ct[i]
    nrm = np.linalg.norm(A, axis=0)
    D = np.where(nrm > 0, 1 / np.where(nrm > 0, nrm, 1), 1.0)  # columns scaled; a parameter no point sees stays 0
    As = A * D
    Hinv = np.linalg.pinv(As.T @ W @ As, rcond=1e-10)
    K = Hinv @ As.T @ W
    cov = D[:, None] * (K @ S @ K.T) * D[None, :]  # of theta and pose
    out = []
    for f in features:
        pts = np.array([[float(v.split()[0]) for v in q] for q in f["points"]])
        plan = Plan(np.arange(2), np.ones(2, int), np.zeros(2), pts, np.ones((2, 3)), np.tile(sc.tool, (2, 1)))
        m = MeasurementModel(model.config, model.errors, plan)
        J = np.stack([(m.machine_points(np.eye(p)[j] * 1e-4)[0] - m.machine_points(-np.eye(p)[j] * 1e-4)[0]) / 2e-4
                      for j in range(p)], axis=-1)  # (2, 3, p)
        u = (pts[1] - pts[0]) / np.linalg.norm(pts[1] - pts[0])
        g = u @ (J[1] - J[0])  # d(distance)/d(theta)
        out.append(float(np.sqrt(g @ cov[:p, :p] @ g)) * 1e3)
    return out


def test_distances_tracker_noise_alone_match_linear_propagation():
    from mtbudget.report import result_json
    from mtbudget.runner import RunSettings, run
    from mtbudget.scenario import build_scenario

    cfg = parse_config(paper(sources={"enable": ["tracker_noise"]}, features=[X_LENGTH, DIAGONAL]), "paper.toml")
    sc = build_scenario(cfg)
    res = run(sc, RunSettings(trials=4096, attribution_trials=0, seed=11))
    feats = result_json(res)["features"]
    expected = linear_u(sc, [X_LENGTH, DIAGONAL])
    for f, u_lin in zip(feats, expected):
        assert f["unit"] == "um" and f["k"] == 1
        assert f["u"] == pytest.approx(u_lin, rel=0.05), (f["name"], f["u"], u_lin)
    assert expected[0] > 1.0 and expected[1] > 1.0  # not a vacuous comparison


# ------------------------------------------------------------------ association against closed forms
def test_circle_fit_recovers_a_shifted_circle():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 2 * np.pi, 7, endpoint=False)
    u, v = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    c = rng.normal(0, 0.01, (5, 2))
    R = 50 + rng.normal(0, 0.01, 5)
    Q = np.stack([c[:, 0, None] + R[:, None] * np.cos(t), c[:, 1, None] + R[:, None] * np.sin(t),
                  np.zeros((5, 7))], axis=-1)
    centre, radius = circle_fit(Q, u, v)
    assert np.allclose(centre, c, atol=1e-12) and np.allclose(radius, R, atol=1e-12)


def test_plane_fit_and_minimum_zone_of_a_tilted_plane():
    g = np.array([[x, y] for x in (-1, 0, 1) for y in (-1, 0, 1)], float) * 100
    h = 1e-3 * g[:, 0] / 100  # a 10 urad tilt, flat
    h2 = h + np.where((g == 0).all(axis=1), 0.004, 0.0)  # the centre 4 um high: zone 4 um along the normal
    Q = np.stack([np.column_stack([g, h]), np.column_stack([g, h2])])
    c, n = plane_fit(Q)
    assert abs(abs(n[0] @ np.array([-1e-5, 0, 1]) / np.linalg.norm([-1e-5, 0, 1])) - 1) < 1e-12
    mz = minimum_zone_flatness(Q, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    assert mz[0] == pytest.approx(0, abs=1e-12) and mz[1] == pytest.approx(0.004, rel=1e-9)


# ------------------------------------------------------------------ in-use sources, budget, decision
def test_in_use_sources_have_their_closed_forms():
    """Probing error alone on a distance: u = sqrt(2) P_FTU / 3.931 (two points along the line); part temperature
    alone: u = L alpha u_T; both as budget rows of their own."""
    from mtbudget.report import result_json
    from mtbudget.runner import RunSettings, run

    f = dict(X_LENGTH, probing_error="4 um", part_temperature="22 degC", part_temperature_u="0.5 K",
             part_cte="10 um/(m*K)")
    cfg = parse_config(paper(sources={"enable": []}, features=[f]), "paper.toml")
    res = run(cfg, RunSettings(trials=2048, attribution_trials=256, seed=5))
    out = result_json(res)["features"][0]
    expected = np.hypot(np.sqrt(2) * 4 / 3.931, 400 * 10e-6 * 0.5 * 1e3)
    assert out["u"] == pytest.approx(expected, rel=0.05)
    rows = {r["source"]: r for r in out["budget"]["rows"]}
    assert rows["probing"]["u_i"] == pytest.approx(np.sqrt(2) * 4 / 3.931, rel=0.15)
    assert rows["part_temperature"]["u_i"] == pytest.approx(2.0, rel=0.15)
    assert out["decision"]["verdict_at_nominal"] == "conforms" and "ISO 14253-1" in out["decision"]["rule"]


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("feature, words", [
    (dict(X_LENGTH, points=[["800 mm", "100 mm", "200 mm"], ["1300 mm", "100 mm", "200 mm"]]),
     "features[0].points[1]: (1300, 100, 200) mm lies outside the verified volume"),
    (dict(X_LENGTH, points=[["800 mm", "100 mm", "200 mm"]]), "features[0].points: a distance needs exactly 2"),
    ({"name": "p", "kind": "flatness", "points": [["800 mm", "100 mm", "200 mm"], ["900 mm", "100 mm", "200 mm"],
                                                  ["1000 mm", "100 mm", "200 mm"], ["1100 mm", "100 mm", "200 mm"]]},
     "features[0].points: the points are collinear"),
    (dict(X_LENGTH, points=[["800 mm", "100 mm", "200 mm"]] * 2),
     "features[0].points: the two points coincide; a distance needs two distinct points"),
    ({"name": "p", "kind": "flatness", "datum": [0, 1, 0],
      "points": [["800 mm", "100 mm", "200 mm"], ["900 mm", "100 mm", "200 mm"], ["900 mm", "200 mm", "200 mm"],
                 ["800 mm", "200 mm", "200 mm"]]},
     "features[0].datum: is not the normal of the plane of the commanded points"),
    (dict(X_LENGTH, tolerance="20 urad"), "features[0].tolerance"),
    (dict(X_LENGTH, kind="cylinder"), "features[0].kind: unknown kind 'cylinder'"),
    (dict(X_LENGTH, colour="red"), "features[0].colour: unknown key"),
    (dict(X_LENGTH, part_cte_u="1 um/(m*K)"), "features[0].part_cte_u: the CTE's uncertainty acts through"),
    ({"name": "o", "kind": "orientation", "part_temperature_u": "0.1 K",
      "points": [["800 mm", "100 mm", "200 mm"], ["900 mm", "100 mm", "200 mm"], ["900 mm", "200 mm", "200 mm"]]},
     "features[0].part_temperature_u: an orientation does not see the part's uniform expansion"),
    ([X_LENGTH, X_LENGTH], "features[1].name: feature 'x length' is named twice"),
])
def test_bad_features_are_refused_in_one_line(feature, words):
    from mtbudget.scenario import build_scenario
    from mtbudget.engine import Engine

    with pytest.raises(ConfigError) as exc:
        Engine(build_scenario(parse_config(paper(features=feature if isinstance(feature, list) else [feature]),
                                           "run.toml")))
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("run.toml: ") and words in msg, msg


# ------------------------------------------------------------------ the engine's features against code written apart
def test_engine_features_equal_an_independent_computation():
    """One block of the example's features without in-use sources: the engine's feature errors equal those of the
    coverage benchmark's own code (truth and identified model at the probed points, scipy/numpy associations) for the
    same verifications, trial by trial."""
    import sys
    from pathlib import Path

    from mtbudget.config import bundled_config
    from mtbudget.engine import Engine
    from mtbudget.scenario import build_scenario

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import bench_features_coverage as bench

    data = tomllib.loads(bundled_config("paper_features").read_text())
    in_use = ("probing_error", "repeatability", "machine_temperature_change", "part_temperature",
              "part_temperature_u", "part_cte", "part_cte_u")
    data["features"] = [{k: v for k, v in f.items() if k not in in_use} for f in data["features"]]
    sc = build_scenario(parse_config(data, "paper_features.toml"))
    eng = Engine(sc, block=16, seed=3)
    got = eng.run_blocks([0])[0].features[:, :, 0]
    want = bench.part_errors(sc, eng, data["features"], [0], np.random.default_rng(0))
    assert got.shape == want.shape == (16, 6)
    # to 0.1 nm (urad): the associations differ at the second order of the micrometre tilts (projection on the
    # nominal plane here, on z = const there), 2e-5 um at most
    assert np.allclose(got, want, rtol=0, atol=1e-4), np.abs(got - want).max(axis=0)
    assert np.abs(want).max(axis=0).min() > 0.1  # every feature moves by more than 0.1 um (urad): not vacuous


def test_features_in_text_and_report(tmp_path):
    from mtbudget.report import budget_text, run_report
    from mtbudget.runner import execute, replay, RunSettings

    cfg = parse_config(paper(sources={"enable": ["tracker_noise"]}, features=[X_LENGTH]))
    log = tmp_path / "run.mcap"
    res = execute(cfg, RunSettings(trials=128, attribution_trials=64, seed=2, progress=False), log_path=log)
    text = budget_text(res)
    assert "Features probed on the compensated machine" in text and "x length" in text and "ISO 14253-1" in text
    again = replay(log)
    out = run_report(again, tmp_path / "rep")
    md = out["markdown"].read_text()
    assert "## Features probed on the compensated machine" in md and "| x length | distance |" in md and "µm" in md


def test_minimum_zone_by_enumeration_equals_linear_programming():
    """The vectorised enumeration of the zone's vertices (up to 12 points) against scipy's linprog on random points."""
    from scipy.optimize import linprog

    from mtbudget.features import _mz_enumerate

    rng = np.random.default_rng(8)
    for N in (4, 5, 9, 12):
        s, t = rng.uniform(-200, 200, (2, 20, N))
        h = 1e-3 * rng.normal(size=(20, N)) + 1e-5 * s - 2e-5 * t
        got = _mz_enumerate(s, t, h)
        for k in range(20):
            A = np.column_stack([s[k], t[k], np.ones(N)])
            r = linprog([0, 0, 0, 1], A_ub=np.vstack([np.column_stack([-A, -np.ones(N)]),
                                                      np.column_stack([A, -np.ones(N)])]),
                        b_ub=np.r_[-h[k], h[k]], bounds=[(None, None)] * 3 + [(0, None)], method="highs")
            assert got[k] == pytest.approx(2 * r.x[3], rel=1e-7, abs=1e-12), (N, k)


def test_a_run_with_resumed_blocks_says_its_features_are_not_available():
    """Blocks read back from a log hold no feature values: the run says so instead of stating a u from some trials."""
    from mtbudget.engine import Engine
    from mtbudget.report import result_json
    from mtbudget.runner import RunSettings, run
    from mtbudget.scenario import build_scenario

    cfg = parse_config(paper(sources={"enable": ["tracker_noise"]}, features=[X_LENGTH]), "paper.toml")
    eng = Engine(build_scenario(cfg), block=64, seed=1)
    b0 = eng.run_block(0)
    b0.features = None  # as read back from a run log
    res = run(engine=eng, settings=RunSettings(trials=128, attribution_trials=0, seed=1, block=64),
              resume_blocks=[b0])
    f = result_json(res)["features"][0]
    assert "u" not in f and "not available" in f["note"]


@pytest.mark.parametrize("u, low, high", [(8.731, -18.712, 15.536), (0.01234, -0.0251, 0.0237), (123.4, -250.2, 240.9)])
def test_feature_rows_show_u_to_two_significant_digits_and_the_rest_to_its_decimal(u, low, high):
    """The features table (text and report) rounds u to two significant digits and the estimate and interval to the
    same decimal, as the run's summary promises (JCGM 101 7.9.2); it printed three decimals whatever u was."""
    from mtbudget.features import features_markdown, features_text

    f = {"name": "bore", "kind": "diameter", "unit": "um", "estimate": (low + high) / 2, "u": u,
         "interval": {"low": low, "high": high, "coverage": 0.95}, "measurand": "the bore's diameter error"}
    import re
    from decimal import Decimal

    nd = max(0, 1 - Decimal(repr(u)).adjusted())  # the decimal of u's second significant digit
    row = next(ln for ln in features_text([f]) if ln.strip().startswith("bore"))
    nums = re.findall(r"-?\d+(?:\.\d+)?", row.split("µm", 1)[1])
    assert nums[:4] == [f"{v:.{nd}f}" for v in (f["estimate"], u, low, high)], row
    two = f"{u:.{nd}f}"
    assert len(two.replace(".", "").lstrip("0")) == 2 or nd == 0
    md = next(ln for ln in features_markdown([f]) if ln.startswith("| bore"))
    assert f"| {two} µm |" in md and f"[{low:.{nd}f}, {high:.{nd}f}]" in md
