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
}

#: how a quantity string may look: a number, an optional exponent, then a unit expression
#: of words, spaces, * / ( ) and single small integer powers (** or ^).
_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d{1,3})?"
_UNIT_WORD = r"[A-Za-zµμΩ°%_][A-Za-z0-9µμΩ°%_]*"
_POWER = r"(?:\s*(?:\*\*|\^)\s*[+-]?\d)?"
_UNIT_EXPR = rf"(?:{_UNIT_WORD}{_POWER}|[()*/\s]|\d(?=\s*\)))*"
_GRAMMAR = re.compile(rf"^\s*(?:{_NUMBER})?\s*{_UNIT_EXPR}\s*$")
_MAX_TEXT = 120


def _fail(error, message):
    from .errors import UnitError

    raise (error or UnitError)(message)


def parse_quantity(value, *, where: str = "value", error=None) -> pint.Quantity:
    """Parse ``value`` ("5 um", "20 degC", 0.5, a Quantity) into a finite pint Quantity.

    ``error`` is a callable that builds the exception to raise from a message
    (default :class:`~mtbudget.errors.UnitError`); the message starts with
    ``where``.
    """
    if isinstance(value, pint.Quantity):
        q = value
    elif isinstance(value, bool) or not isinstance(value, (str, int, float, np.floating, np.integer)):
        _fail(error, f"{where}: expected a quantity string such as \"5 um\", got {type(value).__name__} {value!r}")
    elif isinstance(value, str):
        text = value.strip()
        if not text:
            _fail(error, f"{where}: empty quantity; expected for example \"5 um\"")
        if len(text) > _MAX_TEXT or not _GRAMMAR.match(text):
            _fail(error, f"{where}: {value!r} is not a quantity of the form NUMBER UNIT (for example \"5 um\" or \"0.8 um/m\")")
        try:
            q = ureg.Quantity(text)
        except Exception as exc:  # pint raises several types
            _fail(error, f"{where}: cannot parse {value!r} as a quantity ({type(exc).__name__})")
        if not isinstance(q, pint.Quantity):
            q = Q_(float(q))
    else:
        q = Q_(float(value))
    mag = np.asarray(q.magnitude, dtype=float) if not isinstance(q.magnitude, (int, float)) else q.magnitude
    if not np.all(np.isfinite(mag)):
        _fail(error, f"{where}: {value!r} is not finite")
    return q


def _has_unit(value) -> bool:
    """Whether ``value`` states a unit (a bare number or "5" does not)."""
    if isinstance(value, pint.Quantity):
        return not value.unitless
    if isinstance(value, str):
        q = ureg.Quantity(value.strip())
        return isinstance(q, pint.Quantity) and not q.unitless
    return False


def to_internal(value, unit: str, *, where: str = "value", error=None, absolute_temperature: bool = False) -> float:
    """Parse ``value`` and return its magnitude in ``unit`` (a plain float).

    An angle (``unit`` rad, deg, urad ...) needs an explicit unit; an absolute
    temperature (``absolute_temperature=True``) refuses ``delta_*`` units.
    """
    q = parse_quantity(value, where=where, error=error)
    target = ureg.Unit(unit)
    if target.dimensionality != q.dimensionality:
        _fail(error, f"{where}: {_show(value)} is not a quantity of {_dimension(target)} (for example {unit})")
    if target.dimensionless and target != ureg.dimensionless and not _has_unit(value):
        _fail(error, f"{where}: {_show(value)} needs an explicit unit (for example \"{value} {unit}\"); "
                     "a bare number is ambiguous for an angle")
    if absolute_temperature and any(name.startswith("delta_") for name, _ in q.unit_items()):
        _fail(error, f"{where}: {_show(value)} is a temperature difference; give an absolute temperature such as \"20 degC\"")
    out = q.to(target).magnitude
    return float(out) if np.ndim(out) == 0 else np.asarray(out, float)


def _show(value) -> str:
    return f"{value:~P}" if isinstance(value, pint.Quantity) else repr(value)


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


def from_internal(value, unit: str, out_unit: str | None = None) -> pint.Quantity:
    """Wrap an internal-unit value as a Quantity, optionally converting."""
    q = Q_(value, unit)
    return q.to(out_unit) if out_unit else q


def is_finite_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
