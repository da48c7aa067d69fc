"""The one pint registry of mtbudget, the one quantity parser and the one display helper.

Everything that crosses the boundary (configs, recordings, plugin outputs,
results) carries pint quantities.  Inside, every array is plain float64 in
one fixed system: **mm, rad, K, s** (temperatures as absolute kelvin).
Conversion happens once on the way in (:func:`to_internal`, built on
:func:`parse_quantity`) and once on the way out (:func:`display`,
:func:`factor`).  No other module hard-codes a conversion factor.

The parser is strict on purpose (a wrong unit must never become a silently
wrong number): only strings, numbers and pint quantities are accepted; a
string is checked against a small grammar before pint sees it (no exponent
towers such as ``9**9**9``); the magnitude must be finite; an angle needs an
explicit unit (pint treats radians as dimensionless, so a bare ``5`` would
otherwise be 5 rad); and an absolute temperature refuses a temperature
difference unit (``delta_degC``).
"""

from __future__ import annotations

import math
import re
from functools import lru_cache

import numpy as np
import pint

ureg = pint.UnitRegistry(autoconvert_offset_to_baseunit=True)
ureg.formatter.default_format = "~P"
Q_ = ureg.Quantity
pint.set_application_registry(ureg)

#: internal unit of each physical dimension used in the model
INTERNAL = {
    "[length]": "mm",
    "": "rad",  # angles (pint treats radians as dimensionless)
    "[temperature]": "K",
    "[time]": "s",
    "[length] / [temperature]": "mm/K",
    "[length] / [time]": "mm/s",
    "1 / [temperature]": "1/K",
    "[temperature] / [time]": "K/s",
    "1 / [time]": "1/s",  # a rate of an angle or a ratio (urad/h: a tracker's zero turning in time)
}

#: how a quantity string may look: a number (with an optional exponent), then a
#: unit expression of words, spaces, * / ( ) and single-digit powers (** or ^); ``1/`` may open it.
#: The string is split into tokens by one linear scan (no regular expression with nested
#: repetition, which backtracks exponentially on a long word that fails), the number is read by
#: ``float`` and the unit expression by ``ureg.parse_units``: pint never evaluates an expression.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_TOKEN = re.compile(r"(?P<word>%|°[A-Za-z]*|[A-Za-zµμΩ][A-Za-z0-9_]*)(?P<power>[ ]*(?:\*\*|\^)[ ]*[+-]?[0-9](?![0-9]))?"
                    r"|(?P<one>1(?=[ ]*/))|(?P<op>[*/()])|(?P<space>[ ]+)")
_SPACES = str.maketrans({"\t": " ", "\u00a0": " ", "\u202f": " ", "\u2009": " "})
_NOT_UNITS = {"inf", "infinity", "nan"}
_MAX_TEXT = 120
#: the plausible range of an absolute temperature (K): a machine shop, not a cryostat or a furnace.
#: A value outside it is almost always a unit mix-up (a K column holding degC readings, -300 degC).
ABSOLUTE_TEMPERATURE = (200.0, 400.0)


def _fail(error, message):
    from .errors import UnitError

    raise (error or UnitError)(message)


def _clip(value, n: int = 60) -> str:
    """repr of ``value`` on one line, shortened to about ``n`` characters."""
    r = repr(value)
    return r if len(r) <= n else r[: n - 5] + "..." + r[-2:]


def _split(text: str):
    """(number text or None, unit text, lower-case unit words) of a quantity string, or None when it does
    not follow the grammar."""
    text = text.translate(_SPACES).strip()
    m = _NUMBER.match(text)
    number = m.group(0) if m else None
    pos = m.end() if m else 0
    depth, words = 0, []
    while pos < len(text):
        t = _TOKEN.match(text, pos)
        if t is None:
            return None
        if t.group("word"):
            words.append(t.group("word").lower())
        elif t.group("op") == "(":
            depth += 1
        elif t.group("op") == ")":
            depth -= 1
            if depth < 0:
                return None
        pos = t.end()
    if depth:
        return None
    return number, text[m.end() if m else 0:].strip(), words


def parse_unit(text, *, where: str = "unit", error=None):
    """Parse a unit expression ("mm", "um/(m*K)", "degC") into a pint Unit through the same grammar.

    A unit made of several factors reads an offset temperature unit as a difference (pint's
    ``as_delta``): ``degC/h`` is ``delta_degC/h``.
    """
    if not isinstance(text, str):
        _fail(error, f"{where}: expected a unit such as \"mm\", got {type(text).__name__} {_clip(text)}")
    parts = _split(text) if len(text) <= _MAX_TEXT else None
    if parts is not None and parts[0] == "1" and parts[1].startswith("/"):  # "1/K"
        parts = (None,) + parts[1:]
    if parts is None or parts[0] is not None or not parts[1]:
        _fail(error, f"{where}: {_clip(text)} is not a unit expression (for example \"mm\", \"um/m\" or \"degC\")")
    return _units(parts, text, where, error)


def _units(parts, value, where, error):
    _, unit_text, words = parts
    if set(words) & _NOT_UNITS:
        _fail(error, f"{where}: {_clip(value)} is not finite")
    if unit_text.startswith("/"):
        unit_text = "1" + unit_text
    try:
        return ureg.parse_units(unit_text)
    except Exception as exc:  # pint raises several types (and AssertionError on a dangling operator)
        kind = "unknown unit" if isinstance(exc, pint.UndefinedUnitError) else "cannot parse the unit"
        _fail(error, f"{where}: {_clip(value)}: {kind} {_clip(unit_text)}")


def parse_quantity(value, *, where: str = "value", error=None) -> pint.Quantity:
    """Parse ``value`` ("5 um", "20 degC", 0.5, a Quantity) into a finite pint Quantity.

    ``error`` is a callable that builds the exception to raise from a message
    (default :class:`~mtbudget.errors.UnitError`); the message starts with
    ``where``.
    """
    if isinstance(value, pint.Quantity):
        q = value
    elif isinstance(value, bool) or not isinstance(value, (str, int, float, np.floating, np.integer)):
        _fail(error, f"{where}: expected a quantity string such as \"5 um\", got {type(value).__name__} {_clip(value)}")
    elif isinstance(value, str):
        if not value.strip():
            _fail(error, f"{where}: empty quantity; expected for example \"5 um\"")
        parts = _split(value) if len(value) <= _MAX_TEXT else None
        if parts is None or parts[0] is None:
            if parts is not None and set(parts[2]) & _NOT_UNITS:
                _fail(error, f"{where}: {_clip(value)} is not finite")
            _fail(error, f"{where}: {_clip(value)} is not a quantity of the form NUMBER UNIT (for example \"5 um\" or \"0.8 um/m\")")
        mag = float(parts[0])
        q = Q_(mag, _units(parts, value, where, error)) if parts[1] else Q_(mag)
    else:
        try:
            q = Q_(float(value))
        except OverflowError:
            _fail(error, f"{where}: {_clip(value)} is not finite")
    try:
        mag = np.asarray(q.magnitude, dtype=float)
    except (TypeError, ValueError):
        _fail(error, f"{where}: {_clip(value)} does not have a numeric magnitude")
    if not np.all(np.isfinite(mag)):
        _fail(error, f"{where}: {_clip(value)} is not finite")
    return q


def _has_unit(value) -> bool:
    """Whether ``value`` states a unit (a bare number or "5" does not)."""
    if isinstance(value, pint.Quantity):
        return not value.unitless
    if isinstance(value, str):
        parts = _split(value)
        return bool(parts and parts[1])
    return False


def is_offset_temperature(q) -> bool:
    """Whether the quantity ``q`` is on an offset temperature scale (degC, degF) alone: an absolute reading.

    ``"0.1 degC"`` is such a quantity: pint converts it to 273.25 K.  A temperature *difference* is written in
    K or ``delta_degC``; units in a product (``um/(m*degC)``) are read as differences by :func:`parse_unit`.
    """
    return isinstance(q, pint.Quantity) and _offset_alone(q)


def is_temperature_difference_unit(q) -> bool:
    """Whether the quantity ``q`` has a ``delta_*`` unit (``delta_degC``, ``delta_degF``): a temperature difference."""
    return isinstance(q, pint.Quantity) and any(name.startswith("delta_") for name, _ in q.unit_items())


def _offset_alone(q) -> bool:
    """Whether ``q`` is on an offset temperature scale (degC, degF) alone: an absolute reading."""
    items = list(q.unit_items())
    return len(items) == 1 and items[0][1] == 1 and _is_offset(items[0][0])


@lru_cache(maxsize=64)
def _is_offset(name: str) -> bool:
    return Q_(0.0, name).to_base_units().magnitude != 0


def _is_angle(q) -> bool:
    """Whether a quantity (or unit) is an angle: its root unit is the radian (rad, deg, arcsec, urad/s * s ...)."""
    return (q if isinstance(q, pint.Quantity) else Q_(1.0, q)).to_root_units().units == ureg.radian


def angle_or_ratio_problem(q, expected) -> str | None:
    """None, or why ``q`` (with a unit) does not fit ``expected`` (a unit or quantity of dimension 1): pint counts
    angles and ratios alike, but 0.8 ppm is no angle and 5 urad no ratio (a slope of 1 um/m is an angle of 1 urad,
    and a ratio has to be written as one)."""
    if not isinstance(q, pint.Quantity) or not dict(q.unit_items()) or not q.dimensionless:
        return None  # (pint's `unitless` is also true of ppm and percent)
    want_angle = _is_angle(expected)
    if want_angle and not _is_angle(q):
        return "is a ratio, not an angle; write the angle in an angle unit (urad, mrad, deg, arcsec; a slope of 1 um/m " \
               "is 1 urad)"
    if not want_angle and _is_angle(q):
        return "is an angle, not a ratio; write the ratio as one (um/m, ppm, percent)"
    return None


def to_internal(value, unit: str, *, where: str = "value", error=None, absolute_temperature: bool = False) -> float:
    """Parse ``value`` and return its magnitude in ``unit`` (a plain float).

    An angle or a ratio (``unit`` rad, deg, urad, mm/mm ...) needs an explicit
    unit.  A temperature is an absolute temperature when
    ``absolute_temperature=True``: it refuses ``delta_*`` units and values
    outside :data:`ABSOLUTE_TEMPERATURE`; otherwise it is a temperature
    difference, which refuses an offset scale alone ("0.1 degC" is ambiguous:
    write "0.1 K" or "0.1 delta_degC").
    """
    q = parse_quantity(value, where=where, error=error)
    target = ureg.Unit(unit)
    if target.dimensionality != q.dimensionality:
        _fail(error, f"{where}: {_show(value)} is not a quantity of {_dimension(target)} (for example {unit})")
    if target.dimensionless and unit.strip() not in ("", "1", "dimensionless") and not _has_unit(value):
        what = "an angle" if Q_(1.0, unit).to_root_units().units == ureg.radian else "a ratio"
        _fail(error, f"{where}: {_show(value)} needs an explicit unit (for example \"{_show_bare(value)} {unit}\"); "
                     f"a bare number is ambiguous for {what}")
    if unit.strip() in ("", "1", "dimensionless") and not q.unitless and q.to_root_units().units == ureg.radian:
        _fail(error, f"{where}: {_show(value)} is an angle; expected a plain number")
    if target.dimensionless and unit.strip() not in ("", "1", "dimensionless"):
        problem = angle_or_ratio_problem(q, unit)
        if problem:
            _fail(error, f"{where}: {_show(value)} {problem}")
    temperature = target.dimensionality == ureg.kelvin.dimensionality
    if absolute_temperature and any(name.startswith("delta_") for name, _ in q.unit_items()):
        _fail(error, f"{where}: {_show(value)} is a temperature difference; give an absolute temperature such as \"20 degC\"")
    if temperature and not absolute_temperature and _offset_alone(q):
        _fail(error, f"{where}: {_show(value)} is a temperature difference on an offset scale, which is ambiguous; "
                     f"write it in K or delta_degC (for example \"{_show_bare(q.magnitude)} K\")")
    try:
        out = q.to(target).magnitude
    except Exception as exc:  # pint: an offset unit in a product, a logarithmic unit ...
        _fail(error, f"{where}: {_show(value)} cannot be converted to {unit} ({type(exc).__name__})")
    if np.ndim(out) == 0 and not math.isfinite(float(out)) or np.ndim(out) and not np.all(np.isfinite(out)):
        _fail(error, f"{where}: {_show(value)} is not finite in {unit}")
    if absolute_temperature and temperature:
        k = np.asarray(q.to("K").magnitude, float)
        lo, hi = ABSOLUTE_TEMPERATURE
        if np.any(k < lo) or np.any(k > hi):
            bad = float(k.flat[np.flatnonzero((k < lo) | (k > hi))[0]])
            _fail(error, f"{where}: {_show(value)} ({bad:.6g} K, {bad - 273.15:.6g} degC) is not a plausible absolute "
                         f"temperature; expected {lo:g} K to {hi:g} K ({lo - 273.15:g} degC to {hi - 273.15:g} degC)")
    return float(out) if np.ndim(out) == 0 else np.asarray(out, float)


def _show_bare(value) -> str:
    return f"{value:g}" if isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool) \
        else str(value).strip()[:40]


def _show(value) -> str:
    return _clip(f"{value:~P}") if isinstance(value, pint.Quantity) else _clip(value)


def _dimension(unit) -> str:
    d = str(unit.dimensionality)
    return "dimension 1 (a ratio or an angle)" if d == "dimensionless" else f"dimension {d}"


@lru_cache(maxsize=256)
def factor(from_unit: str, to_unit: str) -> float:
    """Multiplier from ``from_unit`` to ``to_unit`` (for example factor("mm", "um") == 1000); not for offset units."""
    return float(Q_(1.0, from_unit).to(to_unit).magnitude)


def display(value, internal_unit: str, display_unit: str):
    """An internal value (float or array) in ``display_unit``."""
    f = factor(internal_unit, display_unit)
    return value * f if not isinstance(value, (list, tuple)) else [v * f for v in value]


def internal(value, display_unit: str, internal_unit: str):
    """A displayed value back in ``internal_unit`` (the inverse of :func:`display`)."""
    return display(value, display_unit, internal_unit)


@lru_cache(maxsize=256)
def internal_unit_of(unit: str) -> str:
    """The internal unit of the dimension of ``unit`` (mm for um, rad for urad, 1/K for um/(m*K) ...)."""
    d = str(ureg.Unit(unit).dimensionality).replace("dimensionless", "")
    if d == "":  # an angle (radian at its root) or a ratio such as um/m
        return "rad" if Q_(1.0, unit).to_root_units().units == ureg.radian else ""
    if d in INTERNAL:
        return INTERNAL[d]
    raise KeyError(f"no internal unit for {unit!r} ({d})")


@lru_cache(maxsize=256)
def pretty(unit: str) -> str:
    """One spelling of a unit for people: short symbols, µ for micro, a/(b·c) (µm, µrad, µm/(m·K))."""
    if not unit:
        return ""
    u = ureg.Unit(unit)
    if u == ureg.dimensionless:
        return ""
    num, den = [], []
    for name, power in sorted(u._units.items(), key=lambda kv: kv[0]):
        sym = f"{ureg.Unit(name):~P}"
        p = abs(power)
        txt = sym if p == 1 else f"{sym}{'²' if p == 2 else '³' if p == 3 else '^' + str(p)}"
        (num if power > 0 else den).append(txt)
    # lengths first in a numerator and a denominator (µm/(m·K), not µm/(K·m))
    den.sort(key=lambda t: (0 if t.rstrip("²³").endswith("m") else 1, t))
    top = "·".join(num) or "1"
    if not den:
        return top
    bottom = den[0] if len(den) == 1 else "(" + "·".join(den) + ")"
    return f"{top}/{bottom}"


#: the unit results are shown in, for each internal unit: lengths in um, angles in urad, ratios in um/m
SHOWN = {"mm": "um", "rad": "urad", "mm/mm": "um/m"}


def shown_unit(internal_unit: str) -> str:
    """The unit mtbudget shows an internal quantity in (um for mm, urad for rad, um/m for mm/mm)."""
    return SHOWN.get(internal_unit, internal_unit)


def from_internal(value, unit: str, out_unit: str | None = None) -> pint.Quantity:
    """Wrap an internal-unit value as a Quantity, optionally converting."""
    q = Q_(value, unit)
    return q.to(out_unit) if out_unit else q


def is_finite_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
