#!/usr/bin/env python3
"""LinuxCNC "display" for tests/test_controller_linuxcnc.py: drives a headless LinuxCNC and reads HAL back.

LinuxCNC starts it as its DISPLAY program (``driver.py -ini machine.ini``) under the system Python that has
LinuxCNC's ``linuxcnc`` and ``hal`` modules (not mtbudget's virtualenv).  It reads ``plan.json`` beside the INI
file: a list of moves [joint, axis letter, target mm, direction +1/-1]; for each it commands the axis (MDI G0)
to ``target - direction * approach`` and then to ``target``, so it arrives moving in ``direction``, waits, and
reads ``joint.N.pos-cmd`` (the commanded joint position) and ``joint.N.motor-pos-cmd`` (what goes to the motor:
pos-cmd plus the compensation LinuxCNC applies) from HAL.  It writes ``result.json`` beside the INI file and
exits, which shuts LinuxCNC down.  Nothing here knows the tables: the test compares the read-back with them.
"""

import json
import sys
import time
import traceback
from pathlib import Path

import hal
import linuxcnc


def main():
    ini = Path(sys.argv[sys.argv.index("-ini") + 1]).resolve()
    folder = ini.parent
    plan = json.loads((folder / "plan.json").read_text())
    out = {"rows": [], "linuxcnc_version": getattr(linuxcnc, "version", "?")}
    s, c = linuxcnc.stat(), linuxcnc.command()
    comp = hal.component("mtbudget-driver")  # hal.get_value needs this process attached to HAL
    comp.ready()

    def wait(timeout=60.0):
        if c.wait_complete(timeout) == -1:
            raise RuntimeError("LinuxCNC did not complete a command in time")

    def until(cond, what, timeout=30.0):
        end = time.time() + timeout
        while time.time() < end:
            s.poll()
            if cond():
                return
            time.sleep(0.02)
        raise RuntimeError(f"timed out waiting for {what}")

    try:
        c.state(linuxcnc.STATE_ESTOP_RESET)
        wait()
        c.state(linuxcnc.STATE_ON)
        wait()
        until(lambda: s.task_state == linuxcnc.STATE_ON, "machine on")
        c.mode(linuxcnc.MODE_MANUAL)
        wait()
        c.teleop_enable(False)
        wait()
        c.home(-1)
        wait()
        n = plan["joints"]
        until(lambda: all(s.homed[:n]), "homing")
        c.mode(linuxcnc.MODE_MDI)
        wait()
        until(lambda: s.task_mode == linuxcnc.MODE_MDI, "MDI mode")
        approach, settle = plan["approach_mm"], plan["settle_s"]
        for joint, axis, target, direction in plan["moves"]:
            for p in (target - direction * approach, target):
                c.mdi(f"G90 G53 G0 {axis}{p:.6f}")
                wait()
            time.sleep(settle)  # LinuxCNC slews the applied correction to its new value after the move
            pos = hal.get_value(f"joint.{joint}.pos-cmd")
            motor = hal.get_value(f"joint.{joint}.motor-pos-cmd")
            out["rows"].append([joint, axis, target, direction, pos, motor])
    except Exception:
        out["error"] = traceback.format_exc()
    (folder / "result.json").write_text(json.dumps(out))


if __name__ == "__main__":
    main()
