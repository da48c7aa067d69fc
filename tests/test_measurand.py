"""The per-point, per-axis statement: JCGM 101 intervals, an independent linear propagation, replay, the decision."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from conftest import compensated_field_propagation
from click.testing import CliRunner

from mtbudget.budget import conformance, point_lpu
from mtbudget.cli import main
from mtbudget.config import load_config, parse_config
from mtbudget.report import result_json
from mtbudget.runner import execute, replay, run
from mtbudget.scenario import build_scenario
from mtbudget.stats import interval_indices, shortest_interval, symmetric_interval
from mtbudget.units import ureg


# ----------------------------------------------------------------------------- JCGM 101 7.7
@pytest.mark.parametrize("M, p, low, high", [
    (1000, 0.95, 25, 975),  # q = 950, (M - q)/2 = 25 is an integer: [y(25), y(975)] (1-based), the clause's example
    (30, 0.90, 2, 29),      # q = 27, (M - q)/2 = 1.5 is not: r = int((M - q + 1)/2) = 2
    (21, 0.95, 1, 21),      # q = int(19.95 + 0.5) = 20, r = int(2/2) = 1
    (200, 0.90, 10, 190),
    (10_000, 0.99, 50, 9950),
])
def test_symmetric_interval_follows_jcgm_101_7_7_1(M, p, low, high):
    y = np.arange(1, M + 1, dtype=float)  # y(k) = k, so the interval ends are the 1-based order statistics
    q = int(p * M + 0.5)
    r = (M - q) // 2 if (M - q) % 2 == 0 else int((M - q + 1) / 2)  # the clause's two cases, written apart
    assert (r, r + q) == (low, high)
    assert symmetric_interval(y, p) == (float(low), float(high))


def test_shortest_interval_is_the_narrowest_of_width_q():
    rng = np.random.default_rng(1)
    y = np.sort(rng.exponential(1.0, 2000))
    lo, hi = shortest_interval(y, 0.95)
    _, q = interval_indices(2000, 0.95)
    widths = [y[r + q] - y[r] for r in range(2000 - q)]
    assert hi - lo == pytest.approx(min(widths))
    assert 0 <= lo < 0.01  # exponential: the shortest 95 % interval starts at the lower end


# ----------------------------------------------------------------------------- an independent linear propagation
def tracker_only_config():
    raw = copy.deepcopy(load_config().source)  # the paper's configuration
    raw["sources"] = {"enable": ["tracker_noise", "repeatability"], "tracker_noise": {"angular_sd": "0 urad"}}
    return parse_config(raw)


@pytest.fixture(scope="module")
def paper_tracker_run():
    cfg = tracker_only_config()
    return cfg, build_scenario(cfg), run(cfg, trials=1536, attribution_trials=0)


def test_per_point_u_agrees_with_an_independent_linear_propagation(paper_tracker_run):
    cfg, sc, res = paper_tracker_run
    u_lin = compensated_field_propagation(sc)
    pts = res.points()
    u_mcm = np.array([p["u"]["value"] for p in pts])
    ratio = u_mcm / u_lin
    # the MCM standard deviation of N trials has a relative standard error of about 1/sqrt(2N) = 1.8 %
    assert np.median(ratio) == pytest.approx(1.0, abs=0.02)
    assert np.abs(ratio - 1).max() < 0.09
    # the GUF of the report (identification covariance, Jacobian of the field) is the same linear propagation
    g = point_lpu(sc)
    u_guf = np.sqrt(np.diagonal(g["cov"], axis1=1, axis2=2))
    assert np.allclose(u_guf, u_lin, rtol=2e-3)
    assert np.abs(g["estimate"]).max() < 1e-2  # um: the truth lies in the model space, noise-free compensation is exact
    # and the figures the paper configuration gives (x 3-8 um, y 7-15 um, z 7-15 um at the verification tool)
    assert 2.5 < u_lin[:, 0].min() and u_lin[:, 0].max() < 9
    assert 6 < u_lin[:, 1].min() and u_lin[:, 1].max() < 16


def test_the_points_output_contract(paper_tracker_run):
    cfg, sc, res = paper_tracker_run
    out = result_json(res)
    pts = out["points"]
    assert len(pts) == len(sc.mesh_rows) == 75
    assert [p["point"] for p in pts] == list(range(75))
    for p, nominal in zip(pts, sc.plan.nominal[sc.mesh_rows]):
        assert p["nominal"]["value"] == pytest.approx(nominal.tolist())  # commanded axis positions, in plan order
        for key in ("nominal", "mean", "u", "guf_u"):
            assert len(p[key]["value"]) == 3
            ureg.Unit(p[key]["unit"])  # any unit pint parses
        assert p["interval"]["coverage"] == 0.95 and len(p["interval"]["low"]) == 3
        assert all(lo < m < hi for lo, m, hi in zip(p["interval"]["low"], p["mean"]["value"], p["interval"]["high"]))
        assert len(p["clause8"]) == 3
    assert out["points_summary"]["u_rms_over_mesh"][1] > out["points_summary"]["u_rms_over_mesh"][0]
    json.dumps(out)  # plain JSON


# ----------------------------------------------------------------------------- logs, budget, decision
@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    from pathlib import Path

    tmp = tmp_path_factory.mktemp("points")
    small = Path(__file__).parent / "data" / "small.toml"
    res = execute(small, trials=96, block=16, attribution_trials=48, log_path=tmp / "run.mcap")
    return tmp, res


def test_replay_rebuilds_every_point_exactly(logged):
    tmp, res = logged
    again = replay(tmp / "run.mcap")
    assert again.points() == res.points()
    assert result_json(again)["points_summary"] == result_json(res)["points_summary"]


def test_per_point_budget_adds_up(logged):
    _, res = logged
    pb = res.budget["points"]
    assert sum(r["share"] for r in pb["rows"]) + pb["interaction_share"] == pytest.approx(1.0)
    assert abs(pb["interaction_share"]) < 0.1  # independent sources, nearly linear model
    assert all("sensitivity" not in r for r in pb["rows"])  # none is defined for a source that perturbs many inputs
    # the total of the budget run (first 48 trials) and the run's own u agree within their Monte Carlo scatter
    u_run = np.sqrt((np.array([p["u"]["value"] for p in res.points()]) ** 2).mean(axis=0))
    assert np.allclose(pb["total"]["u_rms_over_mesh"], u_run, rtol=0.35)


def test_the_decision_names_its_rule_and_counts_every_point_axis(logged):
    _, res = logged
    pts = res.points()
    lo = np.array([p["interval"]["low"] for p in pts])
    hi = np.array([p["interval"]["high"] for p in pts])
    wide = conformance(res, float(np.abs(np.concatenate([lo, hi])).max()) + 1.0)["per_point"]
    assert wide["conforming"] == wide["of"] == lo.size and wide["verdict"] == "conforms"
    assert wide["scope"] == "per point"
    tight = conformance(res, 1e-3)
    assert tight["scope"] == "machine" and tight["verdict"] == "does not conform"
    tight = tight["per_point"]
    assert tight["conforming"] == 0 and tight["verdict"] != "conforms"
    assert "ISO 14253-1" in tight["rule"] and tight["U_unit"] == "um"
    T = 20.0
    mid = conformance(res, T)["per_point"]
    assert mid["conforming"] == int(((lo >= -T) & (hi <= T)).sum())  # counted here independently
    mx = conformance(res, 1e6, "max")
    assert mx["verdict"] == "conforms" and "compensation_max" in mx["characteristic"]


def test_report_command_with_a_tolerance(logged):
    tmp, _ = logged
    r = CliRunner().invoke(main, ["report", str(tmp / "run.mcap"), "--out", str(tmp / "rep"), "--tolerance", "30 um",
                                  "--characteristic", "max"])
    assert r.exit_code == 0, r.output
    md = (tmp / "rep" / "report.md").read_text()
    assert "Characteristic: largest 3-D error over the mesh" in md
    r = CliRunner().invoke(main, ["report", str(tmp / "run.mcap"), "--out", str(tmp / "rep2"), "--tolerance", "-3 um"])
    assert r.exit_code == 2 and "--tolerance" in r.output
