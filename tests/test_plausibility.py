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
