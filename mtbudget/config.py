"""Configuration files (TOML with pint quantity strings) and the built-in default.

Nothing in a config is evaluated: every value is a string that pint parses,
a number, or a table.  Errors name the file and the key (``tracker.D``).
See docs/configuration.md for every key.
"""

from __future__ import annotations

import copy
import difflib
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from .errors import ConfigError
from .machine import AXES, COMPONENT_ERRORS, SQUARENESS, Configuration, RotaryAxis, check_code
from .plan import Plan, Scale, Sensor, build_plan, mesh
from .recording import (ATTACHED_TO, COLUMNS, MAX_TIME, REPORT_INSTRUMENT_KEYS,
                        REPORT_KEYS, UNCERTAINTIES, cte_problem, magnitude_problem, pivot_problem, report_problem,
                        uncertainty_problem)
from .units import ABSOLUTE_TEMPERATURE, to_internal

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

CONFIG_FORMAT = "mtbudget-config/1"
DEFAULT_CONFIG = "paper_xfyz.toml"
#: size and range guards, checked before anything is allocated: mesh points (time and memory grow linearly with
#: them: a 64-trial block of 10^4 points holds arrays of ~15 MB per quantity), measured points of the plan, |length|
#: of mesh, tools and tracker position (mm)
MAX_MESH_POINTS = 10_000
MAX_PLAN_ROWS = 100_000
MAX_LENGTH = 1.0e5
MAX_CONFIG_BYTES = 1_048_576
#: a [[sensors]] reading noise (K, standard deviation) above this is a unit mistake: the temperature sensors of a
#: machine-tool verification read to 0.01-0.1 K, and 1 K is ten times the poorest (the rule of UNCERTAINTIES)
MAX_SENSOR_NOISE = 1.0


def _printable(text: str) -> str:
    """``text`` on one line: a key with a newline or another control character is shown escaped."""
    text = str(text)
    return text if text.isprintable() else repr(text)[1:-1]


def default_config_path() -> Path:
    """Path of the built-in default configuration (the paper's XFYZ study)."""
    return Path(str(resources.files("mtbudget") / "data" / DEFAULT_CONFIG))


def bundled_config(name: str) -> Path:
    """Path of a bundled configuration: paper_xfyz (the default), four_stations (the paper's machine from four
    stations)."""
    p = Path(str(resources.files("mtbudget") / "data" / f"{name}.toml"))
    if not p.is_file():
        raise ConfigError(f"no bundled configuration {name!r}")
    return p


def example_recording(name: str) -> Path:
    """Path of a bundled example recording (null, thermal_x, reversal_y, tracker_drift, four_stations)."""
    p = Path(str(resources.files("mtbudget") / "data" / "recordings" / name))
    if not p.is_dir():
        raise ConfigError(f"no bundled example recording {name!r}")
    return p


class Reader:
    """Typed access to a TOML table with errors that name file and key."""

    def __init__(self, data: dict, path, prefix: str = "", provenance: list | None = None):
        self.data, self.path, self.prefix, self.provenance = data, path, prefix, provenance

    def where(self, key):
        label = origin(self.provenance, f"{self.prefix}{key}")
        path = self.path if label is None or label == SET_ORIGIN else label
        return _printable(f"{path}: {self.prefix}{key}" if path else f"{self.prefix}{key}")

    def has(self, key):
        return key in self.data

    def sub(self, key, required=False) -> "Reader":
        v = self.data.get(key)
        if v is None:
            if required:
                raise ConfigError(f"{self.where(key)}: missing table [{self.prefix}{key}]")
            v = {}
        if not isinstance(v, dict):
            raise ConfigError(f"{self.where(key)}: expected a table")
        return Reader(v, self.path, f"{self.prefix}{key}.", self.provenance)

    def raw(self, key, default=None):
        return self.data.get(key, default)

    def quantity(self, key, unit: str, default=None, value=None, absolute_temperature: bool = False) -> float:
        text = self.data.get(key, default) if value is None else value
        if text is None:
            raise ConfigError(f"{self.where(key)}: missing (a quantity in {unit})")
        return to_unit(text, unit, self.where(key), absolute_temperature=absolute_temperature)

    def number(self, key, default=None, kind=float, low=None, high=None):
        """A plain TOML number (an integer where ``kind`` is int: 2.5 is refused, never floored), within [low, high]."""
        v = self.data.get(key, default)
        if v is None:
            raise ConfigError(f"{self.where(key)}: missing")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (kind is int and not isinstance(v, int)):
            what = "a whole number" if kind is int else "a number"
            raise ConfigError(f"{self.where(key)}: expected {what}, got {v!r}")
        v = kind(v)
        if (low is not None and v < low) or (high is not None and v > high):
            rng = f"at least {low}" if high is None else f"between {low} and {high}"
            raise ConfigError(f"{self.where(key)}: must be {rng}, got {v!r}")
        return v

    def check_keys(self, allowed, what: str | None = None):
        """Every key of the table is known; a typo gets the closest known key."""
        for k in self.data:
            if k not in allowed:
                close = difflib.get_close_matches(str(k), list(allowed), n=1)
                hint = f"; did you mean {close[0]!r}?" if close else f"; {what or 'it'} takes {', '.join(allowed)}"
                raise ConfigError(f"{self.where(k)}: unknown key{hint}")


#: every key a configuration may hold, by table (docs/configuration.md documents each; a test checks it does).
#: [placement] is checked here with its values (_placement, for every command that reads a configuration) and
#: [sources] by the scenario.
SCHEMA = {
    "": ("format", "name", "description", "machine", "reference_temperature", "seed", "mesh", "plan", "tracker",
         "machine_tool", "geometric_errors", "sensors", "effects", "placement", "sources", "weights", "measurand",
         "stations", "scales", "rotary", "features", "report"),
    "mesh": ("x", "y", "z", "step", "step_x", "step_y", "step_z"),
    "plan": ("runs", "tools", "feed", "stop_time", "tool_change_time", "station_change_time"),
    "tracker": ("D", "L", "H", "a", "b", "d", "angular", "distance", "distance_per_length", "mount"),
    "machine_tool": ("repeatability", "max_degree", "cte", "rotary_harmonics"),
    "geometric_errors": ("seed", "translational", "angular", "squareness", "coefficients", "rotary_location",
                         "rotary_orientation", "rotary_zero", "rotary"),
    "sensors": ("column", "attached_to", "position", "start", "rate", "noise", "cycle_amplitude", "cycle_period",
                "cycle_phase"),
    "effects": ("thermal", "reversal", "drift"),
    "weights": ("angular", "distance", "distance_per_length", "repeatability"),
    "measurand": ("tool",),
    "placement": ("D", "L", "H", "range_min", "range_max", "elevation_max", "tests", "candidates", "envelope",
                  "directions", "eq23", "eq27"),
    "stations": ("kind", "D", "L", "H", "a", "b", "d", "position", "dead_path", "description", "angular", "distance",
                 "distance_per_length"),
    # [scales.<axis>]: the nominal expansion of each axis scale, simulated and corrected (as recording.toml's [scales])
    "scales": AXES,
    "scales.<axis>": ("cte", "fixed_point"),
    # [rotary.<A|B|C>]: a five-axis machine's rotary axes (as recording.toml's format 3) and the angles the plan visits
    "rotary": ("A", "B", "C"),
    "rotary.<axis>": ("pivot", "direction", "angles", "description"),
    # [[features]]: features probed on the compensated machine (docs/features.md; checked by mtbudget.features)
    "features": ("name", "kind", "points", "directions", "tolerance", "association", "datum", "probing_error",
                 "repeatability", "machine_temperature_change", "part_temperature", "part_temperature_u", "part_cte",
                 "part_cte_u", "angles", "rotary_repeatability", "reposition"),
    # [report]: what a laboratory states on the report and the DCC (all optional, free text; mtbudget.report)
    "report": REPORT_KEYS,
    "report.instrument": REPORT_INSTRUMENT_KEYS,
}
#: at most this many commanded angles per rotary axis in a plan
MAX_ROTARY_ANGLES = 72
#: the readings of the paper that its text leaves open, one key of [placement] each, default first (mtbudget.study)
PLACEMENT_READINGS = {"directions": ("machine", "envelope"), "eq23": ("polar", "elevation"),
                      "eq27": ("compensated", "compensated_rigid", "residual")}
#: what the placement study takes from elsewhere in the configuration (one key per physical input)
PLACEMENT_NOISE_KEYS = {"angular_mean": "tracker.angular", "distance": "tracker.distance",
                        "distance_per_length": "tracker.distance_per_length",
                        "angular_sd": "sources.tracker_noise.angular_sd"}
#: the tables that are arrays of tables ([[sensors]], [[stations]]): checked entry by entry
ARRAY_TABLES = ("sensors", "stations", "features")
#: at most this many stations in one verification (each adds 6 or 4 unknowns and a pass over the plan)
MAX_STATIONS = 12


def to_unit(text, unit: str, where: str = "value", *, absolute_temperature: bool = False) -> float:
    """Parse a quantity and convert it to ``unit`` (through :func:`mtbudget.units.to_internal`);
    a ConfigError names ``where``."""
    return to_internal(text, unit, where=where, error=ConfigError, absolute_temperature=absolute_temperature)


#: the physical inputs a configuration states once: key -> (internal unit, SimulationConfig attribute, default).
#: Sources draw them through their ``links``; the identification weights follow them unless [weights] says otherwise.
PHYSICAL_INPUTS = {
    "tracker.angular": ("rad", "angular", "20 urad"),
    "tracker.distance": ("mm", "distance", "4 um"),
    "tracker.distance_per_length": ("mm/mm", "distance_per_length", "0.8 um/m"),
    "machine_tool.repeatability": ("mm", "repeatability", "1.5 um"),
    "machine_tool.cte": ("1/K", "cte", "11.5 um/(m*K)"),
}
#: the identification weights a verification states (the [weights] table): key -> physical input
WEIGHT_KEYS = {"angular": "tracker.angular", "distance": "tracker.distance",
               "distance_per_length": "tracker.distance_per_length", "repeatability": "machine_tool.repeatability"}


@dataclass
class SensorSpec:
    """A simulated sensor: start + rate t + a cycle (air conditioning) + reading noise."""

    sensor: Sensor
    start: float  # K
    rate: float  # K/s
    noise: float  # K (standard deviation of each reading)
    cycle_amplitude: float = 0.0  # K
    cycle_period: float = 1800.0  # s
    cycle_phase: float = 0.0  # rad
    noise_stated: bool = True  # False: no `noise` key, the readings are simulated noise-free (the stated default)

    def values(self, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        T = self.start + self.rate * t
        if self.cycle_amplitude:
            T = T + self.cycle_amplitude * np.sin(2 * np.pi * t / self.cycle_period + self.cycle_phase)
        if self.noise > 0:
            T = T + rng.normal(0.0, self.noise, len(t))
        return T


@dataclass
class SimulationConfig:
    """Everything needed to simulate one verification (internal units)."""

    name: str
    description: str
    machine: str
    reference_temperature: float
    seed: int
    mesh_ranges: dict
    mesh_step: dict
    runs: int
    tools: list
    feed: float
    stop_time: float
    tool_change_time: float
    station_change_time: float  # s, moving to the next station of [[stations]] (and setting it up)
    pose: np.ndarray  # D, L, H, a, b, d
    angular: float
    distance: float
    distance_per_length: float
    repeatability: float
    cte: float  # 1/K, nominal expansion coefficient of the scales of the axes without a [scales.<axis>] table
    max_degree: int
    geometric: dict  # {"coefficients": {...}, "squareness": {...}} or generation std
    sensors: list = field(default_factory=list)
    effects: dict = field(default_factory=dict)  # thermal {axis: 1/K}, reversal {axis: mm}, drift (3,) mm/s
    weights: dict | None = None  # [weights]: identification weights stated apart from the physical inputs
    measurand_tool: list | None = None  # [measurand] tool: where the compensated machine is evaluated (mm)
    stations: list = field(default_factory=list)  # [StationSpec]: [[stations]]; empty: one tracker at [tracker]'s pose
    #: [scales.<axis>]: {axis: plan.Scale}, the scales whose nominal expansion the simulated machine has and the
    #: verification corrects (about each fixed point, at the read axis temperatures); empty: none (the nominal
    #: expansion taken as perfectly corrected, the thermal sources drawing only the deviations about the axis zero)
    scales: dict = field(default_factory=dict)
    #: five-axis machines ([rotary.<A|B|C>]): {letter: machine.RotaryAxis}, the commanded angles (rad) the plan
    #: visits for each (every combination of them with every mesh point), and the error motions' Fourier terms
    rotary: dict = field(default_factory=dict)
    rotary_angles: dict = field(default_factory=dict)
    rotary_harmonics: int = 0
    mount: str = "table"
    source: dict = field(default_factory=dict)  # the raw TOML (for logging)
    path: Path | None = None
    #: the configuration's text as the run log keeps it: None for a plain file (its own text is read), the text
    #: with the resolved table appended for a file that `extends` another or a configuration changed by --set
    text: str | None = None
    #: where each key was stated, nearest first: [(SET_ORIGIN, the --set items as a table), (this file, its own
    #: table), (the file it extends, its own table), ...]; None: every key is this file's (see :func:`origin`)
    provenance: list | None = None

    def mesh_points(self) -> np.ndarray:
        """The plan's nominal poses, (M0, 3 + R): the linear mesh (x fastest) at every combination of the rotary
        axes' angles (the last rotary letter fastest), one pose after the other."""
        pts = mesh(self.mesh_ranges, self.mesh_step)
        letters = sorted(self.rotary)
        if not letters:
            return pts
        grids = np.meshgrid(*[np.asarray(self.rotary_angles[r], float) for r in letters], indexing="ij")
        poses = np.stack([g.ravel() for g in grids], axis=1)  # (P, R)
        return np.concatenate([np.tile(pts, (len(poses), 1)), np.repeat(poses, len(pts), axis=0)], axis=1)

    def stated(self, key: str) -> bool:
        """Whether the configuration itself states ``key`` ("tracker.angular"), rather than leaving its default."""
        node = self.source
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                return False
            node = node[part]
        return True

    def where(self, key: str) -> str:
        """``file: key``, the file being the one that states ``key`` (a base this file extends names itself; a key
        given with --set names this file, and the error gets "(given with --set)", :func:`given_with_set`)."""
        label = origin(self.provenance, key)
        path = self.path if label is None or label == SET_ORIGIN else label
        return _printable(f"{path}: {key}" if path else key)

    def origin_rank(self, key: str) -> int:
        """How near the user ``key`` was stated: 0 for --set, 1 for this file, higher for the files it extends."""
        return origin_rank(self.provenance, key)

    def plan(self, rng: np.random.Generator | None = None) -> Plan:
        """Build the plan (mesh, passes, timing) and its sensor readings."""
        pts = self.mesh_points()
        # several stations measure the plan one after the other: station k's runs are k*runs+1 .. (k+1)*runs
        runs = self.runs * max(1, len(self.stations))
        plan = build_plan(pts, self.tools, runs, self.feed, self.stop_time, self.tool_change_time,
                          rotary=self.rotary or None)
        if len(self.stations) > 1:  # each move to the next station takes station_change_time
            plan.time = plan.time + (plan.run - 1) // self.runs * self.station_change_time
        rng = rng or np.random.default_rng(self.seed)
        plan.sensors = [s.sensor for s in self.sensors]
        plan.scales = dict(self.scales)
        if not plan.time[-1] <= MAX_TIME:
            raise ConfigError(f"{self.where('plan')}: the plan lasts {plan.time[-1]:.3g} s; at most {MAX_TIME:g} s "
                              "(check feed, stop_time, tool_change_time and station_change_time)")
        for i, s in enumerate(self.sensors):
            T = plan.temperature[s.sensor.column] = s.values(plan.time, rng)
            lo, hi = ABSOLUTE_TEMPERATURE
            if not np.all((T >= lo) & (T <= hi)):
                bad = T[~((T >= lo) & (T <= hi))][0]
                raise ConfigError(f"{self.where(f'sensors[{i}]')}: the simulated reading reaches {bad:.6g} K "
                                  f"({bad - 273.15:.6g} degC), not a plausible absolute temperature ({lo:g} K to "
                                  f"{hi:g} K); check start, rate, noise and cycle_amplitude")
        return plan


#: the pose keys of [tracker] and of an xyz station: D, L, H (mm) and the Euler angles a, b, d (rad)
POSE_KEYS = ("D", "L", "H", "a", "b", "d")


@dataclass
class StationSpec:
    """One station of a simulated verification ([[stations]]): a laser tracker (``xyz``) at its pose, or a tracking
    interferometer (``range``) at its position with a dead path.  Every station measures the whole plan, one after
    the other; all of them have the [tracker] uncertainties (a range station only the distance ones)."""

    kind: str  # "xyz" or "range"
    pose: np.ndarray | None  # (6,) D, L, H (mm), a, b, d (rad) of an xyz station
    position: np.ndarray | None  # (3,) mm, machine frame, of a range station
    dead_path: float = 0.0  # mm, a range station's offset (identified with its position)
    description: str = ""
    #: its own standard uncertainties (k = 1; rad, mm, mm/mm) where it states them, else None: the [tracker] ones
    angular: float | None = None
    distance: float | None = None
    distance_per_length: float | None = None

    @property
    def tracker_pose(self) -> np.ndarray:
        """A pose that puts the station at its place: its own (xyz), or its position with no rotation (range: the
        frame in which the norm of a point is its range)."""
        return self.pose if self.kind == "xyz" else np.concatenate([self.position, np.zeros(3)])


def _pose(tr: "Reader") -> np.ndarray:
    pose = np.array([tr.quantity(k, "mm") for k in "DLH"] + [tr.quantity(k, "rad") for k in "abd"])
    if np.any(np.abs(pose[:3]) > MAX_LENGTH):
        raise ConfigError(f"{tr.where('DLH'[int(np.argmax(np.abs(pose[:3])))])}: beyond {MAX_LENGTH:g} mm")
    return pose


def _placement(r: "Reader") -> None:
    """Check [placement] (keys and values) for every command that reads the configuration, not only the placement
    study: a typo or a bad unit there is an error wherever the file is used (the study reads the values)."""
    if not r.has("placement"):
        return
    raw = r.raw("placement")
    if not isinstance(raw, dict):
        raise ConfigError(f"{r.where('placement')}: expected a table")
    p = r.sub("placement")
    for k in raw:
        if k in PLACEMENT_NOISE_KEYS:
            raise ConfigError(f"{p.where(k)}: the tracker noise is stated once, as {PLACEMENT_NOISE_KEYS[k]}; "
                              "remove it from [placement]")
    p.check_keys(SCHEMA["placement"], "[placement]")
    for k in "DLH":
        if k in raw:
            v = raw[k]
            if not (isinstance(v, list) and len(v) == 2):
                raise ConfigError(f"{p.where(k)}: expected [low, high], e.g. [\"-2000 mm\", \"-500 mm\"]")
            lo, hi = (to_unit(x, "mm", p.where(k)) for x in v)
            if not lo <= hi or max(abs(lo), abs(hi)) > MAX_LENGTH:
                raise ConfigError(f"{p.where(k)}: expected low <= high within {MAX_LENGTH:g} mm")
    for k, unit in (("range_min", "mm"), ("range_max", "mm"), ("elevation_max", "rad")):
        if k in raw and not p.quantity(k, unit) > 0:
            raise ConfigError(f"{p.where(k)}: must be positive")
    if "range_min" in raw or "range_max" in raw:
        if not p.quantity("range_min", "mm", "0.5 m") < p.quantity("range_max", "mm", "15 m"):
            raise ConfigError(f"{p.where('range_max')}: must exceed range_min")
    if "envelope" in raw:
        env = raw["envelope"]
        if not (isinstance(env, dict) and set(env) == set(AXES)
                and all(isinstance(env[a], list) and len(env[a]) == 2 for a in AXES)):
            raise ConfigError(f"{p.where('envelope')}: expected {{ x = [lo, hi], y = [lo, hi], z = [lo, hi] }}")
        for a in AXES:
            lo, hi = (to_unit(x, "mm", f"{p.where('envelope')}.{a}") for x in env[a])
            if not lo <= hi:
                raise ConfigError(f"{p.where('envelope')}.{a}: low must not exceed high")
    for k in ("tests", "candidates"):
        if k in raw:
            p.number(k, kind=int, low=1)
    for k, choices in PLACEMENT_READINGS.items():
        if k in raw and raw[k] not in choices:
            raise ConfigError(f"{p.where(k)}: expected one of {', '.join(map(repr, choices))}, got {raw[k]!r:.60}")


def _report_fields(r: "Reader") -> None:
    """[report]: optional text fields of the report and the DCC (keys already checked), checked for their types by
    the rule recording.toml's [report] follows too (:func:`mtbudget.recording.report_problem`)."""
    if not r.has("report"):
        return
    p = r.sub("report")
    if isinstance(p.data.get("instrument"), dict):
        p.sub("instrument").check_keys(SCHEMA["report.instrument"], "[report.instrument]")
    bad = report_problem(p.data)
    if bad:
        raise ConfigError(f"{p.where(bad[0])}: {bad[1]}")


def config_states(data: dict, key: str) -> bool:
    """Whether the raw configuration ``data`` states the dotted ``key`` ("machine_tool.cte")."""
    node = data
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def _scales(r: "Reader", sensors: list) -> dict:
    """[scales.<axis>] cte, fixed_point: the nominal expansion of each axis scale (keys already checked for [scales])."""
    if not r.has("scales"):
        return {}
    sc = r.sub("scales")
    out = {}
    for a in AXES:
        if not sc.has(a):
            continue
        t = sc.sub(a)
        t.check_keys(SCHEMA["scales.<axis>"], f"[scales.{a}]")
        if not t.has("cte"):
            raise ConfigError(f"{t.where('cte')}: missing (the nominal expansion coefficient of the {a} scale, for "
                              "example \"11.5 um/(m*K)\")")
        cte = t.quantity("cte", "1/K")
        if cte_problem(cte):
            raise ConfigError(f"{t.where('cte')}: {cte_problem(cte)}")
        x0 = t.quantity("fixed_point", "mm", "0 mm")
        if abs(x0) > MAX_LENGTH:
            raise ConfigError(f"{t.where('fixed_point')}: beyond {MAX_LENGTH:g} mm; not a position on the {a} axis")
        if not any(s.sensor.axis == a for s in sensors):
            raise ConfigError(f"{sc.where(a)}: no [[sensors]] table is attached to the {a} axis; simulating and "
                              "correcting the scale's expansion needs its temperature")
        out[a] = Scale(cte, x0)
    return out


def _rotary(r: "Reader", code: str) -> tuple[dict, dict]:
    from .model import one_angle_only, rotary_direction

    """[rotary.<A|B|C>] pivot, direction, angles: ({letter: RotaryAxis}, {letter: commanded angles (rad)}), one table
    per rotary letter of the machine code, none for another."""
    letters = sorted(ch.lower() for ch in code if ch in "ABC")
    tables = r.sub("rotary") if r.has("rotary") else Reader({}, r.path, "rotary.", r.provenance)
    for key in tables.data:
        if str(key).lower() not in letters:
            raise ConfigError(f"{tables.where(key)}: machine {code!r} has no rotary axis {key}" +
                              (f" (its rotary axes: {', '.join(x.upper() for x in letters)})" if letters else ""))
    geometry, angles = {}, {}
    for a in letters:
        A = a.upper()
        if not tables.has(A):
            raise ConfigError(f"{tables.where(A)}: machine {code!r} has a rotary axis {A} but no [rotary.{A}] table "
                              "(pivot, direction, angles)")
        t = tables.sub(A)
        t.check_keys(SCHEMA["rotary.<axis>"], f"[rotary.{A}]")
        piv = t.raw("pivot")
        if not (isinstance(piv, list) and len(piv) == 3):
            raise ConfigError(f"{t.where('pivot')}: expected [x, y, z], a point of the axis' average line in the machine "
                              "frame with every axis at zero, e.g. [\"0 mm\", \"-20 mm\", \"-80 mm\"]")
        pivot = tuple(to_unit(v, "mm", f"{t.where('pivot')}[{i}]") for i, v in enumerate(piv))
        if max(abs(v) for v in pivot) > MAX_LENGTH:
            raise ConfigError(f"{t.where('pivot')}: beyond {MAX_LENGTH:g} mm")
        sign, problem = rotary_direction(a, t.raw("direction"))
        if problem:
            raise ConfigError(f"{t.where('direction')}: {problem}")
        geometry[a] = RotaryAxis(a, pivot, sign)
        vals = t.raw("angles")
        if not (isinstance(vals, list) and vals):
            raise ConfigError(f"{t.where('angles')}: expected the commanded angles the plan visits, e.g. [\"0 deg\", "
                              "\"90 deg\", \"180 deg\", \"270 deg\"]")
        if len(vals) > MAX_ROTARY_ANGLES:
            raise ConfigError(f"{t.where('angles')}: {len(vals)} angles; at most {MAX_ROTARY_ANGLES}")
        ang = [to_unit(v, "rad", f"{t.where('angles')}[{i}]") for i, v in enumerate(vals)]
        if max(abs(v) for v in ang) > 200 * np.pi:
            raise ConfigError(f"{t.where('angles')}: beyond 100 turns; not a commanded angle")
        single = one_angle_only(a, ang)
        if single:
            lost = single[1]
            raise ConfigError(f"{t.where('angles')}: one angle only: the location and zero errors of {A} ({lost}) then "
                              "act as a rigid motion of the tracker and cannot be identified; give three or more")
        angles[a] = ang
    return geometry, angles


def _plausible(kind: str, values, where: str) -> None:
    """Each of ``values`` (internal unit) a plausible ``kind`` of a simulated machine (recording.MAGNITUDES: the rule
    of every stated uncertainty), else one line naming the key (and the entry of a list)."""
    values = list(values)
    for i, v in enumerate(values):
        problem = magnitude_problem(kind, float(v))
        if problem:
            raise ConfigError(f"{where}{f'[{i}]' if len(values) > 1 else ''}: {problem}")


def _pivots_near(r: "Reader", rotary: dict, ranges: dict) -> None:
    """Each rotary axis' pivot near the verified volume ([mesh] and the machine zero: recording.pivot_problem)."""
    for letter, axis in rotary.items():
        problem = pivot_problem(axis.pivot, [ranges[a][0] for a in AXES], [ranges[a][1] for a in AXES])
        if problem:
            raise ConfigError(f"{r.where(f'rotary.{letter.upper()}.pivot')}: {problem}")


def _stations(raw: list, path, provenance: list | None = None) -> list:
    """The [[stations]] tables (keys already checked against the schema)."""
    if len(raw) > MAX_STATIONS:
        raise ConfigError(f"{path}: stations: {len(raw)} [[stations]]; at most {MAX_STATIONS}")
    out = []
    for i, s in enumerate(raw):
        sr = Reader(s, path, f"stations[{i}].", provenance)
        kind = s.get("kind")
        if kind not in ("xyz", "range"):
            got = "it is missing" if kind is None else f"got {kind!r:.60}"
            raise ConfigError(f"{sr.where('kind')}: expected \"xyz\" (a laser tracker: range and two angles) or "
                              f"\"range\" (a tracking interferometer: range only); {got}")
        desc = s.get("description", "")
        if not isinstance(desc, str):
            raise ConfigError(f"{sr.where('description')}: expected a string")
        own = {}
        for name, unit in (("angular", "rad"), ("distance", "mm"), ("distance_per_length", "mm/mm")):
            if name in s:
                if name == "angular" and kind == "range":
                    raise ConfigError(f"{sr.where(name)}: a range station measures no angle")
                own[name] = sr.quantity(name, unit)
                problem = uncertainty_problem(f"tracker.{name}", own[name])
                if problem:
                    raise ConfigError(f"{sr.where(name)}: {problem}")
        if kind == "xyz":
            extra = [k for k in ("position", "dead_path") if k in s]
            if extra:
                raise ConfigError(f"{sr.where(extra[0])}: an xyz station states its pose (D, L, H, a, b, d), not "
                                  f"{extra[0]}")
            out.append(StationSpec("xyz", _pose(sr), None, 0.0, desc, **own))
            continue
        extra = [k for k in POSE_KEYS if k in s]
        if extra:
            raise ConfigError(f"{sr.where(extra[0])}: a range station states its position [x, y, z] and dead_path, not "
                              "a pose (it measures no angle)")
        v = s.get("position")
        if not (isinstance(v, list) and len(v) == 3):
            raise ConfigError(f"{sr.where('position')}: expected [x, y, z], the station's position in the machine frame, "
                              "e.g. [\"1500 mm\", \"-800 mm\", \"900 mm\"]")
        pos = np.array([to_unit(x, "mm", f"{sr.where('position')}[{j}]") for j, x in enumerate(v)])
        if np.any(np.abs(pos) > MAX_LENGTH):
            raise ConfigError(f"{sr.where('position')}: beyond {MAX_LENGTH:g} mm")
        dead = sr.quantity("dead_path", "mm", "0 mm")
        if abs(dead) > MAX_LENGTH:
            raise ConfigError(f"{sr.where('dead_path')}: beyond {MAX_LENGTH:g} mm")
        out.append(StationSpec("range", None, pos, dead, desc, **own))
    if out and all(st.kind == "range" for st in out) and len(out) < 3:
        raise ConfigError(f"{path}: stations: {len(out)} range station(s) cannot locate a point in space; state at "
                          "least three range stations, or an xyz station")
    return out


#: how deep `extends` may chain (a file that extends one that extends ...)
MAX_EXTENDS = 8


def load_config(path=None, sets: tuple | list = ()) -> SimulationConfig:
    """Load a configuration file (the built-in default when ``path`` is None).

    A file may start from another: ``extends = "base.toml"`` (relative to the file) or ``extends = "default"``
    (the built-in paper configuration); its own tables and keys then replace the base's, table by table and key by
    key (a list or a value is replaced whole).  ``sets``: "dotted.key=value" overrides applied last (the CLI's
    ``--set``), the value a TOML value or else a string (``sources.tracker_noise.angular_sd=3 urad``); an index
    reaches into an array of tables (``sensors.0.noise=0.02 K``).  An error names the file that states the key (a
    base for a key this file does not state) and ends "(given with --set)" for a key of ``sets``."""
    path = Path(path) if path is not None else default_config_path()
    data, chain, own = _load_with_extends(path, [])
    own = [(p, copy.deepcopy(t)) for p, t in own]  # as the files state them, whatever --set changes in ``data``
    given: dict = {}
    for item in sets:
        _apply_set(data, item, path)
        _apply_set(given, item, path, lenient=True)
    provenance = ([(SET_ORIGIN, given)] if sets else []) + own
    try:
        cfg = parse_config(data, path, provenance)
    except ConfigError as exc:
        raise given_with_set(exc, provenance) from None
    if len(chain) > 1 or sets:
        import json

        own_text = path.read_text(encoding="utf-8", errors="replace")
        cfg.text = (own_text + "\n\n# resolved by mtbudget (extends: " + " <- ".join(str(p) for p in chain[1:]) +
                    ("; --set " + ", ".join(sets) if sets else "") + "), as JSON:\n# " + json.dumps(data, default=str) + "\n")
    return cfg


#: the origin of a key given with --set (:attr:`SimulationConfig.provenance`)
SET_ORIGIN = "--set"


def _key_parts(key: str) -> list:
    """``sensors[0].noise`` or ``sensors.0.noise`` -> ["sensors", "0", "noise"]."""
    return [p for p in re.sub(r"\[(\d+)\]", r".\1", str(key)).split(".") if p]


_ABSENT = object()


def _at(tree, parts):
    node = tree
    for part in parts:
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            return _ABSENT
    return node


def _holds(tree, parts) -> bool:
    return _at(tree, parts) is not _ABSENT


def _origin_index(provenance, key: str) -> int | None:
    """Index into ``provenance`` of the nearest statement of ``key`` or, where no one states it (a missing key), of
    its nearest stated table; None without provenance."""
    if not provenance:
        return None
    parts = _key_parts(key)
    while parts:
        for i, (label, tree) in enumerate(provenance):
            node = _at(tree, parts)
            if node is _ABSENT:
                continue
            if label == SET_ORIGIN and isinstance(node, dict) and any(_holds(t, parts) for _, t in provenance[1:]):
                continue  # a file's table that --set reaches into is the file's
            return i
        parts = parts[:-1]
    return None


def origin(provenance, key: str):
    """Who states ``key``: :data:`SET_ORIGIN`, a file's path, or None (unknown: the configuration's own file)."""
    i = _origin_index(provenance, key)
    return None if i is None else provenance[i][0]


def origin_rank(provenance, key: str) -> int:
    """0 for a key given with --set, 1 for one the configuration's own file states (or nobody), 2 for the file it
    extends, ..."""
    i = _origin_index(provenance, key)
    if i is None:
        return 1
    return i + (0 if provenance[0][0] == SET_ORIGIN else 1)


def given_with_set(exc: ConfigError, provenance) -> ConfigError:
    """``exc`` with "(given with --set)" appended where the key it names was given with --set (a key, or a table
    only --set created, such as a misspelt ``trackr`` of ``trackr.angular``)."""
    if not provenance or provenance[0][0] != SET_ORIGIN or str(exc).endswith("(given with --set)"):
        return exc
    message = str(exc)
    forms = set()

    def walk(node, parts):
        for k, v in (node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()):
            here = parts + [str(k)]
            if _origin_index(provenance, ".".join(here)) == 0:  # this key (or table) exists only through --set
                forms.add(".".join(here))
                forms.add(re.sub(r"\.(\d+)(?=\.|$)", r"[\1]", ".".join(here)))
            walk(v, here)

    walk(provenance[0][1], [])
    if any(f": {f}:" in message or f": {f}." in message or f": {f}[" in message or message.endswith(f": {f}")
           for f in forms):
        return ConfigError(f"{message} (given with --set)")
    return exc


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _load_with_extends(path: Path, seen: list) -> tuple[dict, list, list]:
    """The TOML table of ``path`` with its ``extends`` chain merged in; the chain of files (this one first); each
    file's own table, nearest first, as ``(path, table)`` (the provenance of every key)."""
    if len(seen) >= MAX_EXTENDS:
        raise ConfigError(f"{path}: extends: more than {MAX_EXTENDS} files deep")
    if path.resolve() in [p.resolve() for p in seen]:
        raise ConfigError(f"{seen[-1]}: extends: {path} extends itself (through {' -> '.join(map(str, seen))})")
    data = _read_toml(path)
    base = data.pop("extends", None)
    if base is None:
        return data, [path], [(path, data)]
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"{path}: extends: expected a file name or \"default\" (the built-in configuration)")
    base_path = default_config_path() if base.strip() == "default" else (path.parent / base).resolve()
    if not base_path.exists():
        raise ConfigError(f"{path}: extends: no such configuration file {base_path}")
    merged, chain, own = _load_with_extends(base_path, seen + [path])
    return _merge(merged, data), [path] + chain, [(path, data)] + own


def _apply_set(data: dict, item: str, path, lenient: bool = False) -> None:
    """Set the dotted key of ``item`` in ``data``; ``lenient``: into a table of the --set items alone (the
    provenance), where an index makes a list entry rather than reaching into one."""
    if lenient:
        key, _, text = str(item).partition("=")
        node, parts = data, [p for p in key.strip().split(".") if p]
        for part in parts[:-1]:
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                nxt = node[part] = {}
            node = nxt
        if parts:
            node[parts[-1]] = text
        return
    key, sep, text = str(item).partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE, for example --set 'tracker.angular=25 urad'")
    try:
        value = tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    node, parts = data, key.split(".")
    for i, part in enumerate(parts[:-1]):
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ConfigError(f"--set {key}: {'.'.join(parts[:i])} has {len(node)} entries; {part!r} is not one")
            node = node[int(part)]
            continue
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, (dict, list)):
            raise ConfigError(f"--set {key}: {'.'.join(parts[:i + 1])} is a value, not a table")
        node = nxt
    if isinstance(node, list):
        raise ConfigError(f"--set {key}: name a key inside an entry of {'.'.join(parts[:-1])}")
    node[parts[-1]] = value  # checked with the rest by parse_config (unknown keys, units)


def _read_toml(path: Path) -> dict:
    if not path.exists():
        raise ConfigError(f"{path}: no such configuration file")
    try:
        if path.stat().st_size > MAX_CONFIG_BYTES:
            raise ConfigError(f"{path}: larger than {MAX_CONFIG_BYTES} bytes; not a configuration")
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the file ({exc.strerror or type(exc).__name__})") from None
    raw = raw[3:] if raw.startswith(b"\xef\xbb\xbf") else raw
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise ConfigError(f"{path}: line {line}: byte 0x{raw[exc.start]:02X} at byte offset {exc.start} is not UTF-8; "
                          "save the file as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML ({_printable(exc)})") from None
    except RecursionError:
        raise ConfigError(f"{path}: invalid TOML (nested too deeply)") from None
    return data


def parse_config(data: dict, path=None, provenance: list | None = None) -> SimulationConfig:
    r = Reader(data, path, provenance=provenance)
    fmt = r.raw("format")
    if fmt != CONFIG_FORMAT:
        raise ConfigError(f"{r.where('format')}: expected \"{CONFIG_FORMAT}\", got {fmt!r}")
    r.check_keys(SCHEMA[""], "a configuration")
    for table in [t for t in SCHEMA if t and t not in ARRAY_TABLES and "." not in t]:  # every table; [scales.x]: _scales
        if r.has(table) and table != "placement":
            r.sub(table).check_keys(SCHEMA[table], f"[{table}]")
    _placement(r)
    _report_fields(r)
    for table in ARRAY_TABLES:
        entries = data.get(table, [])
        if not isinstance(entries, list) or not all(isinstance(x, dict) for x in entries):
            raise ConfigError(f"{r.where(table)}: expected [[{table}]] tables")
        for i, x in enumerate(entries):
            Reader(x, path, f"{table}[{i}].", provenance).check_keys(SCHEMA[table], f"[[{table}]]")
    for name in ("name", "description", "machine"):
        if r.has(name) and not isinstance(r.raw(name), str):
            raise ConfigError(f"{r.where(name)}: expected a string, got {r.raw(name)!r}")
    machine = str(r.raw("machine", "XFYZ"))
    try:
        machine = check_code(machine)
    except ConfigError as exc:
        raise ConfigError(f"{r.where('machine')}: {exc}") from None
    rotary, rotary_angles = _rotary(r, machine)
    cfg = Configuration.parse(machine, rotary)
    m = r.sub("mesh", required=True)
    ranges, step = {}, {}
    for a in AXES:
        v = m.raw(a)
        if not (isinstance(v, list) and len(v) == 2):
            raise ConfigError(f"{m.where(a)}: expected [low, high], e.g. [\"800 mm\", \"1200 mm\"]")
        ranges[a] = (to_unit(v[0], "mm", m.where(a)), to_unit(v[1], "mm", m.where(a)))
        if not ranges[a][1] >= ranges[a][0]:
            raise ConfigError(f"{m.where(a)}: low must not exceed high")
        if max(abs(ranges[a][0]), abs(ranges[a][1])) > MAX_LENGTH:
            raise ConfigError(f"{m.where(a)}: beyond {MAX_LENGTH:g} mm; not a machine tool's travel")
        key = f"step_{a}" if m.has(f"step_{a}") else "step"
        step[a] = to_unit(m.raw(key), "mm", m.where(key))
        if not step[a] > 0:
            raise ConfigError(f"{m.where(key)}: the mesh step must be positive")
        if (ranges[a][1] - ranges[a][0]) / step[a] > MAX_MESH_POINTS:
            raise ConfigError(f"{m.where(key)}: more than {MAX_MESH_POINTS} steps along {a}")
    _pivots_near(r, rotary, ranges)
    n_mesh = int(np.prod([round((ranges[a][1] - ranges[a][0]) / step[a]) + 1 for a in AXES]))
    n_mesh *= int(np.prod([len(v) for v in rotary_angles.values()])) if rotary_angles else 1
    if n_mesh > MAX_MESH_POINTS:
        raise ConfigError(f"{m.where('step')}: {n_mesh} mesh points; at most {MAX_MESH_POINTS}")
    pl = r.sub("plan")
    tools_raw = pl.raw("tools", [["0 mm", "0 mm", "0 mm"]])
    if not isinstance(tools_raw, list) or not tools_raw:
        raise ConfigError(f"{pl.where('tools')}: expected at least one tool offset [tx, ty, tz]")
    tools = []
    for i, t in enumerate(tools_raw):
        if not (isinstance(t, list) and len(t) == 3):
            raise ConfigError(f"{pl.where('tools')}[{i}]: expected [tx, ty, tz]")
        tools.append([to_unit(v, "mm", f"{pl.where('tools')}[{i}]") for v in t])
        if max(abs(v) for v in tools[-1]) > MAX_LENGTH:
            raise ConfigError(f"{pl.where('tools')}[{i}]: beyond {MAX_LENGTH:g} mm; not a tool offset")
    measurand_tool = None
    if r.has("measurand"):
        ms = r.sub("measurand")
        if ms.has("tool"):
            t = ms.raw("tool")
            if not (isinstance(t, list) and len(t) == 3):
                raise ConfigError(f"{ms.where('tool')}: expected [tx, ty, tz], the tool offset at which the compensated "
                                  "machine is evaluated")
            measurand_tool = [to_unit(v, "mm", f"{ms.where('tool')}[{i}]") for i, v in enumerate(t)]
            if max(abs(v) for v in measurand_tool) > MAX_LENGTH:
                raise ConfigError(f"{ms.where('tool')}: beyond {MAX_LENGTH:g} mm; not a tool offset")
    runs = pl.number("runs", 2, int, low=1)
    if n_mesh * len(tools) * runs > MAX_PLAN_ROWS:
        raise ConfigError(f"{pl.where('runs')}: {n_mesh} mesh points x {len(tools)} tools x {runs} runs is more than "
                          f"{MAX_PLAN_ROWS} measured points")
    plan_times = {}
    for key, default, low in (("feed", "2000 mm/min", None), ("stop_time", "12 s", 0.0), ("tool_change_time", "120 s", 0.0),
                              ("station_change_time", "10 min", 0.0)):
        plan_times[key] = pl.quantity(key, "mm/s" if key == "feed" else "s", default)
        if (low is None and not plan_times[key] > 0) or (low is not None and plan_times[key] < low):
            raise ConfigError(f"{pl.where(key)}: must be {'positive' if low is None else 'zero or positive'}")
    tr = r.sub("tracker", required=True)
    mount = tr.raw("mount", "table")
    if mount not in ("table", "bed"):
        raise ConfigError(f"{tr.where('mount')}: expected \"table\" (the tracker on the workpiece side, moving with it) "
                          f"or \"bed\", got {mount!r:.40}")
    if mount == "bed" and cfg.workpiece:
        raise ConfigError(f"{tr.where('mount')}: a tracker on the bed with the reflector in the spindle sees none of the "
                          f"workpiece-side axes of {machine} ({', '.join(a.upper() for a in cfg.workpiece)}); stand it "
                          "on the table (mount = \"table\")")
    stations = _stations(data.get("stations", []), path, provenance)
    if stations:
        stated = [k for k in POSE_KEYS if tr.has(k)]
        if stated:
            raise ConfigError(f"{tr.where(stated[0])}: with [[stations]], each station states its own pose; [tracker] "
                              "keeps only the uncertainties (angular, distance, distance_per_length)")
        pose = stations[0].tracker_pose
    else:
        pose = _pose(tr)
    if runs * len(stations or [None]) * n_mesh * len(tools) > MAX_PLAN_ROWS:
        raise ConfigError(f"{r.where('stations')}: {len(stations)} stations x {n_mesh} mesh points x {len(tools)} tools x "
                          f"{runs} runs is more than {MAX_PLAN_ROWS} measured points")
    mt = r.sub("machine_tool")
    ge = r.sub("geometric_errors")
    geometric: dict = {"seed": ge.number("seed", 1, int, low=0)}
    if ge.has("coefficients"):
        co = ge.sub("coefficients")
        coefs = {}
        for name, vals in co.data.items():
            if name not in COMPONENT_ERRORS:
                raise ConfigError(f"{co.where(name)}: unknown component error; expected one of {', '.join(COMPONENT_ERRORS)}")
            if not isinstance(vals, list):
                raise ConfigError(f"{co.where(name)}: expected a list of coefficients, e.g. [\"2 um\", \"-1 um\"]")
            unit = "mm" if name[0] == "d" else "rad"
            coefs[name] = [to_unit(v, unit, co.where(name)) for v in vals]
            _plausible("length error" if unit == "mm" else "angular error", coefs[name], co.where(name))
        geometric["coefficients"] = coefs
        sq = ge.sub("squareness")
        geometric["squareness"] = {k: sq.quantity(k, "rad") for k in sq.data}
        for k in geometric["squareness"]:
            if k not in SQUARENESS:
                raise ConfigError(f"{sq.where(k)}: unknown squareness; expected one of {SQUARENESS}")
            _plausible("angular error", [geometric["squareness"][k]], sq.where(k))
    else:
        for key, unit, default in (("translational", "mm", ["8 um", "3 um", "1.5 um"]),
                                   ("angular", "rad", ["10 urad", "5 urad", "2.5 urad"])):
            vals = ge.raw(key, default)
            if not isinstance(vals, list) or not vals:
                raise ConfigError(f"{ge.where(key)}: expected a list of standard deviations per order, e.g. {default}")
            geometric[key] = [to_unit(v, unit, ge.where(key)) for v in vals]
        geometric["squareness"] = ge.quantity("squareness", "rad", "30 urad")
        if min(geometric["translational"] + geometric["angular"] + [geometric["squareness"]]) < 0:
            raise ConfigError(f"{ge.where('')[:-1]}: a standard deviation must not be negative")
        _plausible("length error", geometric["translational"], ge.where("translational"))
        _plausible("angular error", geometric["angular"], ge.where("angular"))
        _plausible("angular error", [geometric["squareness"]], ge.where("squareness"))
    for key, unit, default in (("rotary_location", "mm", "20 um"), ("rotary_orientation", "rad", "30 urad"),
                               ("rotary_zero", "rad", "30 urad")):
        geometric[key] = ge.quantity(key, unit, default)
        if geometric[key] < 0:
            raise ConfigError(f"{ge.where(key)}: a standard deviation must not be negative")
        _plausible("length error" if unit == "mm" else "angular error", [geometric[key]], ge.where(key))
    if ge.has("rotary"):  # explicit location and zero errors by their ISO 230-7 names
        from .model import parameter_from_iso

        rt = ge.sub("rotary")
        named = {}
        for iso, v in rt.data.items():
            internal = parameter_from_iso(iso)
            if internal is None or internal[3] not in rotary:
                raise ConfigError(f"{rt.where(iso)}: not a location or zero error of this machine's rotary axes "
                                  f"(ISO 230-7 names such as EXOC, EYOC, EAOC, EBOC, ECOC for C)")
            named[internal] = rt.quantity(iso, "mm" if internal[0] == "d" else "rad")
            _plausible("length error" if internal[0] == "d" else "angular error", [named[internal]], rt.where(iso))
        geometric["rotary"] = named
    tref = r.quantity("reference_temperature", "K", "20 degC", absolute_temperature=True)
    sensors = []
    sensors_raw = data.get("sensors", [])
    for i, s in enumerate(sensors_raw):
        sr = Reader(s, path, f"sensors[{i}].", provenance)
        if "column" not in s or "attached_to" not in s:
            raise ConfigError(f"{sr.where('column')}: each [[sensors]] needs column and attached_to")
        for key in ("column", "attached_to"):
            if not isinstance(s[key], str):
                raise ConfigError(f"{sr.where(key)}: expected a string, got {s[key]!r:.60}")
        if not s["column"].isidentifier() or not s["column"].isascii() or s["column"] in COLUMNS:
            raise ConfigError(f"{sr.where('column')}: {s['column']!r:.60} is not a sensor column name (letters, digits "
                              "and _, not a column of points.csv such as x or time)")
        if s["column"] in [x["column"] for x in sensors_raw[:i]]:
            raise ConfigError(f"{sr.where('column')}: column {s['column']!r} is declared twice")
        if s["attached_to"].strip().lower() not in ATTACHED_TO:
            raise ConfigError(f"{sr.where('attached_to')}: expected 'x axis', 'y axis', 'z axis' or 'air', "
                              f"got {s['attached_to']!r:.60}")
        pos = s.get("position")
        sensor = Sensor(s["column"], s["attached_to"], None if pos is None else sr.quantity("position", "mm"))
        if sensor.position is not None and abs(sensor.position) > MAX_LENGTH:
            raise ConfigError(f"{sr.where('position')}: beyond {MAX_LENGTH:g} mm")
        start = sr.quantity("start", "K", "20 degC", absolute_temperature=True)
        rate = sr.quantity("rate", "K/s", "0 K/h")
        noise = sr.quantity("noise", "K", "0 K")
        spec = SensorSpec(sensor, start, rate, noise, sr.quantity("cycle_amplitude", "K", "0 K"),
                          sr.quantity("cycle_period", "s", "30 min"), sr.quantity("cycle_phase", "rad", "0 rad"),
                          noise_stated="noise" in s)
        for key in ("noise", "cycle_amplitude", "cycle_period"):
            if getattr(spec, key) < 0 or (key == "cycle_period" and not spec.cycle_period > 0):
                raise ConfigError(f"{sr.where(key)}: must be {'positive' if key == 'cycle_period' else 'zero or positive'}")
        if spec.noise > MAX_SENSOR_NOISE:
            raise ConfigError(f"{sr.where('noise')}: {spec.noise:g} K is not a plausible standard deviation of a "
                              f"temperature reading; expected 0 to {MAX_SENSOR_NOISE:g} K (a value in mK written as "
                              "K?)")
        sensors.append(spec)
    eff = r.sub("effects")
    effects = {
        "thermal": {a: eff.sub("thermal").quantity(a, "1/K") for a in eff.sub("thermal").data},
        "reversal": {a: eff.sub("reversal").quantity(a, "mm") for a in eff.sub("reversal").data},
        "drift": None,
    }
    for kind in ("thermal", "reversal"):
        for a in effects[kind]:
            if a not in AXES:
                raise ConfigError(f"{eff.where(kind)}.{a}: unknown axis; expected x, y or z")
            _plausible("expansion coefficient" if kind == "thermal" else "reversal", [effects[kind][a]],
                       eff.sub(kind).where(a))
    if eff.has("drift"):
        dv = eff.raw("drift")
        if not (isinstance(dv, list) and len(dv) == 3):
            raise ConfigError(f"{eff.where('drift')}: expected [vx, vy, vz], e.g. [\"4 um/h\", \"0 um/h\", \"0 um/h\"]")
        effects["drift"] = np.array([to_unit(v, "mm/s", eff.where("drift")) for v in dv])
        _plausible("tracker drift", effects["drift"], eff.where("drift"))
    physical = {}
    for key, (unit, attr, default) in PHYSICAL_INPUTS.items():
        table, name = key.split(".")
        physical[attr] = r.sub(table).quantity(name, unit, default)
        if attr != "cte" and physical[attr] < 0:  # a standard uncertainty (a CTE may be negative)
            raise ConfigError(f"{r.sub(table).where(name)}: a standard uncertainty must not be negative")
        problem = uncertainty_problem(key, physical[attr]) if key in UNCERTAINTIES else (
            cte_problem(physical[attr]))  # machine_tool.cte: the scales' CTE, as [scales.<axis>] states it
        if problem:  # the rule of recordings: what `simulate` writes must read back
            raise ConfigError(f"{r.sub(table).where(name)}: {problem}")
    scales = _scales(r, sensors)
    if scales and len(scales) == len(AXES) and config_states(data, "machine_tool.cte"):
        raise ConfigError(f"{r.where('machine_tool.cte')}: the scales' expansion coefficient is stated twice, here and "
                          f"in [scales.x], [scales.y] and [scales.z]; [machine_tool] cte is the CTE of the axes without a "
                          "[scales.<axis>] table: remove it (or one of the [scales] tables)")
    weights = None
    if r.has("weights"):
        w = r.sub("weights")
        weights = {}
        for name in w.data:
            if name not in WEIGHT_KEYS:
                raise ConfigError(f"{w.where(name)}: unknown key; [weights] takes {', '.join(WEIGHT_KEYS)}")
            weights[name] = w.quantity(name, PHYSICAL_INPUTS[WEIGHT_KEYS[name]][0])
            if weights[name] < 0:
                raise ConfigError(f"{w.where(name)}: a standard uncertainty must not be negative")
            problem = uncertainty_problem(WEIGHT_KEYS[name], weights[name])
            if problem:
                raise ConfigError(f"{w.where(name)}: {problem}")
    return SimulationConfig(
        name=str(r.raw("name", Path(path).stem if path else "simulation")),
        description=str(r.raw("description", "")),
        machine=machine,
        reference_temperature=tref,
        seed=r.number("seed", 1, int, low=0),
        mesh_ranges=ranges,
        mesh_step=step,
        runs=runs,
        tools=tools,
        **plan_times,
        pose=pose,
        **physical,
        weights=weights,
        measurand_tool=measurand_tool,
        stations=stations,
        scales=scales,
        rotary=rotary,
        rotary_angles=rotary_angles,
        rotary_harmonics=mt.number("rotary_harmonics", 0, int, low=0, high=6) if rotary else
        mt.number("rotary_harmonics", 0, int, low=0, high=0),
        mount=mount,
        max_degree=mt.number("max_degree", 3, int, low=1, high=9),
        geometric=geometric,
        sensors=sensors,
        effects=effects,
        source=data,
        path=path,
        provenance=provenance,
    )
