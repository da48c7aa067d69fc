"""Compensation tables (issue 17): exporters as plugins, ISO 230-1 names, ISO 230-2 figures, the round trip.

Every controller file is read back here by a parser written in this test from the format's
documentation (docs/compensation.md cites it), not with mtbudget's code; the uncertainties
of the tables are checked against an independent Monte Carlo over the identification
covariance through numpy's Legendre series and through the kinematic chain.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import types

import numpy as np
import pytest
from click.testing import CliRunner
from numpy.polynomial import legendre

from mtbudget.cli import main
from mtbudget.compensate import (COMPONENT_ERRORS, CompensationError, build_table, check_export, export,
                                 find_exporter, iso230_2, iso_name, line_points)
from mtbudget.config import example_recording
from mtbudget.contracts import Exporter
from mtbudget.errors import PluginError
from mtbudget.hookspecs import hookimpl
from mtbudget.machine import AXIS_INDEX, ChainInputs, chain
from mtbudget.plugins import PluginHost
from mtbudget.recording import read_recording


# ----------------------------------------------------------------------------- the hook
class Plain(Exporter):
    name = "plain"
    description = "positions and mean deviations"
    suffix = ".txt"
    convention = "this test"

    def write(self, table, path):
        path.write_text("\n".join(f"{p} {v}" for p, v in zip(table.axes["x"].positions, table.axes["x"].deviation)))
        return [path]


def _plugin(name, fn):
    mod = types.ModuleType(name)
    mod.mtbudget_register_exporters = hookimpl(fn)
    return mod


def test_hook_mtbudget_register_exporters(tmp_path, null):
    # the built-ins come through the entry point "exporters", stamped like sources and candidates
    ex = {e.name: e for e in PluginHost().exporters()}
    assert {"neutral-csv", "neutral-json", "linuxcnc", "beckhoff-lsec"} <= set(ex)
    assert all(e.plugin == "exporters" and e.dist_name == "mtbudget" and e.convention for e in ex.values())
    # a third-party exporter registered in code, found by --format and called through the host
    host = PluginHost(entry_points=False, plugins=(_plugin("mine", lambda register: register(Plain())),))
    (e,) = host.exporters()
    assert e.name == "plain" and e.plugin == "mine"
    written = export(null[1], find_exporter("plain", host), tmp_path / "t.txt")
    assert written == [tmp_path / "t.txt"] and len(written[0].read_text().splitlines()) == len(null[1].axes["x"].positions)
    # register() checks what it gets; an exception in the hook names plugin and hook
    with pytest.raises(PluginError, match="plugin 'wrong'.*mtbudget_register_exporters.*needs a mtbudget.contracts.Exporter"):
        PluginHost(entry_points=False, plugins=(_plugin("wrong", lambda register: register(object())),)).exporters()

    class NoCitation(Plain):
        convention = ""

    with pytest.raises(PluginError, match="must cite the convention"):
        PluginHost(entry_points=False, plugins=(_plugin("lazy", lambda register: register(NoCitation())),)).exporters()
    twice = _plugin("twice", lambda register: (register(Plain()), register(Plain())))
    with pytest.raises(PluginError, match="duplicate exporter name 'plain'"):
        PluginHost(entry_points=False, plugins=(twice,)).exporters()

    class Broken(Plain):
        def write(self, table, path):
            raise OSError("disk full")

    host = PluginHost(entry_points=False, plugins=(_plugin("broken", lambda register: register(Broken())),))
    with pytest.raises(PluginError, match="plugin 'broken'.*plain.*mtbudget_register_exporters.*write.*disk full"):
        export(null[1], find_exporter("plain", host), tmp_path / "b.txt")


# ----------------------------------------------------------------------------- ISO 230-1 names
def test_iso230_1_names():
    expected = {"dx(x)": "EXX", "dy(x)": "EYX", "dz(x)": "EZX", "ex(x)": "EAX", "ey(x)": "EBX", "ez(x)": "ECX",
                "dx(y)": "EXY", "dy(y)": "EYY", "dz(y)": "EZY", "ex(y)": "EAY", "ey(y)": "EBY", "ez(y)": "ECY",
                "dx(z)": "EXZ", "dy(z)": "EYZ", "dz(z)": "EZZ", "ex(z)": "EAZ", "ey(z)": "EBZ", "ez(z)": "ECZ",
                "sxy": "EC(0X)Y", "sxz": "EB(0X)Z", "syz": "EA(0Y)Z"}
    assert {n: iso_name(n) for n in expected} == expected
    assert set(COMPONENT_ERRORS) <= set(expected)


def test_iso_sign_follows_the_tool_relative_to_the_workpiece(null):
    """EXX of the neutral table equals the chain's positioning deviation along X for a pure dx(x)
    (X moves the workpiece on XFYZ: the sign flips); the same for EYY on the tool side."""
    rec, table = null
    model = table.model
    for err, axis in (("dx(x)", "x"), ("dy(y)", "y")):
        theta = np.zeros(model.n_params)
        for j, p in enumerate(model.errors.params):
            if p.error == err:
                theta[j] = 1e-3 * (p.order + 1)  # 1, 2, 3 um on P1, P2, P3
        f = table.function(iso_name(err))
        pts = line_points(axis, f.positions, {"x": 1000.0, "y": 300.0, "z": 300.0})
        inp = ChainInputs(pts, np.broadcast_to(rec.plan.tool[0], pts.shape).copy())
        P = chain(model.config, model.errors, theta[None], inp)[0, :, AXIS_INDEX[axis]]
        P0 = chain(model.config, model.errors, np.zeros((1, model.n_params)), inp)[0, :, AXIS_INDEX[axis]]
        idx = [j for j, p in enumerate(model.errors.params) if p.error == err]
        iso = model.config.side(axis) * (model.errors.basis(pts)[:, idx] @ theta[idx])
        np.testing.assert_allclose((P - P0) * 1e3, iso * 1e3, atol=1e-9)
        assert (model.config.side(axis) == -1) == (axis == "x")


# ----------------------------------------------------------------------------- ISO 230-2 by hand
def test_iso230_2_by_hand_positions_not_cycles_asymmetric():
    """Three targets (0, 100, 250 mm), 3/4/3 approaches up and 2/3/4 down: every figure computed by hand."""
    data = {0.0: ([1, 3, 2], [5, 7]), 100.0: ([-2, -2, -4, 0], [4, 4, 4]), 250.0: ([10, 12, 14], [9, 9, 11, 11])}
    t, d, x = [], [], []
    for pos, (up, down) in data.items():
        t += [pos] * (len(up) + len(down))
        d += [1] * len(up) + [-1] * len(down)
        x += up + down
    order = np.random.default_rng(0).permutation(len(t))  # the approaches in any order
    r = iso230_2("x", np.array(t)[order], np.array(d)[order], np.array(x, float)[order])
    # by hand: means up 2, -2, 12; down 6, 4, 10; s up 1, sqrt(8/3), 2; s down sqrt(2), 0, sqrt(4/3)
    s83, s2, s43 = np.sqrt(8 / 3), np.sqrt(2), np.sqrt(4 / 3)
    np.testing.assert_allclose(r.mean_up, [2, -2, 12])
    np.testing.assert_allclose(r.mean_down, [6, 4, 10])
    np.testing.assert_allclose(r.s_up, [1, s83, 2])
    np.testing.assert_allclose(r.s_down, [s2, 0, s43])
    np.testing.assert_allclose(r.reversal, [-4, -6, 2])
    f = r.figures
    hand = {
        "B": 6.0, "B_mean": -8 / 3,
        "M": 11.0 - 1.0,  # bidirectional means 4, 1, 11
        "E_up": 12 - (-2), "E_down": 10 - 4, "E": 12 - (-2),
        "R_up": 8.0, "R_down": 4 * s2,
        "R": max(2 * 1 + 2 * s2 + 4, 2 * s83 + 0 + 6, 2 * 2 + 2 * s43 + 2),
        "A_up": (12 + 4) - (-2 - 2 * s83),
        "A_down": (10 + 2 * s43) - (6 - 2 * s2),
        "A": (12 + 4) - (-2 - 2 * s83),
    }
    for k, v in hand.items():
        assert f[k] == pytest.approx(v, abs=1e-12), k
    # the direction labels matter: swapping them swaps the unidirectional figures and the sign of B
    s = iso230_2("x", np.array(t), -np.array(d), np.array(x, float))
    assert s.figures["E_up"] == pytest.approx(f["E_down"]) and s.figures["A_up"] == pytest.approx(f["A_down"])
    assert s.figures["B_mean"] == pytest.approx(-f["B_mean"])


def test_iso230_2_needs_both_sides():
    r = iso230_2("y", [0, 0, 10, 10], [1, 1, 1, 1], [0, 1, 2, 3])
    assert not r.figures and "not bidirectional" in r.note


# ----------------------------------------------------------------------------- the neutral table's uncertainty
def test_neutral_uncertainties_against_an_independent_monte_carlo(null):
    """u of every error function vs a Monte Carlo over cov_theta through numpy's Legendre series
    (not mtbudget's basis), and u of the positioning tables vs the same draws through the full chain."""
    _rec, table = null
    model, theta, cov = table.model, table.theta, table.cov_theta
    rng = np.random.default_rng(17)
    w, V = np.linalg.eigh(cov)
    draws = theta + (rng.standard_normal((6000, len(w))) * np.sqrt(np.clip(w, 0, None))) @ V.T
    for f in table.functions:
        if not f.identifiable:
            assert np.all(np.isnan(f.u))
            continue
        lo, hi = model.errors.ranges[f.axis]
        xi = (f.positions - (lo + hi) / 2) / ((hi - lo) / 2)
        idx = [j for j, p in enumerate(model.errors.params) if p.error == f.internal]
        orders = [model.errors.params[j].order for j in idx]
        basis = np.stack([legendre.legval(xi, np.eye(max(orders) + 1)[o]) for o in orders], axis=1)
        to_display = 1e3 if f.unit == "um" else 1e6  # mm -> um, rad -> urad
        vals = draws[:, idx] @ basis.T * model.config.side(f.axis) * to_display
        np.testing.assert_allclose(vals.mean(0), f.value, atol=4 * f.u.max() / np.sqrt(len(draws)) + 1e-9)
        np.testing.assert_allclose(vals.std(0), f.u, rtol=0.06, atol=1e-6)
    for a, t in table.axes.items():
        pts = line_points(a, t.positions, t.reference)
        inp = ChainInputs(pts, np.broadcast_to(t.tool, pts.shape).copy())
        P = chain(model.config, model.errors, draws[:600], inp)[:, :, AXIS_INDEX[a]] * 1e3
        dev = P - P[:, :1]
        np.testing.assert_allclose(dev.std(0)[1:], t.u[1:], rtol=0.15)
        assert t.u[0] == 0.0


# ----------------------------------------------------------------------------- the controller files, read back here
def parse_linuxcnc(path):
    """LinuxCNC COMP_FILE_TYPE 1 as the INI docs describe it: 'nominal forward reverse' per line, ascending."""
    lines = path.read_text().splitlines()
    table = [ln for ln in lines if not ln.startswith("#")]
    # the loader stops at the first line that is not a triplet: the notes must all come after the table
    assert lines[:len(table)] == table and all(ln.startswith("# ") for ln in lines[len(table):])
    rows = [tuple(map(float, line.split())) for line in table]
    assert all(len(r) == 3 for r in rows), "every table line must be a triplet"
    return np.array(rows)


def test_linuxcnc_files_read_back(tmp_path, reversal):
    _rec, table = reversal
    written = export(table, find_exporter("linuxcnc"), tmp_path / "mill.comp")
    assert [p.name for p in written] == ["mill_x.comp", "mill_y.comp", "mill_z.comp"]
    for a, p in zip("xyz", written):
        t = table.axes[a]
        rows = parse_linuxcnc(p)
        assert len(rows) <= 256 and np.all(np.diff(rows[:, 0]) > 0)
        np.testing.assert_allclose(rows[:, 0], t.positions, atol=1e-6)
        # type 1: the trim is added to the command, so it is minus the deviation (nominal - actual), in mm
        np.testing.assert_allclose(rows[:, 1], -t.forward / 1000, atol=1e-6)
        np.testing.assert_allclose(rows[:, 2], -t.reverse / 1000, atol=1e-6)
    # the Y axis has the simulated reversal: reverse trim minus forward trim is the reversal value B (ISO sign)
    y = parse_linuxcnc(written[1])
    np.testing.assert_allclose((y[:, 2] - y[:, 1]) * 1000, table.axes["y"].reversal, atol=2e-3)


def parse_beckhoff(path):
    """Beckhoff kw.ssfk list: 'name value' lines, '# ' whole-line comments, blank lines."""
    kv = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        if line.startswith("#"):
            assert line.startswith("# ") or line == "#", "a whole-line comment is '#' followed by a space"
            continue
        name, value = line.split()
        kv[name] = value if name == "kopf.log_achs_name" else int(value)
    n = kv["kw.ssfk.kw_nr_max"]
    return kv, np.array([[kv[f"kw.ssfk.table[{i}].{k}"] for k in ("setpoint", "pos", "neg")] for i in range(n)])


def test_beckhoff_lists_read_back(tmp_path, reversal):
    _rec, table = reversal
    written = export(table, find_exporter("beckhoff-lsec"), tmp_path / "achskw.lis")
    for a, p in zip("xyz", written):
        t = table.axes[a]
        kv, rows = parse_beckhoff(p)
        assert kv["kw.ssfk.unit"] == 1 and kv["kw.ssfk.bilateral"] == 1 and kv["kw.ssfk.interval"] == 0
        assert kv["kw.ssfk.kw_startpos"] == rows[0, 0]
        np.testing.assert_array_equal(rows[:, 0], np.rint(t.positions * 1e4))  # setpoints in 0.1 um
        # pos / neg = actual - setpoint in 0.1 um (the example: 19856.5 - 19866.7 um -> -102)
        np.testing.assert_allclose(rows[:, 1] / 10, t.forward, atol=0.05 + 1e-9)
        np.testing.assert_allclose(rows[:, 2] / 10, t.reverse, atol=0.05 + 1e-9)
        assert np.abs(rows[:, 1:]).max() < 32767


def test_neutral_csv_and_json(tmp_path, null):
    _rec, table = null
    (c,) = export(table, find_exporter("neutral-csv"), tmp_path / "t.csv")
    text = c.read_text()
    assert "# sign:" in text and "# units:" in text
    rows = list(csv.DictReader(io.StringIO("\n".join(ln for ln in text.splitlines() if not ln.startswith("#")))))
    eyy = [r for r in rows if r["kind"] == "error_function" and r["iso_name"] == "EYY"]
    assert [float(r["position_mm"]) for r in eyy] == pytest.approx(list(table.function("EYY").positions))
    assert [float(r["value"]) for r in eyy] == pytest.approx(list(table.function("EYY").value), abs=1e-4)
    assert {r["unit"] for r in eyy} == {"um"} and all(float(r["u"]) > 0 for r in eyy)
    ecy = [r for r in rows if r["iso_name"] == "ECY"]
    assert ecy and all(r["u"] == "" and r["identifiable"] == "0" for r in ecy)  # the roll of Y is not identifiable
    sq = {r["iso_name"]: r for r in rows if r["kind"] == "squareness"}
    assert set(sq) == {"EC(0X)Y", "EB(0X)Z", "EA(0Y)Z"}
    (j,) = export(table, find_exporter("neutral-json"), tmp_path / "t.json")
    d = json.loads(j.read_text())
    assert d["iso230_1_names"]["ez(y)"] == "ECY" and d["conventions"]["sign"].startswith("error = actual - nominal")
    assert d["positioning"]["x"]["forward"] == pytest.approx(list(table.axes["x"].forward))


# ----------------------------------------------------------------------------- the round trip
@pytest.mark.parametrize("fmt", ["linuxcnc", "beckhoff-lsec", "neutral-csv"])
def test_check_round_trip_on_a_simulated_machine(tmp_path, null, fmt):
    rec, table = null
    ex = find_exporter(fmt)
    written = export(table, ex, tmp_path / f"t{ex.suffix}")
    check = check_export(table, rec, ex, written)
    assert not check.get("mismatch")
    for a, c in check["axes"].items():
        d = c.to_dict()
        assert d["max_abs_after_um"] < 0.3 * d["max_abs_before_um"], a
        assert d["max_abs_z"] < 3.0 and d["within_2u"] >= 0.9, (a, d)
        assert c.iso_after.figures["E"] < c.iso_before.figures["E"]


def test_check_catches_a_table_with_the_wrong_sign(tmp_path, null):
    rec, table = null
    ex = find_exporter("linuxcnc")
    written = export(table, ex, tmp_path / "t.comp")
    rows = parse_linuxcnc(written[0])
    rows[:, 1:] *= -1
    written[0].write_text("".join(f"{n:.6f} {f:.6f} {r:.6f}\n" for n, f, r in rows))
    check = check_export(table, rec, ex, written)
    assert "x" in check["mismatch"]
    assert check["axes"]["x"].to_dict()["max_abs_z"] > 3


def test_reversal_is_estimated_from_the_bidirectional_approaches(reversal):
    _rec, table = reversal
    y = table.axes["y"]
    # the simulated axis stops 8 um short from either side: ISO 230-2 reversal value -8 um
    assert abs(y.reversal - (-8.0)) < 3 * y.u_reversal and y.u_reversal < 2.5
    for a in "xz":
        assert abs(table.axes[a].reversal) < 3 * table.axes[a].u_reversal
    rec_y = table.iso230_2["y"]["recording"].figures
    assert rec_y["B_mean"] == pytest.approx(y.reversal)


# ----------------------------------------------------------------------------- the command
def test_compensate_command(tmp_path):
    out = tmp_path / "m.comp"
    res = CliRunner().invoke(main, ["compensate", "--example", "null", "--format", "linuxcnc", "--out", str(out),
                                    "--check", "--step", "100 mm"])
    assert res.exit_code == 0, res.output
    assert "wrote" in res.output and "check:" in res.output and "EC(0X)Y" in res.output and "ISO 230-2" in res.output
    rows = [ln for ln in (tmp_path / "m_x.comp").read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == 5  # 800..1200 every 100 mm
    res = CliRunner().invoke(main, ["compensate", "--example", "null", "--format", "neutral-json", "--out",
                                    str(tmp_path / "t.json"), "--json"])
    body = json.loads(res.stdout)
    assert body["positioning"]["z"]["positions_mm"] == [200, 250, 300, 350, 400]
    assert body["iso230_2"]["y"]["model"]["figures"]["E"] > 0


@pytest.mark.parametrize("args, message", [
    (["--format", "linuxcnx"], "unknown format 'linuxcnx'; did you mean 'linuxcnc'?"),
    (["--format", "linuxcnc", "--step", "-5 mm"], "--step: '-5 mm' must be one positive length"),
    (["--format", "linuxcnc", "--step", "5 s"], "--step: '5 s' is not a quantity of dimension [length]"),
    (["--format", "linuxcnc", "--step", "five"], "'five'"),
    (["--format", "linuxcnc", "--step", "1 mm"], "format 'linuxcnc' accepts at most 256 per axis"),
])
def test_bad_input_gives_one_line_errors(tmp_path, args, message):
    res = CliRunner().invoke(main, ["compensate", "--example", "null", "--out", str(tmp_path / "t.comp"), *args])
    assert res.exit_code == 2
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], res.output


def test_check_needs_a_truth(tmp_path):
    folder = tmp_path / "rec"
    shutil.copytree(example_recording("null"), folder)
    (folder / "truth.json").unlink()
    res = CliRunner().invoke(main, ["compensate", str(folder), "--format", "linuxcnc", "--out",
                                    str(tmp_path / "t.comp"), "--check"])
    assert res.exit_code == 2 and "--check needs the truth.json" in res.output
    assert len(res.output.strip().splitlines()) == 1
    with pytest.raises(CompensationError):
        find_exporter("nope")


def test_check_on_a_recording_whose_truth_has_a_drift_array(tmp_path):
    """truth.json of tracker_drift holds the drift as a vector: --check runs and says it was not applied."""
    rec = read_recording(example_recording("tracker_drift"))
    table = build_table(rec, 50.0)
    ex = find_exporter("neutral-csv")
    check = check_export(table, rec, ex, export(table, ex, tmp_path / f"t{ex.suffix}"))
    assert check["ignored"] == ["drift"]


def test_compensate_writes_its_report_with_the_residual_against_U_and_the_check(tmp_path):
    res = CliRunner().invoke(main, ["compensate", "--example", "null", "--format", "linuxcnc", "--out",
                                    str(tmp_path / "t" / "t.comp"), "--check", "--report", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    md = (tmp_path / "rep" / "compensation.md").read_text()
    assert "Fit residual at the recording's points" in md and "U (k = 2)" in md and "Round trip" in md
    assert (tmp_path / "rep" / "compensation.html").is_file() and (tmp_path / "rep" / "residual_vs_U.png").is_file()


@pytest.mark.parametrize("name, warns", [("null", False), ("thermal_x", True)])
def test_compensate_carries_the_fit_test_of_its_identification(name, warns, tmp_path):
    """A table's u holds only what the model holds: where the fit fails the chi-square test against the stated noise
    (thermal_x: a thermal expansion the model leaves out), the tables say so first; the null recording does not.
    The test's p-value recomputed here with scipy.stats.chi2."""
    from scipy import stats

    res = CliRunner().invoke(main, ["compensate", "--example", name, "--format", "neutral-json", "--out",
                                    str(tmp_path / "t.json"), "--json"])
    assert res.exit_code == 0, res.output
    idn = json.loads(res.stdout)["identification"]
    t = idn["fit_test"]
    assert t["p_above"] == pytest.approx(stats.chi2.sf(idn["chi2_per_dof"] * idn["dof"], idn["dof"]), rel=1e-6)
    assert (t["warning"] is not None) == warns == (t["p_above"] < 1e-3)
    text = CliRunner().invoke(main, ["compensate", "--example", name, "--format", "neutral-json", "--out",
                                     str(tmp_path / "u.json")]).output
    assert ("WARNING: the identified model does not fit" in text) == warns
    if warns:
        assert "which the tables' u does not contain" in text and "before entering the tables" in text
