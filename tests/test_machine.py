"""The kinematic chain against an independent transcription of the paper's equations."""


import numpy as np
import pytest

from mtbudget.machine import (ALL_CONFIGURATIONS, COMPONENT_ERRORS, ChainInputs, Configuration, ErrorModel, chain,
                              rotation_exact, rotation_small)
from mtbudget.errors import ConfigError

RANGES = {"x": (800.0, 1200.0), "y": (100.0, 500.0), "z": (200.0, 400.0)}


def full_model(convention="free", deg=3):
    return ErrorModel(ranges=RANGES, degrees={n: (2 if n.endswith("(z)") else deg) for n in COMPONENT_ERRORS},
                      straightness_convention=convention)


def random_inputs(rng, M=40):
    nominal = np.column_stack([rng.uniform(*RANGES[a], M) for a in "xyz"])
    tool = np.column_stack([rng.uniform(-50, 50, M), rng.uniform(-50, 50, M), rng.uniform(-300, -100, M)])
    return nominal, tool


def random_theta(model, rng, scale=1.0):
    return np.array([rng.normal(0, 10e-3 if p.unit == "mm" else 20e-6) for p in model.params]) * scale


def paper_eq2_workpiece(model, theta, nominal, tool):
    """Eq. 2 (without the tracker part) and Eq. 5-9 written out literally, point by point."""
    names = model.names
    out = []
    for (x, y, z), T in zip(nominal, tool):
        def err(e, a, pos):
            lo, hi = RANGES[a]
            u = (pos - (lo + hi) / 2) / ((hi - lo) / 2)
            total = 0.0
            for j, p in enumerate(model.params):
                if p.error == e:
                    total += theta[j] * np.polynomial.legendre.Legendre.basis(p.order)(u)
            return total

        def Rm(a, pos):
            ex, ey, ez = (err(f"e{c}({a})", a, pos) for c in "xyz")
            return np.array([[1, -ez, ey], [ez, 1, -ex], [-ey, ex, 1]])  # Eq. 6

        s = {k: theta[names.index(k)] for k in ("sxy", "sxz", "syz")}
        X = np.array([-x + err("dx(x)", "x", x), err("dy(x)", "x", x), err("dz(x)", "x", x)])  # Eq. 7
        Y = np.array([err("dx(y)", "y", y) - y * s["sxy"], y + err("dy(y)", "y", y), err("dz(y)", "y", y)])  # Eq. 8
        Z = np.array([err("dx(z)", "z", z) - z * s["sxz"], err("dy(z)", "z", z) - z * s["syz"],
                      z + err("dz(z)", "z", z)])  # Eq. 9
        out.append(np.linalg.inv(Rm("x", x)) @ (Rm("y", y) @ (Rm("z", z) @ T + Z) + Y - X))
    return np.array(out)


def test_xfyz_chain_is_the_papers_equation_2(rng):
    model = full_model()
    nominal, tool = random_inputs(rng, 25)
    theta = random_theta(model, rng)
    got = chain(Configuration.parse("XFYZ"), model, theta, ChainInputs(nominal, tool))[0]
    want = paper_eq2_workpiece(model, theta, nominal, tool)
    assert np.max(np.abs(got - want)) < 1e-10


@pytest.mark.parametrize("code", ALL_CONFIGURATIONS)
def test_every_configuration_error_free_is_nominal(code, rng):
    model = full_model()
    nominal, tool = random_inputs(rng, 10)
    got = chain(Configuration.parse(code), model, np.zeros(len(model.params)), ChainInputs(nominal, tool))[0]
    assert np.allclose(got, nominal + tool, atol=1e-12)


@pytest.mark.parametrize("code", ["XFYZ", "FXYZ", "XYFZ", "YFXZ", "ZYXF", "ZFXY"])
def test_translational_error_sign_follows_the_carriage_side(code):
    cfg = Configuration.parse(code)
    model = ErrorModel(ranges=RANGES, degrees={"dy(x)": 1, "dx(z)": 1}, squareness=False, straightness_convention="free")
    nominal = np.array([[1200.0, 300.0, 400.0]])  # u = +1 on x and z
    tool = np.zeros((1, 3))
    theta = np.array([1e-3, 2e-3])
    d = chain(cfg, model, theta, ChainInputs(nominal, tool))[0][0] - nominal[0]
    assert d[1] == pytest.approx(cfg.side("x") * 1e-3, abs=1e-12)
    assert d[0] == pytest.approx(cfg.side("z") * 2e-3, abs=1e-12)


@pytest.mark.parametrize("code", ["XFYZ", "FXYZ", "XYFZ", "ZFYX", "YXZF"])
def test_analytic_jacobian_matches_central_differences(code, rng):
    cfg = Configuration.parse(code)
    model = full_model()
    nominal, tool = random_inputs(rng, 12)
    theta = random_theta(model, rng)
    inp = ChainInputs(nominal, tool, offset={"y": rng.normal(0, 1e-3, 12)}, scale={"x": rng.normal(0, 1e-5, 12)})
    _, J = chain(cfg, model, theta, inp, jacobian=True)
    h = np.array([1e-4 if p.unit == "mm" else 1e-7 for p in model.params])
    for j in range(len(model.params)):
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h[j]
        tm[j] -= h[j]
        fd = (chain(cfg, model, tp, inp)[0] - chain(cfg, model, tm, inp)[0]) / (2 * h[j])
        # central differences on ~1e3 mm coordinates carry ~1e-6 of round-off
        assert np.allclose(J[0, ..., j], fd, rtol=1e-6, atol=1e-5), model.params[j].name


def test_first_order_formula_error_is_second_order(rng):
    """P_nom + J(0) theta approximates the exact chain with an error that shrinks as |theta|^2."""
    cfg = Configuration.parse("XFYZ")
    model = full_model()
    nominal, tool = random_inputs(rng, 30)
    inp = ChainInputs(nominal, tool)
    _, J0 = chain(cfg, model, np.zeros(len(model.params)), inp, jacobian=True)
    theta = random_theta(model, rng)
    gaps = []
    for s in (1.0, 0.5, 0.25):
        exact = chain(cfg, model, s * theta, inp)[0]
        linear = nominal + tool + J0[0] @ (s * theta)
        gaps.append(np.abs(exact - linear).max())
    assert gaps[0] < 1e-5  # below 10 nm for errors of ~10 um and ~20 urad
    assert gaps[1] / gaps[0] == pytest.approx(0.25, rel=0.05)
    assert gaps[2] / gaps[1] == pytest.approx(0.25, rel=0.05)


def test_small_angle_versus_exact_rotation(rng):
    """Eq. 6 differs from the exact rotation by second-order terms: |eps|^2/2 on the diagonal."""
    eps = rng.normal(0, 1, (100, 3))
    eps /= np.linalg.norm(eps, axis=1, keepdims=True)
    for mag in (1e-5, 1e-4, 1e-3):
        gap = np.abs(rotation_exact(eps * mag) - rotation_small(eps * mag)).max()
        assert 0.3 * mag**2 < gap < 0.51 * mag**2
    # in the chain, one angular error of magnitude e at the end of its range: gap ~ e^2 * lever, quadratic in e
    cfg = Configuration.parse("XFYZ")
    model = ErrorModel(ranges=RANGES, degrees={"ex(x)": 1}, squareness=False)
    nominal, tool = random_inputs(rng, 30)
    nominal[:, 0] = 1200.0
    gaps = []
    for e in (100e-6, 50e-6):
        d = np.abs(chain(cfg, model, np.array([e]), ChainInputs(nominal, tool), exact=True)[0]
                   - chain(cfg, model, np.array([e]), ChainInputs(nominal, tool))[0]).max()
        lever = np.linalg.norm(nominal + tool, axis=1).max()
        assert d <= e**2 * lever
        gaps.append(d)
    assert gaps[1] / gaps[0] == pytest.approx(0.25, rel=0.02)
    # what that means: at 100 urad and a 1.5 m lever the paper's small-angle model is off by < 15 nm


def test_thermal_scale_and_offset_act_like_equation_15():
    cfg = Configuration.parse("XFYZ")
    model = ErrorModel(ranges=RANGES, degrees={}, squareness=False)
    nominal = np.array([[1000.0, 300.0, 300.0]])
    alpha, dT, beta = 11.5e-6, 2.0, 4e-3
    inp = ChainInputs(nominal, np.zeros((1, 3)), offset={"x": np.array([[beta]])}, scale={"x": np.array([[alpha * dT]])})
    got = chain(cfg, model, np.zeros(0), inp)[0][0]
    assert got[0] == pytest.approx((1000.0 + beta) * (1 + alpha * dT), abs=1e-12)


def test_bad_configuration_codes_are_rejected():
    for bad in ("XYZ", "XFFZ", "XFYW", ""):
        with pytest.raises(ConfigError):
            Configuration.parse(bad)
    assert len(ALL_CONFIGURATIONS) == 24


def test_iso230_convention_drops_linear_straightness_only():
    m = full_model("iso230")
    names = m.names
    assert "dy(x)[P1]" not in names and "dy(x)[P2]" in names
    assert "dx(x)[P1]" in names and "ex(x)[P1]" in names
    assert {"sxy", "sxz", "syz"} <= set(names)


def test_the_componentwise_chain_equals_the_matrix_chain_for_every_configuration():
    """machine.chain (component arithmetic) against machine.chain_reference (a 3 x 3 matrix per point), with
    offsets, scales, projections and models that leave errors out; and the Jacobian against central differences."""
    from mtbudget.machine import ALL_CONFIGURATIONS, ChainInputs, chain, chain_reference

    rng = np.random.default_rng(3)
    M = 30
    nom, tool = rng.uniform(-300, 300, (M, 3)), rng.uniform(-100, 100, (M, 3))
    for code in ALL_CONFIGURATIONS:
        cfg = Configuration.parse(code)
        for conv in ("iso230", "free"):
            em = ErrorModel.default(nom, 3, straightness_convention=conv, tool_axis=cfg.tool[-1] if cfg.tool else None)
            th = rng.standard_normal((3, len(em.params))) * 1e-4
            inp = ChainInputs(nom, tool, offset={"x": rng.standard_normal((3, M)) * 1e-3},
                              scale={"z": rng.standard_normal((1, M)) * 1e-5})
            proj = rng.standard_normal((len(em.params), 5))
            P, J = chain(cfg, em, th, inp, jacobian=True, project=proj)
            Pr, Jr = chain_reference(cfg, em, th, inp, jacobian=True, project=proj)
            assert np.abs(P - Pr).max() < 1e-11  # mm, on points ~500 mm from the origin: round-off
            assert np.abs(J - Jr).max() < 1e-10
            h = 1e-6  # the chain is a low-degree polynomial in theta: central differences are exact to ~1e-9
            d = rng.standard_normal(len(em.params))
            fd = (chain(cfg, em, th + h * d, inp) - chain(cfg, em, th - h * d, inp)) / (2 * h)
            full = chain(cfg, em, th, inp, jacobian=True)[1]
            assert np.abs(fd - full @ d).max() < 1e-6
    em = ErrorModel(ranges={a: (-300, 300) for a in "xyz"}, degrees={"dx(x)": 2, "ey(z)": 1}, squareness=False)
    cfg = Configuration.parse("XFYZ")
    th = rng.standard_normal((2, len(em.params))) * 1e-4
    for a, b in zip(chain(cfg, em, th, ChainInputs(nom, tool), jacobian=True),
                    chain_reference(cfg, em, th, ChainInputs(nom, tool), jacobian=True)):
        assert np.abs(a - b).max() < 1e-11


def test_a_trials_chain_does_not_depend_on_the_trials_evaluated_with_it():
    from mtbudget.machine import ChainInputs, chain

    rng = np.random.default_rng(8)
    nom = rng.uniform(-300, 300, (40, 3))
    em = ErrorModel.default(nom, 3, tool_axis="z")
    cfg = Configuration.parse("XFYZ")
    th = rng.standard_normal((37, len(em.params))) * 1e-4
    inp = ChainInputs(nom, rng.uniform(-100, 100, (40, 3)))
    all_rows = chain(cfg, em, th, inp)
    for lo, hi in ((0, 1), (5, 6), (3, 5), (2, 9), (10, 37)):
        assert np.array_equal(chain(cfg, em, th[lo:hi], inp), all_rows[lo:hi])


def test_the_chain_adjoint_is_the_transposed_jacobian_for_every_configuration():
    """machine.chain_adjoint: J^T v without forming J, against the Jacobian of machine.chain, for every configuration,
    both conventions, offsets and scales, models that leave errors and squareness out, and subsets of the trials;
    a trial's J^T v does not depend on the trials evaluated with it, bit for bit."""
    from mtbudget.machine import chain_adjoint

    rng = np.random.default_rng(5)
    M = 30
    nom, tool = rng.uniform(-300, 300, (M, 3)), rng.uniform(-100, 100, (M, 3))
    models = []
    for code in ALL_CONFIGURATIONS:
        cfg = Configuration.parse(code)
        for conv in ("iso230", "free"):
            models.append((cfg, ErrorModel.default(nom, 3, straightness_convention=conv,
                                                   tool_axis=cfg.tool[-1] if cfg.tool else None)))
    models.append((Configuration.parse("XFYZ"), ErrorModel(ranges={a: (-300, 300) for a in "xyz"},
                                                           degrees={"dx(x)": 2, "ey(z)": 1}, squareness=False)))
    for cfg, em in models:
        th = rng.standard_normal((5, len(em.params))) * 1e-4
        inp = ChainInputs(nom, tool, offset={"x": rng.standard_normal((5, M)) * 1e-3},
                          scale={"z": rng.standard_normal((1, M)) * 1e-5})
        P, J = chain(cfg, em, th, inp, jacobian=True)
        v = rng.standard_normal((5, M, 3))
        ref = np.einsum("nmi,nmip->np", v, J)
        scale = np.abs(ref).max()
        for reference in (False, True):  # compiled, and the numpy formulation
            Pa, adj = chain_adjoint(cfg, em, th, inp, reference=reference)
            assert np.abs(P - Pa).max() <= 1e-12 * np.abs(P).max()
            assert np.abs(adj(v) - ref).max() <= 1e-13 * scale, cfg.code
            idx = np.array([1, 3, 4])
            assert np.abs(adj(v[idx], idx) - ref[idx]).max() <= 1e-13 * scale
    # the same bits for a trial whatever other trials are evaluated with it
    cfg, em = models[0]
    th = rng.standard_normal((9, len(em.params))) * 1e-4
    v = rng.standard_normal((9, M, 3))
    whole = chain_adjoint(cfg, em, th, ChainInputs(nom, tool))[1](v)
    for lo, hi in ((0, 1), (2, 5), (4, 9)):
        assert np.array_equal(chain_adjoint(cfg, em, th[lo:hi], ChainInputs(nom, tool))[1](v[lo:hi]), whole[lo:hi])
    sub = np.array([0, 2, 7])
    assert np.array_equal(chain_adjoint(cfg, em, th, ChainInputs(nom, tool))[1](v[sub], sub), whole[sub])
