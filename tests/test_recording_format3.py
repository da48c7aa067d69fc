"""Format 3 (five-axis recordings, issue 26): read strictly, written back, every mistake one line naming file and key
or line/column, exit 2, no traceback and no number."""

import re
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.machine import RotaryAxis
from mtbudget.plan import build_plan
from mtbudget.recording import Recording, read_recording, write_recording

ROT = {"a": RotaryAxis("a", (0.0, -20.0, -80.0), 1.0), "c": RotaryAxis("c", (50.0, -20.0, 0.0), -1.0)}


def _recording(tmp_path, name="r5"):
    lin = [(x, y, z) for z in (-100.0, 100.0) for y in (-100.0, 100.0) for x in (-150.0, 0.0, 150.0)]
    poses = [(a, c) for a in np.radians([-60.0, 0.0, 45.0]) for c in np.radians([0.0, 120.0, 240.0])]
    pts = np.array([list(l) + list(p) for p in poses for l in lin])
    plan = build_plan(pts, [(0.0, 0.0, -100.0), (0.0, 0.0, -180.0)], runs=1, rotary=ROT)
    rng = np.random.default_rng(0)
    rec = Recording(name=name, machine="CAFXYZ", plan=plan, lt=rng.normal(0, 500, (len(plan), 3)), angular=5e-6,
                    distance=4e-3, distance_per_length=0.8e-6, repeatability=1.5e-3, format_version=3)
    return write_recording(rec, tmp_path / name), rec


def test_round_trip(tmp_path):
    folder, rec = _recording(tmp_path)
    back = read_recording(folder)
    assert back.format_version == 3 and back.machine == "CAFXYZ" and back.mount == "table"
    assert back.rotary == ROT
    for r in "ac":
        np.testing.assert_allclose(back.plan.angles[r], rec.plan.angles[r], atol=1e-11)
        np.testing.assert_array_equal(back.plan.angle_direction[r], rec.plan.angle_direction[r])
    np.testing.assert_allclose(back.lt, rec.lt, atol=1e-6)


def test_angles_in_any_angle_unit_read_the_same(tmp_path):
    folder, rec = _recording(tmp_path)
    text = (folder / "points.csv").read_text().splitlines()
    head = text[0].split(",")
    j = head.index("c [deg]")
    head[j] = "c [arcmin]"
    rows = [head]
    for line in text[1:]:
        cells = line.split(",")
        cells[j] = repr(float(cells[j]) * 60.0)
        rows.append(cells)
    (folder / "points.csv").write_text("\n".join(",".join(r) for r in rows) + "\n")
    np.testing.assert_allclose(read_recording(folder).plan.angles["c"], rec.plan.angles["c"], atol=1e-11)


def _edit_toml(folder, old, new):
    p = folder / "recording.toml"
    text = p.read_text()
    assert old in text, old
    p.write_text(text.replace(old, new, 1))


def _edit_csv(folder, fn):
    p = folder / "points.csv"
    lines = p.read_text().splitlines()
    p.write_text("\n".join(fn(lines)) + "\n")


def _drop_column(name):
    def fn(lines):
        j = lines[0].split(",").index(name)
        return [",".join(c for k, c in enumerate(line.split(",")) if k != j) for line in lines]
    return fn


def _rename_column(old, new):
    def fn(lines):
        return [lines[0].replace(old, new, 1)] + lines[1:]
    return fn


def _add_b(lines):
    return [lines[0] + ",b [deg]"] + [line + ",0" for line in lines[1:]]


def _one_angle(lines):
    j = lines[0].split(",").index("c [deg]")
    return [lines[0]] + [",".join("0" if k == j else c for k, c in enumerate(line.split(","))) for line in lines[1:]]


def _pose_changes(lines):
    j = lines[0].split(",").index("a [deg]")
    cells = lines[2].split(",")
    cells[j] = "1.5"
    return lines[:2] + [",".join(cells)] + lines[3:]


CASES = [
    ("no table", lambda f: _edit_toml(f, '[rotary.C]\npivot = ["50.000000 mm", "-20.000000 mm", "0.000000 mm"]\n'
                                         'direction = "-z"\n', ""), r"recording\.toml.*rotary\.C.*no \[rotary\.C\]"),
    ("direction", lambda f: _edit_toml(f, 'direction = "-z"', 'direction = "+y"'),
     r"rotary\.C\.direction.*does not match axis C"),
    ("extra table", lambda f: _edit_toml(f, "[rotary.C]", "[rotary.B]\npivot = [\"0 mm\", \"0 mm\", \"0 mm\"]\n"
                                         "direction = \"+y\"\n\n[rotary.C]"), r"rotary\.B.*does not have"),
    ("pivot unit", lambda f: _edit_toml(f, '"50.000000 mm"', '"50"'), r"rotary\.C\.pivot\[0\]"),
    ("pivot length", lambda f: _edit_toml(f, 'pivot = ["50.000000 mm", "-20.000000 mm", "0.000000 mm"]',
                                          'pivot = ["50 mm", "0 mm"]'), r"rotary\.C\.pivot.*three lengths"),
    ("format 2", lambda f: _edit_toml(f, "mtbudget-recording/3", "mtbudget-recording/1"),
     r"recording\.toml, format:.*rotary axes"),
    ("mount", lambda f: _edit_toml(f, 'mount = "table"', 'mount = "bed"'), r"tracker\.mount.*sees none"),
    ("angle without unit", lambda f: _edit_csv(f, _rename_column("c [deg]", "c")), r"points\.csv.*column 'c'.*unit"),
    ("angle not an angle", lambda f: _edit_csv(f, _rename_column("c [deg]", "c [ppm]")),
     r"points\.csv.*line 1.*not an angle"),
    ("missing angle", lambda f: _edit_csv(f, _drop_column("a [deg]")), r"points\.csv.*missing column 'a'"),
    ("axis not in machine", lambda f: _edit_csv(f, _add_b), r"points\.csv.*column 'b \[deg\]'.*rotary axis B"),
    ("one angle", lambda f: _edit_csv(f, _one_angle), r"points\.csv.*column 'c'.*one angle only.*EXOC"),
    ("pose changes", lambda f: _edit_csv(f, _pose_changes), r"points\.csv.*line \d+.*one nominal pose"),
]


@pytest.mark.parametrize("label,mutate,pattern", CASES, ids=[c[0] for c in CASES])
def test_bad_format3_input_is_one_line(tmp_path, label, mutate, pattern):
    folder, _ = _recording(tmp_path)
    mutate(folder)
    res = CliRunner().invoke(main, ["identify", str(folder)])
    assert res.exit_code == 2, res.output
    out = res.output.strip()
    assert "Traceback" not in out and len(out.splitlines()) == 1, out
    assert re.search(pattern, out), out
    assert not re.search(r"chi-square|identified '|µm|urad", out)


def test_a_rotary_column_in_format_1_is_refused(tmp_path):
    src = read_recording(shutil.copytree(
        __import__("mtbudget.config", fromlist=["example_recording"]).example_recording("null"), tmp_path / "n"))
    _edit_csv(src.path, _add_b)
    res = CliRunner().invoke(main, ["identify", str(src.path)])
    assert res.exit_code == 2 and "format = \"mtbudget-recording/3\"" in res.output, res.output


def test_a_fit_that_cannot_be_right_is_said_before_any_number(tmp_path):
    """Angles written in degrees under an `a [rad]` header read as a valid recording (radians are an angle unit), but
    the fit cannot describe it: identify says so on stderr (and in the JSON) before a number is used."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from fiveaxis_generator import make_recording

    folder = tmp_path / "r"
    make_recording(folder, "CAFXYZ", seed=2)
    res = CliRunner().invoke(main, ["identify", str(folder)])
    assert res.exit_code == 0 and "warning" not in res.output, res.output  # the right units: no warning
    _edit_csv(folder, _rename_column("a [deg]", "a [rad]"))
    res = CliRunner().invoke(main, ["identify", str(folder), "--json"])
    assert res.exit_code == 0
    assert "warning:" in res.stderr and "not an identification of the machine" in res.stderr
    import json

    assert "not an identification" in json.loads(res.stdout)["warning"]


def test_rotary_harmonics_are_identified_on_request(tmp_path):
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from fiveaxis_generator import make_recording

    folder = tmp_path / "r"
    make_recording(folder, "CAFXYZ", seed=3)
    res = CliRunner().invoke(main, ["identify", str(folder), "--json", "--rotary-harmonics", "2"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    names = {p["iso"] for p in d["parameters"]}
    assert {"ECC[c1]", "ECC[s1]", "EXC[c2]"} <= names and "EXC[c1]" not in names  # radial c1/s1 left out
    # the plan's C angles 0, 90, 180, 270 deg do not see sin 2c: those terms are named as not identifiable
    flat = {e["iso"] for c in d["not_identifiable"] for e in c}
    assert "ECC[s2]" in flat
    assert 0.8 < d["chi2_per_dof"] < 1.25
