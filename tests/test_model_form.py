"""The model-form sources (issue 14): the simulated machine richer than the identification model -- one Legendre
degree higher (model_form), a periodic error with the lead of each screw (model_form_periodic), couplings of two axes
(model_form_coupling) -- and the budget's systematic rows with the sentence on how each was bounded.

GUM 3.2.4 / 6.3.1: an uncorrected systematic effect of unknown size belongs in the budget.  The identification
represents the error functions up to max_degree; the machine's are not polynomials of that degree.
"""

from pathlib import Path

import numpy as np
import pytest

from mtbudget.budget import point_lpu
from mtbudget.config import load_config, parse_config
from mtbudget.engine import Engine
from mtbudget.scenario import build_scenario

from conftest import independent_fit
from mtbudget.simulate import stream

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


# ----------------------------------------------------------------------------- periodic errors, couplings of two axes
# Both act on what the verification measures (point_offset, the plan's rows, machine frame) and on the machine whose
# error is the measurand (measurand_offset, the same displacement at the same rows).  Checked against an independent
# linear calculation: a weighted least-squares fit, written here, of the identification model's finite-difference
# Jacobian (pose and geometric errors), the tracker covariance of Eq. 23 written here, the rigid part removed by a
# projector written here.


NO_ERRORS = '"dx(x)" = ["0 um"]\n'  # an error-free machine: the fit is linear about the nominal


def configured(tmp_path, source, table, name="p.toml"):
    cfg = paper(tmp_path, add=(source,), coefficients=NO_ERRORS, name="base_" + name)
    text = (tmp_path / ("base_" + name)).read_text() + f"\n[sources.{source}]\n" + table
    (tmp_path / name).write_text(text)
    return build_scenario(load_config(tmp_path / name), sources=[source])


def linear_projector(sc, h=1e-4):
    """S (3 M0, 3 M): the compensated error at the mesh points (rigid part removed) of a machine-frame displacement of
    the plan's points that acts on the measurements and on the machine alike, to first order, without the engine
    (conftest.independent_fit)."""
    P, Jm, KB, sel = independent_fit(sc, h)
    return P @ (sel - Jm @ KB)


# about 1 um: the fit moves near-unidentifiable parameters by ten times more, so its second-order terms are ~ 0.3 nm
PERIODIC = 'lead_x = "30 mm"\nlead_y = "40 mm"\nlead_z = "16 mm"\nu_x = "1 um"\nu_y = "0.8 um"\nu_z = "0.6 um"\n'
COUPLING = 'xy = "0.6 um"\nxz = "0.4 um"\nyz = "0.8 um"\n'


@pytest.fixture(scope="module")
def projector(tmp_path_factory):
    return linear_projector(configured(tmp_path_factory.mktemp("s"), "model_form_periodic", PERIODIC))


@pytest.mark.parametrize("source, table", [("model_form_periodic", PERIODIC), ("model_form_coupling", COUPLING)])
def test_what_the_engine_leaves_is_the_independent_weighted_fit(tmp_path, projector, source, table):
    """Noise-free: the displacement the source drew at the plan's rows, put through the fit written above, leaves at
    the mesh points what the engine leaves, to its second-order terms (below 1 nm here: the engine's fit is exact and
    non-linear; at 5 um they reach 5 nm, growing with the square), and that is a good part of what was drawn."""
    sc = configured(tmp_path, source, table)
    src = sc.sources[0]
    n = 16
    comp = Engine(sc, block=n, seed=5).run_block(0).components  # (n, M0, 3) um
    drawn = src.sample(n, stream(5, 0, src), sc.context)
    d = drawn["point_offset"].to("mm").magnitude  # (n, M, 3), the same numbers the engine drew
    assert np.array_equal(d, drawn["measurand_offset"].to("mm").magnitude)
    expected = (d.reshape(n, -1) @ projector.T).reshape(comp.shape) * 1000.0
    assert np.abs(comp - expected).max() < 1e-3  # um
    left = np.sqrt(np.mean(expected**2))
    assert left > 0.15 * np.sqrt(np.mean(d[:, sc.mesh_rows] ** 2)) * 1000.0 and left > 0.1  # um: not absorbed


def test_at_another_tool_the_positioning_error_is_the_same_and_the_fit_is_seen_from_there(tmp_path):
    """[measurand] tool 100 mm off the spindle axis: a periodic positioning error does not depend on the tool, so the
    machine there keeps the same displacement, less what the identified errors do at that tool (rigid part removed
    over the tool's points)."""
    sc = configured(tmp_path, "model_form_periodic", PERIODIC + '\n[measurand]\ntool = ["0 mm", "100 mm", "-150 mm"]\n')
    assert sc.measurand_tool is not None and [s.name for s in sc.sources] == ["model_form_periodic"]
    src = sc.sources[0]
    comp = Engine(sc, block=16, seed=5).run_block(0).components
    d = src.sample(16, stream(5, 0, src), sc.context)["point_offset"].to("mm").magnitude
    expected = (d.reshape(16, -1) @ linear_projector(sc).T).reshape(comp.shape) * 1000.0
    assert np.abs(comp - expected).max() < 1e-3 and np.sqrt(np.mean(expected**2)) > 0.1  # um


def closed_form_covariance(sc, source):
    """(3 M, 3 M) mm^2: the covariance of the displacement at the plan's rows, written from the source's law."""
    P = sc.plan.nominal
    M = len(P)
    C = np.zeros((M, 3, M, 3))
    if source == "model_form_periodic":
        for a, (lead, u) in enumerate([(30.0, 1e-3), (40.0, 0.8e-3), (16.0, 0.6e-3)]):
            w = 2 * np.pi * P[:, a] / lead
            # c cos w + s sin w, c and s independent N(0, u^2): u^2 (cos w_i cos w_j + sin w_i sin w_j)
            C[:, a, :, a] = u**2 * np.cos(w[:, None] - w[None, :])
    else:
        lo, hi = P.min(axis=0), P.max(axis=0)
        t = (P - (lo + hi) / 2) / ((hi - lo) / 2)
        legendre_ = [lambda v: v, lambda v: 1.5 * v**2 - 0.5]
        for (a, b, third), sd in [((0, 1, 2), 0.6e-3), ((0, 2, 1), 0.4e-3), ((1, 2, 0), 0.8e-3)]:
            for f in legendre_:
                for g in legendre_:
                    s = f(t[:, a]) * g(t[:, b])
                    C[:, third, :, third] += sd**2 * np.outer(s, s)
    return C.reshape(3 * M, 3 * M)


@pytest.mark.parametrize("source, table", [("model_form_periodic", PERIODIC), ("model_form_coupling", COUPLING)])
def test_the_budget_row_has_the_closed_form_variance(tmp_path, projector, source, table):
    """The per-point variance of the source's Monte Carlo contribution (2048 trials) against the closed-form
    covariance of its law (E[cos^2 + sin^2] = 1 per coefficient pair) through the same linear projector: the variance
    of N trials scatters by sqrt(2 / N) = 3.1 %; every point-axis that carries more than 10 % of the largest u
    within 15 % in variance (about 5 of those standard errors), the RMS over the mesh within 10 %."""
    sc = configured(tmp_path, source, table)
    comp = np.concatenate([Engine(sc, block=512, seed=11).run_block(b).components for b in range(4)])  # um
    var_mc = comp.var(axis=0, ddof=1)
    var_cf = np.diag(projector @ closed_form_covariance(sc, source) @ projector.T).reshape(-1, 3) * 1e6  # um^2
    big = var_cf > 0.01 * var_cf.max()
    assert big.sum() > 60
    ratio = var_mc[big] / var_cf[big]
    assert np.all(np.abs(ratio - 1.0) < 0.15), (ratio.min(), ratio.max())
    # the budget's own row (the source alone on its 2048 trials): RMS over the mesh and the worst point
    from mtbudget.runner import run

    pb = run(sc.config, trials=64, attribution_trials=2048, sources=[source]).budget["points"]
    (row,) = [r for r in pb["rows"] if r["source"] == source]
    assert row["u_rms_over_mesh"] == pytest.approx(np.sqrt(var_cf.mean(axis=0)).tolist(), rel=0.1)
    assert row["u_at_worst_point"] == pytest.approx(np.sqrt(var_cf[pb["worst_point"]]).tolist(), rel=0.1, abs=0.02)


def test_a_mesh_whole_leads_apart_keeps_nothing_at_its_points_and_says_so(tmp_path):
    """The default leads (10, 10, 5 mm) divide the paper's 100 mm step: every mesh point sees one phase per axis, a
    translation the tracker pose absorbs, so nothing is left at the mesh points; the budget's sentence says why."""
    sc = configured(tmp_path, "model_form_periodic", 'u_x = "5 um"\n')
    comp = Engine(sc, block=32, seed=3).run_block(0).components
    assert np.abs(comp).max() < 1e-6  # um, of a 5 um periodic error (measured 6e-10 um)
    text = sc.sources[0].bounded(sc.context)
    assert "nothing of the x, y, z error is left at the mesh points" in text and "x, y, z: the plan's positions are " \
        "whole leads apart" in text
    other = configured(tmp_path, "model_form_periodic", PERIODIC, name="q.toml")
    text = other.sources[0].bounded(other.context)
    assert "whole leads apart" not in text and "nothing of the z error" in text and "z: a polynomial of degree 2 passes through the error at each of the plan's 3 positions" in text


def test_the_periodic_law(tmp_path):
    """Per trial and axis: a sine of the axis' lead with a uniform phase; at any position its variance is u^2."""
    sc = configured(tmp_path, "model_form_periodic", PERIODIC)
    d = sc.sources[0].sample(20000, np.random.default_rng(1), sc.context)["point_offset"].to("um").magnitude
    P = sc.plan.nominal
    assert np.allclose(d.var(axis=0), np.array([1.0, 0.64, 0.36]), rtol=0.05)
    # the x error depends on x only, with period 30 mm: the same at x and x + 30 mm, whatever y and z
    same = np.flatnonzero((P[:, 0] == P[0, 0]))
    assert np.array_equal(d[:, same, 0], np.repeat(d[:, same[:1], 0], len(same), axis=1))
    # uniform phase: the covariance of two positions is u^2 cos(2 pi (x_j - x_i) / lead); 100 mm apart on a 30 mm lead
    i, j = 0, int(np.flatnonzero(P[:, 0] == P[0, 0] + 100.0)[0])
    assert np.mean(d[:, i, 0] * d[:, j, 0]) == pytest.approx(np.cos(2 * np.pi * 100.0 / 30.0), abs=0.03)
    assert abs(np.mean(d[:, i, 0] * d[:, i, 1])) < 0.03  # the axes are independent


def test_axis_coupling_keeps_its_shape_through_the_shared_helper(tmp_path):
    """The simulated-physics source axis_coupling and model_form_coupling share the shape code: its z error is still
    amplitude x u_x u_y (u scaled to [-1, 1] over the plan's range), written out here."""
    paper(tmp_path, add=("axis_coupling",), name="ac.toml")
    text = (tmp_path / "ac.toml").read_text() + '\n[sources.axis_coupling]\nxy = "7 um"\n'
    (tmp_path / "ac2.toml").write_text(text)
    sc = build_scenario(load_config(tmp_path / "ac2.toml"), sources=["axis_coupling"])
    d = sc.sources[0].sample(2, np.random.default_rng(0), sc.context)["point_offset"].to("um").magnitude
    P = sc.plan.nominal
    ux, uy = (P[:, 0] - 1000.0) / 200.0, (P[:, 1] - 300.0) / 200.0
    assert np.allclose(d[0, :, 2], 7.0 * ux * uy, atol=1e-9) and not d[0, :, :2].any()


def test_the_budget_shows_the_model_form_rows_as_systematic_with_how_they_were_bounded(tmp_path):
    from mtbudget.runner import run

    cfg = paper(tmp_path, add=("model_form", "model_form_periodic", "model_form_coupling"), name="all.toml")
    res = run(cfg, trials=32, attribution_trials=32, sources=["tracker_noise", "model_form", "model_form_periodic",
                                                               "model_form_coupling"])
    pb = res.budget["points"]
    rows = {r["source"]: r for r in pb["rows"]}
    for name in ("model_form", "model_form_periodic", "model_form_coupling"):
        assert rows[name]["systematic"] == "model form" and "[sources." + name + "]" in rows[name]["bounded"]
        assert rows[name]["group"] == "optimisation strategy"
    assert "systematic" not in rows["tracker_noise"]
    (kind,) = pb["systematic"]
    assert kind["systematic"] == "model form" and set(kind["sources"]) == {"model_form", "model_form_periodic",
                                                                           "model_form_coupling"}
    assert kind["share"] == pytest.approx(sum(rows[n]["share"] for n in kind["sources"]))
    assert 0.0 < kind["share"] < 1.0
    assert rows["model_form_periodic"]["share"] < 1e-6  # the paper's mesh is whole leads apart (the sentence says so)
    scalar = {r["source"]: r for r in res.budget["compensation_rms"]["rows"]}
    assert scalar["model_form_coupling"]["systematic"] == "model form"


@pytest.mark.parametrize("source, table, words", [
    ("model_form_periodic", 'lead_y = "0 mm"\n', "'lead_y' must be positive"),
    ("model_form_periodic", 'u_x = "-1 um"\n', "'u_x' must not be negative"),
    ("model_form_coupling", 'degree = "1.5"\n', "'degree' must be a whole number"),
    ("model_form_coupling", 'xy = "1 urad"\n', "does not have the dimension"),
])
def test_a_bound_that_cannot_be_is_refused_naming_the_key(tmp_path, source, table, words):
    from mtbudget.errors import ConfigError

    with pytest.raises(ConfigError) as e:
        configured(tmp_path, source, table)
    assert f"sources.{source}" in str(e.value) and words in str(e.value)
