"""The one quantity parser: strict grammar, no hang, no silently wrong number (issue 19)."""

import math
import time

import pytest

from mtbudget.errors import UnitError
from mtbudget.units import parse_quantity, parse_unit, to_internal, ureg


@pytest.mark.parametrize("text, unit, expected, absolute", [
    ("5 um", "mm", 5e-3, False),
    ("5um", "mm", 5e-3, False),
    ("5\u00a0µm", "mm", 5e-3, False),  # a no-break space and a micro sign from a spreadsheet
    ("0.8 um/m", "mm/mm", 0.8e-6, False),
    ("2000 mm/min", "mm/s", 2000 / 60, False),
    ("20 degC", "K", 293.15, True),
    ("68 degF", "K", 293.15, True),
    ("20 °C", "K", 293.15, True),
    ("0.1 K", "K", 0.1, False),
    ("0.1 delta_degC", "K", 0.1, False),
    ("0.5 degC/h", "K/s", 0.5 / 3600, False),  # a rate: degC is a difference here (pint alone gives 273.65 K/h)
    ("11.5 um/(m*degC)", "1/K", 11.5e-6, False),  # a CTE: per degree of difference (pint alone gives 4.2e-8)
    ("11.5e-6 1/K", "1/K", 11.5e-6, False),
    ("11.5e-6 /K", "1/K", 11.5e-6, False),
    ("5 urad", "rad", 5e-6, False),
    ("1 arcsec", "urad", math.pi / 648000 * 1e6, False),
    ("1e-9999 mm", "mm", 0.0, False),
])
def test_accepted_quantities_have_the_hand_computed_value(text, unit, expected, absolute):
    assert to_internal(text, unit, absolute_temperature=absolute) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("value, unit, message", [
    ("9**9**9 um", "mm", "NUMBER UNIT"),
    ("-9**9**9 mm", "mm", "NUMBER UNIT"),
    ("5 mm**9**9**9", "mm", "NUMBER UNIT"),
    ("5 (mm 3)", "mm", "NUMBER UNIT"),  # pint alone reads 15 mm
    ("5 mm 2", "mm", "NUMBER UNIT"),  # pint alone reads 10 mm
    ("mm", "mm", "NUMBER UNIT"),  # no number: pint alone reads 1 mm
    ("1_000 mm", "mm", "NUMBER UNIT"),
    ("٥ mm", "mm", "NUMBER UNIT"),
    ("1%%1", "", "NUMBER UNIT"),
    ("5 mm/inf", "mm", "not finite"),  # pint alone reads 0 mm
    ("nan mm", "mm", "not finite"),
    ("inf urad", "rad", "not finite"),
    ("1e999 mm", "mm", "not finite"),
    ("1e308 km", "mm", "not finite in mm"),
    (float("inf"), "mm", "not finite"),
    (10**400, "mm", "not finite"),
    (True, "mm", "expected a quantity string"),
    ([1, 2], "mm", "expected a quantity string"),
    (None, "mm", "expected a quantity string"),
    ("5", "rad", "a bare number is ambiguous for an angle"),
    (5, "rad", "a bare number is ambiguous for an angle"),
    ("0.8", "mm/mm", "a bare number is ambiguous for a ratio"),
    ("5 deg", "", "is an angle; expected a plain number"),
    ("5 s", "mm", "not a quantity of dimension [length]"),
    ("5 furlongz", "mm", "unknown unit 'furlongz'"),
    ("0.1 degC", "K", "temperature difference on an offset scale"),
])
def test_refused_quantities_give_one_clean_line(value, unit, message):
    with pytest.raises(UnitError) as info:
        to_internal(value, unit, where="tracker.distance")
    msg = str(info.value)
    assert msg.startswith("tracker.distance: ") and message in msg and "\n" not in msg, msg


@pytest.mark.parametrize("value, message", [
    ("20 delta_degC", "is a temperature difference"),
    ("-300 degC", "not a plausible absolute temperature"),
    ("20 K", "not a plausible absolute temperature"),
    ("1e9 degC", "not a plausible absolute temperature"),
])
def test_absolute_temperatures_refuse_differences_and_implausible_values(value, message):
    with pytest.raises(UnitError, match=message):
        to_internal(value, "K", absolute_temperature=True)


def test_hostile_strings_answer_at_once():
    """The old grammar backtracked exponentially on a long failing word (28 letters: a minute)."""
    for text in ["5 " + "a" * 110 + "!", "5 " + "ab" * 55 + "(", "5 " + "m " * 55 + "**", "5 " + "(" * 58 + "mm",
                 "9**9**9**9**9 um", "1" * 119]:
        t = time.perf_counter()
        with pytest.raises(UnitError):
            to_internal(text, "mm")
        assert time.perf_counter() - t < 0.5, text


def test_parse_unit_shares_the_grammar():
    assert parse_unit("um/(m*K)") == parse_unit("µm/(m·K)".replace("·", "*"))
    assert parse_unit("degC/h") == ureg.Unit("delta_degC/hour")  # in a product, degC is a difference
    assert parse_unit("1/K") == parse_unit("/K") == ureg.Unit("1/K")
    for bad in ["mm**9**9**9", "5 mm", "", "mm/", 5]:
        with pytest.raises(UnitError):
            parse_unit(bad)


def test_parse_quantity_keeps_absolute_temperatures_and_plain_numbers():
    assert parse_quantity("20 degC").to("K").magnitude == pytest.approx(293.15)
    assert parse_quantity("2").magnitude == 2.0 and parse_quantity("2").unitless


def test_offset_scale_and_difference_units_are_told_apart():
    from mtbudget.units import Q_, is_offset_temperature, is_temperature_difference_unit

    assert is_offset_temperature(Q_(0.1, "degC")) and is_offset_temperature(Q_(0.1, "degF"))
    assert not any(is_offset_temperature(Q_(0.1, u)) for u in ("K", "delta_degC", "delta_degF", "um/K"))
    assert is_temperature_difference_unit(Q_(0.1, "delta_degC")) and is_temperature_difference_unit(Q_(1, "delta_degF"))
    assert not any(is_temperature_difference_unit(Q_(0.1, u)) for u in ("K", "degC", "um"))
    # why it matters: pint reads "0.1 degC" as an absolute 273.25 K, "0.1 delta_degC" as 0.1 K
    assert Q_(0.1, "degC").to("K").magnitude == pytest.approx(273.25) and Q_(0.1, "delta_degC").to("K").magnitude == pytest.approx(0.1)
