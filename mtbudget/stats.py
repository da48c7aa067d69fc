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
        x = np.asarray(x, float)
        n = x.shape[0]
        mean = x.mean(axis=0)
        return cls(n, mean, ((x - mean) ** 2).sum(axis=0), x.min(axis=0), x.max(axis=0))

    def merge(self, other: "Moments") -> "Moments":
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


class VectorHistogram:
    """Histograms of K components with ranges fixed from the first block (overflow counted)."""

    def __init__(self, first: np.ndarray, bins: int = 4000):
        lo, hi = first.min(axis=0), first.max(axis=0)
        c, w = (lo + hi) / 2, np.maximum(hi - lo, np.maximum(np.abs(lo + hi) * 1e-9, 1e-12))
        self.low, self.high, self.bins = c - 2 * w, c + 2 * w, bins
        self.counts = np.zeros((first.shape[1], bins), np.int64)
        self.under = np.zeros(first.shape[1], np.int64)
        self.over = np.zeros(first.shape[1], np.int64)

    def add(self, x: np.ndarray):
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

    def quantiles(self, prob) -> np.ndarray:
        """(K, len(prob)) quantiles by linear interpolation of the binned CDF.

        A quantile that falls among the values below or above the histogram's
        range (fixed from the first block) cannot be located: it is NaN, never
        the range's edge.
        """
        prob = np.asarray(prob, float)
        out = np.empty((self.counts.shape[0], len(prob)))
        for k in range(self.counts.shape[0]):
            tot = self.counts[k].sum() + self.under[k] + self.over[k]
            cdf = (self.under[k] + np.concatenate([[0], np.cumsum(self.counts[k])])) / tot
            edges = np.linspace(self.low[k], self.high[k], self.bins + 1)
            out[k] = np.interp(prob, cdf, edges)
            out[k, (prob <= self.under[k] / tot) | (prob >= 1 - self.over[k] / tot)] = np.nan
        return out


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
        """From samples x: (n, K, d)."""
        x = np.asarray(x, float)
        mean = x.mean(axis=0)
        d = x - mean
        return cls(x.shape[0], mean, np.einsum("nki,nkj->kij", d, d))

    def merge(self, other: "CoMoments") -> "CoMoments":
        if self.n == 0:
            return other
        if other.n == 0:
            return self
        n = self.n + other.n
        delta = other.mean - self.mean
        mean = self.mean + delta * (other.n / n)
        C = self.C + other.C + np.einsum("ki,kj->kij", delta, delta) * (self.n * other.n / n)
        return CoMoments(n, mean, C)

    @property
    def cov(self) -> np.ndarray:
        return self.C / (self.n - 1) if self.n > 1 else np.full_like(self.C, np.nan)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.cov, axis1=1, axis2=2), 0.0))


class Accumulator:
    """Streaming statistics of a run, merged in block order (deterministic for any chunking or executor).

    Scalar outputs: exact moments, a fine histogram (bounded memory) and, when
    ``keep_samples``, every value (exact order-statistic intervals).  Vector
    outputs: their moments only.
    """

    def __init__(self, keep_samples: bool = True, keep_vector_samples: bool = True):
        self.keep = keep_samples
        self.keep_vectors = keep_vector_samples
        self.vector_samples: dict = {}
        self.vector_hist: dict = {}
        self.n = 0
        self.not_converged = 0
        self.fallbacks = 0
        self.moments: dict = {}
        self.hist: dict = {}
        self.samples: dict = {}
        self.blocks: list = []

    def add(self, block: int, n: int, scalars: dict, vector_moments: dict, not_converged: int = 0,
            vectors: dict | None = None, fallbacks: int = 0):
        """Merge one block: ``scalars`` name -> (n,) values; ``vector_moments`` name -> Moments (or CoMoments);
        ``vectors`` name -> (n, K) values whose per-component coverage intervals are wanted."""
        for k, v in (vectors or {}).items():
            if self.keep_vectors:
                self.vector_samples.setdefault(k, []).append(v)
            else:
                if k not in self.vector_hist:
                    self.vector_hist[k] = VectorHistogram(v)
                self.vector_hist[k].add(v)
        self.blocks.append(block)
        for k, v in scalars.items():
            col = v[:, None]
            m = Moments.of(col)
            self.moments[k] = m if k not in self.moments else self.moments[k].merge(m)
            if k not in self.hist:
                self.hist[k] = VectorHistogram(col)
            self.hist[k].add(col)
            if self.keep:
                self.samples.setdefault(k, []).append(v)
        for key, m in vector_moments.items():
            self.moments[key] = m if key not in self.moments else self.moments[key].merge(m)
        self.n += n
        self.not_converged += int(not_converged)
        self.fallbacks += int(fallbacks)

    def vector_intervals(self, name: str, coverage: float) -> dict | None:
        """Per-component probabilistically symmetric (and, from samples, shortest) intervals of a vector output."""
        if self.vector_samples.get(name):
            y = np.concatenate(self.vector_samples[name])
            y.sort(axis=0)  # in place: the concatenation is a fresh array
            M = y.shape[0]
            r, q = interval_indices(M, coverage)
            r = min(r, M - q - 1)
            widths = y[q:] - y[: M - q]
            k = np.argmin(widths, axis=0)
            cols = np.arange(y.shape[1])
            return {"low": y[r], "high": y[r + q], "shortest_low": y[k, cols], "shortest_high": y[k + q, cols],
                    "method": "order statistics of every trial (JCGM 101 7.7)"}
        h = self.vector_hist.get(name)
        if h is None:
            return None
        q = h.quantiles(np.array([(1 - coverage) / 2, (1 + coverage) / 2]))
        return {"low": q[:, 0], "high": q[:, 1], "shortest_low": None, "shortest_high": None,
                "method": f"quantiles of a {h.bins}-bin histogram per component (bounded memory; ranges fixed from the first block)"}

    def scalar_samples(self, name: str) -> np.ndarray | None:
        if not self.keep or not self.samples.get(name):
            return None
        return np.concatenate(self.samples[name])

    def summary(self, name: str, coverage: float) -> dict:
        m = self.moments[name]
        y = self.scalar_samples(name)
        if y is not None:
            ys = y
            ys.sort()  # a fresh concatenation: sorted in place
            sym, short = symmetric_interval(ys, coverage), shortest_interval(ys, coverage)
            exact = True
        else:
            h = self.hist[name]
            q = h.quantiles(np.array([(1 - coverage) / 2, (1 + coverage) / 2]))
            sym, short, exact = (float(q[0, 0]), float(q[0, 1])), None, False
        return {"mean": float(np.asarray(m.mean).ravel()[0]), "std": float(np.asarray(m.std).ravel()[0]),
                "symmetric": sym, "shortest": short, "exact_intervals": exact, "n": m.n}


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


def batch_row(y: np.ndarray, coverage: float, presorted: bool = False) -> list:
    """(mean, std, interval low, interval high) of one batch of an output (``presorted``: y is sorted already)."""
    ys = y if presorted else np.sort(y)
    lo, hi = symmetric_interval(ys, coverage)
    return [float(ys.mean()), float(ys.std(ddof=1)), lo, hi]
