"""Compensation tables a controller loads as intended (issue 32) and --check's verdicts (issue 29).

The reference point (table zero), the equidistant steps the Siemens tables need, the documented limits of each
control refused with one line, the Siemens $AN_CEC sign as an explicit choice that --check applies, the
Heidenhain file names; the one-sided plan that raised a traceback, and the verdict per axis with --strict.
The real-controller round trip is tests/test_controller_linuxcnc.py (marker ``controller``).
"""

from __future__ import annotations

import dataclasses
import json
import re
from decimal import Decimal

import numpy as np
import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.compensate import (CompensationError, build_table, check_export, export, find_exporter, grid,
                                 verdict)
from mtbudget.recording import read_recording

AXES = "xyz"


def one_line_error(args, tmp_path):
    res = CliRunner().invoke(main, ["compensate", "--example", "null", "--out", str(tmp_path / "t.out"), *args])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), res.output
    return lines[0]


def with_options(table, **options):
    return dataclasses.replace(table, options=dict(options))


# ----------------------------------------------------------------------------- issue 29: the one-sided plan
@pytest.fixture(scope="module")
def one_sided(tmp_path_factory):
    """`mtbudget simulate` of the built-in default: its plan approaches Z from one side only."""
    out = tmp_path_factory.mktemp("sim") / "sim1"
    res = CliRunner().invoke(main, ["simulate", "--no-identify", "--out", str(out)])
    assert res.exit_code == 0, res.output
    rec = read_recording(out)
    assert set(np.unique(rec.plan.direction[:, 2])) == {1}  # the case of the issue
    return out


def test_check_of_a_plan_approaching_from_one_side_has_no_traceback(one_sided, tmp_path):
    """Issue 29: `simulate --out sim1 && compensate sim1 --format linuxcnc --out f --check` raised
    'zero-size array to reduction operation maximum' (the model's ISO 230-2 figures at no targets)."""
    res = CliRunner().invoke(main, ["compensate", str(one_sided), "--format", "linuxcnc", "--out",
                                    str(tmp_path / "f"), "--check", "--json"])
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    assert res.exit_code == 0, res.output

    body = json.loads(res.stdout)
    z = body["iso230_2"]["z"]
    assert z["recording"]["figures"] == {} and "not bidirectional" in z["recording"]["note"]
    # the model's figures are there, at every target of the recording, without a reversal
    targets = np.unique(read_recording(one_sided).plan.nominal[:, 2])
    assert z["model"]["targets_mm"] == pytest.approx(targets) and z["model"]["figures"]["B"] == 0.0
    assert set(body["check"]["axes"]["z"]) >= {"verdict", "max_abs_before_um"}
    # the text says the reversal was not measured; it never prints a measured-looking 0.00 for Z
    text = CliRunner().invoke(main, ["compensate", str(one_sided), "--format", "linuxcnc", "--out",
                                     str(tmp_path / "g")]).output
    zline = next(ln for ln in text.splitlines() if ln.startswith("  Z: "))
    assert "reversal B not measured (the recording approaches its targets from one side only" in zline, zline
    zmodel = next(ln for ln in text.splitlines() if ln.startswith("  Z model"))
    assert "B not measured" in zmodel and "B   0.00" not in zmodel and "s = the stated repeatability" in zmodel


# ----------------------------------------------------------------------------- issue 29: verdicts, --strict
def test_verdict_rule():
    z_ok = np.zeros(20)
    assert verdict(10.0, 2.0, z_ok) == "improved"
    assert verdict(3.3, 10.1, z_ok) == "worse"
    z_bad = np.r_[np.zeros(18), 3.0, 3.0]  # 90 % within 2u < 95 %
    assert verdict(10.0, 2.0, z_bad) == "under-covered"
    assert verdict(3.3, 10.1, z_bad) == "worse"  # worse wins
    assert verdict(5.0, 5.0 + 0.04, z_ok, rounding=0.05) == "improved"  # within the format's rounding


def test_check_ends_with_a_verdict_per_axis_and_strict_fails_when_one_gets_worse(one_sided, tmp_path):
    args = ["compensate", str(one_sided), "--format", "linuxcnc", "--out", str(tmp_path / "f"), "--check"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    last = res.output.strip().splitlines()[-1]
    assert last.startswith("verdict: ")
    found = dict(re.findall(r"\b([XYZ]) (improved|worse|under-covered)\b", last))
    assert set(found) == {"X", "Y", "Z"}
    # each verdict against the ISO 230-2 E printed on the axis' line (E before -> after), recomputed here
    for a in "XYZ":
        line = next(ln for ln in res.output.splitlines() if ln.startswith(f"  {a}: before"))
        e_before, e_after = map(float, re.search(r"E ([\d.]+) -> ([\d.]+)", line).groups())
        within = float(re.search(r"within 2u (\d+)%", line).group(1)) / 100
        want = "worse" if e_after > e_before else ("under-covered" if within < 0.95 else "improved")
        assert found[a] == want, (a, line)
    assert "worse" in found.values()  # the case: Z, 3.3 -> 10.3 um
    strict = CliRunner().invoke(main, [*args, "--strict"])
    assert strict.exit_code == 1 and strict.output.strip().splitlines()[-1] == last


def test_strict_passes_when_nothing_gets_worse(tmp_path):
    res = CliRunner().invoke(main, ["compensate", "--example", "null", "--format", "linuxcnc", "--out",
                                    str(tmp_path / "f.comp"), "--check", "--strict"])
    assert res.exit_code == 0 and "worse" not in res.output.strip().splitlines()[-1].split("(")[0], res.output


# ----------------------------------------------------------------------------- the reference point
def test_tables_are_zero_at_the_reference_point(null):
    rec, default = null
    ref = {"x": 1010.0, "y": 300.0, "z": 240.0}  # x and z between grid points
    table = build_table(rec, 50.0, reference_point=ref)
    for a in AXES:
        t, t0 = table.axes[a], default.axes[a]
        assert t.zero_at == ref[a]
        # zero where the controller interpolates the table at the reference point, with no uncertainty there
        assert np.interp(ref[a], t.positions, t.deviation) == pytest.approx(0.0, abs=1e-9)
        # the same table as the default (zero at the first point) shifted by a constant: its value at ref
        np.testing.assert_allclose(t.deviation, t0.deviation - np.interp(ref[a], t0.positions, t0.deviation),
                                   atol=1e-9)
        assert t.reversal == t0.reversal
    for c in table.cross.values():
        assert np.interp(ref[c.axis], c.positions, c.deviation) == pytest.approx(0.0, abs=1e-9)
        c0 = default.cross[c.iso]
        np.testing.assert_allclose(c.deviation, c0.deviation - np.interp(ref[c.axis], c0.positions, c0.deviation),
                                   atol=1e-9)
    assert table.axes["y"].u[np.searchsorted(table.axes["y"].positions, 300.0)] == pytest.approx(0.0, abs=1e-9)


def test_the_default_reference_is_the_machine_zero_held_at_the_table_end(null):
    rec, table = null
    for a in AXES:
        t = table.axes[a]
        assert t.positions[0] > 0 and t.zero_at == t.positions[0] and t.deviation[0] == 0.0
    assert table.reference_point == {"x": 0.0, "y": 0.0, "z": 0.0}
    assert any("reference point of X (0 mm) is outside its table" in n for n in table.notes)


def test_check_with_a_reference_inside_the_range(null, tmp_path):
    rec, _ = null
    table = build_table(rec, 50.0, reference_point={"x": 1000.0, "y": 275.0})
    ex = find_exporter("linuxcnc")
    check = check_export(table, rec, ex, export(table, ex, tmp_path / "t.comp"))
    assert not check.get("mismatch")
    for a, c in check["axes"].items():
        i = int(np.argmin(np.abs(c.positions - table.axes[a].zero_at)))
        assert c.positions[i] == table.axes[a].zero_at
        assert 0.5 * (c.after[0, i] + c.after[1, i]) == pytest.approx(0.0, abs=1e-9)
        assert c.verdict == "improved"


@pytest.mark.parametrize("value, message", [
    ("q=5 mm", "AXIS=LENGTH with AXIS one of x, y, z"),
    ("x=5 s", "is not a quantity of dimension [length]"),
    ("x", "AXIS=LENGTH"),
])
def test_bad_reference_is_one_line(tmp_path, value, message):
    assert message in one_line_error(["--format", "linuxcnc", "--reference", value], tmp_path)


# ----------------------------------------------------------------------------- equidistant steps
@pytest.mark.parametrize("lo, hi, step", [(0.0, 1000.0, 33.0), (800.0, 1200.0, 50.0), (-12.3456789, 987.6543, 7.7),
                                          (100.0, 100.4, 0.3)])
def test_grid_steps_divide_the_range_exactly_on_whole_micrometres(lo, hi, step):
    g = grid(lo, hi, step)
    um = g * 1000
    assert np.allclose(um, np.rint(um), atol=1e-6)
    d = np.diff(np.rint(um))
    assert np.all(d == d[0]) and d[0] <= step * 1000
    assert g[0] <= lo < g[0] + 1e-3 and hi <= g[-1] < hi + len(g) * 1e-3  # covers the range, beyond by < n um
    assert len(g) - 1 == int(np.ceil((hi - lo) / step - 1e-9))


def test_siemens_step_printed_so_that_max_minus_min_over_step_is_an_integer(null, tmp_path):
    rec, _ = null
    table = with_options(build_table(rec, 33.0), siemens_cec_sign="error")  # 400 mm / 33 mm: a repeating step
    eec, cec = export(table, find_exporter("siemens-840d"), tmp_path / "t.ini")
    for path, prefix in ((eec, "AA_ENC_COMP"), (cec, "AN_CEC")):
        text = path.read_text()
        found = 0
        for idx, step in re.findall(rf"^\${prefix}_STEP\[([^\]]+)\]=(\S+)$", text, flags=re.M):
            lo = Decimal(re.search(rf"^\${prefix}_MIN\[{re.escape(idx)}\]=(\S+)$", text, flags=re.M).group(1))
            hi = Decimal(re.search(rf"^\${prefix}_MAX\[{re.escape(idx)}\]=(\S+)$", text, flags=re.M).group(1))
            n = (hi - lo) / Decimal(step)
            assert n == n.to_integral_value(), (idx, lo, hi, step)
            # and the table has exactly n + 1 values
            pattern = (rf"^\$AA_ENC_COMP\[0,\d+,{idx.split(',')[-1]}\]=" if prefix == "AA_ENC_COMP"
                       else rf"^\$AN_CEC\[{idx},\d+\]=")
            assert len(re.findall(pattern, text, flags=re.M)) == int(n) + 1
            found += 1
        assert found >= 3
    assert "CHANDATA(1)" in eec.read_text() and "CHANDATA(1)" in cec.read_text()


def test_check_refuses_a_siemens_table_whose_step_does_not_divide_the_range(null, tmp_path):
    rec, table = null
    table = with_options(table, siemens_cec_sign="error")
    ex = find_exporter("siemens-840d")
    eec, cec = export(table, ex, tmp_path / "t.ini")
    eec.write_text(re.sub(r"(\$AA_ENC_COMP_STEP\[0,AX1\]=)\S+", r"\g<1>33.333333", eec.read_text()))
    with pytest.raises(CompensationError, match=r"\(MAX - MIN\) / STEP .* is not an integer"):
        check_export(table, rec, ex, [eec, cec])


# ----------------------------------------------------------------------------- the Siemens $AN_CEC sign
def test_siemens_needs_an_explicit_cec_sign(tmp_path):
    line = one_line_error(["--format", "siemens-840d"], tmp_path)
    assert "needs --siemens-cec-sign error|correction" in line
    assert "needs --siemens-cec-sign" in one_line_error(["--format", "siemens-828d"], tmp_path)


@pytest.mark.parametrize("sign", ["error", "correction"])
def test_check_applies_the_declared_cec_sign_and_a_wrong_one_fails(null, tmp_path, sign):
    rec, table = null
    table = with_options(table, siemens_cec_sign=sign)
    ex = find_exporter("siemens-840d")
    eec, cec = export(table, ex, tmp_path / "t.ini")
    text = cec.read_text()
    assert f"--siemens-cec-sign {sign}" in text and "NO SIEMENS TEXT FOUND STATES THE $AN_CEC SIGN" in text
    assert "MD32450 $MA_BACKLASH[0,AXi] = 0" in text
    # the entry of EYX's first non-zero point: the error (ISO deviation) or minus it, in mm
    c = table.cross["EYX"]
    k = next(k for k, ln in enumerate(re.findall(r"^; table (\d+): (\S+)", text, flags=re.M)) if ln[1] == "EYX:")
    i = int(np.argmax(np.abs(c.deviation)))
    entry = float(re.search(rf"^\$AN_CEC\[{k},{i}\]=(\S+)$", text, flags=re.M).group(1))
    assert entry == pytest.approx((1 if sign == "error" else -1) * c.deviation[i] * 1e-3, abs=1e-6)
    good = check_export(table, rec, ex, [eec, cec])
    assert not good.get("mismatch") and all(x.verdict != "worse" for x in good["cross"].values())
    # the same files checked as if the control used the other sign: --check sees it
    other = with_options(table, siemens_cec_sign="correction" if sign == "error" else "error")
    bad = check_export(other, rec, ex, [eec, cec])
    assert {"EYX", "EXY"} <= set(bad["mismatch"]) and {"x", "y", "z"} <= set(bad["mismatch"])


# ----------------------------------------------------------------------------- the documented limits, one line each
def test_linuxcnc_limit_256_triplets(tmp_path):
    assert "format 'linuxcnc' accepts at most 256 per axis" in one_line_error(
        ["--format", "linuxcnc", "--step", "1 mm"], tmp_path)


def test_beckhoff_limit_fewer_than_1500_entries(null, tmp_path):
    rec, _ = null
    # X's 400 mm: a step of 0.26685 mm needs 1499 intervals, 1500 entries (refused); 0.26703 mm 1499 (taken)
    line = one_line_error(["--format", "beckhoff-lsec", "--step", "0.26685 mm"], tmp_path)
    assert "1500 entries" in line and "accepts at most 1499" in line
    table = build_table(rec, 0.26703)
    assert max(len(t.positions) for t in table.axes.values()) == 1499
    written = export(table, find_exporter("beckhoff-lsec"), tmp_path / "ok.lis")
    assert "kw.ssfk.kw_nr_max               1499" in written[0].read_text()


def test_beckhoff_limit_sgn16_values(null, tmp_path):
    rec, table = null
    big = dataclasses.replace(table, axes={**table.axes, "x": dataclasses.replace(
        table.axes["x"], deviation=table.axes["x"].deviation + 3300.0)})
    with pytest.raises(CompensationError) as err:
        export(big, find_exporter("beckhoff-lsec"), tmp_path / "t.lis")
    msg = str(err.value)
    assert "\n" not in msg and "SGN16" in msg and "3276.7 um" in msg and not (tmp_path / "t_x.lis").exists()


def test_beckhoff_says_twincat_cnc_only(null, tmp_path):
    rec, table = null
    text = export(table, find_exporter("beckhoff-lsec"), tmp_path / "t.lis")[0].read_text()
    assert "TwinCAT CNC" in text and "not for TwinCAT NC PTP" in text and "lr_param.ssfk = 1" in text


def test_heidenhain_limit_256_entries(tmp_path):
    assert "format 'heidenhain-tnc' accepts at most 256 per axis" in one_line_error(
        ["--format", "heidenhain-tnc", "--step", "1 mm"], tmp_path)


def test_828d_limit_200_points_per_table(tmp_path):
    line = one_line_error(["--format", "siemens-828d", "--siemens-cec-sign", "error", "--step", "1.9 mm"], tmp_path)
    assert "the SINUMERIK 828D takes at most 200 per table" in line


def test_828d_limit_8_tables(null, tmp_path):
    rec, table = null
    table = with_options(table, siemens_cec_sign="error")
    ex = find_exporter("siemens-828d")
    eec, cec = export(table, ex, tmp_path / "t.ini")  # the reversal tables only: 6 of 8
    assert len(set(re.findall(r"^\$AN_CEC_INPUT_AXIS\[(\d+)\]", cec.read_text(), flags=re.M))) == 6
    assert "the cross (sag) tables are left out" in cec.read_text()
    with_cross = type(ex)()
    with_cross.cross = True  # the 840D's twelve tables on an 828D
    with pytest.raises(CompensationError, match=r"12 \$AN_CEC tables; the SINUMERIK 828D has at most 8"):
        export(table, with_cross, tmp_path / "u.ini")
    check = check_export(table, rec, ex, [eec, cec])
    assert not check.get("mismatch") and not check["cross"]


# ----------------------------------------------------------------------------- Heidenhain names and notes
def test_heidenhain_writes_com_files_whatever_out_says(null, tmp_path):
    rec, table = null
    written = export(table, find_exporter("heidenhain-tnc"), tmp_path / "mill.txt")
    assert [p.name for p in written] == ["mill_x.com", "mill_y.com", "mill_z.com", "mill.cma", "mill_notes.txt"]
    cma = written[3].read_text()
    assert all(f"MILL_{a.upper()}.COM" in cma for a in AXES)
    notes = written[4].read_text()
    assert "MANUALplus 620" in notes and "UNVERIFIED" in notes and "MP_backLash to 0" in notes
    check = check_export(table, rec, find_exporter("heidenhain-tnc"), written)
    assert not check.get("mismatch")


def test_linuxcnc_notes_come_after_the_table(null, tmp_path):
    rec, table = null
    text = export(table, find_exporter("linuxcnc"), tmp_path / "m.comp")[0].read_text()
    lines = text.splitlines()
    n = len(table.axes["x"].positions)
    assert all(len(ln.split()) == 3 and not ln.startswith("#") for ln in lines[:n])
    assert all(ln.startswith("# ") for ln in lines[n:]) and "COMP_FILE_TYPE = 1" in text and "BACKLASH = 0" in text
