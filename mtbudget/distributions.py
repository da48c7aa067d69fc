"""JCGM 101 probability distributions with pint units.

Each distribution draws samples (``sample(n, rng)`` -> Quantity array), knows
its expectation and standard deviation, and the degrees of freedom the GUF
uses for it (``gum_std``, ``gum_dof``).  Parameters are pint Quantities; a
plain float means dimensionless.  Bad parameters raise
:class:`~mtbudget.errors.DistributionError` naming the distribution and the
parameter.

The optional ``dof`` of the Type B distributions is for the GUF only: the
"degrees of freedom" of an uncertainty that is itself uncertain (GUM G.4.2).

Draws: every distribution draws from the numpy Generator it is given (``mcm.propagate`` gives each input
its own, spawned from the seed), from the Generator's ``random`` (53-bit uniforms on [0, 1)) except where
stated.  Rectangular: ``random``, scaled and shifted in place.  CurvilinearTrapezoid (JCGM 101 6.4.3.4): ``random``
n values for the position, then n for the half-width.  Normal (JCGM 101 6.4.7: the polar form of the
Box-Muller transform), Arcsine (cos 2 phi of a uniform point of the quarter disc) and StudentT (Bailey's
polar method): pairs of uniforms kept inside a disc, drawn in rounds of at most :data:`_ROUND` pairs so that
each round's work stays in the processor's cache (see :func:`_normal`, :func:`_arcsine`, :func:`_student_t`
for their streams); every kept value has exactly the stated distribution.  Triangular, Exponential, Gamma,
Beta, and correlated normals (``mcm.propagate``): numpy's own.  The same seed gives the same draws.
"""

from __future__ import annotations

import math
import numpy as np
import pint


from .errors import DistributionError
from .units import Q_, ureg



def _q(x, what) -> pint.Quantity:
    if isinstance(x, pint.Quantity):
        return x
    if isinstance(x, (int, float, np.floating, np.integer)):
        return Q_(float(x))
    if isinstance(x, str):
        return ureg.Quantity(x)
    raise DistributionError(f"{what}: expected a number or a pint Quantity, got {type(x).__name__}")


def _same_units(a: pint.Quantity, b: pint.Quantity, what: str) -> pint.Quantity:
    if a.dimensionality != b.dimensionality:
        raise DistributionError(f"{what}: units {a.units:~} and {b.units:~} have different dimensions")
    return b.to(a.units)


def _check_dof(dof, name):
    if dof is not None and not (dof > 0):
        raise DistributionError(f"{name}: dof must be positive, got {dof}")


class Distribution:
    """Base class: ``units``, ``mean``, ``std``, ``sample``, ``gum_std``, ``gum_dof``."""

    units: pint.Unit
    dof: float | None = None

    @property
    def mean(self) -> pint.Quantity:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def std(self) -> pint.Quantity:  # pragma: no cover - abstract
        raise NotImplementedError

    def _draw(self, n: int, rng: np.random.Generator) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def sample(self, n: int, rng: np.random.Generator) -> pint.Quantity:
        return Q_(self._draw(int(n), rng), self.units)

    def standard_normal_map(self, z: np.ndarray) -> np.ndarray:
        """Magnitudes with this distribution from standard normal z (for correlated inputs)."""
        raise DistributionError(f"{type(self).__name__}: correlation is defined for Normal inputs only (JCGM 101 6.4.8)")

    @property
    def gum_std(self) -> pint.Quantity:
        """Standard uncertainty the GUF assigns."""
        return self.std

    @property
    def gum_dof(self) -> float:
        return math.inf if self.dof is None else float(self.dof)

    def describe(self) -> str:
        return f"{type(self).__name__}"

    def __repr__(self):
        return self.describe()


class Normal(Distribution):
    """N(mean, std^2) (JCGM 101 6.4.7)."""

    def __init__(self, mean, std, dof=None):
        m, s = _q(mean, "Normal mean"), _q(std, "Normal std")
        s = _same_units(m, s, "Normal")
        if not s.magnitude >= 0:
            raise DistributionError(f"Normal: std must be >= 0, got {s}")
        _check_dof(dof, "Normal")
        self.mu, self.sigma, self.units, self.dof = float(m.magnitude), float(s.magnitude), m.units, dof

    @property
    def mean(self):
        return Q_(self.mu, self.units)

    @property
    def std(self):
        return Q_(self.sigma, self.units)

    def _draw(self, n, rng):
        return _normal(n, rng, self.sigma, self.mu)  # the polar Box-Muller transform, see _normal

    def standard_normal_map(self, z):
        return self.mu + self.sigma * z

    def describe(self):
        return f"Normal(mean={self.mean:~P}, std={self.std:~P})"


class _Bounded(Distribution):
    def _bounds(self, low, high, name):
        lo, hi = _q(low, f"{name} low"), _q(high, f"{name} high")
        hi = _same_units(lo, hi, name)
        if not lo.magnitude < hi.magnitude:
            raise DistributionError(f"{name}: low must be < high, got low={lo:~P}, high={hi:~P}")
        return float(lo.magnitude), float(hi.magnitude), lo.units


class Rectangular(_Bounded):
    """R(a, b) (JCGM 101 6.4.2)."""

    def __init__(self, low, high, dof=None):
        self.a, self.b, self.units = self._bounds(low, high, "Rectangular")
        _check_dof(dof, "Rectangular")
        self.dof = dof

    mean = property(lambda s: Q_((s.a + s.b) / 2, s.units))
    std = property(lambda s: Q_((s.b - s.a) / math.sqrt(12), s.units))

    def _draw(self, n, rng):
        x = rng.random(n)  # scaled and shifted in place (no temporaries of n values)
        x *= self.b - self.a
        x += self.a
        return x

    def describe(self):
        return f"Rectangular({Q_(self.a, self.units):~P}, {Q_(self.b, self.units):~P})"


class Triangular(_Bounded):
    """Triangular on [a, b] with mode (symmetric by default) (JCGM 101 6.4.5)."""

    def __init__(self, low, high, mode=None, dof=None):
        self.a, self.b, self.units = self._bounds(low, high, "Triangular")
        c = (self.a + self.b) / 2 if mode is None else float(_same_units(Q_(1.0, self.units), _q(mode, "Triangular mode"), "Triangular").magnitude)
        if not self.a <= c <= self.b:
            raise DistributionError("Triangular: mode must lie within [low, high]")
        self.c = c
        _check_dof(dof, "Triangular")
        self.dof = dof

    mean = property(lambda s: Q_((s.a + s.b + s.c) / 3, s.units))
    std = property(lambda s: Q_(math.sqrt((s.a**2 + s.b**2 + s.c**2 - s.a * s.b - s.a * s.c - s.b * s.c) / 18), s.units))

    def _draw(self, n, rng):
        return rng.triangular(self.a, self.c, self.b, n)

    def describe(self):
        return f"Triangular({Q_(self.a, self.units):~P}, {Q_(self.b, self.units):~P})"


class Arcsine(_Bounded):
    """U-shaped (arcsine) on [a, b] (JCGM 101 6.4.6)."""

    def __init__(self, low, high, dof=None):
        self.a, self.b, self.units = self._bounds(low, high, "Arcsine")
        _check_dof(dof, "Arcsine")
        self.dof = dof

    mean = property(lambda s: Q_((s.a + s.b) / 2, s.units))
    std = property(lambda s: Q_((s.b - s.a) / (2 * math.sqrt(2)), s.units))

    def _draw(self, n, rng):
        return _arcsine(n, rng, (self.b - self.a) / 2, (self.a + self.b) / 2)  # see _arcsine

    def describe(self):
        return f"Arcsine({Q_(self.a, self.units):~P}, {Q_(self.b, self.units):~P})"


class CurvilinearTrapezoid(_Bounded):
    """Rectangular with inexactly known limits a +- d, b +- d (JCGM 101 6.4.3).

    The GUF sees it one of two ways.  Without ``dof``, as its full standard
    deviation (the inexact limits widen it).  With ``dof`` (GUM G.4.2: the
    uncertainty of the limits expressed as degrees of freedom, as GUM H.1
    does), as the plain rectangular standard deviation with those degrees of
    freedom: the inexactness is then carried by ``dof`` and not counted twice.
    """

    def __init__(self, low, high, d, dof=None):
        self.a, self.b, self.units = self._bounds(low, high, "CurvilinearTrapezoid")
        dd = _same_units(Q_(1.0, self.units), _q(d, "CurvilinearTrapezoid d"), "CurvilinearTrapezoid")
        self.d = float(dd.magnitude)
        if not 0 <= self.d <= (self.b - self.a) / 2:
            raise DistributionError("CurvilinearTrapezoid: d must lie in [0, (high - low)/2]")
        _check_dof(dof, "CurvilinearTrapezoid")
        self.dof = dof

    mean = property(lambda s: Q_((s.a + s.b) / 2, s.units))
    std = property(lambda s: Q_(math.sqrt((s.b - s.a) ** 2 / 12 + s.d**2 / 9), s.units))

    @property
    def gum_std(self):
        return self.std if self.dof is None else Q_((self.b - self.a) / math.sqrt(12), self.units)

    def _draw(self, n, rng):
        # JCGM 101 6.4.3.4: half-width w' drawn from R(w - d, w + d), then X from R(mid - w', mid + w').  The
        # stream: n uniforms r1 (into the result), then n uniforms r2 (a round of at most _ROUND at a time:
        # the same numbers as one call), X = mid + (half - d + 2 d r2) (2 r1 - 1), computed round by round
        x = np.empty(n)
        rng.random(out=x)
        half, mid = (self.b - self.a) / 2, (self.a + self.b) / 2
        buf = np.empty(min(n, _ROUND))
        for s in range(0, n, buf.size):
            r2 = buf[:min(buf.size, n - s)]
            rng.random(out=r2)
            r2 *= 2 * self.d  # w' = half - d + 2 d r2, in place
            r2 += half - self.d
            r1 = x[s:s + r2.size]
            r1 *= 2  # X = mid + w' (2 r1 - 1)
            r1 -= 1
            r1 *= r2
            r1 += mid
        return x

    def describe(self):
        return f"CurvilinearTrapezoid({Q_(self.a, self.units):~P}, {Q_(self.b, self.units):~P}, d={Q_(self.d, self.units):~P})"


class StudentT(Distribution):
    """Scaled and shifted t: mean + scale * t_dof (JCGM 101 6.4.9).

    GUF convention (GUM Type A): standard uncertainty = scale, degrees of
    freedom = dof.  MCM samples the t distribution itself (its standard
    deviation is ``scale * sqrt(dof / (dof - 2))``, defined for dof > 2).
    """

    def __init__(self, mean, scale, dof):
        m, s = _q(mean, "StudentT mean"), _q(scale, "StudentT scale")
        s = _same_units(m, s, "StudentT")
        if not s.magnitude >= 0:
            raise DistributionError(f"StudentT: scale must be >= 0, got {s}")
        if not dof > 2:
            raise DistributionError(f"StudentT: dof must be > 2 for the variance MCM needs to exist, got {dof}")
        if not math.isfinite(dof):
            raise DistributionError("StudentT: dof must be finite (infinitely many degrees of freedom: use Normal)")
        self.mu, self.s, self.nu, self.units, self.dof = float(m.magnitude), float(s.magnitude), float(dof), m.units, float(dof)

    mean = property(lambda s: Q_(s.mu, s.units))
    std = property(lambda s: Q_(s.s * math.sqrt(s.nu / (s.nu - 2)), s.units))
    gum_std = property(lambda s: Q_(s.s, s.units))

    def _draw(self, n, rng):
        return _student_t(self.nu, n, rng, self.s, self.mu)  # Bailey's polar method, see _student_t

    def describe(self):
        return f"StudentT(mean={self.mean:~P}, scale={Q_(self.s, self.units):~P}, dof={self.nu:g})"


class Exponential(Distribution):
    """Exponential with the given mean (JCGM 101 6.4.10)."""

    def __init__(self, mean, dof=None):
        m = _q(mean, "Exponential mean")
        if not m.magnitude > 0:
            raise DistributionError(f"Exponential: mean must be > 0, got {m}")
        _check_dof(dof, "Exponential")
        self.mu, self.units, self.dof = float(m.magnitude), m.units, dof

    mean = property(lambda s: Q_(s.mu, s.units))
    std = property(lambda s: Q_(s.mu, s.units))

    def _draw(self, n, rng):
        return rng.exponential(self.mu, n)

    def describe(self):
        return f"Exponential(mean={self.mean:~P})"


class Gamma(Distribution):
    """Gamma with the given mean and standard deviation (JCGM 101 6.4.11)."""

    def __init__(self, mean, std, dof=None):
        m, s = _q(mean, "Gamma mean"), _q(std, "Gamma std")
        s = _same_units(m, s, "Gamma")
        if not (m.magnitude > 0 and s.magnitude > 0):
            raise DistributionError(f"Gamma: mean and std must be > 0, got {m}, {s}")
        _check_dof(dof, "Gamma")
        self.mu, self.sigma, self.units, self.dof = float(m.magnitude), float(s.magnitude), m.units, dof

    mean = property(lambda s: Q_(s.mu, s.units))
    std = property(lambda s: Q_(s.sigma, s.units))

    def _draw(self, n, rng):
        shape = (self.mu / self.sigma) ** 2
        return rng.gamma(shape, self.sigma**2 / self.mu, n)

    def describe(self):
        return f"Gamma(mean={self.mean:~P}, std={self.std:~P})"


class Beta(_Bounded):
    """Symmetric or general beta on [low, high] with shape parameters (the paper's Eq. 18-20 option)."""

    def __init__(self, low, high, alpha=2.0, beta=None, dof=None):
        self.a, self.b, self.units = self._bounds(low, high, "Beta")
        self.p = float(alpha)
        self.q = float(alpha if beta is None else beta)
        if not (self.p > 0 and self.q > 0):
            raise DistributionError("Beta: shape parameters must be > 0")
        _check_dof(dof, "Beta")
        self.dof = dof

    mean = property(lambda s: Q_(s.a + (s.b - s.a) * s.p / (s.p + s.q), s.units))
    std = property(lambda s: Q_((s.b - s.a) * math.sqrt(s.p * s.q / ((s.p + s.q) ** 2 * (s.p + s.q + 1))), s.units))

    def _draw(self, n, rng):
        return self.a + (self.b - self.a) * rng.beta(self.p, self.q, n)


#: pairs of uniforms per round of the disc samplers (_normal, _arcsine, _student_t): the round's work arrays
#: (about 0.8 MB) stay in the core's cache, where numpy's element-wise operations run several times faster
#: than on arrays of 10^6 values; measured best among 8192-65536 on the project's machine
_ROUND = 32768


def _rounds(n: int, per_pair: float):
    """The disc samplers' rounds: (the output, the round's uniforms, three work arrays); per_pair = values per
    kept pair (1 or 2).  A round draws 2 m uniforms for the r values still missing, m = min(_ROUND,
    int(1.28 r / per_pair) + 64): 1.28 > 4 / pi, so that one round usually suffices below _ROUND."""
    size = min(_ROUND, int(1.28 * n / per_pair) + 64)
    return np.empty(n), np.empty(2 * size), np.empty(size), np.empty(size, bool), np.empty(size, bool)


def _round_size(missing: int, per_pair: float) -> int:
    return min(_ROUND, int(1.28 * missing / per_pair) + 64)


def _keep(x: np.ndarray, kept: np.ndarray, out: np.ndarray, k: int) -> int:
    """Append x[kept] (in order, as many as out still has room for) to out[k:]; return the new count.

    ``flatnonzero`` then ``take``: branch-free, about twice as fast as ``x[kept]`` for a mask of random
    values (a boolean index copies runs and mispredicts at every change)."""
    idx = np.flatnonzero(kept)
    take = min(out.shape[0] - k, idx.size)
    np.take(x, idx[:take], out=out[k:k + take], mode="clip")  # indices are in range: "clip" is not buffered
    return k + take


def _in_disc(w: np.ndarray, kept: np.ndarray, pos: np.ndarray, closed: bool) -> np.ndarray:
    """kept = 0 < w <= 1 (closed) or 0 < w < 1, in place."""
    (np.less_equal if closed else np.less)(w, 1.0, out=kept)
    np.greater(w, 0.0, out=pos)
    kept &= pos
    return kept


def _normal(n: int, rng: np.random.Generator, sigma: float = 1.0, mu: float = 0.0) -> np.ndarray:
    """n draws of N(mu, sigma^2): the polar form of the Box-Muller transform (Marsaglia and Bray 1964).

    (U, V) uniform on the square [-1, 1)^2, kept when 0 < W = U^2 + V^2 < 1 (probability pi/4, the point is
    then uniform in the disc); then U sqrt(-2 ln W / W) and V sqrt(-2 ln W / W) are two independent standard
    normal values, exactly.  From uniforms, one logarithm and one square root per pair: 1.7x faster than
    ``standard_normal`` (numpy's ziggurat) on the project's machine, when run in rounds that stay in cache.
    The stream: rounds of 2 m uniforms from ``rng.random`` (m from :func:`_round_size`, at most
    :data:`_ROUND`), U = 2 r - 1 from the first m and V = 2 r - 1 from the next m; each round appends the
    values from U of its kept pairs in order, then those from V, until n are there.
    """
    out, buf, work, kept, pos = _rounds(n, 2)
    f = np.empty_like(work)
    k = 0
    while k < n:
        m = _round_size(n - k, 2)
        r = buf[:2 * m]
        rng.random(out=r)
        r *= 2.0
        r -= 1.0  # exactly: U and V on a grid of 2^-52, symmetric about 0 inside the disc
        u, v, w, ff = r[:m], r[m:], work[:m], f[:m]
        np.multiply(u, u, out=w)
        np.multiply(v, v, out=ff)
        w += ff
        keep = _in_disc(w, kept[:m], pos[:m], closed=False)
        with np.errstate(divide="ignore", invalid="ignore"):  # the rejected pairs, computed and dropped
            np.log(w, out=ff)
            ff *= -2.0
            ff /= w
            np.sqrt(ff, out=ff)  # sqrt(-2 ln W / W)
            if sigma != 1.0:  # outside the root: sigma^2 would overflow or underflow at extreme scales
                ff *= sigma
        r[:m] *= ff
        r[m:] *= ff
        if mu:
            r += mu
        k = _keep(u, keep, out, k)
        k = _keep(v, keep, out, k)
    return out


def _arcsine(n: int, rng: np.random.Generator, half: float = 1.0, mid: float = 0.0) -> np.ndarray:
    """n draws of the arcsine (U-shaped) distribution on [mid - half, mid + half] (JCGM 101 6.4.6).

    (U, V) uniform on the square [0, 1)^2, kept when 0 < W = U^2 + V^2 <= 1 (probability pi/4: the point is
    then uniform in the quarter disc, its angle phi uniform on [0, pi/2]); then (U^2 - V^2) / W = cos 2 phi,
    with 2 phi uniform on [0, pi], has exactly the arcsine distribution on [-1, 1] (as sin(2 pi R) has, which
    needs a sine: 2.3x slower on the project's machine).  The stream: rounds of 2 m uniforms from
    ``rng.random`` (m from :func:`_round_size`, at most :data:`_ROUND`), U from the first m and V from the next
    m; the kept pairs are taken in order until n are there.
    """
    out, buf, w, kept, pos = _rounds(n, 1)
    k = 0
    while k < n:
        m = _round_size(n - k, 1)
        r = buf[:2 * m]
        rng.random(out=r)
        r *= r
        u2, v2, ww = r[:m], r[m:], w[:m]
        np.add(u2, v2, out=ww)
        keep = _in_disc(ww, kept[:m], pos[:m], closed=True)
        u2 -= v2
        with np.errstate(divide="ignore", invalid="ignore"):  # W = 0: rejected
            u2 /= ww
        u2 *= half
        if mid:
            u2 += mid
        k = _keep(u2, keep, out, k)
    return out


def _student_t(nu: float, n: int, rng: np.random.Generator, scale: float = 1.0, loc: float = 0.0) -> np.ndarray:
    """n draws of loc + scale t_nu, Student's t with nu degrees of freedom: Bailey's polar method (Math. Comp. 62
    (1994) 779-781).

    (U, V) uniform on [-1, 1) x [0, 1), kept when 0 < W = U^2 + V^2 <= 1 (probability pi/4: the point is then
    uniform in the upper half disc, W = R^2 uniform on (0, 1] and independent of the angle phi, uniform on
    [0, pi], U / sqrt(W) = cos phi); then T = U sqrt(nu (W^(-2/nu) - 1) / W) = cos phi sqrt(nu (W^(-2/nu) - 1))
    has exactly the t distribution (Bailey's theorem needs cos phi arcsine-distributed, which phi uniform on
    [0, pi] gives as [0, 2 pi] does).  W^(-2/nu) - 1 is computed as expm1(-2/nu ln W), exact also for large nu.
    Only uniforms, one logarithm, one exponential and one square root per pair: ~2x faster than numpy's
    ``standard_t`` and than Z / sqrt(2 Gamma(nu/2) / nu), when run in rounds that stay in cache.  The stream:
    rounds of 2 m uniforms from ``rng.random`` (m from :func:`_round_size`, at most :data:`_ROUND`), U = 2 r - 1
    from the first m and V = r from the next m; the kept pairs are taken in order until n are there.
    """
    out, buf, w, kept, pos = _rounds(n, 1)
    e = -2.0 / nu
    k = 0
    while k < n:
        m = _round_size(n - k, 1)
        r = buf[:2 * m]
        rng.random(out=r)
        u, v, ww = r[:m], r[m:], w[:m]
        u *= 2.0
        u -= 1.0
        v *= v
        np.multiply(u, u, out=ww)
        ww += v
        keep = _in_disc(ww, kept[:m], pos[:m], closed=True)
        with np.errstate(divide="ignore", invalid="ignore"):  # the rejected pairs, computed and dropped
            np.log(ww, out=v)
            v *= e
            np.expm1(v, out=v)
            v *= nu
            v /= ww
            np.sqrt(v, out=v)  # sqrt(nu (W^(-2/nu) - 1) / W)
            if scale != 1.0:  # outside the root: scale^2 would overflow or underflow at extreme scales
                v *= scale
        v *= u
        if loc:
            v += loc
        k = _keep(v, keep, out, k)
    return out


def t_factor(coverage: float, dof: float) -> float:
    """Coverage factor k from the t distribution (normal for infinite dof).  scipy.special's quantile functions
    (what ``scipy.stats.norm.ppf`` and ``t.ppf`` call: the same numbers) without importing scipy.stats, about 0.35 s
    of every run's CPU."""
    from scipy import special

    if math.isinf(dof):
        return float(special.ndtri(0.5 + coverage / 2))
    return float(special.stdtrit(dof, 0.5 + coverage / 2))
