"""The one pint registry of mtbudget and the internal unit system.

Everything that crosses the boundary (configs, recordings, plugin outputs,
results) carries pint quantities.  Inside, every array is plain float64 in
one fixed system: **mm, rad, K, s** (temperatures as absolute kelvin).
Conversion happens once on the way in (:func:`to_internal`) and once on the
way out (:func:`from_internal`).
"""

from __future__ import annotations

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
}


def parse_quantity(text, *, what: str = "value") -> pint.Quantity:
    """Parse ``text`` ("5 um", "20 degC", a number) into a Quantity.

    Raises :class:`mtbudget.errors.UnitError` naming ``what`` when pint cannot
    parse it.
    """
    from .errors import UnitError

    if isinstance(text, pint.Quantity):
        return text
    if isinstance(text, (int, float)):
        return Q_(float(text))
    try:
        q = ureg.Quantity(str(text).strip())
    except Exception as exc:  # pint raises several types
        raise UnitError(f"{what}: cannot parse {text!r} as a quantity ({exc})") from None
    if not isinstance(q, pint.Quantity):
        q = Q_(float(q))
    return q


def to_internal(q, unit: str, *, what: str = "value") -> np.ndarray | float:
    """Convert ``q`` to ``unit`` and return the plain magnitude.

    Raises :class:`mtbudget.errors.UnitError` if the dimensions differ.
    """
    from .errors import UnitError

    q = parse_quantity(q, what=what) if not isinstance(q, pint.Quantity) else q
    target = ureg.Unit(unit)
    if q.dimensionality != target.dimensionality:
        raise UnitError(
            f"{what}: expected a quantity of dimension {target.dimensionality} "
            f"(for example {unit}), got {q.units:~} ({q.dimensionality})"
        )
    return q.to(target).magnitude


def from_internal(value, unit: str, out_unit: str | None = None) -> pint.Quantity:
    """Wrap an internal-unit value as a Quantity, optionally converting."""
    q = Q_(value, unit)
    return q.to(out_unit) if out_unit else q
