"""The samplers of mtbudget.distributions against their exact laws: Kolmogorov-Smirnov, tails and moments.

10^6 draws at a fixed seed each.  Kolmogorov-Smirnov against the exact CDF (scipy's, or the closed form of the
curvilinear trapezoid) sees a deviation of the CDF of about 0.002 anywhere; the counts beyond the exact 0.1 % and
99.9 % quantiles see the tails, which the KS distance hardly weighs (binomial, 5 standard deviations); the mean
and variance are checked within 5 standard errors of their exact values.  Odd sample sizes go through the
samplers' rounds (the disc samplers draw up to 32768 pairs a round and keep those inside the disc).
"""

import math

import numpy as np
import pytest
from scipy import stats

from mtbudget.distributions import Arcsine, CurvilinearTrapezoid, Normal, Rectangular, StudentT

N = 1_000_000


def ct_cdf(a, b, d):
    """CDF of the curvilinear trapezoid (JCGM 101 6.4.3): X = mid + W (2 R - 1), W rectangular on [w - d, w + d].

    P(X - mid <= z) for z >= 0 is the mean over W of min(1, 1/2 + z / (2 W)):
    (1 / 2d) [(w1 - w0)/2 + (z/2) ln(w1/w0)] for z <= w0, (1 / 2d) [(z - w0) + (w1 - z)/2 + (z/2) ln(w1/z)] for
    w0 < z < w1, 1 beyond; symmetric about mid.
    """
    mid, w0, w1 = (a + b) / 2, (b - a) / 2 - d, (b - a) / 2 + d

    def cdf(x):
        z = np.abs(np.asarray(x, float) - mid)
        inner = ((w1 - w0) / 2 + z / 2 * np.log(w1 / w0)) / (2 * d)
        zc = np.clip(z, w0, w1)
        edge = ((zc - w0) + (w1 - zc) / 2 + zc / 2 * np.log(w1 / zc)) / (2 * d)
        f = np.where(z <= w0, inner, np.where(z < w1, edge, 1.0))
        return np.where(np.asarray(x, float) >= mid, f, 1 - f)

    return cdf


def ct_moments(a, b, d):
    return (a + b) / 2, (b - a) ** 2 / 12 + d**2 / 9  # JCGM 101 6.4.3.3


CASES = [  # (distribution, exact CDF, exact mean, exact variance, seed)
    (Normal(3.0, 2.0), stats.norm(3.0, 2.0).cdf, 3.0, 4.0, 1),
    (Normal(-1e-3, 5e-3), stats.norm(-1e-3, 5e-3).cdf, -1e-3, 25e-6, 2),
    (Arcsine(-0.5, 0.5), stats.arcsine(loc=-0.5, scale=1.0).cdf, 0.0, 0.125, 3),
    (Arcsine(2.0, 10.0), stats.arcsine(loc=2.0, scale=8.0).cdf, 6.0, 8.0, 4),
    (StudentT(0.0, 1.0, 2.5), stats.t(2.5).cdf, 0.0, 5.0, 5),  # infinite fourth moment: the variance is not checked
    (StudentT(0.0, 1.0, 3), stats.t(3).cdf, 0.0, 3.0, 6),
    (StudentT(215.0, 5.8, 24), stats.t(24, loc=215.0, scale=5.8).cdf, 215.0, 5.8**2 * 24 / 22, 7),
    (StudentT(50_000_623.6, 25.0, 18), stats.t(18, loc=50_000_623.6, scale=25.0).cdf, 50_000_623.6, 625 * 18 / 16, 8),
    (StudentT(0.0, 1.0, 5), stats.t(5).cdf, 0.0, 5 / 3, 9),
    (StudentT(0.0, 1.0, 1e4), stats.t(1e4).cdf, 0.0, 1e4 / (1e4 - 2), 10),  # large dof: W^(-2/nu) - 1 by expm1
    (CurvilinearTrapezoid(-1e-6, 1e-6, 0.1e-6), ct_cdf(-1e-6, 1e-6, 0.1e-6), *ct_moments(-1e-6, 1e-6, 0.1e-6), 11),
    (CurvilinearTrapezoid(-0.05, 0.05, 0.025), ct_cdf(-0.05, 0.05, 0.025), *ct_moments(-0.05, 0.05, 0.025), 12),
    (Rectangular(9.5e-6, 13.5e-6), stats.uniform(9.5e-6, 4e-6).cdf, 11.5e-6, 16e-12 / 12, 13),
]


def _quantile(cdf, p, lo, hi):
    """The p-quantile of a continuous CDF by bisection (for the closed-form CDFs without a ppf)."""
    for _ in range(200):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
    return (lo + hi) / 2


@pytest.mark.parametrize("dist, cdf, mean, var, seed", CASES, ids=lambda x: x.describe() if hasattr(x, "describe") else "")
def test_draws_have_the_exact_law(dist, cdf, mean, var, seed):
    x = dist.sample(N, np.random.default_rng(seed)).magnitude
    assert x.shape == (N,) and np.isfinite(x).all()
    assert stats.kstest(x, cdf).pvalue > 1e-3
    # the tails: counts beyond the exact 0.1 % and 99.9 % quantiles, binomial within 5 standard deviations
    s = math.sqrt(var)
    for p in (0.001, 0.999):
        q = _quantile(cdf, p, mean - 1e3 * s, mean + 1e3 * s)
        below = np.count_nonzero(x <= q)
        assert abs(below - p * N) <= 5 * math.sqrt(N * p * (1 - p)), (p, below)
    # the mean within 5 standard errors; the variance within 5 standard errors where the fourth moment exists
    assert abs(x.mean() - mean) <= 5 * s / math.sqrt(N)
    if not (isinstance(dist, StudentT) and dist.nu <= 4):
        m4 = np.mean((x - mean) ** 4)
        assert abs(x.var(ddof=1) - var) <= 5 * math.sqrt((m4 - var**2) / N)


@pytest.mark.parametrize("n", [1, 2, 3, 64, 65, 1000, 32768, 41_000, 100_001])
@pytest.mark.parametrize("dist", [Normal(0.0, 1.0), Arcsine(-1.0, 1.0), StudentT(0.0, 1.0, 5),
                                  CurvilinearTrapezoid(-1.0, 1.0, 0.25)], ids=lambda d: type(d).__name__)
def test_any_size_one_seed_one_stream(dist, n):
    """Every size works through the rounds, and one seed gives one set of draws (the documented stream)."""
    x = dist.sample(n, np.random.default_rng(21)).magnitude
    assert x.shape == (n,) and np.isfinite(x).all()
    assert np.array_equal(x, dist.sample(n, np.random.default_rng(21)).magnitude)
    if isinstance(dist, (Arcsine, CurvilinearTrapezoid)):
        lim = 1.0 if isinstance(dist, Arcsine) else 1.25
        assert np.abs(x).max() <= lim


def test_small_draws_pooled_have_the_law():
    """Many small draws (a single short round each, the last values of a round kept) pooled: still exact."""
    rng = np.random.default_rng(22)
    for dist, cdf in ((Normal(0.0, 1.0), stats.norm.cdf), (StudentT(0.0, 1.0, 4), stats.t(4).cdf),
                      (Arcsine(-1.0, 1.0), stats.arcsine(loc=-1, scale=2).cdf)):
        x = np.concatenate([dist.sample(7, rng).magnitude for _ in range(20_000)])
        assert stats.kstest(x, cdf).pvalue > 1e-3


def documented_stream(kind, n, seed, nu=None):
    """The draws as the docstrings of distributions._normal, _arcsine and _student_t describe them, written out
    plainly: rounds of 2 m uniforms (m = min(32768, int(1.28 r / values per pair) + 64) for the r values still
    missing), U from the first m and V from the next m, the pairs inside the disc kept in order.  Returns the
    values and, for the normal, each round's (position, kept pairs) to find the two values of a pair."""
    rng, out, rounds, k = np.random.default_rng(seed), [], [], 0
    while k < n:
        per = 2 if kind == "normal" else 1
        m = min(32768, int(1.28 * (n - k) / per) + 64)
        r = rng.random(2 * m)
        with np.errstate(divide="ignore", invalid="ignore"):
            if kind == "normal":
                u, v = 2 * r[:m] - 1, 2 * r[m:] - 1
                w = u**2 + v**2
                keep = (w > 0) & (w < 1)
                f = np.sqrt(-2 * np.log(w) / w)
                vals = np.concatenate([(u * f)[keep], (v * f)[keep]])
                rounds.append((k, int(keep.sum())))
            elif kind == "arcsine":
                u, v = r[:m], r[m:]
                w = u**2 + v**2
                keep = (w > 0) & (w <= 1)
                vals = ((u**2 - v**2) / w)[keep]
            else:
                u, v = 2 * r[:m] - 1, r[m:]
                w = u**2 + v**2
                keep = (w > 0) & (w <= 1)
                vals = (u * np.sqrt(nu * np.expm1(-2 / nu * np.log(w)) / w))[keep]
        take = min(n - k, vals.size)
        out.append(vals[:take])
        k += take
    return np.concatenate(out), rounds


@pytest.mark.parametrize("n", [5, 40_000, 300_001])
def test_the_streams_are_the_documented_ones(n):
    """One seed, one documented stream: the samplers give the values their docstrings describe."""
    x = Normal(0.0, 1.0).sample(n, np.random.default_rng(31)).magnitude
    assert np.allclose(x, documented_stream("normal", n, 31)[0], rtol=1e-13, atol=1e-15)
    x = Arcsine(-1.0, 1.0).sample(n, np.random.default_rng(32)).magnitude
    assert np.allclose(x, documented_stream("arcsine", n, 32)[0], rtol=1e-13, atol=1e-15)
    for nu in (2.5, 18.0):
        x = StudentT(0.0, 1.0, nu).sample(n, np.random.default_rng(33)).magnitude
        assert np.allclose(x, documented_stream("t", n, 33, nu)[0], rtol=1e-12, atol=1e-15)
    # the curvilinear trapezoid: n uniforms for the position, then n for the half-width
    rng = np.random.default_rng(34)
    r1, r2 = rng.random(n), rng.random(n)
    x = CurvilinearTrapezoid(-1.0, 3.0, 0.5).sample(n, np.random.default_rng(34)).magnitude
    assert np.allclose(x, 1.0 + (2.0 - 0.5 + 2 * 0.5 * r2) * (2 * r1 - 1), rtol=1e-13, atol=1e-15)


def test_the_two_normal_values_of_a_pair_are_independent():
    """The polar method gives two values per kept pair, U's and V's: uncorrelated, and so are their squares
    (which share W: a wrong transform, e.g. one that made Z1^2 + Z2^2 fixed, would show there first)."""
    x = Normal(0.0, 1.0).sample(N, np.random.default_rng(35)).magnitude
    _, rounds = documented_stream("normal", N, 35)
    first, second = [], []
    for k, c in rounds:  # a round appends the U values of its c kept pairs, then their V values (as many as fit)
        pairs = max(0, min(N - k, 2 * c) - c)
        first.append(x[k:k + pairs])
        second.append(x[k + c:k + c + pairs])
    z1, z2 = np.concatenate(first), np.concatenate(second)
    assert z1.size > 0.45 * N and z1.size == z2.size
    for a, b in ((z1, z2), (z1**2, z2**2), (np.abs(z1), np.abs(z2))):
        assert abs(np.corrcoef(a, b)[0, 1]) < 5 / math.sqrt(z1.size)


def test_extreme_scales_neither_overflow_nor_underflow():
    """The scale multiplies the finished draw (never squared inside a root): 1e155 and 1e-170 give finite, non-zero
    values with the law's spread; a t with 1e300 degrees of freedom is the normal; infinite dof is refused."""
    from mtbudget.distributions import DistributionError

    rng = np.random.default_rng(41)
    for dist, s in ((Normal(0.0, 1e155), 1e155), (Normal(0.0, 1e-170), 1e-170), (StudentT(0.0, 1e-170, 5), 1e-170),
                    (StudentT(0.0, 1e5, 1e300), 1e5)):
        x = dist.sample(20_000, rng).magnitude / s
        assert np.isfinite(x).all() and (x != 0).all()
        assert 0.95 < x.std() / dist.std.magnitude * s < 1.05
    with pytest.raises(DistributionError, match="finite"):
        StudentT(0.0, 1.0, math.inf)
