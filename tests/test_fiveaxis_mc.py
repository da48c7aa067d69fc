"""The Monte Carlo of a five-axis verification (issue 26): the per-point map against a linear propagation written
here (finite differences of simulate -> identify -> compensate), replay bit for bit, the rotary sources against their
definitions, the configuration's strict reading of [rotary]."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from conftest import compensated_field_propagation
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.config import bundled_config, load_config, parse_config
from mtbudget.errors import ConfigError
from mtbudget.identify import identify
from mtbudget.runner import run
from mtbudget.scenario import build_scenario



def small_five_axis(sources=("tracker_noise", "repeatability"), c_angles=("0 deg", "120 deg", "240 deg"),
                    steady_tracker=True, **edits):
    """The bundled CAFXYZ example on a smaller plan: 2 x 2 x 2 linear points at 3 A x 3 C angles, two tools;
    steady_tracker: the tracker's angular noise the same in every trial (angular_sd 0)."""
    raw = copy.deepcopy(load_config(bundled_config("five_axis_cafxyz")).source)
    raw["mesh"] = {"x": ["-200 mm", "200 mm"], "y": ["-200 mm", "200 mm"], "z": ["-100 mm", "200 mm"],
                   "step_x": "400 mm", "step_y": "400 mm", "step_z": "300 mm"}
    raw["rotary"]["A"]["angles"] = ["-90 deg", "0 deg", "60 deg"]
    raw["rotary"]["C"]["angles"] = list(c_angles)
    raw["machine_tool"]["max_degree"] = 1
    raw["geometric_errors"]["translational"] = ["8 um"]
    raw["geometric_errors"]["angular"] = ["20 urad"]
    raw["sources"] = {"enable": list(sources), **({"tracker_noise": {"angular_sd": "0 urad"}} if steady_tracker else {})}
    for k, v in edits.items():
        raw[k] = v
    return parse_config(raw)


@pytest.fixture(scope="module")
def tracker_run():
    cfg = small_five_axis()
    return cfg, build_scenario(cfg), run(cfg, trials=1536, attribution_trials=0)


def test_per_point_map_agrees_with_a_linear_propagation(tracker_run):
    cfg, sc, res = tracker_run
    assert len(sc.mesh_rows) == 8 * 9
    u_lin = compensated_field_propagation(sc)
    pts = res.points()
    u_mcm = np.array([p["u"]["value"] for p in pts])
    ratio = u_mcm / u_lin
    assert np.median(ratio) == pytest.approx(1.0, abs=0.05)  # the issue's +-5 %
    assert np.abs(ratio - 1).max() < 0.12  # each of 216 point-axes: 1.8 % standard error, a 5-sigma margin
    assert set(pts[0]["angles"]["value"]) == {"a", "c"} and pts[0]["angles"]["unit"] == "deg"


def test_the_identification_holds_the_datum_and_the_map_does_not_depend_on_it(tracker_run):
    cfg, sc, _ = tracker_run
    from mtbudget.model import iso_parameter

    held = [iso_parameter(sc.id_model.errors.names[j]) for j in sc.identifiability().held]
    assert "ECOC" in held and "EAOC" in held  # FORMAT-3 section 6, established here from the plan at hand
    # a truth moved along a null direction gives the same compensated field (what the datum cannot see, it cannot
    # get wrong): identify two truths that differ by ECOC and by EAOC - EAOA
    names = sc.id_model.errors.names
    base = sc.truth.predict(sc.theta[None, :], sc.pose)
    moved = sc.theta.copy()
    tn = sc.truth.errors.names
    moved[tn.index("ez(c)[O]")] += 80e-6
    moved[tn.index("ex(c)[O]")] += 60e-6
    moved[tn.index("ex(a)[O]")] -= 60e-6
    other = sc.truth.predict(moved[None, :], sc.pose)
    r1 = identify(sc.id_model, base, sc.noise)
    r2 = identify(sc.id_model, other, sc.noise)
    d = (sc.truth.machine_points(sc.theta[None])[0] - sc.id_model.machine_points(r1.theta)[0]) - (
        sc.truth.machine_points(moved[None])[0] - sc.id_model.machine_points(r2.theta)[0])
    assert np.abs(d[sc.mesh_rows].reshape(-1) @ sc.rigid_free.T).max() < 5e-4  # mm: the EYOC coupling is linear only
    assert r1.theta[0, names.index("ez(c)[O]")] == 0 and r1.theta[0, names.index("ex(c)[O]")] == 0


def test_replay_verify_is_bit_for_bit(tmp_path):
    """The bundled example, every source (the rotary ones among them), run, logged and recomputed."""
    log = tmp_path / "run.mcap"
    r = CliRunner().invoke(main, ["run", str(bundled_config("five_axis_cafxyz")), "--trials", "96",
                                  "--attribution-trials", "0", "--log", str(log), "--quiet"])
    assert r.exit_code == 0, r.output
    v = CliRunner().invoke(main, ["replay", str(log), "--verify"])
    assert v.exit_code == 0 and "bit for bit identical" in v.output, v.output


def test_rotary_reversal_stops_half_short_against_the_approach(tracker_run):
    cfg, sc, _ = tracker_run
    from mtbudget.plugins import default_host

    src = {s.name: s for s in default_host().sources()}["rotary_reversal"]
    out = src.sample_internal(4000, np.random.default_rng(3), sc.context)
    assert set(out) == {"axis_offset.a", "axis_offset.c"}
    for r in "ac":
        d = sc.plan.angle_direction[r]
        half = -out[f"axis_offset.{r}"] / d[None, :]  # B/2 of each trial, the same at every point
        assert np.allclose(half, half[:, :1])
        B = 2 * half[:, 0]
        assert 0 <= B.min() and B.max() <= 20e-6
        assert np.std(B) == pytest.approx(20e-6 / np.sqrt(12), rel=0.05)  # rectangular [0, B_max]


def test_rotary_encoder_is_an_angle_dependent_error(tracker_run):
    cfg, sc, _ = tracker_run
    from mtbudget.plugins import default_host

    src = {s.name: s for s in default_host().sources()}["rotary_encoder"]
    out = src.sample_internal(20000, np.random.default_rng(5), sc.context)["axis_offset.c"]
    # at a random angle its mean square is 2 * E_max^2 / 3 / 2: the source's stated standard uncertainty
    rms = np.sqrt((out**2).mean())
    assert rms == pytest.approx(src.standard_uncertainty().to("urad").magnitude * 1e-6, rel=0.03)
    c = sc.plan.angles["c"]
    same = np.isclose(c[None, :], c[:, None])
    i, j = np.argwhere(~same)[0]
    assert not np.allclose(out[:, i], out[:, j])  # depends on the angle


def test_three_axis_runs_do_not_select_rotary_sources():
    sc = build_scenario(load_config())
    assert not {"rotary_repeatability", "rotary_reversal", "rotary_encoder"} & {s.name for s in sc.sources}
    raw = copy.deepcopy(load_config().source)
    raw["sources"]["add"] = ["rotary_encoder"]
    with pytest.raises(ConfigError, match="acts on rotary axes"):
        build_scenario(parse_config(raw))


@pytest.mark.parametrize("edit,pattern", [
    (lambda r: r["rotary"].pop("C"), r"rotary\.C: machine 'CAFXYZ' has a rotary axis C but no \[rotary\.C\]"),
    (lambda r: r["rotary"]["C"].update(direction="+x"), r"rotary\.C\.direction: '\+x' does not match axis C"),
    (lambda r: r["rotary"]["A"].update(angles=["30 deg", "390 deg"]), r"rotary\.A\.angles: one angle only.*EYOA"),
    (lambda r: r["rotary"]["A"].update(angles=["30"]), r"rotary\.A\.angles\[0\].*explicit unit"),
    (lambda r: r["rotary"].update(B={"pivot": ["0 mm"] * 3, "direction": "+y", "angles": ["0 deg", "9 deg"]}),
     r"rotary\.B: machine 'CAFXYZ' has no rotary axis B"),
    (lambda r: r["tracker"].update(mount="bed"), r"tracker\.mount: .*sees none of the workpiece-side axes"),
    (lambda r: r["rotary"]["C"].update(pivot=["1 mm", "2 mm"]), r"rotary\.C\.pivot: expected \[x, y, z\]"),
    (lambda r: r["rotary"]["C"].update(pivott=["1 mm", "2 mm", "3 mm"]), r"rotary\.C\.pivott.*did you mean 'pivot'"),
    (lambda r: r["geometric_errors"].update(rotary={"EXOB": "3 um"}), r"geometric_errors\.rotary\.EXOB"),
])
def test_bad_rotary_configuration_is_one_line(tmp_path, edit, pattern):
    raw = copy.deepcopy(load_config(bundled_config("five_axis_cafxyz")).source)
    edit(raw)
    import re

    with pytest.raises(ConfigError) as exc:
        parse_config(raw)
    msg = str(exc.value)
    assert "\n" not in msg and re.search(pattern, msg), msg


def test_simulate_identify_compensate_a_five_axis_recording(tmp_path):
    """simulate writes format 3 with the rotary truth; identify reads it back within its u (every parameter not held
    by the datum); compensate lists the same rotary location errors with u in neutral-json and neutral-csv."""
    import json

    cfg = tmp_path / "five.toml"
    # no linear-axis errors: the identification states the rotary errors in the frame the linear axes define (ISO
    # 230-1's convention: X's line, the XY plane), which a simulated straightness P1 would turn (docs/model.md)
    cfg.write_text(bundled_config("five_axis_cafxyz").read_text().replace(
        'disable = ["approximation_degree"]', 'enable = ["tracker_noise", "repeatability"]').replace(
        'translational = ["8 um", "3 um"]', 'translational = ["0 um", "0 um"]').replace(
        'angular = ["20 urad", "8 urad"]', 'angular = ["0 urad", "0 urad"]').replace(
        'squareness = "30 urad"', 'squareness = "0 urad"'))
    out = tmp_path / "sim"
    r = CliRunner().invoke(main, ["simulate", str(cfg), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert 'format = "mtbudget-recording/3"' in (out / "recording.toml").read_text()
    truth = json.loads((out / "truth.json").read_text())["rotary_axes"]["errors"]
    r = CliRunner().invoke(main, ["identify", str(out), "--json"])
    assert r.exit_code == 0, r.output
    ident = json.loads(r.output)
    held = set(ident["datum"]["held"])
    assert {"ECOC", "EAOC"} <= held and all(h[:3] in ("ECY", "ECZ") for h in held - {"ECOC", "EAOC"})
    by_iso = {p["iso"]: p for p in ident["parameters"]}
    # each parameter's identified value is its truth minus what the held ones' truths map onto it
    combos = {c[0]["iso"]: {e["iso"]: e["weight"] for e in c} for c in ident["not_identifiable"]}
    for iso, t in truth.items():
        p = by_iso[iso]
        if iso in held:
            assert p["value"] == 0 and p.get("datum")
            continue
        expect = t - sum(w.get(iso, 0.0) * truth[h] for h, w in combos.items() if h in truth)
        assert abs(p["value"] - expect) < 4 * p["uncertainty"] + 0.05, (iso, p, expect)
    js = tmp_path / "c.json"
    r = CliRunner().invoke(main, ["compensate", str(out), "--format", "neutral-json", "--out", str(js)])
    assert r.exit_code == 0, r.output
    rot = {v["iso"]: v for v in json.loads(js.read_text())["rotary_location_errors"]["values"]}
    assert set(rot) == set(truth)
    for iso, v in rot.items():
        assert v["value"] == pytest.approx(by_iso[iso]["value"], abs=1e-9)
        assert (v["u"] is None) == (iso in held)
    csv = tmp_path / "c.csv"
    r = CliRunner().invoke(main, ["compensate", str(out), "--format", "neutral-csv", "--out", str(csv)])
    assert r.exit_code == 0, r.output
    assert sum(line.startswith("rotary_") for line in csv.read_text().splitlines()) == len(truth)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["CAFXYZ", "FXYZCB"])
def test_diagnose_a_five_axis_null_names_nothing(tmp_path, kind):
    """diagnose's baseline fit and locate on a five-axis recording written by the independent generator: a machine
    with rotary location errors and nothing else is explained by the baseline (no named effect)."""
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from fiveaxis_generator import make_recording

    make_recording(tmp_path / "r", kind, seed=4)
    r = CliRunner().invoke(main, ["diagnose", str(tmp_path / "r"), "--json"])
    assert r.exit_code == 0, r.output[-2000:]
    d = json.loads(r.output[r.output.index("{"):])
    assert not d.get("findings"), d.get("findings")
    assert 0.8 < d["baseline"]["chi2_per_dof"] < 1.25


def test_the_field_at_the_mesh_is_the_chain_at_the_mesh_rows_alone():
    """Scenario.evaluate without an identification's points evaluates the compiled chain at the mesh rows only
    (machine.kernel_rows, issue 31): bit for bit the whole plan's chain at those rows, and the matrix-form chain
    (machine.chain_reference, written apart) to round-off, for a five-axis and a three-axis machine."""
    from mtbudget.machine import chain_reference

    rng = np.random.default_rng(31)
    for cfg in (small_five_axis(), load_config()):  # the paper's three-axis configuration beside it
        sc = build_scenario(cfg)
        for model in (sc.truth, sc.id_model):
            th = rng.standard_normal((5, model.n_params)) * 1e-3
            F = sc.evaluate(model, th)
            assert F.shape == (5, len(sc.mesh_rows), 3)
            assert np.array_equal(F, model.machine_points(th)[:, sc.mesh_rows])
            ref = chain_reference(model.config, model.errors, th, model.inputs, B=model.B)[:, sc.mesh_rows]
            assert np.abs(F - ref).max() < 1e-9  # mm
            assert np.array_equal(sc.evaluate(model, th[2:4]), F[2:4])  # a trial's points are its own


def test_the_gufs_identifications_in_pieces_are_those_of_one_call(monkeypatch):
    """point_guf's central differences identify in calls of whole chunks of identify's (budget._identified, issue 31:
    a five-axis run's GUF peaked at 1.5 GB in one call): every theta bit for bit that of one identify call on all
    the trials (the trials of a chunk share their iteration matrix, so the chunks must be the same)."""
    from mtbudget import budget
    from mtbudget.identify import default_chunk
    from mtbudget.simulate import simulate_block

    sc = build_scenario(small_five_axis())
    meas0 = simulate_block(sc, 0, 1, 0, active=[])[0]
    chunk = default_chunk(meas0.shape[1], sc.id_model.n_params)
    meas = meas0 + np.random.default_rng(4).normal(0, 2e-3, (2 * chunk + 5, meas0.shape[1], 3))
    whole = identify(sc.id_model, meas, sc.noise).theta
    monkeypatch.setattr(budget, "GUF_TRIALS_PER_CALL", 1)  # one chunk per call: three calls
    assert np.array_equal(budget._identified(sc, meas, None), whole)
    monkeypatch.setattr(budget, "GUF_TRIALS_PER_CALL", 10 * len(meas))  # one call
    assert np.array_equal(budget._identified(sc, meas, None), whole)
