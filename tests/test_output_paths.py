"""Every command that writes a folder or a file refuses a path it cannot create in one line, exit 2 (a parent that
is a file, a special file system such as /proc), before computing anything: one helper, mtbudget.errors.make_folder
and check_folder, not one per command."""

import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.errors import OutputError, check_folder, make_folder

HERE = Path(__file__).parent
SMALL = HERE / "data" / "small.toml"


def _commands(afile: Path, log: Path):
    bad = str(afile / "sub")
    return {
        "simulate --out": ["simulate", str(SMALL), "--out", bad],
        "report --out": ["report", str(log), "--out", bad],
        "diagnose --report": ["diagnose", "--example", "null", "--report", bad],
        "posterior --out": ["posterior", "--example", "null", "--out", bad],
        "compensate --out": ["compensate", "--example", "null", "--format", "linuxcnc", "--out", bad + "/t.txt"],
        "compensate --report": ["compensate", "--example", "null", "--format", "linuxcnc", "--out",
                                str(afile.parent / "ok" / "t.txt"), "--report", bad],
        "run --log": ["run", str(SMALL), "--trials", "4", "--log", bad + "/run.mcap"],
        "study placement --out": ["study", "placement", str(SMALL), "--out", bad],
        "study verification --out": ["study", "verification", str(SMALL), "--out", bad],
        "study stations --out": ["study", "stations", str(SMALL), "--out", bad],
        "study station-placement --out": ["study", "station-placement", str(SMALL), "--out", bad],
    }


@pytest.mark.parametrize("name", sorted(_commands(Path("a"), Path("b"))))
def test_a_parent_that_is_a_file_is_one_line_exit_2(tmp_path, name):
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    log = tmp_path / "run.mcap"
    log.write_bytes(b"\x89MCAP0\r\n")  # never read: the path is refused first
    args = _commands(afile, log)[name]
    res = CliRunner().invoke(main, args)
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2, (name, res.exit_code, res.output, res.exception)
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    option = name.split()[-1]
    assert option in lines[0] and "afile" in lines[0] and "cannot create the folder" in lines[0], lines[0]
    assert not (tmp_path / "ok").exists() or name == "compensate --report"  # nothing written before the refusal


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc")
def test_a_folder_the_file_system_refuses_is_one_line():
    with pytest.raises(OutputError, match=r"^--out '/proc/mtbudget-x/y': cannot create the folder \(.+\)$"):
        make_folder("/proc/mtbudget-x/y", "--out")
    res = CliRunner().invoke(main, ["compensate", "--example", "null", "--format", "linuxcnc", "--out",
                                    "/proc/mtbudget-x/t.txt"])
    lines = [ln for ln in res.output.splitlines() if ln.strip() and not ln.startswith("compiling")]
    assert res.exit_code == 2 and len(lines) == 1 and "--out '/proc/mtbudget-x'" in lines[0], res.output


def test_an_existing_file_in_place_of_the_folder(tmp_path):
    f = tmp_path / "f"
    f.write_text("")
    with pytest.raises(OutputError, match="a file of that name is there"):
        check_folder(f, "--out")
    check_folder(tmp_path / "new" / "deeper", "--out")  # creatable: nothing said, nothing created
    assert not (tmp_path / "new").exists()
    assert make_folder(tmp_path / "new" / "deeper").is_dir()
