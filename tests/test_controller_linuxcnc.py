"""A real controller loads mtbudget's LinuxCNC tables and applies them as intended (issue 32).

LinuxCNC (Debian's ``linuxcnc-uspace``, a simulated trivkins XYZ machine in mm, headless: the DISPLAY is
tests/controllers/linuxcnc_driver.py) loads the files ``mtbudget compensate --format linuxcnc`` writes as
``COMP_FILE_TYPE = 1`` joint compensation, is commanded to every grid point and midpoint of each table (and
beyond both ends) arriving once from below and once from above, and the correction it applies is read back
from HAL: ``joint.N.motor-pos-cmd - joint.N.pos-cmd``.  That is compared with the table's intent, computed
here from the :class:`~mtbudget.compensate.AxisTable` (not from the file): moving in +, the trim is
``-(forward deviation)``, in -, ``-(reverse deviation)``, linear between grid points, the end values held
beyond the table; sign and size to the file's resolution (1 nm) plus what the last servo cycle of a move
leaves.  A second table has its reference point inside the range: LinuxCNC must apply zero (mean of the two
directions) there.

Needs LinuxCNC: ``apt-get install linuxcnc-uspace`` (.ci/run does it where it can), then
``python -m pytest -m controller tests/test_controller_linuxcnc.py`` (about a minute).  Skipped, with the
reason, where LinuxCNC is absent.  LinuxCNC runs one instance per machine (its lock file /tmp/linuxcnc.lock):
do not run two of these at once.
"""

from __future__ import annotations

import json
import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

from mtbudget.compensate import build_table, export, find_exporter
from mtbudget.config import example_recording
from mtbudget.recording import read_recording

pytestmark = pytest.mark.controller

DRIVER = Path(__file__).parent / "controllers" / "linuxcnc_driver.py"
AXES = "xyz"
#: the comparison's tolerance (um): the files' 6 decimals in mm (0.0005 um) and the slope of the table times the
#: last servo cycle's travel before the axis stops (LinuxCNC keeps the trim of the last moving cycle)
TOL_UM = 0.002


def _linuxcnc_python():
    """The system Python with LinuxCNC's modules, or None."""
    for py in ("/usr/bin/python3", shutil.which("python3")):
        if py and Path(py).is_file():
            ok = subprocess.run([py, "-c", "import linuxcnc, hal"], capture_output=True).returncode == 0
            if ok:
                return py
    return None


PYTHON = _linuxcnc_python()
if shutil.which("linuxcnc") is None or PYTHON is None:
    pytest.skip("LinuxCNC is not installed (Debian: apt-get install linuxcnc-uspace; .ci/run installs it where it "
                "can): the real-controller round trip needs its `linuxcnc` command and Python modules",
                allow_module_level=True)


HAL = """loadrt [KINS]KINEMATICS
loadrt [EMCMOT]EMCMOT servo_period_nsec=[EMCMOT]SERVO_PERIOD num_joints=[KINS]JOINTS
addf motion-command-handler servo-thread
addf motion-controller servo-thread
net j0 joint.0.motor-pos-cmd => joint.0.motor-pos-fb
net j1 joint.1.motor-pos-cmd => joint.1.motor-pos-fb
net j2 joint.2.motor-pos-cmd => joint.2.motor-pos-fb
net estop-loop iocontrol.0.user-enable-out => iocontrol.0.emc-enable-in
net tool-prep-loop iocontrol.0.tool-prepare => iocontrol.0.tool-prepared
net tool-change-loop iocontrol.0.tool-change => iocontrol.0.tool-changed
"""


def machine_ini(display: Path, comp_files: dict) -> str:
    """A simulated trivkins XYZ machine in mm, homing in place at 0, each joint with its COMP_FILE (type 1)."""
    text = f"""[EMC]
VERSION = 1.1
MACHINE = mtbudget-roundtrip
[DISPLAY]
DISPLAY = {display}
[TASK]
TASK = milltask
CYCLE_TIME = 0.001
[RS274NGC]
PARAMETER_FILE = sim.var
[EMCIO]
EMCIO = io
CYCLE_TIME = 0.100
TOOL_TABLE = tool.tbl
[EMCMOT]
EMCMOT = motmod
SERVO_PERIOD = 1000000
[HAL]
HALFILE = sim.hal
[TRAJ]
COORDINATES = XYZ
LINEAR_UNITS = mm
ANGULAR_UNITS = degree
MAX_LINEAR_VELOCITY = 500
[KINS]
JOINTS = 3
KINEMATICS = trivkins coordinates=XYZ
"""
    for j, a in enumerate(AXES):
        limits = "MIN_LIMIT = -100\nMAX_LIMIT = 2000\nMAX_VELOCITY = 500\nMAX_ACCELERATION = 5000\n"
        text += (f"[AXIS_{a.upper()}]\n{limits}[JOINT_{j}]\nTYPE = LINEAR\n{limits}FERROR = 1\nMIN_FERROR = 1\n"
                 "HOME = 0\nHOME_OFFSET = 0\nHOME_SEARCH_VEL = 0\nHOME_LATCH_VEL = 0\nHOME_SEQUENCE = 0\n"
                 f"BACKLASH = 0\nCOMP_FILE = {comp_files[a].name}\nCOMP_FILE_TYPE = 1\n")
    return text


def run_linuxcnc(comp_files: dict, moves: list) -> dict:
    """Start LinuxCNC with the tables ``comp_files`` (axis -> path) and the driver as its display; return the
    driver's result.json.  It runs in a fresh folder under the system's temporary directory, open to every user:
    started by root, LinuxCNC's realtime part runs as the fallback user (``nobody``), which must reach it."""
    folder = Path(tempfile.mkdtemp(prefix="mtbudget-linuxcnc-"))
    try:
        folder.chmod(0o777)
        local = {a: Path(shutil.copy(p, folder / p.name)) for a, p in comp_files.items()}
        display = folder / "display.sh"
        display.write_text(f'#!/bin/sh\nexec "{PYTHON}" "{DRIVER}" "$@"\n')
        display.chmod(0o755)
        (folder / "sim.hal").write_text(HAL)
        (folder / "tool.tbl").write_text("T1 P1 D0 Z0 ;\n")
        (folder / "machine.ini").write_text(machine_ini(display, local))
        (folder / "plan.json").write_text(json.dumps({"joints": 3, "approach_mm": 1.0, "settle_s": 0.05,
                                                      "moves": moves}))
        env = {**os.environ, "HOME": str(folder)}  # LinuxCNC writes its logs to $HOME on failure
        env.pop("DISPLAY", None)  # headless: no X display for its error dialogs
        if os.geteuid() == 0:  # LinuxCNC refuses to run its realtime part as root without a fallback user
            env["RTAPI_UID"] = str(pwd.getpwnam("nobody").pw_uid)
            env["RTAPI_FIFO_PATH"] = str(folder / ".rtapi_fifo")
        proc = subprocess.run(["linuxcnc", "-r", str(folder / "machine.ini")], cwd=folder, env=env,
                              capture_output=True, text=True, timeout=600)
        result = folder / "result.json"
        debug = folder / "linuxcnc_debug.txt"
        assert result.is_file(), (f"LinuxCNC ended (exit {proc.returncode}) without a result:\n{proc.stdout[-2000:]}"
                                  + (debug.read_text()[-2000:] if debug.is_file() else ""))
        out = json.loads(result.read_text())
        assert "error" not in out, out.get("error", "") + proc.stdout[-2000:]
        return out
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def intent(t, at, direction):
    """The trim (um) the table means at ``at`` arriving in ``direction``: -(deviation), held beyond the ends."""
    dev = t.forward if direction > 0 else t.reverse
    return -np.interp(at, t.positions, dev)


def moves_for(table) -> list:
    moves = []
    for j, a in enumerate(AXES):
        g = table.axes[a].positions
        pts = np.concatenate([[g[0] - 20.0], g, 0.5 * (g[1:] + g[:-1]), [g[-1] + 20.0]])
        moves += [[j, a.upper(), float(p), d] for p in np.sort(pts) for d in (1, -1)]
    return moves


def applied(out) -> dict:
    """(axis, target, direction) -> the correction LinuxCNC applied (um)."""
    return {(AXES[j], round(t, 6), d): (motor - pos) * 1e3 for j, _axis, t, d, pos, motor in out["rows"]}


@pytest.fixture(scope="module")
def reversal_y():
    return read_recording(example_recording("reversal_y"))


def test_linuxcnc_applies_the_tables_from_both_directions(tmp_path, reversal_y):
    table = build_table(reversal_y, 50.0)
    written = export(table, find_exporter("linuxcnc"), tmp_path / "mill.comp")
    out = run_linuxcnc(dict(zip(AXES, written)), moves_for(table))
    got = applied(out)
    assert len(got) == len(moves_for(table)) >= 90
    worst, signs = 0.0, 0
    for (a, at, d), trim in got.items():
        want = intent(table.axes[a], at, d)
        worst = max(worst, abs(trim - want))
        assert trim == pytest.approx(want, abs=TOL_UM), (a, at, d, trim, want)
        if abs(want) > 10 * TOL_UM:
            assert np.sign(trim) == np.sign(want)
            signs += 1
    assert signs > 40  # the sign is tested where the trim is not negligible
    # the reversal of Y (the simulated axis stops 4 um short from either side): the two directions differ by B
    B = table.axes["y"].reversal
    y_mid = float(table.axes["y"].positions[4])
    assert got[("y", round(y_mid, 6), -1)] - got[("y", round(y_mid, 6), 1)] == pytest.approx(B, abs=2 * TOL_UM)
    print(f"LinuxCNC {out['linuxcnc_version']}: {len(got)} positions and directions, largest |applied - intent| "
          f"{worst:.4f} um")


def test_linuxcnc_table_with_the_reference_point_inside_the_range(tmp_path, reversal_y):
    ref = {"x": 1000.0, "y": 275.0, "z": 300.0}  # y between grid points: zero where LinuxCNC interpolates
    table = build_table(reversal_y, 50.0, reference_point=ref)
    written = export(table, find_exporter("linuxcnc"), tmp_path / "mill.comp")
    moves = [[j, a.upper(), ref[a], d] for j, a in enumerate(AXES) for d in (1, -1)] + moves_for(table)[::3]
    got = applied(run_linuxcnc(dict(zip(AXES, written)), moves))
    for a in AXES:
        mean = 0.5 * (got[(a, ref[a], 1)] + got[(a, ref[a], -1)])
        assert mean == pytest.approx(0.0, abs=TOL_UM), (a, mean)  # zero at the reference point
    for (a, at, d), trim in got.items():
        assert trim == pytest.approx(intent(table.axes[a], at, d), abs=TOL_UM), (a, at, d)
