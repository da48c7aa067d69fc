"""Where blocks of trials run: in this process, on threads of this process, in a local process pool, or on a
Dask cluster.

Workers rebuild the engine from a JSON spec (configuration, seed, block
size, sources): nothing is pickled but plain data, and a worker's blocks are
bit-identical to the same blocks run in process (the random streams depend
on seed, block and source only).

Threads (``thread``): each worker thread rebuilds its own engine from the same spec (its own scenario, sources,
identification models and their plan caches, about 1.5 MB and 15 ms each), so no engine state is shared between
threads and nothing in the hot path takes a lock; the engines are built one at a time (pint's registry and the
plugins' ``configure`` are not promised to be thread-safe).  What the threads still share is read-only or
memoising module state (the unit registry, ``identify``'s plan cache dictionary keyed per model object, the CRC
of source names, compiled kernels).  The kernels are compiled ``nogil`` and numpy releases the GIL inside its
larger loops, so threads overlap there; the identification's Python and small numpy operations hold it
(docs/performance.md, "Executors on two cores").  One process: numpy, pint, numba and the engine are loaded
once.
"""

from __future__ import annotations

import json
import os

from .errors import ConfigError

EXECUTORS = ("auto", "inline", "thread", "process", "dask")

#: ``auto``: the trials a run computes (its own and its budget's) from which it uses several cores, the executor it
#: uses them with, and at most how many workers (default: the cores, up to this); below, on one core, or with a
#: source registered in code, it runs inline.  Chosen by measurement (docs/performance.md, "Executors on two
#: cores"): with the compiled chord, two threads run the engine 1.45-1.5x as fast as one on two idle cores (two
#: processes 1.7x), and 10^6 trials with the budget in 55 s within 300 MB (2026-11-26; 73 s before the identification,
#: the simulation and the merge were made cheaper), where two processes took 58 s and 557 MB (378 MB PSS);
#: threads leave no worker behind when a run is killed.  Each thread adds its engine's
#: working set (about 35 MB) and the GIL limits how many help: not measured beyond two cores, hence the cap.
AUTO_MIN_TRIALS = 20_000
AUTO_PARALLEL = "thread"
AUTO_MAX_WORKERS = 4


def engine_from_spec(spec: dict):
    """Rebuild an engine from a JSON-able spec (used by process pools, Dask workers and replay --verify)."""
    from .config import parse_config
    from .engine import Engine
    from .scenario import build_scenario

    cfg = parse_config(spec["config"], spec.get("config_path"))
    return Engine(build_scenario(cfg, sources=spec.get("sources")), block=spec["block"], seed=spec["seed"])


def one_blas_thread():
    """A context in which BLAS uses one thread: the engine's matrices are small (a few hundred rows), and on a
    shared or busy machine a second BLAS thread makes them 10-100x slower, never faster (docs/performance.md).

    Its scope is the library's: OpenBLAS built with pthreads (numpy's wheels) has one process-wide pool, which
    threadpoolctl (>= 3.8) lets only one "controlling" thread limit (other threads' calls do nothing); MKL and
    OpenBLAS on OpenMP limit the calling thread only.  The thread executor therefore limits in the thread that
    opens it (for as long as it is open) and again in each worker thread around every chunk."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def default_workers() -> int:
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` where that is not known)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


_WORKER_CACHE: dict = {}


#: the distribution a plugin registered in code (``PluginHost(plugins=...)``) is stamped with
IN_CODE = "(registered in code)"


def _rebuild(spec_json: str):
    """The engine of ``spec_json``, rebuilt where a worker runs; a configuration it cannot rebuild is one error."""
    try:
        return engine_from_spec(json.loads(spec_json))
    except ConfigError as exc:
        import socket

        raise ConfigError(f"a worker on {socket.gethostname()} could not rebuild the engine: {exc} (workers "
                          "rebuild it from the configuration and the plugins installed where they run: "
                          "install the same plugins there)", key="executor") from None


def _worker_blocks(eng, blocks: list, active: list | None) -> list:
    """``blocks`` run on a worker's engine, with the moments the main process merges computed there."""
    act = None if active is None else [s for s in eng.sources if s.name in active]
    results = eng.run_blocks(blocks, act)
    # the moments the main process merges, computed here rather than there: the main process merges, logs and
    # histograms every worker's blocks, so work moved off it keeps it from holding up the workers
    for r in results:
        if active is None:  # a run: every vector output's moments (merged and logged)
            r.vector_moments()
        else:  # the budget: only the per-point components' co-moments
            r.component_comoments()
    return results


def run_blocks_from_spec(spec_json: str, blocks: list, active: list | None = None) -> list:
    """Worker entry point: run ``blocks`` of the engine described by ``spec_json``."""
    with one_blas_thread():  # the engine built and run with one BLAS thread, as in process: bit-identical
        eng = _WORKER_CACHE.get(spec_json)
        if eng is None:
            eng = _rebuild(spec_json)
            _WORKER_CACHE.clear()
            _WORKER_CACHE[spec_json] = eng
        return _worker_blocks(eng, blocks, active)


def exit_with_parent(every: float = 1.0) -> None:
    """In a worker process: end it when the process that started it is gone.  A run killed hard (``kill -9``, the
    out-of-memory killer) cannot shut its pool down, and its workers, waiting for work that never comes, would
    otherwise stay (measured: orphaned, sleeping, holding their memory).  The parent is the one seen at the start:
    the run (fork, spawn) or the fork server, which ends with the run (forkserver)."""
    import threading
    import time

    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(every)
        os._exit(1)

    threading.Thread(target=watch, name="mtbudget-parent-watch", daemon=True).start()


class _ThreadWorkers:
    """Worker threads of this process, each with its own engine rebuilt from the spec (see the module docstring)."""

    def __init__(self, spec_json: str, workers: int):
        import threading
        from concurrent.futures import ThreadPoolExecutor

        self.spec_json = spec_json
        self.local = threading.local()
        self.build_lock = threading.Lock()  # engines are built one at a time; never taken while blocks run
        # one BLAS thread for as long as the pool is open: OpenBLAS's pool is process-wide and only the thread that
        # limits it first can (threadpoolctl >= 3.8), so the limit is set here, in the thread that opens the pool
        self.blas = one_blas_thread()
        self.blas.__enter__()  # (closed in the same thread: threadpoolctl counts a thread's limits per thread)
        self.pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mtbudget-worker")

    def engine(self):
        eng = getattr(self.local, "engine", None)
        if eng is None:
            with self.build_lock:
                eng = self.local.engine = _rebuild(self.spec_json)
        return eng

    def run(self, blocks: list, active: list | None) -> list:
        with one_blas_thread():  # MKL and OpenBLAS on OpenMP limit per thread; OpenBLAS on pthreads: the pool's
            return _worker_blocks(self.engine(), blocks, active)

    def submit(self, blocks: list, active: list | None):
        return self.pool.submit(self.run, blocks, active)

    def close(self):
        try:
            self.pool.shutdown(wait=True, cancel_futures=True)
        finally:
            self.blas.__exit__(None, None, None)


def in_order(submit, chunks: list, window: int):
    """Results of ``submit(chunk)`` in chunk order, with at most ``window`` chunks in flight: memory is bounded by
    the window, not by the run (a finished chunk is released once it has been handed over)."""
    from collections import deque

    queue: deque = deque()
    for ch in chunks:
        queue.append(submit(ch))
        if len(queue) > window:
            yield queue.popleft().result()
    while queue:
        yield queue.popleft().result()


def check_sources_reach_workers(engine, kind: str) -> None:
    """Workers rebuild the engine from a JSON spec: by name, from the plugins installed where they run.  A source
    registered in code exists only in this process, so it cannot reach them: say so before any work is sent."""
    in_code = [s for s in engine.sources if getattr(s, "dist_name", "") == IN_CODE]
    if in_code:
        s = in_code[0]
        raise ConfigError(f"source {s.name!r} (plugin {s.plugin or '?'}) was registered in code; the {kind} executor's "
                          "workers rebuild the engine from the configuration and the plugins installed as entry "
                          "points, where it does not exist: publish it through the 'mtbudget' entry-point group of "
                          "a package installed on every worker, or run with --executor inline", key="executor")


def auto_executor(engine, workers: int | None, work: int | None) -> tuple[str, int | None]:
    """What ``--executor auto`` runs on: (kind, workers).  ``work``: the trials the run computes (None: many)."""
    cores = default_workers()
    in_code = any(getattr(s, "dist_name", "") == IN_CODE for s in engine.sources)
    if in_code or (workers or cores) < 2 or (work is not None and work < AUTO_MIN_TRIALS):
        return "inline", None
    return AUTO_PARALLEL, workers or min(cores, AUTO_MAX_WORKERS)


class Executor:
    """Runs chunks of blocks and yields their results in chunk order.

    ``work``: the trials the caller will run on it (``auto`` chooses by it, :func:`auto_executor`)."""

    def __init__(self, engine, spec: dict, kind: str = "inline", workers: int | None = None, address=None,
                 work: int | None = None):
        if kind not in EXECUTORS:
            raise ConfigError(f"unknown executor {kind!r}; expected one of {', '.join(EXECUTORS)}", key="executor")
        if kind == "auto":
            kind, workers = auto_executor(engine, workers, work)
        self.engine, self.kind = engine, kind
        if kind != "inline":
            check_sources_reach_workers(engine, kind)
        self.spec_json = json.dumps(spec, sort_keys=True, default=str)
        self.pool = self.client = self.cluster = self.threads = None
        self.n_workers = 1
        if kind == "thread":
            self.n_workers = workers or default_workers()
            self.threads = _ThreadWorkers(self.spec_json, self.n_workers)
        elif kind == "process":
            from concurrent.futures import ProcessPoolExecutor

            # forked on Linux: the libraries' pages shared with this process (docs/performance.md)
            self.pool = ProcessPoolExecutor(max_workers=workers or 2, initializer=exit_with_parent)
            self.n_workers = workers or 2
        elif kind == "dask":
            try:
                from dask.distributed import Client, LocalCluster
            except ImportError:
                raise ConfigError("the dask executor needs the optional extra: pip install 'mtbudget[dask]'") from None
            if address:
                try:
                    self.client = Client(address, timeout="10s")
                except (OSError, TimeoutError) as exc:
                    raise ConfigError(f"no Dask scheduler answers at {address!r} ({type(exc).__name__}: {exc})",
                                      key="address") from None
            else:  # worker processes, one thread each: numpy's small operations hold the GIL, threads would queue
                self.cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True,
                                            dashboard_address=None)
                self.client = Client(self.cluster)
            self.n_workers = max(1, sum(self.client.nthreads().values()))

    def map(self, chunks: list, active_names: list | None = None):
        """Yield the block results of each chunk, in chunk order."""
        if self.kind == "inline":
            act = None if active_names is None else [s for s in self.engine.sources if s.name in active_names]
            for ch in chunks:
                with one_blas_thread():
                    results = self.engine.run_blocks(ch, act)
                yield results
        elif self.kind == "thread":
            yield from in_order(lambda ch: self.threads.submit(ch, active_names), chunks, self.n_workers + 1)
        elif self.kind == "process":
            yield from in_order(lambda ch: self.pool.submit(run_blocks_from_spec, self.spec_json, ch, active_names),
                                 chunks, 2 * self.n_workers + 2)
        else:
            yield from in_order(lambda ch: self.client.submit(run_blocks_from_spec, self.spec_json, ch, active_names,
                                                               pure=False),
                                 chunks, 2 * self.n_workers + 2)

    def close(self):
        if self.threads:
            self.threads.close()
            self.threads = None
        if self.pool:
            self.pool.shutdown()
        if self.client:
            self.client.close()
        if self.cluster:
            self.cluster.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
