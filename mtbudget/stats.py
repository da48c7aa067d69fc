"""Coverage intervals, streaming statistics and the adaptive stopping rule of JCGM 101.

Everything here works on plain float arrays (internal units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def interval_indices(M: int, p: float) -> tuple[int, int]:
    """(r, q) of JCGM 101 7.7.1, with r 0-based: the interval is [y[r], y[r + q]] of the sorted values.

    q = pM if pM is an integer, otherwise the integer part of pM + 1/2; the
    probabilistically symmetric interval takes the 1-based r = (M - q)/2 when
    that is an integer, otherwise the integer part of (M - q + 1)/2: both are
    (M - q + 1) // 2.  For M = 1000, p = 0.95: [y(25), y(975)] (1-based).
    """
    q = int(p * M + 0.5)
    q = min(max(q, 1), M - 1)
    r = (M - q + 1) // 2 - 1
    return max(r, 0), q


def symmetric_interval(sorted_y: np.ndarray, p: float) -> tuple[float, float]:
    """Probabilistically symmetric coverage interval (JCGM 101 7.7.1) from sorted samples."""
    M = sorted_y.shape[0]
    r, q = interval_indices(M, p)
    r = max(0, min(r, M - q - 1))
    return float(sorted_y[r]), float(sorted_y[r + q])


def shortest_interval(sorted_y: np.ndarray, p: float) -> tuple[float, float]:
    """Shortest coverage interval (JCGM 101 7.7.2) from sorted samples."""
    M = sorted_y.shape[0]
    _, q = interval_indices(M, p)
    widths = sorted_y[q:] - sorted_y[: M - q]
    r = int(np.argmin(widths))
    return float(sorted_y[r]), float(sorted_y[r + q])


def numerical_tolerance(u: float, ndig: int = 2) -> float:
    """delta = 1/2 10^l with u = c 10^l, c an integer of ``ndig`` digits (JCGM 101 7.9.2)."""
    if not u > 0 or not math.isfinite(u):
        return 0.0
    l = math.floor(math.log10(abs(u))) - (ndig - 1)
    return 0.5 * 10.0**l


def decimals_for(u: float, ndig: int = 2) -> int:
    """Decimals that show ``u`` to ``ndig`` significant digits (JCGM 101 7.9.2): what the run supports, no more."""
    if not u > 0 or not math.isfinite(u):
        return 3
    return max(0, (ndig - 1) - math.floor(math.log10(abs(u))))


def bound(x: float, direction: str, decimals: int) -> str:
    """``x`` shown to ``decimals`` decimals, rounded towards the safe side of a conformity statement: "up" (an upper
    bound of an error, a guard band: never shown smaller than it is) or "down" (a lower bound; an acceptance zone's
    upper limit: never shown wider than it is), as ISO 14253-1 wants a zone rounded inwards.  Decimal arithmetic on
    the shortest repr, so 15.0 stays 15.0 (a float product 15.0 * 10 may round up to 150.00000000000003)."""
    from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal

    if not math.isfinite(x):
        return f"{x}"
    q = Decimal(1).scaleb(-max(0, int(decimals)))
    d = Decimal(repr(float(x))).quantize(q, rounding=ROUND_CEILING if direction == "up" else ROUND_FLOOR)
    return f"{abs(d) if d == 0 else d:f}"  # no "-0.0"


def decimals_of(values, sig: int = 3) -> int:
    """Decimals that show the largest of ``values`` (in magnitude) to ``sig`` significant digits: one precision for
    the ends of one interval or zone."""
    m = max((abs(v) for v in values if v is not None and math.isfinite(v)), default=0.0)
    return 0 if m == 0 else max(0, sig - 1 - math.floor(math.log10(m)))


def percent(p: float) -> str:
    """A coverage probability as people read it, never rounded into another one: 0.95 -> "95 %", 0.999 -> "99.9 %"."""
    return f"{100 * p:.6g} %"


def clause8(guf_interval, mcm_interval, u: float, ndig: int = 2):
    """JCGM 101 8.2: (d_low, d_high, delta, passed) for a GUF and an MCM coverage interval.

    delta is the numerical tolerance of the GUF standard uncertainty ``u``.
    """
    d_low = abs(guf_interval[0] - mcm_interval[0])
    d_high = abs(guf_interval[1] - mcm_interval[1])
    delta = numerical_tolerance(u, ndig)
    return d_low, d_high, delta, bool(d_low <= delta and d_high <= delta)


@dataclass
class Moments:
    """Mergeable count / mean / M2 (Chan et al.), for streaming runs of any length."""

    n: int = 0
    mean: np.ndarray | float = 0.0
    m2: np.ndarray | float = 0.0
    minimum: np.ndarray | float = math.inf
    maximum: np.ndarray | float = -math.inf

    @classmethod
    def of(cls, x: np.ndarray) -> "Moments":
        """The moments of the rows of x (n, ...) per column.  A (n, K) block with n >= 1 in one compiled pass
        (:func:`mtbudget.kernels_stats.moments`: the same bits as :meth:`of_reference`, the numpy formulation)."""
        x = np.asarray(x, float)
        if x.ndim != 2 or not x.shape[0] or x.shape[1] < 2 or not x.flags.c_contiguous:
            # numpy sums a single column, or the columns of a column-major array, pairwise: the reference's bits
            return cls.of_reference(x)
        from .kernels_stats import moments

        return cls._by_kernel(moments, x, x.shape[1], x.shape[0])

    @classmethod
    def _by_kernel(cls, kernel, x: np.ndarray, K: int, n: int) -> "Moments":
        """The K series' moments over n values each, computed by a compiled ``kernel(x, mean, m2, min, max)``."""
        mean, m2, lo, hi = np.empty(K), np.empty(K), np.empty(K), np.empty(K)
        kernel(x, mean, m2, lo, hi)
        return cls(n, mean, m2, lo, hi)

    @classmethod
    def of_reference(cls, x: np.ndarray) -> "Moments":
        x = np.asarray(x, float)
        n = x.shape[0]
        mean = x.mean(axis=0)
        return cls(n, mean, ((x - mean) ** 2).sum(axis=0), x.min(axis=0), x.max(axis=0))

    @classmethod
    def of_rows(cls, rows: np.ndarray) -> "Moments":
        """The moments of K series at once, from a (K, n) array, one series per row: row k's mean, M2, min and max
        are bit-identical to ``Moments.of(rows[k][:, None])`` (each row is summed as one contiguous series, as a
        column of one series is; ``tests/test_stats_fast.py`` checks it), with one numpy call instead of K."""
        rows = np.asarray(rows, float)
        from .kernels_stats import BUFFER, LIKE_NUMPY, moments_rows  # one compiled pass, numpy's pairwise sums

        if (rows.ndim != 2 or not rows.shape[1] or rows.strides[1] != rows.itemsize
                or (not LIKE_NUMPY and rows.shape[1] > BUFFER)):  # numpy < 2.3 buffered long sums: its own bits
            return cls.of_rows_reference(rows)
        return cls._by_kernel(moments_rows, rows, rows.shape[0], rows.shape[1])

    @classmethod
    def of_rows_reference(cls, rows: np.ndarray) -> "Moments":
        """:meth:`of_rows` in numpy (its reference)."""
        rows = np.asarray(rows, float)
        mean = rows.mean(axis=1)
        return cls(rows.shape[1], mean, ((rows - mean[:, None]) ** 2).sum(axis=1), rows.min(axis=1), rows.max(axis=1))

    def row(self, k: int) -> "Moments":
        """Series k of moments built by :meth:`of_rows` (and merged), as ``Moments.of`` of that series alone holds it."""
        return Moments(self.n, self.mean[k:k + 1], self.m2[k:k + 1], self.minimum[k:k + 1], self.maximum[k:k + 1])

    def merge(self, other: "Moments") -> "Moments":
        """Chan et al.'s update; for (K,) float64 moments in one compiled pass (the same bits as :meth:`merge_reference`,
        the numpy formulation)."""
        if self.n == 0:
            return other
        if other.n == 0:
            return self
        parts = (self.mean, self.m2, self.minimum, self.maximum, other.mean, other.m2, other.minimum, other.maximum)
        K = np.shape(self.mean)
        if not all(type(a) is np.ndarray and a.dtype == np.float64 and a.ndim == 1 and a.shape == K for a in parts):
            return self.merge_reference(other)
        from .kernels_stats import merge_moments

        n = self.n + other.n
        mean, m2, lo, hi = np.empty(K), np.empty(K), np.empty(K), np.empty(K)
        merge_moments(*parts, other.n / n, self.n * other.n / n, mean, m2, lo, hi)
        return Moments(n, mean, m2, lo, hi)

    def merge_reference(self, other: "Moments") -> "Moments":
        if self.n == 0:
            return other
        if other.n == 0:
            return self
        n = self.n + other.n
        d = other.mean - self.mean
        mean = self.mean + d * (other.n / n)
        m2 = self.m2 + other.m2 + d * d * (self.n * other.n / n)
        return Moments(n, mean, m2, np.minimum(self.minimum, other.minimum), np.maximum(self.maximum, other.maximum))

    @property
    def var(self):
        return self.m2 / (self.n - 1) if self.n > 1 else np.nan * np.asarray(self.m2)

    @property
    def std(self):
        return np.sqrt(self.var)

    def to_dict(self) -> dict:
        return {"n": self.n, "mean": np.asarray(self.mean).tolist(), "m2": np.asarray(self.m2).tolist(),
                "min": np.asarray(self.minimum).tolist(), "max": np.asarray(self.maximum).tolist()}

    @classmethod
    def from_dict(cls, d) -> "Moments":
        return cls(int(d["n"]), np.asarray(d["mean"], float), np.asarray(d["m2"], float),
                   np.asarray(d["min"], float), np.asarray(d["max"], float))


#: how a histogram's shortest interval is found (VectorHistogram.shortest), said beside it
HISTOGRAM_SHORTEST = ("the narrowest interval holding the coverage probability under the piecewise-linear CDF of a "
                      "{bins}-bin histogram (JCGM 101 7.7.2 applied to it; its length within about a bin of the "
                      "trials' own shortest interval, its ends less determined where the distribution is nearly "
                      "symmetric, as the trials' own are)")

#: counts held by one VectorHistogram at most (64 MB): 4000 bins per component up to 2000 components, fewer beyond
#: (550 bins for the 14 553 components of a 4851-point mesh), never fewer than HIST_MIN_BINS
HIST_COUNTS = 8_000_000
HIST_BINS, HIST_MIN_BINS = 4000, 500


class VectorHistogram:
    """Histograms of K components with ranges fixed from the first block (overflow counted).  bins: per component,
    by default 4000, fewer for many components (HIST_COUNTS: memory bounded whatever the mesh)."""

    _width = None  # (low, high, high - low) of the last add (a histogram restored from a log has none yet)

    def __init__(self, first: np.ndarray, bins: int | None = None):
        if bins is None:
            bins = int(min(HIST_BINS, max(HIST_MIN_BINS, HIST_COUNTS // max(first.shape[1], 1))))
        lo, hi = first.min(axis=0), first.max(axis=0)
        c, w = (lo + hi) / 2, np.maximum(hi - lo, np.maximum(np.abs(lo + hi) * 1e-9, 1e-12))
        self.low, self.high, self.bins = c - 2 * w, c + 2 * w, bins
        self.counts = np.zeros((first.shape[1], bins), np.int64)
        self.under = np.zeros(first.shape[1], np.int64)
        self.over = np.zeros(first.shape[1], np.int64)

    def add(self, x: np.ndarray):
        """Count the rows of x (n, K) (compiled: :func:`mtbudget.kernels_stats.histogram_add`, row by row;
        :meth:`add_reference` the numpy formulation it is tested against)."""
        from .kernels_stats import histogram_add

        if self._width is None or self._width[0] is not self.low or self._width[1] is not self.high:
            # high - low per component, formed once per range (the kernel divides by it, as the reference does)
            self._width = (self.low, self.high, np.ascontiguousarray(np.asarray(self.high, np.float64)
                                                                     - np.asarray(self.low, np.float64)))
        histogram_add(np.require(x, np.float64, ["C", "W"]), np.require(self.low, np.float64, ["C", "W"]),
                      self._width[2], int(self.bins), self.counts, self.under, self.over)

    def add_reference(self, x: np.ndarray):
        f = (x - self.low) / (self.high - self.low)
        self.under += (f < 0).sum(axis=0)
        self.over += (f >= 1).sum(axis=0)
        ok = (f >= 0) & (f < 1)
        idx = np.minimum((f * self.bins).astype(np.int64), self.bins - 1)
        idx += np.arange(x.shape[1]) * self.bins  # flat bin numbers: one 1-D add.at, ~2.5x faster than (k, bin)
        flat = self.counts.reshape(-1)
        if not np.shares_memory(flat, self.counts):  # a copy would take the counts and drop them silently
            raise ValueError("histogram counts must be one contiguous array")
        np.add.at(flat, idx[ok], 1)

    def bin_width(self) -> np.ndarray:
        """(K,) the width of one bin of each component (its values' unit)."""
        return (np.asarray(self.high, float) - np.asarray(self.low, float)) / self.bins

    def shortest(self, p: float, rows=None) -> np.ndarray:
        """(K, 2) the shortest interval holding the fraction p of each component's trials (JCGM 101 7.7.2 applied to
        the histogram's piecewise-linear CDF, the one :meth:`quantiles` interpolates; ``rows``: only those components).

        The interval's width is piecewise linear in its lower end's probability alpha, with corners where alpha or
        alpha + p is the CDF at a bin edge: the narrowest is found among those corners, exactly for that CDF.  Its
        length lies within about a bin (:meth:`bin_width`) of the trials' own shortest interval's; its ends are less
        determined where the distribution is nearly symmetric (the length hardly changes as the interval slides).  An interval
        that would reach into the values below or above the histogram's range cannot be located: NaN.
        """
        ks = range(self.counts.shape[0]) if rows is None else list(rows)
        out = np.full((len(ks), 2), np.nan)
        for i, k in enumerate(ks):
            tot = self.counts[k].sum() + self.under[k] + self.over[k]
            cdf = (self.under[k] + np.concatenate([[0], np.cumsum(self.counts[k])])) / tot
            edges = np.linspace(self.low[k], self.high[k], self.bins + 1)
            lo_a, hi_a = cdf[0], cdf[-1] - p  # alpha: the interval within the range
            if not tot or hi_a < lo_a:
                continue
            alpha = np.concatenate([cdf, cdf - p])
            alpha = alpha[(alpha >= lo_a) & (alpha <= hi_a)]
            a = _cdf_inverse(cdf, edges, alpha, "right")  # the lower end: the last x with F(x) = alpha
            b = _cdf_inverse(cdf, edges, np.minimum(alpha + p, cdf[-1]), "left")  # the first x with F(x) = alpha + p
            j = int(np.argmin(b - a))
            out[i] = a[j], b[j]
        return out

    def quantiles(self, prob, rows=None) -> np.ndarray:
        """(K, len(prob)) quantiles by linear interpolation of the binned CDF (``rows``: only those components,
        (len(rows), len(prob))).

        A quantile that falls among the values below or above the histogram's
        range (fixed from the first block) cannot be located: it is NaN, never
        the range's edge.
        """
        prob = np.asarray(prob, float)
        ks = range(self.counts.shape[0]) if rows is None else list(rows)
        out = np.empty((len(ks), len(prob)))
        for i, k in enumerate(ks):
            tot = self.counts[k].sum() + self.under[k] + self.over[k]
            cdf = (self.under[k] + np.concatenate([[0], np.cumsum(self.counts[k])])) / tot
            edges = np.linspace(self.low[k], self.high[k], self.bins + 1)
            out[i] = np.interp(prob, cdf, edges)
            out[i, (prob <= self.under[k] / tot) | (prob >= 1 - self.over[k] / tot)] = np.nan
        return out


def _cdf_inverse(cdf: np.ndarray, edges: np.ndarray, t: np.ndarray, side: str) -> np.ndarray:
    """x with F(x) = t for the piecewise-linear CDF through (edges, cdf) (non-decreasing): where F is flat at t (an
    empty bin), the last such x (``side`` "right") or the first ("left")."""
    n = cdf.size
    if side == "left":
        j = np.clip(np.searchsorted(cdf, t, "left"), 1, n - 1)  # cdf[j - 1] < t <= cdf[j]
        i = j - 1
    else:
        i = np.clip(np.searchsorted(cdf, t, "right") - 1, 0, n - 2)  # cdf[i] <= t < cdf[i + 1]
        j = i + 1
    d = cdf[j] - cdf[i]
    # d = 0 only where clipped at the ends (t = cdf[0] on the left, t = cdf[-1] on the right): those ends' edges
    f = np.divide(t - cdf[i], d, out=np.full(d.shape, 0.0 if side == "left" else 1.0), where=d > 0)
    return edges[i] + np.clip(f, 0.0, 1.0) * (edges[j] - edges[i])


@dataclass
class CoMoments:
    """Mergeable count / mean / co-moment matrix of K small vectors (d components each), for per-point covariances.

    mean: (K, d); C: (K, d, d) sums of outer products of deviations (Chan et al.'s update, per vector).
    """

    n: int
    mean: np.ndarray
    C: np.ndarray

    @classmethod
    def of(cls, x: np.ndarray) -> "CoMoments":
        """From samples x: (n, K, d), in one compiled pass when n >= 1 (:func:`mtbudget.kernels_stats.comoments`: the
        same bits as :meth:`of_reference`, the numpy formulation)."""
        x = np.asarray(x, float)
        if x.ndim != 3 or not x.shape[0] or x.shape[1] * x.shape[2] < 2 or not x.flags.c_contiguous:
            return cls.of_reference(x)  # numpy would sum a single series pairwise: the reference's bits
        from .kernels_stats import comoments

        K, d = x.shape[1], x.shape[2]
        mean, C = np.empty((K, d)), np.empty((K, d, d))
        comoments(x, mean, C)
        return cls(x.shape[0], mean, C)

    @classmethod
    def of_reference(cls, x: np.ndarray) -> "CoMoments":
        x = np.asarray(x, float)
        mean = x.mean(axis=0)
        d = x - mean
        return cls(x.shape[0], mean, np.einsum("nki,nkj->kij", d, d))

    def merge(self, other: "CoMoments") -> "CoMoments":
        """Chan et al.'s update per vector; in one compiled pass (the same bits as :meth:`merge_reference`)."""
        if self.n == 0:
            return other
        if other.n == 0:
            return self
        parts = (self.mean, self.C, other.mean, other.C)
        if not (all(type(a) is np.ndarray and a.dtype == np.float64 for a in parts) and self.mean.ndim == 2
                and self.mean.shape == other.mean.shape and self.C.shape == other.C.shape == self.mean.shape
                + self.mean.shape[1:]):
            return self.merge_reference(other)
        from .kernels_stats import merge_comoments

        n = self.n + other.n
        mean, C = np.empty(self.mean.shape), np.empty(self.C.shape)
        merge_comoments(*parts, other.n / n, self.n * other.n / n, mean, C)
        return CoMoments(n, mean, C)

    def merge_reference(self, other: "CoMoments") -> "CoMoments":
        if self.n == 0:
            return other
        if other.n == 0:
            return self
        n = self.n + other.n
        delta = other.mean - self.mean
        mean = self.mean + delta * (other.n / n)
        # the outer products by broadcasting: each entry one product, as einsum("ki,kj->kij") forms it (no sum)
        C = self.C + other.C + (delta[:, :, None] * delta[:, None, :]) * (self.n * other.n / n)
        return CoMoments(n, mean, C)

    @property
    def cov(self) -> np.ndarray:
        return self.C / (self.n - 1) if self.n > 1 else np.full_like(self.C, np.nan)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.cov, axis1=1, axis2=2), 0.0))


class Accumulator:
    """Streaming statistics of a run, merged in block order (deterministic for any chunking or executor).

    Scalar outputs: exact moments (all outputs of a block merged at once, :meth:`Moments.of_rows`) and, when
    ``keep_samples``, every value (exact order-statistic intervals), otherwise a fine histogram per output
    (bounded memory; only runs that do not keep every value read it).  Vector outputs: their moments only, and
    the per-component samples or histograms of ``vectors``.  Summaries and intervals are computed once per state
    (a run's JSON asks for them more than once).  ``keep_until``: with ``keep_samples``, every scalar value is kept
    only until more than this many trials are merged; then they go into the histogram, ranged from the first block
    as a run that never kept them would range it (the same counts: an adaptive run of N trials states the intervals a
    fixed run of N trials states), and memory stays bounded.
    """

    def __init__(self, keep_samples: bool = True, keep_vector_samples: bool = True, keep_until: int | None = None):
        self.keep = keep_samples
        self.keep_until = keep_until
        self.keep_vectors = keep_vector_samples
        self.vector_samples: dict = {}
        self.vector_hist: dict = {}
        self.n = 0
        self.not_converged = 0
        self.fallbacks = 0
        self.moments: dict = {}  # vector outputs: name -> Moments or CoMoments
        self.samples: dict = {}
        self.blocks: list = []
        self.scalar_names: tuple = ()  # the scalar outputs, in the order of the first block
        self.scalar_moments: Moments | None = None  # every scalar output at once: row k is scalar_names[k]
        self.scalar_hist: VectorHistogram | None = None  # one column per scalar output; runs that do not keep samples
        self._cache: dict = {}  # summaries and intervals of the current state (cleared by add)

    def add(self, block: int, n: int, scalars: dict, vector_moments: dict, not_converged: int = 0,
            vectors: dict | None = None, fallbacks: int = 0):
        """Merge one block: ``scalars`` name -> (n,) values; ``vector_moments`` name -> Moments (or CoMoments);
        ``vectors`` name -> (n, K) values whose per-component coverage intervals are wanted."""
        self._cache.clear()
        for k, v in (vectors or {}).items():
            if self.keep_vectors:
                self.vector_samples.setdefault(k, []).append(v)
            else:
                if k not in self.vector_hist:
                    self.vector_hist[k] = VectorHistogram(v)
                self.vector_hist[k].add(v)
        self.blocks.append(block)
        if scalars:
            names = tuple(scalars)
            if not self.scalar_names:
                self.scalar_names = names
            elif names != self.scalar_names:
                raise ValueError(f"a block's scalar outputs {names} differ from the run's {self.scalar_names}")
            rows = np.stack([np.asarray(scalars[k], float) for k in names])  # (K, n): one series per output
            m = Moments.of_rows(rows)
            self.scalar_moments = m if self.scalar_moments is None else self.scalar_moments.merge(m)
            if self.keep:
                for k in names:
                    self.samples.setdefault(k, []).append(scalars[k])
            else:
                if self.scalar_hist is None:
                    self.scalar_hist = VectorHistogram(rows.T)
                self.scalar_hist.add(rows.T)
        for key, m in vector_moments.items():
            self.moments[key] = m if key not in self.moments else self.moments[key].merge(m)
        self.n += n
        self.not_converged += int(not_converged)
        self.fallbacks += int(fallbacks)
        if self.keep and self.keep_until is not None and self.n > self.keep_until and self.scalar_names:
            self._histogram_kept_samples()

    def _histogram_kept_samples(self):
        """From now on, histogram the scalar outputs: the values kept so far are counted and dropped."""
        names = self.scalar_names
        first = np.stack([np.asarray(self.samples[k][0], float) for k in names], axis=1)  # the first block, (n0, K)
        self.scalar_hist = VectorHistogram(first)
        for i in range(len(self.samples[names[0]])):
            self.scalar_hist.add(np.stack([np.asarray(self.samples[k][i], float) for k in names], axis=1))
        self.samples, self.keep = {}, False

    def scalar_moments_of(self, name: str) -> Moments:
        """The moments of one scalar output (as merging ``Moments.of`` of its values block by block gives them)."""
        if name not in self.scalar_names:
            raise KeyError(name)
        return self.scalar_moments.row(self.scalar_names.index(name))

    def vector_intervals(self, name: str, coverage: float) -> dict | None:
        """Per-component probabilistically symmetric (and, from samples, shortest) intervals of a vector output."""
        key = ("vector_intervals", name, coverage)
        if key not in self._cache:
            self._cache[key] = self._vector_intervals(name, coverage)
        hit = self._cache[key]
        return None if hit is None else dict(hit)

    def _vector_intervals(self, name: str, coverage: float) -> dict | None:
        parts = self.vector_samples.get(name)
        if parts:
            # component-major (K, M): each component's values contiguous, sorted row by row (3x faster than sorting
            # the trial-major array along its columns; the same sort of the same values, so the same order statistics)
            M = sum(p.shape[0] for p in parts)
            yt = np.empty((parts[0].shape[1], M))
            at = 0
            for p in parts:
                yt[:, at:at + p.shape[0]] = p.T
                at += p.shape[0]
            yt.sort(axis=1)
            r, q = interval_indices(M, coverage)
            r = min(r, M - q - 1)
            widths = yt[:, q:] - yt[:, : M - q]
            k = np.argmin(widths, axis=1)
            cols = np.arange(yt.shape[0])
            return {"low": yt[:, r].copy(), "high": yt[:, r + q].copy(), "shortest_low": yt[cols, k],
                    "shortest_high": yt[cols, k + q], "method": "order statistics of every trial (JCGM 101 7.7)",
                    "shortest_method": "order statistics of every trial (JCGM 101 7.7.2)"}
        h = self.vector_hist.get(name)
        if h is None:
            return None
        q = h.quantiles(np.array([(1 - coverage) / 2, (1 + coverage) / 2]))
        sh = h.shortest(coverage)
        return {"low": q[:, 0], "high": q[:, 1], "shortest_low": sh[:, 0], "shortest_high": sh[:, 1],
                "method": f"quantiles of a {h.bins}-bin histogram per component (bounded memory; ranges fixed from the first block)",
                "shortest_method": HISTOGRAM_SHORTEST.format(bins=h.bins)}

    def scalar_samples(self, name: str) -> np.ndarray | None:
        if not self.keep or not self.samples.get(name):
            return None
        return np.concatenate(self.samples[name])

    def summary(self, name: str, coverage: float) -> dict:
        key = ("summary", name, coverage)
        if key not in self._cache:
            self._cache[key] = self._summary(name, coverage)
        return dict(self._cache[key])

    def _summary(self, name: str, coverage: float) -> dict:
        m = self.scalar_moments_of(name)
        y = self.scalar_samples(name)
        if y is not None:
            ys = y
            ys.sort()  # a fresh concatenation: sorted in place
            sym, short = symmetric_interval(ys, coverage), shortest_interval(ys, coverage)
            exact = True
        else:
            row = [self.scalar_names.index(name)]
            q = self.scalar_hist.quantiles(np.array([(1 - coverage) / 2, (1 + coverage) / 2]), rows=row)
            sh = self.scalar_hist.shortest(coverage, rows=row)
            # NaN: the interval would reach into the values beyond the histogram's range; then none is stated
            short = None if np.isnan(sh).any() else (float(sh[0, 0]), float(sh[0, 1]))
            sym, exact = (float(q[0, 0]), float(q[0, 1])), False
            hist = {"bins": int(self.scalar_hist.bins), "bin_width": float(self.scalar_hist.bin_width()[row[0]])}
        return {"mean": float(np.asarray(m.mean).ravel()[0]), "std": float(np.asarray(m.std).ravel()[0]),
                "symmetric": sym, "shortest": short, "exact_intervals": exact, "n": m.n,
                **({} if exact else {"histogram": hist})}


class AdaptiveStop:
    """The adaptive Monte Carlo procedure's stopping rule (JCGM 101 7.9), shared by every MCM of mtbudget.

    After each batch of h trials, ``add`` takes, per output, the batch's
    (mean, standard deviation, interval low, interval high).  ``done(u)`` is
    true when twice the standard deviation of the batch means of every
    quantity is within the numerical tolerance of the standard uncertainty
    ``u`` of its output (JCGM 101 7.9.4, 7.9.2).
    """

    def __init__(self, ndig: int = 2):
        self.ndig = ndig
        self.batches: list = []

    def add(self, rows) -> None:
        self.batches.append(np.atleast_2d(np.asarray(rows, float)))

    def done(self, u) -> bool:
        if len(self.batches) < 2:
            return False
        arr = np.array(self.batches)  # (h, outputs, 4)
        s = arr.std(axis=0, ddof=1) / math.sqrt(len(arr))
        deltas = np.array([numerical_tolerance(float(x), self.ndig) for x in np.atleast_1d(u)])
        return bool(np.all(2 * s <= deltas[:, None]))

    def stable(self, u) -> np.ndarray:
        """Per output, whether its mean, standard deviation and interval ends are all within their numerical tolerance
        (JCGM 101 7.9.4): (outputs,) bools, all False before two batches.  ``done(u)`` is ``stable(u).all()``."""
        u = np.atleast_1d(np.asarray(u, float))
        if len(self.batches) < 2:
            return np.zeros(u.shape, bool)
        two_s, deltas, _ = self.spread(u)
        return np.all(two_s <= deltas[:, None], axis=1)

    #: the four quantities of each output the rule checks, in the order of a batch row
    QUANTITIES = ("estimate", "standard uncertainty", "interval low end", "interval high end")

    def spread(self, u) -> tuple:
        """What the rule compares, after two batches or more: (2 s, delta, last change) with 2 s (outputs, 4) twice the
        standard deviation of the average of the batch values of each quantity (:attr:`QUANTITIES`), delta (outputs,)
        the numerical tolerance of each output's u (JCGM 101 7.9.2), and the last change (outputs, 4): how far the
        average of the batch values moved with the last batch."""
        u = np.atleast_1d(np.asarray(u, float))
        arr = np.array(self.batches)  # (h, outputs, 4)
        s = arr.std(axis=0, ddof=1) / math.sqrt(len(arr))
        deltas = np.array([numerical_tolerance(float(x), self.ndig) for x in u])
        return 2 * s, deltas, arr.mean(axis=0) - arr[:-1].mean(axis=0)


def batch_rows(Y: np.ndarray, coverage: float) -> np.ndarray:
    """(K, 4): (mean, std, interval low, interval high) of one batch of K outputs at once, Y (n, K) (each column as
    :func:`batch_row` of that column gives it)."""
    Ys = np.sort(Y, axis=0)
    M = Ys.shape[0]
    r, q = interval_indices(M, coverage)
    r = max(0, min(r, M - q - 1))
    return np.stack([Ys.mean(axis=0), Ys.std(axis=0, ddof=1), Ys[r], Ys[r + q]], axis=1)


def batch_row(y: np.ndarray, coverage: float, presorted: bool = False) -> list:
    """(mean, std, interval low, interval high) of one batch of an output (``presorted``: y is sorted already)."""
    ys = y if presorted else np.sort(y)
    lo, hi = symmetric_interval(ys, coverage)
    return [float(ys.mean()), float(ys.std(ddof=1)), lo, hi]
