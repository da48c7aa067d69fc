"""The run's statistics merged with fewer numpy calls: every number as the per-output computation gives it.

Each check compares with a computation that does not go through the code under test: numpy on the concatenated
values, per-output moments and histograms built one output at a time, JSON serialised once more.
"""

import json
import zlib

import numpy as np
import pytest

from mtbudget.outputs import BlockResult
from mtbudget.runlog import _with_crc
from mtbudget.stats import Accumulator, Moments, VectorHistogram, interval_indices

NAMES = ("a", "b", "c", "d")


def random_blocks(seed, sizes, K=12):
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate(sizes):
        scalars = {k: rng.normal(j * 3.0, 10.0 ** (j - 1), n) for j, k in enumerate(NAMES)}
        out.append((i, n, scalars, rng.normal(size=(n, K))))
    return out


@pytest.mark.parametrize("seed", range(40))
def test_moments_of_rows_are_each_row_alone_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    rows = rng.normal(rng.uniform(-5, 5), 10.0 ** rng.uniform(-3, 3), (7, n))
    if seed % 3 == 0:
        rows = rows[:, : max(1, n // 2)]  # a cut block: rows of a view
    m = Moments.of_rows(rows)
    for k in range(rows.shape[0]):
        ref = Moments.of(np.array(rows[k])[:, None])  # one output alone, as a column, in a fresh array
        got = m.row(k)
        for f in ("mean", "m2", "minimum", "maximum"):
            assert getattr(got, f).tobytes() == np.asarray(getattr(ref, f)).tobytes(), (k, f)


@pytest.mark.parametrize("keep", [True, False])
def test_scalar_statistics_match_numpy_and_per_output_merges(keep):
    blocks = random_blocks(1, [64, 64, 17, 64, 1, 64])
    acc = Accumulator(keep_samples=keep, keep_vector_samples=True)
    ref_m, ref_h = {}, {}
    for b, n, sc, _ in blocks:
        acc.add(b, n, sc, {})
        for k, v in sc.items():  # the per-output merge, one output at a time
            m = Moments.of(v[:, None])
            ref_m[k] = m if k not in ref_m else ref_m[k].merge(m)
            if k not in ref_h:
                ref_h[k] = VectorHistogram(v[:, None])
            ref_h[k].add(v[:, None])
    assert acc.n == sum(n for _, n, _, _ in blocks)
    p = 0.95
    for k in NAMES:
        y = np.concatenate([sc[k] for _, _, sc, _ in blocks])
        s = acc.summary(k, p)
        assert s["mean"] == pytest.approx(y.mean(), rel=1e-12, abs=1e-12)
        assert s["std"] == pytest.approx(y.std(ddof=1), rel=1e-12)
        assert s["mean"] == float(ref_m[k].mean[0]) and s["std"] == float(ref_m[k].std[0])  # bit for bit
        assert s["n"] == y.size
        if keep:
            ys = np.sort(y)
            M = ys.size
            r, q = interval_indices(M, p)
            assert s["symmetric"] == (ys[r], ys[r + q])
            w = ys[q:] - ys[: M - q]
            i = int(np.argmin(w))
            assert s["shortest"] == (ys[i], ys[i + q])
        else:
            lo, hi = ref_h[k].quantiles(np.array([(1 - p) / 2, (1 + p) / 2]))[0]
            assert s["symmetric"] == (lo, hi) and not s["exact_intervals"]
            # the shortest from the same counts (VectorHistogram.shortest: tests/test_run_ux.py against closed forms)
            assert s["shortest"] == tuple(ref_h[k].shortest(p)[0])


def test_a_summary_follows_the_blocks_merged_after_it():
    blocks = random_blocks(2, [32, 32, 32])
    acc = Accumulator()
    acc.add(*blocks[0][:3], {})
    first = acc.summary("a", 0.9)
    acc.add(*blocks[1][:3], {})
    acc.add(*blocks[2][:3], {})
    later = acc.summary("a", 0.9)
    y = np.concatenate([sc["a"] for _, _, sc, _ in blocks])
    assert later["n"] == 96 and first["n"] == 32 and later["mean"] == pytest.approx(y.mean(), rel=1e-12)
    later["mean"] = -1.0  # a caller's copy: the accumulator's answer does not change
    assert acc.summary("a", 0.9)["mean"] == pytest.approx(y.mean(), rel=1e-12)


def test_per_component_intervals_are_the_order_statistics_of_every_column():
    blocks = random_blocks(3, [64, 64, 9, 64], K=30)
    acc = Accumulator(keep_samples=True, keep_vector_samples=True)
    for b, n, sc, v in blocks:
        acc.add(b, n, sc, {}, vectors={"v": v})
    y = np.sort(np.concatenate([v for *_, v in blocks]), axis=0)
    M = y.shape[0]
    for p in (0.95, 0.5):
        r, q = interval_indices(M, p)
        r = min(r, M - q - 1)
        iv = acc.vector_intervals("v", p)
        assert np.array_equal(iv["low"], y[r]) and np.array_equal(iv["high"], y[r + q])
        for j in range(y.shape[1]):
            w = y[q:, j] - y[: M - q, j]
            i = int(np.argmin(w))
            assert iv["shortest_low"][j] == y[i, j] and iv["shortest_high"][j] == y[i + q, j]


def test_a_blocks_moments_are_computed_once_and_a_cut_block_has_its_own():
    rng = np.random.default_rng(4)
    n, M0 = 16, 5
    comp = rng.normal(size=(n, M0, 3))
    b = BlockResult(0, n, {"x": rng.normal(size=n)}, rng.normal(size=(n, M0)), rng.normal(size=(n, 4)),
                    components=comp)
    vm = b.vector_moments()
    assert b.vector_moments()["components"] is vm["components"]  # computed once
    assert b.component_comoments() is vm["components"]
    cut = b.truncated(5)
    cm = cut.vector_moments()["components"]
    d = comp[:5] - comp[:5].mean(axis=0)
    assert cm.n == 5 and np.allclose(cm.C, np.einsum("nki,nkj->kij", d, d), rtol=1e-13, atol=1e-13)
    assert np.allclose(cut.vector_moments()["point_error"].mean, b.point_error[:5].mean(axis=0), rtol=1e-14)
    assert not np.allclose(cm.C, vm["components"].C)


@pytest.mark.parametrize("body", [{}, {"a": 1}, {"crc32": 7, "b": [1.5, None]}, {"t": "é \u2603", "nan": float("nan")},
                                  {"block": 3, "scalars": {"x": {"dtype": "<f8", "data": "AAAA"}}, "n": 2}])
def test_a_message_is_serialised_once_with_the_same_bytes(body):
    topic = "/mtbudget/blocks"
    rest = {k: v for k, v in body.items() if k != "crc32"}
    crc = zlib.crc32(json.dumps(rest).encode(), zlib.crc32(topic.encode() + b"\n"))
    assert _with_crc(topic, body) == json.dumps({**rest, "crc32": crc}).encode()
    assert json.loads(_with_crc(topic, body))["crc32"] == crc


def test_compiled_histogram_counts_as_the_numpy_formulation():
    """VectorHistogram.add (compiled) against add_reference (numpy): the same counts, underflow and overflow for
    values inside, below, above, on the edges of the range, and NaN (counted nowhere by either)."""
    rng = np.random.default_rng(11)
    first = rng.normal(0.0, 1.0, (64, 5))
    a, b = VectorHistogram(first), VectorHistogram(first)
    for x in (rng.normal(0.0, 1.0, (64, 5)), rng.normal(0.0, 3.0, (64, 5)),
              np.array([a.low, a.high, np.nextafter(a.high, -np.inf), np.full(5, np.nan)])):
        a.add(x)
        with np.errstate(invalid="ignore"):  # NaN cast to a bin number (then dropped): numpy warns, counts nothing
            b.add_reference(x)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.under, b.under)
    np.testing.assert_array_equal(a.over, b.over)
    assert a.over.sum() > 0 and a.under.sum() > 0
