"""Several outputs (JCGM 102) through mcm.propagate: GUM H.2, closed-form moments, and the coverage regions."""

import math

import numpy as np
import pytest
from scipy import stats

from mtbudget import ureg
from mtbudget.distributions import Normal
from mtbudget.errors import ModelError
from mtbudget.mcm import MultiResult, gum, gum_multi, propagate

V, mA, rad, ohm = ureg.V, ureg.mA, ureg.rad, ureg.ohm


def h2_model(V, I, phi):
    Z = (V / I).to(ohm)
    return {"R": Z * np.cos(phi), "X": Z * np.sin(phi), "Z": Z}


# GUM H.2 (Table H.2, rounded): the means, standard uncertainties and correlation coefficients of the five readings
H2_INPUTS = {"V": Normal(4.9990 * V, 0.0032 * V), "I": Normal(19.6610 * mA, 0.0095 * mA),
             "phi": Normal(1.04446 * rad, 0.00075 * rad)}
H2_CORR = {("V", "I"): -0.36, ("V", "phi"): 0.86, ("I", "phi"): -0.65}
# GUM H.2 Table H.4 (approach 1): u(R), u(X), u(Z) and r(R, X), r(R, Z), r(X, Z)
H2_U = {"R": 0.071, "X": 0.295, "Z": 0.236}
H2_R = {("R", "X"): -0.588, ("R", "Z"): -0.485, ("X", "Z"): 0.993}


@pytest.fixture(scope="module")
def h2():
    return propagate(h2_model, H2_INPUTS, trials=200_000, seed=3, correlations=H2_CORR)


def test_gum_h2_outputs_and_correlations(h2):
    assert isinstance(h2, MultiResult)
    assert h2.names == ["R", "X", "Z"]
    assert all(u == ohm for u in h2.units)
    assert h2.estimate == pytest.approx([127.732, 219.847, 254.260], abs=0.01)
    for res, label in ((h2, "MCM"), (h2.gum, "GUF")):
        u = dict(zip(h2.names, res.std_uncertainty))
        r = res.correlation
        for n, pub in H2_U.items():
            assert u[n] == pytest.approx(pub, rel=0.03), (label, n)
        for (a, b), pub in H2_R.items():
            assert r[h2.names.index(a), h2.names.index(b)] == pytest.approx(pub, abs=0.03), (label, a, b)
    # each output is the univariate result of today, from the same trials
    assert h2.outputs["Z"].std_uncertainty.to(ohm).magnitude == pytest.approx(h2.std_uncertainty[2], rel=1e-12)
    assert h2.outputs["R"].gum.std_uncertainty.to(ohm).magnitude == pytest.approx(math.sqrt(h2.gum.covariance[0, 0]))
    assert h2.covariance.shape == (3, 3) and np.allclose(h2.covariance, h2.covariance.T)


def test_sensitivity_matrix_is_the_analytic_jacobian():
    g = gum_multi(h2_model, H2_INPUTS, correlations=H2_CORR)
    v, i, p = 4.9990, 19.6610e-3, 1.04446  # V, A, rad: the Jacobian written here by hand
    z = v / i
    J = np.array([[math.cos(p) / i, -z * math.cos(p) / i, -z * math.sin(p)],
                  [math.sin(p) / i, -z * math.sin(p) / i, z * math.cos(p)],
                  [1 / i, -z / i, 0.0]])
    J[:, 1] *= 1e-3  # per mA
    assert g.input_names == ["V", "I", "phi"]
    assert np.allclose(g.sensitivity, J, rtol=1e-6, atol=1e-9)


def polar(X1, X2):
    return {"Y1": X1 * np.cos(X2), "Y2": X1 * np.sin(X2)}


def polar_moments(m1, s1, m2, s2):
    """Closed-form mean and covariance of (X1 cos X2, X1 sin X2), X1 and X2 independent normals."""
    e1, e2 = math.exp(-s2**2 / 2), math.exp(-2 * s2**2)
    q = m1**2 + s1**2
    mean = np.array([m1 * math.cos(m2) * e1, m1 * math.sin(m2) * e1])
    second = np.array([[q * (1 + math.cos(2 * m2) * e2) / 2, q * math.sin(2 * m2) * e2 / 2],
                       [q * math.sin(2 * m2) * e2 / 2, q * (1 - math.cos(2 * m2) * e2) / 2]])
    return mean, second - np.outer(mean, mean)


@pytest.mark.parametrize("m1, s1, m2, s2, guf_ok", [
    (0.001, 0.010, math.pi / 2, 0.010, False),  # JCGM 102 9.3's strongly non-linear case: the GUF misses u(Y1)
    (1.0, 0.030, 0.5, 0.010, True),  # far from the origin: near-linear, the GUF holds
])
def test_polar_to_cartesian_against_closed_form(m1, s1, m2, s2, guf_ok):
    res = propagate(polar, {"X1": Normal(m1, s1), "X2": Normal(m2, s2)}, trials=200_000, seed=7)
    mean, cov = polar_moments(m1, s1, m2, s2)
    u = np.sqrt(np.diagonal(cov))
    assert res.estimate == pytest.approx(mean, abs=5 * u.max() / math.sqrt(res.trials))
    assert res.std_uncertainty == pytest.approx(u, rel=0.01)
    r = cov[0, 1] / (u[0] * u[1])
    assert res.correlation[0, 1] == pytest.approx(r, abs=0.01)
    assert res.validate().passed is guf_ok


def test_regions_of_a_linear_model_of_normal_inputs():
    # Y = A X, X independent standard normals: the outputs are normal with covariance A A^T
    A = np.array([[1.0, 0.5, 0.0], [0.0, 1.0, -0.8], [0.3, 0.0, 1.0]])

    def lin(X1, X2, X3):
        return {f"Y{j + 1}": A[j, 0] * X1 + A[j, 1] * X2 + A[j, 2] * X3 for j in range(3)}

    res = propagate(lin, {f"X{i}": Normal(0.0, 1.0) for i in (1, 2, 3)}, trials=200_000, seed=5)
    assert np.allclose(res.gum.covariance, A @ A.T, atol=1e-9)
    e_mcm, e_guf = res.region("hyperellipsoidal"), res.gum.region("hyperellipsoidal")
    assert e_guf.k == pytest.approx(math.sqrt(stats.chi2.ppf(0.95, 3)), rel=1e-9)
    assert e_mcm.k == pytest.approx(e_guf.k, abs=0.02)
    r_mcm, r_guf = res.region("hyperrectangular"), res.gum.region("hyperrectangular")
    assert r_mcm.k == pytest.approx(r_guf.k, abs=0.02)
    # the region holds what it says, on fresh draws of the same law
    fresh = np.random.default_rng(99).standard_normal((100_000, 3)) @ A.T
    for reg in (e_mcm, r_mcm):
        assert reg.contains(fresh).mean() == pytest.approx(0.95, abs=0.005)
    assert res.validate().passed


def test_independent_outputs_hyperrectangle_is_sidak():
    res = propagate(lambda A, B: {"A": A, "B": B * 2}, {"A": Normal(0, 1), "B": Normal(0, 1)}, trials=200_000, seed=2)
    k = stats.norm.ppf((1 + math.sqrt(0.95)) / 2)
    assert res.gum.region("hyperrectangular").k == pytest.approx(k, abs=2e-3)
    assert res.region("hyperrectangular").k == pytest.approx(k, abs=0.02)


def test_adaptive_several_outputs_stops_on_every_output():
    res = propagate(polar, {"X1": Normal(1.0, 0.01), "X2": Normal(0.5, 0.01)}, trials=None, seed=1, batch=10_000)
    assert res.batches and res.trials == res.batches[-1]
    assert res.trials >= 20_000


def test_bad_multi_output_models_say_what():
    with pytest.raises(ModelError, match="several outputs"):
        gum(polar, {"X1": Normal(1.0, 0.01), "X2": Normal(0.5, 0.01)})
    calls = []

    def flaky(X):
        calls.append(1)
        return {"a": X} if len(calls) < 3 else {"b": X}  # the probe, the GUF, then the trials

    with pytest.raises(ModelError, match="same named outputs"):
        propagate(flaky, {"X": Normal(0, 1)}, trials=100)
    with pytest.raises(ModelError, match="one value per trial"):
        propagate(lambda X: {"a": X, "b": np.ones((len(np.atleast_1d(X.magnitude)), 2))}, {"X": Normal(0, 1)},
                  trials=100)
