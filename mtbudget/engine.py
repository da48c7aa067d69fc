"""The Monte Carlo engine of a verification: sources -> simulate -> identify -> outputs -> budget.

One run draws N trials in blocks of ``block`` trials.  Every block has its
own random streams, one per source, from ``SeedSequence(seed, spawn_key=
(block, crc32(source name)))``: the numbers of a trial depend on the seed,
its block and the source only, never on how blocks are grouped into chunks,
on the executor, or on which other sources are active (common random numbers
for the budget).  Statistics are accumulated per block and merged in block
order, so the same seed gives bit-identical results in process, in a process
pool or on a Dask cluster.

Budget attribution: the model is non-linear, so contributions are measured,
not linearised.  For each source the same trials are run with that source
alone ("one at a time", OAT): its variance V_i.  The GUM-style budget lists
u_i(y) = sqrt(V_i), the source's own standard uncertainty u(x_i) where it has
one, the effective sensitivity c_i = u_i(y) / u(x_i), and the share
V_i / V.  What the contributions do not explain, V - sum V_i, is reported as
the interaction term, so the table adds up exactly.  Optionally the
leave-one-out variant (V - V_without_i) is computed too.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field

import numpy as np

from .config import SimulationConfig, load_config, parse_config
from .errors import ConfigError, PluginError
from .identify import Noise, Strategy, identify
from .model import MeasurementModel, from_targets
from .plugins import PluginHost, default_host
from .simulate import machine_parameters, truth_model
from .contracts import Context, Group, Source, TARGETS, check_sample
from .stats import Moments, numerical_tolerance, shortest_interval, symmetric_interval

#: scalar outputs per trial: name -> (unit, description)
SCALARS = {
    "compensation_rms": ("um", "root mean square over the mesh of the error left after compensation (true minus identified field, rigid-body part removed)"),
    "compensation_mean": ("um", "mean over the mesh of the error left after compensation (true minus identified field, rigid-body part removed)"),
    "compensation_max": ("um", "largest error left after compensation over the mesh"),
    "mean_error_after": ("um", "paper Eq. 27 after compensation: mean distance between measured and compensated points"),
    "mean_error_before": ("um", "paper Eq. 27 before compensation: mean distance between measured and nominal points"),
    "max_residual": ("um", "largest residual distance after compensation"),
    "chi2_per_dof": ("", "weighted residuals against the stated uncertainties"),
}
MAIN_OUTPUT = "compensation_rms"
#: outputs whose budget is attributed by mean square (additive over independent sources), the others by variance
MEAN_SQUARE_OUTPUTS = ("compensation_rms",)


@dataclass
class BlockResult:
    block: int
    n: int
    scalars: dict  # name -> (n,)
    point_error: np.ndarray  # (n, M0) um
    parameters: np.ndarray  # (n, p) um / urad


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
        k = np.broadcast_to(np.arange(x.shape[1]), x.shape)
        np.add.at(self.counts, (k[ok], idx[ok]), 1)

    def quantiles(self, prob) -> np.ndarray:
        """(K, len(prob)) quantiles by linear interpolation of the binned CDF."""
        out = np.empty((self.counts.shape[0], len(prob)))
        for k in range(self.counts.shape[0]):
            tot = self.counts[k].sum() + self.under[k] + self.over[k]
            cdf = (self.under[k] + np.concatenate([[0], np.cumsum(self.counts[k])])) / tot
            edges = np.linspace(self.low[k], self.high[k], self.bins + 1)
            out[k] = np.interp(prob, cdf, edges)
        return out


class Accumulator:
    """Streaming statistics of a run, merged in block order (deterministic)."""

    def __init__(self, keep_samples: bool = True):
        self.keep = keep_samples
        self.n = 0
        self.moments: dict = {}
        self.hist: dict = {}
        self.samples: dict = {k: [] for k in SCALARS}
        self.blocks: list = []

    def add(self, b: BlockResult):
        """Merge one block: scalars exactly (samples, moments, histogram), vector outputs by their moments."""
        self.blocks.append(b.block)
        for k, v in b.scalars.items():
            col = v[:, None]
            m = Moments.of(col)
            self.moments[k] = m if k not in self.moments else self.moments[k].merge(m)
            if k not in self.hist:
                self.hist[k] = VectorHistogram(col)
            self.hist[k].add(col)
            if self.keep:
                self.samples[k].append(v)
        for key, arr, mom in (("point_error", b.point_error, getattr(b, "point_moments", None)),
                              ("parameters", b.parameters, getattr(b, "parameter_moments", None))):
            m = mom if mom is not None else Moments.of(arr)
            self.moments[key] = m if key not in self.moments else self.moments[key].merge(m)
        self.n += b.n

    def scalar_samples(self, name: str) -> np.ndarray | None:
        if not self.keep or not self.samples[name]:
            return None
        return np.concatenate(self.samples[name])

    def summary(self, name: str, coverage: float) -> dict:
        m = self.moments[name]
        y = self.scalar_samples(name) if name in SCALARS else None
        if y is not None:
            ys = np.sort(y)
            sym, short = symmetric_interval(ys, coverage), shortest_interval(ys, coverage)
            exact = True
        else:
            h = self.hist[name]
            q = h.quantiles(np.array([(1 - coverage) / 2, (1 + coverage) / 2]))
            sym, short, exact = (float(q[0, 0]), float(q[0, 1])), None, False
        return {"mean": float(np.asarray(m.mean).ravel()[0]), "std": float(np.asarray(m.std).ravel()[0]),
                "symmetric": sym, "shortest": short, "exact_intervals": exact, "n": m.n}


def _rigid_projector(P: np.ndarray) -> np.ndarray:
    """I - projector onto rigid motions of points P (M, 3): removes what the tracker pose absorbs."""
    M = len(P)
    A = np.zeros((M, 3, 6))
    A[:, :, :3] = np.eye(3)
    c = P - P.mean(0)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1
        A[:, :, 3 + k] = np.cross(e, c)
    A = A.reshape(3 * M, 6)
    return np.eye(3 * M) - A @ np.linalg.pinv(A)


class Engine:
    """Monte Carlo of a verification: build once, run blocks."""

    def __init__(self, config: SimulationConfig, host: PluginHost | None = None, *, block: int = 64,
                 sources: list | None = None, seed: int | None = None):
        self.config = config
        self.block = int(block)
        if self.block < 1:
            raise ConfigError("block size must be >= 1")
        self.seed = config.seed if seed is None else int(seed)
        self.host = host or default_host()
        rng = np.random.default_rng(np.random.SeedSequence(config.seed))  # the plan and sensor readings of the study
        self.plan = config.plan(rng)
        self.truth = truth_model(config, self.plan)
        self.theta = machine_parameters(config, self.truth)
        self.pose = np.asarray(config.pose, float)
        self.max_degree = config.max_degree
        self._id_models: dict = {}
        self.id_model = self._identification_model(self.max_degree)
        self.noise = Noise(config.angular, config.distance, config.distance_per_length, config.repeatability)
        nominal = self.truth.predict(np.zeros(self.truth.n_params), self.pose)[0]
        self.context = Context(self.plan, self.truth, nominal, self.theta, config.reference_temperature, config)
        # mesh points: the rows of the first run with the first tool
        first = (self.plan.run == self.plan.run.min()) & np.all(self.plan.tool == self.plan.tool[0], axis=1)
        self.mesh_rows = np.flatnonzero(first)
        P0 = self.truth.machine_points(np.zeros(self.truth.n_params))[0][self.mesh_rows]
        self.rigid_free = _rigid_projector(P0)
        self.sources = self._select_sources(sources)
        self.shapes = {k: tuple(len(self.plan) if s == "M" else self.truth.n_params if s == "p" else s for s in shape)
                       for k, (_, shape) in TARGETS.items()}
        for s in self.sources:  # probe: keys, shapes, dimensions and NaN checked once, at registration
            self._sample(s, 2, np.random.default_rng(0))

    # ------------------------------------------------------------------ set-up
    def _identification_model(self, max_degree: int) -> MeasurementModel:
        if max_degree not in self._id_models:
            self._id_models[max_degree] = MeasurementModel.for_plan(self.config.machine, self.plan, max_degree=max_degree)
        return self._id_models[max_degree]

    def _select_sources(self, names):
        settings = self.config.source.get("sources", {}) if isinstance(self.config.source, dict) else {}
        if not isinstance(settings, dict):
            raise ConfigError("[sources] must be a table")
        available = {s.name: s for s in self.host.sources()}
        enable = names if names is not None else settings.get("enable")
        disable = set(settings.get("disable", []))
        chosen = list(available) if enable is None else list(enable)
        for n in list(chosen) + list(disable):
            if n not in available:
                raise ConfigError(f"[sources]: unknown source {n!r}; available: {', '.join(sorted(available))}")
        out = []
        for n in chosen:
            if n in disable:
                continue
            src = available[n]
            overrides = settings.get(n, {})
            if overrides:
                src.configure(overrides)
            out.append(src)
        return out

    def _sample(self, src: Source, n: int, rng) -> dict:
        try:
            raw = src.sample(n, rng, self.context)
        except PluginError:
            raise
        except Exception as exc:
            raise PluginError(f"sample() raised {type(exc).__name__}: {exc}", src.plugin, src.name, "sample") from exc
        arrays = check_sample(src, raw, n, self.shapes)
        if "strategy" in arrays:
            k = len(src.options(self.context))
            s = arrays["strategy"]
            if np.any((s != np.round(s)) | (s < 0) | (s >= k)):
                raise PluginError(f"'strategy' must hold option indices 0..{k - 1}", src.plugin, src.name, "sample")
        return arrays

    def stream(self, block: int, source: Source) -> np.random.Generator:
        key = (int(block), zlib.crc32(source.name.encode()))
        return np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=key))

    # ------------------------------------------------------------------ one block
    def simulate(self, block: int, active: list | None = None):
        """The simulated measurements of one block: (measured (B, M, 3), true parameters (B, p), strategy choices).

        Every source in ``active`` (default: all selected) is drawn from its own stream for this block;
        the choices are (source, option index per trial) of the optimisation-strategy sources.
        """
        n = self.block
        active = self.sources if active is None else active
        targets: dict = {}
        choices = []
        for src in active:
            arr = self._sample(src, n, self.stream(block, src))
            for k, v in arr.items():
                if k == "strategy":
                    choices.append((src, v.astype(int)))
                else:
                    targets[k] = targets[k] + v if k in targets else v
        pert = from_targets(targets)
        theta_true = self.theta[None, :] + pert.pop("geometry", 0.0)
        theta_true = np.broadcast_to(theta_true, (n, self.truth.n_params))
        return self.truth.predict(theta_true, self.pose, pert), theta_true, choices

    def run_block(self, block: int, active: list | None = None) -> BlockResult:
        """Trials ``block*B .. (block+1)*B - 1`` with the ``active`` sources (default: all selected)."""
        n = self.block
        meas, theta_true, choices = self.simulate(block, active)
        F_true = self.truth.machine_points(theta_true)[:, self.mesh_rows]

        # group trials by the identification settings the optimisation-strategy sources chose
        keys = np.zeros(n, int)
        for src, c in choices:
            keys = keys * len(src.options(self.context)) + c
        p_base = self.id_model.n_params
        out_scalars = {k: np.empty(n) for k in SCALARS}
        point_err = np.empty((n, len(self.mesh_rows)))
        params = np.zeros((n, p_base))
        for key in np.unique(keys):
            idx = np.flatnonzero(keys == key)
            settings: dict = {}
            rem = int(key)
            for src, _ in reversed(choices):
                opts = src.options(self.context)
                settings.update(opts[rem % len(opts)])
                rem //= len(opts)
            model, strategy = self._identification_setup(settings)
            res = identify(model, meas[idx], self.noise, strategy, chunk=self.block)
            F_id = model.machine_points(res.theta)[:, self.mesh_rows]
            D = (F_true[idx] - F_id).reshape(len(idx), -1) @ self.rigid_free.T
            e = np.linalg.norm(D.reshape(len(idx), -1, 3), axis=2) * 1e3
            point_err[idx] = e
            out_scalars["compensation_rms"][idx] = np.sqrt((e**2).mean(axis=1))
            out_scalars["compensation_mean"][idx] = e.mean(axis=1)
            out_scalars["compensation_max"][idx] = e.max(axis=1)
            out_scalars["mean_error_after"][idx] = res.mean_error_after * 1e3
            out_scalars["mean_error_before"][idx] = res.mean_error_before * 1e3
            out_scalars["max_residual"][idx] = res.max_residual * 1e3
            out_scalars["chi2_per_dof"][idx] = res.chi2_per_dof
            scale = np.array([1e3 if u == "mm" else 1e6 for u in model.errors.units])
            if model is self.id_model:
                params[idx] = res.theta * scale
            else:
                names = self.id_model.errors.names
                for j, nm in enumerate(model.errors.names):
                    if nm in names:
                        params[idx, names.index(nm)] = res.theta[:, j] * scale[j]
        return BlockResult(block, n, out_scalars, point_err, params)

    def _identification_setup(self, settings: dict):
        model = self._identification_model(int(settings.get("max_degree", self.max_degree)))
        phases = settings.get("phases", "one-phase")
        base = Strategy.multi_phase() if phases == "multi-phase" else Strategy.one_phase()
        if "xtol" in settings:
            base.xtol = float(settings["xtol"])
        if "max_iter" in settings:
            base.max_iter = int(settings["max_iter"])
        return model, base

    # ------------------------------------------------------------------ description
    @property
    def parameter_names(self) -> list:
        return self.id_model.errors.names

    @property
    def parameter_units(self) -> list:
        return ["um" if u == "mm" else "urad" for u in self.id_model.errors.units]


def engine_from_spec(spec: dict) -> Engine:
    """Rebuild an engine from a JSON-able spec (used by process pools, Dask workers and replay)."""
    cfg = parse_config(spec["config"], spec.get("config_path"))
    return Engine(cfg, block=spec["block"], sources=spec.get("sources"), seed=spec["seed"])


_WORKER_CACHE: dict = {}


def run_blocks_from_spec(spec_json: str, blocks: list, active: list | None = None) -> list:
    """Worker entry point: run ``blocks`` of the engine described by ``spec_json``."""
    import json

    eng = _WORKER_CACHE.get(spec_json)
    if eng is None:
        eng = engine_from_spec(json.loads(spec_json))
        _WORKER_CACHE.clear()
        _WORKER_CACHE[spec_json] = eng
    act = None if active is None else [s for s in eng.sources if s.name in active]
    return [eng.run_block(b, act) for b in blocks]


# ---------------------------------------------------------------------- running
@dataclass
class RunResult:
    spec: dict
    trials: int
    coverage: float
    acc: Accumulator
    parameter_names: list
    parameter_units: list
    convergence: list = field(default_factory=list)  # per chunk: {"trials", "mean", "std", "low", "high"} of MAIN_OUTPUT
    budget: dict = field(default_factory=dict)  # output -> budget table
    complete: bool = True
    stopped_at_limit: bool = False  # adaptive run that hit max_trials before reaching its tolerance

    def summary(self, name: str = MAIN_OUTPUT) -> dict:
        return self.acc.summary(name, self.coverage)

    def outputs(self) -> dict:
        """Every scalar output: mean, std, intervals, with units."""
        return {k: {**self.summary(k), "unit": SCALARS[k][0], "description": SCALARS[k][1]} for k in SCALARS}


def make_spec(config: SimulationConfig, *, seed: int | None, block: int, sources: list | None, coverage: float) -> dict:
    return {"config": config.source, "config_path": str(config.path) if config.path else None,
            "seed": int(config.seed if seed is None else seed), "block": int(block), "sources": sources,
            "coverage": float(coverage)}


class _Executor:
    """Runs chunks of blocks in order: inline, in a process pool, or on a Dask cluster."""

    def __init__(self, engine: Engine, spec: dict, kind: str = "inline", workers: int | None = None, address=None):
        import json

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
        elif kind != "inline":
            raise ConfigError(f"unknown executor {kind!r}; expected inline, process or dask")

    def map(self, chunks: list, active_names: list | None = None):
        """Yield the block results of each chunk, in chunk order."""
        if self.kind == "inline":
            act = None if active_names is None else [s for s in self.engine.sources if s.name in active_names]
            for ch in chunks:
                yield [self.engine.run_block(b, act) for b in ch]
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


def run(config: SimulationConfig | str | None = None, *, trials: int | None = 1000, seed: int | None = None,
        coverage: float = 0.95, block: int = 64, chunk_blocks: int = 4, sources: list | None = None,
        executor: str = "inline", workers: int | None = None, address=None, progress: bool = False,
        attribution_trials: int | None = 512, keep_samples: bool | None = None, ndig: int = 2,
        adaptive_batch: int | None = None, adaptive_outputs: tuple = (MAIN_OUTPUT,), max_trials: int = 1_000_000,
        on_chunk=None, resume_blocks: list | None = None,
        engine: Engine | None = None, host: PluginHost | None = None) -> RunResult:
    """Run the Monte Carlo of a verification.

    trials: an int runs that many (rounded up to whole blocks and truncated);
    None runs the adaptive procedure of JCGM 101 7.9 on ``adaptive_outputs``
    (default the main output) in batches of ``adaptive_batch`` trials
    (default max(100 / (1 - p), 10^4)), stopping at ``max_trials`` at most.
    on_chunk(blocks, results, acc) is called after each chunk (the run log
    hooks in here).  resume_blocks: block results already computed (from a
    log); they are merged first and not recomputed.  keep_samples: keep every
    trial's scalar outputs in memory for exact intervals (default: for runs of
    up to 200 000 trials and adaptive runs); otherwise memory stays bounded and
    intervals come from fine histograms.
    """
    if not isinstance(config, SimulationConfig):
        config = load_config(config)
    if trials is not None and int(trials) < 2:
        raise ConfigError(f"trials must be >= 2, got {trials}")
    if not 0 < coverage < 1:
        raise ConfigError(f"coverage must lie in (0, 1), got {coverage}")
    eng = engine or Engine(config, host, block=block, sources=sources, seed=seed)
    spec = make_spec(config, seed=eng.seed, block=eng.block, sources=[s.name for s in eng.sources], coverage=coverage)
    if keep_samples is None:
        keep_samples = trials is None or int(trials) <= 200_000
    acc = Accumulator(keep_samples)
    result = RunResult(spec, 0, coverage, acc, eng.parameter_names, eng.parameter_units)
    done = {b.block: b for b in (resume_blocks or [])}
    ex = _Executor(eng, spec, executor, workers, address)
    bar = None
    try:
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=trials, unit="trial", desc="Monte Carlo", leave=True)

        def consume(block_ids, target_n):
            todo = [b for b in block_ids if b not in done]
            chunks = [todo[i:i + chunk_blocks] for i in range(0, len(todo), chunk_blocks)]
            gen = ex.map(chunks)
            cache = dict(done)
            pending = list(block_ids)
            for ch in chunks:
                for r in next(gen):
                    cache[r.block] = r
                # merge every block that is now available, in block order
                merged = []
                while pending and pending[0] in cache:
                    b = cache[pending.pop(0)]
                    left = target_n - acc.n
                    if left < b.n:
                        b = _truncate(b, left)
                    acc.add(b)
                    merged.append(b)
                if merged:
                    _record(result, acc, coverage)
                    if bar:
                        bar.update(sum(b.n for b in merged))
                    if on_chunk:
                        on_chunk(merged, result)
            if pending:  # blocks that were all resumed from a log
                merged = []
                while pending:
                    b = cache[pending.pop(0)]
                    acc.add(b if acc.n + b.n <= target_n else _truncate(b, target_n - acc.n))
                    merged.append(b)
                _record(result, acc, coverage)
                if on_chunk:
                    on_chunk(merged, result)

        if trials is not None:
            nblocks = math.ceil(int(trials) / eng.block)
            consume(list(range(nblocks)), int(trials))
        else:
            h = adaptive_batch or max(int(100 / (1 - coverage)), 10_000)
            per = math.ceil(h / eng.block)
            batch_stats = []
            k = 0
            while True:
                before = acc.n
                consume(list(range(k * per, (k + 1) * per)), before + per * eng.block)
                k += 1
                batch_stats.append(_batch_summary(acc, before, coverage, adaptive_outputs))
                if len(batch_stats) >= 2:
                    arr = np.array(batch_stats)  # (h, outputs, 4): mean, u, interval ends of each batch
                    s = arr.std(axis=0, ddof=1) / math.sqrt(len(arr))
                    deltas = np.array([numerical_tolerance(acc.summary(o, coverage)["std"], ndig) for o in adaptive_outputs])
                    if np.all(2 * s <= deltas[:, None]):
                        break
                    if acc.n >= max_trials:
                        result.stopped_at_limit = True
                        break
        result.trials = acc.n
    finally:
        if bar:
            bar.close()
        ex.close()
    if attribution_trials:
        result.budget = attribution(eng, result, min(attribution_trials, result.trials), ex_kind=executor,
                                    workers=workers, address=address, chunk_blocks=chunk_blocks)
    return result


def _truncate(b: BlockResult, n: int) -> BlockResult:
    if b.point_error is None:
        raise ConfigError("a resumed block cannot be shortened; resume with the logged trial count")
    return BlockResult(b.block, n, {k: v[:n] for k, v in b.scalars.items()}, b.point_error[:n], b.parameters[:n])


def _record(result: RunResult, acc: Accumulator, coverage: float):
    s = acc.summary(MAIN_OUTPUT, coverage)
    result.convergence.append({"trials": acc.n, "mean": s["mean"], "std": s["std"],
                               "low": s["symmetric"][0], "high": s["symmetric"][1]})
    result.trials = acc.n


def _batch_summary(acc: Accumulator, start: int, coverage: float, outputs=tuple(SCALARS)):
    rows = []
    for o in outputs:
        y = np.sort(acc.scalar_samples(o)[start:])
        lo, hi = symmetric_interval(y, coverage)
        rows.append([y.mean(), y.std(ddof=1), lo, hi])
    return rows


def attribution(engine: Engine, result: RunResult, n: int, *, ex_kind="inline", workers=None, address=None,
                chunk_blocks=4, leave_one_out: bool = False) -> dict:
    """One-source-at-a-time budget of every scalar output on the first ``n`` trials (see module docstring)."""
    import uncertainties

    nblocks = math.ceil(n / engine.block)
    blocks = list(range(nblocks))
    spec = result.spec
    ex = _Executor(engine, spec, ex_kind, workers, address)

    def moments(active_names):
        acc = Accumulator(keep_samples=True)
        chunks = [blocks[i:i + chunk_blocks] for i in range(0, len(blocks), chunk_blocks)]
        for res in ex.map(chunks, active_names):
            for b in res:
                acc.add(b if acc.n + b.n <= n else _truncate(b, n - acc.n))
        out = {}
        for o in SCALARS:
            y = acc.scalar_samples(o)
            out[o] = {"variance": float(np.var(y, ddof=1)), "mean_square": float(np.mean(y**2)), "mean": float(y.mean())}
        return out

    try:
        total = moments([s.name for s in engine.sources])
        nominal = moments([])
        per_source = {s.name: moments([s.name]) for s in engine.sources}
        loo = {}
        if leave_one_out:
            for s in engine.sources:
                loo[s.name] = moments([t.name for t in engine.sources if t.name != s.name])
    finally:
        ex.close()
    tables = {}
    for o, (unit, _) in SCALARS.items():
        basis = "mean_square" if o in MEAN_SQUARE_OUTPUTS else "variance"
        rows = []
        V = total[o][basis]
        for s in engine.sources:
            v = per_source[s.name][o][basis]
            ux = s.standard_uncertainty()
            u_y = math.sqrt(max(v, 0.0))
            row = {"source": s.name, "group": Group(s.group).value, "plugin": s.plugin, "distribution": s.distribution,
                   "u_x": None if ux is None else {"value": float(ux.magnitude), "unit": f"{ux.units:~}"},
                   "contribution": v, "u_y": u_y, "share": v / V if V > 0 else 0.0}
            if ux is not None and ux.magnitude:
                row["sensitivity"] = {"value": u_y / float(ux.magnitude),
                                      "unit": f"{unit}/({ux.units:~})" if unit else f"1/({ux.units:~})"}
            if leave_one_out:
                row["loo"] = V - loo[s.name][o][basis]
            rows.append(row)
        groups: dict = {}
        for r in rows:
            groups[r["group"]] = groups.get(r["group"], 0.0) + r["contribution"]
        # law of propagation over the (independent) source contributions, through `uncertainties`
        comb = 0.0
        for r in rows:
            if r["u_y"] > 0:
                comb = comb + uncertainties.ufloat(0.0, r["u_y"], tag=r["source"])
        tables[o] = {
            "unit": unit, "trials": n, "basis": basis, "total": V, "u_total": math.sqrt(max(V, 0.0)),
            "sum_of_contributions": sum(r["contribution"] for r in rows),
            "interaction": V - sum(r["contribution"] for r in rows),
            "nominal": nominal[o][basis],
            "nominal_value": nominal[o]["mean"],
            "u_combined": float(getattr(comb, "std_dev", 0.0)),
            "rows": rows,
            "groups": [{"group": g.value, "contribution": groups.get(g.value, 0.0),
                        "share": groups.get(g.value, 0.0) / V if V > 0 else 0.0} for g in Group],
        }
    return tables
