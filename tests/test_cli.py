"""The mtbudget command: --help everywhere, --version, and the main jobs end to end."""

import json
import subprocess
import sys

import pytest
from click.testing import CliRunner

from mtbudget import __version__
from mtbudget.cli import main


def all_commands(group=main, prefix=()):
    for name, cmd in group.commands.items():
        yield prefix + (name,)
        if hasattr(cmd, "commands"):
            yield from all_commands(cmd, prefix + (name,))


@pytest.mark.parametrize("path", [()] + list(all_commands()), ids=lambda p: " ".join(p) or "mtbudget")
def test_every_command_has_help(path):
    res = CliRunner().invoke(main, list(path) + ["--help"])
    assert res.exit_code == 0, res.output
    assert "Usage:" in res.output
    assert len(res.output.splitlines()) > 4


def test_version():
    res = CliRunner().invoke(main, ["--version"])
    assert res.exit_code == 0 and __version__ in res.output


def test_simulate_then_identify(tmp_path):
    out = tmp_path / "sim"
    res = CliRunner().invoke(main, ["simulate", "--out", str(out), "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert (out / "points.csv").exists() and (out / "truth.json").exists()
    assert "chi-square per dof" in res.output
    res = CliRunner().invoke(main, ["identify", str(out), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert 0.8 < data["chi2_per_dof"] < 1.25
    assert {p["unit"] for p in data["parameters"]} == {"um", "urad"}
    # a simulation's truth is not in the identification's datum: the text says how to compare, and the command it
    # names runs
    text = CliRunner().invoke(main, ["identify", str(out)]).output
    line = next(ln for ln in text.splitlines() if "truth.json (a simulation)" in ln)
    cmd = line[line.index("`") + 1:line.rindex("`")].split()[1:]
    cmd[cmd.index("--out") + 1] = str(tmp_path / "tables.json")
    ran = CliRunner().invoke(main, cmd)
    assert ran.exit_code in (0, 1) and "Traceback" not in ran.output and "check" in ran.output.lower(), ran.output


def test_bad_recording_is_one_line_error_not_a_traceback(tmp_path):
    (tmp_path / "r").mkdir()
    res = CliRunner().invoke(main, ["identify", str(tmp_path / "r")])
    assert res.exit_code == 2
    assert "Traceback" not in res.output
    assert "recording.toml" in res.output


def test_python_dash_m_entry_point():
    res = subprocess.run([sys.executable, "-m", "mtbudget", "--version"], capture_output=True, text=True)
    assert res.returncode == 0 and __version__ in res.stdout


def test_plugins_lists_sources_by_group_with_units_and_origin():
    res = CliRunner().invoke(main, ["plugins", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    src = {s["name"]: s for s in data["sources"]}
    assert src["tracker_noise"]["group"] == "measurement system"
    p = src["tracker_noise"]["parameters"]["angular_mean"]
    from mtbudget.units import Q_

    assert Q_(p["value"], p["unit"]).to("urad").magnitude == pytest.approx(20.0)
    assert src["backlash"]["package"] == "mtbudget" and src["backlash"]["plugin"] == "machine_tool"
    assert {c["effect"] for c in data["candidates"]} >= {"thermal_expansion", "reversal", "tracker_drift"}
    text = CliRunner().invoke(main, ["plugins"]).output
    assert "uncertainty sources:" in text and "[optimisation strategy]" in text


def _leaf_commands(group=main, prefix=()):
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):
            yield from _leaf_commands(cmd, prefix + (name,))
        else:
            yield prefix + (name,), cmd


BAD_NUMBERS = ["-3", "abc", "1e400", "2.5", ""]


def _option_cases():
    import click

    for path, cmd in _leaf_commands():
        for p in cmd.params:
            if not isinstance(p, click.Option) or p.is_flag:
                continue
            if isinstance(p.type, (click.types.IntParamType, click.types.FloatParamType, click.IntRange, click.FloatRange)):
                for bad in BAD_NUMBERS:
                    yield path, p.opts[0], bad


@pytest.mark.parametrize("path, option, bad", list(_option_cases()),
                         ids=lambda x: " ".join(x) if isinstance(x, tuple) else str(x))
def test_every_numeric_option_refuses_bad_values_in_one_line(path, option, bad, tmp_path, monkeypatch):
    """A bad value gives a one-line usage error naming the option, or is a valid value; never a traceback."""
    monkeypatch.chdir(tmp_path)
    args = list(path) + [option, bad]
    if path[-1] in ("identify", "diagnose"):
        args += ["--example", "null"]
    if path[-1] in ("replay", "report"):
        args = list(path) + [str(tmp_path / "missing.mcap"), option, bad]
    res = CliRunner().invoke(main, args)
    assert res.exception is None or isinstance(res.exception, SystemExit), (args, res.exception)
    if res.exit_code != 0:
        assert "Traceback" not in res.output
        assert option in res.output or "Invalid value" in res.output or "error:" in res.output, (args, res.output)
        said = [ln for ln in res.output.strip().splitlines() if not ln.startswith("compiling the engine's kernels")]
        assert len(said) == 1, (args, res.output)  # one line, not click's usage block (beside a fresh machine's note)


def test_run_resume_of_nothing_and_of_a_complete_log_are_one_line(tmp_path):
    missing = tmp_path / "none.mcap"
    res = CliRunner().invoke(main, ["run", "--resume", str(missing), "--quiet"])
    assert res.exit_code == 2 and "nothing to resume" in res.output and len(res.output.strip().splitlines()) == 1
    log = tmp_path / "done.mcap"
    small = str(__import__("pathlib").Path(__file__).parent / "data" / "small.toml")
    res = CliRunner().invoke(main, ["run", small, "--trials", "16", "--block", "8", "--attribution-trials", "0",
                                    "--log", str(log), "--quiet"])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["run", "--resume", str(log), "--quiet"])
    assert res.exit_code == 2 and "the run is complete" in res.output and len(res.output.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["done.mcap"]  # no lock, partial or temporary file left


def test_run_on_threads_prints_the_numbers_of_the_inline_run(tmp_path):
    small = str(__import__("pathlib").Path(__file__).parent / "data" / "small.toml")
    out = {}
    for ex in ("inline", "thread", "auto"):
        workers = [] if ex == "inline" else ["--workers", "2"]  # inline runs on one core: --workers is refused there
        res = CliRunner().invoke(main, ["run", small, "--trials", "48", "--block", "8", "--attribution-trials", "8",
                                        "--executor", ex, *workers, "--json", "--quiet",
                                        "--log", str(tmp_path / f"{ex}.mcap")])
        assert res.exit_code == 0, res.output
        out[ex] = json.loads(res.output)
    assert out["thread"]["outputs"] == out["inline"]["outputs"] and out["thread"]["budget"] == out["inline"]["budget"]
    assert out["auto"]["outputs"] == out["inline"]["outputs"]


def test_a_group_without_its_command_shows_its_help_not_an_error():
    """Usage errors are one line, but a group called without a command still shows its help (click raises that as a
    usage error too)."""
    res = CliRunner().invoke(main, ["study"])
    assert res.output.startswith("Usage: main study") or res.output.startswith("Usage: mtbudget study"), res.output
    assert "error:" not in res.output and len(res.output.splitlines()) > 4
