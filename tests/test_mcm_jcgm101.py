"""The generic propagation against the published JCGM 101 and GUM examples and closed forms."""

import math

import numpy as np
import pytest
from scipy import optimize, stats

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


def mass_exact(p=None):
    """JCGM 101 9.3 exactly: the output's standard deviation (p None) or its p-quantile, in mg.

    Given the three rectangular densities, Y = A (1 + B) - m_nom with A = m_Rc + dm_Rc normal is normal
    (mean mu_A (1 + B) - m_nom, standard deviation s_A (1 + B)), B = (rho_a - rho_a0)(1/rho_W - 1/rho_R): the CDF
    is the mean of the normal CDF over the three rectangular inputs (Gauss-Legendre, 20 nodes each: converged to
    1e-11 mg).  The variance is closed: s_A^2 E(1 + B)^2 + mu_A^2 Var B, with E B = 0, E 1/rho = ln(b/a)/(b - a)
    and E 1/rho^2 = 1/(a b) for rho rectangular on [a, b].
    """
    mu_a, s_a = 100_000 + 1.234, math.hypot(0.050, 0.020)
    e1, e2 = (lambda a, b: math.log(b / a) / (b - a)), (lambda a, b: 1 / (a * b))
    d2 = e2(7e3, 9e3) - e1(7e3, 9e3) ** 2 + e2(7.95e3, 8.05e3) - e1(7.95e3, 8.05e3) ** 2 + (e1(7e3, 9e3) - e1(7.95e3, 8.05e3)) ** 2
    var_b = 0.2**2 / 12 * d2
    if p is None:
        return math.sqrt(s_a**2 * (1 + var_b) + mu_a**2 * var_b)
    x, w = np.polynomial.legendre.leggauss(20)
    (ra, wa), (rw, ww), (rr, wr) = [((a + b) / 2 + (b - a) / 2 * x, w / 2) for a, b in ((1.10, 1.30), (7e3, 9e3), (7.95e3, 8.05e3))]
    B = ((ra - 1.2)[:, None, None] * (1 / rw[None, :, None] - 1 / rr[None, None, :])).ravel()
    W = (wa[:, None, None] * ww[None, :, None] * wr[None, None, :]).ravel()
    return optimize.brentq(lambda y: W @ stats.norm.cdf((y - mu_a * (1 + B) + 100_000) / (s_a * (1 + B))) - p, 0.5, 2.0, xtol=1e-12)


def test_9_3_mass_calibration():
    res = propagate(mass_model, MASS_INPUTS, trials=M6, seed=4)
    assert res.gum.estimate.to(mg).magnitude == pytest.approx(1.2340, abs=5e-5)
    assert res.gum.std_uncertainty.to(mg).magnitude == pytest.approx(0.0539, abs=5e-5)
    # JCGM 101 Table 9 (one run of 10^6 trials): 1.2341 mg, u = 0.0754 mg, shortest 95 % [1.0834, 1.3825] mg.
    # Exactly (mass_exact): the mean is 1.2340 mg (E rho_a = rho_a0), u = 0.075480 mg, and the law is symmetric about
    # the mean (to 3e-8 mg), so the shortest 95 % interval is the symmetric one, [1.08443, 1.38357] mg.  Tolerances: 4 standard
    # errors of 10^6 trials (mean: u / 1000; u: 4e-5; symmetric ends: sqrt(0.025 0.975 / 10^6) / pdf = 2.1e-4; the
    # shortest interval's ends scatter by about 1e-3 from run to run, the published ones too)
    u = mass_exact()
    assert u == pytest.approx(0.0754, abs=1e-4)  # the published value, from the closed form
    assert res.estimate.to(mg).magnitude == pytest.approx(1.2340, abs=4 * u / 1000)
    assert res.std_uncertainty.to(mg).magnitude == pytest.approx(u, abs=1.6e-4)
    q_lo, q_hi = mass_exact(0.025), mass_exact(0.975)
    assert (q_lo, q_hi) == pytest.approx((1.0834, 1.3825), abs=1.5e-3)  # the published interval, within its scatter
    lo, hi = res.interval("symmetric")
    assert (lo.to(mg).magnitude, hi.to(mg).magnitude) == pytest.approx((q_lo, q_hi), abs=8.5e-4)
    lo, hi = res.interval("shortest")
    assert (lo.to(mg).magnitude, hi.to(mg).magnitude) == pytest.approx((q_lo, q_hi), abs=4e-3)
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


@pytest.mark.parametrize("case", ["heavy tails", "ties", "small", "narrow coverage", "wide coverage"])
def test_the_symmetric_interval_without_sorting_is_the_sorted_one(case):
    """propagate leaves the trials unsorted until a sort is needed: the symmetric interval's two order
    statistics, picked out without sorting, are exactly those of the sorted values (JCGM 101 7.7.1)."""
    from mtbudget.stats import symmetric_interval

    model, inputs, n, p = {
        "heavy tails": (lambda x: x, {"x": StudentT(0.0, 1.0, 2.5)}, 300_000, 0.95),
        "ties": (lambda x: np.round(x), {"x": Normal(0.0, 2.0)}, 200_000, 0.95),  # few distinct values, many ties
        "small": (lambda x, y: x * y, {"x": Normal(1.0, 0.1), "y": Rectangular(1.0, 2.0)}, 5_001, 0.95),
        "narrow coverage": (lambda x, y: x + y, {"x": Normal(0.0, 1.0), "y": Arcsine(-3.0, 3.0)}, 200_001, 0.1),
        "wide coverage": (lambda x: np.exp(x), {"x": Normal(0.0, 1.0)}, 100_000, 0.999),
    }[case]
    res = propagate(model, inputs, coverage=p, trials=n, seed=13)
    assert not res.is_sorted
    values = res.values.copy()
    lo, hi = res.interval("symmetric")
    assert not res.is_sorted  # the interval did not sort
    assert (lo.magnitude, hi.magnitude) == symmetric_interval(np.sort(values), p)
    # the estimate and the standard uncertainty as numpy computes them
    assert res.estimate.magnitude == pytest.approx(values.mean(), rel=1e-14, abs=1e-300)
    assert res.std_uncertainty.magnitude == pytest.approx(values.std(ddof=1), rel=1e-12)
    # samples: the same values, sorted (in place, once)
    assert np.array_equal(res.samples, np.sort(values)) and res.is_sorted
    assert res.interval("symmetric") == (lo, hi)


def test_the_model_s_array_is_not_the_result_s():
    """A model that returns an array it keeps: the Result holds its own copy, and sorting it leaves the model's."""
    kept = {}

    def model(x):
        kept["y"] = 2 * x
        return kept["y"]

    res = propagate(model, {"x": Normal(0.0, 1.0)}, trials=300_000, seed=14)
    before = kept["y"].magnitude.copy()
    res.samples  # noqa: B018 - sorts
    assert np.array_equal(kept["y"].magnitude, before)
    assert not np.shares_memory(res.values, kept["y"].magnitude)


def test_one_thread_or_two_the_same_numbers(monkeypatch):
    from mtbudget import mcm

    inputs = {"a": Normal(1.0, 0.1), "b": StudentT(0.0, 1.0, 5), "c": Arcsine(-1.0, 1.0)}
    ys = []
    for threads in (1, 2):
        monkeypatch.setattr(mcm, "DRAW_THREADS", threads)
        ys.append(propagate(lambda a, b, c: a * b + c, inputs, trials=250_000, seed=15).values)
    assert np.array_equal(ys[0], ys[1])


def test_the_order_statistics_are_exact_whatever_the_order_of_the_values():
    """The interval's order statistics come from a strided sample's bound, checked by counting: values in an
    adversarial order (the strided places hold the extremes, so the bound falls short) still give exactly the
    sorted values' interval."""
    from mtbudget.mcm import Result
    from mtbudget.stats import symmetric_interval

    n = 100_003
    rng = np.random.default_rng(16)
    for extremes in (-1e6, 1e6):
        y = rng.standard_normal(n)
        y[:: n // 8192] = extremes + rng.standard_normal(y[:: n // 8192].size)
        for p in (0.95, 0.5):
            res = Result(y.copy(), ureg.m, p, None, [])
            lo, hi = res.interval("symmetric")
            assert not res.is_sorted
            assert (lo.magnitude, hi.magnitude) == symmetric_interval(np.sort(y), p)


def test_the_estimate_and_u_do_not_depend_on_what_is_asked_first():
    """The mean and u are summed in trial order, before any sort: the same bits whichever is asked first."""
    inputs = {"x": Normal(0.0, 1.0), "y": Arcsine(-1.0, 1.0)}
    first = propagate(lambda x, y: x * y + x, inputs, trials=300_000, seed=5)
    u1 = first.std_uncertainty
    second = propagate(lambda x, y: x * y + x, inputs, trials=300_000, seed=5)
    second.interval("shortest")  # sorts
    assert second.std_uncertainty == u1 and second.estimate == first.estimate


def test_an_input_beyond_double_precision_is_one_error_naming_it():
    """u = 1e300 um: the law of propagation overflows; the error names the input (a new user got an OverflowError from
    inside the uncertainties package)."""
    from mtbudget.mcm import ModelError

    with pytest.raises(ModelError, match="'a'.*beyond double precision"):
        propagate(lambda a, b: a + b, {"a": Normal(1 * ureg.um, 1e300 * ureg.um), "b": Normal(0 * ureg.um, 1 * ureg.um)},
                  trials=1000)
    with pytest.raises(ModelError, match="non-finite u"):
        propagate(lambda a: a * a / (1 * ureg.um), {"a": Normal(1 * ureg.um, 1e200 * ureg.um)}, trials=1000)


def test_a_result_says_what_it_is_in_one_line():
    """repr: the estimate, u with k = 1, the coverage and the unit, to u's second significant digit; never the
    200 000 trial values (a new user printed a result and got the array)."""
    import re

    res = propagate(lambda a: a, {"a": Normal(1234.0 * ureg.um, 30.0 * ureg.um)}, trials=200_000, seed=3)
    text = repr(res)
    assert len(text) < 300 and "\n" not in text
    m = re.search(r"y = ([0-9.]+) µm, u\(y\) = ([0-9.]+) µm \(standard uncertainty, k = 1\), 95 % probabilistically "
                  r"symmetric coverage interval \[([0-9.]+), ([0-9.]+)\] µm; M = 200000 trials", text)
    assert m, text
    y, u, lo, hi = map(float, m.groups())
    assert (y, u) == (1234.0, 30.0)  # N(1234, 30): to u's second digit
    assert abs(lo - (1234 - 1.96 * 30)) <= 1 and abs(hi - (1234 + 1.96 * 30)) <= 1
