"""The compiled block statistics (mtbudget.kernels_stats) against numpy, bit for bit, and against independent sums.

Each kernel replaces a numpy formulation that stays as its reference (``Moments.of_reference``,
``CoMoments.of_reference``, ``engine.compensation_figures_reference``): their numbers must be the same bits, since
the run's logged and merged statistics were computed with numpy before.  Beside that, every figure is checked
against a computation that shares nothing with either (``math.fsum`` of the values, two passes, ``np.cov``,
``math.hypot``), so that a kernel and its reference cannot agree on a wrong number.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from mtbudget.engine import compensation_figures, compensation_figures_reference
from mtbudget.kernels_stats import _pairwise
from mtbudget.stats import CoMoments, Moments

RNG = np.random.default_rng(20261126)


def same_bits(a, b) -> bool:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("n", [0, 1, 2, 7, 8, 9, 15, 16, 17, 75, 127, 128, 129, 130, 255, 256, 257, 1000, 4851,
                               14553, 100_003])
def test_pairwise_sum_is_numpys_and_close_to_the_exact_sum(n):
    for scale in (1.0, 1e-6, 1e6):
        a = RNG.standard_normal(n + 3) * scale + scale  # summed from an offset: a run that starts inside an array
        got = _pairwise(a, 3, n)
        assert same_bits(got, np.add.reduce(a[3:]))
        exact = math.fsum(a[3:])
        assert abs(got - exact) <= 1e-13 * max(math.fsum(np.abs(a[3:])), 1e-300)


@pytest.mark.parametrize("N,M", [(1, 1), (2, 7), (3, 8), (64, 75), (5, 129), (4, 300), (2, 9001)])
def test_compensation_figures_are_the_numpy_formulation_bit_for_bit(N, M):
    D = RNG.standard_normal((N, M, 3)) * 1e-3  # mm
    D[0, 0] = [-2e-3, 0.0, 1e-9]  # a negative largest component and an exact zero
    um = 1000.0
    s_kernel, s_ref = {}, {}
    comp, e, whole = compensation_figures(D, um, s_kernel)
    comp_r, e_r, whole_r = compensation_figures_reference(D, um, s_ref)
    assert same_bits(comp, comp_r) and same_bits(e, e_r)
    assert list(s_kernel) == list(s_ref) and all(same_bits(s_kernel[k], s_ref[k]) for k in s_ref)
    assert list(whole) == list(whole_r) and all(same_bits(whole[k], whole_r[k]) for k in whole_r)
    s_parts = {}  # the blocks of a chunk one after the other: each trial's figures are its own
    cuts = [0, N // 3, N // 2, N] if N > 2 else [0, N]
    comp_p, e_p, whole_p = compensation_figures([D[a:b] for a, b in zip(cuts, cuts[1:])], um, s_parts)
    assert same_bits(comp_p, comp) and same_bits(e_p, e) and all(same_bits(s_parts[k], s_ref[k]) for k in s_ref)
    assert all(same_bits(whole_p[k], whole_r[k]) for k in whole_r)
    # independently: lengths by hypot, means by fsum, maxima by sorting
    for t in range(N):
        lengths = [math.hypot(*(D[t, m] * um)) for m in range(M)]
        assert np.allclose(e[t], lengths, rtol=1e-15, atol=0)
        assert s_kernel["compensation_rms"][t] == pytest.approx(math.sqrt(math.fsum(x * x for x in lengths) / M),
                                                                rel=1e-14)
        assert s_kernel["compensation_mean"][t] == pytest.approx(math.fsum(lengths) / M, rel=1e-14)
        assert s_kernel["compensation_max"][t] == pytest.approx(sorted(lengths)[-1], rel=1e-15)
        for a, k in enumerate(("largest_abs_component_x", "largest_abs_component_y", "largest_abs_component_z")):
            assert whole[k][t] == sorted(abs(D[t, m, a]) * um for m in range(M))[-1]
        assert whole["largest_abs_component"][t] == max(whole[k][t] for k in list(whole)[:3])


def test_compensation_figures_propagate_nan_as_numpy():
    D = RNG.standard_normal((3, 10, 3))
    D[1, 4, 2] = np.nan
    s_kernel, s_ref = {}, {}
    comp, e, whole = compensation_figures(D, 1000.0, s_kernel)
    comp_r, e_r, whole_r = compensation_figures_reference(D, 1000.0, s_ref)
    assert same_bits(e, e_r) and all(same_bits(s_kernel[k], s_ref[k]) for k in s_ref)
    assert all(same_bits(whole[k], whole_r[k]) for k in whole_r)
    assert np.isnan(s_kernel["compensation_max"][1]) and np.isnan(whole["largest_abs_component"][1])
    assert not np.isnan(whole["largest_abs_component"][[0, 2]]).any()


@pytest.mark.parametrize("n,K", [(1, 1), (1, 75), (3, 10), (64, 54), (64, 75), (17, 225), (200, 7), (200, 1),
                                 (64, 2), (1000, 2)])
def test_moments_are_numpys_bit_for_bit_and_the_two_pass_sums(n, K):
    x = RNG.standard_normal((n, K)) * 10 + 3
    m, r = Moments.of(x), Moments.of_reference(x)
    assert m.n == r.n == n
    for a, b in ((m.mean, r.mean), (m.m2, r.m2), (m.minimum, r.minimum), (m.maximum, r.maximum)):
        assert same_bits(a, b)
    for k in range(K):
        col = x[:, k].tolist()
        mean = math.fsum(col) / n
        assert m.mean[k] == pytest.approx(mean, rel=1e-13)
        assert m.m2[k] == pytest.approx(math.fsum((v - mean) ** 2 for v in col), rel=1e-12, abs=1e-12)
        assert (m.minimum[k], m.maximum[k]) == (min(col), max(col))


@pytest.mark.parametrize("layout", ["C", "view", "F"])
def test_moments_of_views_and_with_nan_are_numpys(layout):
    x = RNG.standard_normal((300, 40))
    x = {"C": x, "view": x[::2, 5:30], "F": np.asfortranarray(x)}[layout]
    x[2, 3] = np.nan
    m, r = Moments.of(x), Moments.of_reference(x)
    for a, b in ((m.mean, r.mean), (m.m2, r.m2), (m.minimum, r.minimum), (m.maximum, r.maximum)):
        assert same_bits(a, b)
    assert np.isnan(m.minimum[3]) and np.isnan(m.maximum[3]) and not np.isnan(m.minimum[4])


@pytest.mark.parametrize("n,K,d", [(1, 4, 3), (2, 75, 3), (64, 75, 3), (33, 10, 2), (64, 4851, 3), (200, 1, 1),
                                   (200, 1, 2), (200, 2, 1), (64, 1, 3)])
def test_comoments_are_numpys_bit_for_bit_and_np_cov(n, K, d):
    x = RNG.standard_normal((n, K, d)) * 5 + 1
    x[:, :, 0] += 0.5 * x[:, :, -1]  # correlated components
    c, r = CoMoments.of(x), CoMoments.of_reference(x)
    assert c.n == r.n == n and same_bits(c.mean, r.mean) and same_bits(c.C, r.C)
    if n > 1:
        for k in range(0, K, max(1, K // 7)):
            assert np.allclose(c.cov[k], np.cov(x[:, k, :], rowvar=False), rtol=1e-12, atol=1e-12)


def test_comoments_merge_is_the_einsum_formula_bit_for_bit():
    xa, xb = RNG.standard_normal((64, 75, 3)), RNG.standard_normal((13, 75, 3)) + 0.1
    a, b = CoMoments.of(xa), CoMoments.of(xb)
    m = a.merge(b)
    n = a.n + b.n
    delta = b.mean - a.mean
    C = a.C + b.C + np.einsum("ki,kj->kij", delta, delta) * (a.n * b.n / n)
    assert same_bits(m.C, C) and same_bits(m.mean, a.mean + delta * (b.n / n))
    pooled = np.concatenate([xa, xb])  # and it is the co-moments of the pooled samples, to round-off
    assert np.allclose(m.C, np.einsum("nki,nkj->kij", pooled - pooled.mean(0), pooled - pooled.mean(0)), rtol=1e-12,
                       atol=1e-12)


@pytest.mark.parametrize("n,K,bins", [(1, 1, 500), (64, 225, 4000), (130, 7, 10), (3, 2, 1)])
def test_histogram_counts_are_the_references(n, K, bins):
    from mtbudget.stats import VectorHistogram

    first = RNG.standard_normal((max(n, 2), K))
    x = RNG.standard_normal((n, K)) * 3  # some below and above the range fixed from the first block
    x[0, 0] = np.nan  # counted nowhere
    if K > 1:
        h0 = VectorHistogram(first, bins)
        x[-1, 1] = h0.low[1]  # the range's low edge: bin 0; its high edge: over
        x[0, -1] = h0.high[-1]
    fast, ref = (VectorHistogram(first, bins) for _ in range(2))
    fast.add(first)
    ref.add_reference(first)
    fast.add(x)
    fast.add(x[: max(1, n // 2)])  # twice: the width is formed once and reused
    ref.add_reference(x)
    ref.add_reference(x[: max(1, n // 2)])
    assert np.array_equal(fast.counts, ref.counts) and np.array_equal(fast.under, ref.under)
    assert np.array_equal(fast.over, ref.over)
    total = fast.counts.sum(axis=1) + fast.under + fast.over  # every finite value counted once
    assert np.array_equal(total, np.isfinite(np.concatenate([first, x, x[: max(1, n // 2)]])).sum(axis=0))


def _moments_equal(m, r):
    return m.n == r.n and all(same_bits(getattr(m, f), getattr(r, f)) for f in ("mean", "m2", "minimum", "maximum"))


@pytest.mark.parametrize("K,n", [(1, 1), (11, 64), (11, 17), (3, 129), (2, 1000), (7, 8), (3, 20011)])
def test_moments_of_rows_and_merges_are_numpys_bit_for_bit(K, n):
    rows = RNG.standard_normal((K, n)) * 10.0 ** RNG.uniform(-3, 3, (K, 1)) + 5
    rows[0, n // 2] = np.nan if K > 2 else rows[0, n // 2]
    m, r = Moments.of_rows(rows), Moments.of_rows_reference(rows)
    assert _moments_equal(m, r)
    view = rows[:, : max(1, n // 2)]  # a block cut to a run's last trials: rows of a view
    assert _moments_equal(Moments.of_rows(view), Moments.of_rows_reference(view))
    other = Moments.of_rows(RNG.standard_normal((K, 5)))
    assert _moments_equal(m.merge(other), r.merge_reference(other))
    assert _moments_equal(other.merge(m), other.merge_reference(r))
    if K > 1:  # each merged series is the pooled series' moments (independently: fsum, two passes)
        a, b = rows[1].tolist(), RNG.standard_normal(7).tolist()
        mm = Moments.of_rows(np.array([a])).merge(Moments.of_rows(np.array([b])))
        mu = math.fsum(a + b) / len(a + b)
        assert mm.mean[0] == pytest.approx(mu, rel=1e-13, abs=1e-13)
        assert mm.m2[0] == pytest.approx(math.fsum((v - mu) ** 2 for v in a + b), rel=1e-12)


def test_minima_maxima_and_merges_resolve_ties_and_nan_as_numpy():
    # 0.0 and -0.0 compare equal: numpy keeps the later value of a reduction and the second operand of minimum/maximum
    x = np.array([[0.0, -0.0, 1.0, np.nan], [-0.0, 0.0, np.nan, 1.0], [0.0, -0.0, 2.0, 3.0]])
    for m, r in ((Moments.of(x), Moments.of_reference(x)),):
        assert _moments_equal(m, r)
    a, b = Moments.of(x[:2]), Moments.of(x[1:])
    assert _moments_equal(a.merge(b), a.merge_reference(b)) and _moments_equal(b.merge(a), b.merge_reference(a))
    s_kernel, s_ref = {}, {}
    D = np.array([[[0.0, -0.0, 0.0], [-0.0, 0.0, -0.0]]])
    _, _, whole = compensation_figures(D, 1000.0, s_kernel)
    _, _, whole_r = compensation_figures_reference(D, 1000.0, s_ref)
    assert all(same_bits(whole[k], whole_r[k]) for k in whole_r) and all(same_bits(s_kernel[k], s_ref[k]) for k in s_ref)


def test_comoments_merge_kernel_is_the_reference_bit_for_bit():
    a, b = CoMoments.of(RNG.standard_normal((64, 75, 3))), CoMoments.of(RNG.standard_normal((3, 75, 3)) * 4)
    for x, y in ((a, b), (b, a)):
        m, r = x.merge(y), x.merge_reference(y)
        assert m.n == r.n and same_bits(m.mean, r.mean) and same_bits(m.C, r.C)


def test_the_cache_holds_the_kernels_once_called():
    """What the first-run note (cli._first_run_note) asks: after a call of each, numba's cache holds them."""
    from mtbudget import kernels_stats

    x = RNG.standard_normal((4, 3, 3))
    compensation_figures(x, 1.0, {})
    a, b = Moments.of(x[:, :, 0].copy()), CoMoments.of(x)
    Moments.of_rows(x[:, :, 0].T.copy())
    a.merge(a), b.merge(b)
    from mtbudget.stats import VectorHistogram

    VectorHistogram(x[:, :, 0].copy()).add(x[:, :, 0].copy())
    assert kernels_stats.compiled_here() in (True, None)


def test_an_older_numpy_keeps_its_own_sums_of_long_series(monkeypatch):
    """numpy up to 2.2 summed a contiguous run of more than 8192 values by buffers (the reviewer measured 1.26.4 and
    2.2.6): there the callers must take the numpy formulations for such series, not the kernels' one pairwise tree.
    The dispatch is checked with a kernel that cannot be called."""
    import mtbudget.kernels_stats as ks
    from mtbudget import engine

    def refuse(*a):
        raise AssertionError("the kernel was called for a long series under an older numpy")

    monkeypatch.setattr(ks, "LIKE_NUMPY", False)
    monkeypatch.setattr(ks, "moments_rows", refuse)
    monkeypatch.setattr(ks, "compensation_figures", refuse)
    rows = RNG.standard_normal((2, ks.BUFFER + 1))
    assert _moments_equal(Moments.of_rows(rows), Moments.of_rows_reference(rows))
    D = RNG.standard_normal((2, ks.BUFFER + 1, 3))
    s, s_ref = {}, {}
    comp, e, _ = engine.compensation_figures(D, 1000.0, s)
    comp_r, e_r, _ = engine.compensation_figures_reference(D, 1000.0, s_ref)
    assert same_bits(comp, comp_r) and same_bits(e, e_r)
    with pytest.raises(AssertionError, match="long series"):  # a short series still takes the kernel
        Moments.of_rows(rows[:, :100])


@pytest.mark.slow
def test_a_short_run_compiles_every_kernel_the_first_run_note_looks_for(tmp_path):
    """On a fresh cache, a short run compiles every kernel of KERNELS (kernels and kernels_stats): the note is then
    not shown again.  (histogram_add was looked for too, and only runs of ~11 000 trials compile it: a machine that
    never ran one was told of a compilation at every command.)  Slow: it compiles every kernel (~20 s)."""
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), OPENBLAS_NUM_THREADS="1")
    subprocess.run([sys.executable, "-m", "mtbudget", "run", "--trials", "200", "--quiet", "--log",
                    str(tmp_path / "r.mcap")], check=True, env=env, cwd=tmp_path, capture_output=True)
    out = subprocess.run([sys.executable, "-c", "from mtbudget import kernels, kernels_stats; "
                          "print(kernels.compiled_here(), kernels_stats.compiled_here())"],
                         check=True, env=env, capture_output=True, text=True).stdout.split()
    assert out == ["True", "True"], out
