"""Compiled kernels of a block's figures and statistics (numba; issue 31): one pass where numpy made a dozen.

:func:`compensation_figures` turns the engine's compensated field (rigid motions removed) into the per-point errors
and every trial's scalars; :func:`moments` and :func:`comoments` are ``stats.Moments.of`` and ``stats.CoMoments.of``
of a block.  Each gives **the same bits** as the numpy formulation it replaces, which stays beside it as the
reference (``tests/test_kernels_stats.py`` compares them bit for bit, and with sums computed independently by
``math.fsum``):

* a sum over the trials of a block (numpy's reduction along the first axis of a C-ordered array) is taken in trial
  order, one accumulator per component, as numpy's strided reduction adds row after row;
* a sum over the points of one trial (numpy's reduction along the contiguous last axis) is numpy's pairwise sum
  (:func:`_pairwise`: eight partial sums below 128 values, halves above), as ``np.add.reduce`` does;
* products, quotients and square roots are IEEE operations in the same order (no ``fastmath``: no reassociation,
  no fused multiply-add); minima and maxima are exact and NaN propagates.  Where a series mixes 0.0 and -0.0, the
  sign of a zero minimum, maximum or mean of :func:`moments_rows` may differ from numpy's, and a merge may give a NaN
  of the other sign: no output of a run is affected (they are non-negative, and a NaN is a NaN).

numpy summed a contiguous run in buffers of 8192 values, each pairwise, up to its 2.2 and one pairwise tree from 2.3
on (measured on 1.26.4, 2.2.6, 2.3.5 and 2.4.6); the kernels sum as 2.3 does, so on an older numpy the callers use
the numpy formulations for series longer than :data:`BUFFER` (``LIKE_NUMPY``), and the bits stay numpy's there too.

Every trial's figures depend on that trial's values only, a block's statistics on that block's only: results do
not depend on how blocks are grouped.  Only plain float64 arrays cross this boundary.
"""

from __future__ import annotations

import math

import numpy as np

from .kernels import compiled  # one njit rule for every kernel module (cached, nogil, no fastmath)

#: numpy's reduction buffer (``np.getbufsize()``'s default): up to numpy 2.2 a contiguous sum longer than this was
#: the sum of its buffers' pairwise sums, from 2.3 on one pairwise sum, which :func:`_pairwise` reproduces
BUFFER = 8192
#: whether this numpy sums a contiguous run as :func:`_pairwise` does at any length
LIKE_NUMPY = np.lib.NumpyVersion(np.__version__) >= "2.3.0"


@compiled
def _pairwise_leaf(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise sum of a[lo:lo + n] for n <= 128: in order below 8 values, else 8 partial sums."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    m = n - n % 8
    i = 8
    while i < m:
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@compiled
def _pairwise(a, lo, n):  # pragma: no cover - compiled
    """sum(a[lo:lo + n]) as numpy's pairwise summation adds a contiguous run of float64 (``pairwise_sum`` of numpy's
    umath loops: up to 128 values :func:`_pairwise_leaf`, above that the sum of the two halves, cut at a multiple of
    8).  The halving is walked with an explicit stack (numba's cache cannot hold a recursive function)."""
    if n <= 128:
        return _pairwise_leaf(a, lo, n)
    seg = np.empty((192, 3), np.int64)  # (lo, n, halves summed already?): depth <= 64 for any int64 n
    val = np.empty(96)
    top, nv = 0, 0
    seg[0, 0], seg[0, 1], seg[0, 2] = lo, n, 0
    while top >= 0:
        s_lo, s_n, done = seg[top, 0], seg[top, 1], seg[top, 2]
        top -= 1
        if s_n <= 128:
            val[nv] = _pairwise_leaf(a, s_lo, s_n)
            nv += 1
        elif done:
            val[nv - 2] = val[nv - 2] + val[nv - 1]  # the first half's sum + the second half's
            nv -= 1
        else:
            n2 = s_n // 2
            n2 -= n2 % 8
            seg[top + 1, 0], seg[top + 1, 1], seg[top + 1, 2] = s_lo, s_n, 1
            seg[top + 2, 0], seg[top + 2, 1], seg[top + 2, 2] = s_lo + n2, s_n - n2, 0
            seg[top + 3, 0], seg[top + 3, 1], seg[top + 3, 2] = s_lo, n2, 0
            top += 3
    return val[0]


@compiled
def _keeps_min(cur, v):  # pragma: no cover - compiled
    """Whether numpy's minimum of (cur, v) is cur: cur < v, or cur is NaN (on a tie, and for a NaN v, it is v)."""
    return cur < v or cur != cur


@compiled
def _keeps_max(cur, v):  # pragma: no cover - compiled
    """Whether numpy's maximum of (cur, v) is cur: cur > v, or cur is NaN (on a tie, and for a NaN v, it is v)."""
    return cur > v or cur != cur


@compiled
def compensation_figures(D, um, comp, e, rms, mean, emax, amax):  # pragma: no cover - compiled
    """The compensated field D (N, M, 3) in mm, rigid motions removed, as the engine reports it, per trial t:
    comp[t] = D[t] um (um), e[t] = |D[t]| um over the last axis (``tracker.norm3``, then scaled), rms[t] =
    sqrt(mean(e[t]^2)), mean[t] = mean(e[t]), emax[t] = max(e[t]), amax[t] = (max |comp[t, :, a]| for a = x, y, z, and
    their max): the numbers of ``norm3``, ``mean(axis=1)``, ``max(axis=1)`` and ``np.abs(comp).max(axis=1)``."""
    N, M = D.shape[0], D.shape[1]
    sq = np.empty(M)
    for t in range(N):
        et = e[t]
        ct = comp[t]
        for m in range(M):
            x = D[t, m, 0]
            y = D[t, m, 1]
            z = D[t, m, 2]
            ct[m, 0] = x * um
            ct[m, 1] = y * um
            ct[m, 2] = z * um
            v = math.sqrt(x * x + y * y + z * z) * um
            et[m] = v
            sq[m] = v * v
        rms[t] = math.sqrt(_pairwise(sq, 0, M) / M)
        mean[t] = _pairwise(et, 0, M) / M
        big = et[0]
        for m in range(1, M):
            if not _keeps_max(big, et[m]):
                big = et[m]
        emax[t] = big
        top = -1.0
        for a in range(3):
            c = abs(ct[0, a])
            for m in range(1, M):
                v = abs(ct[m, a])
                if not _keeps_max(c, v):
                    c = v
            amax[t, a] = c
            if a == 0 or not _keeps_max(top, c):
                top = c
        amax[t, 3] = top


@compiled
def moments(x, mean, m2, lo, hi):  # pragma: no cover - compiled
    """``stats.Moments.of`` of x (n, K), n >= 1: per column the mean (summed in row order, then / n), the sum of
    squared deviations (in row order), the minimum and maximum, into mean, m2, lo, hi (K,)."""
    n, K = x.shape[0], x.shape[1]
    for k in range(K):
        mean[k] = 0.0
        m2[k] = 0.0
        lo[k] = x[0, k]
        hi[k] = x[0, k]
    for i in range(n):
        for k in range(K):
            mean[k] += x[i, k]
    for k in range(K):
        mean[k] = mean[k] / n
    for i in range(n):
        for k in range(K):
            v = x[i, k]
            d = v - mean[k]
            m2[k] += d * d
            if i:
                if not _keeps_min(lo[k], v):
                    lo[k] = v
                if not _keeps_max(hi[k], v):
                    hi[k] = v


@compiled
def comoments(x, mean, C):  # pragma: no cover - compiled
    """``stats.CoMoments.of`` of x (n, K, d), n >= 1: mean (K, d) summed in row order then / n; C (K, d, d) the sums
    over the rows, in row order, of the outer products of the deviations (``einsum("nki,nkj->kij")``'s numbers)."""
    n, K, d = x.shape[0], x.shape[1], x.shape[2]
    for k in range(K):
        for a in range(d):
            mean[k, a] = 0.0
            for b in range(d):
                C[k, a, b] = 0.0
    for i in range(n):
        for k in range(K):
            for a in range(d):
                mean[k, a] += x[i, k, a]
    for k in range(K):
        for a in range(d):
            mean[k, a] = mean[k, a] / n
    if d == 3:  # the per-point components: the same operations, unrolled
        for i in range(n):
            for k in range(K):
                d0 = x[i, k, 0] - mean[k, 0]
                d1 = x[i, k, 1] - mean[k, 1]
                d2 = x[i, k, 2] - mean[k, 2]
                C[k, 0, 0] += d0 * d0
                C[k, 0, 1] += d0 * d1
                C[k, 0, 2] += d0 * d2
                C[k, 1, 0] += d1 * d0
                C[k, 1, 1] += d1 * d1
                C[k, 1, 2] += d1 * d2
                C[k, 2, 0] += d2 * d0
                C[k, 2, 1] += d2 * d1
                C[k, 2, 2] += d2 * d2
        return
    dev = mean[0].copy()
    for i in range(n):
        for k in range(K):
            for a in range(d):
                dev[a] = x[i, k, a] - mean[k, a]
            for a in range(d):
                for b in range(d):
                    C[k, a, b] += dev[a] * dev[b]


@compiled
def histogram_add(x, low, width, bins, counts, under, over):  # pragma: no cover - compiled
    """Count the rows of x (n, K) into K histograms of ``bins`` bins on [low, low + width) (``width`` = high - low):
    ``stats.VectorHistogram.add_reference``'s numbers (f = (x - low) / width, below 0 under, from 1 over, else bin
    min(floor(f bins), bins - 1); NaN nowhere).  Row by row: the K bins of a row first (contiguous reads, the
    divisions independent of each other), then the K increments; 3.8x faster than the column-by-column kernel it
    replaced (``kernels.histogram_add`` up to 0.3.0) on the paper mesh's 225 components.  counts (K, bins), under and over (K,)
    int64, added to in place."""
    n, K = x.shape[0], x.shape[1]
    idx = np.empty(K, np.int64)
    for i in range(n):
        for k in range(K):
            f = (x[i, k] - low[k]) / width[k]
            j = -1  # NaN: counted nowhere
            if f < 0:
                j = -2
            elif f >= 1:
                j = -3
            elif f >= 0:
                j = min(int(f * bins), bins - 1)
            idx[k] = j
        for k in range(K):
            j = idx[k]
            if j >= 0:
                counts[k, j] += 1
            elif j == -2:
                under[k] += 1
            elif j == -3:
                over[k] += 1


@compiled
def moments_rows(rows, mean, m2, lo, hi):  # pragma: no cover - compiled
    """``stats.Moments.of_rows`` of rows (K, n), each row contiguous, n >= 1: per row its mean (numpy's pairwise sum,
    then / n), the pairwise sum of its squared deviations, its minimum and maximum, into mean, m2, lo, hi (K,)."""
    K, n = rows.shape[0], rows.shape[1]
    sq = np.empty(n)
    for k in range(K):
        r = rows[k]
        mu = _pairwise(r, 0, n) / n
        a = r[0]
        b = r[0]
        for i in range(n):
            d = r[i] - mu
            sq[i] = d * d
            v = r[i]
            if i:
                if not _keeps_min(a, v):
                    a = v
                if not _keeps_max(b, v):
                    b = v
        mean[k] = mu
        m2[k] = _pairwise(sq, 0, n)
        lo[k] = a
        hi[k] = b


@compiled
def merge_moments(am, am2, alo, ahi, bm, bm2, blo, bhi, wb, wab, mean, m2, lo, hi):  # pragma: no cover - compiled
    """``stats.Moments.merge`` of two (K,) moments, elementwise, with wb = nb / n and wab = na nb / n (Python floats):
    d = bm - am, mean = am + d wb, m2 = am2 + bm2 + d d wab, lo = minimum, hi = maximum (NaN propagates)."""
    for k in range(am.shape[0]):
        d = bm[k] - am[k]
        mean[k] = am[k] + d * wb
        m2[k] = am2[k] + bm2[k] + d * d * wab
        lo[k] = alo[k] if _keeps_min(alo[k], blo[k]) else blo[k]
        hi[k] = ahi[k] if _keeps_max(ahi[k], bhi[k]) else bhi[k]


@compiled
def merge_comoments(am, aC, bm, bC, wb, wab, mean, C):  # pragma: no cover - compiled
    """``stats.CoMoments.merge`` of (K, d) means and (K, d, d) co-moments, elementwise: delta = bm - am, mean = am +
    delta wb, C = aC + bC + (delta_i delta_j) wab."""
    K, d = am.shape[0], am.shape[1]
    delta = np.empty(d)
    for k in range(K):
        for i in range(d):
            delta[i] = bm[k, i] - am[k, i]
            mean[k, i] = am[k, i] + delta[i] * wb
        for i in range(d):
            for j in range(d):
                C[k, i, j] = aC[k, i, j] + bC[k, i, j] + (delta[i] * delta[j]) * wab


#: the kernels a run compiles (what :func:`compiled_here` looks for)
#: the kernels every run compiles (what :func:`compiled_here` looks for); ``histogram_add`` only runs that histogram
#: (from about 11 000 trials on) compile, about a second inside a run that shows its progress: were it looked for, a
#: machine that never ran a long run would be told of a compilation at every command
KERNELS = (compensation_figures, moments, comoments, moments_rows, merge_moments, merge_comoments)


def compiled_here() -> bool | None:
    """Whether numba's cache already holds these kernels on this machine (False: a run's first call compiles them,
    about 2.6 s of CPU); None when that cannot be told (:func:`mtbudget.kernels.compiled_here`)."""
    from .kernels import compiled_here as cached

    return cached(KERNELS)
