"""Coverage intervals, streaming statistics and the adaptive stopping rule of JCGM 101.

Everything here works on plain float arrays (internal units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def interval_indices(M: int, p: float) -> tuple[int, int]:
    """(r, q): JCGM 101 7.7: q = pM rounded (+1/2 rule), the interval is [y_(r), y_(r+q)] (0-based)."""
    q = int(p * M + 0.5)
    q = min(max(q, 1), M - 1)
    r = int(round((M - q) / 2))
    return r, q


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


@dataclass
class Histogram:
    """Fixed-range histogram with overflow bins, for quantiles of runs too long to keep.

    The range is fixed from the first block (its range widened 4x about its
    centre); values beyond it land in the two overflow counts, which the
    quantile read-out reports so a caller can tell when the tails were clipped.
    """

    low: float
    high: float
    counts: np.ndarray = field(default=None)
    under: int = 0
    over: int = 0
    bins: int = 20000

    def __post_init__(self):
        if self.counts is None:
            self.counts = np.zeros(self.bins, np.int64)

    @classmethod
    def for_sample(cls, x: np.ndarray, bins: int = 20000) -> "Histogram":
        lo, hi = float(np.min(x)), float(np.max(x))
        c, w = (lo + hi) / 2, max(hi - lo, abs(lo + hi) * 1e-12, 1e-300)
        return cls(c - 2 * w, c + 2 * w, bins=bins)

    def add(self, x: np.ndarray):
        x = np.asarray(x, float)
        self.under += int((x < self.low).sum())
        self.over += int((x >= self.high).sum())
        inside = x[(x >= self.low) & (x < self.high)]
        idx = ((inside - self.low) / (self.high - self.low) * self.bins).astype(np.int64)
        self.counts += np.bincount(np.clip(idx, 0, self.bins - 1), minlength=self.bins)

    def merge(self, other: "Histogram"):
        if (other.low, other.high, other.bins) != (self.low, self.high, self.bins):
            raise ValueError("histograms with different ranges cannot be merged")
        self.counts += other.counts
        self.under += other.under
        self.over += other.over

    def quantile(self, prob: np.ndarray) -> np.ndarray:
        total = self.counts.sum() + self.under + self.over
        cdf = (self.under + np.concatenate([[0], np.cumsum(self.counts)])) / total
        edges = np.linspace(self.low, self.high, self.bins + 1)
        return np.interp(prob, cdf, edges)

    def intervals(self, p: float) -> dict:
        lo, hi = self.quantile(np.array([(1 - p) / 2, (1 + p) / 2]))
        # shortest: scan lower tail probabilities
        a = np.linspace(0, 1 - p, 2001)
        low = self.quantile(a)
        high = self.quantile(a + p)
        k = int(np.argmin(high - low))
        return {"symmetric": (float(lo), float(hi)), "shortest": (float(low[k]), float(high[k])),
                "clipped": self.under + self.over}
