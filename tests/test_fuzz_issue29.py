"""Fuzzing the holes issue 29 found: cut files, temperature scales, [placement], angles vs ratios, overlays.

Every input ends in a clean one-line mtbudget error or in a result equal to an expectation computed here by hand
(never by the code under test); none may raise anything else, hang (a time limit per input) or be read silently
wrong.  The default suite tries a few inputs per class; ``-m slow`` tries 1250 (250 per class) and prints the
counts (MTBUDGET_FUZZ29_REPORT=FILE writes them as JSON):

    python -m pytest -m slow tests/test_fuzz_issue29.py -q -s
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mtbudget.config import SCHEMA, load_config, parse_config
from mtbudget.errors import MtbudgetError
from mtbudget.recording import read_recording
from mtbudget.scenario import build_scenario

from test_fuzz import BASE_LINES, BASE_REC, BASE_TOML, HEADER, clean, fuzz_settings, same_as_base, time_limit

SMALL = Path(__file__).parent / "data" / "small.toml"
FAST = int(os.environ.get("MTBUDGET_FUZZ_FAST", "8"))
SLOW = int(os.environ.get("MTBUDGET_FUZZ29_SLOW", "250"))
COUNTS: dict = defaultdict(Counter)

#: hand-written factors to the internal unit (mm, rad, mm/mm): not pint
ANGLE = {"rad": 1.0, "mrad": 1e-3, "urad": 1e-6, "deg": math.pi / 180, "arcsec": math.pi / 648000}
RATIO = {"ppm": 1e-6, "um/m": 1e-6, "mm/m": 1e-3, "percent": 1e-2}
LENGTH = {"mm": 1.0, "m": 1e3, "um": 1e-3, "in": 25.4}
ODD = ["furlongz", "s", "K", "degC", "", "mm**9**9", "nan", "5", "urad/s", "1/mm"]


def _read(csv_bytes: bytes):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "rec"
        folder.mkdir()
        (folder / "recording.toml").write_text(BASE_TOML)
        (folder / "points.csv").write_bytes(csv_bytes)
        with time_limit():
            return read_recording(folder)


def _outcome(cls: str, fn):
    """('error', message) or ('read', value); anything else escapes and fails the test."""
    try:
        value = fn()
    except MtbudgetError as exc:
        COUNTS[cls]["clean error"] += 1
        return "error", clean(exc)
    return "read", value


# ------------------------------------------------------------------ 1. a file cut anywhere in its last rows
@st.composite
def cut_files(draw):
    rows = draw(st.integers(3, len(BASE_LINES) - 1))  # the first rows of the file ...
    data = ("\n".join(BASE_LINES[:rows + 1]) + "\n").encode()
    if draw(st.booleans()):  # ... cut anywhere in its last row, or at its end without the final newline
        cut = data[:len(data) - draw(st.integers(1, len(BASE_LINES[rows]) + 1))]
    else:
        cut = data
    if draw(st.booleans()):
        cut = cut.replace(b"\n", b"\r\n")
    return cut


def check_cut(cut: bytes):
    kind, got = _outcome("cut files", lambda: _read(cut))
    complete = cut.endswith(b"\n")
    if kind == "error":
        assert not complete or cut.count(b"\n") < 4, f"a file of complete rows was refused: {got}"
        return
    assert complete, "a file whose last row is cut was read (a number cut mid-way reads as another number)"
    rows = [ln for ln in cut.decode().replace("\r\n", "\n").split("\n")[1:] if ln.strip()]
    assert len(got) == len(rows)
    want = np.array([[float(c) for c in r.split(",")[12:15]] for r in rows])
    assert np.array_equal(got.lt, want), "the kept rows must read exactly as written"
    COUNTS["cut files"]["read, every row as written"] += 1


@fuzz_settings(FAST)
@given(cut=cut_files())
def test_fuzz_cut_files(cut):
    check_cut(cut)


# ------------------------------------------------------------------ 2. temperature columns on another scale
TEMPS = [j for j, h in enumerate(HEADER) if h.startswith("T_")]


@st.composite
def temperature_scales(draw):
    j = draw(st.sampled_from(TEMPS))
    unit = draw(st.sampled_from(["degF", "K", "degC"]))
    converted = draw(st.booleans())  # the values converted by hand to the header's unit, or left in degC
    rows = draw(st.integers(3, len(BASE_LINES) - 1))  # the first rows
    out = []
    for i, ln in enumerate(BASE_LINES[:rows + 1]):
        cells = ln.split(",")
        if i == 0:
            cells[j] = cells[j].replace("[degC]", f"[{unit}]")
        elif converted:
            t = float(cells[j])
            cells[j] = repr(t * 9 / 5 + 32 if unit == "degF" else t + 273.15 if unit == "K" else t)
        out.append(",".join(cells))
    return ("\n".join(out) + "\n").encode(), converted or unit == "degC"


def check_scale(case):
    data, right = case
    kind, got = _outcome("temperature scales", lambda: _read(data))
    if right:
        assert kind == "read", f"a correctly converted temperature column was refused: {got}"
        n = len(got)
        assert n == len(BASE_REC) or n < len(BASE_REC)
        for c in BASE_REC.plan.temperature:
            assert np.allclose(got.plan.temperature[c], BASE_REC.plan.temperature[c][:n], rtol=1e-12, atol=1e-9)
        assert np.array_equal(got.lt, BASE_REC.lt[:n])
        COUNTS["temperature scales"]["read, equals the original rows"] += 1
    else:
        assert kind == "error", "degC readings under a degF or K header were read as another temperature"


@fuzz_settings(FAST)
@given(case=temperature_scales())
def test_fuzz_temperature_scales(case):
    check_scale(case)


# ------------------------------------------------------------------ 3. [placement], checked by every command
PLACEMENT_LENGTHS = ("range_min", "range_max")


@st.composite
def placements(draw):
    keys = list(SCHEMA["placement"])
    op = draw(st.sampled_from(["typo", "length", "pair", "reading", "count", "noise"]))
    if op == "typo":
        k = draw(st.sampled_from(keys))
        bad = draw(st.sampled_from([k + "x", k.upper() if k.upper() != k else k + "_", k[:-1] or "q", "x" + k]))
        return {bad: "1 m"}, None
    if op == "length":
        k = draw(st.sampled_from(PLACEMENT_LENGTHS))
        x, unit = draw(st.floats(0.1, 50, allow_nan=False)), draw(st.sampled_from(sorted(LENGTH) + ODD))
        want = x * LENGTH[unit] if unit in LENGTH else None
        other = {"range_min": "1e-6 mm"} if k == "range_max" else {"range_max": "1000 m"}
        return {k: f"{x!r} {unit}".strip(), **other}, (k, want)
    if op == "pair":
        k = draw(st.sampled_from(["D", "L", "H"]))
        v = draw(st.sampled_from([["-1 m", "1 m"], ["1 m", "-1 m"], "5 m", ["1 s", "2 s"], ["nan mm", "1 mm"], ["1 m"]]))
        ok = v == ["-1 m", "1 m"]
        return {k: v}, (k, [-1000.0, 1000.0]) if ok else None
    if op == "reading":
        k = draw(st.sampled_from(["directions", "eq23", "eq27"]))
        v = draw(st.sampled_from(["machine", "envelope", "polar", "elevation", "compensated", "residual", "Machine", ""]))
        return {k: v}, (k, v) if v in {"directions": ("machine", "envelope"), "eq23": ("polar", "elevation"),
                                       "eq27": ("compensated", "compensated_rigid", "residual")}[k] else None
    if op == "count":
        k = draw(st.sampled_from(["tests", "candidates"]))
        v = draw(st.sampled_from([0, -3, 2.5, "10", True, 17]))
        return {k: v}, (k, v) if v == 17 else None
    return {draw(st.sampled_from(["angular_mean", "distance", "angular_sd"])): "1 urad"}, None


def check_placement(case):
    table, want = case
    raw = copy.deepcopy(load_config(SMALL).source)
    raw["placement"] = table
    kind, got = _outcome("placement", lambda: parse_config(raw, SMALL))
    if want is None or (isinstance(want, tuple) and want[1] is None):
        assert kind == "error", f"[placement] {table} was accepted"
        assert "placement." in got, got
        return
    assert kind == "read", f"[placement] {table} was refused: {got}"
    COUNTS["placement"]["read"] += 1


@fuzz_settings(FAST)
@given(case=placements())
def test_fuzz_placement(case):
    check_placement(case)


# ------------------------------------------------------------------ 4. angles and ratios
KEYS = {"tracker.a": "angle", "tracker.angular": "angle", "tracker.distance_per_length": "ratio",
        "sources.tracker_noise.angular_sd": "angle"}


@st.composite
def angle_ratio(draw):
    key = draw(st.sampled_from(sorted(KEYS)))
    unit = draw(st.sampled_from(sorted(ANGLE) + sorted(RATIO)))
    x = draw(st.floats(0.0, 5.0, allow_nan=False))
    return key, f"{x!r} {unit}", x, unit


def check_angle_ratio(case):
    key, text, x, unit = case
    raw = copy.deepcopy(load_config(SMALL).source)
    raw["sources"]["tracker_noise"].pop("angular_mean", None)  # tracker.angular stated once, so it may change
    node = raw
    for part in key.split(".")[:-1]:
        node = node.setdefault(part, {})
    node[key.split(".")[-1]] = text
    kind, got = _outcome("angles and ratios", lambda: build_scenario(parse_config(raw, SMALL)))
    same_kind = (unit in ANGLE) == (KEYS[key] == "angle")
    if not same_kind:
        assert kind == "error" and ("not an angle" in got or "not a ratio" in got), f"{key} = {text!r}: {got}"
        return
    if kind == "error":  # the right kind, refused for its size (an implausible uncertainty): said so
        assert key.split(".")[-1] in got, got
        return
    factor = ANGLE.get(unit) or RATIO[unit]
    cfg = got.config
    if key == "tracker.a":
        assert cfg.pose[3] == pytest.approx(x * factor, rel=1e-12, abs=1e-300)
    elif key == "tracker.angular":
        assert cfg.angular == pytest.approx(x * factor, rel=1e-12, abs=1e-300)
    elif key == "tracker.distance_per_length":
        assert cfg.distance_per_length == pytest.approx(x * factor, rel=1e-12, abs=1e-300)
    else:
        src = {s.name: s for s in got.sources}["tracker_noise"]
        assert src.value("angular_sd", "rad") == pytest.approx(x * factor, rel=1e-12, abs=1e-300)
    COUNTS["angles and ratios"]["read, equals the hand-computed value"] += 1


@fuzz_settings(FAST)
@given(case=angle_ratio())
def test_fuzz_angles_and_ratios(case):
    check_angle_ratio(case)


# ------------------------------------------------------------------ 5. overlays: extends and --set
def _leaves(node, prefix=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, prefix + (k,))
    elif not isinstance(node, list):
        yield prefix, node


SMALL_RAW = load_config(SMALL).source
LEAVES = [(".".join(p), v) for p, v in _leaves(SMALL_RAW) if p[0] != "format"]


@st.composite
def overlays(draw):
    key, value = draw(st.sampled_from(LEAVES))
    op = draw(st.sampled_from(["same", "typo", "garbage"]))
    if op == "same":  # the file's own value again: the configuration must not change
        return key, json.dumps(value) if isinstance(value, str) else json.dumps(value), True
    if op == "typo":
        parts = key.split(".")
        parts[-1] = parts[-1] + draw(st.text("abcdefghijklmnopqrstuvwxyz_0123456789", min_size=1, max_size=3))
        return ".".join(parts), json.dumps(value), False
    junk = draw(st.one_of(st.sampled_from(['"5 furlongz"', "[1, 2]", '"nan mm"', "{a = 1}", '"-1e400 um"', "true"]),
                          st.builds(lambda x, u: json.dumps(f"{x!r} {u}"), st.floats(-1e6, 1e6, allow_nan=False),
                                    st.sampled_from(sorted(ANGLE) + sorted(RATIO) + sorted(LENGTH) + ODD))))
    return key, junk, None


def check_overlay(case):
    key, text, same = case
    with tempfile.TemporaryDirectory() as tmp:
        over = Path(tmp) / "over.toml"
        over.write_text(f'extends = "{SMALL}"\n')
        kind, got = _outcome("overlays", lambda: build_scenario(load_config(over, [f"{key}={text}"])))
    if same:
        assert kind == "read", f"--set {key}={text} (the same value) was refused: {got}"
        assert got.config.source == SMALL_RAW
        COUNTS["overlays"]["read, equals the base"] += 1
    elif same is False:
        assert kind == "error" and ("unknown key" in got or "unknown parameter" in got), f"--set {key}={text}: {got}"
    elif kind == "read":
        COUNTS["overlays"]["read (a value the key takes)"] += 1


@fuzz_settings(FAST)
@given(case=overlays())
def test_fuzz_overlays(case):
    check_overlay(case)


# ------------------------------------------------------------------ the campaign
@pytest.mark.slow
def test_fuzz_issue29_campaign():
    """1250 new inputs (250 per class): 0 tracebacks, 0 hangs, 0 silent wrong results; counts printed."""
    COUNTS.clear()
    for strategy, check in ((cut_files(), check_cut), (temperature_scales(), check_scale), (placements(), check_placement),
                            (angle_ratio(), check_angle_ratio), (overlays(), check_overlay)):
        @fuzz_settings(SLOW)
        @given(case=strategy)
        def one(case):
            check(case)

        one()
    table = {cls: dict(c) for cls, c in sorted(COUNTS.items())}
    total = sum(sum(c.values()) for c in table.values())
    print()
    for cls, counts in table.items():
        print(f"{cls:24s} tried {sum(counts.values()):5d}  " + "; ".join(f"{k}: {v}" for k, v in sorted(counts.items())))
    print(f"total {total}")
    out = os.environ.get("MTBUDGET_FUZZ29_REPORT")
    if out:
        Path(out).write_text(json.dumps(table, indent=1))
    assert total >= 5 * SLOW * 0.9  # hypothesis may draw a few duplicates
