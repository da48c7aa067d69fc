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
its own, spawned from the seed), scaled and shifted in place.  Normal: ``standard_normal``; Rectangular,
Arcsine (``sin(2 pi U)``) and CurvilinearTrapezoid (JCGM 101 6.4.3.4): ``random``; StudentT: Bailey's polar
method from ``uniform(-1, 1)`` pairs (:func:`_student_t`); Triangular, Exponential, Gamma, Beta: numpy's own.
The same seed gives the same draws.
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
        z = rng.standard_normal(n)  # scaled and shifted in place: the same numbers as mu + sigma * z, one array
        z *= self.sigma
        z += self.mu
        return z

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
        x = rng.random(n)
        x *= 2 * np.pi
        np.sin(x, out=x)
        x *= (self.b - self.a) / 2
        x += (self.a + self.b) / 2
        return x

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
        # JCGM 101 6.4.3.4: half-width w drawn from R(w - d, w + d), then X from R(mid - w', mid + w')
        r1, r2 = rng.random(n), rng.random(n)
        half = (self.b - self.a) / 2
        r2 *= 2 * self.d  # w = half - d + 2 d r2, in place
        r2 += half - self.d
        r1 *= 2  # X = mid + w (2 r1 - 1)
        r1 -= 1
        r1 *= r2
        r1 += (self.a + self.b) / 2
        return r1

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
        self.mu, self.s, self.nu, self.units, self.dof = float(m.magnitude), float(s.magnitude), float(dof), m.units, float(dof)

    mean = property(lambda s: Q_(s.mu, s.units))
    std = property(lambda s: Q_(s.s * math.sqrt(s.nu / (s.nu - 2)), s.units))
    gum_std = property(lambda s: Q_(s.s, s.units))

    def _draw(self, n, rng):
        return _shift(_student_t(self.nu, n, rng), self.s, self.mu)  # Bailey's polar method, see _student_t

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


def _shift(x: np.ndarray, scale: float, loc: float) -> np.ndarray:
    """loc + scale * x, in place."""
    x *= scale
    x += loc
    return x


def _student_t(nu: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """n draws of Student's t with nu degrees of freedom: Bailey's polar method (Math. Comp. 62 (1994) 779-781).

    (U, V) uniform on the square (-1, 1)^2, kept when W = U^2 + V^2 lies in (0, 1] (probability pi/4); then
    T = U sqrt(nu (W^(-2/nu) - 1) / W) has exactly the t distribution.  Only uniforms and one power per draw:
    ~1.3-1.7x faster than Z / sqrt(2 Gamma(nu/2) / nu) (a normal and a gamma draw each) on the project's
    machine.  The stream: pairs are drawn in rounds of int(1.28 m) + 64 (all U then all V, from
    ``rng.uniform(-1, 1)``) for the m values still missing, and the accepted values are taken in order: the
    same seed gives the same draws.
    """
    out = np.empty(n)
    k = 0
    while k < n:
        m = int((n - k) * 1.28) + 64
        uv = rng.uniform(-1.0, 1.0, 2 * m)  # -1 + 2 * rng.random(): the same numbers, in one pass
        u, v = uv[:m], uv[m:]
        w = u * u
        w += v * v
        ok = w <= 1.0
        ok &= w > 0.0
        with np.errstate(invalid="ignore", divide="ignore"):  # the rejected pairs, computed and dropped
            c = np.power(w, -2.0 / nu)
            c -= 1.0
            c *= nu
            c /= w
            np.sqrt(c, out=c)
        c *= u
        c = c[ok]  # one selection, at the end: cheaper than selecting u and w first
        take = min(n - k, c.size)
        out[k:k + take] = c[:take]
        k += take
    return out


def t_factor(coverage: float, dof: float) -> float:
    """Coverage factor k from the t distribution (normal for infinite dof)."""
    if math.isinf(dof):
        from scipy import stats

        return float(stats.norm.ppf(0.5 + coverage / 2))
    from scipy import stats

    return float(stats.t.ppf(0.5 + coverage / 2, dof))
