"""Recordings with periodic, local, refraction and rotation physics, written independently of the candidates (issue 30).

The rigid machine, its geometric errors, the tracker at a random pose, the temperatures and the noise are drawn by
mtbudget's simulator (the one every verification uses; it holds no candidate).  The physics under test is then put
into the measured tracker points by the plain numpy below, from the physical statement of each effect, never from
a candidate's columns:

* ``screw``: a lead-screw (ISO 230-2 periodic) error of X: the axis stands A sin(2 pi x / P + phi) further along x
  than commanded;
* ``adm``: the ADM's cyclic error: every measured distance is A sin(2 pi r / P + phi) too long;
* ``range_scale``: every distance is (1 + s) times the true one (a refractive index wrong by s: for example a
  weather station's altitude not entered);
* ``local_backlash``: lost motion B of X only where x > c (a worn section of the nut): approaching from either side
  the axis stops B/2 short of the target there;
* ``rotation``: the tracker's azimuth zero turning at w (rad/s): every measured azimuth is off by w (t - t0);
* nothing (a null).

The machine's frame is recovered from the points themselves (a Kabsch fit of the nominal tool points to the
measured ones), so a machine-frame displacement is put into the tracker frame without the simulator's pose
convention.  The mesh is finer along X (25 mm) than the calibration's (100 mm), so a period of 100-200 mm is seen.
"""

from __future__ import annotations

import copy
import tempfile
from pathlib import Path

import numpy as np

from mtbudget.config import parse_config
from mtbudget.recording import read_recording, write_recording
from mtbudget.scenario import build_scenario
from mtbudget.simulate import simulate_recording
from mtbudget.testing import BASE


def config(seed: int, step_x: float = 25.0):
    """A random verification: tracker pose, drifting temperatures, the calibration's noise, a fine X mesh."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 30]))
    raw = copy.deepcopy(BASE)
    raw["seed"] = int(seed)
    raw["geometric_errors"]["seed"] = int(seed) + 3000
    raw["mesh"] = {"x": ["800 mm", "1200 mm"], "y": ["100 mm", "500 mm"], "z": ["200 mm", "400 mm"],
                   "step": "200 mm", "step_x": f"{step_x} mm"}
    t = raw["tracker"]
    t["D"] = f"{rng.uniform(-1100, -600):.3f} mm"
    t["L"] = f"{rng.uniform(-100, 500):.3f} mm"
    t["H"] = f"{rng.uniform(500, 800):.3f} mm"
    t["a"], t["b"] = f"{rng.normal(0, 0.003):.6f} rad", f"{rng.normal(0, 0.003):.6f} rad"
    t["d"] = f"{rng.uniform(-0.45, 0.45):.6f} rad"
    raw["sensors"] = []
    for col, att in (("T_x", "x axis"), ("T_y", "y axis"), ("T_z", "z axis"), ("T_air", "air")):
        raw["sensors"].append({"column": col, "attached_to": att, "start": f"{rng.uniform(19.8, 20.8):.3f} degC",
                               "rate": f"{rng.choice([-1, 1]) * rng.uniform(0.2, 0.5):.3f} K/h", "noise": "0.015 K",
                               "cycle_amplitude": f"{rng.uniform(0.0, 0.1):.3f} K",
                               "cycle_period": f"{rng.uniform(15, 40):.1f} min",
                               "cycle_phase": f"{rng.uniform(0, 6.28):.3f} rad"})
    return parse_config(raw)


def _kabsch(A, B):
    """Rotation R minimising |R (A - mean A) - (B - mean B)|: A in the machine frame, B in the tracker frame."""
    a, b = A - A.mean(0), B - B.mean(0)
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def add_physics(rec, effect: dict | None):
    """Put ``effect`` (a dict with ``kind`` and its parameters, mm, s, rad) into the recording's tracker points."""
    if not effect:
        return rec
    plan = rec.plan
    P = rec.lt.copy()
    Pm = plan.nominal + plan.tool
    R = _kabsch(Pm, P)  # machine -> tracker (to a few urad: the geometric errors are um)
    if np.sqrt(np.mean(np.sum((Pm - Pm.mean(0)) @ R.T - (P - P.mean(0)), axis=1) ** 2)) > 1.0:
        # the table moves the part: the measured tool point moves against x; try the mirrored machine frame
        raise AssertionError("the machine frame could not be matched to the tracker points")
    kind = effect["kind"]
    x = plan.nominal[:, 0]
    if kind == "screw":
        d = np.zeros_like(P)
        d[:, 0] = effect["amplitude"] * np.sin(2 * np.pi * x / effect["period"] + effect["phase"])
        P = P + d @ R.T
    elif kind == "local_backlash":
        d = np.zeros_like(P)
        d[:, 0] = -plan.direction[:, 0] * effect["B"] / 2 * (x > effect["above"])
        P = P + d @ R.T
    elif kind == "adm":
        r = np.linalg.norm(P, axis=1)
        P = P * ((r + effect["amplitude"] * np.sin(2 * np.pi * r / effect["period"] + effect["phase"])) / r)[:, None]
    elif kind == "range_scale":
        P = P * (1 + effect["scale"])
    elif kind == "rotation":
        ang = effect["rate"] * (plan.time - plan.time[0])
        c, s = np.cos(ang), np.sin(ang)
        P = np.stack([c * P[:, 0] - s * P[:, 1], s * P[:, 0] + c * P[:, 1], P[:, 2]], axis=1)
    else:
        raise ValueError(f"unknown effect {kind!r}")
    rec.lt = P
    return rec


def recording(seed: int, effect: dict | None = None, step_x: float = 25.0):
    """The recording of ``seed`` with ``effect``, written and read back as a shop would send it."""
    cfg = config(seed, step_x)
    rec, _ = simulate_recording(build_scenario(cfg))
    rec = add_physics(rec, effect)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "rec"
        write_recording(rec, folder)
        return read_recording(folder)


def draw(kind: str, rng, variant: int = 1) -> dict:
    """An effect of ``kind`` with random parameters in the ranges of issue 30 (amplitudes in mm, rates in rad/s).

    ``variant`` 2 is the second set, drawn after the method was fixed: other magnitudes, periods and regions."""
    if variant == 2:
        return _draw2(kind, rng)
    if kind == "screw":
        return {"kind": kind, "amplitude": rng.uniform(0.005, 0.008), "period": rng.uniform(110.0, 170.0) + 0.37,
                "phase": rng.uniform(0, 2 * np.pi)}
    if kind == "adm":
        return {"kind": kind, "amplitude": rng.uniform(0.005, 0.008), "period": rng.uniform(30.0, 60.0) + 0.29,
                "phase": rng.uniform(0, 2 * np.pi)}
    if kind == "range_scale":
        return {"kind": kind, "scale": rng.choice([-1, 1]) * rng.uniform(10e-6, 30e-6)}
    if kind == "local_backlash":
        return {"kind": kind, "B": rng.uniform(0.012, 0.018), "above": rng.choice([960.0, 1010.0, 1060.0]) + 2.5}
    if kind == "rotation":
        return {"kind": kind, "rate": rng.choice([-1, 1]) * rng.uniform(6e-6, 10e-6) / 3600.0}
    if kind == "none":
        return {}
    raise ValueError(kind)


def _draw2(kind, rng):
    if kind == "screw":
        return {"kind": kind, "amplitude": rng.uniform(0.004, 0.010), "period": rng.uniform(85.0, 220.0),
                "phase": rng.uniform(0, 2 * np.pi)}
    if kind == "adm":
        return {"kind": kind, "amplitude": rng.uniform(0.004, 0.010), "period": rng.uniform(20.0, 90.0),
                "phase": rng.uniform(0, 2 * np.pi)}
    if kind == "range_scale":
        return {"kind": kind, "scale": rng.choice([-1, 1]) * rng.uniform(10e-6, 30e-6)}
    if kind == "local_backlash":
        return {"kind": kind, "B": rng.uniform(0.010, 0.022), "above": rng.choice([937.5, 987.5, 1037.5, 1087.5])}
    if kind == "rotation":
        return {"kind": kind, "rate": rng.choice([-1, 1]) * rng.uniform(5e-6, 12e-6) / 3600.0}
    return {}


KINDS = ("none", "screw", "adm", "range_scale", "local_backlash", "rotation")
