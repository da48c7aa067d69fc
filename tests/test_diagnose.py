"""Diagnosis: the examples, the output contract, units, calibration on concealed cases, bad input."""

import json
import shutil
import types

import numpy as np
import pytest
from click.testing import CliRunner

from mtbudget.testing import case_config, named, named_or_confounded, run_case, simulate_case
from mtbudget.cli import main
from mtbudget.config import example_recording
from mtbudget.contracts import Candidate
from mtbudget.diagnose import diagnose
from mtbudget.errors import DiagnosisError
from mtbudget.errors import PluginError
from mtbudget.hookspecs import hookimpl
from mtbudget.machine import AXIS_INDEX
from mtbudget.plugins import PluginHost, default_host
from mtbudget.recording import read_recording
from mtbudget.report_diagnosis import diagnosis_text

from test_recording import convert_to_imperial


@pytest.fixture(scope="module")
def candidates():
    return default_host().candidates()


def truth(name):
    return json.loads((example_recording(name) / "truth.json").read_text())["effects"]


def test_null_example_has_no_finding(candidates):
    d = diagnose(read_recording(example_recording("null")), candidates)
    assert d.findings == []


@pytest.mark.parametrize("name,effect,axis", [("thermal_x", "thermal_expansion", "x"), ("reversal_y", "reversal", "y"),
                                              ("tracker_drift", "tracker_drift", None)])
def test_examples_name_the_hidden_effect_and_estimate_it(name, effect, axis, candidates):
    d = diagnose(read_recording(example_recording(name)), candidates)
    assert named(d) == {(effect, axis)}
    f = d.findings[0]
    t = truth(name)
    want = {"thermal_expansion": t["thermal"].get(axis), "reversal": t["reversal"].get(axis), "tracker_drift": t["drift"]}[effect]
    est, unc = np.atleast_1d(f.estimate), np.atleast_1d(f.uncertainty)
    assert np.all(np.abs(est - np.atleast_1d(want)) < 3.5 * unc), (est, unc, want)
    assert d.final["chi2_per_dof"] < d.baseline["chi2_per_dof"]
    assert 0.8 < d.final["chi2_per_dof"] < 1.25


def test_same_findings_in_inch_minutes_and_fahrenheit(tmp_path, candidates):
    convert_to_imperial(example_recording("reversal_y"), tmp_path / "r")
    a = diagnose(read_recording(example_recording("reversal_y")), candidates)
    b = diagnose(read_recording(tmp_path / "r"), candidates)
    assert named(a) == named(b)
    assert a.findings[0].estimate[0] == pytest.approx(b.findings[0].estimate[0], rel=1e-6)


def test_json_contract_is_one_object():
    res = CliRunner().invoke(main, ["diagnose", "--example", "thermal_x", "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    assert set(d) >= {"recording", "baseline", "mismatch", "findings", "final"}
    assert d["recording"] == "thermal_x"
    f = d["findings"][0]
    assert f["effect"] == "thermal_expansion" and f["axis"] == "x"
    assert f["estimate"]["unit"] == "um/(m*K)" and f["uncertainty"]["value"] > 0
    assert {"chi2_per_dof", "rms"} <= set(f["after"]) and f["after"]["rms"]["unit"] == "um"
    assert {"by_run", "by_time", "by_direction", "by_position", "by_temperature"} <= set(d["mismatch"])
    from mtbudget.units import ureg

    ureg.Unit(f["estimate"]["unit"])  # parses


def test_human_output_and_report(tmp_path):
    res = CliRunner().invoke(main, ["diagnose", "--example", "null", "--report", str(tmp_path / "rep")])
    assert res.exit_code == 0
    assert "explained by the baseline model within its stated uncertainty" in res.output
    assert (tmp_path / "rep" / "residuals.png").stat().st_size > 10_000
    assert "# Diagnosis of null" in (tmp_path / "rep" / "diagnosis.md").read_text()


# --------------------------------------------------------------------------- calibration
def test_calibration_no_effect_no_claim(candidates):
    """100 simulated recordings with no hidden effect: an effect is claimed in at most 5 % of them."""
    claims = sum(bool(run_case(seed, (), candidates=candidates)[0].findings) for seed in range(100))
    assert claims <= 5


CALIBRATED = [("thermal_expansion", "x"), ("thermal_expansion", "y"), ("thermal_expansion", "z"), ("reversal", "x"),
              ("reversal", "y"), ("reversal", "z"), ("tracker_drift", None), ("axis_coupling", "xy"),
              ("air_temperature_drift", None)]


@pytest.mark.parametrize("effect", CALIBRATED, ids=lambda e: f"{e[0]}-{e[1]}")
def test_calibration_effect_at_2_5_noise_is_named(effect, candidates):
    """Named: reported as the finding, or inside the group of candidates it says it cannot tell apart.

    A wrong effect claimed without declaring the confusion counts as a miss.
    """
    n = 30
    hits = sum(effect in named_or_confounded(run_case(500 + seed, (effect,), 2.5, candidates=candidates)[0])
               for seed in range(n))
    assert hits >= 0.9 * n


@pytest.mark.slow
@pytest.mark.parametrize("effect", CALIBRATED, ids=lambda e: f"{e[0]}-{e[1]}")
def test_calibration_full_100_cases(effect, candidates):
    hits = sum(effect in named_or_confounded(run_case(10_000 + seed, (effect,), 2.5, candidates=candidates)[0])
               for seed in range(100))
    assert hits >= 90


@pytest.mark.parametrize("pair", [(("thermal_expansion", "x"), ("reversal", "y")),
                                  (("tracker_drift", None), ("reversal", "x"))], ids=["thermal+reversal", "drift+reversal"])
def test_pairs_in_imperial_units_are_both_named(pair, candidates):
    hits = 0
    for seed in range(10):
        d, _ = run_case(900 + seed, pair, 3.0, imperial=True, candidates=candidates)
        hits += set(pair) <= named_or_confounded(d)
    assert hits >= 9


def test_confounded_candidates_are_said_to_be(tmp_path, candidates):
    """Air temperature rising in step with time: tracker drift and air-temperature drift cannot be told apart."""
    cfg, _ = case_config(3, (("tracker_drift", None),), 4.0)
    for s in cfg.sensors:
        s.cycle_amplitude, s.noise = 0.0, 0.0005
    d = diagnose(simulate_case(cfg, tmp_path / "c"), candidates)
    hint = "Repeat the test with the air temperature held, or measure a fixed reference point every few minutes."
    if d.findings:
        f = d.findings[0]
        pair = {f.candidate.effect} | {c["effect"] for c in f.confounded_with}
        assert {"tracker_drift", "air_temperature_drift"} <= pair
        # the measurement that would separate them comes from the candidates' own hints
        assert hint in f.hints
    else:
        # issue 30: the air-temperature drift it is identical to would need an implausible size (-75 um/K), so the
        # drift is reported as fitting like it, never found; with the same measurement to separate them
        s = next(x for x in d.stand_ins if x["effect"] == "tracker_drift")
        assert s["fits_like"]["effect"] == "air_temperature_drift" and s["outside_span"] < 0.2
        assert s["separating_measurement"] == hint
        assert d.unexplained is not None
    assert hint in diagnosis_text(d)


# --------------------------------------------------------------------------- bad input and plugins
def test_too_small_recording(tmp_path):
    rec = read_recording(example_recording("null"))
    keep = np.arange(len(rec)) < 8
    rec.plan, rec.lt = rec.plan.subset(keep), rec.lt[keep]
    with pytest.raises(DiagnosisError, match=r"null: only \d+ degrees of freedom are left after the baseline \(8 points\)"):
        diagnose(rec)
    # a little larger: identifiable, and diagnosed with the candidates it can test
    rec = read_recording(example_recording("null"))
    keep = np.arange(len(rec)) < 30
    rec.plan, rec.lt = rec.plan.subset(keep), rec.lt[keep]
    d = diagnose(rec)
    assert any(s["effect"] == "approximation_degree" for s in d.skipped)


def test_missing_columns_skip_candidates_and_say_so(tmp_path, candidates):
    dst = tmp_path / "nosensor"
    shutil.copytree(example_recording("thermal_x"), dst)
    toml = (dst / "recording.toml").read_text()
    (dst / "recording.toml").write_text(toml.split("[[sensors]]")[0])
    d = diagnose(read_recording(dst), candidates)
    reasons = {(s["effect"], s["axis"]): s["reason"] for s in d.skipped}
    assert "no temperature sensor is attached to the x axis" == reasons[("thermal_expansion", "x")]
    assert ("air_temperature_drift", None) in reasons


def _through_hook(*candidates):
    """Register ``candidates`` through the hook of a plugin module named broken_candidates."""
    mod = types.ModuleType("broken_candidates")

    def register_all(register):
        for c in candidates:
            register(c)

    mod.mtbudget_register_candidates = hookimpl(register_all)
    return PluginHost(entry_points=False, plugins=(mod,)).candidates()


class LostMotion(Candidate):
    """A third-party reversal written from scratch: lost motion B of one axis, B/2 short from either side."""

    effect = "lost_motion"
    description = "lost motion"
    parameters = {"B": "um"}

    def columns(self, ctx):
        C = np.zeros((len(ctx.plan), 3, 1))
        i = AXIS_INDEX[self.axis]
        C[:, i, 0] = -ctx.plan.direction[:, i] / 2.0
        return C


def test_candidate_plugin_through_the_hook_and_its_errors():
    class Wobble(Candidate):
        effect = "wobble"
        parameters = {"a": "um"}

        def columns(self, ctx):
            return np.zeros((len(ctx.plan), 2))  # wrong shape

    cands = _through_hook(Wobble())
    assert [c.effect for c in cands] == ["wobble"] and cands[0].plugin == "broken_candidates"
    with pytest.raises(PluginError, match=r"plugin 'broken_candidates'.*wobble.*method columns\(\).*shape") as exc:
        diagnose(read_recording(example_recording("null")), cands)
    assert (exc.value.plugin, exc.value.source, exc.value.method) == ("broken_candidates", "wobble", "columns")
    assert exc.value.hook == "mtbudget_register_candidates"


@pytest.mark.parametrize("method", ["requires", "columns", "perturbation", "summary"])
def test_an_exception_inside_a_candidate_names_plugin_and_method(method):
    """Every call into candidate code goes through the plugin host: the error says whose code failed, and where."""

    def broken(self, *args):
        raise ZeroDivisionError("boom")

    Broken = type("Broken", (LostMotion,), {method: broken})
    cands = _through_hook(Broken("y"))
    with pytest.raises(PluginError) as exc:
        diagnose(read_recording(example_recording("reversal_y")), cands)
    e = exc.value
    assert (e.plugin, e.source, e.method) == ("broken_candidates", "lost_motion[y]", method)
    assert f"method {method}()" in str(e) and "ZeroDivisionError: boom" in str(e)


def test_a_candidate_with_only_columns_uses_the_defaults():
    """Default summary (the one parameter's display unit) and perturbation (columns times the estimate)."""
    rec = read_recording(example_recording("reversal_y"))
    d = diagnose(rec, _through_hook(LostMotion("y")))
    assert named(d) == {("lost_motion", "y")}
    f = d.findings[0]
    assert f.unit == "um" and f.to_dict()["estimate"]["unit"] == "um"
    B = truth("reversal_y")["reversal"]["y"]  # um
    assert abs(f.estimate[0] - B) < 3.5 * f.uncertainty[0]
    assert d.final["chi2_per_dof"] < d.baseline["chi2_per_dof"]


@pytest.mark.parametrize("attrs,message", [
    ({"parameters": {}}, "parameters must be a non-empty dict"),
    ({"parameters": {"a": "furlongs per fortnight squared"}}, "parameter 'a'"),
    ({"frame": "world"}, "frame must be 'machine' or 'tracker'"),
])
def test_bad_declarations_name_the_plugin(attrs, message):
    Bad = type("Bad", (LostMotion,), attrs)
    with pytest.raises(PluginError, match=f"plugin 'broken_candidates'; source 'lost_motion\\[y\\]'.*{message}"):
        diagnose(read_recording(example_recording("null")), _through_hook(Bad("y")))


def test_builtin_candidates_declare_their_units_and_hints(candidates):
    from mtbudget.units import internal_unit_of

    by_label = {c.label: c for c in candidates}
    assert by_label["thermal_expansion[x]"].units() == [("cte", "um/(m*K)", "1/K")]
    assert by_label["tracker_drift"].units() == [("velocity", "um/h", "mm/s")]
    for c in candidates:
        assert c.frame in ("machine", "tracker") and c.description
        for unit in c.parameters.values():
            internal_unit_of(unit)
        for other, text in c.hints.items():
            assert other in {x.effect for x in candidates} and text.endswith(".")


def test_approximation_degree_summary_puts_lengths_in_um_and_angles_in_urad(candidates):
    """RMS over dx, dy, dz (mm) and ex, ey, ez (rad): 1 urad counts like 1 um (a 1 m lever)."""
    c = next(x for x in candidates if x.label == "approximation_degree[x]")
    beta = np.array([0.003, -0.004, 0.0, 12e-6, 0.0, 0.0])  # in mm and rad: 3, -4, 0 um; 12, 0, 0 urad
    cov = np.diag([0.001**2] * 3 + [2e-6**2] * 3)  # u = 1 um (in mm) and 2 urad (in rad)
    est, unc, unit = c.summary(beta, cov)
    assert unit == "um"
    assert est[0] == pytest.approx(np.sqrt((9 + 16 + 144) / 6))
    assert unc[0] == pytest.approx(np.sqrt((3 * 1 + 3 * 4) / 6))


def test_approximation_degree_columns_follow_its_parameters(candidates):
    """Column j is the next-degree term of the error named by parameter j: dx(x) moves points along x only."""
    rec = read_recording(example_recording("null"))
    from mtbudget.contracts import DiagnosisContext
    from mtbudget.model import MeasurementModel

    model = MeasurementModel.for_plan(rec.machine, rec.plan)
    P = model.machine_points(np.zeros(model.n_params))[0]
    ctx = DiagnosisContext(rec, model, np.zeros(6), np.zeros(model.n_params), P, P)
    c = next(x for x in candidates if x.label == "approximation_degree[x]")
    C = c.columns(ctx)
    assert C.shape == (len(rec), 3, 6)
    for j in range(3):  # translational errors: a displacement along their own direction only
        others = [k for k in range(3) if k != j]
        assert np.abs(C[:, others, j]).max() == 0 and np.abs(C[:, j, j]).max() > 0.5
