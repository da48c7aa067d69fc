"""Siemens 840D and Heidenhain TNC compensation files (issue 17), the compensated machine's residual against U,
ISO 230-1 names of parameters, and the HTML report's table cells.

The controller files are read back by parsers written here from the formats' documentation
(docs/compensation.md cites it), and their values are compared with the identified model evaluated
here through the kinematic chain, not with the exporters' code path.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from mtbudget.compensate import build_table, check_export, export, find_exporter, iso230_2
from mtbudget.config import example_recording
from mtbudget.machine import AXIS_INDEX, ChainInputs, chain
from mtbudget.model import iso_name, iso_parameter
from mtbudget.recording import read_recording

AXES = "xyz"


# ----------------------------------------------------------------------------- the model, evaluated here
def model_lines(table):
    """(axis, direction) -> deviation (um) of the identified model on each table's line, relative to the first
    grid point, through the chain; the X line defines X, X and Y the XY plane (least-squares slopes of EYX,
    EZX, EZY removed by a small rotation), as ISO 230-1 references squareness."""
    model, theta = table.model, table.theta
    dev = {}
    for a in AXES:
        t = table.axes[a]
        pts = np.zeros((len(t.positions), 3))
        for b in AXES:
            pts[:, AXIS_INDEX[b]] = t.positions if b == a else t.reference[b]
        inp = ChainInputs(pts, np.tile(t.tool, (len(pts), 1)))
        d = (chain(model.config, model.errors, theta[None], inp) -
             chain(model.config, model.errors, np.zeros((1, model.n_params)), inp))[0] * 1e3
        for b in AXES:
            dev[(a, b)] = (t.positions, d[:, AXIS_INDEX[b]] - d[0, AXIS_INDEX[b]])
    wz = np.polyfit(*dev[("x", "y")], 1)[0]
    wy = -np.polyfit(*dev[("x", "z")], 1)[0]
    wx = np.polyfit(*dev[("y", "z")], 1)[0]
    # small rotation w: the deviation of line a in direction b changes by (w x e_a)_b (p - p0)
    rot = {("x", "y"): wz, ("x", "z"): -wy, ("y", "x"): -wz, ("y", "z"): wx, ("z", "x"): wy, ("z", "y"): -wx}
    return {k: (p, v - rot.get(k, 0.0) * (p - p[0])) for k, (p, v) in dev.items()}


def reversal_by_hand(rec, table, a):
    """Mean over targets of x_up - x_down of the recording's deviations, from iso230_2's per-target means."""
    r = table.iso230_2[a]["recording"]
    return float(np.mean(r.mean_up - r.mean_down)) if r.figures else 0.0


# ----------------------------------------------------------------------------- Siemens
def parse_siemens(text):
    """SINUMERIK programs: '%_N_..._INI' first, ';' comments, '$NAME[i,j]=value' assignments, M17 last."""
    lines = [ln.split(";")[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    assert lines[0].startswith("%_N_") and lines[0].endswith("_INI") and lines[-1] == "M17"
    out = {}
    for ln in lines[1:-1]:
        if ln == "CHANDATA(1)":
            continue
        m = re.fullmatch(r"\$([A-Z_]+)\[([^\]]+)\]=(\S+)", ln)
        assert m, ln
        out[(m.group(1), tuple(i.strip() for i in m.group(2).split(",")))] = m.group(3)
    return out


def siemens_table(kv, values_key, index):
    """Values (mm) and their positions MIN + N STEP of one equidistant table, N from 0 to (MAX - MIN)/STEP."""
    step = float(kv[(values_key + "_STEP", index)])
    lo, hi = float(kv[(values_key + "_MIN", index)]), float(kv[(values_key + "_MAX", index)])
    n = round((hi - lo) / step)
    assert abs(lo + n * step - hi) < 1e-6
    if values_key == "AA_ENC_COMP":
        vals = [float(kv[(values_key, (index[0], str(i), index[1]))]) for i in range(n + 1)]
    else:
        vals = [float(kv[(values_key, (index[0], str(i)))]) for i in range(n + 1)]
    return lo + step * np.arange(n + 1), np.array(vals)


@pytest.mark.parametrize("cec_sign", ["error", "correction"])
def test_siemens_tables_read_back_against_the_model(tmp_path, reversal, cec_sign):
    rec, table = reversal
    table.options["siemens_cec_sign"] = cec_sign
    eec, cec = export(table, find_exporter("siemens-840d"), tmp_path / "comp.ini")
    sgn = 1.0 if cec_sign == "error" else -1.0  # a $AN_CEC entry: the error, or the correction = -error
    assert eec.name == "comp_eec.ini" and cec.name == "comp_cec.ini"
    lec, sag = parse_siemens(eec.read_text()), parse_siemens(cec.read_text())
    lines = model_lines(table)
    names = {"AX1": "x", "AX2": "y", "AX3": "z"}
    for ax, a in names.items():
        pos, val = siemens_table(lec, "AA_ENC_COMP", ("0", ax))
        assert lec[("AA_ENC_COMP_IS_MODULO", ("0", ax))] == "0"
        p_model, e_model = lines[(a, a)]
        np.testing.assert_allclose(pos, p_model, atol=1e-6)
        # entry = the measured error in mm (a positive value moves the axis in the negative direction)
        np.testing.assert_allclose(val * 1e3, e_model, atol=2e-3)
    tables = sorted({int(k[1][0]) for k in sag})
    seen = {}
    for t in tables:
        i = (str(t),)
        # the K3 manual's examples write the axis in brackets: $AN_CEC_INPUT_AXIS[0]=(AX2)
        assert sag[("AN_CEC_INPUT_AXIS", i)].startswith("(") and sag[("AN_CEC_OUTPUT_AXIS", i)].endswith(")")
        a, b = names[sag[("AN_CEC_INPUT_AXIS", i)].strip("()")], names[sag[("AN_CEC_OUTPUT_AXIS", i)].strip("()")]
        direction = int(sag[("AN_CEC_DIRECTION", i)])
        assert sag[("AN_CEC_IS_MODULO", i)] == "0" and sag[("AN_CEC_MULT_BY_TABLE", i)] == "0"
        pos, val = siemens_table(sag, "AN_CEC", i)
        seen[(a, b, direction)] = (pos, sgn * val * 1e3)
    for a in AXES:  # the reversal: + direction B/2, - direction -B/2, B of the recording (x_up - x_down)
        B = reversal_by_hand(rec, table, a)
        np.testing.assert_allclose(seen[(a, a, 1)][1], B / 2, atol=2e-3)
        np.testing.assert_allclose(seen[(a, a, -1)][1], -B / 2, atol=2e-3)
        for b in AXES:
            if b != a:
                np.testing.assert_allclose(seen[(a, b, 0)][0], lines[(a, b)][0], atol=1e-6)
                np.testing.assert_allclose(seen[(a, b, 0)][1], lines[(a, b)][1], atol=2e-3)
    assert len(seen) == 12
    # the simulated reversal of Y: the axis stops 4 um short from either side, B = -8 um
    assert seen[("y", "y", 1)][1][0] == pytest.approx(-4.0, abs=3.0)


# ----------------------------------------------------------------------------- Heidenhain
def parse_tnc_table(text):
    """A TNC table: 'BEGIN name [MM]', a line of column names, rows of values, '[END]'."""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert lines[0].startswith("BEGIN ") and lines[-1] == "[END]"
    head = lines[1].split()
    rows = [dict(zip(head, ln.split())) for ln in lines[2:-1]]
    assert all(len(r) == len(head) for r in rows)
    return lines[0].split(), head, rows


def test_heidenhain_tables_read_back_against_the_model(tmp_path, reversal):
    rec, table = reversal
    written = export(table, find_exporter("heidenhain-tnc"), tmp_path / "mill.com")
    assert [p.name for p in written] == ["mill_x.com", "mill_y.com", "mill_z.com", "mill.cma", "mill_notes.txt"]
    begin, head, rows = parse_tnc_table(written[3].read_text())
    assert head == ["NR", "X", "Y", "Z", "ACTIVE"] and len(rows) == 1 and rows[0]["ACTIVE"] == "*"
    lines = model_lines(table)
    for a in AXES:
        fname = rows[0][a.upper()]
        begin, head, com = parse_tnc_table((tmp_path / fname.lower()).read_text())
        assert begin == ["BEGIN", fname, "MM"] and head[:2] == ["NR", "AXISPOS"] and head[-1] == "BACKLASH"
        assert len(com) <= 256 and [int(r["NR"]) for r in com] == list(range(len(com)))
        pos = np.array([float(r["AXISPOS"]) for r in com])
        np.testing.assert_allclose(pos, lines[(a, a)][0], atol=1e-4)
        B = reversal_by_hand(rec, table, a)
        fwd = np.array([float(r[a.upper()]) for r in com]) * 1e3
        back = np.array([float(r["BACKLASH"]) for r in com]) * 1e3
        # the axis' own column: the error moving in +; BACKLASH: the error measured moving in -  (0.1 um resolution)
        np.testing.assert_allclose(fwd, lines[(a, a)][1] + B / 2, atol=0.05 + 2e-3)
        np.testing.assert_allclose(back, lines[(a, a)][1] - B / 2, atol=0.05 + 2e-3)
        for b in AXES:
            if b != a:
                v = np.array([float(r[b.upper()]) for r in com]) * 1e3
                np.testing.assert_allclose(v, lines[(a, b)][1], atol=0.05 + 2e-3)


# ----------------------------------------------------------------------------- the round trip
@pytest.mark.parametrize("fmt", ["siemens-840d", "heidenhain-tnc"])
def test_round_trip_positioning_and_sag(tmp_path, null, fmt):
    rec, table = null
    table.options["siemens_cec_sign"] = "error"
    ex = find_exporter(fmt)
    check = check_export(table, rec, ex, export(table, ex, tmp_path / f"t{ex.suffix}"))
    assert not check.get("mismatch")
    for a, c in check["axes"].items():
        d = c.to_dict()
        assert d["max_abs_after_um"] < 0.3 * d["max_abs_before_um"] and d["within_2u"] >= 0.9, (a, d)
    assert set(check["cross"]) == {"EYX", "EZX", "EXY", "EZY", "EXZ", "EYZ"}
    for k, c in check["cross"].items():
        d = c.to_dict()
        assert d["max_abs_z"] < 3.0 and d["within_2u"] >= 0.9, (k, d)
    before = sum(c.to_dict()["max_abs_before_um"] for c in check["cross"].values())
    after = sum(c.to_dict()["max_abs_after_um"] for c in check["cross"].values())
    assert after < 0.5 * before


def test_round_trip_catches_a_siemens_file_with_the_wrong_sign(tmp_path, null):
    rec, table = null
    table.options["siemens_cec_sign"] = "error"
    ex = find_exporter("siemens-840d")
    eec, cec = export(table, ex, tmp_path / "t.ini")
    text = cec.read_text()
    flipped = re.sub(r"^(\$AN_CEC\[\d+,\d+\]=)(-?)", lambda m: m.group(1) + ("" if m.group(2) else "-"), text, flags=re.M)
    cec.write_text(flipped)
    check = check_export(table, rec, ex, [eec, cec])
    assert {"EYX", "EZX", "EXY", "EZY", "EXZ", "EYZ"} <= set(check["mismatch"])
    assert max(c.to_dict()["max_abs_z"] for c in check["cross"].values()) > 3


# ----------------------------------------------------------------------------- residual against U
def test_residual_uncertainty_against_a_monte_carlo_of_the_stated_noise(null):
    """u of the residual (U/2) vs the spread of the residuals over 300 re-identifications of the fitted points
    plus noise drawn from the stated point covariances (the whitener's inverse)."""
    from mtbudget.identify import Noise, Strategy, identify

    rec, table = null
    model = table.model
    from mtbudget.compensate import identify_recording

    _, res = identify_recording(rec)
    P = model.predict(res.theta[0], res.pose[0])[0]
    L = np.linalg.inv(res.whitener[0])
    rng = np.random.default_rng(170)
    z = rng.standard_normal((300, len(P), 3))
    meas = P[None] + np.einsum("mij,nmj->nmi", L, z)
    mc = identify(model, meas, Noise.of(rec), Strategy.one_phase())
    sd = mc.residual_machine.std(axis=0) * 1e3  # (M, 3) um
    for a in AXES:
        u = table.residual[a].U / 2
        ratio = sd[:, AXIS_INDEX[a]] / u
        assert abs(np.median(ratio) - 1) < 0.05, a
        assert np.all(np.abs(ratio - 1) < 0.3), a


def test_residual_summary_counts(null):
    _, table = null
    for a, r in table.residual.items():
        d = r.summary()
        assert d["k"] == 2.0 and d["points"] == len(r.residual)
        assert d["within_U"] == pytest.approx(np.mean(np.abs(r.residual) <= r.U))
        assert 0.85 < d["within_U"] <= 1.0  # the null example: residuals consistent with the stated noise


# ----------------------------------------------------------------------------- ISO 230-2, one more hand computation
def test_iso230_2_four_targets_one_side_only_left_out():
    """Targets 10, 20, 35, 60 mm; 35 is approached only in + (left out); counts 2/3 up, 3/2 down; deviation =
    actual - target."""
    target = {10: ([10.002, 10.004], [9.999, 10.001, 10.000]),
              20: ([20.000, 20.003, 20.000], [19.996, 19.998]),
              35: ([35.001, 35.002], []),
              60: ([59.990, 59.994], [59.995, 59.999, 59.997])}
    t, d, x = [], [], []
    for pos, (up, down) in target.items():
        for v in up:
            t, d, x = t + [pos], d + [1], x + [(v - pos) * 1e3]
        for v in down:
            t, d, x = t + [pos], d + [-1], x + [(v - pos) * 1e3]
    r = iso230_2("x", t, d, x)
    assert list(r.targets) == [10, 20, 60] and "35 mm" in r.note
    up = {10: [2, 4], 20: [0, 3, 0], 60: [-10, -6]}
    dn = {10: [-1, 1, 0], 20: [-4, -2], 60: [-5, -1, -3]}
    mu = np.array([np.mean(up[k]) for k in (10, 20, 60)])
    md = np.array([np.mean(dn[k]) for k in (10, 20, 60)])
    su = np.array([np.std(up[k], ddof=1) for k in (10, 20, 60)])
    sd = np.array([np.std(dn[k], ddof=1) for k in (10, 20, 60)])
    f = r.figures
    assert f["B"] == pytest.approx(np.max(np.abs(mu - md)), abs=1e-9)
    assert f["B_mean"] == pytest.approx(np.mean(mu - md), abs=1e-9)
    assert f["M"] == pytest.approx(np.ptp((mu + md) / 2), abs=1e-9)
    assert f["E"] == pytest.approx(max(mu.max(), md.max()) - min(mu.min(), md.min()), abs=1e-9)
    assert f["R_up"] == pytest.approx(4 * su.max(), abs=1e-9) and f["R_down"] == pytest.approx(4 * sd.max(), abs=1e-9)
    assert f["R"] == pytest.approx(np.max(np.maximum(2 * su + 2 * sd + np.abs(mu - md), np.maximum(4 * su, 4 * sd))),
                                   abs=1e-9)
    assert f["A"] == pytest.approx(max((mu + 2 * su).max(), (md + 2 * sd).max()) -
                                   min((mu - 2 * su).min(), (md - 2 * sd).min()), abs=1e-9)


# ----------------------------------------------------------------------------- names, report
def test_iso_parameter_names():
    assert iso_name("ez(y)") == "ECY"  # the yaw of Y, not its roll
    assert iso_name("ey(z)") == "EBZ" and iso_name("ex(x)") == "EAX"
    assert iso_parameter("dy(x)[P2]") == "EYX[P2]" and iso_parameter("ez(z)[P0]") == "ECZ[P0]"
    assert iso_parameter("sxz") == "EB(0X)Z" and iso_parameter("D") == "D"


def test_html_conditions_row_keeps_a_pipe_in_a_name(tmp_path):
    from mtbudget.report import md_escape, write_html

    md = ["## Conditions", "", "| item | value |", "| --- | --- |",
          f"| configuration | {md_escape('a|b.toml')} ({md_escape('mill | left')}) |", "| machine | XFYZ |"]
    write_html(md, tmp_path, tmp_path / "r.html", "t")
    html = (tmp_path / "r.html").read_text()
    row = re.search(r"<tr><td>configuration</td>(.*?)</tr>", html).group(1)
    assert row == "<td>a|b.toml (mill | left)</td>"


def test_compensation_report_writes_markdown_html_and_figure(tmp_path, null):
    from mtbudget.report import compensation_report

    _, table = null
    out = compensation_report(table, tmp_path)
    md = out["markdown"].read_text()
    assert "against its uncertainty" in md and "U (k = 2)" in md
    for a in "XYZ":
        assert re.search(rf"^\| {a} \| 300 \|", md, flags=re.M)
    assert out["figure"].is_file() and "data:image/png;base64" in out["html"].read_text()
