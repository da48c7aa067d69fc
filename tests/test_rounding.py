"""Conformity statements round towards the safe side (ISO 14253-1): an acceptance zone inwards, an upper bound of an
error or a guard band upwards. Checked against exact decimal arithmetic written here with fractions, and through the
features' decision text."""

import math
import re
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, strategies as st

from mtbudget.features import decision
from mtbudget.stats import bound, decimals_of


def _exact(x: float, direction: str, d: int) -> Fraction:
    """x rounded up or down to d decimals, exactly, from its shortest decimal form."""
    f, q = Fraction(repr(x)), Fraction(1, 10 ** d)
    n = f / q
    return (math.ceil(n) if direction == "up" else math.floor(n)) * q


@given(st.floats(-1e6, 1e6, allow_nan=False), st.sampled_from(["up", "down"]), st.integers(0, 4))
def test_bound_rounds_to_the_side_it_is_asked_for(x, direction, d):
    shown = Fraction(bound(x, direction, d))
    assert shown == _exact(x, direction, d)
    assert (shown >= Fraction(repr(x))) if direction == "up" else (shown <= Fraction(repr(x)))


def test_an_exact_value_is_not_moved_and_no_minus_zero():
    assert bound(15.0, "down", 1) == "15.0" and bound(15.0, "up", 1) == "15.0"  # 15.0 * 10 is 150.00000000000003
    assert bound(-0.04, "up", 1) == "0.0" and bound(0.04, "down", 1) == "0.0"
    assert decimals_of([-18.3, 14.96]) == 1 and decimals_of([0.0123]) == 4 and decimals_of([]) == 0


def test_a_features_acceptance_zone_is_rounded_inwards_at_one_precision():
    """T = 20 um, the error's interval [-5.04, 1.7]: the zone for a measured deviation is [-20 + 1.7, 20 - 5.04] =
    [-18.3, 14.96], shown [-18.3, 14.9] (14.96 shown as 15 would accept parts outside the zone)."""
    f = {"tolerance": 20.0, "unit": "um", "one_sided": False}
    d = decision(f, 0.0, -5.04, 1.7, 0.95)
    lo, hi = map(float, re.search(r"deviation: \[(\S+), (\S+)\] um \(rounded inwards\)", d["statement"]).groups())
    assert (lo, hi) == (-18.3, 14.9) and d["acceptance_zone"] == pytest.approx([-18.3, 14.96])
    one = decision({"tolerance": 10.0, "unit": "um", "one_sided": True}, 1.0, 0.2, 2.345, 0.95)
    assert "value: <= 7.65 um" in one["statement"] and "U = 2.35 um (rounded up)" in one["rule"]


def _points(u, half):
    return [{"u": {"value": [u, u, u], "unit": "um"}, "mean": {"value": [0.0, 0.0, 0.0]},
             "interval": {"low": [-half] * 3, "high": [half] * 3}}]


def _brief(points, trials):
    from mtbudget.report import statement_in_brief

    return statement_in_brief(kind="a priori", kind_text="", measurand="", points=points, coverage=0.95,
                              frame=False, statement=None, tolerance_um=None, characteristic="", fields={},
                              machine="m", date="2026-11-26", command="mtbudget report", trials=trials)


@pytest.mark.parametrize("half, longer", [(1.8, False), (2.6, True)])
def test_the_brief_says_when_the_monte_carlo_interval_is_wider_than_U(half, longer):
    """U = 2u = 2.0 um; a 95 % interval of half-width 2.6 um (a distribution with longer tails than the normal) is
    wider than U beyond what 10^4 trials scatter (4 x 1.2 %): the statement says so and points to the intervals;
    1.8 um (shorter tails) is not."""
    b = _brief(_points(1.0, half), 10_000)
    assert b["U_max"] == 2.0 and b["half_width_max"] == half
    assert ("larger than U: somewhere the distribution is not normal" in b["U_text"]) == longer


def test_normal_components_are_not_called_non_normal_by_their_own_scatter():
    """75 points x 3 axes, each drawn normal (numpy, here) with n trials; the brief's u and half-width computed as
    the engine computes them (std, order statistics). Monte Carlo scatter alone must not make the statement call
    the distribution non-normal (it did in 17 of 20 runs of 128 trials, comparing the largest half-width with the
    largest U); a Laplace distribution (its 95 % half-width ln(20) b against 2u = 2 sqrt(2) b: 1.06 times U) is
    called so at 10^5 trials."""
    from mtbudget.stats import symmetric_interval

    rng = np.random.default_rng(7)

    def points(draw, n, count=75):
        pts = []
        for _ in range(count):
            y = draw((n, 3))
            iv = [symmetric_interval(np.sort(y[:, j]), 0.95) for j in range(3)]
            pts.append({"u": {"value": list(y.std(axis=0, ddof=1)), "unit": "um"}, "mean": {"value": [0.0] * 3},
                        "interval": {"low": [a for a, _ in iv], "high": [b for _, b in iv]}})
        return pts

    said = [("not normal" in _brief(points(rng.standard_normal, n), n)["U_text"]) for n in (128,) * 10 + (1000,) * 5]
    assert not any(said)
    assert math.log(20) / (2 * math.sqrt(2)) == pytest.approx(1.059, abs=1e-3)
    assert "not normal" in _brief(points(lambda s: rng.laplace(0.0, 1.0, s), 100_000, 3), 100_000)["U_text"]


def test_a_feature_budget_with_a_large_interaction_says_how_much_sampling_explains():
    """sqrt(2 / (n - 1)) at n = 65: 17.7 %, shown 18 %; an interaction within +-10 % gets no note."""
    from mtbudget.features import _sampling_note

    note = _sampling_note({"trials": 65, "interaction_share": -0.27})
    assert "from 65 trials is uncertain by about 18 % of itself" in note and "--attribution-trials" in note
    assert _sampling_note({"trials": 65, "interaction_share": 0.08}) == ""
