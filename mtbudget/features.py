"""Features probed on the verified machine: the machine tool as a measuring instrument (the paper's Fig. 1).

A ``[[features]]`` table of a run configuration names a feature a user probes on the compensated machine (a
distance, a circle's diameter or position, a plane's flatness or orientation) by its probed points, commanded
axis positions inside the verified volume.  In every Monte Carlo trial the compensated machine's error field,
true minus identified (the same state of the machine for every probed point of the feature: the points are
correlated), is evaluated at those points and the measurand's tool, exactly as the per-point measurand is at the
mesh (:meth:`mtbudget.scenario.Scenario.evaluate`) but **without** removing the rigid-body part: a distance, a
diameter and a flatness do not see it, a position or an orientation relative to the machine frame does.  The
in-use sources a feature states (probing error, repeatability, the machine's temperature change since the
verification, the part's temperature and CTE) are drawn on their own streams and added to the probed points.
The feature is then associated (least squares; flatness also minimum zone) from the measured points of a part at
nominal, and its error (measured minus true) is the trial's value.

Docs: docs/features.md.  The engine calls :meth:`FeatureSet.evaluate` and :meth:`FeatureSet.block_values`; the
budget (:func:`feature_budget`) and the reports (:func:`features_json`, :func:`features_text`) read the results.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field

import numpy as np

from .config import SCHEMA, Reader, to_unit
from .errors import ConfigError
from .machine import Configuration, is_rotary, workpiece_rotation
from .model import MeasurementModel
from .outputs import WORKPIECE_FRAME
from .plan import Plan
from .stats import bound, decimals_for, decimals_of, percent
from .units import pretty

#: upper bounds of the in-use uncertainties of [[features]] (internal unit, display unit, display per internal), by
#: the rule of every stated uncertainty (mtbudget.recording.UNCERTAINTIES): several times the poorest in use, below a
#: thousand times the smallest, so a value in the next unit up is refused: a touch probe's P_FTU is 1-20 um; the
#: axes' temperature change since the verification and a part's temperature are known to 0.1-2 K; a metal part's
#: CTE to 0.1-2 um/(m*K), a polymer part's (70-150 um/(m*K): PA, POM, PEEK) to 5-30 um/(m*K), so up to 50: a value in
#: mm/(m*K) (1000 um/(m*K) and more) is still refused
IN_USE_BOUNDS = {"probing_error": (0.1, "um", 1e3), "machine_temperature_change": (10.0, "K", 1.0),
                 "part_temperature_u": (10.0, "K", 1.0), "part_cte_u": (50e-6, "um/(m*K)", 1e6),
                 "rotary_repeatability": (500e-6, "urad", 1e6)}  # a rotary axis repeats within 1-50 urad


#: kinds -> (fewest points, unit of the value, one-sided characteristic (value <= T) or two-sided (|deviation| <= T))
KINDS = {
    "distance": (2, "um", False),
    "diameter": (3, "um", False),
    "position": (3, "um", True),
    "flatness": (4, "um", True),
    "orientation": (3, "urad", True),
}
#: keys of a [[features]] table
FEATURE_KEYS = SCHEMA["features"]
#: the expected range of 25 independent normal deviations (the d2 constant for n = 25): ISO 230-10's probing error
#: P_FTU is the range of the radial deviations of 25 points on a sphere, so u per point = P_FTU / D2_25
D2_25 = 3.931
#: at most this many probed points per feature (each is evaluated in every trial)
MAX_FEATURE_POINTS = 500
#: a point may lie this far outside the verified volume and still count as inside (mm): rounding of the mesh ends
INSIDE_SLACK = 1e-6
#: commanded points of a plane may lie off one plane by this much RMS, those of a circle off one circle by this much
#: (mm): the nominal part is the commanded points themselves (a flatness is that of the measured points, so they must
#: be flat; a diameter or position is relative to the least-squares circle of the commanded points)
PLANE_SLACK = 1e-4
CIRCLE_SLACK = 1e-2
#: the in-use sources, in the order of their budget rows (each drawn on its own stream)
IN_USE = ("probing", "repeatability_in_use", "machine_thermal_drift", "part_temperature", "part_cte",
          "rotary_repeatability_in_use")
IN_USE_TEXT = {
    "probing": "probing error at each point along its probing direction, normal, u = P_FTU / 3.931 (ISO 230-10)",
    "repeatability_in_use": "the machine's positioning repeatability at each probed point, normal per axis, "
                            "u = [machine_tool] repeatability",
    "machine_thermal_drift": "the machine's axis temperatures changed since the verification: each scale expands by "
                             "CTE x dT_a about its fixed point (the axis zero without [scales]), dT_a normal per axis "
                             "and trial, the same for every point of the feature",
    "part_temperature": "the part's temperature reading: its error dT (normal) expands the part by part_cte x dT "
                        "about the feature's centre",
    "part_cte": "the part's CTE: its error (normal) times (part_temperature - 20 degC) expands the part about the "
                "feature's centre",
    "rotary_repeatability_in_use": "five axes: each rotary axis' positioning repeatability, normal, one draw per axis "
                                   "and positioning (the points probed in a row at one commanded angle of the axis "
                                   "share it: the axis is held while the linear axes probe), u = the feature's "
                                   "rotary_repeatability, else the run's [sources.rotary_repeatability] R; the tool "
                                   "point moves as the chain turns it",
}
#: the same with ``reposition = true``: every point its own positioning of every rotary axis
ROTARY_REPOSITION_TEXT = ("five axes: each rotary axis' positioning repeatability at each probed point, normal per axis "
                          "and point (reposition = true: every axis re-positioned before every point), u = the "
                          "feature's rotary_repeatability, else the run's [sources.rotary_repeatability] R; the tool "
                          "point moves as the chain turns it")
#: what a five-axis feature's measurand adds when the rotary axes' in-use repeatability is in its budget
ROTARY_HELD = ("; the rotary axes' repeatability drawn once per positioning: each axis is held while consecutive "
               "points share its commanded angle (one turn of it for those points)")
ROTARY_REPOSITIONED = "; every rotary axis re-positioned before every point (reposition = true: its repeatability " \
                      "drawn at each point)"

MEASURANDS = {
    "distance": "error of the distance between the two probed points (measured minus true, a part at nominal), um; "
                "a distance does not see a rigid motion of the machine",
    "diameter": "error of the least-squares circle's diameter through the probed points (measured minus true), um; "
                "invariant to a rigid motion",
    "position": "positional deviation the machine reports for a circle at nominal: twice the distance between the "
                "least-squares centre of the measured points and the true centre (ISO 1101 position zone diameter), "
                "um, relative to the {frame} (the rigid part is kept)",
    "flatness": "flatness the machine reports for a perfectly flat plane: the range of the measured points' "
                "distances from the associated plane ({association}), um; invariant to a rigid motion",
    "orientation": "angle between the least-squares plane of the measured points and the true plane (a part at "
                   "nominal), urad, relative to the {frame} (the rigid part is kept)",
}
#: five-axis machines: what every feature's measurand adds (the frame its points and value are in)
ROTARY_MEASURAND = ("; each point probed at its commanded rotary angles ({angles}), the points and the feature in the "
                    "{frame}")
#: the frame of a five-axis machine whose table turns: the one the per-point measurand is stated in (outputs.py)
FEATURE_TABLE_FRAME = ("workpiece (table) frame (x, y, z: the machine's X, Y, Z with every rotary axis at zero, "
                       "turning with the table)")
#: what a feature's JSON ``points`` are, and (five axes) its ``nominal_points``
COMMANDED_POINTS = ("commanded machine positions of the linear axes (X, Y, Z) at each probed point, in the order of "
                    "probing (five axes: with the commanded angles of the rotary axes, points.angles)")
NOMINAL_POINTS = ("the nominal probed points that define the part: where an error-free machine puts the tool at each "
                  "commanded pose, in the frame stated (the chain at zero errors)")
#: an angle may lie this far outside the angles the verification visited and still count as inside (rad)
ANGLE_SLACK = 1e-9
#: a commanded angle more than this many turns from zero is refused as such (a typing error, not a pose)
MAX_TURNS = 100


@dataclass
class FeatureSpec:
    """One [[features]] table, in internal units (mm, rad, K, 1/K)."""

    name: str
    kind: str
    points: np.ndarray  # (N, 3) commanded axis positions, mm
    directions: np.ndarray  # (N, 3) unit probing directions
    tolerance: float | None  # um (urad for orientation)
    association: str = "least squares"
    probing_error: float = 0.0  # mm, ISO 230-10 P_FTU
    repeatability: bool = False
    machine_temperature_change: float = 0.0  # K, standard uncertainty
    part_temperature: float | None = None  # K, the reading
    part_temperature_u: float = 0.0  # K
    part_cte: float = 11.5e-6  # 1/K
    part_cte_u: float = 0.0  # 1/K
    centre: np.ndarray = field(default=None)  # (3,) mm: the nominal centre the part expands about
    datum: np.ndarray | None = None  # (3,) the plane's true normal (orientation, flatness)
    #: five-axis machines: {letter: (N,) commanded angle of each rotary axis at each point, rad}; empty on three axes
    angles: dict = field(default_factory=dict)
    #: (N, 3) mm the nominal probed points where the part is: the commanded points on a three-axis machine, the nominal
    #: tool points in the workpiece (table) frame on a five-axis one (the chain at zero errors, the measurand's tool)
    geometry: np.ndarray | None = None
    table_frame: bool = False  # a rotary axis carries the workpiece: the feature is in the workpiece (table) frame
    #: five axes: u of each rotary axis' angle at each probed point (rad); stated, or the run's rotary_repeatability
    #: source's R when ``repeatability`` is true (FeatureSet.of resolves it); None: not stated
    rotary_repeatability: float | None = None
    #: five axes: every rotary axis re-positioned before every point (its repeatability drawn per point); false: one
    #: positioning per run of consecutive points at the same commanded angle of that axis (held while they are probed)
    reposition: bool = False

    @property
    def unit(self) -> str:
        return KINDS[self.kind][1]

    @property
    def one_sided(self) -> bool:
        return KINDS[self.kind][2]

    def measurand(self) -> str:
        text = MEASURANDS[self.kind].format(association=self.association,
                                            frame="workpiece (table) frame" if self.table_frame else "machine frame")
        if self.angles:
            text += ROTARY_MEASURAND.format(angles=", ".join(sorted(a.upper() for a in self.angles)),
                                            frame=FEATURE_TABLE_FRAME if self.table_frame else "machine frame")
            if "rotary_repeatability_in_use" in self.in_use():
                text += ROTARY_REPOSITIONED if self.reposition else ROTARY_HELD
        return text

    def in_use_text(self, source: str) -> str:
        """The budget row's description of the in-use source ``source`` for this feature."""
        if source == "rotary_repeatability_in_use" and self.reposition:
            return ROTARY_REPOSITION_TEXT
        return IN_USE_TEXT[source]

    def positionings(self) -> dict:
        """{letter: (N,) int} five axes: the index of the point at which each point's positioning of each rotary axis
        was made: a new positioning where the commanded angle changes from the previous point (or at every point with
        ``reposition``), the axis held over the run of points at one angle; the first point is one."""
        out = {}
        for a, th in self.angles.items():
            idx = np.arange(len(th))
            for j in range(1, len(th)):
                if not self.reposition and abs(th[j] - th[j - 1]) <= ANGLE_SLACK:
                    idx[j] = idx[j - 1]
            out[a] = idx
        return out

    def in_use(self) -> list:
        """The in-use sources this feature states, in budget order."""
        on = {"probing": self.probing_error > 0, "repeatability_in_use": self.repeatability,
              "machine_thermal_drift": self.machine_temperature_change > 0,
              "part_temperature": self.part_temperature_u > 0 and self.kind in ("distance", "diameter"),
              "part_cte": self.part_cte_u > 0 and self.part_temperature is not None
              and self.kind in ("distance", "diameter"),
              "rotary_repeatability_in_use": bool(self.angles) and (self.rotary_repeatability or 0.0) > 0}
        return [s for s in IN_USE if on[s]]

    def describe(self) -> dict:
        """JSON-able description (the run's spec holds it)."""
        return {"name": self.name, "kind": self.kind, "unit": self.unit, "measurand": self.measurand(),
                "points": self.points.tolist(), "points_unit": "mm", "directions": self.directions.tolist(),
                "tolerance": self.tolerance, "one_sided": self.one_sided, "association": self.association,
                "in_use": self.in_use(),
                **({"angles": {a.upper(): np.degrees(v).tolist() for a, v in sorted(self.angles.items())},
                    "angles_unit": "deg", "frame": WORKPIECE_FRAME if self.table_frame else "machine frame",
                    "nominal_points": self.geometry.tolist()}
                   if self.angles else {})}


# ------------------------------------------------------------------ parsing
def parse_features(config, nominal=None) -> list:
    """The [[features]] of a configuration as :class:`FeatureSpec` s, checked; errors name file and key.

    ``nominal(points, angles)``: (N, 3) the nominal tool points in the workpiece frame of commanded points (N, 3) mm
    at commanded angles {letter: (N,) rad} (the chain at zero errors): a five-axis feature's geometry is checked and
    derived there, where the part is; unused on a three-axis machine (the commanded points are the part's)."""
    data = config.source.get("features", []) if isinstance(config.source, dict) else []
    if not data:
        return []
    if not isinstance(data, list) or not all(isinstance(x, dict) for x in data):
        raise ConfigError(f"{config.where('features')}: expected [[features]] tables")
    out, names = [], set()
    for i, raw in enumerate(data):
        f = _parse_one(Reader(raw, config.path, f"features[{i}]."), config, nominal)
        if f.name in names:
            raise ConfigError(f"{config.where(f'features[{i}].name')}: feature {f.name!r} is named twice")
        names.add(f.name)
        out.append(f)
    return out


def _parse_one(r: Reader, config, nominal=None) -> FeatureSpec:
    r.check_keys(FEATURE_KEYS, "[[features]]")
    name = r.raw("name")
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"{r.where('name')}: expected a name (a string)")
    kind = r.raw("kind")
    if kind not in KINDS:
        raise ConfigError(f"{r.where('kind')}: unknown kind {kind!r:.40}; expected one of {', '.join(KINDS)}")
    least, unit, _ = KINDS[kind]
    pts_raw = r.raw("points")
    if not isinstance(pts_raw, list) or not all(isinstance(p, list) and len(p) == 3 for p in pts_raw):
        raise ConfigError(f"{r.where('points')}: expected a list of commanded positions [x, y, z], e.g. "
                          "[[\"800 mm\", \"100 mm\", \"200 mm\"], [\"1200 mm\", \"100 mm\", \"200 mm\"]]")
    n = len(pts_raw)
    if n < least or (kind == "distance" and n != 2) or n > MAX_FEATURE_POINTS:
        want = "exactly 2" if kind == "distance" else f"at least {least}" + ("" if n <= MAX_FEATURE_POINTS else
                                                                              f" and at most {MAX_FEATURE_POINTS}")
        raise ConfigError(f"{r.where('points')}: a {kind} needs {want} probed points, got {n}")
    P = np.array([[to_unit(v, "mm", f"{r.where('points')}[{j}]") for v in p] for j, p in enumerate(pts_raw)])
    lo = np.array([config.mesh_ranges[a][0] for a in "xyz"]) - INSIDE_SLACK
    hi = np.array([config.mesh_ranges[a][1] for a in "xyz"]) + INSIDE_SLACK
    for j, p in enumerate(P):
        if not (np.all(p >= lo) and np.all(p <= hi)):
            raise ConfigError(f"{r.where('points')}[{j}]: ({', '.join(f'{v:g}' for v in p)}) mm lies outside the "
                              f"verified volume {_volume(config)}; extrapolating the identified errors is not covered")
    angles = _angles(r, config, n)
    # where the part is: the commanded points (three axes), the nominal tool points in the workpiece frame (five axes)
    G = P if not angles else np.asarray(nominal(P, angles), float)
    P_cmd, P = P, G
    # what the checks below are on: the commanded points (three axes), the nominal points where the part is (five)
    frame = "workpiece (table) frame" if angles and _table_turns(config) else "machine frame"
    on = "the points" if not angles else f"the nominal points in the {frame} (the tool at the commanded poses)"
    centre, datum = P.mean(axis=0), None
    if kind == "distance":
        if np.linalg.norm(P[1] - P[0]) < 1e-3:
            raise ConfigError(f"{r.where('points')}: the two points coincide; a distance needs two distinct points"
                              if not angles else
                              f"{r.where('points')}: {on} coincide, at ({', '.join(f'{v:.4g}' for v in P[0])}) mm; "
                              "a distance needs two distinct points on the part")
    else:
        Q = P - centre
        s = np.linalg.svd(Q, compute_uv=False)
        if s[1] <= 1e-6 * max(s[0], 1e-12):
            raise ConfigError(f"{r.where('points')}: {on} are collinear; a {kind} needs points spanning a "
                              + ("plane" if kind in ("flatness", "orientation") else "circle"))
        datum = np.linalg.svd(Q)[2][2]
        state = ("state the commanded points of the nominal {}" if not angles else
                 f"state commanded poses whose nominal points in the {frame} lie on the nominal {{}}")

        def of(thing):
            return f"the points of {thing}" if not angles else \
                f"the nominal points of {thing} in the {frame} (the tool at the commanded poses)"

        if kind in ("diameter", "position"):
            if s[2] / np.sqrt(n) > PLANE_SLACK:
                raise ConfigError(f"{r.where('points')}: {of('a circle')} must lie in one plane (off it by "
                                  f"{s[2] / np.sqrt(n):.3g} mm RMS)")
            centre, radius = _circle_nominal(P, datum)
            resid = np.abs(np.linalg.norm(P - centre, axis=1) - radius)
            if resid.max() > CIRCLE_SLACK:
                raise ConfigError(f"{r.where('points')}: {on} do not lie on one circle (off by up to "
                                  f"{resid.max():.3g} mm): " + state.format("circle"))
        elif s[2] / np.sqrt(n) > PLANE_SLACK:
            raise ConfigError(f"{r.where('points')}: {of('a plane')} must lie in one plane (off it by "
                              f"{s[2] / np.sqrt(n):.3g} mm RMS): " + state.format("plane"))
    if r.has("datum"):
        d = r.raw("datum")
        if kind not in ("orientation", "flatness") or not (isinstance(d, list) and len(d) == 3):
            raise ConfigError(f"{r.where('datum')}: only a plane (orientation, flatness) takes a datum, its nominal "
                              "normal as three plain numbers")
        datum = _unit_vector(d, r.where("datum"))
        normal = np.linalg.svd(P - P.mean(0))[2][2]
        if abs(abs(datum @ normal) - 1) > 1e-6:
            if not angles:
                raise ConfigError(f"{r.where('datum')}: is not the normal of the plane of the commanded points")
            normal = normal if normal[np.argmax(np.abs(normal))] > 0 else -normal
            raise ConfigError(f"{r.where('datum')}: is not the normal of the plane of {on}, which is "
                              f"[{', '.join(_num(v) for v in normal)}] (or its opposite): a datum is stated in the "
                              f"{frame}, where the part is")
    dirs = _directions(r, kind, P, centre, datum)
    tol = None
    if r.has("tolerance"):
        tol = to_unit(r.raw("tolerance"), unit, r.where("tolerance"))
        if not tol > 0:
            raise ConfigError(f"{r.where('tolerance')}: a tolerance must be positive")
        if tol > 1e9:
            raise ConfigError(f"{r.where('tolerance')}: implausibly large")
    assoc = r.raw("association", "least squares")
    if assoc not in ("least squares", "minimum zone") or (assoc == "minimum zone" and kind != "flatness"):
        raise ConfigError(f"{r.where('association')}: expected \"least squares\"" +
                          (" or \"minimum zone\"" if kind == "flatness" else " (minimum zone: flatness only)"))
    rep = r.raw("repeatability", False)
    if not isinstance(rep, bool):
        raise ConfigError(f"{r.where('repeatability')}: expected true or false (true: the machine's repeatability, "
                          "[machine_tool] repeatability, at each probed point)")

    def nonneg(key, unit, default):
        v = r.quantity(key, unit, default)
        if v < 0 or not np.isfinite(v):
            raise ConfigError(f"{r.where(key)}: must not be negative")
        high, shown, factor = IN_USE_BOUNDS[key]
        if v > high:  # the rule of every stated uncertainty (mtbudget.recording.UNCERTAINTIES)
            raise ConfigError(f"{r.where(key)}: {v * factor:g} {shown} is not plausible; expected 0 to "
                              f"{high * factor:g} {shown}")
        return v

    part_keys = [k for k in ("part_temperature", "part_temperature_u", "part_cte", "part_cte_u") if r.has(k)]
    if part_keys and kind not in ("distance", "diameter"):
        raise ConfigError(f"{r.where(part_keys[0])}: {'an' if kind[0] in 'aeiou' else 'a'} {kind} does not see the part's uniform expansion; only a "
                          "distance or a diameter takes the part's temperature and CTE")
    if r.has("part_cte_u") and not r.has("part_temperature"):
        raise ConfigError(f"{r.where('part_cte_u')}: the CTE's uncertainty acts through the part's temperature "
                          "difference from 20 degC: state part_temperature too")

    part_t = None if not r.has("part_temperature") else r.quantity("part_temperature", "K", absolute_temperature=True)
    rot = None
    if r.has("rotary_repeatability"):
        if not angles:
            raise ConfigError(f"{r.where('rotary_repeatability')}: machine {config.machine!r} has no rotary axis; "
                              "only a five-axis feature takes the rotary axes' repeatability")
        rot = nonneg("rotary_repeatability", "rad", None)
    repos = r.raw("reposition", False)
    if r.has("reposition"):
        if not angles:
            raise ConfigError(f"{r.where('reposition')}: machine {config.machine!r} has no rotary axis; only a "
                              "five-axis feature re-positions its rotary axes")
        if not isinstance(repos, bool):
            raise ConfigError(f"{r.where('reposition')}: expected true or false (true: every rotary axis re-positioned "
                              "before every probed point; false: held over consecutive points at one angle)")
    return FeatureSpec(name.strip(), kind, P_cmd, dirs, tol, assoc, probing_error=nonneg("probing_error", "mm", "0 um"),
                       repeatability=rep, machine_temperature_change=nonneg("machine_temperature_change", "K", "0 K"),
                       part_temperature=part_t, part_temperature_u=nonneg("part_temperature_u", "K", "0 K"),
                       part_cte=r.quantity("part_cte", "1/K", "11.5 um/(m*K)"),
                       part_cte_u=nonneg("part_cte_u", "1/K", "0 um/(m*K)"), centre=centre, datum=datum,
                       angles=angles, geometry=P, table_frame=bool(angles) and _table_turns(config),
                       rotary_repeatability=rot, reposition=repos)


def _table_turns(config) -> bool:
    """Whether a rotary axis carries the workpiece (the table turns: the workpiece frame is not the machine frame;
    machine.workpiece_rotation's rule)."""
    return any(is_rotary(a) for a in Configuration.parse(config.machine, config.rotary or None).workpiece)


def _angles(r: Reader, config, n: int) -> dict:
    """A feature's ``angles``: {letter: (n,) rad}, the commanded angle of every rotary axis of the machine at each
    probed point (a list in the order of the points, as a recording's angle columns; one quantity for every point),
    inside the angles the verification visited (modulo a turn); empty on a three-axis machine, which takes none."""
    letters = sorted(getattr(config, "rotary", None) or {})
    if not letters:
        if r.has("angles"):
            raise ConfigError(f"{r.where('angles')}: machine {config.machine!r} has no rotary axis; a feature's points "
                              "take no angles (state angles on a five-axis machine only)")
        return {}
    names = ", ".join(a.upper() for a in letters)
    example = "angles = {" + ", ".join(f'{a.upper()} = ["0 deg", "90 deg", ...]' for a in letters) + "}"
    if not r.has("angles"):
        raise ConfigError(f"{r.where('angles')}: missing: machine {config.machine!r} has rotary axes {names}; state "
                          f"the commanded angle of each at every probed point, e.g. {example} (one per point, in the "
                          "order of points, or one angle for every point)")
    raw = r.raw("angles")
    if not isinstance(raw, dict):
        raise ConfigError(f"{r.where('angles')}: expected a table of the rotary axes' angles, e.g. {example}")
    given = {}
    for k, v in raw.items():
        if str(k).lower() not in letters:
            raise ConfigError(f"{r.where('angles')}.{k}: machine {config.machine!r} has no rotary axis {k} (its rotary "
                              f"axes: {names})")
        if str(k).lower() in given:  # A and a are one axis: which angle is meant cannot be guessed
            raise ConfigError(f"{r.where('angles')}.{k}: rotary axis {str(k).upper()} is stated twice (as "
                              f"{given[str(k).lower()][0]} and {k}); state each axis' angles once")
        given[str(k).lower()] = (k, v)
    out = {}
    for a in letters:
        if a not in given:
            raise ConfigError(f"{r.where('angles')}.{a.upper()}: missing: machine {config.machine!r} has a rotary axis "
                              f"{a.upper()}; state its commanded angle at every probed point (or one for all)")
        key, v = given[a]
        where = f"{r.where('angles')}.{key}"
        if isinstance(v, list):
            if len(v) != n:
                raise ConfigError(f"{where}: {len(v)} angles for {n} probed points; state one per point, in the order "
                                  "of points (or one angle for every point)")
            th = np.array([to_unit(x, "rad", f"{where}[{j}]") for j, x in enumerate(v)])
        else:
            th = np.full(n, to_unit(v, "rad", where))
        visited = np.asarray(config.rotary_angles[a], float)
        lo, hi = float(visited.min()), float(visited.max())
        for j, t in enumerate(th):
            at = f"{where}[{j}]" if isinstance(v, list) else where
            if not abs(t) <= MAX_TURNS * 2 * np.pi:  # also NaN: a commanded angle, not a count of turns
                raise ConfigError(f"{at}: {np.degrees(t):g} deg is more than {MAX_TURNS} turns from zero; state the "
                                  f"commanded angle (within +-{MAX_TURNS * 360} deg), e.g. the visited "
                                  f"[{np.degrees(lo):g}, {np.degrees(hi):g}] deg")
            turns = np.ceil((lo - t) / (2 * np.pi) - ANGLE_SLACK)  # the turn that brings t to lo or just above
            if not t + 2 * np.pi * turns <= hi + ANGLE_SLACK:
                raise ConfigError(f"{at}: {np.degrees(t):g} deg lies outside the angles the verification visited, "
                                  f"[{np.degrees(lo):g}, {np.degrees(hi):g}] deg (modulo a turn); extrapolating the "
                                  "identified errors is not covered")
        out[a] = th
    return out


def _volume(config) -> str:
    return "x " + ", y ".join(f"[{config.mesh_ranges[a][0]:g}, {config.mesh_ranges[a][1]:g}]" for a in "xy") + \
        f", z [{config.mesh_ranges['z'][0]:g}, {config.mesh_ranges['z'][1]:g}] mm"


def _unit_vector(v, where) -> np.ndarray:
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise ConfigError(f"{where}: expected three plain numbers (a direction)")
    a = np.asarray(v, float)
    n = np.linalg.norm(a)
    if not n > 0 or not np.isfinite(n):
        raise ConfigError(f"{where}: a direction must not be zero")
    return a / n


def _directions(r: Reader, kind, P, centre, datum) -> np.ndarray:
    """The probing direction of every point: stated, else along the line (distance), radial (circle), the normal
    (plane).  Only the probing error uses them."""
    if r.has("directions"):
        d = r.raw("directions")
        if not isinstance(d, list) or len(d) != len(P) or not all(isinstance(x, list) and len(x) == 3 for x in d):
            raise ConfigError(f"{r.where('directions')}: expected one direction [dx, dy, dz] (plain numbers) per point, "
                              f"{len(P)} of them")
        return np.array([_unit_vector(x, f"{r.where('directions')}[{j}]") for j, x in enumerate(d)])
    if kind == "distance":
        u = (P[1] - P[0]) / np.linalg.norm(P[1] - P[0])
        return np.array([-u, u])
    if kind in ("diameter", "position"):
        return (P - centre) / np.linalg.norm(P - centre, axis=1, keepdims=True)
    return np.tile(datum, (len(P), 1))


def _circle_nominal(P, normal):
    """Centre and radius of the circle through the coplanar points P (least squares in their plane)."""
    c0 = P.mean(axis=0)
    u = np.linalg.svd(P - c0)[2]
    xy = (P - c0) @ u[:2].T
    A = np.column_stack([2 * xy, np.ones(len(P))])
    sol = np.linalg.lstsq(A, (xy**2).sum(1), rcond=None)[0]
    centre = c0 + sol[:2] @ u[:2]
    return centre, float(np.sqrt(sol[2] + sol[:2] @ sol[:2]))


# ------------------------------------------------------------------ association, vectorised over trials
def circle_fit(Q: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Least-squares circle of points Q (n, N, 3) projected on the plane spanned by u, v (the nominal circle's plane,
    through the origin of Q): centre (n, 2) in (u, v) and radius (n,), the algebraic (Kasa) fit refined by
    Gauss-Newton steps of the geometric fit."""
    x, y = Q @ u, Q @ v
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=-1)
    b = x * x + y * y
    sol = np.linalg.solve(np.einsum("nik,nil->nkl", A, A), np.einsum("nik,ni->nk", A, b)[..., None])[..., 0]
    a, c = sol[:, 0], sol[:, 1]
    R = np.sqrt(sol[:, 2] + a * a + c * c)
    for _ in range(3):  # geometric least squares: residual |q - c| - R
        dx, dy = x - a[:, None], y - c[:, None]
        d = np.sqrt(dx * dx + dy * dy)
        J = np.stack([-dx / d, -dy / d, -np.ones_like(d)], axis=-1)
        res = d - R[:, None]
        step = np.linalg.solve(np.einsum("nik,nil->nkl", J, J), np.einsum("nik,ni->nk", J, res)[..., None])[..., 0]
        a, c, R = a - step[:, 0], c - step[:, 1], R - step[:, 2]
    return np.stack([a, c], axis=-1), R


def plane_fit(Q: np.ndarray):
    """Least-squares plane of points Q (n, N, 3): centroid (n, 3) and unit normal (n, 3) (smallest singular vector)."""
    c = Q.mean(axis=1)
    _, _, vt = np.linalg.svd(Q - c[:, None], full_matrices=False)
    return c, vt[:, 2]


#: up to this many points a minimum zone is found by enumerating its candidate planes (vectorised over trials,
#: exact); above, by one linear programme per trial (scipy.optimize.linprog, about 8 ms each)
MZ_ENUMERATE_POINTS = 12


def minimum_zone_flatness(Q: np.ndarray, normal: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Minimum-zone flatness of the points Q (n, N, 3) (the Chebyshev plane) in the nominal plane's frame: the smallest
    t such that |h_i - (a s_i + b t_i + c)| <= t / 2, h the height along the nominal normal and (s, t) the in-plane
    coordinates (exact for the zone measured along that normal; the true minimum zone differs by the second order
    of the plane's tilt, < 1e-9 of the zone for the micrometre tilts here).

    A linear programme in (a, b, c, t / 2): its optimum is a vertex where four constraints are active, four points
    at +-t/2 from the plane.  Up to :data:`MZ_ENUMERATE_POINTS` points every such vertex is solved (each 4 points
    and sign pattern: a 4 x 4 system) and the narrowest zone of the candidate planes is taken, which is the
    optimum; with more points, one linprog (HiGHS) per trial."""
    s, t, h = Q @ u, Q @ v, Q @ normal
    if Q.shape[1] <= MZ_ENUMERATE_POINTS:
        return _mz_enumerate(s, t, h)
    from scipy.optimize import linprog

    out = np.empty(len(Q))
    N = Q.shape[1]
    for k in range(len(Q)):
        # variables a, b, c, w (w = t/2); rows:  h - a s - b t - c <= w  and  -(h - a s - b t - c) <= w
        A = np.vstack([np.column_stack([-s[k], -t[k], -np.ones(N), -np.ones(N)]),
                       np.column_stack([s[k], t[k], np.ones(N), -np.ones(N)])])
        bnd = np.concatenate([-h[k], h[k]])
        res = linprog([0, 0, 0, 1], A_ub=A, b_ub=bnd, bounds=[(None, None)] * 3 + [(0, None)], method="highs")
        out[k] = 2 * res.x[3] if res.success else np.nan
    return out


def _mz_enumerate(s: np.ndarray, t: np.ndarray, h: np.ndarray, chunk: int = 256) -> np.ndarray:
    """The minimum zone over every vertex of the linear programme (see :func:`minimum_zone_flatness`), (n,).

    At a vertex four points lie at +-t/2: three on one side (their plane gives the tilt) or two on each (the plane is
    parallel to both their edges).  Either way the tilt (a, b) makes two edges of the point set level:
    a ds + b dt = dh for both, a 2 x 2 system solved in closed form for every pair of edges; the narrowest zone of
    those tilts is the optimum (each candidate's zone is feasible, the optimum is among them)."""
    import itertools

    n, N = h.shape
    edges = np.array(list(itertools.combinations(range(N), 2)))  # (E, 2)
    pairs = np.array(list(itertools.combinations(range(len(edges)), 2)))  # (C, 2)
    e1, e2 = edges[pairs[:, 0]], edges[pairs[:, 1]]
    L = max(float(np.abs(s).max()), float(np.abs(t).max()), 1e-12)
    s, t = s / L, t / L  # a, b scaled alike: the width does not change
    out = np.empty(n)
    for i0 in range(0, n, chunk):
        S, T, H = s[i0:i0 + chunk], t[i0:i0 + chunk], h[i0:i0 + chunk]
        ds1, dt1, dh1 = (X[:, e1[:, 1]] - X[:, e1[:, 0]] for X in (S, T, H))
        ds2, dt2, dh2 = (X[:, e2[:, 1]] - X[:, e2[:, 0]] for X in (S, T, H))
        det = ds1 * dt2 - ds2 * dt1
        ok = np.abs(det) > 1e-9
        det = np.where(ok, det, 1.0)
        a = (dh1 * dt2 - dh2 * dt1) / det
        b = (ds1 * dh2 - ds2 * dh1) / det
        r = H[:, None, :] - a[..., None] * S[:, None, :] - b[..., None] * T[:, None, :]  # (m, C, N)
        width = r.max(axis=-1) - r.min(axis=-1)
        width[~ok] = np.inf
        out[i0:i0 + chunk] = width.min(axis=1)
    return out


# ------------------------------------------------------------------ per trial
class FeatureSet:
    """The features of a scenario: their points at the measurand's tool, evaluated per trial."""

    def __init__(self, scenario, specs: list):
        self.scenario = scenario
        self.specs = specs
        self.slices, k = [], 0
        for f in specs:
            self.slices.append(slice(k, k + len(f.points)))
            k += len(f.points)
        self.points = np.concatenate([f.points for f in specs])  # (Nf, 3) commanded
        self.geometry = np.concatenate([f.geometry for f in specs])  # (Nf, 3) the part's nominal points
        self.angles = {a: np.concatenate([f.angles[a] for f in specs]) for a in specs[0].angles}  # five axes: rad
        # five axes: {letter: (Nf,) int} the point (index into all features' points) whose positioning of the axis
        # each point is probed at: one draw of the axis' repeatability per positioning (FeatureSpec.positionings)
        self.held = {a: np.concatenate([sl.start + f.positionings()[a] for f, sl in zip(specs, self.slices)])
                     for a in self.angles}
        self.n_columns = 2 + len(IN_USE)  # total, verification alone, each in-use source alone
        self.plan = _probe_plan(scenario, self.points, self.angles)
        # five axes, a turning table: (Nf, 3, 3) the table's nominal orientation at each point's pose (v_machine =
        # R v_workpiece), which turns what acts along the machine's axes into the workpiece frame; None otherwise
        self.to_machine = workpiece_rotation(scenario.truth.config, self.angles) if self.angles else None
        # five axes: {letter: (Nf, 3) mm/rad} how the nominal tool point moves in the workpiece frame when the axis
        # turns (the chain at zero errors, central differences of an angle offset)
        self.turn = _turn_rates(scenario, self.points, self.angles) if self.angles else {}
        self._models: dict = {}
        cfg = scenario.config
        self.rep = float(scenario.drawn.get("machine_tool.repeatability", cfg.repeatability))
        self.cte = np.array([float(sc.cte) if a in (cfg.scales or {}) and (sc := cfg.scales[a]) is not None
                             else float(scenario.drawn.get("machine_tool.cte", cfg.cte)) for a in "xyz"])
        self.x0 = np.array([float(cfg.scales[a].fixed_point) if a in (cfg.scales or {}) else 0.0 for a in "xyz"])
        # the nominal tool points: where the tool of an error-free machine is at the commanded points (the part)
        self.tool_points = self.evaluate(scenario.truth, np.zeros((1, scenario.truth.n_params)))[0]
        self.warnings = _warnings(scenario)

    @classmethod
    def of(cls, scenario):
        """The scenario's feature set (built once), or None without [[features]]."""
        def make():
            specs = parse_features(scenario.config, lambda P, angles: _nominal_points(scenario, P, angles))
            if not specs:
                return None
            if scenario.null_bias is not None or scenario.context.measurand is not None:
                raise ConfigError(f"{scenario.config.where('features')}: at a [measurand] tool the verification cannot "
                                  "fully identify, the features are not evaluated yet (what it leaves unidentified is "
                                  "drawn at the mesh only); probe at the verification's tool")
            for i, f in enumerate(specs):  # five axes: the machine's repeatability includes its rotary axes'
                if f.angles and f.repeatability and f.rotary_repeatability is None:
                    src = next((s for s in scenario.sources if s.name == "rotary_repeatability"), None)
                    if src is None:
                        raise ConfigError(
                            f"{scenario.config.where(f'features[{i}].repeatability')}: on a five-axis machine the "
                            "repeatability at a probed point includes the rotary axes', the R of source "
                            "rotary_repeatability, which this run does not select; state the feature's "
                            "rotary_repeatability (e.g. \"10 urad\"; \"0 urad\" leaves it out)")
                    f.rotary_repeatability = src.value("R", "rad")
            return cls(scenario, specs)

        return scenario.cached("features", make)

    def evaluate(self, model: MeasurementModel, theta: np.ndarray) -> np.ndarray:
        """(n, Nf, 3) mm: the tool points of ``model`` with ``theta`` at the features' commanded points and the
        measurand's tool (the error functions over the verification's ranges)."""
        key = id(model)
        if key not in self._models:  # the model kept beside its copy so that its id is not reused
            self._models[key] = (model, MeasurementModel(model.config, model.errors, self.plan))
        return self._models[key][1].machine_points(theta)

    def block_values(self, e: np.ndarray, seed: int, block: int) -> np.ndarray:
        """(n, K, 2 + len(IN_USE)) the features' errors in a block: total, the verification's state alone, each
        in-use source alone (zero where a feature does not state it).  ``e`` (n, Nf, 3) mm is the compensated
        machine's error at the features' points, true minus identified, rigid part kept."""
        n = len(e)
        out = np.zeros((n, len(self.specs), self.n_columns))
        draws = {s: self._draw(s, n, seed, block) for s in IN_USE}
        for k, (f, sl) in enumerate(zip(self.specs, self.slices)):
            S = self.tool_points[sl]
            d_ver = -e[:, sl]  # the controller reports S - e where the tool touches S (docs/features.md)
            parts = {s: draws[s](f, sl, S) for s in f.in_use()}
            total = d_ver + sum(parts.values()) if parts else d_ver
            out[:, k, 0] = self._value(f, S, total)
            out[:, k, 1] = self._value(f, S, d_ver) if parts else out[:, k, 0]
            for s, d in parts.items():
                out[:, k, 2 + IN_USE.index(s)] = self._value(f, S, d)
        return out

    def _draw(self, name: str, n: int, seed: int, block: int):
        """The in-use source ``name``: a function (feature, its slice, its nominal points) -> displacements (n, N, 3)
        mm, drawn from the source's own stream (seed, block, source), the same numbers whichever features use it."""
        rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(block),
                                                                                 zlib.crc32(f"feature:{name}".encode()))))
        Nf = len(self.points)
        if name == "probing":
            z = rng.standard_normal((n, Nf))
            return lambda f, sl, S: (z[:, sl] * (f.probing_error / D2_25))[..., None] * f.directions[None]
        if name == "repeatability_in_use":  # along the machine's axes, turned into the workpiece frame (five axes)
            z = rng.standard_normal((n, Nf, 3))
            return lambda f, sl, S: self._to_workpiece(z[:, sl] * self.rep, sl)
        if name == "rotary_repeatability_in_use":  # each rotary axis' angle, through the chain's turn rate
            letters = sorted(self.angles)
            if not letters:
                return None
            z = rng.standard_normal((n, Nf, len(letters)))
            # one draw per axis and positioning: a point takes the draw of the point its axis was positioned at
            zh = np.stack([z[:, self.held[a], j] for j, a in enumerate(letters)], axis=-1)
            return lambda f, sl, S: sum(zh[:, sl, j, None] * f.rotary_repeatability * self.turn[a][sl][None]
                                        for j, a in enumerate(letters))
        if name == "machine_thermal_drift":  # the linear axes' scales, at the commanded positions
            z = rng.standard_normal((n, 1, 3))
            return lambda f, sl, S: self._to_workpiece(
                z * (f.machine_temperature_change * self.cte) * (self.points[sl] - self.x0)[None], sl)
        z = rng.standard_normal((n, 1, 1))  # the part expands about its centre, where it is (its nominal points)
        if name == "part_temperature":
            return lambda f, sl, S: z * (f.part_cte * f.part_temperature_u) * (self.geometry[sl] - f.centre)[None]
        if name == "part_cte":
            return lambda f, sl, S: z * (f.part_cte_u * (f.part_temperature - 293.15)) * (self.geometry[sl] - f.centre)[None]
        raise KeyError(name)

    def _to_workpiece(self, d: np.ndarray, sl: slice) -> np.ndarray:
        """Displacements (n, N, 3) along the machine's axes at the points ``sl`` in the workpiece frame the features
        are computed in (R^T d at each point's pose); unchanged where the frames are the same."""
        if self.to_machine is None:
            return d
        return np.einsum("mji,nmj->nmi", self.to_machine[sl], d)

    @staticmethod
    def _value(f: FeatureSpec, S: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(n,) the feature's error from the measured points S + d (measured minus true; S: the part at nominal)."""
        um = 1e3
        M = S[None] + d
        if f.kind == "distance":
            return (np.linalg.norm(M[:, 1] - M[:, 0], axis=-1) - np.linalg.norm(S[1] - S[0])) * um
        if f.kind in ("diameter", "position"):
            c0 = S.mean(axis=0)
            basis = np.linalg.svd(S - c0)[2]
            centre, R = circle_fit(M - c0, basis[0], basis[1])
            nc, nR = _circle_nominal(S, basis[2])
            if f.kind == "diameter":
                return 2 * (R - nR) * um
            true = np.array([(nc - c0) @ basis[0], (nc - c0) @ basis[1]])
            return 2 * np.linalg.norm(centre - true[None], axis=-1) * um
        if f.kind == "flatness":
            nrm = f.datum
            basis = np.linalg.svd(S - S.mean(0))[2]
            if f.association == "minimum zone":
                return minimum_zone_flatness(M - S.mean(0), nrm, basis[0], basis[1]) * um
            c, n_ = plane_fit(M)
            h = np.einsum("nik,nk->ni", M - c[:, None], n_)
            return (h.max(axis=1) - h.min(axis=1)) * um
        # orientation: angle between the measured and the true plane
        _, n_ = plane_fit(M)
        cosang = np.abs(n_ @ f.datum)
        sin = np.linalg.norm(np.cross(n_, f.datum[None]), axis=-1)
        return np.arctan2(sin, cosang) * 1e6


def _probe_plan(scenario, points: np.ndarray, angles: dict) -> Plan:
    """The plan of probed points at the measurand's tool: commanded positions and, on a five-axis machine, the
    commanded angles of each rotary axis with the plan's rotary geometry (the chain evaluates them as the mesh)."""
    n = len(points)
    extra = {"angles": dict(angles), "rotary": dict(scenario.plan.rotary)} if angles else {}
    return Plan(np.arange(n), np.ones(n, int), np.zeros(n), np.array(points, float), np.ones((n, 3)),
                np.tile(np.asarray(scenario.tool, float), (n, 1)), **extra)


def _nominal_points(scenario, points: np.ndarray, angles: dict) -> np.ndarray:
    """(N, 3) mm: where an error-free machine puts the measurand's tool at commanded points and angles, in the
    workpiece frame (the truth's chain at zero errors): the part a five-axis feature is probed on."""
    truth = scenario.truth
    model = MeasurementModel(truth.config, truth.errors, _probe_plan(scenario, points, angles))
    return model.machine_points(np.zeros((1, truth.n_params)))[0]


#: the angle step of the turn rates' central differences (rad): the rotation is exact, the difference's error is
#: of order step^2 (1e-12 of the rate)
TURN_STEP = 1e-6


def _turn_rates(scenario, points: np.ndarray, angles: dict) -> dict:
    """{letter: (N, 3) mm/rad} the derivative of the nominal tool point in the workpiece frame with each rotary axis'
    angle at the probed poses: the chain's own ``axis_offset.<letter>`` input, by central differences."""
    truth = scenario.truth
    model = MeasurementModel(truth.config, truth.errors, _probe_plan(scenario, points, angles))
    zero = np.zeros((1, truth.n_params))
    n = len(points)
    out = {}
    for a in sorted(angles):
        step = np.full((1, n), TURN_STEP)
        out[a] = (model.machine_points(zero, {f"axis_offset.{a}": step})[0]
                  - model.machine_points(zero, {f"axis_offset.{a}": -step})[0]) / (2 * TURN_STEP)
    return out


def _warnings(scenario) -> list:
    """Sentences on what the features do not include: sources that act on the compensated machine at the mesh
    rows only (``measurand_offset``: they are not evaluated at the features' points)."""
    names = [s.name for s in scenario.sources if "measurand_offset" in (s.targets or ())]
    if not names:
        return []
    return [f"WARNING: source(s) {', '.join(names)} act on the compensated machine at the mesh points only; their part "
            "is not evaluated at the features' points and is not in the features' uncertainty"]


# ------------------------------------------------------------------ statistics, budget, decision
def describe(scenario) -> list | None:
    """The features of a run for its spec (None without [[features]])."""
    fs = FeatureSet.of(scenario)
    if fs is None:
        return None
    return [f.describe() for f in fs.specs] + ([{"warnings": fs.warnings}] if fs.warnings else [])


def feature_budget(engine, total: dict, per_source: dict, n: int) -> dict:
    """The features' budget: each verification source alone on the same trials (common random numbers), the feature
    error from the verification's state; each in-use source from the same trials with every source active (it does
    not depend on the verification's sources); the interaction term closes the table."""
    fs = FeatureSet.of(engine.scenario)
    V = total["features"]  # (K, C) variances
    out = []
    for k, f in enumerate(fs.specs):
        Vt = float(V[k, 0])
        rows = []
        for s in engine.sources:
            v = float(per_source[s.name]["features"][k, 1])
            rows.append({"source": s.name, "group": str(getattr(s.group, "value", s.group)), "u_i": float(np.sqrt(v)),
                         "share": v / Vt if Vt > 0 else 0.0})
        for s in f.in_use():
            v = float(V[k, 2 + IN_USE.index(s)])
            rows.append({"source": s, "group": "in use", "u_i": float(np.sqrt(v)), "share": v / Vt if Vt > 0 else 0.0,
                         "description": f.in_use_text(s)})
        inter = Vt - sum(r["u_i"] ** 2 for r in rows)
        out.append({"name": f.name, "unit": f.unit, "trials": n, "u_total": float(np.sqrt(max(Vt, 0))), "rows": rows,
                    "interaction_share": inter / Vt if Vt > 0 else 0.0})
    return {"features": out, "basis": "variance, each source alone on the same trials (k = 1)"}


def _interval(y: np.ndarray, p: float):
    lo, hi = np.quantile(y, [(1 - p) / 2, (1 + p) / 2], method="inverted_cdf")
    return float(lo), float(hi)


def _shortest(y: np.ndarray, p: float):
    s = np.sort(y)
    m = len(s)
    q = int(np.ceil(p * m))
    if q >= m:
        return float(s[0]), float(s[-1])
    w = s[q:] - s[: m - q]
    j = int(np.argmin(w))
    return float(s[j]), float(s[j + q])


def decision(f: dict, estimate: float, low: float, high: float, p: float) -> dict:
    """ISO 14253-1 decision against the feature's tolerance, with the rule: the acceptance zone for a measured value,
    and the verdict for a part at nominal, whose expected measured value is the estimate."""
    T = f["tolerance"]
    u = f["unit"]
    if T is None:
        return None
    if f["one_sided"]:
        U = max(high, 0.0)
        zone = [None, T - U] if T - U >= 0 else None
        rule = (f"ISO 14253-1 guarded acceptance, one-sided characteristic (value <= T): conformance is proven for a "
                f"measured value v when v <= T - U, U = {bound(U, 'up', decimals_of([U]))} {u} (rounded up) the upper end of the {percent(p)} interval of "
                f"the machine's error of this feature (a conservative guard band: the error of a real part's value "
                f"is not additive); non-conformance when v > T + U")
        proven = zone is not None and estimate <= zone[1]
        refuted = estimate > T + U
    else:
        lo_z, hi_z = -T + high, T + low
        zone = [lo_z, hi_z] if hi_z >= lo_z else None
        rule = (f"ISO 14253-1 guarded acceptance, two-sided (|deviation from nominal| <= T): a measured deviation d "
                f"leaves the true deviation in [d - {high:.3g}, d - ({low:.3g})] {u} (the {percent(p)} interval of the "
                f"error E, true = d - E); conformance is proven when that lies within [-T, T], d in "
                f"[{bound(lo_z, 'up', decimals_of([lo_z, hi_z]))}, {bound(hi_z, 'down', decimals_of([lo_z, hi_z]))}] {u}"
                + (" (empty)" if hi_z < lo_z else " (rounded inwards)")
                + "; non-conformance when it lies outside")
        proven = zone is not None and lo_z <= estimate <= hi_z
        refuted = estimate - high > T or estimate - low < -T
    verdict = "conforms" if proven else "does not conform" if refuted else "undecided"
    where = ("no acceptance zone: the machine's " + percent(p) + " error interval is wider than the tolerance, "
             "conformance cannot be proven on it") if zone is None else (
        "acceptance zone for a measured " + ("value: <= " + f"{bound(zone[1], 'down', decimals_of(zone[1:]))} {u}"
                                             if f["one_sided"] else
                                             f"deviation: [{bound(zone[0], 'up', decimals_of(zone))}, "
                                             f"{bound(zone[1], 'down', decimals_of(zone))}] {u} (rounded inwards)"))
    return {"tolerance": T, "unit": u, "coverage": p, "rule": rule, "acceptance_zone": zone,
            "verdict_at_nominal": verdict,
            "statement": f"tolerance {T:g} {u}, {percent(p)} coverage: {where}; a part at nominal (measured value the "
                         f"estimate, {estimate:.3g} {u}) {verdict}"}


def features_json(spec_features: list | None, samples: np.ndarray | None, coverage: float, budget: dict | None) -> list:
    """Per feature: its measurand, the estimate (mean) of its error, u (k = 1), the coverage intervals, the budget
    by source and the ISO 14253-1 decision.  ``samples``: (n, K, C) the run's trials."""
    if not spec_features:
        return None
    specs = [f for f in spec_features if "kind" in f]
    warnings = [w for f in spec_features for w in f.get("warnings", [])]
    rows = {b["name"]: b for b in (((budget or {}).get("features") or {}).get("features") or [])}
    out = []
    for k, f in enumerate(specs):
        e = {"name": f["name"], "kind": f["kind"], "measurand": f["measurand"] + ("; " + "; ".join(warnings)
                                                                                   if warnings else ""),
             "unit": f["unit"], "points": {"quantity": COMMANDED_POINTS, "value": f["points"], "unit": "mm"},
             "in_use": f["in_use"]}
        if "angles" in f:  # five axes: each point's commanded angles, and the frame the feature is computed in
            e["points"]["angles"] = {"value": f["angles"], "unit": f["angles_unit"]}
            e["frame"] = f["frame"]
            if "nominal_points" in f:  # the part's points (a log written before they were stated has none)
                e["nominal_points"] = {"quantity": NOMINAL_POINTS, "value": f["nominal_points"], "unit": "mm",
                                       "frame": f["frame"]}
        if samples is None or not len(samples):
            e["note"] = "the trials' feature values are not available (a run resumed from a log: rerun it)"
            out.append(e)
            continue
        y = samples[:, k, 0]
        lo, hi = _interval(y, coverage)
        e.update({"estimate": float(y.mean()), "u": float(y.std(ddof=1)), "k": 1, "trials": int(len(y)),
                  "interval": {"low": lo, "high": hi, "coverage": coverage, "kind": "probabilistically symmetric",
                               "method": "order statistics of every trial"},
                  "shortest_interval": dict(zip(("low", "high"), _shortest(y, coverage)))})
        if f["name"] in rows:
            e["budget"] = rows[f["name"]]
        dec = decision(f, float(y.mean()), lo, hi, coverage)
        if dec is not None:
            e["decision"] = dec
        out.append(e)
    return out


def features_text(feats: list | None) -> list:
    """The features table of the text output."""
    if not feats:
        return []
    lines = ["", "Features probed on the compensated machine (docs/features.md): error of each feature, measured "
                 "minus true, for a part at nominal" + frame_note(feats)]
    lines.append(f"  {'feature':<22} {'kind':<12} {'unit':<5} {'estimate':>9} {'u (k=1)':>9}   {'interval':>22}  "
                 f"decision for a part at nominal")
    for f in feats:
        if "u" not in f:
            lines.append(f"  {f['name']:<22} {f['kind']:<12} {f['note']}")
            continue
        iv = f["interval"]
        dec = f.get("decision")
        nd = decimals_for(f["u"])  # u to two significant digits, the rest to the same decimal (JCGM 101 7.9.2)
        lines.append(f"  {f['name']:<22} {f['kind']:<12} {pretty(f['unit']):<5} {f['estimate']:9.{nd}f} {f['u']:9.{nd}f}   "
                     f"[{iv['low']:8.{nd}f}, {iv['high']:8.{nd}f}]  " + (dec["verdict_at_nominal"] if dec else "-"))
    p = feats[0].get("interval", {}).get("coverage")
    if p:
        lines.append(f"  interval: probabilistically symmetric, {percent(p)} coverage; measurands:")
    for f in feats:
        lines.append(f"    {f['name']}: {f['measurand']}")
        if "budget" in f:
            b = f["budget"]
            lines.append(f"      budget (u_i in {pretty(f['unit'])}, k = 1, each source alone): " + ", ".join(
                f"{r['source']} {r['u_i']:.3g}" for r in sorted(b["rows"], key=lambda r: -r["share"]) if r["share"] > 0.001)
                + f"; interaction {b['interaction_share']:.1%}" + _sampling_note(b))
        if "decision" in f:
            lines.append(f"      decision: {f['decision']['statement']}")
            lines.append(f"      rule: {f['decision']['rule']}")
    return lines


def _sampling_note(b: dict) -> str:
    """Where a feature budget's interaction is beyond +-10 %: how much of it the budget's own sampling explains (a
    variance from n trials has a relative standard deviation of about sqrt(2 / (n - 1)), one per source)."""
    n = int(b.get("trials") or 0)
    if abs(b.get("interaction_share", 0.0)) <= 0.10 or n < 2:
        return ""
    rel = math.sqrt(2.0 / (n - 1))
    return (f" (each source's variance from {n} trials is uncertain by about {100 * rel:.0f} % of itself, sqrt(2/(n - 1)): "
            "the shares and the interaction carry that sampling noise; more --attribution-trials narrow it)")


def frame_note(feats: list) -> str:
    """Where the features are computed, when not in the machine frame (five axes, a turning table)."""
    return f", in the {FEATURE_TABLE_FRAME}" if any(f.get("frame", "machine frame") != "machine frame"
                                                   for f in feats) else ""


def _num(v: float) -> str:
    """A coordinate or angle to 0.1 um / 0.0001 deg, without trailing zeros (-0 shown as 0)."""
    t = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if t in ("-0", "") else t


def probed_points(f: dict) -> list:
    """[(commanded (3,) mm, {letter: deg} or {}, nominal (3,) mm on the part or None)] of a feature's JSON entry."""
    pts = f["points"]
    ang = (pts.get("angles") or {}).get("value") or {}
    nom = (f.get("nominal_points") or {}).get("value")
    return [(p, {a: v[j] for a, v in sorted(ang.items())}, None if nom is None else nom[j])
            for j, p in enumerate(pts["value"])]


def points_text(f: dict) -> str:
    """The probed points of a feature's JSON entry as one sentence: commanded position (mm) and angles (deg) of each
    point, and where it lies on the part when that is another frame (five axes)."""
    rows = []
    for j, (p, ang, nom) in enumerate(probed_points(f)):
        t = f"{j + 1}: ({', '.join(_num(v) for v in p)}) mm"
        if ang:
            t += ", " + ", ".join(f"{a} = {_num(v)}°" for a, v in ang.items())
        if nom is not None:
            t += f" → ({', '.join(_num(v) for v in nom)}) mm on the part"
        rows.append(t)
    five = any(a for _, a, _ in probed_points(f))
    return ("Probed points (commanded position of the linear axes" + (" and commanded rotary angles" if five else "")
            + (f", and the nominal point on the part in the {f['nominal_points'].get('frame', WORKPIECE_FRAME)}"
               if f.get("nominal_points") else "")
            + "): " + "; ".join(rows))


def features_markdown(feats: list | None) -> list:
    """The features table of the report (Markdown)."""
    if not feats:
        return []
    md = ["", "## Features probed on the compensated machine", "",
          "Error of each feature (measured minus true, a part at nominal), from the same Monte Carlo trials: the "
          "verification's state of the machine at every probed point, plus the in-use sources the feature states "
          "(docs/features.md)" + frame_note(feats) + ".", "",
          "| feature | kind | estimate | u (k = 1) | interval | decision for a part at nominal |", "| --- | --- | --- | --- | --- | --- |"]
    for f in feats:
        if "u" not in f:
            md.append(f"| {f['name']} | {f['kind']} | {f['note']} | | | |")
            continue
        iv, dec = f["interval"], f.get("decision")
        un, nd = pretty(f["unit"]), decimals_for(f["u"])  # two significant digits of u (JCGM 101 7.9.2)
        md.append(f"| {f['name']} | {f['kind']} | {f['estimate']:.{nd}f} {un} | {f['u']:.{nd}f} {un} | "
                  f"[{iv['low']:.{nd}f}, {iv['high']:.{nd}f}] {un} ({percent(iv['coverage'])}) | "
                  f"{dec['verdict_at_nominal'] if dec else '-'} |")
    md.append("")
    for f in feats:
        md.append(f"* **{f['name']}**: {f['measurand']}.")
        if "points" in f:
            md.append("  " + points_text(f) + ".")
        if "budget" in f:
            md.append("  Budget (u_i, each source alone): " + ", ".join(
                f"{r['source']} {r['u_i']:.3g} {pretty(f['unit'])} ({r['share']:.1%})"
                for r in sorted(f["budget"]["rows"], key=lambda r: -r["share"]) if r["share"] > 0.001) + ".")
        if "decision" in f:
            md.append(f"  Decision (ISO 14253-1): {f['decision']['statement']}. Rule: {f['decision']['rule']}.")
    return md
