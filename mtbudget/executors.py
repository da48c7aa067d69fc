"""Where blocks of trials run: in this process, in a local process pool, or on a Dask cluster.

Workers rebuild the engine from a JSON spec (configuration, seed, block
size, sources): nothing is pickled but plain data, and a worker's blocks are
bit-identical to the same blocks run in process (the random streams depend
on seed, block and source only).
"""

from __future__ import annotations

import json

from .errors import ConfigError

EXECUTORS = ("inline", "process", "dask")


def engine_from_spec(spec: dict):
    """Rebuild an engine from a JSON-able spec (used by process pools, Dask workers and replay --verify)."""
    from .config import parse_config
    from .engine import Engine
    from .scenario import build_scenario

    cfg = parse_config(spec["config"], spec.get("config_path"))
    return Engine(build_scenario(cfg, sources=spec.get("sources")), block=spec["block"], seed=spec["seed"])


def one_blas_thread():
    """A context in which BLAS uses one thread: the engine's matrices are small (a few hundred rows), and on a
    shared or busy machine a second BLAS thread makes them 10-100x slower, never faster (docs/performance.md)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


_WORKER_CACHE: dict = {}


def run_blocks_from_spec(spec_json: str, blocks: list, active: list | None = None) -> list:
    """Worker entry point: run ``blocks`` of the engine described by ``spec_json``."""
    with one_blas_thread():  # the engine built and run with one BLAS thread, as in process: bit-identical
        eng = _WORKER_CACHE.get(spec_json)
        if eng is None:
            eng = engine_from_spec(json.loads(spec_json))
            _WORKER_CACHE.clear()
            _WORKER_CACHE[spec_json] = eng
        act = None if active is None else [s for s in eng.sources if s.name in active]
        return [eng.run_block(b, act) for b in blocks]


class Executor:
    """Runs chunks of blocks and yields their results in chunk order."""

    def __init__(self, engine, spec: dict, kind: str = "inline", workers: int | None = None, address=None):
        if kind not in EXECUTORS:
            raise ConfigError(f"unknown executor {kind!r}; expected one of {', '.join(EXECUTORS)}", key="executor")
        self.engine, self.kind = engine, kind
        self.spec_json = json.dumps(spec, sort_keys=True, default=str)
        self.pool = self.client = self.cluster = None
        if kind == "process":
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(max_workers=workers or 2)
        elif kind == "dask":
            try:
                from dask.distributed import Client, LocalCluster
            except ImportError:
                raise ConfigError("the dask executor needs the optional extra: pip install 'mtbudget[dask]'") from None
            if address:
                self.client = Client(address)
            else:
                self.cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=False,
                                            dashboard_address=None)
                self.client = Client(self.cluster)

    def map(self, chunks: list, active_names: list | None = None):
        """Yield the block results of each chunk, in chunk order."""
        if self.kind == "inline":
            act = None if active_names is None else [s for s in self.engine.sources if s.name in active_names]
            for ch in chunks:
                with one_blas_thread():
                    results = [self.engine.run_block(b, act) for b in ch]
                yield results
        elif self.kind == "process":
            futs = [self.pool.submit(run_blocks_from_spec, self.spec_json, ch, active_names) for ch in chunks]
            for f in futs:
                yield f.result()
        else:
            futs = self.client.map(run_blocks_from_spec, [self.spec_json] * len(chunks), chunks,
                                   [active_names] * len(chunks), pure=False)
            for f in futs:
                yield f.result()

    def close(self):
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
