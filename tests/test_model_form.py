"""The model-form source (issue 14): the simulated machine one Legendre degree richer than the identification.

GUM 3.2.4 / 6.3.1: an uncorrected systematic effect of unknown size belongs in the budget.  The identification
represents the error functions up to max_degree; the machine's are not polynomials of that degree.
"""

from pathlib import Path

import numpy as np

from mtbudget.budget import point_lpu
from mtbudget.config import load_config, parse_config
from mtbudget.scenario import build_scenario

PAPER = Path(__file__).parents[1] / "mtbudget" / "data" / "paper_xfyz.toml"


def paper(tmp_path, add=(), coefficients=None, name="c.toml"):
    text = PAPER.read_text()
    if add:
        text = text.replace('disable = ["approximation_degree", "multilateration"]',
                            'disable = ["approximation_degree", "multilateration"]\nadd = ' +
                            "[" + ", ".join(f'"{a}"' for a in add) + "]")
    if coefficients is not None:
        start = text.index("[geometric_errors]")
        end = text.index("\n[", start + 1)
        text = text[:start] + "[geometric_errors.coefficients]\n" + coefficients + text[end:]
    p = tmp_path / name
    p.write_text(text)
    return load_config(p)


def test_the_same_machine_with_and_without_the_model_form_source(tmp_path):
    a = build_scenario(paper(tmp_path, name="a.toml"))
    b = build_scenario(paper(tmp_path, add=("model_form",), name="b.toml"))
    assert "model_form" in {s.name for s in b.sources} and "model_form" not in {s.name for s in a.sources}
    names_a, names_b = a.truth.errors.names, b.truth.errors.names
    extra = [n for n in names_b if n not in names_a]
    assert extra and all(n.endswith("[P4]") for n in extra)  # x and y have 5 positions: degree 4 is there
    for n, v in zip(names_a, a.theta):
        assert b.theta[names_b.index(n)] == v  # the lower degrees are the same machine, bit for bit
    assert all(b.theta[names_b.index(n)] == 0.0 for n in extra)
    assert a.id_model.errors.names == b.id_model.errors.names  # the identification is unchanged


def test_a_next_degree_term_is_left_after_compensation_and_a_lower_one_is_not(tmp_path):
    """Noise-free: a 3 um P3 of dx(x) is identified and compensated; a 3 um P4 cannot be, and what it leaves at the
    mesh points is at least its part orthogonal to cubics over the five x positions (a weighted fit can only do
    worse than the best cubic for that one function)."""
    from numpy.polynomial import legendre

    low = build_scenario(paper(tmp_path, add=("model_form",), coefficients='"dx(x)" = ["0 um", "0 um", "3 um"]\n',
                               name="low.toml"))
    high = build_scenario(paper(tmp_path, add=("model_form",),
                                coefficients='"dx(x)" = ["0 um", "0 um", "0 um", "3 um"]\n', name="high.toml"))
    assert np.abs(point_lpu(low)["estimate"]).max() < 1e-3  # um
    y = point_lpu(high)["estimate"]
    x = high.commanded[:, 0]
    xn = (x - 1000.0) / 200.0
    p4 = legendre.legval(xn, [0, 0, 0, 0, 3.0])  # um
    V = np.stack([legendre.legval(xn, np.eye(4)[k]) for k in range(4)], axis=1)
    orth = p4 - V @ np.linalg.lstsq(V, p4, rcond=None)[0]
    assert np.sqrt(np.mean(y**2)) * np.sqrt(3) >= 0.99 * np.sqrt(np.mean(orth**2))


def test_the_budget_carries_the_model_form_term(tmp_path):
    from mtbudget.runner import run

    res = run(paper(tmp_path, add=("model_form",)), trials=64, attribution_trials=64, sources=None)
    rows = {r["source"]: r for r in res.budget["points"]["rows"]}
    assert "model_form" in rows and max(rows["model_form"]["u_rms_over_mesh"]) > 1.0  # um: 2 um next terms
    assert rows["model_form"]["group"] == "optimisation strategy"
