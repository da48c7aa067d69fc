"""Findings tested against explanations outside the library (issue 16): a finding that an alternative the library
does not hold explains about as well is declared confounded with it, never named alone; a finding the plan can
separate from every alternative is still named alone.

The recordings come from mtbudget.testing's generator (the opt-in sources of plugins/machine_tool.py and of the
simulated physics, written independently of the candidates' columns); about 1 s per case.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from mtbudget.diagnose import diagnose
from mtbudget.errors import PluginError
from mtbudget.report_diagnosis import diagnosis_report, diagnosis_text
from mtbudget.testing import (
    case_config,
    declared_outside,
    named,
    named_alone,
    simulate_case,
    wrong_named,
)



def _recording(tmp, seed, effects, multiple, sensor=None):
    """A simulated recording; ``sensor``: (column, rate K/s, cycle amplitude K, period s) replaces that sensor's
    drift by a cycle (a temperature that goes up and then down)."""
    cfg, truth = case_config(seed, effects, multiple)
    if sensor:
        col, rate, amp, period = sensor
        for s in cfg.sensors:
            if s.sensor.column == col:
                s.rate, s.cycle_amplitude, s.cycle_period, s.cycle_phase = rate, amp, period, 1.0
    return simulate_case(cfg, Path(tmp) / "rec"), truth


@pytest.fixture(scope="module")
def spindle_against_original(original_library, tmp_path_factory):
    """Spindle growth along the tool (3x noise, its sensor warming steadily) against a library without it: named
    tracker_drift in 100 % of calibration cases before (docs/diagnose.md)."""
    out = []
    for seed in (23_000, 23_003):
        rec, _ = _recording(tmp_path_factory.mktemp("spindle"), seed, (("spindle_growth", None),), 3.0)
        out.append((rec, diagnose(rec, original_library)))
    return out


def test_out_of_library_drift_is_declared_confounded_not_named_alone(spindle_against_original):
    for _, d in spindle_against_original:
        assert d.findings, "the drift of the tool points is significant: something is named"
        assert not named_alone(d), named(d)
        assert not wrong_named(d, {("spindle_growth", None)})
        for f in d.findings:
            kinds = {a["kind"] for a in f.outside}
            assert f.outside and not f.named_alone
            if f.candidate.effect == "tracker_drift":
                # the declared physical alternative (the same displacement of every point) and a data-driven term that
                # follows a temperature (the spindle head's sensor, or another one warming in step)
                assert "declared by the candidate" in kinds
                assert any(a["kind"] == "data-driven" and a["test"]["p_value"] >= a["test"]["level"]
                           for a in f.outside)
        text = diagnosis_text(d)
        assert "CONFOUNDED WITH AN ALTERNATIVE OUTSIDE THE LIBRARY" in text
        assert "fixed reflector on the table" in text


def test_the_declaration_reaches_the_json_and_the_report(spindle_against_original, tmp_path):
    rec, d = spindle_against_original[0]
    js = json.loads(json.dumps(d.to_dict()))
    f = js["findings"][0]
    assert {"confounded_with", "confounded_outside_library", "named_alone", "status"} <= set(f)
    assert f["named_alone"] is False and f["status"] == "confounded with an alternative outside the library"
    for a in f["confounded_outside_library"]:
        assert {"alternative", "kind", "description", "separating_measurement", "test"} <= set(a)
        if a["kind"] == "data-driven":
            assert "data-driven, not a named physical effect" in a["description"]
            assert a["test"]["p_value"] >= a["test"]["level"] == js["settings"]["alpha"]
            ho = a["held_out"]
            assert ho["residuals"] > 0 and ho["chi2_per_residual_with_alternative"] > 0
    md = diagnosis_report(d, rec, tmp_path / "rep").read_text()
    assert "Not named alone" in md and "alternative outside the library" in md
    assert "Not every finding is named alone" in md


def test_column_tilt_against_the_original_library_is_not_named_alone(original_library, tmp_path):
    """A column tilting with its sensor (3x noise): named reversal[x], air_temperature_drift or thermal_expansion[x]
    in 62 % of calibration cases before; now whatever is named is declared confounded."""
    for seed in (23_001, 23_002):
        rec, _ = _recording(tmp_path / str(seed), seed, (("column_tilt", "x"),), 3.0)
        d = diagnose(rec, original_library)
        assert not wrong_named(d, {("column_tilt", "x")}), [(f.candidate.label, f.outside) for f in d.findings]
        assert not named_alone(d)


def test_in_library_reversal_with_a_separable_plan_is_named_alone(candidates, tmp_path):
    """The plan's first point of every row is approached from the other side: a reversal is not a function of the
    run, and no alternative takes its place."""
    for seed in (30_000, 30_001):
        rec, truth = _recording(tmp_path / str(seed), seed, (("reversal", "x"),), 2.5)
        d = diagnose(rec, candidates)
        assert named_alone(d) == {("reversal", "x")}, [(f.candidate.label, f.outside) for f in d.findings]


def test_reversal_with_strictly_alternating_runs_is_confounded_with_a_change_between_runs(candidates, tmp_path):
    """The same recording without the points approached against their run's direction: x is approached from + in
    run 1 and from - in run 2 only, so a reversal is a step between the runs and the diagnosis says so."""
    rec, _ = _recording(tmp_path, 30_000, (("reversal", "x"),), 2.5)
    d_x = rec.plan.direction[:, 0]
    keep = ((rec.plan.run == 1) & (d_x > 0)) | ((rec.plan.run == 2) & (d_x < 0))
    assert 0.6 * len(rec) < keep.sum() < len(rec)
    rec.plan, rec.lt = rec.plan.subset(keep), rec.lt[keep]
    d = diagnose(rec, candidates)
    f = next(f for f in d.findings if f.candidate.label == "reversal[x]")
    assert not f.named_alone
    alt = next(a for a in f.outside if a["alternative"] == "a change between runs")
    assert alt["kind"] == "declared by the candidate" and alt["test"]["p_value"] >= alt["test"]["level"]
    assert "Repeat a run in the same direction" in diagnosis_text(d)


def test_thermal_expansion_following_a_sensor_not_linear_in_time_is_named_alone(candidates, tmp_path):
    """The x sensor goes up and down (a 0.3 K cycle of 50 min, no drift): nothing that follows time, or another
    sensor, takes the place of the expansion."""
    for seed in (800, 801):
        rec, _ = _recording(tmp_path / str(seed), seed, (("thermal_expansion", "x"),), 2.5, ("T_x", 0.0, 0.3, 3000.0))
        d = diagnose(rec, candidates)
        assert named_alone(d) == {("thermal_expansion", "x")}, [(f.candidate.label, f.outside) for f in d.findings]


def test_thermal_expansion_following_a_steady_sensor_is_declared_confounded_with_time(candidates, tmp_path):
    """The calibration's sensors warm steadily: the expansion is named, and declared confounded with the scale
    following time (the measurement that separates them: a temperature that goes up and then down)."""
    rec, _ = _recording(tmp_path, 30_000, (("thermal_expansion", "x"),), 2.5)
    d = diagnose(rec, candidates)
    assert ("thermal_expansion", "x") in declared_outside(d)
    f = d.findings[0]
    alt = next(a for a in f.outside if a["kind"] == "declared by the candidate")
    assert alt["alternative"] == "the x scale following time"
    assert "goes up and then down" in alt["separating_measurement"]


def test_a_broken_alternatives_declaration_names_the_plugin():
    from test_diagnose import LostMotion, _through_hook

    from mtbudget.config import example_recording
    from mtbudget.recording import read_recording

    class Declares(LostMotion):
        def alternatives(self, ctx):
            return [{"name": "bad", "description": "wrong shape", "separate": "None.", "columns": np.zeros((3, 3))}]

    with pytest.raises(PluginError, match=r"lost_motion\[y\].*method alternatives\(\).*shape"):
        diagnose(read_recording(example_recording("reversal_y")), _through_hook(Declares("y")))


def test_the_closed_form_scan_is_the_explicit_partial_f_test():
    """Every single-term alternative at once (closed form) equals the explicit fit with the term in the finding's
    place and the finding added to it."""
    import mtbudget.diagnose as D

    rng = np.random.default_rng(5)
    n, k, L = 400, 3, 25
    Cc = rng.normal(size=(n, k))
    Qc = D._orth(Cc)
    A = rng.normal(size=(n, L)) + 0.7 * Cc[:, [0]]  # alternatives correlated with the finding
    q = A / np.linalg.norm(A, axis=0)
    w = Cc @ np.array([0.3, -0.2, 0.1]) + rng.normal(size=n)
    ok = np.ones(L, bool)
    chi, F, p, dof = D._scan_terms(w, Qc, q, ok, n - 1)
    for j in range(L):
        chi_alt, _, Fj, dofj, pj = D._given(w, Cc, q[:, [j]], n)
        assert chi[j] == pytest.approx(chi_alt, rel=1e-9)
        assert F[j] == pytest.approx(Fj, rel=1e-7) and p[j] == pytest.approx(pj, rel=1e-6, abs=1e-12)
        assert dof == dofj[1]


def test_a_finding_is_named_alone_against_the_true_alternative_at_most_alpha_of_the_time():
    """The error the test controls: when the truth is an alternative (here one term), the finding is significant
    given it, and so could be named alone, in about alpha of the recordings (the partial F-test is exact)."""
    import mtbudget.diagnose as D

    rng = np.random.default_rng(11)
    n, alpha, trials = 300, 0.05, 2000
    a = rng.normal(size=n)
    Cc = (0.9 * a + 0.45 * rng.normal(size=n))[:, None]  # a finding that resembles the truth (correlation 0.9)
    Qc = D._orth(Cc)
    q = (a / np.linalg.norm(a))[:, None]
    rejected = 0
    for _ in range(trials):
        w = 0.5 * a + rng.normal(size=n)  # the truth: the alternative, plus unit noise
        _, _, p, _ = D._scan_terms(w, Qc, q, np.ones(1, bool), n - 1)
        rejected += p[0] < alpha
    assert abs(rejected / trials - alpha) < 4 * np.sqrt(alpha * (1 - alpha) / trials)
