"""Size limits that keep a command from hanging (issue 29): a clear refusal, fast, instead of minutes of swapping."""

import time

import pytest
from click.testing import CliRunner

import mtbudget.identify as identify_module
from mtbudget.cli import main
from mtbudget.config import example_recording
from mtbudget.errors import IdentificationError
from mtbudget.identify import Noise, identify
from mtbudget.recording import read_recording
from mtbudget.model import MeasurementModel


def test_one_identification_refuses_more_points_than_its_limit(monkeypatch):
    """The guard at identify's entry: the limit (1e5 points, 3.7 GB) scaled down to 100 on the 300-point example."""
    rec = read_recording(example_recording("null"))
    monkeypatch.setattr(identify_module, "MAX_POINTS", 100)
    with pytest.raises(IdentificationError, match=r"300 measured points in one identification; at most 100 "):
        identify(MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=3), rec.lt, Noise.of(rec))


@pytest.mark.parametrize("command", [["identify"], ["diagnose", "--quiet"], ["compensate", "--format", "neutral-csv"]])
def test_commands_that_identify_refuse_a_too_long_recording_before_parsing_it(command, monkeypatch, tmp_path):
    """A 10^6-row recording kept `identify` busy past 150 s (37 GB); the reader now refuses it on its byte count,
    naming the file and the line, before a row is parsed."""
    monkeypatch.setattr(identify_module, "MAX_POINTS", 100)
    start = time.perf_counter()
    extra = ["--out", str(tmp_path / "c")] if command[0] == "compensate" else []
    res = CliRunner().invoke(main, command + [str(example_recording("null"))] + extra)
    assert res.exit_code == 2, res.output
    assert "points.csv, line 102: more than 100 data rows" in res.output and len(res.output.strip().splitlines()) == 1
    assert time.perf_counter() - start < 10
