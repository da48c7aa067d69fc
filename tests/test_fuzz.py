"""Fuzzing the boundary: mutated recordings, mutated configurations and quantity strings.

Every outcome must be either a clean mtbudget error (a subclass of MtbudgetError with a
one-line message) or a result that equals an independently computed expectation:

* a recording that reads is compared with a naive reader written here (split on commas,
  ``float`` each cell, a hand-written unit table); a harmless edit (CRLF, a BOM, blank lines,
  spaces, columns reordered or converted to inch by hand, an ignored column) must read exactly
  like the original;
* a configuration that builds a scenario must give finite arrays, the plan size counted here
  from the mesh, and a simulated recording that reads back; a harmless edit (a quantity
  rewritten in another unit, converted by hand) must give the same scenario;
* a quantity string that parses must equal the number times the factor of a hand-written table.

No other exception may escape, and no input may hang (each one runs under a time limit).
The default suite tries a few dozen inputs per class; the slow test (``-m slow``) tries
thousands and prints the figures of docs/reliability.md:

    MTBUDGET_FUZZ_REPORT=fuzz.json python -m pytest -m slow tests/test_fuzz.py -q -s
"""

from __future__ import annotations

import codecs
import copy
import json
import math
import os
import re
import signal
import tempfile
from collections import Counter, defaultdict
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from mtbudget.config import default_config_path, example_recording, load_config, parse_config
from mtbudget.errors import MtbudgetError
from mtbudget.recording import read_recording, write_recording
from mtbudget.scenario import build_scenario
from mtbudget.simulate import simulate_recording
from mtbudget.units import to_internal

SMALL = Path(__file__).parent / "data" / "small.toml"
FAST_EXAMPLES = int(os.environ.get("MTBUDGET_FUZZ_FAST", "25"))
SLOW_EXAMPLES = int(os.environ.get("MTBUDGET_FUZZ_SLOW", "1500"))
TIME_LIMIT = float(os.environ.get("MTBUDGET_FUZZ_TIME_LIMIT", "20"))  # s per input: a hang fails, not a stuck suite


def fuzz_settings(n):
    return settings(max_examples=n, derandomize=True, deadline=None, database=None, print_blob=True,
                    suppress_health_check=list(HealthCheck), phases=(Phase.explicit, Phase.generate, Phase.shrink))


#: outcome counts per input class (the slow test reports them)
STATS: dict = defaultdict(Counter)


class Hang(Exception):
    pass


@contextmanager
def time_limit(seconds=TIME_LIMIT):
    def on_alarm(signum, frame):
        raise Hang(f"no answer within {seconds} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def clean(exc: MtbudgetError):
    msg = str(exc)
    assert msg and "\n" not in msg and "\r" not in msg, f"not a one-line message: {msg!r}"
    return msg


# ============================================================================ quantities
#: unit -> (group, factor to the group's internal unit); written by hand, not by pint
UNITS = {
    "mm": ("length", 1.0), "m": ("length", 1000.0), "um": ("length", 1e-3), "µm": ("length", 1e-3),
    "in": ("length", 25.4), "cm": ("length", 10.0), "nm": ("length", 1e-6), "ft": ("length", 304.8),
    "rad": ("angle", 1.0), "urad": ("angle", 1e-6), "mrad": ("angle", 1e-3), "µrad": ("angle", 1e-6),
    "deg": ("angle", math.pi / 180), "arcsec": ("angle", math.pi / 648000), "arcmin": ("angle", math.pi / 10800),
    "s": ("time", 1.0), "min": ("time", 60.0), "h": ("time", 3600.0), "ms": ("time", 1e-3),
    "um/m": ("ratio", 1e-6), "mm/m": ("ratio", 1e-3), "ppm": ("ratio", 1e-6),
    "K/h": ("rate", 1 / 3600), "K/min": ("rate", 1 / 60), "K/s": ("rate", 1.0), "mK/s": ("rate", 1e-3),
    "degC/h": ("rate", 1 / 3600),
    "mm/min": ("speed", 1 / 60), "mm/s": ("speed", 1.0), "m/min": ("speed", 1000 / 60), "in/min": ("speed", 25.4 / 60),
    "um/(m*K)": ("cte", 1e-6), "1/K": ("cte", 1.0), "ppm/K": ("cte", 1e-6), "um/(m*degC)": ("cte", 1e-6),
    "um/h": ("drift", 1e-3 / 3600), "mm/h": ("drift", 1 / 3600), "um/s": ("drift", 1e-3),
    "K": ("kdiff", 1.0), "mK": ("kdiff", 1e-3), "delta_degC": ("kdiff", 1.0),
}
INTERNAL = {"length": "mm", "angle": "rad", "time": "s", "ratio": "mm/mm", "rate": "K/s", "speed": "mm/s",
            "cte": "1/K", "drift": "mm/s", "kdiff": "K"}
ABSOLUTE = {"degC": (1.0, 273.15), "K": (1.0, 0.0), "degF": (5 / 9, 273.15 - 32 * 5 / 9)}

numbers = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64),
    st.integers(-10**6, 10**6).map(float),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, 5e-324, 1.7976931348623157e308]),
)


@st.composite
def number_text(draw):
    x = draw(numbers)
    style = draw(st.sampled_from(["repr", "g", "e", "f"]))
    text = repr(x) if style == "repr" else format(x, {"g": ".6g", "e": ".3e", "f": ".4f"}[style])
    return text, float(text)


@st.composite
def quantity_texts(draw):
    """A quantity string with the value it must have, or None where nothing is expected."""
    kind = draw(st.sampled_from(["good", "good", "absolute", "garbage", "hostile"]))
    if kind == "good":
        (text, x), unit = draw(number_text()), draw(st.sampled_from(sorted(UNITS)))
        sep = draw(st.sampled_from([" ", "", "  ", "\t", "\u00a0"]))
        if sep == "" and unit[0] in "0123456789/":
            sep = " "
        group, f = UNITS[unit]
        return f"{text}{sep}{unit}", (INTERNAL[group], x * f, False)
    if kind == "absolute":
        (text, x), unit = draw(number_text()), draw(st.sampled_from(sorted(ABSOLUTE)))
        a, b = ABSOLUTE[unit]
        return f"{text} {unit}", ("K", a * x + b, True)
    if kind == "garbage":
        alphabet = st.sampled_from(list("0123456789.eE+-*/^() _µ°%abcdegKmnrsuμΩ,;\n\t\x00'\"[]{}#!") + ["**", "inf", "nan"])
        return "".join(draw(st.lists(alphabet, max_size=40))), None
    return draw(st.sampled_from([
        "9**9**9 um", "-9**9**9 mm", "5 mm**9**9**9", "5 " + "a" * 100 + "!", "5 " + "ab" * 55, "1e999 mm", "inf urad",
        "nan mm", "5 mm/inf", "5 (mm 3)", "5 mm 2", "20 delta_degC", "-300 degC", "1e400 um", "0x10 mm", "1_000 mm",
        "٥ mm", "５ mm", "5 mm)", "5 (mm", "((((((((((((((((((((mm))))))))))))))))))))", "5 " + "(" * 60 + "mm" + ")" * 59,
        "5e5e5 mm", "5 m" * 40, "5 mm/", "5 *mm", "5 mm^99", "5 mm**-9", "1 kelvin", "5 lightyear", "5 e", "5 %",
        "__import__('os')", "5 mm; rm -rf /", "{0}", "%s", "5 um/(m*K**2)", "5 1/K", "5 /K", "20 °C", "20 ° C",
    ])), None


@pytest.mark.parametrize("seed_class", ["quantities"])
@fuzz_settings(FAST_EXAMPLES * 8)
@given(case=quantity_texts(), target=st.sampled_from(sorted(set(INTERNAL.values()) | {"mm/K", "K", "rad", ""})))
def test_fuzz_quantity_parser(seed_class, case, target):
    check_quantity(case, target)


def check_quantity(case, target):
    text, expected = case
    absolute = bool(expected and expected[2])
    if expected is not None:
        target = expected[0]
    try:
        with time_limit(min(5.0, TIME_LIMIT)):
            value = to_internal(text, target, where="fuzz", absolute_temperature=absolute)
    except MtbudgetError as exc:
        msg = clean(exc)
        assert msg.startswith("fuzz: ")
        STATS["quantities"]["clean error"] += 1
        return
    assert math.isfinite(value), (text, value)
    if expected is None:
        STATS["quantities"]["accepted, no expectation"] += 1
        return
    assert value == pytest.approx(expected[1], rel=1e-12, abs=1e-300), (text, target, value, expected)
    STATS["quantities"]["accepted, equals the hand-computed value"] += 1


# ============================================================================ recordings
BASE = example_recording("null")
BASE_TOML = (BASE / "recording.toml").read_text(encoding="utf-8")
BASE_CSV = (BASE / "points.csv").read_text(encoding="utf-8")
BASE_LINES = BASE_CSV.splitlines()
HEADER = BASE_LINES[0].split(",")
BASE_REC = read_recording(BASE)

CELL_VALUES = ["", " ", "nan", "NaN", "inf", "-inf", "Infinity", "1e19", "1e400", "-1e400", "1e-400", "1,5", "1668,945719",
               "abc", "0", "-1", "+1", "1.0", "-1.0", "2", "0.5", "1.5", "-0", "  3  ", "1_000", "٣", "１", "0x1A", "1e5",
               "9" * 30, "-9" * 10, "1.7976931348623157e308", "\"1,5\"", "\"quoted\"", "'1'", "1;2", "µ", "°", "1 2",
               "-100", "300", "20", "-273.15", "1e6", "1e9", "999999999", "1000000000", "12.5e-3", ".5", "5.", "e5"]
UNIT_TEXT = ["mm", "in", "m", "um", "µm", "s", "min", "h", "degC", "degF", "K", "delta_degC", "rad", "", " ", "mm**9**9**9",
             "furlong", "°C", "furlongz", "mm/s", "1", "1/mm", "ms", "kelvin", "degR", "mm mm", "((mm)", "[mm]", "dimensionless"]

#: the naive reader's unit table: unit -> (factor, offset) to mm, s or K
NAIVE_UNITS = {"mm": (1.0, 0.0), "in": (25.4, 0.0), "m": (1000.0, 0.0), "um": (1e-3, 0.0), "µm": (1e-3, 0.0),
               "s": (1.0, 0.0), "min": (60.0, 0.0), "h": (3600.0, 0.0), "ms": (1e-3, 0.0),
               "degC": (1.0, 273.15), "°C": (1.0, 273.15), "K": (1.0, 0.0), "kelvin": (1.0, 0.0),
               "degF": (5 / 9, 273.15 - 32 * 5 / 9)}
NAIVE_TOML_UNITS = {"urad": 1e-6, "rad": 1.0, "mrad": 1e-3, "um": 1e-3, "mm": 1.0, "nm": 1e-6, "um/m": 1e-6,
                    "mm/m": 1e-3}


INVALID = "invalid"


def naive_read(toml_text: str, csv_bytes: bytes):
    """An independent reading of a simple recording, INVALID where it must be refused, or None where this
    naive reader does not apply."""
    try:
        text = csv_bytes.decode("utf-8")
    except UnicodeDecodeError:
        return None
    text = text[1:] if text.startswith("\ufeff") else text
    if '"' in text or "\r" in text.replace("\r\n", "\n"):
        return None
    lines = [ln for ln in text.replace("\r\n", "\n").split("\n") if ln.strip()]
    header = [h.strip() for h in lines[0].split(",")]
    cols = {}
    for j, h in enumerate(header):
        m = re.fullmatch(r"(\w+)\s*(?:\[\s*(.*?)\s*\])?", h)
        if not m:
            return None
        unit = m.group(2)
        if unit is not None and unit not in NAIVE_UNITS:
            return None
        cols[m.group(1)] = (j, NAIVE_UNITS.get(unit, (1.0, 0.0)))
    rows = [ln.split(",") for ln in lines[1:]]
    if not rows or any(len(r) != len(header) for r in rows):
        return INVALID  # a row with another number of cells than the header must be refused
    out = {}
    for name, (j, (f, off)) in cols.items():
        try:
            out[name] = np.array([float(r[j]) for r in rows]) * f + off
        except ValueError:
            return None
        if not np.all(np.isfinite(out[name])):
            return INVALID
    meta = {}
    for key in ("angular", "distance", "distance_per_length", "repeatability"):
        m = re.search(rf'^{key}\s*=\s*"\s*([0-9.eE+-]+)\s*([a-z/]+)\s*"\s*$', toml_text, re.M)
        if not m or m.group(2) not in NAIVE_TOML_UNITS:
            return None
        meta[key] = float(m.group(1)) * NAIVE_TOML_UNITS[m.group(2)]
    return out, meta


def same_as_naive(rec, naive):
    out, meta = naive
    p = rec.plan
    pairs = [(p.point, out["point"]), (p.run, out["run"]), (p.time, out["time"]), (p.nominal[:, 0], out["x"]),
             (p.nominal[:, 1], out["y"]), (p.nominal[:, 2], out["z"]), (p.direction[:, 0], out["dir_x"]),
             (p.direction[:, 1], out["dir_y"]), (p.direction[:, 2], out["dir_z"]), (p.tool[:, 0], out["tool_x"]),
             (p.tool[:, 1], out["tool_y"]), (p.tool[:, 2], out["tool_z"]), (rec.lt[:, 0], out["lt_x"]),
             (rec.lt[:, 1], out["lt_y"]), (rec.lt[:, 2], out["lt_z"])]
    pairs += [(p.temperature[c], out[c]) for c in p.temperature]
    for a, b in pairs:
        assert len(a) == len(b) and np.allclose(a, b, rtol=1e-12, atol=1e-12), "the reader and the naive reader differ"
    for key, v in meta.items():
        assert getattr(rec, key) == pytest.approx(v, rel=1e-12), key


def same_as_base(rec):
    a, b = BASE_REC, rec
    assert len(a) == len(b)
    for x, y in [(a.plan.point, b.plan.point), (a.plan.run, b.plan.run), (a.plan.time, b.plan.time),
                 (a.plan.nominal, b.plan.nominal), (a.plan.direction, b.plan.direction), (a.plan.tool, b.plan.tool),
                 (a.lt, b.lt)] + [(a.plan.temperature[c], b.plan.temperature[c]) for c in a.plan.temperature]:
        assert np.allclose(x, y, rtol=1e-12, atol=1e-9), "a harmless edit changed the numbers"
    for key in ("angular", "distance", "distance_per_length", "repeatability", "reference_temperature"):
        assert getattr(a, key) == pytest.approx(getattr(b, key), rel=1e-12)


def invariants(rec):
    p = rec.plan
    for arr in (p.time, p.nominal, p.tool, rec.lt, *p.temperature.values()):
        assert np.all(np.isfinite(arr))
    assert np.all(np.isin(p.direction, (-1.0, 1.0)))
    assert np.all(np.diff(p.time) >= 0) and np.all(p.time >= 0)
    assert p.point.dtype.kind == "i" and np.all(p.point >= 0)
    for T in p.temperature.values():
        assert np.all((T >= 200) & (T <= 400))


def set_cells(lines, edits):
    lines = list(lines)
    for line_no, j, value in edits:
        if line_no >= len(lines):
            continue
        cells = lines[line_no].split(",")
        if j < len(cells):
            cells[j] = value
        lines[line_no] = ",".join(cells)
    return lines


def join(lines, ending="\n"):
    return (ending.join(lines) + ending).encode("utf-8")


@st.composite
def recording_mutations(draw, kind):
    """(recording.toml text, points.csv bytes, whether the edit is harmless)."""
    toml, lines = BASE_TOML, list(BASE_LINES)
    n = len(lines)
    if kind == "bytes":
        which = draw(st.sampled_from(["csv", "csv", "csv", "toml"]))
        data = bytearray(join(lines) if which == "csv" else toml.encode())
        for _ in range(draw(st.integers(1, 3))):
            op = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
            i = draw(st.integers(0, max(0, len(data) - 1)))
            b = draw(st.integers(0, 255))
            if op == "flip" and data:
                data[i] ^= 1 << draw(st.integers(0, 7))
            elif op == "set" and data:
                data[i] = b
            elif op == "insert":
                data[i:i] = bytes([b])
            elif op == "delete" and data:
                del data[i]
            elif op == "truncate":
                del data[i:]
        if which == "csv":
            return toml, bytes(data), False
        return bytes(data), join(lines), False
    if kind == "cells":
        edits = [(draw(st.integers(1, n - 1)), draw(st.integers(0, len(HEADER) - 1)),
                  draw(st.one_of(st.sampled_from(CELL_VALUES), number_text().map(lambda t: t[0]))))
                 for _ in range(draw(st.integers(1, 3)))]
        return toml, join(set_cells(lines, edits)), False
    if kind == "rows":
        op = draw(st.sampled_from(["drop", "duplicate", "swap", "keep", "blank", "comma-row", "reverse"]))
        i, k = draw(st.integers(1, n - 1)), draw(st.integers(1, n - 1))
        if op == "drop":
            del lines[i:i + draw(st.integers(1, 5))]
        elif op == "duplicate":
            lines.insert(k, lines[i])
        elif op == "swap":
            lines[i], lines[k] = lines[k], lines[i]
        elif op == "keep":
            lines = lines[:draw(st.integers(0, 4))]
        elif op == "blank":
            lines.insert(k, draw(st.sampled_from(["", " ", "\t", ",,,", ","])))
            harmless = lines[k].strip() == ""
            return toml, join(lines), harmless
        elif op == "comma-row":
            lines[i] = lines[i] + ","
        else:
            lines = [lines[0]] + lines[1:][::-1]
        return toml, join(lines), False
    if kind == "header":
        head = list(HEADER)
        op = draw(st.sampled_from(["unit", "rename", "drop", "duplicate", "add", "space", "case"]))
        j = draw(st.integers(0, len(head) - 1))
        name = head[j].split(" [")[0]
        if op == "unit":
            head[j] = f"{name} [{draw(st.sampled_from(UNIT_TEXT))}]"
        elif op == "rename":
            head[j] = draw(st.sampled_from(["X", "lt_X", "T_air2", "station", "", "1x", "x y", "lt-x", "T_X", "point "])) + \
                (head[j][len(name):])
        elif op == "drop":
            del head[j]
            lines = [",".join(c for i, c in enumerate(ln.split(",")) if i != j) for ln in lines]
        elif op == "duplicate":
            head[draw(st.integers(0, len(head) - 1))] = head[j]
        elif op == "add":
            head.append(draw(st.sampled_from(["comment", "T_spindle [degC]", "humidity [percent]", "station"])))
            lines = [ln + ",1" for ln in lines]
        elif op == "space":
            head[j] = f"  {name}   [ {head[j][len(name):].strip(' []') or ''} ] ".replace("[  ]", "")
            if " [" not in HEADER[j]:
                head[j] = f"  {name}  "
            lines[0] = ",".join(head)
            return toml, join(lines), True
        else:
            head[j] = head[j].upper()
        lines[0] = ",".join(head)
        return toml, join(lines), False
    if kind == "encoding":
        op = draw(st.sampled_from(["latin1-mu", "latin1-degree", "utf16", "utf16-bom", "bom", "crlf", "cr", "semicolon",
                                   "nul", "cp1252-data", "utf32", "bom-crlf", "overlong"]))
        text = "\n".join(lines) + "\n"
        if op == "latin1-mu":
            return toml, text.replace("x [mm]", "x [µm]", 1).encode("latin-1"), False
        if op == "latin1-degree":
            return toml, text.replace("[degC]", "[°C]").encode("latin-1"), False
        if op == "utf16":
            return toml, text.encode("utf-16-le"), False
        if op == "utf16-bom":
            return toml, text.encode("utf-16"), False
        if op == "utf32":
            return toml, text.encode("utf-32"), False
        if op == "bom":
            return toml, codecs.BOM_UTF8 + text.encode(), True
        if op == "bom-crlf":
            return toml, codecs.BOM_UTF8 + text.replace("\n", "\r\n").encode(), True
        if op == "crlf":
            return toml, text.replace("\n", "\r\n").encode(), True
        if op == "cr":
            return toml, text.replace("\n", "\r").encode(), False
        if op == "semicolon":
            return toml, text.replace(",", ";").replace(".", ",").encode(), False
        if op == "nul":
            data = bytearray(text.encode())
            data[draw(st.integers(0, len(data) - 1))] = 0
            return toml, bytes(data), False
        if op == "overlong":
            return toml, (lines[0] + "\n" + "1" * 70000 + "\n").encode(), False
        i = draw(st.integers(1, n - 1))
        lines[i] = lines[i] + "\u00b5"
        return toml, ("\n".join(lines) + "\n").encode("cp1252"), False
    if kind == "harmless":
        op = draw(st.sampled_from(["inch", "reorder", "spaces", "ignored", "extra-key", "sensor-order"]))
        if op == "inch":
            j = draw(st.sampled_from([i for i, h in enumerate(HEADER) if h.endswith("[mm]")]))
            unit, f = draw(st.sampled_from([("in", 25.4), ("m", 1000.0), ("um", 1e-3)]))
            out = []
            for i, ln in enumerate(lines):
                cells = ln.split(",")
                cells[j] = cells[j].replace("[mm]", f"[{unit}]") if i == 0 else repr(float(cells[j]) / f)
                out.append(",".join(cells))
            return toml, join(out), True
        if op == "reorder":
            perm = draw(st.permutations(range(len(HEADER))))
            return toml, join([",".join(ln.split(",")[k] for k in perm) for ln in lines]), True
        if op == "spaces":
            rows = draw(st.lists(st.integers(1, n - 1), min_size=1, max_size=5))
            for i in rows:
                lines[i] = ",".join(f" {c} " for c in lines[i].split(","))
            return toml, join(lines), True
        if op == "ignored":
            toml = 'ignore_columns = ["operator"]\n' + toml
            return toml, join([ln + (",operator" if i == 0 else ",J. Doe; shift 2") for i, ln in enumerate(lines)]), True
        if op == "extra-key":
            return 'shop = "Hall 3"\n' + toml, join(lines), True
        return toml.replace('column = "T_x"', 'column = "TMP"').replace('column = "T_z"', 'column = "T_x"').replace(
            'column = "TMP"', 'column = "T_z"').replace('attached_to = "x axis"', 'attached_to = "TMP"').replace(
            'attached_to = "z axis"', 'attached_to = "x axis"').replace('attached_to = "TMP"', 'attached_to = "z axis"'), \
            join(lines), True
    # kind == "toml": values, types and keys of recording.toml
    key = draw(st.sampled_from(["format", "name", "machine", "description", "reference_temperature", "tracker.angular",
                                "tracker.distance", "tracker.distance_per_length", "machine_tool.repeatability",
                                "sensors.column", "sensors.attached_to", "sensors.position", "tracker", "machine_tool",
                                "sensors", "ignore_columns"]))
    value = draw(st.one_of(
        st.sampled_from(['"5 urad"', "5", "5.0", "inf", "nan", "-inf", "true", "[1, 2]", '["a"]', "{a = 1}", '"inf urad"',
                         '"-1 um"', '"0 um"', '"1e300 um"', '"1e-300 urad"', '"20 delta_degC"', '"-300 degC"', '"20 K"',
                         '"5 s"', '"9**9**9 um"', '""', '"x axis"', '"T_x"', '"spindle"', "1979-05-27", '"XYZ"', '"XFYZ"',
                         '"mtbudget-recording/2"', '"0.8"', '"5"', '"20 degC"', '"68 degF"', '"0.5 mm"', "-5", "0",
                         '"lt_x"', '"T y"', '"T_air"', '"point"']),
        quantity_texts().map(lambda c: json.dumps(c[0]))))
    table, _, name = key.rpartition(".")
    lines_t = toml.splitlines()
    if table == "sensors":
        idx = [i for i, ln in enumerate(lines_t) if ln.startswith(f"{name} =")] or [
            i for i, ln in enumerate(lines_t) if ln == "[[sensors]]"]
        i = draw(st.sampled_from(idx))
        if lines_t[i].startswith(f"{name} ="):
            lines_t[i] = f"{name} = {value}"
        else:
            lines_t.insert(i + 1, f"{name} = {value}")
    elif name in ("tracker", "machine_tool", "sensors"):
        header = "[[sensors]]" if name == "sensors" else f"[{name}]"
        if draw(st.booleans()):  # the table replaced by a value, or removed
            lines_t = [f"{name} = {value}"] + [ln for ln in lines_t if ln != header]
        else:
            lines_t = [ln for ln in lines_t if ln != header]
    else:
        prefix = f"[{table}]" if table else None
        found = [i for i, ln in enumerate(lines_t) if ln.startswith(f"{name} =")]
        if found and draw(st.booleans()):
            if draw(st.booleans()):
                lines_t[found[0]] = f"{name} = {value}"
            else:
                del lines_t[found[0]]
        else:
            at = lines_t.index(prefix) + 1 if prefix else 0
            lines_t.insert(at, f"{name} = {value}")
    return "\n".join(lines_t) + "\n", join(lines), False


RECORDING_CLASSES = ("bytes", "cells", "rows", "header", "encoding", "toml", "harmless")


def check_recording(kind, mutation):
    toml, csv_bytes, harmless = mutation
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "rec"
        folder.mkdir()
        (folder / "recording.toml").write_bytes(toml if isinstance(toml, bytes) else toml.encode("utf-8"))
        (folder / "points.csv").write_bytes(csv_bytes)
        try:
            with time_limit():
                rec = read_recording(folder)
        except MtbudgetError as exc:
            msg = clean(exc)
            assert not harmless, f"a harmless edit was refused: {msg}"
            assert "points.csv" in msg or "recording.toml" in msg or str(folder) in msg, msg
            STATS[f"recordings: {kind}"]["clean error"] += 1
            return
    invariants(rec)
    if harmless:
        same_as_base(rec)
        STATS[f"recordings: {kind}"]["read, equals the original"] += 1
        return
    toml_text = toml.decode("utf-8", errors="replace") if isinstance(toml, bytes) else toml
    naive = naive_read(toml_text, csv_bytes)
    assert naive is not INVALID, "read a recording the naive reader finds invalid (a row shifted, a value not finite)"
    if naive is None:
        STATS[f"recordings: {kind}"]["read, no independent expectation"] += 1
        return
    same_as_naive(rec, naive)
    STATS[f"recordings: {kind}"]["read, equals the naive reader"] += 1


@pytest.mark.parametrize("kind", RECORDING_CLASSES)
@fuzz_settings(FAST_EXAMPLES)
@given(data=st.data())
def test_fuzz_recordings(kind, data):
    check_recording(kind, data.draw(recording_mutations(kind)))


# ============================================================================ configurations
BASES = {"small": load_config(SMALL).source, "paper": load_config(default_config_path()).source}
BASE_SCENARIOS = {k: build_scenario(parse_config(copy.deepcopy(v))) for k, v in BASES.items()}
QUANTITY = re.compile(r"^\s*([+-]?[0-9.]+(?:[eE][+-]?[0-9]+)?)\s*(.*?)\s*$")


def paths(node, prefix=()):
    """Every path (tuple of keys and list indices) into a configuration dict."""
    out = []
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        out.append(prefix + (k,))
        out += paths(v, prefix + (k,))
    return out


def get(node, path):
    for k in path:
        node = node[k]
    return node


def put(node, path, value):
    get(node, path[:-1])[path[-1]] = value


VALUES = st.one_of(
    st.integers(-10**20, 10**20), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
    st.text(max_size=20), quantity_texts().map(lambda c: c[0]),
    st.lists(st.one_of(st.integers(-5, 5), quantity_texts().map(lambda c: c[0])), max_size=4),
    st.dictionaries(st.sampled_from(["x", "y", "z", "a", "enable", "angular", "start"]), st.integers(-3, 3), max_size=2),
    st.sampled_from(["0 mm", "-1 mm", "1e-300 mm", "1e300 mm", "1 mm", "0.001 mm", "1e-9 mm", "0 s", "-12 s", "1e9 s",
                     "0 mm/min", "-2000 mm/min", "1e-300 mm/min", "0 K", "-1 K", "1e6 K/h", "0 min", "-30 min",
                     "1e9 degC", "-300 degC", "20 delta_degC", "0.1 degC", "0 urad", "-5 urad", "1e300 urad", "5",
                     "inf urad", "nan mm", "9**9**9 um", "1e6 mm", "1e5 mm", "1000 mm", "10000", "", "x axis", "air",
                     "spindle", "XFYZ", "XYZ", "FXYZ", "ZYXF", "tracker_noise", "reversal", "nonsense"]),
)


def scale_quantity(text, factor_text):
    m = QUANTITY.match(text) if isinstance(text, str) else None
    if not m or not m.group(2):
        return None
    return f"{factor_text} {m.group(2)}"


def rewrite_harmless(text):
    """The same quantity in another unit of the hand table, converted here; None when the table has no other unit."""
    m = QUANTITY.match(text) if isinstance(text, str) else None
    if not m:
        return []
    x, unit = float(m.group(1)), m.group(2)
    if unit in ABSOLUTE:
        k = ABSOLUTE[unit][0] * x + ABSOLUTE[unit][1]
        return [f"{k!r} K", f"{(k - 273.15) * 9 / 5 + 32!r} degF"] if unit == "degC" else []
    if unit not in UNITS:
        return []
    group, f = UNITS[unit]
    return [f"{x * f / g!r} {u}" for u, (grp, g) in sorted(UNITS.items()) if grp == group and u != unit]


@st.composite
def config_mutations(draw, kind):
    base = draw(st.sampled_from(sorted(BASES)))
    raw = copy.deepcopy(BASES[base])
    all_paths = paths(raw)
    harmless = False
    if kind == "harmless":
        cands = [p for p in all_paths if rewrite_harmless(get(raw, p))]
        for p in draw(st.lists(st.sampled_from(cands), min_size=1, max_size=4, unique=True)):
            put(raw, p, draw(st.sampled_from(rewrite_harmless(get(raw, p)))))
        harmless = True
    else:
        for _ in range(draw(st.integers(1, 2))):
            all_paths = paths(raw) or [()]
            p = draw(st.sampled_from(all_paths))
            if kind == "values":
                leafs = [q for q in all_paths if isinstance(get(raw, q), (str, int, float))]
                p = draw(st.sampled_from(leafs))
                v = get(raw, p)
                new = draw(st.one_of(
                    st.sampled_from(["0", "-1", "1e-300", "1e300", "-1e300", "1e-12", "1e12", "nan", "inf", "2.5", "1e6",
                                     "-0.5", "1e19"]).map(lambda f, v=v: scale_quantity(v, f) or f),
                    quantity_texts().map(lambda c: c[0]),
                    st.integers(-100, 100), VALUES))
                put(raw, p, new)
            elif kind == "types":
                put(raw, p, draw(VALUES))
            elif kind == "keys":
                op = draw(st.sampled_from(["delete", "add", "rename", "newline-key", "move"]))
                parent = get(raw, p[:-1])
                if op == "delete":
                    del parent[p[-1]]
                elif isinstance(parent, dict):
                    if op == "add":
                        parent[draw(st.sampled_from(["extra", "D", "step", "enable", "seed", "x", "column", "1", ""]))] = \
                            draw(VALUES)
                    elif op == "rename":
                        parent[str(p[-1]) + draw(st.sampled_from(["s", "_", "X", " "]))] = parent.pop(p[-1])
                    elif op == "newline-key":
                        parent[f"bad\nkey{p[-1]}"] = parent.pop(p[-1])
                    else:
                        value = parent.pop(p[-1])
                        target = draw(st.sampled_from([q for q in paths(raw) if isinstance(get(raw, q), dict)] or [()]))
                        get(raw, target)[p[-1]] = value
            else:  # units: a unit swapped for another (of another dimension, or none)
                leafs = [q for q in all_paths if isinstance(get(raw, q), str) and QUANTITY.match(get(raw, q))]
                p = draw(st.sampled_from(leafs))
                m = QUANTITY.match(get(raw, p))
                put(raw, p, f"{m.group(1)} {draw(st.sampled_from(sorted(UNITS) + sorted(ABSOLUTE) + ['', 'furlong']))}")
    return base, raw, harmless


CONFIG_CLASSES = ("values", "types", "keys", "units", "harmless")


def naive_plan_rows(raw):
    """Rows of the plan counted from the configuration by hand (None where this does not apply)."""
    try:
        mesh, plan = raw["mesh"], raw.get("plan", {})
        n = 1
        for a in "xyz":
            lo, hi = (naive_mm(v) for v in mesh[a])
            step = naive_mm(mesh.get(f"step_{a}", mesh.get("step")))
            n *= int(round((hi - lo) / step)) + 1
        return n * plan.get("runs", 2) * len(plan.get("tools", [0]))
    except Exception:
        return None


def naive_mm(text):
    m = QUANTITY.match(text)
    return float(m.group(1)) * UNITS[m.group(2)][1] if UNITS[m.group(2)][0] == "length" else None


def check_config(kind, mutation):
    base, raw, harmless = mutation
    stats = STATS[f"configurations: {kind}"]
    try:
        with time_limit():
            cfg = parse_config(raw, SMALL if base == "small" else default_config_path())
            sc = build_scenario(cfg)
    except MtbudgetError as exc:
        clean(exc)
        assert not harmless, f"a harmless edit was refused: {exc}"
        stats["clean error"] += 1
        return
    p = sc.plan
    for arr in (p.time, p.nominal, p.tool, sc.theta, sc.pose, *p.temperature.values()):
        assert np.all(np.isfinite(arr)), "a scenario with non-finite numbers"
    rows = naive_plan_rows(raw)
    if rows is not None:
        assert len(p) == rows, (len(p), rows)
    if harmless:
        b = BASE_SCENARIOS[base]
        for x, y in [(b.plan.nominal, p.nominal), (b.plan.time, p.time), (b.plan.tool, p.tool), (b.theta, sc.theta),
                     (b.pose, sc.pose)] + [(b.plan.temperature[c], p.temperature[c]) for c in b.plan.temperature]:
            assert np.allclose(x, y, rtol=1e-9, atol=1e-12), "a harmless edit changed the scenario"
        assert np.allclose([b.noise.angular, b.noise.distance, b.noise.distance_per_length, b.noise.repeatability],
                           [sc.noise.angular, sc.noise.distance, sc.noise.distance_per_length, sc.noise.repeatability],
                           rtol=1e-9)
    # what `mtbudget simulate` writes must read back, with the same points
    with tempfile.TemporaryDirectory() as tmp:
        try:
            with time_limit():
                rec, truth = simulate_recording(sc)
        except MtbudgetError as exc:
            clean(exc)
            stats["scenario built, simulation refused cleanly"] += 1
            return
        write_recording(rec, Path(tmp) / "sim")
        back = read_recording(Path(tmp) / "sim")
        assert np.abs(back.lt - rec.lt).max() <= 0.5e-6 + 1e-9 * np.abs(rec.lt).max()
    stats["built; simulated recording reads back" + (", equals the original" if harmless else "")] += 1


@pytest.mark.parametrize("kind", CONFIG_CLASSES)
@fuzz_settings(FAST_EXAMPLES)
@given(data=st.data())
def test_fuzz_configurations(kind, data):
    check_config(kind, data.draw(config_mutations(kind)))


# ============================================================================ the large fuzz
@pytest.mark.slow
def test_fuzz_large_and_report():
    """Thousands of inputs per class; prints the table of docs/reliability.md (and writes it as JSON when
    MTBUDGET_FUZZ_REPORT names a file)."""
    STATS.clear()
    n = SLOW_EXAMPLES

    @fuzz_settings(n * 4)
    @given(case=quantity_texts(), target=st.sampled_from(sorted(set(INTERNAL.values()) | {"mm/K", "K", "rad", ""})))
    def quantities(case, target):
        check_quantity(case, target)

    quantities()
    for kind in RECORDING_CLASSES:
        @fuzz_settings(n)
        @given(data=st.data())
        def recordings(data):
            check_recording(kind, data.draw(recording_mutations(kind)))

        recordings()
    for kind in CONFIG_CLASSES:
        @fuzz_settings(max(n // 3, 1))
        @given(data=st.data())
        def configurations(data):
            check_config(kind, data.draw(config_mutations(kind)))

        configurations()
    table = {cls: dict(c) for cls, c in sorted(STATS.items())}
    print()
    for cls, counts in table.items():
        print(f"{cls:32s} tried {sum(counts.values()):6d}  " + "; ".join(f"{k}: {v}" for k, v in sorted(counts.items())))
    out = os.environ.get("MTBUDGET_FUZZ_REPORT")
    if out:
        Path(out).write_text(json.dumps(table, indent=1))
