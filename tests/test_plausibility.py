"""Strict at the boundary (issue: nonsense inputs must not produce numbers).

1. An identification no machine tool can give (a column in inches labelled mm, degrees labelled rad, a stated noise
   far below the residuals) is said by `identify` and refused by `compensate`: no controller table is written.
2. Every stated standard uncertainty obeys one plausibility rule wherever it is stated (configuration keys,
   [weights], [[stations]], the sources' linked parameters, --set, recording.toml), and trials whose identification
   did not converge are said in the output and the report.
3. Errors name the key the user wrote and the file that holds it (a base of `extends`, or "(given with --set)").
4. The reader's negative-uncertainty message is whole.
"""

import copy
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, Phase, assume, given, settings
from hypothesis import strategies as st

from mtbudget.cli import main
from mtbudget.compensate import CompensationError, build_table, identify_recording
from mtbudget.config import default_config_path, example_recording, load_config, parse_config
from mtbudget.errors import ConfigError, RecordingError
from mtbudget.identify import PLAUSIBLE_ANGLE, PLAUSIBLE_ERROR_FLOOR, PLAUSIBLE_ERROR_PER_LENGTH, implausible
from mtbudget.recording import read_recording
from mtbudget.scenario import build_scenario

HERE = Path(__file__).parent
SMALL = HERE / "data" / "small.toml"


def _copy_null(tmp_path, name="rec") -> Path:
    folder = tmp_path / name
    shutil.copytree(example_recording("null"), folder)
    for extra in folder.glob("truth.json"):
        extra.unlink()
    return folder


def _edit(path: Path, old: str, new: str):
    text = path.read_text()
    assert old in text, (old, path)
    path.write_text(text.replace(old, new, 1))


# ----------------------------------------------------------------------------- 1. implausible identifications
def test_inches_labelled_mm_are_said_by_identify_and_refused_by_compensate(tmp_path):
    folder = _copy_null(tmp_path)
    _edit(folder / "points.csv", "lt_x [mm]", "lt_x [in]")  # the values are still mm: 25.4 times too long
    res = CliRunner().invoke(main, ["identify", str(folder)])
    assert res.exit_code == 0
    assert "warning:" in res.stderr and "not an identification of the machine" in res.stderr, res.stderr
    assert "NOT AN IDENTIFICATION" in res.stdout  # a file of stdout alone carries it too
    assert "mean error before compensation" in res.stderr and "EXX" in res.stderr  # which figure, by name
    out = tmp_path / "tables" / "l.txt"
    res = CliRunner().invoke(main, ["compensate", str(folder), "--format", "linuxcnc", "--out", str(out)])
    lines = [ln for ln in res.output.splitlines() if ln.strip() and not ln.startswith("compiling")]
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert "no table is written" in lines[0] and "units" in lines[0] and "stated noise" in lines[0]
    assert not (tmp_path / "tables").exists() or not any((tmp_path / "tables").iterdir())


def test_a_stated_noise_far_below_the_residuals_is_refused(tmp_path):
    """The null recording's residuals are its 5 urad / 4 um noise; stated 1000 times smaller (still within the
    plausible bounds of a stated uncertainty) the fit's chi-square per dof is near 1e6: not an identification."""
    folder = _copy_null(tmp_path)
    toml = folder / "recording.toml"
    _edit(toml, 'angular = "5.0 urad"', 'angular = "0.005 urad"')
    _edit(toml, 'distance = "4 um"', 'distance = "0.004 um"')
    _edit(toml, 'distance_per_length = "0.8 um/m"', 'distance_per_length = "0.0008 um/m"')
    _edit(toml, 'repeatability = "1.5 um"', 'repeatability = "0.0015 um"')
    rec = read_recording(folder)
    with pytest.raises(CompensationError, match=r"no table is written: chi-square per dof [0-9.e+]+ \(at most 1000"):
        build_table(rec)


def test_degrees_labelled_rad_on_a_five_axis_machine_are_refused(tmp_path):
    sys.path.insert(0, str(HERE))
    from fiveaxis_generator import make_recording

    folder = tmp_path / "r"
    make_recording(folder, "CAFXYZ", seed=2)
    text = (folder / "points.csv").read_text()
    (folder / "points.csv").write_text(text.replace("a [deg]", "a [rad]", 1))
    with pytest.raises(CompensationError, match="chi-square per dof"):
        build_table(read_recording(folder))


@pytest.fixture(scope="module")
def null_identified():
    rec = read_recording(example_recording("null"))
    model, res = identify_recording(rec)
    return rec, model, res


@pytest.mark.parametrize("name", ["null", "thermal_x", "reversal_y", "tracker_drift"])
def test_the_bundled_recordings_are_plausible(name):
    """No false alarm: real-looking recordings, one with a thermal drift and one with reversal the model leaves out."""
    rec = read_recording(example_recording(name))
    assert implausible(identify_recording(rec)[1]) == []


def _with(res, theta):
    out = copy.copy(res)
    out.theta = np.asarray(theta, float)[None]
    return out


#: parameter -> (the largest |change| of its function per unit coefficient over the 41-point grid: along the travel
#: from its start for a positioning or straightness error, the value for an angle; the bound it is held to)
CLOSED_FORM = {
    # dx(x) = c P1(u) over 800..1200 mm changes by 2c from u = -1 to 1; bound 2 mm/m * 400 mm + 0.1 mm
    "dx(x)[P1]": (2.0, PLAUSIBLE_ERROR_PER_LENGTH * 400 + PLAUSIBLE_ERROR_FLOOR),
    # P2(u) = (3u^2 - 1)/2 changes by 1.5 from u = -1 to u = 0 (100..500 mm)
    "dy(y)[P2]": (1.5, PLAUSIBLE_ERROR_PER_LENGTH * 400 + PLAUSIBLE_ERROR_FLOOR),
    # an angular error c P1(u) reaches |c| at the ends of the travel
    "ex(y)[P1]": (1.0, PLAUSIBLE_ANGLE),
    "sxy": (1.0, PLAUSIBLE_ANGLE),
}


def _with_u(res, j, sigma):
    """``res`` with a covariance that holds only parameter ``j``'s variance sigma^2 (every function's u is then that
    of its one coefficient, in closed form)."""
    out = _with(res, res.theta[0])
    cov = np.zeros_like(res.cov_theta)
    cov[0, j, j] = sigma**2
    out._at_solution = {**res._at_solution, "cov_theta": cov}
    return out


@pytest.mark.parametrize("factor", [0.99, 1.01])
@pytest.mark.parametrize("param", sorted(CLOSED_FORM))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_bounds_of_an_error_function_in_closed_form(null_identified, param, factor, sign):
    """With no uncertainty, a function just inside its bound stands, just beyond it is refused, by its name."""
    rec, model, res = null_identified
    j = model.errors.index(param)
    per_unit, bound = CLOSED_FORM[param]
    probe = _with_u(res, j, 0.0)
    probe.theta = np.zeros((1, model.n_params))
    probe.theta[0, j] = sign * factor * bound / per_unit
    problems = implausible(probe)
    assert bool(problems) == (factor > 1), problems
    if problems:
        from mtbudget.model import iso_name

        assert iso_name(param.split("[")[0]) in problems[0]


@pytest.mark.parametrize("k", [2.9, 3.1])
@pytest.mark.parametrize("param", sorted(CLOSED_FORM))
def test_a_function_is_beyond_its_bound_only_by_more_than_3_u(null_identified, param, k):
    """u of the largest change is per_unit * sigma when only this coefficient is uncertain: at bound + 2.9 u the
    function stands (a short travel identifies loosely: noise is not a mistake), at bound + 3.1 u it is refused."""
    rec, model, res = null_identified
    j = model.errors.index(param)
    per_unit, bound = CLOSED_FORM[param]
    sigma = 0.05 * bound / per_unit
    probe = _with_u(res, j, sigma)
    probe.theta = np.zeros((1, model.n_params))
    probe.theta[0, j] = (bound + k * per_unit * sigma) / per_unit
    assert bool(implausible(probe)) == (k > 3)


# ----------------------------------------------------------------------------- 2. one rule for stated uncertainties
#: a value in the next unit up (um -> mm, urad -> mrad, um/m -> mm/m) of each physical input's default
SLIPS = {"tracker.angular": "20 mrad", "tracker.distance": "4 mm", "tracker.distance_per_length": "0.8 mm/m",
         "machine_tool.repeatability": "1.5 mm"}
#: the recording.toml key and the null recording's value of each
RECORDING_KEYS = {"tracker.angular": 'angular = "5.0 urad"', "tracker.distance": 'distance = "4 um"',
                  "tracker.distance_per_length": 'distance_per_length = "0.8 um/m"',
                  "machine_tool.repeatability": 'repeatability = "1.5 um"'}
#: a source parameter linked to each
LINKED = {"tracker.angular": ("tracker_noise", "angular_mean"), "tracker.distance": ("tracker_noise", "distance"),
          "tracker.distance_per_length": ("tracker_noise", "distance_per_length"),
          "machine_tool.repeatability": ("repeatability", "R")}


@pytest.mark.parametrize("key", sorted(SLIPS))
def test_a_unit_slip_is_refused_wherever_the_uncertainty_is_stated(tmp_path, key):
    table, name = key.split(".")
    slip = SLIPS[key]
    # the configuration key
    raw = load_config(SMALL).source
    raw[table][name] = slip
    with pytest.raises(ConfigError, match=rf"small\.toml: {key}: .*not a plausible standard uncertainty"):
        parse_config(copy.deepcopy(raw), SMALL)
    # --set
    with pytest.raises(ConfigError, match=rf"{key}: .*not a plausible standard uncertainty.*\(given with --set\)$"):
        load_config(SMALL, [f"{key}={slip}"])
    # [weights]
    raw = load_config(SMALL).source
    raw["weights"] = {name: slip}
    with pytest.raises(ConfigError, match=rf"weights\.{name}: .*not a plausible standard uncertainty"):
        parse_config(raw, SMALL)
    # the linked source parameter, the configuration key left out
    raw = load_config(SMALL).source
    raw.get(table, {}).pop(name, None)
    source, param = LINKED[key]
    raw["sources"].setdefault(source, {})[param] = slip
    with pytest.raises(ConfigError, match=rf"sources\.{source}\.{param}: .*not a plausible standard uncertainty"):
        build_scenario(parse_config(raw, SMALL))
    # recording.toml
    folder = _copy_null(tmp_path)
    line = RECORDING_KEYS[key]
    _edit(folder / "recording.toml", line, line.split("=")[0] + f'= "{slip}"')
    with pytest.raises(RecordingError, match=rf"recording\.toml, {key}: .*not a plausible standard uncertainty"):
        read_recording(folder)


def test_an_implausible_sensor_noise_is_refused():
    with pytest.raises(ConfigError, match=r"sensors\[0\]\.noise: 20 K is not a plausible"):
        load_config(default_config_path(), ["sensors.0.noise=20 K"])


def _fuzz(n):
    return settings(max_examples=n, derandomize=True, deadline=None, database=None, print_blob=True,
                    suppress_health_check=list(HealthCheck), phases=(Phase.explicit, Phase.generate, Phase.shrink))


@pytest.fixture(scope="module")
def null_folder(tmp_path_factory):
    return _copy_null(tmp_path_factory.mktemp("fuzz"))


#: the bounds as docs/configuration.md states them (internal units: rad, mm, mm/mm), written apart from the code's table
DOCUMENTED_BOUNDS = {"tracker.angular": (1e-12, 200e-6), "tracker.distance": (1e-9, 0.05),
                     "tracker.distance_per_length": (0.0, 50e-6), "machine_tool.repeatability": (1e-9, 0.1)}
UNITS = {"tracker.angular": ["urad", "mrad", "arcsec", "deg"], "tracker.distance": ["um", "mm", "nm"],
         "tracker.distance_per_length": ["um/m", "mm/m", "ppm"], "machine_tool.repeatability": ["um", "mm", "nm"]}
#: each unit in the internal unit of its key (rad, mm, mm/mm)
TO_INTERNAL = {"urad": 1e-6, "mrad": 1e-3, "arcsec": np.pi / 648000, "deg": np.pi / 180, "um": 1e-3, "mm": 1.0,
               "nm": 1e-6, "um/m": 1e-6, "mm/m": 1e-3, "ppm": 1e-6}


@_fuzz(25)
@given(data=st.data())
def test_fuzz_one_rule_in_the_recording_reader_the_configuration_and_set(null_folder, data):
    """The same stated value is accepted or refused alike by recording.toml, a configuration and --set, and refused
    exactly outside the documented bounds (an independent statement of them: the table of docs/configuration.md)."""
    key = data.draw(st.sampled_from(sorted(UNITS)))
    unit = data.draw(st.sampled_from(UNITS[key]))
    value = data.draw(st.floats(1e-4, 1e4).map(lambda v: float(f"{v:.3g}")))
    text = f"{value:g} {unit}"
    internal = value * TO_INTERNAL[unit]
    low, high = DOCUMENTED_BOUNDS[key]
    assume(all(abs(internal - b) > 1e-9 * b for b in (low, high) if b))  # not on a bound, where round-off decides
    ok = low <= internal <= high
    toml = null_folder / "recording.toml"
    original = toml.read_text()
    line = RECORDING_KEYS[key]
    try:
        toml.write_text(original.replace(line, line.split("=")[0] + f'= "{text}"', 1))
        try:
            read_recording(null_folder)
            rec_ok = True
        except RecordingError as exc:
            rec_ok = False
            assert "recording.toml" in str(exc) and key in str(exc) and "\n" not in str(exc)
    finally:
        toml.write_text(original)
    try:
        load_config(SMALL, [f"{key}={text}"])
        set_ok = True
    except ConfigError as exc:
        set_ok = False
        assert str(exc).endswith("(given with --set)") and key in str(exc), str(exc)
    assert rec_ok == set_ok == ok, (text, rec_ok, set_ok, ok)


def test_trials_that_did_not_converge_are_said_in_the_output_and_the_report(tmp_path):
    from mtbudget.report import budget_text, run_report
    from mtbudget.runner import run

    res = run(load_config(SMALL), trials=16, block=8, attribution_trials=0)
    assert res.not_converged == 0 and "WARNING" not in budget_text(res)
    res.acc.not_converged = 3  # as a run whose identification failed on 3 trials counts them
    assert "WARNING: the identification of 3 of 16 trials (18.8 %) did not converge" in budget_text(res)
    run_report(res, tmp_path / "rep")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "the identification of 3 of 16 trials" in md and "every number below includes them" in md


# ----------------------------------------------------------------------------- 3. the key the user wrote, and where
def test_an_overlay_is_named_for_the_key_it_states_not_the_base_key(tmp_path):
    over = tmp_path / "rep.toml"
    over.write_text('extends = "default"\n[machine_tool]\nrepeatability = "3 um"\n')
    with pytest.raises(ConfigError) as info:
        build_scenario(load_config(over))
    msg = str(info.value)
    assert msg.startswith(f"{over}: machine_tool.repeatability: states the physical input"), msg
    assert f"{default_config_path()}: sources.repeatability.R, a file this configuration extends" in msg
    assert "\n" not in msg


def _overlay(tmp_path, line):
    (tmp_path / "base_ok.toml").write_text(SMALL.read_text())
    over = tmp_path / "over.toml"
    over.write_text(f'extends = "base_ok.toml"\n[plan]\n{line}\n')
    return over


def test_a_base_key_is_named_in_its_own_file(tmp_path):
    base = tmp_path / "base.toml"
    base.write_text(SMALL.read_text().replace('runs = 1\n', 'runs = 1\nfeed = "-5 mm/min"\n', 1))
    assert 'feed = "-5 mm/min"' in base.read_text()
    over = tmp_path / "over.toml"
    over.write_text('extends = "base.toml"\n[plan]\nruns = 1\n')
    with pytest.raises(ConfigError, match=rf"^{base}: plan\.feed: must be positive"):
        load_config(over)
    with pytest.raises(ConfigError, match=rf"^{over}: plan\.runs: must be at least 1"):  # its own key: itself
        load_config(_overlay(tmp_path, "runs = 0"))


@pytest.mark.parametrize("sets, message", [
    (["trackr.angular=5 urad"], r"trackr: unknown key; did you mean 'tracker'\? \(given with --set\)$"),
    (["sources.tracker_noise.angular_mean=5 urad"],
     r"sources\.tracker_noise\.angular_mean: states the physical input tracker\.angular a second time.*"
     r"\(given with --set\)$"),
    (["tracker.angular=5 urad"], r"tracker\.angular: states the physical input tracker\.angular a second time.*"
                                 r"\(given with --set\)$"),
])
def test_a_key_given_with_set_says_so(sets, message):
    with pytest.raises(ConfigError, match=message):
        build_scenario(load_config(default_config_path(), sets))


def test_a_file_key_is_not_said_to_be_given_with_set():
    with pytest.raises(ConfigError) as info:  # the file's tracker_noise conflicts with --set's tracker.angular ...
        build_scenario(load_config(default_config_path(), ["sources.tracker_noise.angular_sd=1 urad", "plan.runs=2",
                                                           "tracker.distance=5 um"]))
    assert "tracker.distance" in str(info.value) and str(info.value).endswith("(given with --set)")
    cfg = load_config(default_config_path(), ["plan.runs=2"])  # ... and an error at another key of the file is not
    assert cfg.where("tracker.angular") == f"{default_config_path()}: tracker.angular"


# ----------------------------------------------------------------------------- 4. the reader's negative-u message
def test_a_negative_uncertainty_message_is_whole(tmp_path):
    folder = _copy_null(tmp_path)
    _edit(folder / "recording.toml", 'distance = "4 um"', 'distance = "-4 um"')
    with pytest.raises(RecordingError) as info:
        read_recording(folder)
    assert str(info.value).endswith("'-4 um' is negative; a standard uncertainty must not be negative")


def test_posterior_makes_no_statement_about_an_implausible_identification(tmp_path):
    from mtbudget.errors import IdentificationError
    from mtbudget.posterior import posterior

    folder = _copy_null(tmp_path)
    _edit(folder / "points.csv", "lt_x [mm]", "lt_x [in]")
    with pytest.raises(IdentificationError, match="no a posteriori statement is made: the mean error before"):
        posterior(folder, trials=4)


@pytest.mark.parametrize("key, slip, words", [
    ("probing_error", "2 mm", "2000 um is not plausible; expected 0 to 100 um"),
    ("machine_temperature_change", "300 K", "300 K is not plausible; expected 0 to 10 K"),
    ("part_temperature_u", "200 K", "200 K is not plausible; expected 0 to 10 K"),
    ("part_cte_u", "1 mm/(m*K)", "1000 um/(m*K) is not plausible; expected 0 to 50 um/(m*K)"),
])
def test_a_features_in_use_uncertainty_obeys_the_same_rule(key, slip, words):
    from mtbudget.engine import Engine

    raw = load_config(default_config_path()).source
    feature = {"name": "x length", "kind": "distance", "points": [["800 mm", "100 mm", "200 mm"],
                                                                   ["1200 mm", "100 mm", "200 mm"]], key: slip}
    if key == "part_cte_u":
        feature["part_temperature"] = "21 degC"
    raw["features"] = [feature]
    with pytest.raises(ConfigError, match=rf"^run\.toml: features\[0\]\.{key}: {re.escape(words)}"):
        Engine(build_scenario(parse_config(raw, "run.toml")))  # the engine reads [[features]]
    feature[key] = {"probing_error": "2 um", "machine_temperature_change": "0.3 K", "part_temperature_u": "0.2 K",
                    "part_cte_u": "1 um/(m*K)"}[key]
    Engine(build_scenario(parse_config(raw, "run.toml")))  # the values in use stand
    if key == "part_cte_u":  # a polymer part: PA6, CTE about 80 um/(m*K), known to about 15
        feature.update(part_cte="80 um/(m*K)", part_cte_u="15 um/(m*K)")
        Engine(build_scenario(parse_config(raw, "run.toml")))


def test_identify_warns_on_a_recording_of_several_stations_too(tmp_path):
    folder = tmp_path / "fs"
    shutil.copytree(example_recording("four_stations"), folder)
    res = CliRunner().invoke(main, ["identify", str(folder), "--json"])
    assert res.exit_code == 0 and "warning" not in res.stderr, res.stderr  # as recorded: no false alarm
    _edit(folder / "points.csv", "lt_x [mm]", "lt_x [in]")
    res = CliRunner().invoke(main, ["identify", str(folder), "--json"])
    assert res.exit_code == 0 and "not an identification of the machine" in res.stderr, res.stderr
    import json

    assert json.loads(res.stdout)["implausible"][0].startswith("chi-square per dof")


def test_a_tight_instrument_with_unmodelled_drift_is_not_called_a_unit_slip():
    """chi2/dof of 1000-10 000 with micrometre residuals (a tracking interferometer's 0.15 um noise and 10 um of
    drift the model leaves out) is diagnose's business, not a mistake: implausible says nothing; the same chi2 with
    residuals of millimetres (a unit slip in a column), or a chi2 of 10^6 whatever the residual (the stated noise
    a thousand times too small), is named."""
    from types import SimpleNamespace

    from mtbudget.config import example_recording
    from mtbudget.identify import implausible
    from mtbudget.model import MeasurementModel

    rec = read_recording(example_recording("null"))
    model = MeasurementModel.for_plan(rec.machine, rec.plan)

    def res(chi2, rms_mm):
        M = 50
        r = np.full((1, M, 3), rms_mm)
        return SimpleNamespace(chi2_per_dof=np.array([chi2]), residual=r, model=model,
                               theta=np.zeros((1, model.n_params)), cov_theta=np.zeros((1, model.n_params, model.n_params)),
                               initial_error=None)

    assert implausible(res(5e3, 0.010)) == []
    assert "chi-square per dof" in implausible(res(5e3, 2.0))[0]
    assert "chi-square per dof" in implausible(res(1e6, 0.004))[0]


# ----------------------------------------------------------------------------- 5. the machine's values, same rule
FIVE = Path(__file__).parent.parent / "examples" / "five_axis_cafxyz.toml"

#: a value in the next unit up of a value in use, the key the one line names and the words it says (the new-user
#: trial's slips first); each is refused by the configuration and by --set
MACHINE_SLIPS = [
    ("geometric_errors.rotary_zero", '"50 deg"', "geometric_errors.rotary_zero", "not a plausible angular error"),
    ("geometric_errors.rotary_zero", '"50 mrad"', "geometric_errors.rotary_zero", "not a plausible angular error"),
    ("geometric_errors.translational", '["8 mm", "3 um"]', r"geometric_errors.translational\[0\]",
     "8000 um is not a plausible length error"),
    ("geometric_errors.angular", '["20 urad", "8 mrad"]', r"geometric_errors.angular\[1\]",
     "not a plausible angular error"),
    ("geometric_errors.rotary_location", '"30 mm"', "geometric_errors.rotary_location", "not a plausible length error"),
    ("geometric_errors.rotary_orientation", '"50 mrad"', "geometric_errors.rotary_orientation", "angular error"),
    ("geometric_errors.squareness", '"30 deg"', "geometric_errors.squareness", "not a plausible angular error"),
    ("effects.reversal.y", '"8 mm"', "effects.reversal.y", "8000 um is not a plausible reversal"),
    ("effects.thermal.x", '"11.5 mm/(m*K)"', "effects.thermal.x", "not a plausible expansion coefficient"),
    ("effects.drift", '["4 mm/h", "0 um/h", "0 um/h"]', r"effects.drift\[0\]", "4000 um/h is not a plausible"),
    ("rotary.C.pivot", '["50 m", "-20 mm", "0 mm"]', "rotary.C.pivot", "is not a plausible pivot"),
]


@pytest.mark.parametrize("key, slip, named, words", MACHINE_SLIPS)
def test_a_machine_value_in_the_next_unit_up_is_refused_in_one_line(key, slip, named, words):
    with pytest.raises(ConfigError) as info:
        load_config(FIVE, [f"{key}={slip}"])
    msg = str(info.value)
    assert re.match(rf"^{re.escape(str(FIVE))}: {named}: .*{re.escape(words)}.*; expected .*\(given with --set\)$",
                    msg), msg
    assert "\n" not in msg and "(" in msg.split("expected", 1)[1]  # the range and, in brackets, why


def test_the_trial_slips_exit_2_in_one_line_before_any_computation(tmp_path):
    """The new-user trial: rotary_zero = "50 deg" in the five-axis example sat 7 minutes and gave a certificate."""
    cfg = tmp_path / "x.toml"
    cfg.write_text(FIVE.read_text().replace('rotary_zero = "50 urad"', 'rotary_zero = "50 deg"', 1))
    res = CliRunner().invoke(main, ["run", str(cfg), "--trials", "4", "--log", str(tmp_path / "x.mcap")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert lines[0].startswith(f"error: {cfg}: geometric_errors.rotary_zero: 872665 urad is not a plausible")
    assert not (tmp_path / "x.mcap").exists()


#: the bounds as docs/configuration.md states them ("Plausible values of the simulated machine"), in display units,
#: written apart from the code's table: key to --set, unit, bound
DOCUMENTED_MACHINE = [("geometric_errors.rotary_zero", "urad", 1000.0),
                      ("geometric_errors.rotary_orientation", "urad", 1000.0),
                      ("geometric_errors.squareness", "urad", 1000.0),
                      ("geometric_errors.rotary_location", "um", 2000.0),
                      ("effects.reversal.x", "um", 500.0),
                      ("effects.thermal.z", "um/(m*K)", 100.0)]


@pytest.mark.parametrize("factor", [0.99, 1.01])
@pytest.mark.parametrize("key, unit, bound", DOCUMENTED_MACHINE)
def test_the_documented_machine_bounds(key, unit, bound, factor):
    value = f'"{-factor * bound if key.startswith("effects") else factor * bound:g} {unit}"'  # signed: |value|
    if factor < 1:
        load_config(FIVE, [f"{key}={value}"])
    else:
        with pytest.raises(ConfigError, match=rf"{re.escape(key)}: .* is not a plausible"):
            load_config(FIVE, [f"{key}={value}"])


def test_explicit_coefficients_and_iso_named_rotary_errors_obey_it(tmp_path):
    raw = load_config(SMALL).source
    raw["geometric_errors"] = {"coefficients": {"dx(x)": ["8 um", "0.8 um"], "ex(y)": ["20 urad"]},
                               "squareness": {"sxy": "30 urad"}}
    parse_config(copy.deepcopy(raw), SMALL)  # in use
    for table, name, slip, words in (("coefficients", "dx(x)", ["8 um", "8 mm"], r"dx\(x\)\[1\]: 8000 um"),
                                     ("coefficients", "ex(y)", ["20 mrad"], r"ex\(y\): 20000 urad"),
                                     ("squareness", "sxy", "30 mrad", "sxy: 30000 urad")):
        bad = copy.deepcopy(raw)
        bad["geometric_errors"][table][name] = slip
        with pytest.raises(ConfigError, match=rf"small\.toml: geometric_errors\.{table}\.{words} is not a plausible"):
            parse_config(bad, SMALL)
    with pytest.raises(ConfigError, match=r"geometric_errors\.rotary\.ECOC: 50000 urad is not a plausible"):
        load_config(FIVE, ['geometric_errors.rotary.ECOC=50 mrad'])
    load_config(FIVE, ['geometric_errors.rotary.ECOC=50 urad', 'geometric_errors.rotary.EXOC=30 um'])


def test_a_pivot_is_bounded_by_the_travel():
    """The five-axis example's linear travel is 400 mm at most (x, y: -200..200 mm): a pivot up to 5 x 400 = 2000 mm
    outside the box of the mesh and the machine zero stands, farther is refused, whatever its direction."""
    load_config(FIVE, ['rotary.C.pivot=["2190 mm", "-20 mm", "0 mm"]'])  # 1990 mm beyond x = 200 mm
    with pytest.raises(ConfigError, match=r"rotary\.C\.pivot: 2010 mm outside the verified volume .* within 2000 mm"):
        load_config(FIVE, ['rotary.C.pivot=["2210 mm", "-20 mm", "0 mm"]'])
    d = 2010.0 / np.sqrt(3)  # the distance to the box's corner, not per coordinate
    with pytest.raises(ConfigError, match=r"rotary\.A\.pivot: 2010 mm outside"):
        load_config(FIVE, [f'rotary.A.pivot=["{200 + d:.6f} mm", "{200 + d:.6f} mm", "{200 + d:.6f} mm"]'])


# ----------------------------------------------------------------------------- 6. the sources' own bounds
def test_every_source_bound_follows_the_rule():
    """Every ``plausible`` bound names a parameter, has its dimension, and obeys the rule for the default in use:
    at least 3 times it (several times what is in use) and below 1000 times it (the next unit up is refused)."""
    import pint

    from mtbudget.contracts import Source

    classes, seen = [Source], []
    while classes:
        c = classes.pop()
        seen.append(c)
        classes.extend(c.__subclasses__())
    bounded = [c for c in seen if c.__dict__.get("plausible")]
    assert len(bounded) >= 20, [c.__name__ for c in bounded]
    names = {c.name for c in bounded}
    assert {"rotary_encoder", "rotary_reversal", "backlash", "reversal", "thermal_expansion"} <= names, names
    for c in bounded:
        for k, bound in c.plausible.items():
            assert k in c.parameters and k not in c.links, (c.name, k)
            default = c.parameters[k]
            assert isinstance(default, pint.Quantity) and bound.dimensionality == default.dimensionality, (c.name, k)
            d = abs(float(default.to(bound.units).magnitude))
            if d:
                assert 3 * d <= bound.magnitude < 1000 * d, (c.name, k, d, bound)
            assert c().plausibility_problem(k) is None


@pytest.mark.parametrize("source, param, slip, shown", [
    ("rotary_encoder", "E_max", "10 deg", "174533 urad is not plausible; expected at most 1000 urad"),
    ("rotary_reversal", "B_max", "20 mrad", "20000 urad is not plausible; expected at most 1000 urad"),
    ("backlash", "B_max", "3 mm", "3000 um is not plausible; expected at most 500 um"),
])
def test_a_source_parameter_in_the_next_unit_up_is_refused_naming_its_key(source, param, slip, shown):
    with pytest.raises(ConfigError) as info:
        build_scenario(load_config(FIVE, [f"sources.{source}.{param}={slip}"]))
    assert str(info.value) == (f"{FIVE}: sources.{source}.{param}: {shown} in magnitude (several times the poorest "
                               "in use; a value in the next unit up?) (given with --set)")


def test_a_plugin_authors_bound_is_checked_where_the_parameter_is_set():
    from mtbudget.contracts import Source
    from mtbudget.errors import PluginError
    from mtbudget.units import Q_

    class Wobble(Source):
        name = "wobble"
        parameters = {"amplitude": Q_(2.0, "um")}
        plausible = {"amplitude": Q_(100.0, "um")}

    assert Wobble(amplitude="-90 um").parameters["amplitude"].magnitude == -90
    with pytest.raises(PluginError, match=r"source 'wobble': parameter 'amplitude': -2000 um is not plausible"):
        Wobble(amplitude="-2 mm")


# ----------------------------------------------------------------------------- 7. a run that does not converge
@pytest.fixture
def iteration_limit_of_one(monkeypatch):
    """The identification held to one iteration (and one chord step): no trial reaches its minimum."""
    import dataclasses

    import mtbudget.engine as engine_module

    real = engine_module.identify

    def limited(model, meas, x0, strategy, *args, **kwargs):
        return real(model, meas, x0, dataclasses.replace(strategy, max_iter=1, chord_iter=1), *args, **kwargs)

    monkeypatch.setattr(engine_module, "identify", limited)


def test_a_run_that_does_not_converge_says_so_first_and_gets_no_certificate(tmp_path, iteration_limit_of_one):
    log, out = tmp_path / "x.mcap", tmp_path / "rep"
    out.mkdir()
    (out / "certificate.xml").write_text("<a previous run's certificate/>")
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "16", "--attribution-trials", "0", "--log", str(log),
                                    "--quiet"])
    assert res.exit_code == 0, res.output
    assert res.stdout.startswith("WARNING: the identification of 16 of 16 trials (100 %) did not converge"), res.stdout
    assert "NOT A STATEMENT TO SIGN" in res.stdout.splitlines()[1]
    assert "warning: the identification of 16 of 16 trials" in res.stderr
    rep = CliRunner().invoke(main, ["report", str(log), "--out", str(out)])
    assert rep.exit_code == 0, rep.output
    assert "warning: certificate.xml is not written: the identification of 16 of 16 trials" in rep.stderr
    assert not (out / "certificate.xml").exists()  # nor a previous one standing for this run
    md = (out / "report.md").read_text()
    assert "| WARNING | **WARNING: the identification of 16 of 16 trials" in md and "certificate.xml is not written" in md
    from mtbudget.errors import IdentificationError
    from mtbudget.report_dcc import write_dcc
    from mtbudget.runner import replay

    with pytest.raises(IdentificationError, match="certificate.xml is not written"):
        write_dcc(replay(log), tmp_path / "c.xml")


def test_a_small_share_that_does_not_converge_is_the_certificates_warning_statement(tmp_path, monkeypatch):
    """At or below the share (1 %) the DCC is written, and says it in its statements (dcc:statement 'warning')."""
    import xml.etree.ElementTree as ET

    import mtbudget.outputs as outputs_module
    from mtbudget.report import too_many_not_converged
    from mtbudget.report_dcc import write_dcc
    from mtbudget.runner import run

    assert not too_many_not_converged(1, 100) and too_many_not_converged(2, 100) and too_many_not_converged(1, 16)
    res = run(load_config(SMALL), trials=16, block=8, attribution_trials=0)
    path = write_dcc(res, tmp_path / "ok.xml")
    assert "did not converge" not in path.read_text()
    res.acc.not_converged = 1
    monkeypatch.setattr(outputs_module, "MAX_NOT_CONVERGED", 0.1)  # 1 of 16 below the share
    root = ET.parse(write_dcc(res, tmp_path / "c.xml")).getroot()
    ns = {"dcc": "https://ptb.de/dcc"}
    said = {s.find("dcc:name/dcc:content", ns).text: s.find("dcc:declaration/dcc:content", ns).text
            for s in root.iterfind(".//dcc:statements/dcc:statement", ns)}
    assert said["warning"].startswith("WARNING: the identification of 1 of 16 trials (6.25 %) did not converge"), said


def test_a_cte_stated_through_a_thermal_source_obeys_the_rule_of_its_key():
    """machine_tool.cte and the thermal sources' linked ``cte`` state one physical input: one bound for both (it was
    unchecked through the source)."""
    with pytest.raises(ConfigError, match=r"sources\.cte_uncertainty\.cte: 11500 um/\(m\*K\) is not a plausible "
                                          r"expansion coefficient of a machine's axis or scale \(expected -2 to 30"):
        build_scenario(load_config(SMALL, ["sources.cte_uncertainty.cte=11.5 mm/(m*K)"]))
    build_scenario(load_config(SMALL, ["sources.cte_uncertainty.cte=23 um/(m*K)"]))  # aluminium


def test_a_recordings_pivot_is_bounded_by_its_recorded_travel(tmp_path):
    """The reader holds a recording's [rotary.<axis>] pivot to the configuration's rule, against the commanded x, y,
    z it recorded; the generated recording (its pivots 50 mm from the table centre) reads."""
    sys.path.insert(0, str(HERE))
    from fiveaxis_generator import make_recording

    folder = tmp_path / "r"
    make_recording(folder, "CAFXYZ", seed=2)
    rec = read_recording(folder)
    xyz = rec.plan.nominal
    travel = float((xyz.max(axis=0) - xyz.min(axis=0)).max())
    reach = max(5 * travel, 1000.0)
    text = (folder / "recording.toml").read_text()
    old = 'pivot = ["50 mm", "-20 mm", "0 mm"]'
    assert text.count(old) == 1
    far = max(xyz[:, 0].max(), 0.0) + reach + 10.0  # 10 mm beyond the bound along +x
    (folder / "recording.toml").write_text(text.replace(old, f'pivot = ["{far:.6f} mm", "-20 mm", "0 mm"]'))
    with pytest.raises(RecordingError, match=rf"recording\.toml, rotary\.C\.pivot: {reach + 10:g} mm outside the "
                                             rf"verified volume .* expected within {reach:g} mm"):
        read_recording(folder)
    (folder / "recording.toml").write_text(text.replace(old, f'pivot = ["{far - 20:.6f} mm", "-20 mm", "0 mm"]'))
    read_recording(folder)


ROOT = HERE.parent
SHIPPED = sorted([*ROOT.glob("examples/*.toml"), *ROOT.glob("mtbudget/data/*.toml"), *ROOT.glob("tests/data/*.toml")])


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_no_value_in_use_is_refused(path):
    """The bounds refuse no value of a shipped configuration (its sources built too) nor of a bundled recording."""
    assert len(SHIPPED) >= 11
    build_scenario(load_config(path))


@pytest.mark.parametrize("name", ["null", "thermal_x", "reversal_y", "tracker_drift", "four_stations"])
def test_no_bundled_recording_is_refused(name):
    read_recording(example_recording(name), several_stations=True)


def test_an_a_posteriori_statement_whose_trials_do_not_converge_gets_no_certificate(tmp_path, monkeypatch):
    """The recording's own identification as it is, its Monte Carlo trials held to one iteration: the statement says
    so first, and no certificate.xml is written although recording.toml states its date."""
    import mtbudget.posterior as posterior_module
    from mtbudget.identify import Strategy

    real, calls = posterior_module.identify, []

    def trials_limited(model, y, noise, *args, **kwargs):
        calls.append(1)
        if len(calls) == 1:  # the recording's identification
            return real(model, y, noise, *args, **kwargs)
        return real(model, y, noise, Strategy(max_iter=1, chord_iter=1), *args, **kwargs)

    monkeypatch.setattr(posterior_module, "identify", trials_limited)
    folder = _copy_null(tmp_path)
    with (folder / "recording.toml").open("a") as f:
        f.write('\n[report]\ndate = "2026-11-20"\n')
    out = tmp_path / "post"
    res = CliRunner().invoke(main, ["posterior", str(folder), "--trials", "8", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert res.stdout.startswith("WARNING: the identification of 8 of 8 trials (100 %) did not converge"), res.stdout
    assert "warning: certificate.xml is not written: the identification of 8 of 8 trials" in res.stderr
    assert not (out / "certificate.xml").exists() and (out / "posterior.md").exists()
    assert "WARNING: the identification of 8 of 8 trials" in (out / "posterior.md").read_text()


def test_a_large_gantrys_real_values_stand():
    """A 9 m x 3 m gantry, uncompensated: a rack-and-pinion's period (pi m z, about 400 mm), the environment's
    variation over 10 m of steel at 2 K (11.5 um/(m*K) x 10 m x 2 K = 230 um, so E_VE 150 um), positioning errors of
    0.8 mm and a backlash of 250 um: each a value a real machine shows, none refused (they were, by the bounds of
    a 1 m machine)."""
    sets = ["sources.add=[\"model_form_periodic\"]", "sources.model_form_periodic.lead_x=400 mm", "sources.environmental_variation.E_VE=150 um",
            "geometric_errors.translational=[\"800 um\", \"400 um\", \"200 um\"]", "sources.backlash.B_max=250 um",
            "effects.reversal.x=250 um"]
    cfg = load_config(default_config_path(), sets)
    build_scenario(cfg)  # the sources' own bounds are checked where their parameters are set


def test_the_scales_cte_has_one_bound_whichever_key_states_it(tmp_path):
    """[machine_tool] cte (a configuration) and [scales.<axis>] cte (here a recording's, the same reader rule as a
    configuration's) state the same quantity, the scales' expansion coefficient: -50 um/(m*K) was accepted by one
    and refused by the other. Both now follow recording.CTE_RANGE (-2 to 30 um/(m*K))."""
    words = r"-50 um/\(m\*K\) is not a plausible expansion coefficient of a machine's axis or scale \(expected -2 to 30"
    with pytest.raises(ConfigError, match=r"machine_tool\.cte: " + words):
        load_config(SMALL, ["machine_tool.cte=-50 um/(m*K)"])
    load_config(SMALL, ["machine_tool.cte=23 um/(m*K)"])  # aluminium
    folder = tmp_path / "r"
    shutil.copytree(example_recording("null"), folder)
    with open(folder / "recording.toml", "a", encoding="utf-8") as fh:
        fh.write('\n[scales.x]\ncte = "-50 um/(m*K)"\nfixed_point = "0 mm"\n')
    with pytest.raises(RecordingError, match=words):
        read_recording(folder)
