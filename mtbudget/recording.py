"""Read and write verification recordings (docs/recording-format.md).

A recording is a folder with ``recording.toml`` and ``points.csv``.  Column
units are anything pint parses; values are converted once to the internal
system (mm, s, K).  Every problem raises :class:`RecordingError` naming the
file, the line and the column.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import RecordingError
from .plan import Plan, Sensor, T20
from .units import Q_, display, to_internal, ureg

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

FORMAT = "mtbudget-recording/1"
_HEADER = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[(.*)\])?\s*$")

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


@dataclass
class Recording:
    """A verification recording in internal units."""

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

    def __len__(self):
        return len(self.plan)


def _quantity(text, *, path, key, dim, unit, nonnegative=False, absolute_temperature=False):
    """One value of recording.toml in internal units, through the one strict parser; errors name file and key."""
    value = to_internal(text, unit, where=key, absolute_temperature=absolute_temperature,
                        error=lambda m: RecordingError(m.split(": ", 1)[1] if m.startswith(key + ": ") else m, path, key=key))
    if nonnegative and value < 0:
        raise RecordingError(f"{text!r} is negative; a standard uncertainty must not be", path, key=key)
    return value


def read_recording(folder) -> Recording:
    """Read a recording folder; raise :class:`RecordingError` on any violation."""
    folder = Path(folder)
    toml_path = folder / "recording.toml"
    csv_path = folder / "points.csv"
    if not folder.is_dir():
        raise RecordingError("not a folder (a recording is a folder with recording.toml and points.csv)", folder)
    if not toml_path.exists():
        raise RecordingError("missing recording.toml", folder)
    if not csv_path.exists():
        raise RecordingError("missing points.csv", folder)
    try:
        meta = tomllib.loads(toml_path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise RecordingError(f"invalid TOML ({exc})", toml_path) from None
    fmt = meta.get("format")
    if fmt is None:
        raise RecordingError(f"missing 'format' key; expected format = \"{FORMAT}\"", toml_path)
    if fmt != FORMAT:
        raise RecordingError(f"unsupported format {fmt!r}; this version reads {FORMAT!r}", toml_path)
    tr = meta.get("tracker", {})
    mt = meta.get("machine_tool", {})

    def need(table, key, where, dim, unit):
        if key not in table:
            raise RecordingError(f"missing key {where}.{key}", toml_path)
        return _quantity(table[key], path=toml_path, key=f"{where}.{key}", dim=dim, unit=unit, nonnegative=True)

    angular = need(tr, "angular", "tracker", "angle", "rad")
    distance = need(tr, "distance", "tracker", "[length]", "mm")
    dpl = need(tr, "distance_per_length", "tracker", "dimensionless (length per length)", "mm/mm")
    repeat = need(mt, "repeatability", "machine_tool", "[length]", "mm")
    tref = _quantity(meta.get("reference_temperature", "20 degC"), path=toml_path, key="reference_temperature",
                     dim="[temperature]", unit="K", absolute_temperature=True)
    for key, val in (("tracker.angular", angular), ("tracker.distance", distance), ("machine_tool.repeatability", repeat)):
        if not val > 0:
            raise RecordingError(f"must be positive, got {val}", toml_path, key=key)
    sensors = []
    for i, s in enumerate(meta.get("sensors", [])):
        if "column" not in s or "attached_to" not in s:
            raise RecordingError(f"sensors[{i}] needs 'column' and 'attached_to'", toml_path)
        if s["attached_to"].strip().lower() not in ("x axis", "y axis", "z axis", "air"):
            raise RecordingError(f"sensors[{i}].attached_to {s['attached_to']!r}: expected 'x axis', 'y axis', 'z axis' or 'air'", toml_path)
        pos = s.get("position")
        sensors.append(Sensor(s["column"], s["attached_to"],
                              None if pos is None else _quantity(pos, path=toml_path, key=f"sensors[{i}].position", dim="[length]", unit="mm")))
    machine = str(meta.get("machine", "XFYZ"))
    from .machine import Configuration

    try:
        Configuration.parse(machine)
    except Exception as exc:
        raise RecordingError(str(exc), toml_path, column="machine") from None

    columns, temps = _read_points(csv_path, sensors)
    known = {"format", "name", "machine", "description", "reference_temperature", "tracker", "machine_tool", "sensors"}
    plan = Plan(
        point=columns["point"].astype(int),
        run=columns["run"].astype(int),
        time=columns["time"],
        nominal=np.stack([columns["x"], columns["y"], columns["z"]], axis=1),
        direction=np.stack([columns["dir_x"], columns["dir_y"], columns["dir_z"]], axis=1),
        tool=np.stack([columns["tool_x"], columns["tool_y"], columns["tool_z"]], axis=1),
        temperature=temps,
        sensors=sensors,
    )
    return Recording(
        name=str(meta.get("name", folder.name)),
        machine=machine,
        plan=plan,
        lt=np.stack([columns["lt_x"], columns["lt_y"], columns["lt_z"]], axis=1),
        angular=angular, distance=distance, distance_per_length=dpl, repeatability=repeat,
        reference_temperature=tref, description=str(meta.get("description", "")),
        extra={k: v for k, v in meta.items() if k not in known}, path=folder,
    )


def _read_points(csv_path: Path, sensors):
    with open(csv_path, newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise RecordingError("empty file (no header line)", csv_path, line=1) from None
        rows = [(i, row) for i, row in enumerate(reader, start=2) if any(c.strip() for c in row)]
    parsed = {}
    for j, h in enumerate(header):
        m = _HEADER.match(h)
        if not m:
            raise RecordingError(f"bad column header {h!r}; expected 'name [unit]' or 'name'", csv_path, line=1, column=h)
        name, unit = m.group(1), m.group(2)
        if name in parsed:
            raise RecordingError(f"column {name!r} appears twice", csv_path, line=1, column=h)
        parsed[name] = (j, unit, h)
    temp_cols = {s.column for s in sensors}
    for name in list(COLUMNS) + sorted(temp_cols):
        if name not in parsed:
            raise RecordingError(f"missing column {name!r}", csv_path, line=1, column=name)
    if not rows:
        raise RecordingError("no data rows", csv_path, line=2)
    out, temps = {}, {}
    for name, (j, unit, h) in parsed.items():
        if name in COLUMNS:
            spec = COLUMNS[name]
        elif name in temp_cols:
            spec = ("[temperature]", "K")
        else:
            continue  # unknown columns are kept out of the model and not checked
        if spec is None and unit:
            raise RecordingError(f"column {name!r} is a count or sign and takes no unit, got [{unit}]", csv_path, line=1, column=h)
        values = np.empty(len(rows))
        for k, (line, row) in enumerate(rows):
            if j >= len(row) or not row[j].strip():
                raise RecordingError("empty cell", csv_path, line=line, column=h)
            try:
                v = float(row[j])
            except ValueError:
                raise RecordingError(f"not a number: {row[j]!r}", csv_path, line=line, column=h) from None
            if not math.isfinite(v):
                raise RecordingError(f"value {row[j]!r} is not finite", csv_path, line=line, column=h)
            values[k] = v
        if spec is None:
            out[name] = values
            continue
        dim, internal = spec
        if not unit:
            raise RecordingError(f"column {name!r} needs a unit of {dim}, e.g. '{name} [{internal}]'", csv_path, line=1, column=h)
        try:
            u = ureg.Unit(unit)
        except Exception:
            raise RecordingError(f"unit {unit!r} is not a unit pint knows", csv_path, line=1, column=h) from None
        if u.dimensionality != ureg.Unit(internal).dimensionality:
            raise RecordingError(f"unit {unit!r} has dimension {u.dimensionality}, expected {dim}", csv_path, line=1, column=h)
        conv = Q_(values, u).to(internal).magnitude
        (temps if name in temp_cols else out)[name] = conv
    # semantic checks
    for name in ("dir_x", "dir_y", "dir_z"):
        bad = np.flatnonzero(~np.isin(out[name], (-1.0, 1.0)))
        if bad.size:
            raise RecordingError(f"direction must be +1 or -1, got {out[name][bad[0]]:g}", csv_path, line=rows[bad[0]][0], column=name)
    for name in ("point", "run"):
        bad = np.flatnonzero((out[name] != np.round(out[name])) | (out[name] < 0))
        if bad.size:
            raise RecordingError(f"must be a whole number >= 0, got {out[name][bad[0]]:g}", csv_path, line=rows[bad[0]][0], column=name)
    t = out["time"]
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        k = back[0] + 1
        raise RecordingError(f"time goes backwards ({t[k - 1]:g} s then {t[k]:g} s); rows must be in time order",
                             csv_path, line=rows[k][0], column=parsed["time"][2])
    key = np.stack([out["point"], out["run"], t, out["tool_x"], out["tool_y"], out["tool_z"]], axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup_key = key[first[np.argmax(counts > 1)]]
        idx = np.flatnonzero(np.all(key == dup_key, axis=1))
        raise RecordingError(f"duplicate row (same point, run, time and tool as line {rows[idx[0]][0]})",
                             csv_path, line=rows[idx[1]][0])
    return out, temps


def _fmt_row(values):
    return ",".join(values)


def write_recording(rec: Recording, folder, *, truth: dict | None = None) -> Path:
    """Write ``rec`` as a recording folder (mm, s, degC, 6 decimals for lengths)."""
    import json

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    p = rec.plan
    lines = [
        f'format = "{FORMAT}"',
        f"name = {json.dumps(rec.name)}",
        f"machine = {json.dumps(rec.machine)}",
        f"description = {json.dumps(rec.description)}",
        f'reference_temperature = "{rec.reference_temperature - 273.15:.6g} degC"',
        "",
        "[tracker]",
        f'angular = "{display(rec.angular, "rad", "urad"):.9g} urad"',
        f'distance = "{display(rec.distance, "mm", "um"):.9g} um"',
        f'distance_per_length = "{display(rec.distance_per_length, "", "um/m"):.9g} um/m"',
        "",
        "[machine_tool]",
        f'repeatability = "{display(rec.repeatability, "mm", "um"):.9g} um"',
    ]
    for s in p.sensors:
        lines += ["", "[[sensors]]", f"column = {json.dumps(s.column)}", f"attached_to = {json.dumps(s.attached_to)}"]
        if s.position is not None:
            lines.append(f'position = "{s.position:.6f} mm"')
    (folder / "recording.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    tcols = [s.column for s in p.sensors if s.column in p.temperature]
    header = ["point", "run", "time [s]", "x [mm]", "y [mm]", "z [mm]", "dir_x", "dir_y", "dir_z",
              "tool_x [mm]", "tool_y [mm]", "tool_z [mm]", "lt_x [mm]", "lt_y [mm]", "lt_z [mm]"]
    header += [f"{c} [degC]" for c in tcols]
    with open(folder / "points.csv", "w", newline="", encoding="utf-8") as fh:
        fh.write(",".join(header) + "\n")
        for i in range(len(p)):
            vals = [str(int(p.point[i])), str(int(p.run[i])), f"{p.time[i]:.4f}"]
            vals += [f"{v:.6f}" for v in p.nominal[i]]
            vals += [str(int(v)) for v in p.direction[i]]
            vals += [f"{v:.6f}" for v in p.tool[i]]
            vals += [f"{v:.6f}" for v in rec.lt[i]]
            vals += [f"{p.temperature[c][i] - 273.15:.4f}" for c in tcols]
            fh.write(_fmt_row(vals) + "\n")
    if truth is not None:
        (folder / "truth.json").write_text(json.dumps(truth, indent=1), encoding="utf-8")
    return folder
