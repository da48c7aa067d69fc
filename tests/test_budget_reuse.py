"""The budget does not recompute what it already has: the run's first trials ("all sources") and the one nominal
block ("no source").  Every table must be what computing each row block by block gives, bit for bit."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mtbudget.budget import attribution
from mtbudget.config import load_config
from mtbudget.engine import Engine
from mtbudget.executors import one_blas_thread
from mtbudget.outputs import SCALARS
from mtbudget.runner import run
from mtbudget.scenario import build_scenario

SMALL = Path(__file__).parent / "data" / "small.toml"


@pytest.fixture(scope="module")
def small():
    return load_config(SMALL)


def counting(monkeypatch):
    """Record every Engine.run_blocks call: (blocks, names of the active sources or None for all)."""
    calls = []
    orig = Engine.run_blocks

    def run_blocks(self, blocks, active=None):
        calls.append((tuple(blocks), None if active is None else tuple(s.name for s in active)))
        return orig(self, blocks, active)

    monkeypatch.setattr(Engine, "run_blocks", run_blocks)
    return calls


def same(a, b):
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def row_by_row(eng, n, active, chunk=4):
    """A budget row computed independently: every block of the first n trials, with these sources, in one call per
    chunk, cut to n trials; per output its variance, mean square and mean."""
    nb = math.ceil(n / eng.block)
    with one_blas_thread():
        res = [r for i in range(0, nb, chunk) for r in eng.run_blocks(list(range(i, min(nb, i + chunk))), active)]
    out = {}
    for o in SCALARS:
        y = np.concatenate([r.scalars[o] for r in res])[:n]
        out[o] = {"variance": float(np.var(y, ddof=1)), "mean_square": float(np.mean(y**2)), "mean": float(y.mean())}
    return out


@pytest.mark.parametrize("trials, n, block", [(80, 40, 16), (40, 64, 16), (50, 50, 8), (48, 20, 16)])
def test_the_all_sources_row_is_the_runs_own_trials_bit_for_bit(small, monkeypatch, trials, n, block):
    eng = Engine(build_scenario(small), block=block, seed=3)
    calls = counting(monkeypatch)
    res = run(engine=eng, trials=trials, attribution_trials=n)
    names = tuple(s.name for s in eng.sources)
    assert not [c for c in calls if c[1] == names], "the budget recomputed the run's own trials"
    # the same budget with the all-sources row computed as before, block by block
    res.prefix = None
    again = attribution(eng, res, min(n, trials), chunk_blocks=3)
    assert any(c[1] == names for c in calls)
    assert same(res.budget, again)
    # and against an independent computation of the row
    total = row_by_row(eng, min(n, trials), None)
    for o in SCALARS:
        basis = res.budget[o]["basis"]
        assert res.budget[o]["total"] == total[o][basis]


def test_an_adaptive_run_reuses_its_first_trials_too(small, monkeypatch):
    eng = Engine(build_scenario(small), block=16, seed=2)
    calls = counting(monkeypatch)
    res = run(engine=eng, trials=None, adaptive_batch=32, max_trials=64, attribution_trials=40)
    names = tuple(s.name for s in eng.sources)
    assert not [c for c in calls if c[1] == names]
    res.prefix = None
    assert same(res.budget, attribution(eng, res, 40))


def test_the_no_source_row_is_one_block_and_equals_every_block_computed(small, monkeypatch):
    eng = Engine(build_scenario(small), block=16, seed=9)
    calls = counting(monkeypatch)
    res = run(engine=eng, trials=64, attribution_trials=56)
    nominal_calls = [c for c in calls if c[1] == ()]
    assert nominal_calls == [((0, 1), ())], nominal_calls
    ref = row_by_row(eng, 56, [])  # every block without any source
    for o in SCALARS:
        t = res.budget[o]
        assert t["nominal"] == ref[o][t["basis"]] and t["nominal_value"] == ref[o]["mean"], o


def test_blocks_that_differ_without_sources_are_all_computed(small, monkeypatch):
    """Should a block ever depend on its index without any source, every block is computed (never replicated)."""
    eng = Engine(build_scenario(small), block=16, seed=9)
    orig = Engine.run_blocks

    def run_blocks(self, blocks, active=None):
        out = orig(self, blocks, active)
        if active is not None and not active:
            for r in out:
                r.scalars = {k: v + 1e-6 * r.block for k, v in r.scalars.items()}
        return out

    monkeypatch.setattr(Engine, "run_blocks", run_blocks)
    res = run(engine=eng, trials=64, attribution_trials=56)
    ref = {o: np.concatenate([eng.run_block(b, []).scalars[o] for b in range(4)])[:56] for o in SCALARS}
    for o in SCALARS:
        assert res.budget[o]["nominal_value"] == float(ref[o].mean()), o
        if o == "chi2_per_dof":
            assert res.budget[o]["nominal"] == float(np.var(ref[o], ddof=1)) > 0


def test_a_resumed_run_computes_the_all_sources_row_itself(small, tmp_path, monkeypatch):
    """Blocks taken from a log may come from another mtbudget: the budget does not build on them."""
    from mtbudget.runlog import read_runlog
    from mtbudget.runner import _block_results, execute

    log = tmp_path / "r.mcap"
    full = execute(SMALL, trials=64, block=16, attribution_trials=32, log_path=log)
    kept = _block_results(read_runlog(log).blocks[:2])
    eng = Engine(build_scenario(small), block=16, seed=full.spec["seed"])
    calls = counting(monkeypatch)
    resumed = run(engine=eng, trials=64, attribution_trials=32, resume_blocks=kept)
    names = tuple(s.name for s in eng.sources)
    assert any(c[1] == names for c in calls)
    assert same(resumed.budget, full.budget)


def test_the_process_executor_budget_is_the_inline_one(small):
    a = run(small, trials=48, block=16, attribution_trials=40, seed=4)
    b = run(small, trials=48, block=16, attribution_trials=40, seed=4, executor="process", workers=2)
    assert same(a.budget, b.budget)
    assert a.prefix is None and b.prefix is None  # released after the budget


def test_the_budget_runs_on_the_runs_executor(small, monkeypatch):
    """No second pool: the run's workers have built the engine already."""
    import mtbudget.budget as budget

    def refuse(*args, **kwargs):
        raise AssertionError("the budget started an executor of its own")

    monkeypatch.setattr(budget, "Executor", refuse)
    a = run(small, trials=32, block=16, attribution_trials=32, seed=4, executor="process", workers=2)
    assert a.budget["compensation_rms"]["rows"]
