"""The independent four-station generator of the tests (issue 20), written from the paper's equations with plain
numpy: the Eq. 6 small-angle chain of an XFYZ machine with Legendre error functions, the Eq. 22 rotation as
Rx(a) Ry(b) Rz(d), spherical tracker noise, ranges plus a dead path.  It calls neither mtbudget's chain nor its
tracker model nor any diagnosis candidate; tests/test_multistation.py and tests/test_diagnose_stations.py draw
their recordings with it (mtbudget holds the numbers: Plan, Recording).
"""

from __future__ import annotations

import numpy as np
from numpy.polynomial import legendre

from mtbudget.plan import Plan
from mtbudget.recording import Recording, Station

X_POS, Y_POS, Z_POS = [800., 900., 1000., 1100., 1200.], [100., 200., 300., 400., 500.], [200., 300., 400.]
DEGREE = {"x": 3, "y": 3, "z": 2}  # distinct positions - 1, at most 3 (the default error model's choice)


def true_errors(rng) -> dict:
    """A machine: {parameter name: value (mm or rad)}, the terms of the default (ISO 230-1) error model.

    The roll of Y and Z (ez(y), ez(z)) is zero: with tool offsets along z only, no station can see it.
    """
    out = {}
    for a in "xyz":
        for kind in "de":
            for c in "xyz":
                err = f"{kind}{c}({a})"
                if kind == "e" and c == "z" and a in "yz":
                    continue
                first = 2 if (kind == "d" and c != a) else 1
                if kind == "e" and a == "z":
                    first = 0  # the tilt of the tool holder, seen through the tool offsets
                for n in range(first, DEGREE[a] + 1):
                    scale = 6e-3 if kind == "d" else 8e-6  # a few um, a few urad
                    out[f"{err}[P{n}]"] = float(rng.normal(0, scale / max(n, 1)))
    for s in ("sxy", "sxz", "syz"):
        out[s] = float(rng.normal(0, 30e-6))
    return out


def _legendre(axis, pos, coefs: dict) -> np.ndarray:
    vals = {"x": X_POS, "y": Y_POS, "z": Z_POS}[axis]
    lo, hi = min(vals), max(vals)
    u = (pos - 0.5 * (lo + hi)) / (0.5 * (hi - lo))
    out = np.zeros_like(pos)
    for n, c in coefs.items():
        e = np.zeros(n + 1)
        e[n] = 1.0
        out += c * legendre.legval(u, e)
    return out


def _component(errors, kind, comp, axis, pos):
    coefs = {}
    for name, v in errors.items():
        if name.startswith(f"{kind}{comp}({axis})["):
            coefs[int(name.split("[P")[1][:-1])] = v
    return _legendre(axis, pos, coefs)


def _cross(e, v):
    return np.stack([e[:, 1] * v[:, 2] - e[:, 2] * v[:, 1], e[:, 2] * v[:, 0] - e[:, 0] * v[:, 2],
                     e[:, 0] * v[:, 1] - e[:, 1] * v[:, 0]], axis=1)


def machine_point(errors, nominal, tool) -> np.ndarray:
    """The XFYZ tool point in the workpiece frame (paper Eq. 2, 6-9): P_W = R_X^-1 (A_Y(A_Z(T)) - t_X)."""
    px, py, pz = nominal[:, 0], nominal[:, 1], nominal[:, 2]
    delta = {a: np.stack([_component(errors, "d", c, a, nominal[:, i]) for c in "xyz"], axis=1)
             for i, a in enumerate("xyz")}
    eps = {a: np.stack([_component(errors, "e", c, a, nominal[:, i]) for c in "xyz"], axis=1)
           for i, a in enumerate("xyz")}
    z0 = np.zeros_like(px)
    t_x = np.stack([-px, z0, z0], axis=1) + delta["x"]  # X carries the workpiece: s = -1
    t_y = np.stack([-py * errors["sxy"], py, z0], axis=1) + delta["y"]
    t_z = np.stack([-pz * errors["sxz"], -pz * errors["syz"], pz], axis=1) + delta["z"]
    v = tool + _cross(eps["z"], tool) + t_z  # A_Z(T) = (I + [eps_z]x) T + t_z
    v = v + _cross(eps["y"], v) + t_y  # A_Y
    w = v - t_x
    out = np.empty_like(w)
    for i in range(len(w)):  # R_X^-1 (w), R_X = I + [eps_x]x, inverted exactly
        e = eps["x"][i]
        R = np.eye(3) + np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
        out[i] = np.linalg.solve(R, w[i])
    return out


def rot(a, b, d) -> np.ndarray:
    """Eq. 22: Rx(a) Ry(b) Rz(d)."""
    ca, sa, cb, sb, cd, sd = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(d), np.sin(d)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rz = np.array([[cd, -sd, 0], [sd, cd, 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


TRACKER = {"angular": 5e-6, "distance": 4e-3, "distance_per_length": 0.8e-6}  # rad, mm, mm/mm (k = 1)
INTERFEROMETER = {"distance": 0.5e-3, "distance_per_length": 0.3e-6}
REPEAT = 1.5e-3  # mm


def station_recording(cols: dict, stations, name: str, repeat: float = REPEAT) -> Recording:
    """The format-2 recording of generated rows (``cols``: per station, point, run, nominal, tool, station, lt,
    range), the stations declared with the stated uncertainties above, one row every 20 s."""
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    M = len(cat["point"])
    plan = Plan(point=cat["point"], run=cat["run"], time=np.arange(M) * 20.0, nominal=cat["nominal"],
                direction=np.ones((M, 3)), tool=cat["tool"])
    decl = [Station(sid, kind, TRACKER["angular"] if kind == "xyz" else None,
                    TRACKER["distance"] if kind == "xyz" else INTERFEROMETER["distance"],
                    TRACKER["distance_per_length"] if kind == "xyz" else INTERFEROMETER["distance_per_length"])
            for sid, kind, _ in stations]
    return Recording(name=name, machine="XFYZ", plan=plan, lt=cat["lt"], angular=TRACKER["angular"],
                     distance=TRACKER["distance"], distance_per_length=TRACKER["distance_per_length"],
                     repeatability=repeat, station=cat["station"], stations=decl, lt_range=cat["range"],
                     format_version=2)
