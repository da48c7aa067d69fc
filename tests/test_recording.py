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


# ----------------------------------------------------------------------------- strict reader (issue 19)
def edit_bytes(folder, fn, name="points.csv"):
    p = folder / name
    p.write_bytes(fn(p.read_bytes()))


def edit_toml(folder, old, new):
    p = folder / "recording.toml"
    text = p.read_text()
    assert old in text
    p.write_text(text.replace(old, new, 1))


def _to_fahrenheit(line, header, column):
    """``line`` with the cell of ``column`` converted from degC to degF by hand (9/5 t + 32), its header unchanged."""
    j = [h.split(" [")[0] for h in header.split(",")].index(column)
    cells = line.split(",")
    cells[j] = repr(float(cells[j]) * 9 / 5 + 32)
    return ",".join(cells)


STRICT = {
    "decimal comma": (lambda f: edit_csv(f, lambda L: [L[0], L[1].replace("1668.945719", "1668,945719")] + L[2:]),
                      ["points.csv", "line 2", "lt_x", "decimal comma", "1668,945719", "20 cells, the header has 19"]),
    "decimal comma in a quoted cell": (lambda f: edit_csv(f, lambda L: set_cell(L, 4, "x", '"800,5"')),
                                       ["points.csv", "line 4", "'x", "decimal point"]),
    "too many cells": (lambda f: edit_csv(f, lambda L: L[:9] + [L[9] + ",7"] + L[10:]),
                       ["points.csv", "line 10", "20 cells, the header has 19"]),
    "too few cells": (lambda f: edit_csv(f, lambda L: L[:9] + [L[9].rsplit(",", 2)[0]] + L[10:]),
                      ["points.csv", "line 10", "column 'T_z [degC]'", "17 cells, the header has 19"]),
    "latin-1 micro in a header": (lambda f: edit_bytes(f, lambda b: b.replace(b"tool_z [mm]", "tool_z [µm]".encode("latin-1"))),
                                  ["points.csv", "line 1", "0xB5", "byte offset 90", "µ (micro) in Latin-1", "tool_z", "UTF-8"]),
    "latin-1 byte in a data row": (lambda f: edit_bytes(f, lambda b: b.replace(b"19.990", b"19.99\xb0", 1)),
                                   ["points.csv", "line 2", "column 'T_y [degC]'", "0xB0", "byte offset"]),
    "UTF-16": (lambda f: edit_bytes(f, lambda b: b.decode().encode("utf-16")), ["points.csv", "UTF-16", "UTF-8"]),
    "NUL byte": (lambda f: edit_bytes(f, lambda b: b[:300] + b"\x00" + b[301:]), ["points.csv", "NUL byte at byte offset 300"]),
    "semicolons": (lambda f: edit_bytes(f, lambda b: b.replace(b",", b";")), ["points.csv", "line 1", "separated by ';'"]),
    "huge point index": (lambda f: edit_csv(f, lambda L: set_cell(L, 5, "point", "1e19")),
                         ["points.csv", "line 5", "'point'", "whole number from 0 to 999999999", "1e+19"]),
    "underscore number": (lambda f: edit_csv(f, lambda L: set_cell(L, 5, "lt_y", "1_000")),
                          ["points.csv", "line 5", "lt_y", "not a number: '1_000'"]),
    "overflowing number": (lambda f: edit_csv(f, lambda L: set_cell(L, 6, "y", "1e400")), ["points.csv", "line 6", "'y", "not finite"]),
    "infinite cell": (lambda f: edit_csv(f, lambda L: set_cell(L, 8, "tool_x", "-inf")), ["points.csv", "line 8", "tool_x", "not finite"]),
    "negative time": (lambda f: edit_csv(f, lambda L: set_cell(L, 2, "time", "-5")), ["points.csv", "line 2", "time", "-5 s"]),
    "direction 0.5": (lambda f: edit_csv(f, lambda L: set_cell(L, 3, "dir_z", "0.5")), ["points.csv", "line 3", "dir_z", "+1 or -1"]),
    "kelvin column holding degC": (lambda f: edit_csv(f, lambda L: [L[0].replace("T_x [degC]", "T_x [K]")] + L[1:]),
                                   ["points.csv", "line 2", "T_x [K]", "19.912 K", "plausible absolute temperature",
                                    "write 'T_x [degC]'"]),
    "degF header over degC readings": (lambda f: edit_csv(f, lambda L: [L[0].replace("T_z [degC]", "T_z [degF]")] + L[1:]),
                                       ["points.csv", "T_z [degF]", "not a machine shop's temperature",
                                        "look like degC readings", "write 'T_z [degC]'"]),
    "degC header over degF readings": (lambda f: edit_csv(f, lambda L: [L[0]] + [_to_fahrenheit(ln, L[0], "T_air") for ln in L[1:]]),
                                       ["points.csv", "T_air [degC]", "look like degF readings", "write 'T_air [degF]'"]),
    "delta_degC header": (lambda f: edit_csv(f, lambda L: [L[0].replace("T_y [degC]", "T_y [delta_degC]")] + L[1:]),
                          ["points.csv", "line 1", "T_y", "temperature difference"]),
    "implausible temperature": (lambda f: edit_csv(f, lambda L: set_cell(L, 40, "T_air", "-300")),
                                ["points.csv", "line 40", "T_air", "not a plausible absolute temperature"]),
    "exponent tower in a unit": (lambda f: edit_csv(f, lambda L: [L[0].replace("x [mm]", "x [mm**9**9**9]", 1)] + L[1:]),
                                 ["points.csv", "line 1", "x [mm**9**9**9]", "not a unit"]),
    "undeclared column, implausible": (lambda f: edit_csv(f, lambda L: [L[0] + ",T_spindle [degC]"] + [ln + ",521.0" for ln in L[1:]]),
                                       ["points.csv", "line 2", "T_spindle", "not a plausible absolute temperature"]),
    "undeclared column, not a number": (lambda f: edit_csv(f, lambda L: [L[0] + ",humidity [percent]"] + [ln + ",4O" for ln in L[1:]]),
                                        ["points.csv", "line 2", "humidity [percent]", "not a number: '4O'"]),
    "misspelt column": (lambda f: edit_csv(f, lambda L: [L[0].replace("lt_z", "lt_Z")] + L[1:]),
                        ["points.csv", "line 1", "missing column 'lt_z'; the header has 'lt_Z': a misspelling?"]),
    "station column": (lambda f: edit_csv(f, lambda L: [L[0] + ",station"] + [ln + ",1" for ln in L[1:]]),
                       ["points.csv", "line 1", "'station'", "format 2"]),
    "one point at two positions": (lambda f: edit_csv(f, lambda L: set_cell(L, 80, "x", "801")),
                                   ["points.csv", "line 80", "point", "one point index is one nominal position"]),
    "too few rows": (lambda f: edit_csv(f, lambda L: L[:3]), ["points.csv", "line 3", "2 data rows", "at least 3"]),
    "a row of empty cells": (lambda f: edit_csv(f, lambda L: L[:10] + [",,,"] + L[10:]), ["points.csv", "line 11", "4 cells"]),
    # recording.toml
    "sensor column not a string": (lambda f: edit_toml(f, 'column = "T_x"', "column = 5"),
                                   ["recording.toml", "sensors[0].column", "expected a string, got int 5"]),
    "sensor attached to a number": (lambda f: edit_toml(f, 'attached_to = "y axis"', "attached_to = 2.5"),
                                    ["recording.toml", "sensors[1].attached_to", "expected a string"]),
    "sensor column declared twice": (lambda f: edit_toml(f, 'column = "T_y"', 'column = "T_x"'),
                                     ["recording.toml", "sensors[1].column", "two [[sensors]] tables"]),
    "tracker is not a table": (lambda f: edit_toml(f, "[tracker]\n", 'tracker = "Leica"\n[tracker_]\n'),
                               ["recording.toml", "tracker", "expected a table"]),
    "missing uncertainty": (lambda f: edit_toml(f, 'repeatability = "1.5 um"', ""),
                            ["recording.toml", "machine_tool.repeatability", "missing key"]),
    "infinite uncertainty": (lambda f: edit_toml(f, 'angular = "5.0 urad"', 'angular = "inf urad"'),
                             ["recording.toml", "tracker.angular", "not finite"]),
    "TOML inf": (lambda f: edit_toml(f, 'distance = "4 um"', "distance = inf"), ["recording.toml", "tracker.distance", "not finite"]),
    "bare number for an angle": (lambda f: edit_toml(f, 'angular = "5.0 urad"', "angular = 5"),
                                 ["recording.toml", "tracker.angular", "needs an explicit unit"]),
    "bare number for a ratio": (lambda f: edit_toml(f, 'distance_per_length = "0.8 um/m"', 'distance_per_length = "0.8"'),
                                ["recording.toml", "tracker.distance_per_length", "needs an explicit unit"]),
    "list for a quantity": (lambda f: edit_toml(f, 'distance_per_length = "0.8 um/m"', "distance_per_length = [1, 2]"),
                            ["recording.toml", "tracker.distance_per_length", "expected a quantity string"]),
    "implausible uncertainty": (lambda f: edit_toml(f, 'repeatability = "1.5 um"', 'repeatability = "1.5 m"'),
                                ["recording.toml", "machine_tool.repeatability", "not a plausible standard uncertainty"]),
    "delta reference temperature": (lambda f: edit_toml(f, '"20 degC"', '"20 delta_degC"'),
                                    ["recording.toml", "reference_temperature", "temperature difference"]),
    "reference temperature below absolute zero": (lambda f: edit_toml(f, '"20 degC"', '"-300 degC"'),
                                                  ["recording.toml", "reference_temperature", "plausible"]),
    "name not a string": (lambda f: edit_toml(f, 'name = "null"', "name = 7"), ["recording.toml", "name", "expected a string"]),
    "latin-1 recording.toml": (lambda f: edit_bytes(f, lambda b: b.replace(b'description = ""', 'description = "Maß"'.encode("latin-1")),
                                                    "recording.toml"),
                               ["recording.toml", "line 4", "0xDF", "byte offset"]),
}


@pytest.mark.parametrize("case", sorted(CASES) + [f"strict: {k}" for k in sorted(STRICT)])
def test_bad_input_names_file_line_and_column(case, broken):
    """Every damaged recording: one line naming the file, the line and the column (or key)."""
    damage, must_contain = STRICT[case[len("strict: "):]] if case.startswith("strict: ") else CASES[case]
    damage(broken)
    with pytest.raises(RecordingError) as info:
        read_recording(broken)
    msg = str(info.value)
    for part in must_contain:
        assert part in msg, (case, msg)
    assert "\n" not in msg



@pytest.mark.parametrize("edit", ["bom", "crlf", "bom+crlf", "blank lines", "spaces", "ignored column", "reordered"])
def test_harmless_variants_read_identically(edit, broken):
    base = read_recording(broken)
    if edit == "bom":
        edit_bytes(broken, lambda b: b"\xef\xbb\xbf" + b)
    elif edit == "crlf":
        edit_bytes(broken, lambda b: b.replace(b"\n", b"\r\n"))
    elif edit == "bom+crlf":
        edit_bytes(broken, lambda b: b"\xef\xbb\xbf" + b.replace(b"\n", b"\r\n"))
    elif edit == "blank lines":
        edit_csv(broken, lambda L: L[:5] + ["", "   "] + L[5:] + [""])
    elif edit == "spaces":
        edit_csv(broken, lambda L: [",".join(f" {c} " for c in ln.split(",")) for ln in L])
    elif edit == "ignored column":
        edit_toml(broken, 'format = "mtbudget-recording/1"', 'format = "mtbudget-recording/1"\nignore_columns = ["operator"]')
        edit_csv(broken, lambda L: [L[0] + ",operator"] + [ln + ",J. Doe (shift 2)" for ln in L[1:]])
    else:
        edit_csv(broken, lambda L: [",".join(reversed(ln.split(","))) for ln in L])
    back = read_recording(broken)
    for a, b in [(base.plan.point, back.plan.point), (base.plan.time, back.plan.time), (base.plan.nominal, back.plan.nominal),
                 (base.plan.direction, back.plan.direction), (base.plan.tool, back.plan.tool), (base.lt, back.lt)]:
        assert np.array_equal(a, b)
    for c in base.plan.temperature:
        assert np.array_equal(base.plan.temperature[c], back.plan.temperature[c])


def test_a_last_line_cut_mid_number_is_refused_naming_file_and_line(broken):
    """Issue 29: '646.506904' cut to '64' with no final newline read as 64 mm (exit 0); a file whose last line has no
    line ending is refused with its line number, and the same line ended by a newline reads."""
    data = (broken / "points.csv").read_bytes()
    last = data.rstrip(b"\n").count(b"\n") + 1  # the line number of the last row
    (broken / "points.csv").write_bytes(data.rstrip(b"\n")[:-4])
    with pytest.raises(RecordingError) as info:
        read_recording(broken)
    msg = str(info.value)
    assert "points.csv" in msg and f"line {last}:" in msg and "no line ending" in msg and "\n" not in msg
    (broken / "points.csv").write_bytes(data.rstrip(b"\n")[:-4] + b"\r\n")  # ended: it is a complete line, read
    assert len(read_recording(broken)) == last - 1


def test_size_guards_refuse_before_parsing(broken):
    with pytest.raises(RecordingError, match=r"points\.csv, line 12: more than 10 data rows; .*max_rows=10"):
        read_recording(broken, max_rows=10)
    with pytest.raises(RecordingError, match=r"line 1: 19 columns; .*max_columns=12"):
        read_recording(broken, max_columns=12)
    edit_csv(broken, lambda L: L[:3] + ["1" * 70000] + L[3:])
    with pytest.raises(RecordingError, match=r"line 4: line longer than 65536 bytes"):
        read_recording(broken)


def test_an_explicit_encoding_reads_a_latin1_export(broken):
    edit_toml(broken, 'format = "mtbudget-recording/1"', 'format = "mtbudget-recording/1"\nignore_columns = ["remark"]')
    edit_csv(broken, lambda L: [L[0] + ",remark"] + [ln + ",20°C Halle" for ln in L[1:]])
    edit_bytes(broken, lambda b: b.decode().encode("latin-1"))
    with pytest.raises(RecordingError, match="0xB0 .* it is ° .*Latin-1"):
        read_recording(broken)
    assert len(read_recording(broken, encoding="latin-1")) == 300
    with pytest.raises(RecordingError, match="not an ASCII-compatible encoding"):
        read_recording(broken, encoding="utf-16")


def test_writer_escapes_names_and_reads_them_back(broken, tmp_path):
    rec = read_recording(broken)
    rec.name, rec.description = 'shop "A"\\hall\n3\x7f', "tab\there"
    back = read_recording(write_recording(rec, tmp_path / "w"))
    assert (back.name, back.description) == (rec.name, rec.description)
    assert np.array_equal(back.plan.point, rec.plan.point)


def test_undeclared_columns_are_checked_then_left_out_and_listed(broken):
    """A column no [[sensors]] table declares (a sensor taken out, an operator's note) reads but is not used."""
    base = read_recording(broken)
    toml = (broken / "recording.toml").read_text()
    (broken / "recording.toml").write_text(toml.split("[[sensors]]")[0])  # no sensor declared any more
    edit_csv(broken, lambda L: [L[0] + ",note,humidity [percent]"] + [ln + ",ok; re-zeroed,45" for ln in L[1:]])
    rec = read_recording(broken)
    assert rec.plan.temperature == {} and rec.unused_columns == ["T_x", "T_y", "T_z", "T_air", "note", "humidity"]
    assert np.array_equal(rec.lt, base.lt) and base.unused_columns == []
