"""One scenario, one simulator, one key per physical input."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.config import load_config, parse_config
from mtbudget.engine import Engine
from mtbudget.errors import ConfigError
from mtbudget.recording import read_recording
from mtbudget.runner import run
from mtbudget.scenario import build_scenario
from mtbudget.simulate import simulate_recording
from mtbudget.testing import case_config, simulate_case

SMALL = Path(__file__).parent / "data" / "small.toml"


def raw_small() -> dict:
    return copy.deepcopy(load_config(SMALL).source)


def toml_value(v) -> str:
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return str(v)


def write_toml(data: dict, path: Path):
    """A small TOML writer for the test configurations (tables, arrays of tables, strings, numbers, lists)."""
    lines = []

    def table(prefix, d):
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and not (isinstance(v, list) and v and isinstance(v[0], dict))}
        if prefix:
            lines.append(f"[{prefix}]")
        lines.extend(f"{k} = {toml_value(v)}" for k, v in scalars.items())
        for k, v in d.items():
            if isinstance(v, dict):
                table(f"{prefix}.{k}" if prefix else k, v)
            elif isinstance(v, list) and v and isinstance(v[0], dict):
                for item in v:
                    lines.append(f"[[{prefix + '.' if prefix else ''}{k}]]")
                    lines.extend(f"{a} = {toml_value(b)}" for a, b in item.items())

    table("", data)
    path.write_text("\n".join(lines) + "\n")
    return path


# ----------------------------------------------------------------------------- one simulator
def test_simulate_the_engine_and_the_calibration_harness_draw_the_same_points(tmp_path):
    cfg, _ = case_config(11, (("thermal_expansion", "x"), ("reversal", "y")), 3.0)
    sc = build_scenario(cfg)
    rec, _ = simulate_recording(sc, seed=cfg.seed, trial=0)
    meas, _, _ = Engine(sc).simulate(0)
    assert np.array_equal(rec.lt, meas[0])  # the same trial, bit for bit
    back = simulate_case(cfg, tmp_path / "case")  # written and read back like a shop's recording
    assert np.abs(back.lt - meas[0]).max() <= 0.5e-6 + 1e-12  # the 6 decimals of mm the writer keeps
    # the command line: the same configuration written as a file gives the same points
    path = write_toml(cfg.source, tmp_path / "case.toml")
    res = CliRunner().invoke(main, ["simulate", str(path), "--out", str(tmp_path / "cli"), "--no-identify"])
    assert res.exit_code == 0, res.output
    assert np.abs(read_recording(tmp_path / "cli").lt - meas[0]).max() <= 0.5e-6 + 1e-12
    # a later trial of the run is a later trial of the engine
    rec5, _ = simulate_recording(sc, seed=cfg.seed, trial=5)
    assert np.array_equal(rec5.lt, meas[5])


def test_an_effect_source_adds_its_own_physics_and_nothing_else():
    """thermal_expansion of x moves each point along x by x * CTE * (T_x - 20 degC), computed here independently."""
    cfg, truth = case_config(12, (("thermal_expansion", "x"),), 3.0)
    plain = copy.deepcopy(cfg.source)
    del plain["sources"]["thermal_expansion"]
    plain["sources"]["enable"] = ["tracker_noise", "repeatability"]
    sc_with, sc_without = build_scenario(cfg), build_scenario(parse_config(plain))
    a, _, _ = Engine(sc_with).simulate(0)
    b, _, _ = Engine(sc_without).simulate(0)
    plan = sc_with.plan
    T = plan.temperature["T_x"]  # one sensor on x: the axis temperature is its reading (K)
    cte = truth[("thermal_expansion", "x")] * 1e-6  # um/(m K) -> 1/K
    dx = plan.nominal[:, 0] * cte * (T - 293.15)  # machine frame, mm
    from mtbudget import tracker as lt

    R = lt.rotation(*sc_with.pose[3:])  # machine -> tracker frame rotation
    expected = (np.zeros((len(plan), 3)) + np.column_stack([dx, 0 * dx, 0 * dx])) @ R
    assert np.allclose(a[0] - b[0], expected, atol=2e-6)  # mm; the chain's second-order terms stay below 2 nm


# ----------------------------------------------------------------------------- one key per physical input
def test_a_physical_input_stated_twice_with_different_values_is_an_error():
    raw = raw_small()
    raw["tracker"]["angular"] = "5 urad"
    raw["sources"]["tracker_noise"]["angular_mean"] = "20 urad"
    with pytest.raises(ConfigError, match=r"sources\.tracker_noise\.angular_mean: states the physical input "
                                          r"tracker\.angular a second time"):
        build_scenario(parse_config(raw))


def test_the_same_value_twice_is_accepted_and_one_statement_sets_both():
    raw = raw_small()  # small.toml states 10 urad in both places
    sc = build_scenario(parse_config(raw))
    assert sc.noise.angular == pytest.approx(10e-6) and sc.drawn["tracker.angular"] == pytest.approx(10e-6)
    del raw["tracker"]["angular"]
    raw["sources"]["tracker_noise"]["angular_mean"] = "12 urad"  # stated by the source only: the weights follow it
    sc = build_scenario(parse_config(raw))
    assert sc.noise.angular == pytest.approx(12e-6)
    noise = [s for s in sc.sources if s.name == "tracker_noise"][0]
    assert noise.value("angular_mean", "rad") == pytest.approx(12e-6)
    raw["machine_tool"]["repeatability"] = "3 um"  # stated by the configuration only: the source draws it
    sc = build_scenario(parse_config(raw))
    rep = [s for s in sc.sources if s.name == "repeatability"][0]
    assert rep.value("R", "mm") == pytest.approx(3e-3) and sc.noise.repeatability == pytest.approx(3e-3)


def test_misstated_weights_are_an_explicit_reported_choice():
    raw = raw_small()
    raw["weights"] = {"angular": "2.5 urad"}  # the verification states a quarter of the noise it has
    res = run(parse_config(raw, SMALL), trials=64, block=32, sources=["tracker_noise"], attribution_trials=0)
    assert res.weights["angular"]["stated"] == pytest.approx(2.5e-6)
    assert res.weights["angular"]["drawn"] == pytest.approx(10e-6)
    honest = run(load_config(SMALL), trials=64, block=32, sources=["tracker_noise"], attribution_trials=0)
    assert honest.weights is None
    # transverse noise 4x what is stated: chi2/dof far above the honest run's
    assert res.summary("chi2_per_dof")["mean"] > 4 * honest.summary("chi2_per_dof")["mean"]
    from mtbudget.report import budget_text

    text = budget_text(res)
    assert "stated 2.5 µrad, drawn 10 µrad" in text.replace("  ", " ")


@pytest.mark.parametrize("edit, message", [
    (lambda r: r.setdefault("effects", {}).setdefault("thermal", {}).update(x="10 um/(m*K)")
     or r["sources"].update(thermal_expansion={"cte_x": "10 um/(m*K)"}), "stated twice, in \\[effects\\] and"),
    (lambda r: r["sources"].update(reversal={"B_x": "5 um"}), "'reversal' is configured but not enabled"),
    (lambda r: r["sources"].update(enable=["tracker_noise", "multilateration"]),
     "sources.enable: multilateration is simulated from the stations themselves .*\\[\\[stations\\]\\]"),
    (lambda r: r["sources"].update(multilateration={"stations": "4"}), "sources.multilateration: multilateration is"),
    (lambda r: r["sources"].update(disable=["multilateration"]) or r["sources"].update(enable=["tracker_nosie"]),
     "did you mean 'tracker_noise'"),
    (lambda r: r["sources"].update(enable=["tracker_nosie"]), "unknown source 'tracker_nosie'; did you mean 'tracker_noise'"),
    (lambda r: r["sources"].update(control_error={"C": "-1.5 um"}, enable=["control_error"]),
     "sources.control_error: parameter 'C' must not be negative"),
    (lambda r: r["machine_tool"].update(repeatability="-1.5 um"), "machine_tool.repeatability: a standard uncertainty must not be negative"),
    (lambda r: r["sources"].update(tracker_noise={"angular_sd": "3"}), "needs an explicit unit"),
    (lambda r: r["sources"].update(typo_key=3), "sources.typo_key: unknown key"),
    (lambda r: r["sources"].update(tracker_noise={"angular_sd": "3 ppm"}), "'3 ppm' is a ratio, not an angle"),
])
def test_source_settings_are_strict(edit, message):
    raw = raw_small()
    edit(raw)
    with pytest.raises(ConfigError, match=message):
        build_scenario(parse_config(raw, SMALL))


def test_opt_in_sources_are_off_unless_enabled():
    sc = build_scenario(load_config())
    names = {s.name for s in sc.sources}
    assert not names & {"thermal_expansion", "reversal", "multilateration", "approximation_degree", "tracker_drift"}
    raw = copy.deepcopy(load_config().source)
    raw["sources"]["add"] = ["reversal"]
    raw["sources"]["reversal"] = {"B_y": "8 um"}
    sc = build_scenario(parse_config(raw))
    rev = [s for s in sc.sources if s.name == "reversal"][0]
    assert rev.value("B_y", "mm") == pytest.approx(8e-3)


def test_context_arrays_are_read_only():
    sc = build_scenario(load_config(SMALL))
    with pytest.raises(ValueError):
        sc.context.theta[0] = 1.0
    with pytest.raises(ValueError):
        sc.context.nominal_tracker_points[0, 0] = 1.0


# ----------------------------------------------------------------------------- strict configuration
@pytest.mark.parametrize("edit, message", [
    (lambda r: r["plan"].update(rns=3), r"plan\.rns: unknown key; did you mean 'runs'\?"),
    (lambda r: r["machine_tool"].update(repeatibility="1 um"), "did you mean 'repeatability'"),
    (lambda r: r.update(sed=4), "sed: unknown key; did you mean 'seed'"),
    (lambda r: r["plan"].update(runs=2.5), r"plan\.runs: expected a whole number, got 2\.5"),
    (lambda r: r["plan"].update(runs=0), r"plan\.runs: must be at least 1"),
    (lambda r: r.update(seed="abc"), "seed: expected a whole number"),
    (lambda r: r["plan"].update(tools=[]), "plan.tools: expected at least one tool offset"),
    (lambda r: r["tracker"].update(angular=5), "needs an explicit unit"),
    (lambda r: r["tracker"].update(angular="inf urad"), "is not finite"),
    (lambda r: r["tracker"].update(distance="9**9**9 um"), "is not a quantity of the form NUMBER UNIT"),
    (lambda r: r["tracker"].update(distance_per_length=[1, 2]), "expected a quantity string"),
    (lambda r: r.update(reference_temperature="20 delta_degC"), "is a temperature difference"),
    (lambda r: r["machine_tool"].update(max_degree=-1), r"max_degree: must be between 1 and 9"),
    (lambda r: r["sensors"][0].update(positon="10 mm"), r"sensors\[0\]\.positon: unknown key; did you mean 'position'"),
    # issue 29: [placement] is checked wherever the configuration is read, not only by the placement study
    (lambda r: r.update(placement={"Lx": ["-2000 mm", "2000 mm"]}), r"placement\.Lx: unknown key; did you mean 'L'\?"),
    (lambda r: r.update(placement={"range_max": "5 furlongz"}), r"placement\.range_max: .*furlongz"),
    (lambda r: r.update(placement={"range_max": "5 s"}), r"placement\.range_max: '5 s' is not a quantity of dimension"),
    (lambda r: r.update(placement={"D": "nan mm"}), r"placement\.D: expected \[low, high\]"),
    (lambda r: r.update(placement={"D": ["nan mm", "1 mm"]}), r"placement\.D: 'nan mm' is not finite"),
    (lambda r: r.update(placement={"directions": "machin"}), r"placement\.directions: expected one of 'machine'"),
    (lambda r: r.update(placement={"tests": 0}), r"placement\.tests: must be at least 1"),
    (lambda r: r.update(placement={"angular_mean": "20 urad"}), r"placement\.angular_mean: the tracker noise is stated once"),
    (lambda r: r.update(placement={"envelope": {"x": ["0 mm", "1 mm"]}}), r"placement\.envelope: expected \{ x ="),
    # ratios are not angles, angles not ratios (pint counts both as dimension 1)
    (lambda r: r["tracker"].update(a="0.8 ppm"), r"tracker\.a: '0\.8 ppm' is a ratio, not an angle"),
    (lambda r: r["tracker"].update(angular="0.02 mm/m"), r"tracker\.angular: '0\.02 mm/m' is a ratio, not an angle"),
    (lambda r: r["tracker"].update(distance_per_length="0.8 urad"), r"distance_per_length: '0\.8 urad' is an angle, not a ratio"),
])
def test_configuration_is_strict(edit, message):
    raw = raw_small()
    edit(raw)
    with pytest.raises(ConfigError, match=message):
        parse_config(raw, SMALL)


def test_configuration_page_lists_every_key():
    """docs/configuration.md documents every key of mtbudget.config.SCHEMA in the row of its table."""
    import re

    from mtbudget.config import SCHEMA

    doc = (Path(__file__).resolve().parents[1] / "docs" / "configuration.md").read_text()
    first_cells = [line.split("|")[1].strip() for line in doc.splitlines() if line.startswith("| `")]
    missing = []
    for table, keys in SCHEMA.items():
        for k in keys:
            if table == "":
                rows = [c for c in first_cells if not c.startswith("`[")] + [c for c in first_cells if c.startswith(f"`[{k}")
                                                                              or c.startswith(f"`[[{k}")]
                ok = any(re.search(rf"\b{k}\b", c) for c in rows)
            else:
                rows = [c for c in first_cells if re.match(rf"`\[\[?{table}[\].]", c)]
                ok = any(re.search(rf"\b{k}\b", c) for c in rows)
            if not ok:
                missing.append(f"[{table}] {k}" if table else k)
    assert not missing, f"docs/configuration.md does not document {missing}"


@pytest.mark.parametrize("command", ["run", "simulate"])
def test_a_placement_typo_stops_run_and_simulate(command, tmp_path):
    """Issue 29: `run` and `simulate` accepted anything in [placement]; now one line naming the key, exit 2."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(SMALL.read_text() + '\n[placement]\nLx = ["-2000 mm", "2000 mm"]\n')
    args = [command, str(cfg), "--out", str(tmp_path / "o")] if command == "simulate" else \
        [command, str(cfg), "--trials", "4", "--log", str(tmp_path / "r.mcap"), "--quiet"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1, res.output
    assert "placement.Lx: unknown key; did you mean 'L'?" in res.output and str(cfg) in res.output


def test_a_sensor_without_noise_is_simulated_noise_free_and_says_so(tmp_path):
    """Issue 29: a deleted sensor `noise` silently became 0 K; it is the stated default (docs/configuration.md) and
    `simulate` says so for the sensors it applies to."""
    cfg = load_config(SMALL)
    assert [s.noise_stated for s in cfg.sensors] == [False] and cfg.sensors[0].noise == 0.0
    res = CliRunner().invoke(main, ["simulate", str(SMALL), "--out", str(tmp_path / "sim"), "--no-identify"])
    assert res.exit_code == 0, res.output
    assert "no reading noise stated for sensor T_x: simulated noise-free" in res.stderr
    stated = tmp_path / "stated.toml"
    stated.write_text(SMALL.read_text().replace('column = "T_x"', 'column = "T_x"\nnoise = "0.02 K"', 1))
    res = CliRunner().invoke(main, ["simulate", str(stated), "--out", str(tmp_path / "sim2"), "--no-identify"])
    assert res.exit_code == 0 and "noise" not in res.stderr
