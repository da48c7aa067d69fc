"""The generic propagation against the published JCGM 101 and GUM examples and closed forms."""

import math

import numpy as np
import pytest
from scipy import stats

from mtbudget import ureg
from mtbudget.distributions import (Arcsine, CurvilinearTrapezoid, DistributionError, Exponential, Gamma, Normal,
                                    Rectangular, StudentT, Triangular)
from mtbudget.mcm import ModelError, propagate
from mtbudget.stats import numerical_tolerance

nm, mg, kgm3, degC, perK = ureg.nm, ureg.mg, ureg("kg/m^3").units, ureg.delta_degC, ureg("1/K").units
M6 = 1_000_000


def additive(X1, X2, X3, X4):
    return X1 + X2 + X3 + X4


def test_9_2_2_normal_inputs():
    res = propagate(additive, {f"X{i}": Normal(0.0, 1.0) for i in range(1, 5)}, trials=M6, seed=1)
    assert res.gum.std_uncertainty.magnitude == pytest.approx(2.0, abs=1e-9)
    lo, hi = res.gum.interval()
    assert (lo.magnitude, hi.magnitude) == pytest.approx((-3.92, 3.92), abs=0.005)
    assert res.std_uncertainty.magnitude == pytest.approx(2.00, abs=0.005)
    lo, hi = res.interval("symmetric")
    assert (round(lo.magnitude, 2), round(hi.magnitude, 2)) == pytest.approx((-3.92, 3.92), abs=0.011)
    assert res.validate().passed


def test_9_2_3_rectangular_inputs():
    s3 = math.sqrt(3)
    res = propagate(additive, {f"X{i}": Rectangular(-s3, s3) for i in range(1, 5)}, trials=M6, seed=2)
    assert res.gum.std_uncertainty.magnitude == pytest.approx(2.0, abs=1e-9)
    lo, hi = res.interval("symmetric")
    assert (lo.magnitude, hi.magnitude) == pytest.approx((-3.88, 3.88), abs=0.011)
    assert res.validate().passed  # JCGM 101: the GUF is validated (|3.92 - 3.88| <= 0.05)


def test_9_2_4_one_dominant_rectangular_input():
    s3 = math.sqrt(3)
    inputs = {"X1": Normal(0, 1), "X2": Normal(0, 1), "X3": Normal(0, 1), "X4": Rectangular(-10 * s3, 10 * s3)}
    res = propagate(additive, inputs, trials=M6, seed=3)
    assert res.gum.std_uncertainty.magnitude == pytest.approx(10.15, abs=0.005)
    g_lo, g_hi = res.gum.interval()
    assert g_hi.magnitude == pytest.approx(19.9, abs=0.05)
    assert res.std_uncertainty.magnitude == pytest.approx(10.2, abs=0.05)
    lo, hi = res.interval("symmetric")
    assert (lo.magnitude, hi.magnitude) == pytest.approx((-17.0, 17.0), abs=0.06)
    assert not res.validate().passed  # JCGM 101: the GUF is not validated here


def mass_model(m_Rc, dm_Rc, rho_a, rho_W, rho_R):
    rho_a0 = 1.2 * kgm3
    m_nom = 100_000 * mg
    return (m_Rc + dm_Rc) * (1 + (rho_a - rho_a0) * (1 / rho_W - 1 / rho_R)) - m_nom


MASS_INPUTS = {
    "m_Rc": Normal(100_000.000 * mg, 0.050 * mg),
    "dm_Rc": Normal(1.234 * mg, 0.020 * mg),
    "rho_a": Rectangular(1.10 * kgm3, 1.30 * kgm3),
    "rho_W": Rectangular(7e3 * kgm3, 9e3 * kgm3),
    "rho_R": Rectangular(7.95e3 * kgm3, 8.05e3 * kgm3),
}


def test_9_3_mass_calibration():
    res = propagate(mass_model, MASS_INPUTS, trials=M6, seed=4)
    assert res.gum.estimate.to(mg).magnitude == pytest.approx(1.2340, abs=5e-5)
    assert res.gum.std_uncertainty.to(mg).magnitude == pytest.approx(0.0539, abs=5e-5)
    assert res.estimate.to(mg).magnitude == pytest.approx(1.2341, abs=2e-4)
    assert res.std_uncertainty.to(mg).magnitude == pytest.approx(0.0754, abs=3e-4)
    lo, hi = res.interval("shortest")
    assert lo.to(mg).magnitude == pytest.approx(1.0834, abs=1e-3)
    assert hi.to(mg).magnitude == pytest.approx(1.3825, abs=1e-3)
    assert not res.validate().passed
    # the budget: share of variance adds up to one; rho_W dominates nothing at first order
    assert sum(r.share for r in res.budget) == pytest.approx(1.0)


@pytest.mark.parametrize("x1", [0.0, 0.010, 0.050])
def test_9_4_comparison_loss_against_exact_moments(x1):
    u = 0.005

    def loss(X1, X2):
        return X1**2 + X2**2

    res = propagate(loss, {"X1": Normal(x1, u), "X2": Normal(0.0, u)}, trials=M6, seed=5)
    exact_mean = x1**2 + 2 * u**2
    exact_u = math.sqrt(4 * u**2 * x1**2 + 4 * u**4)
    assert res.estimate.magnitude == pytest.approx(exact_mean, rel=5e-3, abs=2e-7)
    assert res.std_uncertainty.magnitude == pytest.approx(exact_u, rel=5e-3)
    # GUF (first order): y = x1^2, u = 2 x1 u -- zero at x1 = 0
    assert res.gum.estimate.magnitude == pytest.approx(x1**2, abs=1e-15)
    assert res.gum.std_uncertainty.magnitude == pytest.approx(2 * x1 * u, rel=1e-6, abs=1e-12)
    if x1 == 0.0:
        # Y/u^2 is chi-square with 2 dof: the shortest 95 % interval is [0, -2u^2 ln 0.05]
        lo, hi = res.interval("shortest")
        assert lo.magnitude == pytest.approx(0.0, abs=1e-7)
        assert hi.magnitude == pytest.approx(-2 * u**2 * math.log(0.05), rel=0.01)
        assert hi.magnitude == pytest.approx(150e-6, abs=1e-6)


def test_9_4_correlated_inputs():
    u, x1, r = 0.005, 0.010, 0.9

    def loss(X1, X2):
        return X1**2 + X2**2

    res = propagate(loss, {"X1": Normal(x1, u), "X2": Normal(0.0, u)}, trials=M6, seed=6, correlations={("X1", "X2"): r})
    # exact: E = x1^2 + 2u^2 ; Var = 4u^2 x1^2 + 4u^4 (1 + r^2)
    assert res.estimate.magnitude == pytest.approx(x1**2 + 2 * u**2, rel=5e-3)
    assert res.std_uncertainty.magnitude == pytest.approx(math.sqrt(4 * u**2 * x1**2 + 4 * u**4 * (1 + r**2)), rel=5e-3)


def gauge_block(Ls, D1, D2, D3, alpha_s, theta_bar, Delta, dalpha, dtheta):
    """JCGM 101 9.5 (GUM H.1) full model: deviation of the length from 50 mm."""
    L_nom = 50_000_000 * nm
    D = D1 + D2 + D3
    theta = theta_bar + Delta
    alpha = alpha_s + dalpha
    theta_s = theta - dtheta
    L = (Ls * (1 + alpha_s * theta_s) + D) / (1 + alpha * theta)
    return (L - L_nom).to(nm)


GAUGE = {
    "Ls": StudentT(50_000_623.6 * nm, 25 * nm, 18),
    "D1": StudentT(215 * nm, 5.8 * nm, 24),
    "D2": StudentT(0 * nm, 3.9 * nm, 5),
    "D3": StudentT(0 * nm, 6.7 * nm, 8),
    "alpha_s": Rectangular(9.5e-6 * perK, 13.5e-6 * perK),
    "theta_bar": Normal(-0.1 * degC, 0.2 * degC),
    "Delta": Arcsine(-0.5 * degC, 0.5 * degC),
    "dalpha": CurvilinearTrapezoid(-1e-6 * perK, 1e-6 * perK, 0.1e-6 * perK, dof=50),
    "dtheta": CurvilinearTrapezoid(-0.050 * degC, 0.050 * degC, 0.025 * degC, dof=2),
}


def test_9_5_gauge_block_and_gum_h1():
    res = propagate(gauge_block, GAUGE, coverage=0.99, trials=M6, seed=7)
    # GUF (GUM H.1): 838 nm, u = 32 nm, nu_eff = 16, 99 % interval [745, 931] nm
    assert res.gum.estimate.to(nm).magnitude == pytest.approx(838, abs=0.7)
    assert res.gum.std_uncertainty.to(nm).magnitude == pytest.approx(32, abs=0.5)
    assert int(res.gum.dof) == 16
    # MCM (JCGM 101 9.5): u = 36 nm, 99 % interval about [745, 932] nm
    assert res.estimate.to(nm).magnitude == pytest.approx(838, abs=1.0)
    assert res.std_uncertainty.to(nm).magnitude == pytest.approx(36, abs=0.6)
    lo, hi = res.interval("symmetric")
    assert lo.to(nm).magnitude == pytest.approx(745, abs=2)
    assert hi.to(nm).magnitude == pytest.approx(932, abs=2)


def test_budget_rows_have_units_and_add_up():
    res = propagate(gauge_block, GAUGE, coverage=0.99, trials=20_000, seed=8)
    rows = {r.name: r for r in res.budget}
    assert rows["Ls"].contribution.to(nm).magnitude == pytest.approx(25, rel=1e-3)
    assert rows["dtheta"].contribution.to(nm).magnitude == pytest.approx(16.6, abs=0.1)
    assert rows["dtheta"].sensitivity.dimensionality == (nm / degC).dimensionality
    assert sum(r.share for r in res.budget) == pytest.approx(1.0, rel=1e-9)


def test_adaptive_reaches_its_numerical_tolerance():
    res = propagate(additive, {f"X{i}": Normal(0.0, 1.0) for i in range(1, 5)}, trials=None, seed=11)
    assert res.trials >= 20_000 and res.trials % 10_000 == 0
    # the JCGM 101 7.9 criterion is met at the end: twice the standard deviation of the batch means <= delta
    arr = np.array([b[1:] for b in res.batches])
    s = arr.std(axis=0, ddof=1) / math.sqrt(len(arr))
    assert np.all(2 * s <= numerical_tolerance(res.std_uncertainty.magnitude, 2))  # = 0.05 for u = 2.0
    # and the result is right to the tolerance the procedure promises (2 significant digits of u = 2.0)
    assert res.std_uncertainty.magnitude == pytest.approx(2.0, abs=numerical_tolerance(2.0, 2))


def test_coverage_is_what_it_says():
    """Repeated experiments with known truth: the 95 % MCM interval covers the truth ~95 % of the time."""
    rng = np.random.default_rng(0)
    hits, n = 0, 400
    for k in range(n):
        truth = 10.0
        x_obs = truth + rng.normal(0, 0.3) + rng.uniform(-0.5, 0.5)
        res = propagate(lambda e1, e2: x_obs - e1 - e2, {"e1": Normal(0, 0.3), "e2": Rectangular(-0.5, 0.5)},
                        trials=4000, seed=k)
        lo, hi = res.interval("symmetric")
        hits += lo.magnitude <= truth <= hi.magnitude
    # binomial: 95 % of 400 = 380, sd 4.4; accept +- 3.5 sd
    assert abs(hits - 380) <= 16


def test_distribution_moments_and_units(rng):
    cases = [
        (Normal(5 * ureg.um, 2 * ureg.um), 5, 2),
        (Rectangular(0 * ureg.um, 12 * ureg.um), 6, 12 / math.sqrt(12)),
        (Triangular(-3 * ureg.um, 3 * ureg.um), 0, 3 / math.sqrt(6)),
        (Arcsine(-2 * ureg.um, 2 * ureg.um), 0, 2 / math.sqrt(2)),
        (StudentT(1 * ureg.um, 1 * ureg.um, 6), 1, math.sqrt(6 / 4)),
        (CurvilinearTrapezoid(-1 * ureg.um, 1 * ureg.um, 0.2 * ureg.um), 0, math.sqrt(4 / 12 + 0.04 / 9)),
        (Exponential(3 * ureg.um), 3, 3),
        (Gamma(4 * ureg.um, 1 * ureg.um), 4, 1),
    ]
    for dist, mean, std in cases:
        x = dist.sample(400_000, rng)
        assert x.units == ureg.um
        assert dist.mean.magnitude == pytest.approx(mean)
        assert dist.std.magnitude == pytest.approx(std, rel=1e-12)
        assert x.magnitude.mean() == pytest.approx(mean, abs=5 * std / math.sqrt(4e5))
        assert x.magnitude.std() == pytest.approx(std, rel=0.01)
    # shapes: Kolmogorov-Smirnov against scipy's own distributions
    x = Arcsine(-2, 2).sample(50_000, rng).magnitude
    assert stats.kstest(x, stats.arcsine(loc=-2, scale=4).cdf).pvalue > 1e-3
    x = StudentT(0, 1, 5).sample(50_000, rng).magnitude
    assert stats.kstest(x, stats.t(5).cdf).pvalue > 1e-3


@pytest.mark.filterwarnings("ignore:invalid value encountered")
def test_bad_input():
    with pytest.raises(DistributionError, match="std must be >= 0"):
        Normal(0, -1)
    with pytest.raises(DistributionError, match="low must be < high"):
        Rectangular(2, 1)
    with pytest.raises(DistributionError, match="dof must be > 2"):
        StudentT(0, 1, 2)
    with pytest.raises(DistributionError, match="different dimensions"):
        Normal(1 * ureg.mm, 1 * ureg.s)
    with pytest.raises(ModelError, match="units do not fit"):
        propagate(lambda a, b: a + b, {"a": Normal(1 * ureg.mm, 0.1 * ureg.mm), "b": Normal(1 * ureg.s, 0.1 * ureg.s)},
                  trials=100)
    with pytest.raises(ModelError, match="NaN or infinity for [0-9]+ of 2000 trials.*x="):
        propagate(lambda x: np.sqrt(x), {"x": Normal(0.5, 1.0)}, trials=2000)
    with pytest.raises(ModelError, match="not positive definite"):
        propagate(lambda a, b, c: a + b + c, {"a": Normal(0, 1), "b": Normal(0, 1), "c": Normal(0, 1)}, trials=100,
                  correlations={("a", "b"): 0.9, ("b", "c"): 0.9, ("a", "c"): -0.9})
    with pytest.raises(ModelError, match="only Normal"):
        propagate(lambda a, b: a + b, {"a": Normal(0, 1), "b": Rectangular(0, 1)}, trials=100, correlations={("a", "b"): 0.5})


@pytest.mark.parametrize("dist, law", [
    (StudentT(5.0, 2.0, 5), stats.t(5, loc=5.0, scale=2.0)),
    (StudentT(0.0, 1.0, 24), stats.t(24)),
    (Arcsine(-1.0, 3.0), stats.arcsine(loc=-1.0, scale=4.0)),
    (Rectangular(2.0, 5.0), stats.uniform(loc=2.0, scale=3.0)),
])
def test_draws_follow_their_law_and_the_seed(dist, law):
    """The in-place draws (and Bailey's polar method for t) have the stated law, and one seed gives one stream."""
    x = dist.sample(200_000, np.random.default_rng(11)).magnitude
    assert np.array_equal(x, dist.sample(200_000, np.random.default_rng(11)).magnitude)
    assert stats.kstest(x, law.cdf).pvalue > 1e-3
    assert x.std(ddof=1) == pytest.approx(dist.std.magnitude, rel=0.02)
    small = dist.sample(7, np.random.default_rng(11)).magnitude  # few draws: the same code path
    assert small.shape == (7,) and np.isfinite(small).all()


def test_curvilinear_trapezoid_draws_have_its_variance():
    d = CurvilinearTrapezoid(-1.0, 1.0, 0.25)
    x = d.sample(400_000, np.random.default_rng(12)).magnitude
    assert x.var() == pytest.approx(1 / 3 + 0.25**2 / 9, rel=0.01)
    assert np.abs(x).max() <= 1.25
