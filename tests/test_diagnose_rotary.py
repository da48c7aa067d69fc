"""Diagnosis candidates for rotary axes: each rotary axis' reversal and its angular periodic (encoder) error.

The five-axis example (examples/five_axis_cafxyz.toml) draws ``rotary_reversal`` (B/2 against the approach direction
of each rotary axis) and ``rotary_encoder`` (E1 sin(theta + phi1) + E2 sin(2 theta + phi2) per rotary axis); the
identification models neither, and before these candidates the diagnosis said NOT EXPLAINED and named nothing.

What is checked, against numbers the diagnosis does not make:

* truth.json's ``drawn`` and ``diagnosable`` against numpy's own draws from each source's documented stream
  (``SeedSequence(seed, spawn_key=(block, crc32(name)))``, blocks of 64 trials) and the closed form of a phase-shifted
  sine's Fourier coefficients (E sin(theta + phi) = E sin(phi) cos(theta) + E cos(phi) sin(theta));
* the candidates' columns against central finite differences of the simulator's own input, an angle added to the
  commanded angle (``axis_offset.<r>``, which the sources draw), for a rotary axis turning about +Z and about -Z;
* the diagnosis of recordings the simulator draws with its own options (``--set``, here ``load_config(..., sets)``):
  a large reversal or a large encoder error of C named, within 3 u of what truth.json says was drawn, and A's not
  named; both sources off, no rotary candidate named.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from mtbudget.config import load_config
from mtbudget.contracts import DiagnosisContext
from mtbudget.diagnose import _expand_per_rotary_axis, diagnose
from mtbudget.model import MeasurementModel
from mtbudget.recording import read_recording, write_recording
from mtbudget.report_diagnosis import diagnosis_report, diagnosis_text
from mtbudget.scenario import build_scenario
from mtbudget.simulate import simulate_recording, stream
from plugins.physics import RotaryPeriodicError, RotaryReversal, all_candidates

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "five_axis_cafxyz.toml"
#: a coarser mesh than the example's (2 x 2 x 2 positions instead of 3 x 3 x 3, the same 5 A x 4 C angles and two
#: tools: 320 points), so a diagnosis takes seconds; the full example is in the slow tests
SMALL = ("mesh.step_x=400 mm", "mesh.step_y=400 mm", "mesh.step_z=300 mm")
ROTARY_EFFECTS = ("rotary_reversal", "rotary_periodic_error")


def _simulate(tmp_path, sets=(), name="rec", seed=None, trial=0):
    cfg = load_config(EXAMPLE, list(sets))
    sc = build_scenario(cfg)
    rec, truth = simulate_recording(sc, seed, trial)
    folder = tmp_path / name
    write_recording(rec, folder, truth=truth)
    return read_recording(folder), truth, sc


def _context(rec):
    """A diagnosis context at the nominal machine (no baseline fit needed for columns)."""
    model = MeasurementModel.for_plan(rec.machine, rec.plan)
    theta = np.zeros(model.n_params)
    P_W = model.machine_points(theta, rec.fixed_inputs())[0]
    return DiagnosisContext(rec, model, np.zeros(6), theta, P_W, P_W.copy())


def _per_axis(cls, ctx):
    return {c.axis: c for c in cls().per_rotary_axis(ctx)}


# --------------------------------------------------------------------- truth.json
def test_truth_gives_the_rotary_draws_of_the_trial(tmp_path):
    """B of each rotary axis and the encoder's Fourier coefficients, against numpy's draws from the sources' streams:
    the reversal one (n, 1) uniform draw per axis in turn (A, then C); the encoder per axis the two amplitudes then
    the two phases as (2, n, 1) draws."""
    seed, trial = 7, 5
    rec, truth, sc = _simulate(tmp_path, SMALL, seed=seed, trial=trial)
    by = {s.name: s for s in sc.sources}
    rng = stream(seed, 0, by["rotary_reversal"])
    B = {r: rng.uniform(0, 20e-6, (64, 1))[trial, 0] * 1e6 for r in "ac"}  # B_max 20 urad, in urad
    rng = stream(seed, 0, by["rotary_encoder"])
    coef = {}
    for r in "ac":
        amp = rng.uniform(0, 10e-6, (2, 64, 1))[:, trial, 0] * 1e6
        ph = rng.uniform(0, 2 * np.pi, (2, 64, 1))[:, trial, 0]
        # E sin(n theta + phi) = E sin(phi) cos(n theta) + E cos(phi) sin(n theta); both axes turn about +X, +Z
        coef[r] = [amp[0] * np.sin(ph[0]), amp[0] * np.cos(ph[0]), amp[1] * np.sin(ph[1]), amp[1] * np.cos(ph[1])]
    drawn, named = truth["drawn"], truth["diagnosable"]
    for r in "ac":
        e = drawn["rotary_reversal"][f"B_{r}"]
        assert e["value"] == pytest.approx(B[r], rel=1e-9) and e["unit"] == "urad"
        assert e["effect"] == f"rotary_reversal[{r}]" and "B/2 short" in e["meaning"]
        assert named[f"rotary_reversal[{r}]"]["value"] == pytest.approx(B[r], rel=1e-9)
        h = drawn["rotary_encoder"][f"harmonics_{r}"]
        assert h["unit"] == "urad" and h["effect"] == f"rotary_periodic_error[{r}]"
        seen = named[f"rotary_periodic_error[{r}]"]["value"]
        if r == "a":  # -90 ... 90 deg in 45 deg steps: every term seen
            assert seen == pytest.approx(coef[r], rel=1e-7, abs=1e-9)
        else:  # 0, 90, 180, 270 deg: sin 2C is zero at every angle, the others seen
            assert seen[3] is None and seen[:3] == pytest.approx(coef[r][:3], rel=1e-7, abs=1e-9)


def test_a_rotary_source_on_one_axis_draws_the_same_numbers_and_zeros_the_other(tmp_path):
    seed, trial = 7, 5
    _, truth, sc = _simulate(tmp_path, SMALL + ("sources.rotary_reversal.axes=c", "sources.rotary_encoder.axes=c"),
                             seed=seed, trial=trial)
    _, full, _ = _simulate(tmp_path, SMALL, name="full", seed=seed, trial=trial)
    named, ref = truth["diagnosable"], full["diagnosable"]
    assert named["rotary_reversal[a]"]["value"] == 0.0
    assert named["rotary_reversal[c]"]["value"] == pytest.approx(ref["rotary_reversal[c]"]["value"], rel=1e-12)
    assert named["rotary_periodic_error[a]"]["value"] == [0.0, 0.0, 0.0, 0.0]
    assert named["rotary_periodic_error[c]"]["value"][:3] == pytest.approx(
        ref["rotary_periodic_error[c]"]["value"][:3], rel=1e-12)


def test_a_wrong_axes_word_is_one_line():
    from mtbudget.errors import MtbudgetError

    with pytest.raises(MtbudgetError, match="axes"):
        build_scenario(load_config(EXAMPLE, ["sources.rotary_reversal.axes=q"]))


# --------------------------------------------------------------------- columns
@pytest.mark.parametrize("direction", ["+z", "-z"])
def test_columns_are_the_chain_turned_by_the_angle(tmp_path, direction):
    """Each column against the central difference of the simulator's angle offset: the reversal's -dir/2 per rad of
    B; the periodic error's cos/sin(n theta) per rad of the coefficient, about +Z (ECC: an offset about -Z is minus
    it)."""
    rec, _, _ = _simulate(tmp_path, SMALL + (f"rotary.C.direction={direction}",))
    ctx = _context(rec)
    sign = 1.0 if direction == "+z" else -1.0
    th, d = rec.plan.angles["c"], rec.plan.direction_of("c")
    eps = 1e-6

    def fd(offset):
        P = [ctx.model.machine_points(ctx.theta, {**rec.fixed_inputs(), "axis_offset.c": (s * eps * offset)[None]})[0]
             for s in (1, -1)]
        return (P[0] - P[1]) / (2 * eps)

    rev = _per_axis(RotaryReversal, ctx)["c"]
    assert rev.requires(ctx) is None
    C = rev.columns(ctx)
    ref = fd(-d / 2)
    assert np.abs(ref).max() > 50  # mm per rad: a lever of some 100 mm
    assert np.abs(C[:, :, 0] - ref).max() < 1e-6 * np.abs(ref).max()
    per = _per_axis(RotaryPeriodicError, ctx)["c"]
    assert per.requires(ctx) is None and per.kept == ["c1", "s1", "c2"]
    C = per.columns(ctx)
    for j, f in enumerate((np.cos(th), np.sin(th), np.cos(2 * th))):
        ref = fd(sign * f)
        assert np.abs(C[:, :, j] - ref).max() < 1e-6 * np.abs(ref).max(), j
    assert not C[:, :, 3].any()  # sin 2C is zero at 0, 90, 180, 270 deg: left out


def test_what_a_recording_cannot_separate_is_skipped_with_its_reason(tmp_path):
    rec, _, _ = _simulate(tmp_path, SMALL + ('rotary.A.angles=["0 deg", "90 deg"]',))
    ctx = _context(rec)
    assert "2 distinct angles" in _per_axis(RotaryPeriodicError, ctx)["a"].requires(ctx)
    # only the points approached from + on C: its reversal cannot be seen
    folder = tmp_path / "one_side"
    src = tmp_path / "rec"
    folder.mkdir()
    (folder / "recording.toml").write_text((src / "recording.toml").read_text())
    with open(src / "points.csv", newline="") as fi, open(folder / "points.csv", "w", newline="") as fo:
        rows = csv.reader(fi)
        head = next(rows)
        w = csv.writer(fo)
        w.writerow(head)
        w.writerows(r for r in rows if r[head.index("dir_c")] == "1")
    ctx = _context(read_recording(folder))
    assert "approached from one side only (dir_c)" in _per_axis(RotaryReversal, ctx)["c"].requires(ctx)
    assert _per_axis(RotaryReversal, ctx)["a"].requires(ctx) is None


def test_a_three_axis_recording_gets_no_rotary_candidate():
    from mtbudget.config import example_recording

    ctx = _context(read_recording(example_recording("reversal_y")))
    labels = [c.label for c in _expand_per_rotary_axis(all_candidates(), ctx)]
    assert not any(lb.startswith(ROTARY_EFFECTS) for lb in labels)
    assert "reversal[x]" in labels


# --------------------------------------------------------------------- the diagnosis
def _rotary_named(d):
    """Labels of rotary candidates the diagnosis names: findings, and partial effects of an unexplained recording."""
    labels = [f.candidate.label for f in d.findings]
    labels += [p.get("effect", "") + (f"[{p['axis']}]" if p.get("axis") else "")
               for p in ((d.unexplained or {}).get("partial") or [])]
    return [lb for lb in labels if lb.startswith(ROTARY_EFFECTS)]


def _finding(d, label):
    return next((f for f in d.findings if f.candidate.label == label), None)


def test_a_large_reversal_of_c_is_named_within_3u(tmp_path):
    """C's reversal drawn in [0, 150] urad (A's off), C's encoder error off (A's at the example's values): named,
    within 3 u of truth.json's value; A's reversal not named.  C's encoder error is off for the reason of the next
    test: on this plan its part at 0 deg looks like a reversal (the example's draw, 5.9 urad there, moves B by 1.7 u)."""
    rec, truth, _ = _simulate(tmp_path, SMALL + ("sources.rotary_reversal.B_max=150 urad",
                                                 "sources.rotary_reversal.axes=c", "sources.rotary_encoder.axes=a"))
    B = truth["diagnosable"]["rotary_reversal[c]"]["value"]
    assert B > 40  # the premise: large (the draw of the example's seed is 71 urad)
    d = diagnose(rec, data_driven=False)
    f = _finding(d, "rotary_reversal[c]")
    assert f is not None, diagnosis_text(d)
    est, u = f.estimate[0], f.uncertainty[0]
    assert f.unit == "urad" and abs(est - B) < 3 * u, (est, u, B)
    assert "rotary_reversal[a]" not in _rotary_named(d)
    # the outputs carry it with its unit: the text, the JSON, the Markdown report
    assert "FOUND rotary_reversal (c)" in diagnosis_text(d) and "µrad" in diagnosis_text(d)
    j = next(x for x in d.to_dict()["findings"] if x["effect"] == "rotary_reversal")
    assert j["axis"] == "c" and j["estimate"]["unit"] == "urad"
    md = diagnosis_report(d, rec, tmp_path / "report").read_text()
    assert "rotary\\_reversal[c]" in md and "µrad" in md  # Markdown-escaped


def test_a_large_encoder_error_of_c_is_named_within_3u(tmp_path):
    """C's encoder error drawn with amplitudes in [0, 100] urad (A's off), C's reversal off (A's at the example's
    value): rotary_periodic_error[c] named, each term it fits within 3 u of truth.json's coefficients.

    C's reversal is off because this plan approaches C = 0 deg from - and every other angle from +: a reversal of C
    is then (nearly) an error at 0 deg, which on four angles is 1/4 + cos(C)/2 + cos(2C)/4 of it; the example's
    9.5 urad, too small to be named beside 100 urad of encoder error, moves c1 by 4.8 urad (2.3 u) and c2 by 2.4."""
    rec, truth, _ = _simulate(tmp_path, SMALL + ("sources.rotary_encoder.E_max=100 urad",
                                                 "sources.rotary_encoder.axes=c", "sources.rotary_reversal.axes=a"))
    coef = truth["diagnosable"]["rotary_periodic_error[c]"]["value"]
    assert max(abs(x) for x in coef[:3]) > 30
    d = diagnose(rec, data_driven=False)
    f = _finding(d, "rotary_periodic_error[c]")
    assert f is not None, diagnosis_text(d)
    assert f.candidate.kept == ["c1", "s1", "c2"] and f.unit == "urad" and len(f.estimate) == 3
    for x, ux, t in zip(f.estimate, f.uncertainty, coef[:3]):
        assert abs(x - t) < 3 * ux, (f.estimate, f.uncertainty, coef)
    assert "rotary_periodic_error[a]" not in _rotary_named(d)


def test_no_rotary_source_no_rotary_name(tmp_path):
    """Both rotary sources off (everything else at the example's values): no rotary candidate named, neither as a
    finding nor as a partial effect of an unexplained recording."""
    rec, truth, _ = _simulate(tmp_path, SMALL + ("sources.rotary_reversal.B_max=0 urad",
                                                 "sources.rotary_encoder.E_max=0 urad"))
    assert truth["diagnosable"]["rotary_reversal[c]"]["value"] == 0.0
    d = diagnose(rec, data_driven=False)
    assert not _rotary_named(d), diagnosis_text(d)
    tested = {c["effect"] + f"[{c['axis']}]" for c in d.to_dict()["considered"]}
    assert {"rotary_reversal[a]", "rotary_reversal[c]", "rotary_periodic_error[a]",
            "rotary_periodic_error[c]"} <= tested


# --------------------------------------------------------------------- the full example (about a minute each)
def _within_3u(f, truth):
    """Every term of a rotary finding within 3 u of what truth.json says was drawn (the terms the plan sees)."""
    v = truth["diagnosable"][f.candidate.label]["value"]
    v = v if isinstance(v, list) else [v]
    kept = getattr(f.candidate, "kept", None)
    v = [v[["c1", "s1", "c2", "s2"].index(t)] for t in kept] if kept else v
    return all(abs(e - t) < 3 * u for e, u, t in zip(f.estimate, f.uncertainty, v))


@pytest.mark.slow
def test_the_full_example_with_a_large_reversal_of_c_names_it_and_explains_the_recording(tmp_path):
    """The example's plan and every source at its values, but C's reversal drawn in [0, 150] urad and A's off: the
    reversal of C and both encoder errors named (each within 3 u of truth.json), the recording explained."""
    rec, truth, _ = _simulate(tmp_path, ("sources.rotary_reversal.B_max=150 urad", "sources.rotary_reversal.axes=c"))
    d = diagnose(rec)
    assert d.unexplained is None, diagnosis_text(d)
    rotary = [f for f in d.findings if f.candidate.effect in ROTARY_EFFECTS]
    assert "rotary_reversal[c]" in {f.candidate.label for f in rotary}, diagnosis_text(d)
    assert "rotary_reversal[a]" not in {f.candidate.label for f in rotary}
    for f in rotary:
        assert _within_3u(f, truth), (f.candidate.label, f.estimate, f.uncertainty)


@pytest.mark.slow
def test_the_full_example_with_a_large_encoder_error_of_c_names_it(tmp_path):
    rec, truth, _ = _simulate(tmp_path, ("sources.rotary_encoder.E_max=100 urad", "sources.rotary_encoder.axes=c",
                                         "sources.rotary_reversal.axes=a"))
    d = diagnose(rec)
    f = _finding(d, "rotary_periodic_error[c]")
    assert f is not None and _within_3u(f, truth), diagnosis_text(d)
    assert "rotary_periodic_error[a]" not in _rotary_named(d)


@pytest.mark.slow
def test_the_full_example_without_rotary_sources_names_no_rotary_candidate(tmp_path):
    rec, _, _ = _simulate(tmp_path, ("sources.rotary_reversal.B_max=0 urad", "sources.rotary_encoder.E_max=0 urad"))
    d = diagnose(rec)
    assert not _rotary_named(d), diagnosis_text(d)


@pytest.mark.slow
def test_the_example_as_it_is_names_only_rotary_effects_it_drew(tmp_path):
    """The example unchanged (`mtbudget simulate examples/five_axis_cafxyz.toml`): whatever rotary candidate it names,
    as a finding or a partial effect, the trial drew (more than 1 urad)."""
    rec, truth, _ = _simulate(tmp_path)
    d = diagnose(rec)
    named = _rotary_named(d)
    assert named, diagnosis_text(d)
    for lb in named:
        v = truth["diagnosable"][lb]["value"]
        assert any(abs(x) > 1 for x in (v if isinstance(v, list) else [v]) if x is not None), lb


def test_a_rotary_source_on_an_axis_the_machine_does_not_have_is_refused_in_one_line(tmp_path):
    """CAFXYZ has A and C: `axes = "b"` would act on nothing (its row zero, its u printed): one line, exit 2."""
    from click.testing import CliRunner

    from mtbudget.cli import main

    res = CliRunner().invoke(main, ["run", str(EXAMPLE), "--trials", "4", "--attribution-trials", "0", "--quiet",
                                    "--set", "sources.rotary_reversal.axes=c, b", "--log", str(tmp_path / "x.mcap")])
    assert res.exit_code == 2 and res.output.count("\n") == 1, res.output
    assert "sources.rotary_reversal.axes: the machine has no rotary axis B (its rotary axes: A, C)" in res.output
