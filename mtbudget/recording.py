"""Read and write verification recordings (docs/recording-format.md).

A recording is a folder with ``recording.toml`` and ``points.csv``.  Column
units are anything the one quantity grammar accepts (:func:`mtbudget.units.parse_unit`);
values are converted once to the internal system (mm, s, K).  The reader is
strict: every cell is checked (count per row, number, range), the file must be
UTF-8, and its size is bounded before anything is allocated.  Every problem
raises :class:`RecordingError` naming the file, the line (1-based, the header
is line 1) and the column, or the key of ``recording.toml``.
"""

from __future__ import annotations

import codecs
import csv
import difflib
import math
import re
from array import array
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import RecordingError, make_folder
from .plan import Plan, Scale, Sensor, T20
from .units import ABSOLUTE_TEMPERATURE, Q_, display, parse_unit, to_internal, ureg

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

FORMAT = "mtbudget-recording/1"
#: several stations (docs/recording-format.md, "Format 2: several stations")
FORMAT2 = "mtbudget-recording/2"
#: five-axis machines: format 2 plus rotary axes (docs/recording-format.md, "Format 3: rotary axes")
FORMAT3 = "mtbudget-recording/3"
FORMATS = (FORMAT, FORMAT2, FORMAT3)
_HEADER = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[(.*)\])?\s*$")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")

#: required columns: name -> (dimension, internal unit) ; None = a bare count/sign
COLUMNS = {
    "point": None,
    "run": None,
    "time": ("[time]", "s"),
    "x": ("[length]", "mm"),
    "y": ("[length]", "mm"),
    "z": ("[length]", "mm"),
    "dir_x": None,
    "dir_y": None,
    "dir_z": None,
    "tool_x": ("[length]", "mm"),
    "tool_y": ("[length]", "mm"),
    "tool_z": ("[length]", "mm"),
    "lt_x": ("[length]", "mm"),
    "lt_y": ("[length]", "mm"),
    "lt_z": ("[length]", "mm"),
}

#: size guards, checked before the rows are parsed (read_recording takes other limits)
MAX_ROWS = 1_000_000
MAX_COLUMNS = 256
MAX_LINE_BYTES = 65_536
MAX_TOML_BYTES = 1_048_576
MIN_ROWS = 3  # three points fix the tracker pose (6 unknowns); the identification checks the rest
#: plausible ranges of the values (internal units); outside them a value is a unit or typing mistake
MAX_INDEX = 999_999_999  # point and run: whole numbers 0 .. MAX_INDEX
MAX_LENGTH = 1.0e6  # mm: |x|, |tool_x|, |lt_x| ... at most 1 km
MAX_TIME = 1.0e8  # s: about three years
#: the stated standard uncertainties (k = 1) of recording.toml and of a configuration (every key that states
#: one: [tracker], [[stations]], [weights], [machine_tool] repeatability, the sources' parameters linked to them,
#: --set): key -> (internal unit, display unit, low, high): positive and within low .. high, or, where low is 0,
#: zero or at most high.  One rule for the four upper bounds: several times the poorest instrument or machine of
#: its kind (laser trackers state about 1-25 urad per angle, 0.5-15 um and 0.3-6 um/m; a machine tool a tracker
#: verifies repeats within about 0.5-25 um), and below a thousand times the smallest value in use, so a value
#: written in the next unit up (mm for um, mrad for urad, mm/m for um/m) is refused, never run.  The lower
#: bounds only keep the identification's weights finite (1e-300 would overflow them).  docs/configuration.md
#: and docs/recording-format.md state the same bounds.
UNCERTAINTIES = {
    "tracker.angular": ("rad", "urad", 1e-12, 200e-6),
    "tracker.distance": ("mm", "um", 1e-9, 0.05),
    "tracker.distance_per_length": ("mm/mm", "um/m", 0.0, 50e-6),
    "machine_tool.repeatability": ("mm", "um", 1e-9, 0.1),
}
#: the simulated machine's error magnitudes and physical amplitudes a configuration states ([geometric_errors], its
#: coefficients, squareness and rotary location, orientation and zero errors, [effects], a rotary axis' pivot is
#: bounded apart, by the travel), by the rule of UNCERTAINTIES: several times the poorest machine of its kind, below
#: a thousand times the smallest value in use, so a value written in the next unit up ("8 mm" for "8 um", "50 mrad"
#: or "50 deg" for "50 urad") is refused, never simulated.  kind -> (internal unit, display unit, the largest
#: |value|, why).  The sources' parameters declare theirs (``Source.plausible``, mtbudget.contracts).
MAGNITUDES = {
    "length error": ("mm", "um", 2.0, "a machine tool's positioning, straightness and rotary location errors are "
                                      "1-100 um per metre of travel: up to about 1 mm on an uncompensated 10 m gantry"),
    "angular error": ("rad", "urad", 1e-3, "a machine tool's angular, squareness, orientation and zero errors are "
                                           "2-200 urad"),
    "reversal": ("mm", "um", 0.5, "a linear axis' reversal (backlash) is 1-50 um, up to 250 um on a large "
                                  "rack-and-pinion gantry"),
    "expansion coefficient": ("1/K", "um/(m*K)", 100e-6, "a machine axis or its scale expands by -1-25 "
                                                          "um/(m*K): glass ceramic 0, steel 11.5, aluminium 23"),
    "tracker drift": ("mm/s", "um/h", 0.2 / 3600, "a laser tracker drifts by 0-20 um/h"),
}


#: a rotary axis' pivot lies at most this many times the largest linear travel (and at least PIVOT_FLOOR mm) outside
#: the box of the verified volume and the machine zero: a table or a trunnion sits inside the machine, so a pivot
#: metres beyond the travel is a unit mistake ("50 m" for "50 mm"), which would put every angle's lever arm in error
PIVOT_REACH = 5.0
PIVOT_FLOOR = 1000.0  # mm


def pivot_problem(pivot, low, high) -> str | None:
    """None when a rotary axis' ``pivot`` (mm) lies within :data:`PIVOT_REACH` times the largest travel (at least
    :data:`PIVOT_FLOOR`) of the box from ``low`` to ``high`` (the verified volume's commanded x, y, z, mm) and the
    machine zero, otherwise what is wrong, with the bound and its reason (configurations and recordings alike)."""
    lo, hi = np.minimum(np.asarray(low, float), 0.0), np.maximum(np.asarray(high, float), 0.0)
    travel = float(np.max(np.asarray(high, float) - np.asarray(low, float)))
    reach = max(PIVOT_REACH * travel, PIVOT_FLOOR)
    p = np.asarray(pivot, float)
    outside = float(np.linalg.norm(np.maximum(lo - p, 0.0) + np.maximum(p - hi, 0.0)))
    if outside <= reach:
        return None
    return (f"{outside:.6g} mm outside the verified volume (its commanded x, y, z and the machine zero) is not a "
            f"plausible pivot; expected within {reach:g} mm of it ({PIVOT_REACH:g} times the largest travel, "
            f"{travel:g} mm, at least {PIVOT_FLOOR:g} mm: a rotary table or trunnion sits inside the machine; a value "
            "in the next unit up?)")


def magnitude_problem(kind: str, value: float) -> str | None:
    """None when ``value`` (internal unit) is a plausible ``kind`` (a key of :data:`MAGNITUDES`) of a simulated
    machine, otherwise what is wrong, with the plausible range and its reason."""
    unit, disp, high, why = MAGNITUDES[kind]
    if math.isfinite(value) and abs(value) <= high:
        return None
    shown = display(value, unit, disp)
    return (f"{shown:g} {disp} is not a plausible {kind}; expected at most {display(high, unit, disp):g} {disp} in "
            f"magnitude ({why}; a value in the next unit up?)")
ATTACHED_TO = ("x axis", "y axis", "z axis", "air")
#: keys of recording.toml this version reads (others are kept in Recording.extra)
KNOWN_KEYS = ("format", "name", "machine", "description", "reference_temperature", "tracker", "machine_tool",
              "sensors", "scales", "ignore_columns", "stations", "rotary", "report")
#: [report]: what a laboratory states on its statement and DCC (all optional text), in a configuration (the a priori
#: statement of a run) and in recording.toml (the a posteriori statement of a recording) alike
REPORT_KEYS = ("laboratory", "instrument", "machine", "customer", "operator", "date", "traceability", "certificate",
               "country", "location")
REPORT_INSTRUMENT_KEYS = ("model", "serial", "calibration")
#: [report] location: where the verification is performed (the DCC 3.3.0 performanceLocation values)
PERFORMANCE_LOCATIONS = ("laboratory", "customer", "laboratoryBranch", "customerBranch", "other")
#: format 3: the commanded angle of each rotary axis and, optionally, the direction it last approached from
ROTARY_COLUMNS = {r: ("[angle]", "rad") for r in "abc"}
ROTARY_DIRECTIONS = {f"dir_{r}": None for r in "abc"}
#: format 3: the keys of a [rotary.<A|B|C>] table, and where the tracker stands
ROTARY_KEYS = ("pivot", "direction", "description")
TRACKER_MOUNTS = ("table", "bed")
MAX_ANGLE = 200.0 * math.pi  # rad: 100 turns; beyond, a commanded angle is a unit or typing mistake
#: format 2 only: the columns a recording from several stations adds
COLUMNS_V2 = {"station": None, "lt_range": ("[length]", "mm")}
#: a station's measurement kind: "xyz" (a laser tracker: range and two angles, Cartesian in its own frame) or
#: "range" (a tracking interferometer: a distance with an unknown dead-path offset)
STATION_KINDS = ("xyz", "range")
#: the keys of a [[stations]] table
STATION_KEYS = ("id", "kind", "angular", "distance", "distance_per_length", "description")
#: distinct measured positions a station needs for its own unknowns: an xyz station's pose (6) needs 3 points
#: off one line, a range station's position and dead path (4) need 4 ranges off one plane
MIN_STATION_POINTS = {"xyz": 3, "range": 4}
#: plausible nominal CTE of an axis scale (1/K): glass ceramics and Invar near 0, steel 11.5, aluminium 23
CTE_RANGE = (-2e-6, 30e-6)


def cte_problem(cte: float) -> str | None:
    """None when ``cte`` (1/K) is a plausible expansion coefficient of a machine's axis or scale (:data:`CTE_RANGE`:
    glass ceramic about 0, steel 11.5, aluminium 23 um/(m*K)); otherwise what is wrong.  The one rule of every key
    that states it: [scales.<axis>] cte in a configuration and a recording, [machine_tool] cte and the sources'
    cte linked to it."""
    if math.isfinite(cte) and CTE_RANGE[0] <= cte <= CTE_RANGE[1]:
        return None
    return (f"{cte * 1e6:g} um/(m*K) is not a plausible expansion coefficient of a machine's axis or scale (expected "
            f"{CTE_RANGE[0] * 1e6:g} to {CTE_RANGE[1] * 1e6:g} um/(m*K): glass ceramic 0, steel 11.5, aluminium 23)")

#: bytes that are common non-UTF-8 characters of real exports (Latin-1 / Windows-1252)
_LATIN1_HINTS = {0xB5: "µ (micro)", 0xB0: "° (degree)", 0xB2: "² (squared)", 0xB3: "³ (cubed)", 0xE4: "ä", 0xF6: "ö",
                 0xFC: "ü", 0xDF: "ß", 0xE9: "é", 0xE8: "è", 0xF1: "ñ", 0xC4: "Ä", 0xD6: "Ö", 0xDC: "Ü"}
_BOMS = ((codecs.BOM_UTF32_LE, "UTF-32"), (codecs.BOM_UTF32_BE, "UTF-32"), (codecs.BOM_UTF16_LE, "UTF-16"),
         (codecs.BOM_UTF16_BE, "UTF-16"))
_INT_CELL = re.compile(r"\s*[+-]?[0-9]+\s*")
_FRACTION_CELL = re.compile(r"[0-9]+(?:[eE][+-]?[0-9]+)?\s*")


@dataclass(frozen=True)
class Station:
    """One station of a recording: its id (the ``station`` column), its kind and its stated uncertainties (k = 1).

    ``angular`` is None for a ``range`` station (it measures no angle); ``distance`` (mm) and
    ``distance_per_length`` (mm/mm) state u_r = distance + distance_per_length * r.
    """

    id: int
    kind: str  # "xyz" or "range"
    angular: float | None  # rad
    distance: float  # mm
    distance_per_length: float  # mm/mm
    description: str = ""

    @property
    def unknowns(self) -> int:
        """Its own unknowns: a pose (6) for an xyz station, a position and a dead-path offset (4) for a range one."""
        return 6 if self.kind == "xyz" else 4

    @property
    def label(self) -> str:
        return f"station {self.id} ({self.kind})"


@dataclass
class Recording:
    """A verification recording in internal units.

    Format 2 (several stations) adds ``station`` (M,) the station of every row, ``stations`` the
    declared :class:`Station` tables and ``lt_range`` (M,) the range of every row of a range station;
    ``lt`` then holds each xyz row in its own station's frame, NaN on the rows of range stations (and
    ``lt_range`` is NaN on the rows of xyz stations).  A format 1 recording is one xyz station.
    """

    name: str
    machine: str
    plan: Plan
    lt: np.ndarray  # (M, 3) mm, tracker frame
    angular: float  # rad, per angle (k = 1)
    distance: float  # mm
    distance_per_length: float  # mm/mm
    repeatability: float  # mm
    reference_temperature: float = T20  # K
    description: str = ""
    extra: dict = field(default_factory=dict)
    path: Path | None = None
    #: columns of points.csv left out of the model: listed in ignore_columns, free text (no unit), or a
    #: quantity no [[sensors]] table declares (its cells checked as numbers all the same)
    unused_columns: list = field(default_factory=list)
    station: np.ndarray | None = None  # (M,) int: the station of every row (format 2)
    stations: list = field(default_factory=list)  # [Station]: format 2's [[stations]]; empty: one xyz station
    lt_range: np.ndarray | None = None  # (M,) mm: the range of every row of a range station, else NaN
    format_version: int = 1
    mount: str = "table"  # format 3: where the tracker stands ("table": on the workpiece side, moving with it)
    #: [report]: the laboratory's fields of the statement (laboratory, instrument, customer ...); empty: not stated
    report: dict = field(default_factory=dict)

    @property
    def rotary(self) -> dict:
        """The rotary axes' nominal geometry (letter -> machine.RotaryAxis); empty for a three-axis machine."""
        return self.plan.rotary

    def __len__(self):
        return len(self.plan)

    def station_list(self) -> list:
        """The stations (a format 1 recording: one xyz station, id 1, with the [tracker] uncertainties)."""
        if self.stations:
            return list(self.stations)
        return [Station(1, "xyz", self.angular, self.distance, self.distance_per_length)]

    def station_ids(self) -> np.ndarray:
        """(M,) the station of every row."""
        if self.station is None:
            return np.full(len(self), self.station_list()[0].id, dtype=np.int64)
        return self.station

    @property
    def several_stations(self) -> bool:
        """True when the recording is more than one xyz station (several stations, or any range station)."""
        st = self.station_list()
        return len(st) > 1 or st[0].kind != "xyz"

    def fixed_inputs(self) -> dict:
        """What the identification takes as known: the nominal expansion of the stated scales (``[scales]``)."""
        return self.plan.nominal_expansion(self.reference_temperature)

    @property
    def thermal_correction(self) -> str:
        """One sentence on the correction to the reference temperature applied to this recording."""
        tref = f"{self.reference_temperature - 273.15:g} degC"
        if not self.plan.scales:
            return (f"no correction to {tref} applied: recording.toml states no [scales] (nominal expansion "
                    f"coefficients), so the identified errors include the scales' expansion at the test temperatures")
        parts = [f"{a} {sc.cte * 1e6:g} um/(m*K) about {sc.fixed_point:g} mm" for a, sc in sorted(self.plan.scales.items())]
        return f"scales corrected to {tref}: " + ", ".join(parts)


def _quantity(text, *, path, key, dim, unit, nonnegative=False, absolute_temperature=False):
    """One value of recording.toml in internal units, through the one strict parser; errors name file and key."""
    value = to_internal(text, unit, where=key, absolute_temperature=absolute_temperature,
                        error=lambda m: RecordingError(m.split(": ", 1)[1] if m.startswith(key + ": ") else m, path, key=key))
    if nonnegative and value < 0:
        raise RecordingError(f"{text!r} is negative; a standard uncertainty must not be negative", path, key=key)
    return value


def _decode_error(exc: UnicodeDecodeError, raw: bytes, offset: int, path, line: int, column=None, encoding="utf-8"):
    """A RecordingError for bytes that are not ``encoding``: the byte, its offset in the file, a hint."""
    byte = raw[exc.start]
    hint = _LATIN1_HINTS.get(byte)
    what = (f"byte 0x{byte:02X} at byte offset {offset + exc.start} is not {encoding.upper()}"
            + (f"; it is {hint} in Latin-1/Windows-1252, a common export encoding" if hint else ""))
    return RecordingError(f"{what}: save the file as UTF-8 (with or without BOM)", path, line=line, column=column)


def _read_toml(path: Path) -> dict:
    try:
        size = path.stat().st_size
        if size > MAX_TOML_BYTES:
            raise RecordingError(f"{size} bytes; a recording.toml has at most {MAX_TOML_BYTES}", path)
        raw = path.read_bytes()
    except OSError as exc:
        raise RecordingError(f"cannot read the file ({exc.strerror or type(exc).__name__})", path) from None
    for bom, name in _BOMS:
        if raw.startswith(bom):
            raise RecordingError(f"the file is {name} (byte order mark at byte offset 0): save it as UTF-8", path, line=1)
    if raw.startswith(codecs.BOM_UTF8):
        raw = raw[len(codecs.BOM_UTF8):]
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise _decode_error(exc, raw, 0, path, line) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RecordingError(f"invalid TOML ({str(exc).splitlines()[0]})", path) from None
    except RecursionError:
        raise RecordingError("invalid TOML (nested too deeply)", path) from None


def _string(meta, key, path, default=None):
    value = meta.get(key, default)
    if not isinstance(value, str):
        raise RecordingError(f"expected a string, got {type(value).__name__} {value!r:.60}", path, key=key)
    return value


def _table(meta, key, path) -> dict:
    value = meta.get(key)
    if value is None:
        raise RecordingError(f"missing table [{key}]", path, key=key)
    if not isinstance(value, dict):
        raise RecordingError(f"expected a table [{key}], got {type(value).__name__}", path, key=key)
    return value


def uncertainty_problem(key: str, value: float) -> str | None:
    """None when ``value`` (internal unit) is a plausible stated standard uncertainty ``key`` (a key of
    :data:`UNCERTAINTIES`), otherwise what is wrong; configurations apply the same rule."""
    unit, disp, low, high = UNCERTAINTIES[key]
    if low > 0 and not value > 0:
        return f"must be positive, got {display(value, unit, disp):g} {disp}"
    if value < 0:
        return f"a standard uncertainty must not be negative, got {display(value, unit, disp):g} {disp}"
    if value and not low <= value <= high:
        lo, hi = display(low, unit, disp), display(high, unit, disp)
        return (f"{display(value, unit, disp):g} {disp} is not a plausible standard uncertainty; expected "
                f"{'0 or ' if low == 0 else ''}{lo:g} to {hi:g} {disp}")
    return None


def _uncertainty(table: dict, key: str, path) -> float:
    """A stated standard uncertainty (``tracker.angular`` ...): present, a quantity, within its plausible range."""
    section, name = key.split(".")
    if name not in table:
        raise RecordingError(f"missing key {key}", path, key=key)
    value = _quantity(table[name], path=path, key=key, dim=None, unit=UNCERTAINTIES[key][0], nonnegative=True)
    problem = uncertainty_problem(key, value)
    if problem:
        raise RecordingError(f"{table[name]!r:.60}: {problem}", path, key=key)
    return value


def _no_misspelt_keys(table: dict, known, prefix: str, path):
    """Keys mtbudget does not read are kept (``Recording.extra``), but one that resembles a key it reads is
    a typo that would silently change the result (``reference_temprature``): an error naming both."""
    import difflib

    for k in table:
        if k in known or not isinstance(k, str):
            continue
        close = difflib.get_close_matches(k, list(known), n=1, cutoff=0.8)
        if close:
            raise RecordingError(f"unknown key {k!r:.40}; did you mean {close[0]!r}? (keys that resemble none mtbudget "
                                 "reads are kept and ignored)", path, key=prefix + k)


def report_problem(data: dict) -> tuple | None:
    """The first problem of a [report] table's values (its keys checked by the caller): (key below [report], what is
    wrong), None when every value is sound.  The configuration's reader and recording.toml's share it."""
    import datetime

    for k in REPORT_KEYS:
        if k not in data or k == "instrument":
            continue
        v = data[k]
        if not isinstance(v, str) or not v.strip():
            return k, "expected a non-empty string" + (' (a date as "2026-11-25", quoted)' if k == "date" else "")
    if "date" in data:
        try:
            if not re.fullmatch(r"\d{4}-\d{2}-\d{2}", data["date"].strip()):  # xs:date's form, not ISO's others
                raise ValueError(data["date"])
            datetime.date.fromisoformat(data["date"].strip())
        except ValueError:
            return "date", f"expected a date YYYY-MM-DD, got {data['date']!r:.40}"
    if "location" in data and data["location"] not in PERFORMANCE_LOCATIONS:
        return "location", (f"where the verification is performed: one of {', '.join(map(repr, PERFORMANCE_LOCATIONS))} "
                            "(the DCC's performanceLocation)")
    if "country" in data and not re.fullmatch(r"[A-Z]{2}", data["country"]):
        return "country", "expected an ISO 3166-1 code of two capital letters (DE, ES, FR ...)"
    if "instrument" in data:
        ins = data["instrument"]
        if not isinstance(ins, dict):
            return "instrument", "expected a table: model, serial, calibration"
        for k, v in ins.items():
            if k in REPORT_INSTRUMENT_KEYS and (not isinstance(v, str) or not v.strip()):
                return f"instrument.{k}", "expected a non-empty string"
    return None


def _report(meta, path) -> dict:
    """recording.toml's optional [report] table, strict: every key known, every value sound (:func:`report_problem`);
    errors name the file and the key."""
    import difflib

    if "report" not in meta:
        return {}
    rep = meta["report"]
    if not isinstance(rep, dict):
        raise RecordingError(f"expected a table [report], got {type(rep).__name__}", path, key="report")
    for prefix, table, known in (("report.", rep, REPORT_KEYS),
                                 ("report.instrument.", rep.get("instrument") if isinstance(rep.get("instrument"), dict)
                                  else {}, REPORT_INSTRUMENT_KEYS)):
        for k in table:
            if k not in known:
                close = difflib.get_close_matches(str(k), list(known), n=1)
                hint = f"did you mean {close[0]!r}?" if close else f"[{prefix[:-1]}] takes {', '.join(known)}"
                raise RecordingError(f"unknown key {str(k)!r:.40}; {hint}", path, key=prefix + str(k))
    bad = report_problem(rep)
    if bad:
        raise RecordingError(bad[1], path, key="report." + bad[0])
    return {k: (dict(v) if isinstance(v, dict) else v.strip() if k == "date" else v) for k, v in rep.items()}


def _sensors(meta, path) -> list:
    raw = meta.get("sensors", [])
    if not isinstance(raw, list) or not all(isinstance(s, dict) for s in raw):
        raise RecordingError("expected [[sensors]] tables", path, key="sensors")
    sensors, seen = [], set()
    for i, s in enumerate(raw):
        where = f"sensors[{i}]"
        for key in ("column", "attached_to"):
            if key not in s:
                raise RecordingError(f"missing key {key!r}; each [[sensors]] table needs 'column' and 'attached_to'",
                                     path, key=f"{where}.{key}")
            if not isinstance(s[key], str):
                raise RecordingError(f"expected a string, got {type(s[key]).__name__} {s[key]!r:.60}", path,
                                     key=f"{where}.{key}")
        column = s["column"]
        if not _NAME.match(column):
            raise RecordingError(f"{column!r:.60} is not a column name (letters, digits and _; for example \"T_x\")",
                                 path, key=f"{where}.column")
        if column in COLUMNS or column in COLUMNS_V2:
            raise RecordingError(f"{column!r} is a column of points.csv mtbudget reads, not a sensor", path,
                                 key=f"{where}.column")
        if column in seen:
            raise RecordingError(f"column {column!r} is declared by two [[sensors]] tables", path, key=f"{where}.column")
        seen.add(column)
        if s["attached_to"].strip().lower() not in ATTACHED_TO:
            raise RecordingError(f"{s['attached_to']!r:.60}: expected 'x axis', 'y axis', 'z axis' or 'air'", path,
                                 key=f"{where}.attached_to")
        pos = s.get("position")
        if pos is not None:
            pos = _quantity(pos, path=path, key=f"{where}.position", dim="[length]", unit="mm")
            if abs(pos) > MAX_LENGTH:
                raise RecordingError(f"{s['position']!r} is not a plausible position (at most {MAX_LENGTH:g} mm)", path,
                                     key=f"{where}.position")
        sensors.append(Sensor(column, s["attached_to"], pos))
    return sensors


def _scales(meta, path, sensors) -> dict:
    """``[scales.<axis>]``: the nominal CTE and fixed point of each axis scale whose expansion is corrected."""
    raw = meta.get("scales")
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise RecordingError(f"expected a table [scales], got {type(raw).__name__}", path, key="scales")
    out = {}
    for axis, t in raw.items():
        where = f"scales.{axis}"
        if axis not in ("x", "y", "z"):
            raise RecordingError(f"unknown axis {axis!r:.20}; expected [scales.x], [scales.y] or [scales.z]", path,
                                 key=where)
        if not isinstance(t, dict):
            raise RecordingError(f"expected a table [{where}] with cte and fixed_point, got {type(t).__name__}", path,
                                 key=where)
        unknown = sorted(set(t) - {"cte", "fixed_point"})
        if unknown:
            raise RecordingError(f"unknown key {unknown[0]!r:.40}; [{where}] has cte and fixed_point", path,
                                 key=f"{where}.{unknown[0]}")
        if "cte" not in t:
            raise RecordingError("missing key 'cte', the nominal expansion coefficient of the scale "
                                 "(for example \"11.5 um/(m*K)\")", path, key=f"{where}.cte")
        cte = _quantity(t["cte"], path=path, key=f"{where}.cte", dim=None, unit="1/K")
        if cte_problem(cte):
            raise RecordingError(cte_problem(cte), path, key=f"{where}.cte")
        x0 = _quantity(t.get("fixed_point", "0 mm"), path=path, key=f"{where}.fixed_point", dim=None, unit="mm")
        if abs(x0) > MAX_LENGTH:
            raise RecordingError(f"{t['fixed_point']!r:.60} is not a plausible position (at most {MAX_LENGTH:g} mm)",
                                 path, key=f"{where}.fixed_point")
        if not any(s.axis == axis for s in sensors):
            raise RecordingError(f"no [[sensors]] table is attached to the {axis} axis; correcting the scale's "
                                 f"expansion needs its temperature", path, key=where)
        out[axis] = Scale(cte, x0)
    return out


def read_recording(folder, *, max_rows: int = MAX_ROWS, max_columns: int = MAX_COLUMNS,
                   encoding: str = "utf-8", several_stations: bool = False) -> Recording:
    """Read a recording folder; raise :class:`RecordingError` on any violation.

    ``max_rows`` and ``max_columns`` bound points.csv (checked before the rows are parsed);
    ``encoding`` reads a points.csv that is not UTF-8 (an ASCII-compatible encoding such as
    ``"latin-1"`` or ``"cp1252"``); a UTF-8 byte order mark is always accepted.

    ``several_stations``: a format 2 recording of more than one xyz station (several stations, or a
    range station) is refused unless the caller says it identifies several stations
    (:mod:`mtbudget.multistation`): a one-station consumer would otherwise fit every station's frame
    as one.  Format 1 recordings, and format 2 with one xyz station, read either way.
    """
    folder = Path(folder)
    toml_path = folder / "recording.toml"
    csv_path = folder / "points.csv"
    if not folder.is_dir():
        raise RecordingError("not a folder (a recording is a folder with recording.toml and points.csv)", folder)
    if not toml_path.is_file():
        raise RecordingError("missing recording.toml", folder)
    if not csv_path.is_file():
        raise RecordingError("missing points.csv", folder)
    meta = _read_toml(toml_path)
    fmt = meta.get("format")
    if fmt is None:
        raise RecordingError(f"missing 'format' key; expected format = \"{FORMAT}\"", toml_path, key="format")
    if fmt not in FORMATS:
        raise RecordingError(f"unsupported format {fmt!r:.60}; this version reads {FORMAT!r}, {FORMAT2!r} and "
                             f"{FORMAT3!r}", toml_path, key="format")
    version = FORMATS.index(fmt) + 1
    tr = _table(meta, "tracker", toml_path)
    mt = _table(meta, "machine_tool", toml_path)
    _no_misspelt_keys(meta, KNOWN_KEYS, "", toml_path)
    _no_misspelt_keys(tr, ("angular", "distance", "distance_per_length") + (("mount",) if version >= 3 else ()),
                      "tracker.", toml_path)
    _no_misspelt_keys(mt, ("repeatability",), "machine_tool.", toml_path)
    angular = _uncertainty(tr, "tracker.angular", toml_path)
    distance = _uncertainty(tr, "tracker.distance", toml_path)
    dpl = _uncertainty(tr, "tracker.distance_per_length", toml_path)
    repeat = _uncertainty(mt, "machine_tool.repeatability", toml_path)
    tref = _quantity(meta.get("reference_temperature", "20 degC"), path=toml_path, key="reference_temperature",
                     dim="[temperature]", unit="K", absolute_temperature=True)
    sensors = _sensors(meta, toml_path)
    scales = _scales(meta, toml_path, sensors)
    report = _report(meta, toml_path)
    if version == 1 and "stations" in meta:
        raise RecordingError(f"[[stations]] needs format = \"{FORMAT2}\" (several stations)", toml_path, key="stations")
    stations = _stations(meta, toml_path, angular, distance, dpl) if version == 2 or (
        version == 3 and "stations" in meta) else []
    ignored = meta.get("ignore_columns", [])
    if not isinstance(ignored, list) or not all(isinstance(c, str) for c in ignored):
        raise RecordingError("expected a list of column names", toml_path, key="ignore_columns")
    for c in ignored:
        if c in COLUMNS or c in COLUMNS_V2 or c in {s.column for s in sensors}:
            raise RecordingError(f"{c!r} is a column mtbudget reads; it cannot be ignored", toml_path, key="ignore_columns")
    machine = _string(meta, "machine", toml_path, "XFYZ")
    name = _string(meta, "name", toml_path, folder.name)
    description = _string(meta, "description", toml_path, "")
    from .machine import Configuration, check_code

    try:
        code = check_code(machine)
    except Exception as exc:
        raise RecordingError(str(exc), toml_path, key="machine") from None
    letters = sorted(ch.lower() for ch in code if ch in "ABC")
    if letters and version < 3:
        raise RecordingError(f"machine {code!r} has rotary axes ({', '.join(x.upper() for x in letters)}): that needs "
                             f"format = \"{FORMAT3}\" with a [rotary.{letters[0].upper()}] table per rotary axis",
                             toml_path, key="format")
    if version < 3 and "rotary" in meta:
        raise RecordingError(f"[rotary] tables need format = \"{FORMAT3}\" (rotary axes)", toml_path, key="rotary")
    rotary = _rotary(meta, toml_path, code, letters) if version >= 3 else {}
    mount = _string(tr, "mount", toml_path, "table") if version >= 3 else "table"
    if mount not in TRACKER_MOUNTS:
        raise RecordingError(f"unknown tracker mount {mount!r:.40}; expected one of {', '.join(TRACKER_MOUNTS)}",
                             toml_path, key="tracker.mount")
    config = Configuration.parse(code, rotary)
    if mount == "bed" and config.workpiece:
        raise RecordingError(f"a tracker on the bed with the reflector in the spindle sees none of the workpiece-side "
                             f"axes of {code} ({', '.join(a.upper() for a in config.workpiece)}): their errors would be "
                             "invisible; stand it on the table (mount = \"table\")", toml_path, key="tracker.mount")

    try:
        columns, temps, unused = _read_points(csv_path, sensors, ignored=set(ignored), max_rows=max_rows,
                                              max_columns=max_columns, encoding=encoding, stations=stations or None,
                                              toml_path=toml_path, rotary=letters if version >= 3 else None)
    except OSError as exc:
        raise RecordingError(f"cannot read the file ({exc.strerror or type(exc).__name__})", csv_path) from None
    n = len(columns["point"])
    from .model import one_angle_only

    for r in letters:  # a rotary axis seen at one angle: its location errors are a rigid motion of the tracker
        single = one_angle_only(r, columns[r])
        if single:
            angle, lost = single
            raise RecordingError(f"rotary axis {r.upper()} is commanded to one angle only ({angle:g} "
                                 f"deg): its location and zero errors ({lost}) then act as a rigid motion of the "
                                 "tracker and cannot be identified; measure it at three or more angles", csv_path,
                                 column=r)
    if rotary:  # the rule of a configuration's [rotary.<axis>] pivot, against the recorded travel
        xyz = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
        for r, ax in rotary.items():
            problem = pivot_problem(ax.pivot, xyz.min(axis=0), xyz.max(axis=0))
            if problem:
                raise RecordingError(problem, toml_path, key=f"rotary.{r.upper()}.pivot")
    lt_cols = [columns.get(c, np.full(n, np.nan)) for c in ("lt_x", "lt_y", "lt_z")]
    station = lt_range = None
    if stations:  # format 2, or format 3 with [[stations]]
        station = columns["station"].astype(np.int64) if "station" in columns else np.full(n, stations[0].id, np.int64)
        lt_range = columns.get("lt_range", np.full(n, np.nan))
        if len(stations) > 1 or stations[0].kind != "xyz":
            if not several_stations:
                kinds = ", ".join(f"{sum(s.kind == k for s in stations)} {k}" for k in STATION_KINDS
                                  if any(s.kind == k for s in stations))
                raise RecordingError(f"{len(stations)} station{'s' if len(stations) > 1 else ''} ({kinds}): this "
                                     "command reads one-station recordings only; identify several stations with "
                                     "`mtbudget identify` (mtbudget.multistation)", toml_path, key="stations")
        else:  # one xyz station: a format 1 recording with that station's uncertainties
            angular, distance, dpl = stations[0].angular, stations[0].distance, stations[0].distance_per_length
    plan = Plan(
        point=columns["point"].astype(np.int64),
        run=columns["run"].astype(np.int64),
        time=columns["time"],
        nominal=np.stack([columns["x"], columns["y"], columns["z"]], axis=1),
        direction=np.stack([columns["dir_x"], columns["dir_y"], columns["dir_z"]], axis=1),
        tool=np.stack([columns["tool_x"], columns["tool_y"], columns["tool_z"]], axis=1),
        temperature=temps,
        sensors=sensors,
        scales=scales,
        angles={r: columns[r] for r in letters},
        angle_direction={r: columns.get(f"dir_{r}", np.ones(n)) for r in letters},
        rotary=rotary,
    )
    return Recording(
        name=name,
        machine=machine,
        plan=plan,
        lt=np.stack(lt_cols, axis=1),
        angular=angular, distance=distance, distance_per_length=dpl, repeatability=repeat,
        reference_temperature=tref, description=description,
        extra={k: v for k, v in meta.items() if k not in KNOWN_KEYS}, path=folder, unused_columns=unused,
        station=station, stations=stations, lt_range=lt_range, format_version=version, mount=mount, report=report,
    )


def _rotary(meta, path, code: str, letters: list) -> dict:
    """Format 3's ``[rotary.<A|B|C>]`` tables: {letter: machine.RotaryAxis}, one per rotary letter of the code."""
    from .machine import RotaryAxis
    from .model import rotary_direction

    tables = meta.get("rotary", {})
    if not isinstance(tables, dict):
        raise RecordingError("expected tables [rotary.A], [rotary.B], [rotary.C]", path, key="rotary")
    for key in tables:
        if str(key).lower() not in letters or str(key) != str(key).upper():
            raise RecordingError(f"[rotary.{key}] describes a rotary axis machine {code!r} does not have"
                                 + (f" (its rotary axes: {', '.join(x.upper() for x in letters)})" if letters else
                                    " (no rotary axis)"), path, key=f"rotary.{key}")
    out = {}
    for r in letters:
        R = r.upper()
        t = tables.get(R)
        if t is None:
            raise RecordingError(f"machine {code!r} has a rotary axis {R} but no [rotary.{R}] table (pivot, direction)",
                                 path, key=f"rotary.{R}")
        if not isinstance(t, dict):
            raise RecordingError("expected a table with pivot and direction", path, key=f"rotary.{R}")
        _no_misspelt_keys(t, ROTARY_KEYS, f"rotary.{R}.", path)
        piv = t.get("pivot")
        if not isinstance(piv, list) or len(piv) != 3:
            raise RecordingError("expected a list of three lengths, e.g. pivot = [\"0 mm\", \"-20 mm\", \"-80 mm\"]",
                                 path, key=f"rotary.{R}.pivot")
        pivot = tuple(_quantity(v, path=path, key=f"rotary.{R}.pivot[{i}]", dim="[length]", unit="mm")
                      for i, v in enumerate(piv))
        for i, v in enumerate(pivot):
            if abs(v) > MAX_LENGTH:
                raise RecordingError(f"{v:g} mm is not a plausible position (at most {MAX_LENGTH:g} mm)", path,
                                     key=f"rotary.{R}.pivot[{i}]")
        sign, problem = rotary_direction(r, t.get("direction"))
        if problem:
            raise RecordingError(f"direction {problem}", path, key=f"rotary.{R}.direction")
        out[r] = RotaryAxis(r, pivot, sign)
    return out


def _stations(meta, path, angular, distance, dpl) -> list:
    """Format 2's ``[[stations]]``: id, kind and the uncertainties that override ``[tracker]``."""
    raw = meta.get("stations")
    if raw is None:
        raise RecordingError("format 2 needs at least one [[stations]] table (id and kind)", path, key="stations")
    if not isinstance(raw, list) or not raw or not all(isinstance(s, dict) for s in raw):
        raise RecordingError("expected one or more [[stations]] tables (id and kind)", path, key="stations")
    out, seen = [], {}
    for i, s in enumerate(raw):
        where = f"stations[{i}]"
        unknown = sorted(set(s) - set(STATION_KEYS))
        if unknown:
            raise RecordingError(f"unknown key {unknown[0]!r:.40}; a [[stations]] table has {', '.join(STATION_KEYS)}",
                                 path, key=f"{where}.{unknown[0]}")
        for key in ("id", "kind"):
            if key not in s:
                raise RecordingError(f"missing key {key!r}; each [[stations]] table needs 'id' and 'kind'", path,
                                     key=f"{where}.{key}")
        sid = s["id"]
        if isinstance(sid, bool) or not isinstance(sid, int) or not 0 <= sid <= MAX_INDEX:
            raise RecordingError(f"expected a whole number from 0 to {MAX_INDEX} (the station column's value), got "
                                 f"{type(sid).__name__} {sid!r:.40}", path, key=f"{where}.id")
        if sid in seen:
            raise RecordingError(f"station {sid} is declared twice (also stations[{seen[sid]}])", path, key=f"{where}.id")
        seen[sid] = i
        kind = s["kind"]
        if not isinstance(kind, str) or kind not in STATION_KINDS:
            raise RecordingError(f"{kind!r:.40}: expected kind = \"xyz\" (a laser tracker) or \"range\" (a tracking "
                                 "interferometer)", path, key=f"{where}.kind")
        description = _string(s, "description", path, "") if "description" in s else ""
        values = {}
        for name, default in (("angular", angular), ("distance", distance), ("distance_per_length", dpl)):
            key = f"{where}.{name}"
            if name not in s:
                values[name] = default
                continue
            if name == "angular" and kind == "range":
                raise RecordingError("a range station measures no angle; state its distance and distance_per_length "
                                     "only", path, key=key)
            value = _quantity(s[name], path=path, key=key, dim=None, unit=UNCERTAINTIES[f"tracker.{name}"][0],
                              nonnegative=True)
            problem = uncertainty_problem(f"tracker.{name}", value)
            if problem:
                raise RecordingError(f"{s[name]!r:.60}: {problem}", path, key=key)
            values[name] = value
        out.append(Station(sid, kind, None if kind == "range" else values["angular"], values["distance"],
                           values["distance_per_length"], description))
    return out


class _Lines:
    """The decoded lines of points.csv for :mod:`csv`, checked one at a time: encoding, NUL bytes, length.

    ``line`` is the physical line last read (1-based) and ``offset`` the byte offset of its start.
    """

    def __init__(self, fh, path, encoding):
        self.fh, self.path, self.encoding = fh, path, encoding
        self.line, self.offset, self.next_offset = 0, 0, 0
        self.unterminated = False  # the line last read has no line ending: the file's last, maybe cut short
        self.header = None  # the column names, once known (for the column of a bad byte)

    def __iter__(self):
        return self

    def __next__(self) -> str:
        raw = self.fh.readline(MAX_LINE_BYTES + 1)
        if not raw:
            raise StopIteration
        self.line += 1
        self.offset, self.next_offset = self.next_offset, self.next_offset + len(raw)
        self.unterminated = not raw.endswith((b"\n", b"\r"))
        if self.line == 1:
            for bom, name in _BOMS:
                if raw.startswith(bom):
                    raise RecordingError(f"the file is {name} (byte order mark at byte offset 0): save it as UTF-8",
                                         self.path, line=1)
            if raw.startswith(codecs.BOM_UTF8):
                raw = raw[len(codecs.BOM_UTF8):]
                self.offset += len(codecs.BOM_UTF8)
        if len(raw) > MAX_LINE_BYTES:
            raise RecordingError(f"line longer than {MAX_LINE_BYTES} bytes (a file with other line endings, or not a "
                                 "CSV file?)", self.path, line=self.line)
        nul = raw.find(b"\x00")
        if nul >= 0:
            raise RecordingError(f"NUL byte at byte offset {self.offset + nul} (a binary file, or UTF-16?)", self.path,
                                 line=self.line, column=self._column(raw, nul))
        try:
            return raw.decode(self.encoding)
        except UnicodeDecodeError as exc:
            raise _decode_error(exc, raw, self.offset, self.path, self.line, self._column(raw, exc.start),
                                self.encoding) from None

    def _column(self, raw: bytes, pos: int):
        j = raw.count(b",", 0, pos)
        if self.header is None:  # the header itself: the cell, decoded as well as it can be
            return raw.split(b",")[j].decode(self.encoding, errors="backslashreplace").strip()
        return self.header[j] if j < len(self.header) else None


def _count_rows(path: Path, limit: int) -> int:
    """Non-blank lines after the header, counted on the bytes and stopping past ``limit`` (nothing is kept)."""
    n = -1
    with open(path, "rb") as fh:
        for raw in iter(lambda: fh.readline(MAX_LINE_BYTES + 1), b""):
            if len(raw) > MAX_LINE_BYTES:
                break  # the parse reports the over-long line with its number
            if raw.strip(b" \t\r\n,"):
                n += 1
                if n > limit:
                    break
    return n


def _bad_count(cells, header, path, line):
    """The error of a row whose cell count differs from the header's; finds a decimal comma when it can."""
    n, m = len(cells), len(header)
    if n > m:
        for j in range(min(n - 1, m)):
            if _INT_CELL.fullmatch(cells[j]) and _FRACTION_CELL.fullmatch(cells[j + 1]):
                merged = cells[:j] + [cells[j].strip() + "." + cells[j + 1].strip()] + cells[j + 2:]
                if len(merged) == m and j > 1 and header[j].split("[")[0].strip() not in ("dir_x", "dir_y", "dir_z"):
                    return RecordingError(f"{n} cells, the header has {m}: {cells[j].strip()},{cells[j + 1].strip()} looks "
                                          f"like a number with a decimal comma; points.csv needs a decimal point "
                                          f"({cells[j].strip()}.{cells[j + 1].strip()}) and commas only between cells",
                                          path, line=line, column=header[j])
        return RecordingError(f"{n} cells, the header has {m} (a decimal comma, or a separator inside a cell?)",
                              path, line=line, column=header[-1])
    return RecordingError(f"{n} cells, the header has {m}: no cell for this column and the ones after it", path,
                          line=line, column=header[n] if n < m else None)


def _bad_cell(text, path, line, column):
    t = text.strip()
    if not t:
        return RecordingError("empty cell", path, line=line, column=column)
    if t.lower().lstrip("+-") in ("nan", "inf", "infinity"):
        return RecordingError(f"value {text!r} is not finite", path, line=line, column=column)
    try:
        v = float(t)
    except ValueError:
        v = None
    if v is not None and not math.isfinite(v):
        return RecordingError(f"value {text!r:.40} is not finite (out of the range of a float)", path, line=line,
                              column=column)
    hint = "; use a decimal point, not a comma" if re.fullmatch(r"[+-]?[0-9]*,[0-9]+", t) else ""
    return RecordingError(f"not a number: {text!r:.40}{hint}", path, line=line, column=column)


def _read_points(csv_path: Path, sensors, *, ignored=frozenset(), max_rows=MAX_ROWS, max_columns=MAX_COLUMNS,
                 encoding="utf-8", stations=None, toml_path=None, rotary=None):
    try:
        ascii_compatible = "\n,.-+0123456789eE".encode(encoding) == b"\n,.-+0123456789eE"
    except (LookupError, UnicodeError):
        ascii_compatible = False
    if not ascii_compatible:
        raise RecordingError(f"encoding {encoding!r} is not an ASCII-compatible encoding this reader takes "
                             "(save the file as UTF-8)", csv_path)
    n_rows = _count_rows(csv_path, max_rows)
    if n_rows > max_rows:
        raise RecordingError(f"more than {max_rows} data rows; the reader's limit is max_rows={max_rows}", csv_path,
                             line=max_rows + 2)
    temp_cols = {s.column for s in sensors}
    if stations is None:  # format 1
        columns, required, optional = COLUMNS, list(COLUMNS), ()
    else:  # format 2: the measured columns follow the stations' kinds; a cell a row's kind does not use is empty
        columns = {**COLUMNS, **COLUMNS_V2}
        kinds = {s.kind for s in stations}
        required = [c for c in COLUMNS if "xyz" in kinds or not c.startswith("lt_")]
        required += (["lt_range"] if "range" in kinds else []) + (["station"] if len(stations) > 1 else [])
        optional = ("lt_x", "lt_y", "lt_z", "lt_range")
    if rotary is not None:  # format 3: every rotary axis' angle column; its approach direction may be given
        columns = {**columns, **ROTARY_COLUMNS, **ROTARY_DIRECTIONS}
        required = list(required) + list(rotary)
    with open(csv_path, "rb") as fh:
        lines = _Lines(fh, csv_path, encoding)
        reader = csv.reader(lines, strict=True)
        try:
            header = next(reader, None)
            if header is None:
                raise RecordingError("empty file (no header line)", csv_path, line=1)
            parsed, targets, unused = _parse_header(header, csv_path, temp_cols, ignored, max_columns, columns,
                                                    required, stations is not None, rotary)
            lines.header = header
            values = {name: array("d") for name in targets.values()}
            appends = [(j, values[name].append, header[j]) for j, name in targets.items()]
            may_be_empty = {j for j, name in targets.items() if name in optional}
            rows = []  # line number of every data row
            m = len(header)
            for cells in reader:
                line = lines.line
                if not cells or (len(cells) == 1 and not cells[0].strip()):
                    continue  # a blank line
                if lines.unterminated:  # a number cut mid-way would read as another number
                    raise RecordingError("the last line has no line ending: the file looks cut short (an interrupted "
                                         "copy or export?); if the line is complete, end the file with a newline",
                                         csv_path, line=line)
                if len(cells) != m:
                    raise _bad_count(cells, header, csv_path, line)
                for j, append, h in appends:
                    c = cells[j]
                    try:
                        v = float(c)
                    except ValueError:
                        if j in may_be_empty and not c.strip():
                            append(math.nan)  # a cell this row's station kind does not use (checked below)
                            continue
                        raise _bad_cell(c, csv_path, line, h) from None
                    if v - v != 0.0 or not c.isascii() or "_" in c:
                        raise _bad_cell(c, csv_path, line, h)
                    append(v)
                rows.append(line)
        except csv.Error as exc:
            raise RecordingError(f"not a valid CSV line ({exc})", csv_path, line=lines.line) from None
    if not rows:
        raise RecordingError("no data rows", csv_path, line=2)
    if len(rows) < MIN_ROWS:
        raise RecordingError(f"{len(rows)} data row{'s' if len(rows) > 1 else ''}; a recording needs at least {MIN_ROWS} "
                             "(the tracker pose alone has 6 unknowns)", csv_path, line=rows[-1])
    out, temps = _convert(parsed, {k: np.frombuffer(v, dtype=float) for k, v in values.items()}, rows, csv_path,
                          temp_cols, columns, rotary or ())
    if stations is not None:
        _check_stations(out, parsed, rows, csv_path, stations, toml_path)
    return out, temps, unused


def _check_stations(out, parsed, rows, csv_path, stations, toml_path):
    """Format 2: every row's station declared, its cells those of its kind, enough points per station."""
    n = len(rows)
    by_id = {s.id: s for s in stations}
    sid = out["station"] if "station" in out else np.full(n, stations[0].id, float)
    known = np.isin(sid, list(by_id))
    if not known.all():
        k = int(np.flatnonzero(~known)[0])
        raise RecordingError(f"station {int(sid[k])} is not declared in recording.toml (its [[stations]] ids: "
                             f"{', '.join(str(s.id) for s in stations)})", csv_path, line=rows[k],
                             column=parsed["station"][2])
    nan = np.full(n, np.nan)
    lt = {c: out.get(c, nan) for c in ("lt_x", "lt_y", "lt_z", "lt_range")}
    is_range = np.isin(sid, [s.id for s in stations if s.kind == "range"])
    for c, v in lt.items():
        uses = is_range if c == "lt_range" else ~is_range
        extra = np.flatnonzero(~uses & ~np.isnan(v))
        if extra.size:
            k = int(extra[0])
            st = by_id[int(sid[k])]
            what = ("an xyz station (a laser tracker: lt_x, lt_y, lt_z in its own frame)" if st.kind == "xyz" else
                    "a range station (a tracking interferometer: lt_range only)")
            raise RecordingError(f"station {st.id} is {what}, but this row has a {c} value; one row is one kind of "
                                 f"measurement: leave the cell empty", csv_path, line=rows[k], column=parsed[c][2])
        missing = np.flatnonzero(uses & np.isnan(v))
        if missing.size:
            k = int(missing[0])
            raise RecordingError(f"empty cell: station {int(sid[k])} is {'a range' if c == 'lt_range' else 'an xyz'} "
                                 f"station and measures {c}", csv_path, line=rows[k],
                                 column=parsed[c][2] if c in parsed else c)
    where = np.stack([out["x"] + out["tool_x"], out["y"] + out["tool_y"], out["z"] + out["tool_z"]], axis=1)
    for i, st in enumerate(stations):
        mine = np.flatnonzero(sid == st.id)
        if not mine.size:
            raise RecordingError(f"station {st.id} measures no row of points.csv; remove its [[stations]] table",
                                 toml_path, key=f"stations[{i}].id")
        distinct = len(np.unique(where[mine], axis=0))
        need = MIN_STATION_POINTS[st.kind]
        if distinct < need:
            own = "pose (6 unknowns)" if st.kind == "xyz" else "position and dead-path offset (4 unknowns)"
            raise RecordingError(f"station {st.id} ({st.kind}) measures {distinct} distinct point"
                                 f"{'s' if distinct != 1 else ''}; its {own} needs at least {need}", csv_path,
                                 line=rows[int(mine[-1])], column=parsed["station"][2] if "station" in parsed else None)


def _unit_names(u) -> list:
    return [name for name, _ in Q_(1.0, u).unit_items()]


def _parse_header(header, csv_path, temp_cols, ignored, max_columns, columns=COLUMNS, required=None,
                  format2=False, rotary=None):
    """{name: (index, unit, header text)} of the columns, {index: name} of the columns to parse, and the
    names of the columns left out of the model."""
    if len(header) > max_columns:
        raise RecordingError(f"{len(header)} columns; the reader's limit is max_columns={max_columns}", csv_path, line=1)
    if len(header) == 1 and (";" in header[0] or "\t" in header[0]):
        sep = "';'" if ";" in header[0] else "a tab"
        raise RecordingError(f"the header is separated by {sep}; points.csv is comma-separated (with a decimal point)",
                             csv_path, line=1, column=header[0][:40])
    parsed = {}
    for j, h in enumerate(header):
        m = _HEADER.match(h)
        if not m:
            raise RecordingError(f"bad column header {h!r:.60}; expected 'name [unit]' or 'name'", csv_path, line=1,
                                 column=h[:60])
        name, unit = m.group(1), m.group(2)
        if name in parsed:
            raise RecordingError(f"column {name!r} appears twice", csv_path, line=1, column=h)
        if name in COLUMNS_V2 and not format2:
            raise RecordingError(f"a {name} column needs format 2 (several stations): format = \"{FORMAT2}\" and "
                                 "[[stations]] tables in recording.toml", csv_path, line=1, column=h)
        axis = name[-1] if name in ROTARY_COLUMNS or name in ROTARY_DIRECTIONS else None
        if axis is not None and rotary is None:
            raise RecordingError(f"a {name} column is the {'angle' if name == axis else 'approach direction'} of a "
                                 f"rotary axis {axis.upper()}: that needs format = \"{FORMAT3}\" and a machine code "
                                 f"with {axis.upper()}", csv_path, line=1, column=h)
        if axis is not None and axis not in rotary:
            raise RecordingError(f"column {name!r} belongs to a rotary axis {axis.upper()}, which the machine does not "
                                 f"have" + (f" (its rotary axes: {', '.join(x.upper() for x in rotary)})" if rotary
                                            else ""), csv_path, line=1, column=h)
        parsed[name] = (j, unit, h)
    for name in list(COLUMNS if required is None else required) + sorted(temp_cols):
        if name not in parsed:
            unknown = [n for n in parsed if n not in columns and n not in temp_cols]
            close = difflib.get_close_matches(name, unknown, n=1, cutoff=0.6)
            hint = f"; the header has {close[0]!r}: a misspelling?" if close else ""
            raise RecordingError(f"missing column {name!r}{hint}", csv_path, line=1, column=name)
    targets, unused = {}, []
    for name, (j, unit, h) in parsed.items():
        known = name in columns or name in temp_cols
        if name in ignored or (not known and not (unit and unit.strip())):
            unused.append(name)  # free text (or a count nobody reads): left out, not parsed
            continue
        spec = columns.get(name, ("[temperature]", "K") if name in temp_cols else None)
        if spec is None and known:
            if unit is not None and unit.strip():
                raise RecordingError(f"column {name!r} is a count or sign and takes no unit, got [{unit}]", csv_path,
                                     line=1, column=h)
        else:
            if unit is None or not unit.strip():
                raise RecordingError(f"column {name!r} needs a unit of {spec[0]}, e.g. '{name} [{spec[1]}]'", csv_path,
                                     line=1, column=h)
            u = parse_unit(unit.strip(), where="unit", error=lambda msg: RecordingError(
                f"unit {msg.split(': ', 1)[-1]}", csv_path, line=1, column=h))
            if spec is not None and u.dimensionality != ureg.Unit(spec[1]).dimensionality:
                raise RecordingError(f"unit {unit!r} has dimension {u.dimensionality}, expected {spec[0]}", csv_path,
                                     line=1, column=h)
            if spec is not None and spec[0] == "[angle]" and Q_(1.0, u).to_root_units().units != ureg.radian:
                raise RecordingError(f"unit {unit!r} is not an angle; the angle of a rotary axis needs an angle unit "
                                     f"such as '{name} [deg]', '{name} [rad]' or '{name} [arcmin]'", csv_path, line=1,
                                     column=h)
            if name in temp_cols and any(n.startswith("delta_") for n in _unit_names(u)):
                raise RecordingError(f"unit {unit!r} is a temperature difference; a sensor column holds absolute "
                                     f"temperatures, e.g. '{name} [degC]' or '{name} [K]'", csv_path, line=1, column=h)
            parsed[name] = (j, u, h)
            if not known:  # a quantity column nobody declared: checked, then left out of the model
                unused.append(name)
        targets[j] = name
    return parsed, targets, unused


def _convert(parsed, values, rows, csv_path, temp_cols, columns=COLUMNS, rotary=()):
    """Columns in internal units, checked against their meaning: indices, signs, time order, plausible ranges."""
    out, temps = {}, {}

    def fail(name, k, reason):
        raise RecordingError(reason, csv_path, line=rows[k], column=parsed[name][2])

    lo, hi = ABSOLUTE_TEMPERATURE
    for name, v in values.items():
        unit = parsed[name][1]
        if columns.get(name, True) is None:
            out[name] = v
            continue
        if name not in columns and name not in temp_cols:  # an undeclared quantity column, left out of the model
            names = _unit_names(unit)
            if len(names) == 1 and Q_(0.0, unit).to_base_units().magnitude != 0:  # degC, degF: absolute readings
                bad = np.flatnonzero(~((Q_(v, unit).to("K").magnitude >= lo) & (Q_(v, unit).to("K").magnitude <= hi)))
                if bad.size:
                    fail(name, bad[0], f"{v[bad[0]]:g} {unit:~P} is not a plausible absolute temperature "
                                       f"({lo:g} K to {hi:g} K)")
            continue
        conv = np.asarray(Q_(v, unit).to("K" if name in temp_cols else columns[name][1]).magnitude, float)
        bad = np.flatnonzero(~np.isfinite(conv) & ~np.isnan(v))  # NaN: an empty cell of format 2, checked later
        if bad.size:
            fail(name, bad[0], f"value {v[bad[0]]:g} is not finite in internal units")
        (temps if name in temp_cols else out)[name] = conv
    for name in ("dir_x", "dir_y", "dir_z") + tuple(f"dir_{r}" for r in rotary if f"dir_{r}" in out):
        bad = np.flatnonzero((out[name] != 1.0) & (out[name] != -1.0))
        if bad.size:
            fail(name, bad[0], f"direction must be +1 or -1, got {out[name][bad[0]]:g}")
    for name in ("point", "run", "station"):
        if name not in out:
            continue
        v = out[name]
        bad = np.flatnonzero((v != np.round(v)) | (v < 0) | (v > MAX_INDEX))
        if bad.size:
            fail(name, bad[0], f"must be a whole number from 0 to {MAX_INDEX}, got {v[bad[0]]:.10g}")
    for name in ("x", "y", "z", "tool_x", "tool_y", "tool_z", "lt_x", "lt_y", "lt_z", "lt_range"):
        if name not in out:
            continue
        bad = np.flatnonzero(np.abs(out[name]) > MAX_LENGTH)
        if bad.size:
            fail(name, bad[0], f"{out[name][bad[0]]:g} mm is not a plausible position (at most {MAX_LENGTH:g} mm)")
    for name in rotary:
        bad = np.flatnonzero(np.abs(out[name]) > MAX_ANGLE)
        if bad.size:
            fail(name, bad[0], f"{np.degrees(out[name][bad[0]]):g} deg is not a plausible commanded angle (at most "
                               f"{np.degrees(MAX_ANGLE):g} deg)")
    t = out["time"]
    bad = np.flatnonzero((t < 0) | (t > MAX_TIME))
    if bad.size:
        fail("time", bad[0], f"{t[bad[0]]:g} s is not a time since the start of the test (0 to {MAX_TIME:g} s)")
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        k = back[0] + 1
        fail("time", k, f"time goes backwards ({t[k - 1]:g} s then {t[k]:g} s); rows must be in time order")
    for name, T in temps.items():
        bad = np.flatnonzero((T < lo) | (T > hi))
        if bad.size:
            k = bad[0]
            unit = parsed[name][1]
            hint = ""
            if unit == ureg.kelvin and -60 <= values[name][k] <= 130:
                hint = f"; the column is in K but holds what look like degC readings: write '{name} [degC]'"
            kelvin = "" if unit == ureg.kelvin else f" ({T[k]:.6g} K)"
            fail(name, k, f"{values[name][k]:g} {unit:~P}{kelvin} is not a plausible absolute temperature "
                          f"({lo:g} K to {hi:g} K){hint}")
        # a header on the other scale: readings a shop has in degC (5-40) under degF read as below 5 degC, and
        # readings a shop has in degF (50-105) under degC read as above 50 degC; neither is a verification's air
        unit, med = parsed[name][1], float(np.median(values[name]))
        other = ("degC", 5 <= med <= 40 and np.median(T) < 278.15) if unit == ureg.degree_Fahrenheit else \
            ("degF", 50 <= med <= 105) if unit == ureg.degree_Celsius else None
        if other is not None and other[1]:
            k = int(np.argmin(np.abs(values[name] - med)))
            fail(name, k, f"the readings of this column (median {med:g} {unit:~P}, {np.median(T) - 273.15:.1f} degC) are "
                          f"not a machine shop's temperature; they look like {other[0]} readings: write "
                          f"'{name} [{other[0]}]' (or check the sensor)")
    nominal = np.stack([out["x"], out["y"], out["z"]], axis=1)
    _, first, inverse = np.unique(out["point"], return_index=True, return_inverse=True)
    moved = np.flatnonzero(np.any(nominal != nominal[first[inverse.ravel()]], axis=1))
    if moved.size:
        k = moved[0]
        k0 = first[inverse.ravel()[k]]
        fail("x", k, f"point {int(out['point'][k])} is at ({', '.join(f'{c:g}' for c in nominal[k])}) mm here and at "
                     f"({', '.join(f'{c:g}' for c in nominal[k0])}) mm on line {rows[k0]}; one point index is one "
                     "nominal position")
    for name in rotary:
        turned = np.flatnonzero(out[name] != out[name][first[inverse.ravel()]])
        if turned.size:
            k = turned[0]
            k0 = first[inverse.ravel()[k]]
            fail(name, k, f"point {int(out['point'][k])} has {name} = {np.degrees(out[name][k]):g} deg here and "
                          f"{np.degrees(out[name][k0]):g} deg on line {rows[k0]}; one point index is one nominal pose")
    key = [out["point"], out["run"], t, out["tool_x"], out["tool_y"], out["tool_z"]]
    if "station" in out:  # several stations may measure one point at one time (simultaneous interferometers)
        key.append(out["station"])
    key = np.stack(key, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup_key = key[first[np.argmax(counts > 1)]]
        idx = np.flatnonzero(np.all(key == dup_key, axis=1))
        same = "point, run, time, tool and station" if "station" in out else "point, run, time and tool"
        raise RecordingError(f"duplicate row (same {same} as line {rows[idx[0]]})",
                             csv_path, line=rows[idx[1]], column=parsed["point"][2])
    return out, temps


def _fmt_row(values):
    return ",".join(values)


def _toml_string(text) -> str:
    """A TOML basic string of ``text``: quote, backslash and control characters escaped; a lone surrogate
    (which no file can hold) becomes U+FFFD."""
    out = []
    for ch in str(text):
        c = ord(ch)
        if ch in '"\\':
            out.append("\\" + ch)
        elif c < 0x20 or c == 0x7F:
            out.append(f"\\u{c:04X}")
        elif 0xD800 <= c <= 0xDFFF:
            out.append("\ufffd")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def write_recording(rec: Recording, folder, *, truth: dict | None = None) -> Path:
    """Write ``rec`` as a recording folder (mm, s, degC, 6 decimals for lengths).

    Format 2 (a ``station`` column, ``[[stations]]`` with each station's stated uncertainties written
    out) when ``rec`` has several stations or was read as format 2; format 1 otherwise.
    """
    import json

    folder = make_folder(folder)
    p = rec.plan
    v3 = rec.format_version == 3 or bool(p.angles)
    v2 = not v3 and (rec.format_version == 2 or bool(rec.stations))
    letters = sorted(p.angles)
    stations = rec.station_list()
    lines = [
        f'format = "{FORMAT3 if v3 else FORMAT2 if v2 else FORMAT}"',
        f"name = {_toml_string(rec.name)}",
        f"machine = {_toml_string(rec.machine)}",
        f"description = {_toml_string(rec.description)}",
        f'reference_temperature = "{rec.reference_temperature - 273.15:.6g} degC"',
        "",
        "[tracker]",
        f'angular = "{display(rec.angular, "rad", "urad"):.9g} urad"',
        f'distance = "{display(rec.distance, "mm", "um"):.9g} um"',
        f'distance_per_length = "{display(rec.distance_per_length, "", "um/m"):.9g} um/m"',
        *([f"mount = {_toml_string(rec.mount)}"] if v3 else []),
        "",
        "[machine_tool]",
        f'repeatability = "{display(rec.repeatability, "mm", "um"):.9g} um"',
    ]
    for s in p.sensors:
        lines += ["", "[[sensors]]", f"column = {_toml_string(s.column)}", f"attached_to = {_toml_string(s.attached_to)}"]
        if s.position is not None:
            lines.append(f'position = "{s.position:.6f} mm"')
    for axis, sc in sorted(p.scales.items()):
        lines += ["", f"[scales.{axis}]", f'cte = "{display(sc.cte, "1/K", "um/(m*K)"):.9g} um/(m*K)"',
                  f'fixed_point = "{sc.fixed_point:.6f} mm"']
    for r in letters:
        ax = p.rotary[r]
        lines += ["", f"[rotary.{r.upper()}]", "pivot = [" + ", ".join(f'"{v:.6f} mm"' for v in ax.pivot) + "]",
                  f'direction = "{"+" if ax.sign > 0 else "-"}{"xyz"[ax.index]}"']
    if v2 or (v3 and rec.stations):
        for st in stations:
            lines += ["", "[[stations]]", f"id = {int(st.id)}", f'kind = "{st.kind}"']
            if st.kind == "xyz":
                lines.append(f'angular = "{display(st.angular, "rad", "urad"):.9g} urad"')
            lines += [f'distance = "{display(st.distance, "mm", "um"):.9g} um"',
                      f'distance_per_length = "{display(st.distance_per_length, "", "um/m"):.9g} um/m"']
            if st.description:
                lines.append(f"description = {_toml_string(st.description)}")
    if rec.report:  # the laboratory's [report] fields, as read
        lines += ["", "[report]"] + [f"{k} = {_toml_string(v)}" for k, v in rec.report.items() if not isinstance(v, dict)]
        if isinstance(rec.report.get("instrument"), dict):
            lines += ["", "[report.instrument]"] + [f"{k} = {_toml_string(v)}" for k, v in rec.report["instrument"].items()]
    (folder / "recording.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    tcols = [s.column for s in p.sensors if s.column in p.temperature]
    kinds = {st.kind for st in stations}
    header = ["point", "run", "time [s]", "x [mm]", "y [mm]", "z [mm]", "dir_x", "dir_y", "dir_z",
              "tool_x [mm]", "tool_y [mm]", "tool_z [mm]"]
    header += [f"{r} [deg]" for r in letters] + [f"dir_{r}" for r in letters if r in p.angle_direction]
    several = v2 or (v3 and bool(rec.stations))
    header += (["station"] if several else []) + (["lt_x [mm]", "lt_y [mm]", "lt_z [mm]"] if "xyz" in kinds else [])
    header += ["lt_range [mm]"] if "range" in kinds else []
    header += [f"{c} [degC]" for c in tcols]
    sid = rec.station_ids()
    lt_range = rec.lt_range if rec.lt_range is not None else np.full(len(p), np.nan)

    def cell(v):
        return "" if np.isnan(v) else f"{v:.6f}"

    with open(folder / "points.csv", "w", newline="", encoding="utf-8") as fh:
        fh.write(",".join(header) + "\n")
        for i in range(len(p)):
            vals = [str(int(p.point[i])), str(int(p.run[i])), f"{p.time[i]:.4f}"]
            vals += [f"{v:.6f}" for v in p.nominal[i]]
            vals += [str(int(v)) for v in p.direction[i]]
            vals += [f"{v:.6f}" for v in p.tool[i]]
            vals += [f"{np.degrees(p.angles[r][i]):.9f}" for r in letters]
            vals += [str(int(p.angle_direction[r][i])) for r in letters if r in p.angle_direction]
            if several:
                vals.append(str(int(sid[i])))
            if "xyz" in kinds:
                vals += [cell(v) for v in rec.lt[i]]
            if "range" in kinds:
                vals.append(cell(lt_range[i]))
            vals += [f"{p.temperature[c][i] - 273.15:.4f}" for c in tcols]
            fh.write(_fmt_row(vals) + "\n")
    if truth is not None:
        (folder / "truth.json").write_text(json.dumps(truth, indent=1), encoding="utf-8")
    return folder
