"""Reading and writing recordings: units, round trip, and every bad input with file, line and column."""

import shutil
from pathlib import Path

import numpy as np
import pytest

from mtbudget.config import example_recording
from mtbudget.errors import RecordingError
from mtbudget.recording import read_recording, write_recording
from mtbudget.scenario import build_scenario
from mtbudget.simulate import simulate_recording

from conftest import EXAMPLES

MM_PER_IN = 25.4


def convert_to_imperial(src: Path, dst: Path):
    """The same recording in inch, minutes and degF, converted by hand (not by pint)."""
    shutil.copytree(src, dst)
    lines = (src / "points.csv").read_text().splitlines()
    header = lines[0].split(",")
    new_header, conv = [], []
    for h in header:
        if h.endswith("[mm]"):
            new_header.append(h.replace("[mm]", "[in]"))
            conv.append(lambda v: repr(float(v) / MM_PER_IN))
        elif h.endswith("[s]"):
            new_header.append(h.replace("[s]", "[min]"))
            conv.append(lambda v: repr(float(v) / 60.0))
        elif h.endswith("[degC]"):
            new_header.append(h.replace("[degC]", "[degF]"))
            conv.append(lambda v: repr(float(v) * 9 / 5 + 32))
        else:
            new_header.append(h)
            conv.append(lambda v: v)
    out = [",".join(new_header)]
    for line in lines[1:]:
        out.append(",".join(f(v) for f, v in zip(conv, line.split(","))))
    (dst / "points.csv").write_text("\n".join(out) + "\n")


@pytest.mark.parametrize("name", EXAMPLES)
def test_examples_in_mm_and_in_inch_give_identical_points(name, tmp_path):
    src = example_recording(name)
    a = read_recording(src)
    convert_to_imperial(src, tmp_path / name)
    b = read_recording(tmp_path / name)
    assert len(a) == 300
    assert np.allclose(a.plan.nominal, b.plan.nominal, rtol=0, atol=1e-9)
    assert np.allclose(a.plan.tool, b.plan.tool, rtol=0, atol=1e-9)
    assert np.allclose(a.lt, b.lt, rtol=0, atol=1e-9)
    assert np.allclose(a.plan.time, b.plan.time, rtol=0, atol=1e-9)
    for col in a.plan.temperature:
        assert np.allclose(a.plan.temperature[col], b.plan.temperature[col], rtol=0, atol=1e-9)


def test_simulation_round_trip_is_lossless_to_written_precision(default_config, tmp_path):
    rec, truth = simulate_recording(build_scenario(default_config))
    write_recording(rec, tmp_path / "sim", truth=truth)
    back = read_recording(tmp_path / "sim")
    assert np.abs(back.lt - rec.lt).max() <= 0.5e-6 + 1e-12  # 6 decimals of mm
    assert np.array_equal(back.plan.nominal, rec.plan.nominal)
    assert np.array_equal(back.plan.direction, rec.plan.direction)
    assert np.abs(back.plan.time - rec.plan.time).max() <= 0.5e-4 + 1e-12
    for key in ("angular", "distance", "distance_per_length", "repeatability"):
        assert getattr(back, key) == pytest.approx(getattr(rec, key), rel=1e-9)
    assert (tmp_path / "sim" / "truth.json").exists()


@pytest.fixture
def broken(tmp_path):
    dst = tmp_path / "rec"
    shutil.copytree(example_recording("null"), dst)
    return dst


def edit_csv(folder, fn):
    p = folder / "points.csv"
    lines = p.read_text().splitlines()
    p.write_text("\n".join(fn(lines)) + "\n")


def set_cell(lines, line_no, col_name, value):
    header = lines[0].split(",")
    j = [h.split(" [")[0] for h in header].index(col_name)
    cells = lines[line_no - 1].split(",")
    cells[j] = value
    lines[line_no - 1] = ",".join(cells)
    return lines


CASES = {
    "missing format": (lambda f: (f / "recording.toml").write_text((f / "recording.toml").read_text().replace('format = "mtbudget-recording/1"\n', "")),
                       ["recording.toml", "format"]),
    "unknown format version": (lambda f: (f / "recording.toml").write_text((f / "recording.toml").read_text().replace("recording/1", "recording/9")),
                               ["recording.toml", "recording/9"]),
    "missing column": (lambda f: edit_csv(f, lambda L: [",".join(c for i, c in enumerate(l.split(",")) if i != 13) for l in L]),
                       ["points.csv", "line 1", "lt_y"]),
    "unparsable unit": (lambda f: edit_csv(f, lambda L: [L[0].replace("x [mm]", "x [furlongz]")] + L[1:]),
                        ["points.csv", "line 1", "furlongz"]),
    "wrong dimension": (lambda f: edit_csv(f, lambda L: [L[0].replace("lt_x [mm]", "lt_x [degC]")] + L[1:]),
                        ["points.csv", "line 1", "lt_x", "dimension"]),
    "NaN cell": (lambda f: edit_csv(f, lambda L: set_cell(L, 7, "lt_z", "nan")), ["points.csv", "line 7", "lt_z", "not finite"]),
    "empty cell": (lambda f: edit_csv(f, lambda L: set_cell(L, 12, "T_y", "")), ["points.csv", "line 12", "T_y", "empty"]),
    "non-monotonic time": (lambda f: edit_csv(f, lambda L: set_cell(L, 20, "time", "1.0")), ["points.csv", "line 20", "time", "backwards"]),
    "duplicate rows": (lambda f: edit_csv(f, lambda L: L[:5] + [L[4]] + L[5:]), ["points.csv", "line 6", "duplicate"]),
    "bad direction": (lambda f: edit_csv(f, lambda L: set_cell(L, 3, "dir_y", "0")), ["points.csv", "line 3", "dir_y"]),
    "not a number": (lambda f: edit_csv(f, lambda L: set_cell(L, 9, "x", "12,5".replace(",", ";"))), ["points.csv", "line 9", "'x"]),
    "tracker key with wrong unit": (lambda f: (f / "recording.toml").write_text((f / "recording.toml").read_text().replace('distance = "4 um"', 'distance = "4 s"')),
                                    ["recording.toml", "tracker.distance"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_names_file_line_and_column(case, broken):
    damage, must_contain = CASES[case]
    damage(broken)
    with pytest.raises(RecordingError) as info:
        read_recording(broken)
    msg = str(info.value)
    for part in must_contain:
        assert part in msg, (case, msg)
    assert "\n" not in msg


def test_missing_folder_and_files(tmp_path):
    with pytest.raises(RecordingError, match="not a folder"):
        read_recording(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="recording.toml"):
        read_recording(tmp_path / "empty")


def test_errors_are_picklable():
    import pickle

    e = RecordingError("bad", "a/points.csv", 3, "x")
    e2 = pickle.loads(pickle.dumps(e))
    assert str(e2) == str(e) and e2.line == 3
