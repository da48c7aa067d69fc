"""The independent five-axis recording generator (issue 26): recordings in format 3 with their truth.

Written from the equations of ../shared/recordings/FORMAT-3.md (section 4) and docs/model.md (format 1) with
numpy and scipy's exact rotations only; it imports nothing from mtbudget (neither its chain, its tracker model,
its plan nor its recording writer), so that identifying its recordings with mtbudget is a test against truth
drawn by separate code.  tests/test_fiveaxis_acceptance.py and benchmarks/make_five_axis.py use it.

The model (every rotation exact):

* rotary axis k (pivot ``p``, nominal direction ``u``, recorded angle ``theta``): the element it carries maps to
  its carrier by ``G(v) = p + delta + Rot(w) R_u(theta) (v - p)``, ``w = e + eps u`` the small error rotation
  vector.  Its machine-frame components are the ISO 230-7 parameters: for C ``delta = (EXOC, EYOC, 0)`` um and
  ``w = (EAOC, EBOC, ECOC)`` urad; for A ``delta = (0, EYOA, EZOA)``, ``w = (EAOA, EBOA, ECOA)``; for B
  ``delta = (EXOB, 0, EZOB)``, ``w = (EAOB, EBOB, ECOB)``.  (FORMAT-3 writes ``E(e) R_u(theta + eps)``: the two
  differ by O(e eps), below 1e-12 mm here.)  With ``direction = "-x"`` (say) the ISO zero error stays the
  machine-frame component ``w_x``, so the angle error along ``u`` is ``-EAOA``.
* linear axis k (format 1): ``G(v) = R_k v + t_k``, ``R_k = Rot(eps_k)`` exact, ``t_k = s d_k + delta_k``,
  ``s = +1`` on the tool side and ``-1`` on the workpiece side, ``d_x = (x, 0, 0)``,
  ``d_y = (-y sxy, y, 0)``, ``d_z = (-z sxz, -z syz, z)``; ``delta_k``, ``eps_k``: Legendre P1..Pn of the axis
  position normalised to [-1, 1] over the positions the plan visits.
* tool point ``P_M = G_1(G_2(...G_n(T)))`` over the tool-side letters from ``F`` outwards, workpiece frame
  ``P_W = G_m^-1(...G_1^-1(P_M))`` over the workpiece-side letters from ``F`` outwards (``G_1`` next to ``F``
  applied first: for CAFXYZ ``P_W = G_C^-1(G_A^-1(P_M))``, FORMAT-3 section 4).
* tracker on the table (the workpiece-side element farthest from ``F``; the bed if there is none):
  ``lt = R_LT^T (P_W - T_LT)``, ``R_LT = Rx(a) Ry(b) Rz(d)`` (paper Eq. 22).
* noise: the machine's repeatability, isotropic normal at the tool point (added to ``P_M``), then normal noise
  in range (``u = distance + distance_per_length r``), azimuth and elevation (``u = angular``).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from numpy.polynomial import legendre
from scipy.spatial.transform import Rotation

FORMAT = "mtbudget-recording/3"
KINDS = ("CAFXYZ", "FXYZCB")  # the two; PRESETS also has the table-head CFXYZB
ROTARY = "ABC"
AXIS_INDEX = {"A": 0, "B": 1, "C": 2, "x": 0, "y": 1, "z": 2}
NOISE = {"angular": 5e-6, "distance": 4e-3, "distance_per_length": 0.8e-6, "repeatability": 1.5e-3}  # rad, mm, -, mm
LINEAR_SCALE = {"d": 6e-3, "e": 8e-6, "squareness": 30e-6}  # mm, rad, rad (like the bundled null example)
ROTARY_MAGNITUDE = {"offset": (10.0, 60.0), "orientation": (20.0, 100.0), "zero": (20.0, 100.0)}  # um, urad, urad
DT = 20.0  # s between rows

#: the default set-ups: chain, pivots (mm, machine frame with every axis at zero), directions, tracker pose
#: (D, L, H mm; a, b, d rad, in the table frame) and the plan (linear grid, rotary angles in deg, tool offsets in mm)
PRESETS = {
    "CAFXYZ": {
        "pivots": {"A": (0.0, -20.0, -80.0), "C": (50.0, -20.0, 0.0)},
        "directions": {"A": "+x", "C": "+z"},
        "tracker_pose": (-700.0, 250.0, 150.0, -0.002, 0.0004, -0.30),
        "plan": {"x": (-150.0, 0.0, 150.0), "y": (-150.0, 0.0, 150.0), "z": (100.0, 200.0, 300.0),
                 "angles": {"A": (-90.0, -45.0, 0.0, 45.0, 90.0), "C": (0.0, 90.0, 180.0, 270.0)},
                 "tools": ((0.0, 0.0, -100.0), (0.0, 0.0, -200.0))},
    },
    "FXYZCB": {
        "pivots": {"C": (0.0, 0.0, 300.0), "B": (0.0, 0.0, 150.0)},
        "directions": {"C": "+z", "B": "+y"},
        "tracker_pose": (-900.0, 250.0, 300.0, 0.0015, -0.0006, 0.25),
        "plan": {"x": (-200.0, 0.0, 200.0), "y": (-150.0, 0.0, 150.0), "z": (-100.0, 0.0, 100.0),
                 "angles": {"C": (0.0, 90.0, 180.0, 270.0), "B": (-60.0, -30.0, 0.0, 30.0, 60.0)},
                 "tools": ((0.0, 0.0, -100.0), (40.0, 0.0, -180.0))},
    },
    "CFXYZB": {  # table-head: C table on the bed (tracker on it), B head on Z
        "pivots": {"C": (30.0, -10.0, 0.0), "B": (0.0, 0.0, 150.0)},
        "directions": {"C": "+z", "B": "+y"},
        "tracker_pose": (-700.0, 250.0, 150.0, -0.002, 0.0004, -0.30),
        "plan": {"x": (-150.0, 0.0, 150.0), "y": (-150.0, 0.0, 150.0), "z": (100.0, 200.0, 300.0),
                 "angles": {"C": (0.0, 90.0, 180.0, 270.0), "B": (-60.0, -30.0, 0.0, 30.0, 60.0)},
                 "tools": ((0.0, 0.0, -100.0), (40.0, 0.0, -180.0))},
    },
}


# ---------------------------------------------------------------------------------------------- the machine
def split(machine: str) -> tuple[str, str]:
    """(workpiece-side letters from F outwards, tool-side letters from F outwards)."""
    f = machine.index("F")
    return machine[:f][::-1], machine[f + 1:]


def rotary_letters(machine: str) -> str:
    return "".join(L for L in ROTARY if L in machine)


def rotary_names(letter: str) -> dict:
    """ISO 230-7 names of one rotary axis: two offsets (um), two orientation errors and the zero error (urad)."""
    i = AXIS_INDEX[letter]
    others = [j for j in range(3) if j != i]
    return {"offset": [f"E{'XYZ'[j]}O{letter}" for j in others],
            "orientation": [f"E{'ABC'[j]}O{letter}" for j in others],
            "zero": f"E{'ABC'[i]}O{letter}"}


def all_rotary_names(machine: str) -> list:
    out = []
    for L in rotary_letters(machine):
        n = rotary_names(L)
        out += n["offset"] + n["orientation"] + [n["zero"]]
    return out


def direction_vector(text: str) -> np.ndarray:
    u = np.zeros(3)
    u[AXIS_INDEX[text[1]]] = 1.0 if text[0] == "+" else -1.0
    return u


def rotary_errors(letter: str, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """(delta mm, w rad): the machine-frame location offset and error rotation vector of one rotary axis."""
    i = AXIS_INDEX[letter]
    delta, w = np.zeros(3), np.zeros(3)
    for j in range(3):
        if j != i:
            delta[j] = params.get(f"E{'XYZ'[j]}O{letter}", 0.0) * 1e-3
        w[j] = params.get(f"E{'ABC'[j]}O{letter}", 0.0) * 1e-6
    return delta, w


def linear_error_names(degree: dict) -> list:
    """mtbudget's internal names of the linear-axis terms the truth may use: no straightness P1 and no P0 (the
    intersection of the ISO 230-1 and the free convention, so either identification represents them)."""
    out = []
    for a in "xyz":
        for kind in "de":
            for c in "xyz":
                first = 2 if (kind == "d" and c != a) else 1
                out += [f"{kind}{c}({a})[P{n}]" for n in range(first, degree[a] + 1)]
    return out


def _legendre(u, coefs: dict) -> np.ndarray:
    out = np.zeros_like(u)
    for n, c in coefs.items():
        e = np.zeros(n + 1)
        e[n] = 1.0
        out = out + c * legendre.legval(u, e)
    return out


def _linear_component(params, name, u):
    """One error function (mm or rad) of the normalised position u from params in um / urad."""
    scale = 1e-3 if name[0] == "d" else 1e-6
    coefs = {}
    for k, v in params.items():
        if k.startswith(name + "[P"):
            coefs[int(k[len(name) + 2:-1])] = v * scale
    return _legendre(u, coefs)


def normalised(pos, rng_mm):
    lo, hi = rng_mm
    return (pos - 0.5 * (lo + hi)) / (0.5 * (hi - lo)) if hi > lo else np.zeros_like(pos)


def linear_axis(letter, pos, params, ranges, side):
    """(R (M, 3, 3) as a scipy Rotation, t (M, 3) mm) of a linear axis at positions pos (mm)."""
    u = normalised(pos, ranges[letter])
    delta = np.stack([_linear_component(params, f"d{c}({letter})", u) for c in "xyz"], axis=1)
    eps = np.stack([_linear_component(params, f"e{c}({letter})", u) for c in "xyz"], axis=1)
    z0 = np.zeros_like(pos)
    sxy, sxz, syz = (params.get(s, 0.0) * 1e-6 for s in ("sxy", "sxz", "syz"))
    d = {"x": np.stack([pos, z0, z0], axis=1),
         "y": np.stack([-pos * sxy, pos, z0], axis=1),
         "z": np.stack([-pos * sxz, -pos * syz, pos], axis=1)}[letter]
    s = 1.0 if side == "tool" else -1.0
    return Rotation.from_rotvec(eps), s * d + delta


class Machine:
    """A five-axis machine of the generator: chain code, rotary pivots (mm) and directions."""

    def __init__(self, machine: str, pivots: dict, directions: dict, error_rotation: str = "exact"):
        self.machine = machine
        self.error_rotation = error_rotation  # "exact" Rot(w), or "small" I + [w]x (a diagnostic, not the truth)
        self.work, self.tool = split(machine)
        self.pivots = {L: np.asarray(p, float) for L, p in pivots.items()}
        self.directions = dict(directions)
        for L in rotary_letters(machine):
            if L not in self.pivots or L not in self.directions:
                raise ValueError(f"rotary axis {L} needs a pivot and a direction")
            if self.directions[L][1] != "xyz"[AXIS_INDEX[L]]:
                raise ValueError(f"direction {self.directions[L]!r} does not match the letter {L}")

    def _maps(self, letter, plan, params, ranges, side):
        """(forward, inverse) of axis ``letter`` over the plan's rows."""
        if letter in ROTARY:
            p, u = self.pivots[letter], direction_vector(self.directions[letter])
            theta = np.radians(plan["angles"][letter])
            R_nom = Rotation.from_rotvec(theta[:, None] * u)
            delta, w = rotary_errors(letter, params)
            if self.error_rotation == "small":
                E = np.eye(3) + np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
                return ((lambda v: p + delta + R_nom.apply(v - p) @ E.T),
                        (lambda v: p + R_nom.inv().apply(np.linalg.solve(E, (v - p - delta).T).T)))
            R = Rotation.from_rotvec(w) * R_nom  # Rot(w) R_u(theta): applied as R_nom first
            return (lambda v: p + delta + R.apply(v - p)), (lambda v: p + R.inv().apply(v - p - delta))
        pos = plan["xyz"][:, AXIS_INDEX[letter.lower()]]
        R, t = linear_axis(letter.lower(), pos, params, ranges, side)
        return (lambda v: R.apply(v) + t), (lambda v: R.inv().apply(v - t))

    def table_points(self, plan: dict, params: dict, ranges: dict, repeat_noise=None) -> np.ndarray:
        """P_W (M, 3) mm: the tool point in the table frame; params by name in um / urad."""
        P = np.asarray(plan["tool"], float).copy()
        for L in self.tool[::-1]:  # G_n first
            P = self._maps(L, plan, params, ranges, "tool")[0](P)
        if repeat_noise is not None:
            P = P + repeat_noise
        for L in self.work:  # G_1^-1 first
            P = self._maps(L, plan, params, ranges, "work")[1](P)
        return P


def tracker_rotation(a, b, d) -> np.ndarray:
    """Eq. 22: Rx(a) Ry(b) Rz(d)."""
    ca, sa, cb, sb, cd, sd = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(d), np.sin(d)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rz = np.array([[cd, -sd, 0], [sd, cd, 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


def to_tracker(P_W, pose) -> np.ndarray:
    D, L, H, a, b, d = pose
    return (P_W - np.array([D, L, H])) @ tracker_rotation(a, b, d)  # rows: R^T (P - T)


def spherical_noise(lt, noise_draw) -> np.ndarray:
    """lt shifted by (dr mm, d azimuth rad, d elevation rad) per row, exactly in spherical coordinates."""
    r = np.linalg.norm(lt, axis=1)
    az = np.arctan2(lt[:, 1], lt[:, 0])
    el = np.arcsin(lt[:, 2] / r)
    r, az, el = r + noise_draw[:, 0], az + noise_draw[:, 1], el + noise_draw[:, 2]
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)


# ---------------------------------------------------------------------------------------------- the plan
def make_plan(spec: dict, machine: str) -> dict:
    """Rows: one run per tool offset; in a run the rotary poses in turn (last letter fastest), at each the linear
    grid (x fastest).  ``point`` is the index of the (rotary pose, linear point) pair, shared by the runs."""
    lin = np.array([(x, y, z) for z in spec["z"] for y in spec["y"] for x in spec["x"]], float)
    letters = rotary_letters(machine)
    grids = np.meshgrid(*[np.asarray(spec["angles"][L], float) for L in letters], indexing="ij")
    poses = np.stack([g.ravel() for g in grids], axis=1) if letters else np.zeros((1, 0))
    n_lin, n_rot, tools = len(lin), len(poses), np.asarray(spec["tools"], float)
    per_run = n_lin * n_rot
    M = per_run * len(tools)
    xyz = np.tile(lin, (n_rot * len(tools), 1))
    ang = np.tile(np.repeat(poses, n_lin, axis=0), (len(tools), 1))
    return {"point": np.tile(np.arange(per_run), len(tools)), "run": np.repeat(np.arange(1, len(tools) + 1), per_run),
            "time": np.arange(M) * DT, "xyz": xyz, "angles": {L: ang[:, i] for i, L in enumerate(letters)},
            "tool": np.repeat(tools, per_run, axis=0)}


def plan_ranges(plan: dict) -> dict:
    return {a: (float(plan["xyz"][:, i].min()), float(plan["xyz"][:, i].max())) for i, a in enumerate("xyz")}


def plan_degree(plan: dict) -> dict:
    """Legendre degree per linear axis: min(3, distinct positions - 1), mtbudget's default."""
    return {a: min(3, len(np.unique(plan["xyz"][:, i])) - 1) for i, a in enumerate("xyz")}


# ---------------------------------------------------------------------------------------------- the truth
def draw_rotary(rng, machine, magnitude=ROTARY_MAGNITUDE) -> dict:
    out = {}
    for L in rotary_letters(machine):
        n = rotary_names(L)
        for group, names in (("offset", n["offset"]), ("orientation", n["orientation"]), ("zero", [n["zero"]])):
            lo, hi = magnitude[group]
            for name in names:
                out[name] = float(rng.uniform(lo, hi) * rng.choice([-1.0, 1.0]))
    return out


def draw_linear(rng, degree: dict, scale=LINEAR_SCALE) -> dict:
    out = {}
    for name in linear_error_names(degree):
        n = int(name.split("[P")[1][:-1])
        out[name] = float(rng.normal(0, (scale["d"] * 1e3 if name[0] == "d" else scale["e"] * 1e6) / n))
    for s in ("sxy", "sxz", "syz"):
        out[s] = float(rng.normal(0, scale["squareness"] * 1e6))
    return out


def _fmt(v) -> str:
    return f"{v:.6f}"


def make_recording(folder, kind: str = "CAFXYZ", *, linear_errors: bool = False, null: bool = False, seed: int = 0,
                   **overrides) -> dict:
    """Write recording.toml, points.csv and truth.json of one simulated five-axis verification into ``folder``;
    return the truth (the content of truth.json).

    kind: a preset of PRESETS ("CAFXYZ" table-table, "FXYZCB" head-head) or any chain code with ``pivots`` and
    ``directions`` given.  null: every rotary parameter zero.  linear_errors: Legendre terms and squareness of the
    linear axes (else zero).  Overrides: pivots, directions, tracker_pose (D, L, H mm, a, b, d rad), plan (a spec
    like PRESETS[...]["plan"]), rotary (name -> um / urad, replaces the drawn values it names), linear (name ->
    um / urad), rotary_magnitude, linear_scale, noise (keys of NOISE, internal units), noise_free (bool),
    rotary_dir_columns (bool: dir_a/b/c = +1), sensors (bool: constant 20 degC T_x, T_y, T_z, T_air columns),
    name, description.
    """
    preset = PRESETS.get(kind, {})
    known = {"error_rotation", "pivots", "directions", "tracker_pose", "plan", "rotary", "linear", "rotary_magnitude", "linear_scale",
             "noise", "noise_free", "rotary_dir_columns", "sensors", "name", "description"}
    unknown = set(overrides) - known
    if unknown:
        raise TypeError(f"unknown overrides {sorted(unknown)}")
    pivots = overrides.get("pivots", preset.get("pivots"))
    directions = overrides.get("directions", preset.get("directions"))
    machine = Machine(kind, pivots or {}, directions or {}, overrides.get("error_rotation", "exact"))
    pose = tuple(float(v) for v in overrides.get("tracker_pose", preset.get("tracker_pose")))
    plan_spec = overrides.get("plan", preset.get("plan"))
    plan = make_plan(plan_spec, kind)
    ranges, degree = plan_ranges(plan), plan_degree(plan)
    noise = {**NOISE, **overrides.get("noise", {})}
    rng = np.random.default_rng(seed)

    rot = {} if null else draw_rotary(rng, kind, overrides.get("rotary_magnitude", ROTARY_MAGNITUDE))
    rot = {name: rot.get(name, 0.0) for name in all_rotary_names(kind)}
    for k, v in overrides.get("rotary", {}).items():
        if k not in rot:
            raise KeyError(f"{k} is no rotary parameter of {kind}")
        rot[k] = float(v)
    lin = draw_linear(rng, degree, overrides.get("linear_scale", LINEAR_SCALE)) if linear_errors else {}
    lin.update({k: float(v) for k, v in overrides.get("linear", {}).items()})
    params = {**rot, **lin}

    M = len(plan["point"])
    if overrides.get("noise_free", False):
        repeat, sph = np.zeros((M, 3)), np.zeros((M, 3))
    else:
        repeat = rng.normal(0, noise["repeatability"], (M, 3))
        sph = np.zeros((M, 3))
    P_W = machine.table_points(plan, params, ranges, repeat_noise=repeat)
    lt_true = to_tracker(P_W, pose)
    if not overrides.get("noise_free", False):
        r = np.linalg.norm(lt_true, axis=1)
        sph = np.stack([rng.normal(0, noise["distance"] + noise["distance_per_length"] * r),
                        rng.normal(0, noise["angular"], M), rng.normal(0, noise["angular"], M)], axis=1)
    lt = spherical_noise(lt_true, sph)

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    name = overrides.get("name", folder.name)
    description = overrides.get("description", f"simulated {kind} machine (tests/fiveaxis_generator.py, seed {seed}"
                                f"{', null' if null else ''}{', linear-axis errors' if linear_errors else ''})")
    sensors = bool(overrides.get("sensors", False))
    _write_toml(folder / "recording.toml", name, kind, description, noise, machine, sensors)
    _write_csv(folder / "points.csv", plan, lt, kind, bool(overrides.get("rotary_dir_columns", False)), sensors)

    letters = rotary_letters(kind)
    truth = {
        "generator": "tests/fiveaxis_generator.py (numpy + scipy Rotation; no mtbudget code)",
        "kind": kind, "seed": seed, "null": null, "linear_errors": linear_errors,
        "conventions": {
            "rotary": "G(v) = p + delta + Rot(w) R_u(theta) (v - p), w = e + eps u: the ISO 230-7 parameters are the "
                      "machine-frame components of delta (um) and w (urad); exact rotations",
            "linear": "format 1 (docs/model.md): t = s d + delta, R = exact rotation by eps (the rotation vector); "
                      "squareness in d; s = +1 tool side, -1 workpiece side",
            "linear_terms": "Legendre P1..Pn of the axis position normalised to [-1, 1] over the plan's range "
                            "(ranges_mm); no straightness P1 and no P0 terms (representable under both the ISO 230-1 "
                            "and the free convention); um for d*, urad for e*",
            "chain": "P_M = G_1(...G_n(T)) tool side, P_W = G_m^-1(...G_1^-1(P_M)) workpiece side, G_1 next to F",
            "tracker_pose": "D, L, H in mm and a, b, d in rad of the tracker frame in the table frame; "
                            "lt = R^T (P_W - T), R = Rx(a) Ry(b) Rz(d) (the paper's Eq. 21-22)",
            "noise": "repeatability: isotropic at the tool point (machine frame, before the table's inverse); "
                     "tracker: normal in range, azimuth = atan2(y, x), elevation = asin(z / r) of lt",
            "sensors": "constant 20 degC T_x, T_y, T_z, T_air columns" if sensors else "none",
        },
        "tracker_pose": dict(zip(("D", "L", "H", "a", "b", "d"), pose)),
        "noise": {"angular_urad": noise["angular"] * 1e6, "dist_um": noise["distance"] * 1e3,
                  "dist_ppm": noise["distance_per_length"] * 1e6, "repeat_um": noise["repeatability"] * 1e3},
        "drawn_noise": {"repeat_um": (repeat * 1e3).round(6).tolist(), "range_um": (sph[:, 0] * 1e3).round(6).tolist(),
                        "azimuth_urad": (sph[:, 1] * 1e6).round(6).tolist(),
                        "elevation_urad": (sph[:, 2] * 1e6).round(6).tolist()},
        "rotary": {L: {"pivot_mm": machine.pivots[L].tolist(), "direction": machine.directions[L],
                       "parameters": {n: rot[n] for n in all_rotary_names(L)}} for L in letters},
        "rotary_parameters": rot,
        "rotary_units": "um for EXO*, EYO*, EZO*; urad for EAO*, EBO*, ECO*",
        "squareness_urad": {s: lin.get(s, 0.0) for s in ("sxy", "sxz", "syz")},
        "geometric_errors": {
            "basis": "Legendre P1..Pn of the axis position normalised to [-1, 1] over ranges_mm; um for d*, urad "
                     "for e*; the list index i holds P(i + 1)",
            "ranges_mm": ranges, "degree": degree,
            "coefficients": {f: [lin.get(f"{f}[P{n}]", 0.0) for n in range(1, degree[f[3]] + 1)]
                             for f in (f"{k}{c}({a})" for a in "xyz" for k in "de" for c in "xyz")},
        },
        "parameters": params,
        "parameter_units": "um for d* terms and EXO*/EYO*/EZO*; urad for e* terms, squareness and EAO*/EBO*/ECO*",
        "plan": {"description": _plan_text(plan_spec, kind), "rows": M, "spec": _jsonable(plan_spec)},
    }
    text = json.dumps(truth, indent=1) + "\n"
    (folder / "truth.json").write_text(text)
    return json.loads(text)  # exactly what truth.json holds


def _plan_text(spec, kind) -> str:
    parts = [f"{len(spec['x'])}x{len(spec['y'])}x{len(spec['z'])} linear grid"]
    parts += [f"{L} in [{', '.join(f'{float(v):.4g}' for v in spec['angles'][L])}] deg" for L in rotary_letters(kind)]
    tools = ", ".join("(" + ", ".join(f"{float(v):.4g}" for v in t) + ")" for t in spec["tools"])
    parts.append(f"tools [{tools}] mm (one run each)")
    return " x ".join(parts)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in x]
    return float(x) if isinstance(x, (np.floating, np.integer)) else x


def _write_toml(path, name, machine_code, description, noise, machine: Machine, sensors: bool):
    lines = ['format = "mtbudget-recording/3"', f'name = "{name}"', f'machine = "{machine_code}"',
             f'description = "{description}"', 'reference_temperature = "20 degC"', "",
             "[tracker]", f'angular = "{noise["angular"] * 1e6:g} urad"', f'distance = "{noise["distance"] * 1e3:g} um"',
             f'distance_per_length = "{noise["distance_per_length"] * 1e6:g} um/m"', 'mount = "table"', "",
             "[machine_tool]", f'repeatability = "{noise["repeatability"] * 1e3:g} um"', ""]
    for L in rotary_letters(machine_code):
        p = machine.pivots[L]
        lines += [f"[rotary.{L}]", "pivot = [" + ", ".join(f'"{float(v):.17g} mm"' for v in p) + "]",
                  f'direction = "{machine.directions[L]}"', ""]
    if sensors:
        for col, att in (("T_x", "x axis"), ("T_y", "y axis"), ("T_z", "z axis"), ("T_air", "air")):
            lines += ["[[sensors]]", f'column = "{col}"', f'attached_to = "{att}"', ""]
    Path(path).write_text("\n".join(lines))


def csv_columns(machine_code: str, rotary_dir_columns=False, sensors=False) -> list:
    letters = rotary_letters(machine_code).lower()
    cols = ["point", "run", "time [s]", "x [mm]", "y [mm]", "z [mm]", "dir_x", "dir_y", "dir_z"]
    cols += [f"{L} [deg]" for L in letters]
    if rotary_dir_columns:
        cols += [f"dir_{L}" for L in letters]
    cols += ["tool_x [mm]", "tool_y [mm]", "tool_z [mm]", "lt_x [mm]", "lt_y [mm]", "lt_z [mm]"]
    if sensors:
        cols += ["T_x [degC]", "T_y [degC]", "T_z [degC]", "T_air [degC]"]
    return cols


def _write_csv(path, plan, lt, machine_code, rotary_dir_columns, sensors):
    letters = rotary_letters(machine_code)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(csv_columns(machine_code, rotary_dir_columns, sensors))
        for i in range(len(plan["point"])):
            row = [int(plan["point"][i]), int(plan["run"][i]), f"{plan['time'][i]:.4f}"]
            row += [_fmt(v) for v in plan["xyz"][i]] + [1, 1, 1]
            row += [f"{plan['angles'][L][i]:.9f}" for L in letters]  # 1e-9 deg: below 1e-11 mm per mm of lever
            if rotary_dir_columns:
                row += [1] * len(letters)
            row += [_fmt(v) for v in plan["tool"][i]] + [_fmt(v) for v in lt[i]]
            if sensors:
                row += ["20.000"] * 4
            w.writerow(row)


# ---------------------------------------------------------------------------------------------- other machines
def random_overrides(rng, kind: str) -> dict:
    """Another machine and plan: pivots, magnitudes, angles, grid, tools and tracker drawn at random."""
    if kind == "CAFXYZ":
        pivots = {"A": (0.0, rng.uniform(-60, 60), rng.uniform(-150, -30)),
                  "C": (rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(-20, 20))}
        amax = rng.choice([60.0, 90.0, 110.0])
        nc = int(rng.integers(3, 6))
        angles = {"A": tuple(np.linspace(-amax, amax, rng.integers(3, 6))),
                  "C": tuple(rng.uniform(0, 90) + np.arange(nc) * 360.0 / nc)}
        pose = (rng.uniform(-900, -500), rng.uniform(-300, 300), rng.uniform(0, 300))
    elif kind == "CFXYZB":
        pivots = {"C": (rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(-20, 20)),
                  "B": (rng.uniform(-10, 10), 0.0, rng.uniform(80, 200))}
        bmax = rng.choice([45.0, 60.0, 90.0])
        nc = int(rng.integers(3, 6))
        angles = {"B": tuple(np.linspace(-bmax, bmax, rng.integers(3, 6))),
                  "C": tuple(rng.uniform(0, 90) + np.arange(nc) * 360.0 / nc)}
        pose = (rng.uniform(-900, -500), rng.uniform(-300, 300), rng.uniform(0, 300))
    else:
        pivots = {"C": (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(200, 400)),
                  "B": (rng.uniform(-10, 10), 0.0, rng.uniform(80, 200))}
        bmax = rng.choice([45.0, 60.0, 90.0])
        nc = int(rng.integers(3, 6))
        angles = {"B": tuple(np.linspace(-bmax, bmax, rng.integers(3, 6))),
                  "C": tuple(rng.uniform(0, 90) + np.arange(nc) * 360.0 / nc)}
        pose = (rng.uniform(-1200, -700), rng.uniform(-400, 400), rng.uniform(0, 500))
    grid = {a: tuple(np.linspace(lo, lo + span, rng.integers(3, 5)))
            for a, lo, span in (("x", rng.uniform(-300, 0), rng.uniform(200, 500)),
                                ("y", rng.uniform(-300, 0), rng.uniform(200, 500)),
                                ("z", rng.uniform(0, 200), rng.uniform(100, 300)))}
    tools = [(0.0, 0.0, -rng.uniform(80, 150)), (0.0, 0.0, -rng.uniform(180, 300))]
    if kind in ("FXYZCB", "CFXYZB") or rng.random() < 0.5:
        tools.append((rng.uniform(-60, 60), rng.uniform(-60, 60), -rng.uniform(100, 250)))
    f = rng.uniform(0.3, 3.0)
    return {"pivots": pivots, "plan": {**grid, "angles": angles, "tools": tuple(tools)},
            "tracker_pose": (*pose, rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), rng.uniform(-np.pi, np.pi)),
            "rotary_magnitude": {k: (lo * f, hi * f) for k, (lo, hi) in ROTARY_MAGNITUDE.items()}}



# ---------------------------------------------------------------------------------------------- identifiability
def setup_of(truth: dict):
    """(Machine, plan, ranges, pose) of a recording from its truth.json alone."""
    kind = truth["kind"]
    m = Machine(kind, {L: r["pivot_mm"] for L, r in truth["rotary"].items()},
                {L: r["direction"] for L, r in truth["rotary"].items()})
    plan = make_plan(truth["plan"]["spec"], kind)
    return m, plan, plan_ranges(plan), np.array([truth["tracker_pose"][k] for k in ("D", "L", "H", "a", "b", "d")])


def iso_convention_names(machine: str, degree: dict) -> list:
    """Rotary ISO names, squareness and the linear terms under the ISO 230-1 convention (no straightness P1; P0
    angular terms of the last tool-side linear axis): the parameter set an identification would use."""
    lin = [L.lower() for L in split(machine)[1] if L not in ROTARY]
    out = all_rotary_names(machine) + ["sxy", "sxz", "syz"]
    for a in "xyz":
        for kind in "de":
            for c in "xyz":
                first = 2 if (kind == "d" and c != a) else (0 if (kind == "e" and lin and a == lin[-1]) else 1)
                out += [f"{kind}{c}({a})[P{n}]" for n in range(first, degree[a] + 1)]
    return out


def known_parameter(name: str, machine: str) -> bool:
    """Whether the generator's model has a parameter of this name (ISO rotary, Legendre linear, squareness)."""
    if name in all_rotary_names(machine) or name in ("sxy", "sxz", "syz"):
        return True
    return (len(name) >= 9 and name[0] in "de" and name[1] in "xyz" and name[2] == "(" and name[3] in "xyz"
            and name[4:7] == ")[P" and name[-1] == "]" and name[7:-1].isdigit())


def jacobian(truth: dict, names: list, h: float = 1.0) -> np.ndarray:
    """d lt / d (names in um / urad, then the tracker pose in um and urad), (3 M, n + 6), in um per unit, by
    central differences of the generator's own chain at zero errors (noise-free)."""
    m, plan, ranges, pose0 = setup_of(truth)

    def lt(params, pose):
        return to_tracker(m.table_points(plan, params, ranges), pose).ravel()

    cols = [(lt({n: h}, pose0) - lt({n: -h}, pose0)) / (2 * h) for n in names]
    for j in range(6):
        dp = np.zeros(6)
        dp[j] = 1e-3 if j < 3 else 1e-6
        cols.append((lt({}, pose0 + dp) - lt({}, pose0 - dp)) / 2)
    return np.stack(cols, axis=1) * 1e3


def null_space(truth: dict, names: list, rtol: float = 1e-9, J=None) -> np.ndarray:
    """The machine-parameter part (n, k) of the null directions of the plan (parameters `names` plus the tracker
    pose), from the generator's own Jacobian: singular values below rtol times the largest."""
    J = jacobian(truth, names) if J is None else J
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0  # a parameter that moves nothing: its own null direction
    _, s, Vt = np.linalg.svd(J / scale, full_matrices=False)  # unit columns: the threshold is about geometry
    V = Vt[s < rtol * s[0]].T
    return (V / scale[:, None])[:len(names)]  # back to um / urad coordinates
