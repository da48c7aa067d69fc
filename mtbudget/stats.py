"""Coverage intervals, streaming statistics and the adaptive stopping rule of JCGM 101.

Everything here works on plain float arrays (internal units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
