"""Five-axis results: the frame of the per-point measurand, the rotary angles in every per-point label, and
compensation tables whose check compares what they can carry (the new user's trial on five_axis_cafxyz)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from mtbudget import compensate as C
from mtbudget.config import bundled_config, load_config, parse_config
from mtbudget.model import MeasurementModel
from mtbudget.recording import read_recording, write_recording
from mtbudget.scenario import build_scenario
from mtbudget.simulate import parameters_from_truth, simulate_recording


def five_config(sources):
    raw = copy.deepcopy(load_config(bundled_config("five_axis_cafxyz")).source)
    raw["sources"] = {"enable": list(sources)}
    return parse_config(raw)


# ----------------------------------------------------------------------------- truth.json: the trial's machine
def test_truth_json_holds_the_machine_the_trial_measured(tmp_path):
    """With no noise and only geometric_error_uncertainty drawn, truth.json's errors and pose reproduce every recorded
    point: the machine of that trial, not the configuration's machine without the draw (which misses by um)."""
    sc = build_scenario(five_config(["geometric_error_uncertainty"]))
    rec, truth = simulate_recording(sc, trial=3)
    write_recording(rec, tmp_path / "rec", truth=truth)
    rec = read_recording(tmp_path / "rec")
    truth = json.loads((tmp_path / "rec" / "truth.json").read_text())
    model = MeasurementModel(sc.truth.config, sc.truth.errors, rec.plan)
    theta, pose, _ = parameters_from_truth(truth, model)
    lt = model.predict(theta[None], pose)[0]
    # the recording's 1e-6 mm resolution and the display units' round trip: well below 1 nm
    assert np.abs(lt - rec.lt).max() < 2e-6
    # the configuration's machine alone (what truth.json held before) does not reproduce them
    assert np.abs(model.predict(sc.theta[None], pose)[0] - rec.lt).max() > 5e-4


# ----------------------------------------------------------------------------- compensation: the check's coverage
def test_interpolation_error_is_the_chord_of_a_parabola():
    """Between two entries h apart, the chord of a line with curvature b (e = b x^2) misses by b h^2 / 4 at the
    midpoint: written here for the null example's X positioning, a parabola added through one P2 coefficient."""
    from mtbudget.compensate import identify_recording, interpolation_error
    from mtbudget.config import example_recording

    rec = read_recording(example_recording("null"))
    model, _ = identify_recording(rec)
    errors = model.errors
    theta = np.zeros(len(errors.params))
    j = errors.index("dx(x)[P2]")
    theta[j] = 1e-3  # 1 um of P2 = (3 s^2 - 1) / 2, s = (x - centre) / half: e = 1.5 um s^2 + const
    lo, hi = errors.ranges["x"]
    half = 0.5 * (hi - lo)
    b = 1.5e-3 / half**2  # mm per mm^2
    g = np.linspace(lo, hi, 5)
    h = g[1] - g[0]
    mid = 0.5 * (g[1:] + g[:-1])
    ref = {"x": 0.0, "y": 0.5 * sum(errors.ranges["y"]), "z": 0.5 * sum(errors.ranges["z"])}
    i = interpolation_error(model.config, errors, theta, "x", g, mid, ref, rec.plan.tool[0])
    assert np.abs(np.abs(i) - b * h**2 / 4).max() < 1e-12  # the sign is the chain's (X moves the workpiece on XFYZ)
    assert np.abs(interpolation_error(model.config, errors, theta, "x", g, g, ref, rec.plan.tool[0])).max() < 1e-12


def test_five_axis_tables_are_covered_when_the_truth_holds_only_what_they_carry(tmp_path):
    """The bundled five-axis example simulated with only what a table's u contains (the stated tracker noise and
    repeatability) and the machine's per-verification variation (geometric_error_uncertainty, which is the machine
    and must be in truth.json): the check's coverage is near its nominal 95 % for k = 2, over six simulated
    verifications and every positioning and cross line (siemens-840d carries both).  Before: the truth missed the
    drawn variation (Y, Z 4-6 u off) and the check took the table's u for the error between its entries, where the
    controller's linear interpolation leaves the line's curvature (X 88 % within 2u on a noise-only truth)."""
    sc = build_scenario(five_config(["tracker_noise", "repeatability", "geometric_error_uncertainty"]))
    ex = C.find_exporter("siemens-840d")
    z, verdicts = [], []
    for trial in range(6):
        rec, truth = simulate_recording(sc, trial=trial)
        write_recording(rec, tmp_path / str(trial), truth=truth)
        rec = read_recording(tmp_path / str(trial))
        table = C.build_table(rec, max_degree=2)
        table.options["siemens_cec_sign"] = "error"
        check = C.check_export(table, rec, ex, C.export(table, ex, tmp_path / str(trial) / "comp.ini"))
        assert check["not_in_u"] == []
        for group in ("axes", "cross"):
            for c in check[group].values():
                zz = c.z.ravel()
                z.append(zz[c.u.ravel() > 0])
                verdicts.append(c.verdict)
    z = np.concatenate(z)
    within = np.mean(np.abs(z) <= 2.0)
    assert 0.93 <= within <= 1.0, within
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.25
    assert verdicts.count("under-covered") <= 3, verdicts  # of 54 lines of 13 to 17 points each


def test_check_names_the_sources_the_tables_u_does_not_contain(tmp_path):
    sc = build_scenario(five_config(["tracker_noise", "repeatability", "backlash", "temperature_drift"]))
    rec, truth = simulate_recording(sc, trial=0)
    write_recording(rec, tmp_path / "r", truth=truth)
    rec = read_recording(tmp_path / "r")
    table = C.build_table(rec, max_degree=2)
    ex = C.find_exporter("neutral-json")
    check = C.check_export(table, rec, ex, C.export(table, ex, tmp_path / "r" / "t.json"))
    assert check["not_in_u"] == ["backlash", "temperature_drift"]
    text = C.table_text(table, [], ex, check)
    assert "also drew backlash, temperature_drift: physics the identification does not model" in text
    assert C.check_json(check)["not_in_u"] == ["backlash", "temperature_drift"]


# ----------------------------------------------------------------------------- the frame of the per-point measurand
def small_five(sources=("tracker_noise", "repeatability")):
    """The small CAFXYZ plan of test_fiveaxis_mc with C at 0, 90 and 240 deg (a quarter turn swaps x and y), the
    tracker's angular noise drawn per trial."""
    from test_fiveaxis_mc import small_five_axis

    return small_five_axis(sources, c_angles=("0 deg", "90 deg", "240 deg"), steady_tracker=False)


def table_orientation(a_deg, c_deg):
    """Written here with scipy: CAFXYZ's table (C on A, A about +X on the bed) turned by a about X, then the C table
    by c about its own Z: a table-frame vector in the machine frame is Rx(a) Rz(c) v."""
    from scipy.spatial.transform import Rotation

    return (Rotation.from_rotvec(np.radians(a_deg) * np.array([1.0, 0.0, 0.0])) *
            Rotation.from_rotvec(np.radians(c_deg) * np.array([0.0, 0.0, 1.0]))).as_matrix()


def test_workpiece_rotation_is_the_nominal_chain_s_turn_of_a_tool_offset():
    """machine.workpiece_rotation against scipy (above) and against the nominal chain itself: moving the tool by d in
    the machine frame moves the table-frame point by R^T d (finite difference of machine_points, no error)."""
    from mtbudget.machine import workpiece_rotation

    sc = build_scenario(small_five())
    plan = sc.plan
    R = workpiece_rotation(sc.truth.config, plan.angles)
    deg = {r: np.degrees(v) for r, v in plan.angles.items()}
    want = np.array([table_orientation(a, c) for a, c in zip(deg["a"], deg["c"])])
    assert np.abs(R - want).max() < 1e-12
    model = MeasurementModel(sc.truth.config, sc.truth.errors, plan)
    zero = np.zeros((1, model.n_params))
    base = model.machine_points(zero)[0]
    for k in range(3):
        d = np.zeros(3)
        d[k] = 1.0
        moved = MeasurementModel(sc.truth.config, sc.truth.errors, _shift_tool(plan, d)).machine_points(zero)[0]
        assert np.abs((moved - base) - R[:, k, :]).max() < 1e-9  # row k of R = (R^T e_k)


def _shift_tool(plan, d):
    import dataclasses

    return dataclasses.replace(plan, tool=plan.tool + d)


@pytest.fixture(scope="module")
def five_run(tmp_path_factory):
    from mtbudget.report import run_report
    from mtbudget.report_dcc import write_dcc
    from mtbudget.runner import execute, replay

    folder = tmp_path_factory.mktemp("five")
    execute(small_five(), trials=64, block=16, attribution_trials=32, log_path=folder / "r.mcap")
    res = replay(folder / "r.mcap")
    run_report(res, folder / "rep")
    write_dcc(res, folder / "rep" / "certificate.xml")
    return res, folder


def test_each_point_states_its_frame_and_the_machine_frame_is_its_covariance_turned_by_the_table(five_run):
    """The per-point components are in the table frame and say so; machine_frame is the same covariance turned by the
    table's orientation at the point's pose (computed here with scipy), after the log's round trip (replay)."""
    res, _ = five_run
    pts = res.points()
    assert len(pts) == 72
    for q in pts:
        R = table_orientation(q["angles"]["value"]["a"], q["angles"]["value"]["c"])
        C = np.array(q["covariance"]["value"])
        m = q["machine_frame"]
        assert np.allclose(m["u"], np.sqrt(np.diag(R @ C @ R.T)), rtol=1e-12, atol=1e-12)
        assert np.allclose(m["mean"], R @ np.array(q["mean"]["value"]), atol=1e-12)
        assert q["frame"].startswith("workpiece (table) frame")
    # a point at c = 90 deg: its table-frame x is the machine's Y (A at 0 deg): the u of x there is u(Y)
    q = next(q for q in pts if q["angles"]["value"] == {"a": 0.0, "c": 90.0})
    assert q["machine_frame"]["u"][1] == pytest.approx(q["u"]["value"][0], rel=1e-12)


def test_the_text_report_and_certificate_name_the_frame_and_every_point_s_angles(five_run):
    import xml.etree.ElementTree as ET

    from mtbudget.report import budget_text
    from mtbudget.report_dcc import DCC_NS

    res, folder = five_run
    text = budget_text(res)
    assert "per machine axis" not in text and "per axis of the workpiece (table) frame" in text
    assert "in the machine frame (X, Y, Z at each pose" in text
    md = (folder / "rep" / "report.md").read_text()
    assert "per machine axis" not in md and "u X, Y, Z (machine frame)" in md and "mean x, y, z (table frame)" in md
    root = ET.parse(folder / "rep" / "certificate.xml").getroot()
    names = [el.text for el in root.iter(f"{{{DCC_NS}}}content") if el.text and el.text.startswith("point ")]
    assert len(names) == 72 and len(set(names)) == 72  # the commanded a, c make every label its point's own
    assert all(", a, c = " in n and n.endswith(" deg (commanded)") for n in names)
    assert "e_machine_Y" in (folder / "rep" / "certificate.xml").read_text()
    results = json.loads((folder / "rep" / "results.json").read_text())
    assert results["points_summary"]["frame"].startswith("workpiece (table) frame")
    assert set(results["points"][0]) >= {"angles", "frame", "machine_frame"}


def test_the_posterior_labels_every_point_with_its_angles_and_frame(tmp_path):
    from mtbudget.posterior import posterior_result, posterior_text
    from mtbudget.report import posterior_report
    from mtbudget.report_dcc import write_dcc

    sc = build_scenario(small_five())
    rec, truth = simulate_recording(sc, trial=0)
    write_recording(rec, tmp_path / "rec", truth=truth)
    post = posterior_result(tmp_path / "rec", trials=48, max_degree=1)
    p = post.data
    assert "per machine axis" not in p["measurand"] and "workpiece (table) frame" in p["measurand"]
    labels = set()
    for q in p["points"]:
        ang = q["angles"]["value"]
        labels.add((*q["nominal"]["value"], ang["a"], ang["c"]))
        R = table_orientation(ang["a"], ang["c"])
        assert np.allclose(q["machine_frame"]["mean"], R @ np.array(q["mean"]["value"]), atol=1e-9)
        # a rotation keeps the sum of the variances of the three components
        assert np.sum(np.square(q["machine_frame"]["u"])) == pytest.approx(np.sum(np.square(q["u"]["value"])), rel=1e-9)
    assert len(labels) == len(p["points"]) == 72
    assert "(table frame)" in posterior_text(p)
    md = posterior_report(post, tmp_path / "post")["markdown"].read_text()
    rows = [ln for ln in md.splitlines() if ln.startswith("| ") and "a, c = (" in ln]
    assert len(rows) == 72 and "u X, Y, Z (machine frame)" in md
    # the statement in brief names the frame of its components, the machine frame beside it, as a run's does
    brief = md[md.index("## Statement in brief"):md.index("## Kind of statement")]
    assert "workpiece (table) frame" in brief and "machine\\_frame" in brief and "per machine axis" not in brief
    post.data["report"] = {"date": "2026-11-20"}  # a certificate needs the measurement's date
    xml = write_dcc(post, tmp_path / "post" / "certificate.xml").read_text()
    assert "e_machine_Y" in xml and "workpiece (table) frame" in xml


def test_U_and_the_decision_say_their_frame_and_the_machine_frame_says_its_assumption(five_run):
    """U_max is the largest of the table-frame components and says so, with the machine frame's largest U (from
    machine_frame's u, computed here) beside it; a decision names the frame it is decided in (a +-T box is not the
    same box turned); the DCC's machine-frame values of a run carry U = k u with the normal's coverage for that k,
    and say that it is assumed (the Monte Carlo gave them no interval in that frame)."""
    import xml.etree.ElementTree as ET

    from mtbudget.budget import conformance
    from mtbudget.report import headline
    from mtbudget.report_dcc import SI_NS

    res, folder = five_run
    h = headline(res, 20.0)
    pts = res.points()
    um = max(max(q["machine_frame"]["u"]) for q in pts)
    assert "the largest over the mesh points and axes of the workpiece (table) frame" in h["U_text"]
    assert h["U_machine_max"] == pytest.approx(2 * um, abs=0.51 * 10 ** -h["decimals"])
    assert f"{h['U_machine_max']:.{h['decimals']}f}" in h["U_text"].split("machine's X, Y, Z")[1]
    conf = conformance(res, 20.0)
    assert "x, y, z of the workpiece (table) frame" in conf["characteristic"]
    assert "x, y, z of the workpiece (table) frame" in conf["per_point"]["characteristic"]
    root = ET.parse(folder / "rep" / "certificate.xml").getroot()
    reals = [r for r in root.iter(f"{{{SI_NS}}}real") if r.find(f"{{{SI_NS}}}label").text.startswith("e_machine_")]
    assert len(reals) == 3 * len(pts)
    from scipy.stats import norm

    p2 = round(2 * norm.cdf(2.0) - 1, 4)  # the normal's coverage of +-2 sigma: the assumption the names state
    assert all(r.find(f".//{{{SI_NS}}}coverageFactor").text == "2" and
               float(r.find(f".//{{{SI_NS}}}coverageProbability").text) == p2 == 0.9545 for r in reals)
    names = [e.text for e in root.iter() if e.text and "machine frame at this pose" in e.text]
    assert names and all("normal distribution assumed" in t for t in names)


def test_a_log_written_before_the_machine_frame_was_logged_gets_it_from_its_configuration(five_run):
    """A five-axis log without workpiece_to_machine (written before it was logged) states the machine frame all the
    same, computed from its logged configuration and commanded angles: the same as a new log's to round-off (the
    measurand text promises it)."""
    from mtbudget.runlog import read_runlog
    from mtbudget.runner import logged_to_machine

    res, folder = five_run
    h = dict(read_runlog(folder / "r.mcap").header)
    assert h.get("workpiece_to_machine")
    old = {k: v for k, v in h.items() if k != "workpiece_to_machine"}
    assert np.allclose(logged_to_machine(old), np.asarray(h["workpiece_to_machine"]), atol=1e-15, rtol=0)
    three = {k: v for k, v in old.items() if k != "commanded_angles"}
    assert logged_to_machine(three) is None
