"""Scale-out: several blocks identified together, worker processes, an existing Dask scheduler, in-code sources.

The promise (docs/architecture.md, docs/performance.md): a block's numbers depend on the seed, the block and
the sources only, never on which blocks are computed with it or where.
"""

from pathlib import Path

import numpy as np
import pytest

from mtbudget.config import load_config
from mtbudget.engine import Engine
from mtbudget.errors import ConfigError
from mtbudget.executors import one_blas_thread
from mtbudget.outputs import SCALARS
from mtbudget.plugins import PluginHost
from mtbudget.runner import run
from mtbudget.scenario import build_scenario

from conftest import OffsetSource, plugin_module

SMALL = Path(__file__).parent / "data" / "small.toml"


@pytest.fixture(scope="module")
def small():
    return load_config(SMALL)


def same_block(a, b):
    return (a.block == b.block and a.n == b.n and a.not_converged == b.not_converged and a.fallbacks == b.fallbacks
            and all(np.array_equal(a.scalars[k], b.scalars[k]) for k in SCALARS)
            and np.array_equal(a.point_error, b.point_error) and np.array_equal(a.parameters, b.parameters)
            and np.array_equal(a.components, b.components))


@pytest.mark.parametrize("block", [1, 3, 16])
def test_blocks_identified_together_equal_each_block_alone(small, block):
    # block 1: every identification group holds one trial (BLAS's single-row path); 3: odd row counts
    eng = Engine(build_scenario(small), block=block, seed=11)
    with one_blas_thread():
        alone = {b: eng.run_block(b) for b in range(6)}
        for group in ([0, 1, 2, 3, 4, 5], [5, 2], [3], [1, 4, 0]):
            for r in eng.run_blocks(group):
                assert same_block(r, alone[r.block]), (group, r.block)


def test_blocks_together_also_with_a_source_subset_and_the_default_configuration():
    sc = build_scenario(load_config())
    eng = Engine(sc, block=8, seed=5)
    act = [s for s in eng.sources if s.name in ("tracker_noise", "phase_sequence", "repeatability")]
    with one_blas_thread():
        together = eng.run_blocks([2, 0, 1], act)
        for r in together:
            assert same_block(r, eng.run_block(r.block, act))
    # and the subset really is a different run (common random numbers, not the same numbers)
    assert not np.array_equal(together[0].point_error, eng.run_block(2).point_error)


def test_worker_threads_run_the_default_configuration_block_for_block_as_in_process():
    """The thread executor on the paper's configuration (75 points, every source), chunks of one and two blocks on two
    threads, all sources and then a subset: each block equals the inline engine's run of that block alone."""
    from mtbudget.executors import Executor
    from mtbudget.runner import RunSettings, make_spec

    eng = Engine(build_scenario(load_config()), block=8, seed=5)
    spec = make_spec(eng.scenario, eng, RunSettings())
    subset = ["tracker_noise", "phase_sequence", "repeatability"]
    with Executor(eng, spec, "thread", 2) as ex:
        threaded = {None: [r for ch in ex.map([[0], [1, 2], [3], [4, 5]]) for r in ch],
                    "subset": [r for ch in ex.map([[5], [2, 0], [1]], subset) for r in ch]}
    with one_blas_thread():
        for r in threaded[None]:
            assert same_block(r, eng.run_block(r.block)), r.block
        act = [s for s in eng.sources if s.name in subset]
        for r in threaded["subset"]:
            assert same_block(r, eng.run_block(r.block, act)), r.block
    assert [r.block for r in threaded[None]] == [0, 1, 2, 3, 4, 5]  # in chunk order, whichever thread finished first


def test_the_thread_executor_holds_blas_to_one_thread_while_it_is_open_and_gives_it_back():
    """OpenBLAS (numpy's wheels: pthreads) has one process-wide pool: the executor limits it from the thread that
    opens it, and the worker threads see that limit; closing it restores what was there."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from mtbudget.executors import Executor

    def blas_threads():
        return {i["internal_api"]: i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"}

    eng = Engine(build_scenario(load_config(SMALL)), block=4, seed=1)
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        if not before or set(before.values()) != {2}:
            pytest.skip(f"this BLAS cannot be set to two threads here: {before}")
        ex = Executor(eng, {"config": load_config(SMALL).source, "config_path": str(SMALL), "seed": 1, "block": 4,
                            "sources": [s.name for s in eng.sources]}, "thread", 2)
        try:
            assert set(blas_threads().values()) == {1}
            seen = ex.threads.pool.submit(blas_threads).result()  # what a worker thread's BLAS calls get
            assert set(seen.values()) == {1}, seen
            assert [r.block for ch in ex.map([[0], [1]]) for r in ch] == [0, 1]
        finally:
            ex.close()
        assert blas_threads() == before


def test_auto_runs_short_runs_inline_and_long_ones_on_every_core(small, monkeypatch):
    from mtbudget import executors

    eng = Engine(build_scenario(small), block=16, seed=1)
    monkeypatch.setattr(executors, "default_workers", lambda: 2)
    assert executors.auto_executor(eng, None, executors.AUTO_MIN_TRIALS - 1) == ("inline", None)
    assert executors.auto_executor(eng, None, executors.AUTO_MIN_TRIALS) == (executors.AUTO_PARALLEL, 2)
    assert executors.auto_executor(eng, 3, None) == (executors.AUTO_PARALLEL, 3)  # adaptive: many trials
    assert executors.auto_executor(eng, 1, None) == ("inline", None)  # --workers 1: one core
    monkeypatch.setattr(executors, "default_workers", lambda: 64)
    assert executors.auto_executor(eng, None, 10**6) == (executors.AUTO_PARALLEL, executors.AUTO_MAX_WORKERS)
    monkeypatch.setattr(executors, "default_workers", lambda: 1)
    assert executors.auto_executor(eng, None, 10**6) == ("inline", None)  # a one-core machine
    monkeypatch.setattr(executors, "default_workers", lambda: 2)
    coded = Engine(build_scenario(small, _in_code_host(), ["tracker_noise", "in_code_offset"]), block=16, seed=1)
    assert executors.auto_executor(coded, None, 10**6) == ("inline", None)  # workers could not rebuild it
    res = run(small, trials=32, block=16, attribution_trials=0, executor="auto")
    assert res.executor == {"kind": "inline", "workers": 1, "requested": "auto"}
    monkeypatch.setattr(executors, "AUTO_MIN_TRIALS", 16)
    a = run(small, trials=48, block=16, attribution_trials=0, executor="auto", workers=2)
    assert a.executor == {"kind": executors.AUTO_PARALLEL, "workers": 2, "requested": "auto"}
    b = run(small, trials=48, block=16, attribution_trials=0)
    assert np.array_equal(a.acc.scalar_samples("compensation_rms"), b.acc.scalar_samples("compensation_rms"))


def test_a_run_on_threads_is_logged_and_verifies_bit_for_bit(small, tmp_path):
    from mtbudget.runner import execute, verify

    res = execute(small, trials=48, block=16, attribution_trials=0, executor="thread", workers=2,
                  log_path=tmp_path / "t.mcap")
    inline = run(small, trials=48, block=16, attribution_trials=0)
    assert np.array_equal(res.acc.scalar_samples("compensation_rms"), inline.acc.scalar_samples("compensation_rms"))
    v = verify(tmp_path / "t.mcap")
    assert v["identical"] and v["trials"] == 48, v


def test_a_multiprocess_dask_cluster_at_an_address_gives_the_numbers_of_the_inline_run(small):
    distributed = pytest.importorskip("dask.distributed", reason="the dask extra is not installed")
    inline = run(small, trials=48, block=16, attribution_trials=16)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        remote = run(small, trials=48, block=16, attribution_trials=16, executor="dask", address=cl.scheduler_address)
    for k in SCALARS:
        assert np.array_equal(inline.acc.scalar_samples(k), remote.acc.scalar_samples(k)), k
    assert np.array_equal(inline.acc.moments["point_error"].mean, remote.acc.moments["point_error"].mean)
    for name, row in inline.budget.items():
        assert row == remote.budget[name], name


class InCode(OffsetSource):
    """A source that exists only in the process that registered it."""

    name = "in_code_offset"


def _in_code_host():
    return PluginHost(plugins=(plugin_module("in_code_plugin", lambda register: register(InCode())),))


def test_a_source_registered_in_code_runs_inline(small):
    res = run(small, trials=16, block=16, attribution_trials=0, host=_in_code_host(),
              sources=["tracker_noise", "in_code_offset"])
    assert res.spec["sources"] == ["tracker_noise", "in_code_offset"]


@pytest.mark.parametrize("executor", ["thread", "process", "dask"])
def test_a_source_registered_in_code_cannot_reach_workers_and_says_so(small, executor):
    if executor == "dask":
        pytest.importorskip("dask.distributed", reason="the dask extra is not installed")
    with pytest.raises(ConfigError, match=r"source 'in_code_offset' .*registered in code.*--executor inline"):
        run(small, trials=16, block=16, attribution_trials=0, host=_in_code_host(), executor=executor,
            sources=["tracker_noise", "in_code_offset"])


@pytest.mark.slow  # waits for the 10 s connection timeout
def test_an_address_where_no_scheduler_answers_is_one_clear_error(small):
    pytest.importorskip("dask.distributed", reason="the dask extra is not installed")
    with pytest.raises(ConfigError, match="no Dask scheduler answers at 'tcp://127.0.0.1:9'"):
        run(small, trials=16, block=16, attribution_trials=0, executor="dask", address="tcp://127.0.0.1:9")


def test_workers_get_a_bounded_window_of_chunks_and_results_come_back_in_order():
    from concurrent.futures import Future

    from mtbudget.executors import in_order

    outstanding, most = [], [0]

    def submit(ch):
        f = Future()
        f.set_result(ch * 10)
        outstanding.append(f)
        most[0] = max(most[0], sum(not getattr(g, "_taken", False) for g in outstanding))
        return f

    out = []
    for r in in_order(submit, list(range(50)), window=4):
        out.append(r)
        for g in outstanding:  # what has been handed over is no longer held by the executor
            if g.result() == r:
                g._taken = True
    assert out == [c * 10 for c in range(50)]
    assert most[0] == 5  # the window plus the one being handed over, never the whole run


def test_worker_processes_end_when_the_run_is_killed_hard(tmp_path):
    """A run killed with SIGKILL cannot shut its pool down: its worker processes notice and end (they stayed,
    orphaned, before)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "run.py"
    script.write_text(
        "import os, sys\n"
        "from mtbudget.config import load_config\n"
        "from mtbudget.engine import Engine\n"
        "from mtbudget.executors import Executor\n"
        "from mtbudget.runner import RunSettings, make_spec\n"
        "from mtbudget.scenario import build_scenario\n"
        f"cfg = load_config({str(SMALL)!r})\n"
        "eng = Engine(build_scenario(cfg), block=4, seed=1)\n"
        "ex = Executor(eng, make_spec(eng.scenario, eng, RunSettings()), 'process', 2)\n"
        "list(ex.map([[0], [1], [2], [3]]))\n"
        "print(' '.join(str(p) for p in ex.pool._processes), flush=True)\n"
        "sys.stdin.read()\n")
    proc = subprocess.Popen([sys.executable, str(script)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    workers = [int(p) for p in proc.stdout.readline().split()]
    assert workers
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 15
    alive = workers
    while alive and time.monotonic() < deadline:
        time.sleep(0.2)
        alive = [p for p in alive if os.path.exists(f"/proc/{p}") and
                 open(f"/proc/{p}/stat").read().split(")")[-1].split()[0] != "Z"]
    assert not alive, f"worker processes {alive} outlived the killed run"
