"""The rotary axes in the one chain (issue 26): against a transcription of FORMAT-3 section 4 written here with
exact rotation matrices (scipy's Rotation), the Jacobian against finite differences, the compiled forward pass and
J^T v against the matrix form."""

import numpy as np
import pytest
from numpy.polynomial import legendre
from scipy.spatial.transform import Rotation

from mtbudget.machine import (ChainInputs, Configuration, ErrorModel, RotaryAxis, chain, chain_adjoint,
                              chain_reference)

MACHINES = {
    "CAFXYZ": {"a": RotaryAxis("a", (0.0, -20.0, -80.0), 1.0), "c": RotaryAxis("c", (50.0, -20.0, 0.0), 1.0)},
    "FXYZCB": {"c": RotaryAxis("c", (10.0, -5.0, 300.0), 1.0), "b": RotaryAxis("b", (0.0, 12.0, 150.0), -1.0)},
    "CFXYZB": {"c": RotaryAxis("c", (5.0, 6.0, 0.0), -1.0), "b": RotaryAxis("b", (0.0, 10.0, 150.0), 1.0)},
    "BFXYZ": {"b": RotaryAxis("b", (0.0, 0.0, -50.0), 1.0)},
}
UNIT = {"a": np.array([1.0, 0, 0]), "b": np.array([0, 1.0, 0]), "c": np.array([0, 0, 1.0])}


def _setup(code, seed=0, M=30, harmonics=0):
    rng = np.random.default_rng(seed)
    cfg = Configuration.parse(code, MACHINES[code])
    nominal = rng.uniform(-300, 300, (M, 3))
    tool = np.column_stack([rng.uniform(-20, 20, M), rng.uniform(-20, 20, M), rng.uniform(-200, -50, M)])
    angles = {r: rng.uniform(-np.pi, np.pi, M) for r in cfg.rotary_letters}
    em = ErrorModel.default(nominal, 2, angles=angles, harmonics=harmonics, tool_axis=cfg.tool[-1],
                            straightness_convention="free")
    theta = np.zeros(len(em.params))
    for j, p in enumerate(em.params):
        theta[j] = rng.normal(0, 0.02 if p.unit == "mm" else 4e-5)
    return cfg, em, theta, ChainInputs(nominal, tool, angles=angles), rng


def _transcription(cfg, em, theta, inp):
    """FORMAT-3 section 4 and docs/model.md, point by point with exact rotations: P_M = G_1(...G_n(T)) over the
    tool-side letters from F outwards, P_W = G_1^-1(...G_m^-1(P_M)) over the workpiece-side letters."""
    names = em.names
    val = dict(zip(names, theta))
    M = inp.nominal.shape[0]
    out = np.empty((M, 3))
    for m in range(M):
        maps = {}
        for k, a in enumerate("xyz"):  # linear axes: exact rotation of the component errors, translation t
            p = inp.nominal[m, k]
            lo, hi = em.ranges[a]
            u = (p - 0.5 * (lo + hi)) / (0.5 * (hi - lo))
            delta, eps = np.zeros(3), np.zeros(3)
            for c, comp in enumerate("xyz"):
                for kind, vec in (("d", delta), ("e", eps)):
                    err = f"{kind}{comp}({a})"
                    coefs = [0.0] + [val.get(f"{err}[P{n}]", 0.0) for n in range(1, 5)]
                    coefs[0] = val.get(f"{err}[P0]", 0.0)
                    vec[c] = legendre.legval(u, coefs)
            d = np.zeros(3)
            d[k] = p
            if a == "y":
                d[0] -= p * val.get("sxy", 0.0)
            if a == "z":
                d[0] -= p * val.get("sxz", 0.0)
                d[1] -= p * val.get("syz", 0.0)
            s = 1.0 if a in cfg.tool else -1.0
            R = Rotation.from_rotvec(eps).as_matrix()
            t = s * d + delta
            maps[a] = (lambda v, R=R, t=t: R @ v + t, lambda w, R=R, t=t: R.T @ (w - t))
        for r in cfg.rotary:
            a = r.letter
            th = inp.angles[a][m] + (inp.offset[a][0, m] if a in inp.offset else 0.0)
            delta, w = np.zeros(3), np.zeros(3)
            for c, comp in enumerate("xyz"):
                for kind, vec in (("d", delta), ("e", w)):
                    err = f"{kind}{comp}({a})"
                    vec[c] = val.get(f"{err}[O]", 0.0)
                    for n in range(1, 4):
                        vec[c] += val.get(f"{err}[c{n}]", 0.0) * np.cos(n * inp.angles[a][m])
                        vec[c] += val.get(f"{err}[s{n}]", 0.0) * np.sin(n * inp.angles[a][m])
            G = Rotation.from_rotvec(w).as_matrix() @ Rotation.from_rotvec(r.sign * th * UNIT[a]).as_matrix()
            piv = np.asarray(r.pivot)
            maps[a] = (lambda v, G=G, piv=piv, dl=delta: piv + dl + G @ (v - piv),
                       lambda v, G=G, piv=piv, dl=delta: piv + G.T @ (v - piv - dl))
        v = inp.tool[m].copy()
        for a in reversed(cfg.tool):
            v = maps[a][0](v)
        for a in cfg.workpiece:
            v = maps[a][1](v)
        out[m] = v
    return out


@pytest.mark.parametrize("code", sorted(MACHINES))
def test_chain_equals_an_independent_transcription_with_exact_rotations(code):
    cfg, em, theta, inp, _ = _setup(code, harmonics=2)
    ref = _transcription(cfg, em, theta, inp)
    exact = chain(cfg, em, theta, inp, exact=True)[0]
    assert np.abs(exact - ref).max() < 1e-9  # the same equations, exact rotations on both sides
    small = chain(cfg, em, theta, inp)[0]  # Eq. 6: the error rotations to first order
    assert 1e-9 < np.abs(small - ref).max() < 2e-5  # O(eps^2 * lever): tens of nm at 40-100 urad on ~1 m


@pytest.mark.parametrize("code", sorted(MACHINES))
def test_nominal_rotation_turns_the_tool_point_about_the_pivot(code):
    """Error-free: a rotary axis turns what it carries about its pivot by the commanded angle, right-handed about
    its direction; a workpiece-side one turns the tool point the other way in the table frame."""
    cfg, em, theta, inp, rng = _setup(code, seed=3)
    base = chain(cfg, em, np.zeros_like(theta), inp)[0]
    r = cfg.rotary[0]
    turned = dict(inp.angles)
    turned[r.letter] = inp.angles[r.letter] + 0.3
    moved = chain(cfg, em, np.zeros_like(theta), ChainInputs(inp.nominal, inp.tool, angles=turned))[0]
    if r.letter in cfg.workpiece and cfg.workpiece[-1] == r.letter:  # the outermost workpiece axis: the last map
        R = Rotation.from_rotvec(-0.3 * r.sign * UNIT[r.letter]).as_matrix()
        np.testing.assert_allclose(moved, (base - r.pivot) @ R.T + r.pivot, atol=1e-9)
    elif r.letter in cfg.tool and cfg.tool[0] == r.letter:  # the tool-side axis next to the bed
        R = Rotation.from_rotvec(0.3 * r.sign * UNIT[r.letter]).as_matrix()
        np.testing.assert_allclose(moved, (base - r.pivot) @ R.T + r.pivot, atol=1e-9)
    else:
        assert np.abs(moved - base).max() > 1.0


@pytest.mark.parametrize("code", sorted(MACHINES))
def test_jacobian_equals_finite_differences(code):
    cfg, em, theta, inp, _ = _setup(code, seed=1, M=12, harmonics=1)
    _, J = chain(cfg, em, theta, inp, jacobian=True)
    h = 1e-6
    for j in range(len(theta)):
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        fd = (chain(cfg, em, tp, inp)[0] - chain(cfg, em, tm, inp)[0]) / (2 * h)
        assert np.abs(J[0, :, :, j] - fd).max() < 1e-5 * max(1.0, np.abs(fd).max()), em.names[j]


@pytest.mark.parametrize("code", sorted(MACHINES))
def test_compiled_points_and_adjoint_equal_the_matrix_form(code):
    cfg, em, theta, inp, rng = _setup(code, seed=2, M=25, harmonics=2)
    thetas = theta + rng.normal(0, 1e-5, (4, theta.size))
    a = cfg.rotary_letters[-1]
    inp = ChainInputs(inp.nominal, inp.tool, angles=inp.angles, offset={a: rng.normal(0, 1e-4, (4, 25))})
    P = chain(cfg, em, thetas, inp)
    Pr, J = chain_reference(cfg, em, thetas, inp, jacobian=True)
    np.testing.assert_allclose(P, Pr, atol=1e-10)
    _, adj = chain_adjoint(cfg, em, thetas, inp)
    v = rng.normal(size=(4, 25, 3))
    want = np.einsum("nmcp,nmc->np", J, v)
    np.testing.assert_allclose(adj(v), want, atol=1e-9 * np.abs(want).max())
    np.testing.assert_allclose(adj(v[1:3], np.array([1, 2])), want[1:3], atol=1e-9 * np.abs(want).max())


def test_an_angle_offset_is_a_change_of_the_commanded_angle():
    cfg, em, theta, inp, _ = _setup("CAFXYZ", seed=4)
    off = np.full((1, inp.nominal.shape[0]), 2e-4)
    a = chain(cfg, em, theta, ChainInputs(inp.nominal, inp.tool, angles=inp.angles, offset={"c": off}))
    turned = dict(inp.angles, c=inp.angles["c"] + 2e-4)
    em2 = ErrorModel.default(inp.nominal, 2, angles=inp.angles, tool_axis="z", straightness_convention="free")
    B = em2.basis(inp.nominal, inp.angles)  # the error motions stay those of the commanded angle
    b = chain(cfg, em2, theta, ChainInputs(inp.nominal, inp.tool, angles=turned), B=B)
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_a_configuration_with_a_rotary_letter_needs_its_geometry():
    from mtbudget.errors import ConfigError

    with pytest.raises(ConfigError, match=r"rotary axis C has no pivot"):
        Configuration.parse("CAFXYZ", {"a": MACHINES["CAFXYZ"]["a"]})
    with pytest.raises(ConfigError, match=r"has no rotary axis B"):
        Configuration.parse("XFYZ", {"b": MACHINES["BFXYZ"]["b"]})
    with pytest.raises(ConfigError, match=r"at most one of each rotary letter"):
        Configuration.parse("CCFXYZ", MACHINES["CAFXYZ"])
