"""Correction of the scales' nominal expansion to the reference temperature (issue 14, paper Eq. 7-9).

The identification takes the stated nominal expansion (``[scales]`` of recording.toml) as a known model
input, so the geometric errors it returns are those of the machine at 20 degC.  Checked against the
shared example ``thermal_x``, whose truth (written by the recordings' own generator, not by mtbudget)
expands the X scale by 11.5 um/(m K) about the axis zero.
"""

import json
import shutil

import numpy as np
import pytest

from mtbudget.errors import RecordingError
from mtbudget.identify import Noise, identify
from mtbudget.machine import ChainInputs
from mtbudget.model import MeasurementModel
from mtbudget.plan import Scale
from mtbudget.recording import read_recording, write_recording

from mtbudget.config import example_recording

CTE_STEEL = "11.5 um/(m*K)"  # the truth's CTE of the X scale (truth.json "effects.thermal.x")


def with_scales(tmp_path, text, name="thermal_x"):
    dst = tmp_path / name
    shutil.copytree(example_recording(name), dst)
    with open(dst / "recording.toml", "a", encoding="utf-8") as fh:
        fh.write("\n" + text + "\n")
    return dst


def identified(folder):
    rec = read_recording(folder)
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=3)
    res = identify(model, rec.lt, Noise.of(rec), fixed=rec.fixed_inputs())
    j = model.errors.index("dx(x)[P1]")
    return rec, res.theta[0, j], np.sqrt(res.cov_theta[0, j, j]), res.chi2[0] / res.dof


def test_effective_position_is_expansion_about_the_fixed_point():
    """The chain's (p + offset)(1 + scale) equals x0 + (p - x0)(1 + cte dT), written out by hand."""
    from mtbudget.plan import Plan, Sensor

    M = 7
    p = np.linspace(-300.0, 900.0, M)
    T = 293.15 + np.linspace(0.4, 2.4, M)
    nominal = np.stack([p, np.zeros(M), np.zeros(M)], axis=1)
    plan = Plan(np.arange(M), np.ones(M, int), np.arange(M, dtype=float), nominal, np.ones((M, 3)),
                np.zeros((M, 3)), {"T_x": T}, [Sensor("T_x", "x axis")], {"x": Scale(11.5e-6, 250.0)})
    fixed = plan.nominal_expansion(293.15)
    inp = ChainInputs(nominal, np.zeros((M, 3)), offset={"x": fixed["axis_offset.x"]},
                      scale={"x": fixed["axis_scale.x"]})
    expected = 250.0 + (p - 250.0) * (1.0 + 11.5e-6 * (T - 293.15))
    np.testing.assert_allclose(inp.effective("x")[0], expected, rtol=0, atol=1e-12)
    assert set(fixed) == {"axis_scale.x", "axis_offset.x"}


def test_no_scales_means_no_correction_and_says_so():
    rec = read_recording(example_recording("thermal_x"))
    assert rec.fixed_inputs() == {}
    assert rec.thermal_correction.startswith("no correction to 20 degC applied")


def test_thermal_x_identifies_within_its_uncertainty_with_the_correction(tmp_path):
    truth = json.loads((example_recording("thermal_x") / "truth.json").read_text())
    assert truth["effects"]["thermal"]["x"] == 11.5 and "about the axis zero" in truth["conventions"]["thermal"]
    true_p1 = truth["geometric_errors"]["coefficients"]["dx(x)"][0] * 1e-3  # um -> mm
    _, raw, u_raw, chi_raw = identified(example_recording("thermal_x"))
    rec, cor, u_cor, chi_cor = identified(with_scales(tmp_path, f'[scales.x]\ncte = "{CTE_STEEL}"\nfixed_point = "0 mm"'))
    assert rec.thermal_correction.startswith("scales corrected to 20 degC: x 11.5 um/(m*K)")
    # without the correction the scale error carries the expansion: further from the truth
    assert abs(raw - true_p1) > 1.5 * abs(cor - true_p1)
    # with it, the truth lies within the expanded uncertainty (k = 2) and the fit is explained
    assert abs(cor - true_p1) < 2 * u_cor
    assert chi_raw > 1.3 and chi_cor < 1.1


def test_the_fit_is_best_at_the_true_fixed_point(tmp_path):
    """The truth expands about the axis zero: a fixed point 600 mm either side leaves an offset drift
    (600 mm x 11.5 um/(m K) x 2 K = 14 um over the test), which the fit shows (chi2/dof sd ~0.05 at 852 dof)."""
    chi = {}
    for x0 in (-600, 0, 600):
        folder = with_scales(tmp_path / str(x0), f'[scales.x]\ncte = "{CTE_STEEL}"\nfixed_point = "{x0} mm"')
        chi[x0] = identified(folder)[3]
    assert chi[-600] > chi[0] + 0.1 and chi[600] > chi[0] + 0.1


def test_scales_round_trip_through_the_writer(tmp_path):
    rec = read_recording(with_scales(tmp_path, '[scales.x]\ncte = "6.4 ppm/degF"\nfixed_point = "-2 in"'))
    sc = rec.plan.scales["x"]
    assert sc.cte == pytest.approx(6.4e-6 * 9 / 5, rel=1e-12) and sc.fixed_point == pytest.approx(-50.8, abs=1e-12)
    back = read_recording(write_recording(rec, tmp_path / "w"))
    assert back.plan.scales["x"].cte == pytest.approx(sc.cte, rel=1e-8)
    assert back.plan.scales["x"].fixed_point == pytest.approx(sc.fixed_point, abs=1e-6)


@pytest.mark.parametrize("text, key, words", [
    ('[scales.w]\ncte = "11.5 um/(m*K)"', "scales.w", "unknown axis"),
    ('[scales.x]\nfixed_point = "0 mm"', "scales.x.cte", "missing key 'cte'"),
    ('[scales.x]\ncte = "11.5 um"', "scales.x.cte", "1 / [temperature]"),
    ('[scales.x]\ncte = "11.5"', "scales.x.cte", "not a quantity"),
    ('[scales.x]\ncte = "115 um/(m*K)"', "scales.x.cte", "not a plausible expansion coefficient"),
    ('[scales.x]\ncte = "11.5 um/(m*K)"\nfixed_point = "3 degC"', "scales.x.fixed_point", "[length]"),
    ('[scales.x]\ncte = "11.5 um/(m*K)"\nzero = "0 mm"', "scales.x.zero", "unknown key"),
    ('scales = 3', "scales", "expected a table"),
])
def test_bad_scales_name_the_key(tmp_path, text, key, words):
    folder = with_scales(tmp_path, text)
    if text.startswith("scales ="):  # a top-level key must precede the tables
        toml = (folder / "recording.toml").read_text().replace("\n" + text + "\n", "")
        (folder / "recording.toml").write_text(text + "\n" + toml)
    with pytest.raises(RecordingError) as e:
        read_recording(folder)
    msg = str(e.value)
    assert key in msg and words in msg and "recording.toml" in msg and "\n" not in msg


def test_a_scale_needs_a_sensor_on_its_axis(tmp_path):
    folder = with_scales(tmp_path, '[scales.x]\ncte = "11.5 um/(m*K)"')
    text = (folder / "recording.toml").read_text()
    block = '[[sensors]]\ncolumn = "T_x"\nattached_to = "x axis"\n'
    assert block in text
    (folder / "recording.toml").write_text(text.replace(block, ""))
    with pytest.raises(RecordingError, match="no \\[\\[sensors\\]\\] table is attached to the x axis"):
        read_recording(folder)


def test_compensation_of_thermal_x_holds_at_20_degC_only_with_the_correction(tmp_path):
    """The exported X table, applied to the true machine of truth.json at the reference temperature: with the
    correction the compensated X axis is within 2u everywhere; without it, the expansion at 20.4-22.4 degC is
    written into the table and most of the line is outside."""
    from mtbudget.compensate import build_table, check_export, export, find_exporter

    within = {}
    for label, folder in (("raw", example_recording("thermal_x")),
                          ("corrected", with_scales(tmp_path, f'[scales.x]\ncte = "{CTE_STEEL}"'))):
        rec = read_recording(folder)
        table = build_table(rec, 50.0)
        assert table.notes[0] == rec.thermal_correction
        ex = find_exporter("neutral-csv")
        written = export(table, ex, tmp_path / f"{label}{ex.suffix}")
        within[label] = check_export(table, rec, ex, written)["axes"]["x"].to_dict()["within_2u"]
    assert within["corrected"] == 1.0 and within["raw"] < 0.5


def test_diagnosis_of_thermal_x_finds_nothing_left_once_the_stated_expansion_is_corrected(tmp_path):
    """Without [scales] the diagnosis names the expansion (the truth's 11.5 um/(m K) within 2u); with it stated
    nothing is left to find, and both say which correction they applied."""
    from mtbudget.diagnose import diagnose

    raw = diagnose(read_recording(example_recording("thermal_x")))
    (f,) = raw.findings
    assert (f.candidate.effect, f.candidate.axis) == ("thermal_expansion", "x")
    assert abs(f.estimate[0] - 11.5) < 2 * f.uncertainty[0] and f.unit in ("um/(m*K)", "um / m / K", "µm/(m·K)")
    cor = diagnose(read_recording(with_scales(tmp_path, f'[scales.x]\ncte = "{CTE_STEEL}"')))
    assert cor.findings == [] and cor.unexplained is None
    assert raw.settings["thermal_correction"].startswith("no correction")
    assert cor.settings["thermal_correction"].startswith("scales corrected to 20 degC")


def test_a_wrong_stated_cte_is_found_as_a_deviation_with_a_shifted_plausible_range(tmp_path):
    """Stating 4 um/(m K) for a scale that expands by 11.5: the diagnosis finds the deviation, +7.5 within 2u,
    although a stated 25 would make a deviation of -13.5 plausible too (total 11.5 within 0-30)."""
    from mtbudget.diagnose import diagnose

    for stated in (4.0, 25.0):
        d = diagnose(read_recording(with_scales(tmp_path / str(stated), f'[scales.x]\ncte = "{stated} um/(m*K)"')))
        (f,) = d.findings
        assert (f.candidate.effect, f.candidate.axis) == ("thermal_expansion", "x")
        assert abs(f.estimate[0] - (11.5 - stated)) < 2 * f.uncertainty[0]
        assert d.unexplained is None


def test_the_cte_deviation_expands_about_the_stated_fixed_point(tmp_path):
    """thermal_x with its commanded X shifted by -800 mm: its truth now expands about x = -800 mm.  Stated with that
    fixed point but a CTE 4 um/(m K) low, the deviation is found about it (within 2u of 4) and the recording is then
    explained; a deviation taken about the axis zero would leave an offset drift of 800 mm x 4 um/(m K) x dT."""
    from mtbudget.diagnose import diagnose

    folder = with_scales(tmp_path, '[scales.x]\ncte = "7.5 um/(m*K)"\nfixed_point = "-800 mm"')
    # the truth expands about the axis zero; stating the zero at -800 mm in shifted coordinates is the same point
    csv = (folder / "points.csv").read_text().splitlines()
    head = csv[0].split(",")
    ix = head.index("x [mm]")
    rows = [csv[0]]
    for line in csv[1:]:
        c = line.split(",")
        c[ix] = f"{float(c[ix]) - 800.0:.6f}"
        rows.append(",".join(c))
    (folder / "points.csv").write_text("\n".join(rows) + "\n")
    d = diagnose(read_recording(folder))
    (f,) = d.findings
    assert (f.candidate.effect, f.candidate.axis) == ("thermal_expansion", "x")
    assert abs(f.estimate[0] - 4.0) < 2 * f.uncertainty[0]
    assert d.unexplained is None and d.final["chi2_per_dof"] < 1.1


@pytest.mark.parametrize("line, key, close", [('reference_temprature = "23 degC"', "reference_temprature",
                                               "reference_temperature"),
                                              ('scale = 3', "scale", "scales")])
def test_a_misspelt_top_level_key_is_an_error_not_silently_ignored(tmp_path, line, key, close):
    folder = with_scales(tmp_path, "")
    toml = (folder / "recording.toml").read_text()
    (folder / "recording.toml").write_text(line + "\n" + toml)
    with pytest.raises(RecordingError) as e:
        read_recording(folder)
    assert f"unknown key {key!r}; did you mean {close!r}" in str(e.value) and "recording.toml" in str(e.value)


def test_a_misspelt_tracker_key_names_the_typo(tmp_path):
    folder = with_scales(tmp_path, "")
    toml = (folder / "recording.toml").read_text().replace("angular =", "angualr =")
    (folder / "recording.toml").write_text(toml)
    with pytest.raises(RecordingError, match="tracker.angualr: unknown key 'angualr'; did you mean 'angular'"):
        read_recording(folder)
