"""Running a verification Monte Carlo: settings, the run loop, the run log, replay and verify.

:func:`run` draws blocks of trials (inline, in a process pool or on Dask),
merges their statistics in block order and, after the trials, computes the
budget.  :func:`execute` is the ``mtbudget run`` command: the same run,
logged to MCAP as it goes (resumable).  :func:`replay` rebuilds a run's
results from its log; :func:`verify` recomputes the logged trials and
compares them bit for bit.
"""

from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from . import __version__
from .budget import RunPrefix, attribution, point_guf
from .config import SimulationConfig, load_config, parse_config
from .engine import Engine
from .errors import ConfigError, RunLogError
from .executors import EXECUTORS, Executor, one_blas_thread
from .outputs import (KEEP_SAMPLES_TRIALS, MACHINE_SCALARS, MAIN_OUTPUT, POINT_UNIT, SCALARS, RunResult,
                      accumulate_block, frame_word)
from .plugins import PluginHost
from .progress import progress_bar
from .scenario import Scenario, build_scenario
from .stats import Accumulator, AdaptiveStop, batch_row, batch_rows, shortest_interval, symmetric_interval

DEFAULT_LOG = "mtbudget-run.mcap"


@dataclass
class RunSettings:
    """How to run the Monte Carlo of a verification (every option of ``mtbudget run`` in one place).

    trials: an int runs that many (rounded up to whole blocks and truncated);
    None runs the adaptive procedure of JCGM 101 7.9 on ``adaptive_outputs`` ("points": every point-axis of the
    per-point measurand, its u and interval ends; the others scalar outputs)
    in batches of ``adaptive_batch`` trials (default max(100 / (1 - p), 10^4)),
    stopping at ``max_trials`` at most.  keep_samples: keep every trial's
    scalar outputs for exact intervals (default: up to ``outputs.KEEP_SAMPLES_TRIALS``, 200 000 trials: a fixed run
    of at most that many, an adaptive run until it passes them); otherwise memory stays bounded and intervals
    come from fine histograms.  chunk_blocks: blocks identified together, then merged and logged (None:
    :func:`auto_chunk_blocks`); the results do not depend on it, only the speed and the convergence rows.
    """

    trials: int | None = 1000
    seed: int | None = None
    coverage: float = 0.95
    block: int = 64
    chunk_blocks: int | None = None  # blocks identified together and then logged; None: auto_chunk_blocks
    sources: list | None = None
    executor: str = "inline"
    workers: int | None = None
    address: str | None = None
    progress: bool = False
    attribution_trials: int = 512
    keep_samples: bool | None = None
    ndig: int = 2
    adaptive_batch: int | None = None
    adaptive_outputs: tuple = ("points", MAIN_OUTPUT)
    max_trials: int = 1_000_000

    def adaptive_batch_trials(self, block: int | None = None) -> int:
        """Trials of one batch of an adaptive run: ``adaptive_batch`` or JCGM 101's max(100 / (1 - p), 10^4), in
        whole blocks."""
        block = block or self.block
        h = self.adaptive_batch or max(int(100 / (1 - self.coverage)), 10_000)
        return math.ceil(h / block) * block

    def validate(self) -> "RunSettings":
        """Every number checked at the boundary; the error names the option."""
        def need(ok, option, text):
            if not ok:
                raise ConfigError(text, key=option)

        if self.trials is not None:
            need(isinstance(self.trials, (int, np.integer)) and self.trials >= 2, "--trials",
                 f"must be a whole number >= 2 (or 0 for an adaptive run), got {self.trials}")
        need(isinstance(self.coverage, float | int) and 0 < self.coverage < 1, "--coverage",
             f"must lie strictly between 0 and 1, got {self.coverage}")
        need(self.block >= 1, "block", f"must be >= 1, got {self.block}")
        need(self.chunk_blocks is None or self.chunk_blocks >= 1, "chunk_blocks",
             f"must be >= 1 (or None: automatic), got {self.chunk_blocks}")
        need(self.attribution_trials is not None and self.attribution_trials >= 0, "--attribution-trials",
             f"must be 0 (no budget) or a positive number of trials, got {self.attribution_trials}")
        need(self.attribution_trials == 0 or self.attribution_trials >= 2, "--attribution-trials",
             f"needs at least 2 trials to estimate a variance, got {self.attribution_trials}")
        need(self.executor in EXECUTORS, "--executor", f"must be one of {', '.join(EXECUTORS)}, got {self.executor!r}")
        need(self.workers is None or self.workers >= 1, "--workers", f"must be >= 1, got {self.workers}")
        need(self.adaptive_batch is None or self.adaptive_batch >= 2, "--adaptive-batch",
             f"must be >= 2, got {self.adaptive_batch}")
        need(self.max_trials >= 2, "max_trials", f"must be >= 2, got {self.max_trials}")
        need(1 <= self.ndig <= 4, "ndig", f"must be 1 to 4 significant digits, got {self.ndig}")
        return self

    def check_limit(self, block: int) -> "RunSettings":
        """An adaptive run's limit holds the two batches its rule always runs (batches of whole blocks of
        ``block`` trials, the engine's); the error names the option."""
        if self.trials is None:
            batch = self.adaptive_batch_trials(block)
            if self.max_trials < 2 * batch:
                raise ConfigError(f"must be at least two adaptive batches ({2 * batch} trials: two of {batch}, JCGM "
                                  f"101 7.9 compares batches), got {self.max_trials}; raise it or make the batches "
                                  "smaller (--adaptive-batch)", key="--max-trials")
        return self


#: trials x measured points identified together at most (the arrays of a chunk grow with both): 16 blocks of 64
#: trials of the paper's 75 points; a 4851-point mesh gets one block per chunk (measured: 8.6-9.4 ms per trial
#: against 10.1-10.4 with 4 blocks, and 0.95 GB of memory for 1280 trials with chunks of 5 blocks)
CHUNK_ROWS = 16 * 64 * 75


def auto_chunk_blocks(n_blocks: int, block_rows: int | None = None) -> int:
    """Blocks identified together in a run of ``n_blocks`` blocks: a quarter of them (a run has at least four
    convergence rows and log records), at least 4 and at most 16: 16 from 64 blocks (4096 trials of 64) on.
    Identifying more trials per call shares each call's fixed cost: measured, chunks of 16 blocks are 1.11x faster
    per trial than 4 at 4096 trials, 8 nearly as fast, 32 no faster (docs/performance.md, issue 31).  Before issue
    31 the rule was ``min(16, max(4, n_blocks // 64))``: 4 up to 511 blocks; a resumed log that recorded no chunk
    size gets this rule, the same numbers and other convergence rows."""
    c = min(16, max(4, int(n_blocks) // 4))
    if block_rows:  # trials x measured points of one block: at most CHUNK_ROWS together
        c = max(1, min(c, CHUNK_ROWS // int(block_rows)))
    return c


def chunk_blocks_for(settings: RunSettings, block: int, rows: int | None = None) -> int:
    """The blocks identified together in a run with these settings: ``settings.chunk_blocks`` when given, else
    :func:`auto_chunk_blocks` of the run's blocks (an adaptive run's: one batch) and, given ``rows`` (the plan's
    measured points), of their size.  The run log records the value used, and a resume reuses it."""
    if settings.chunk_blocks:
        return int(settings.chunk_blocks)
    trials = settings.trials
    return auto_chunk_blocks(math.ceil((int(trials) if trials is not None else settings.adaptive_batch or 10_000)
                                       / int(block)), None if rows is None else int(block) * int(rows))


#: per-point components kept as every trial's values (exact intervals) up to this many numbers (20 MB, and as much
#: again to sort them: about 11 000 trials of the paper's 75 points, 170 of 4851), else streamed into histograms
#: (memory bounded for any number of trials; the intervals say their method)
VECTOR_SAMPLE_LIMIT = 2_500_000


def keep_vector_samples(settings: RunSettings, n_points: int) -> bool:
    """Whether a run keeps every trial's per-point components (at most 20 MB) or histograms them."""
    if settings.keep_samples is False:
        return False
    total = settings.max_trials if settings.trials is None else int(settings.trials)
    return total * n_points * 3 <= VECTOR_SAMPLE_LIMIT


def logged_to_machine(header: dict):
    """The table frame's orientation at each mesh point's pose of a logged five-axis run: the header's
    ``workpiece_to_machine``, or, for a log written before it was logged, the same computed from the logged
    configuration and commanded angles (None where neither gives it: three axes, or a configuration no longer read)."""
    if header.get("workpiece_to_machine"):
        return np.asarray(header["workpiece_to_machine"])
    angles = header.get("commanded_angles")
    if not angles:
        return None
    from .config import parse_config
    from .errors import MtbudgetError
    from .machine import Configuration

    try:
        cfg = parse_config(header["spec"]["config"])
        machine = Configuration.parse(cfg.machine, cfg.plan().rotary or None)
    except (MtbudgetError, KeyError, TypeError, ValueError):
        return None
    return _table_orientation(machine, angles)


def _table_orientation(machine, angles_deg: dict):
    """(M0, 3, 3) the nominal orientation of the table frame in the machine frame at each mesh point's pose
    (``machine.workpiece_rotation`` of the commanded angles, deg); None where no rotary axis carries the workpiece."""
    from .machine import workpiece_rotation

    return workpiece_rotation(machine, {r: np.radians(np.asarray(v, float)) for r, v in angles_deg.items()})


def _to_machine(scenario: Scenario):
    """Five-axis with a rotary table: (M0, 3, 3) the nominal orientation of the table frame, in which the per-point
    components are stated, in the machine frame at each mesh point's pose; None otherwise."""
    return _table_orientation(scenario.truth.config, scenario.commanded_angles) if scenario.commanded_angles else None


def make_spec(scenario: Scenario, engine: Engine, settings: RunSettings) -> dict:
    """The JSON-able description a worker (or replay --verify) rebuilds the engine from."""
    cfg = scenario.config
    other_tool = scenario.measurand_tool is not None
    spec = {"config": cfg.source, "config_path": str(cfg.path) if cfg.path else None, "seed": int(engine.seed),
            "block": int(engine.block), "sources": [s.name for s in engine.sources], "coverage": float(settings.coverage),
            "measurand": {"tool": [float(v) for v in scenario.tool], "tool_unit": "mm",
                          "verification_tool": not other_tool,
                          "in_use": any(s.name == "in_use" for s in engine.sources),
                          "unidentified": scenario.unidentified_at_tool() if other_tool else []}}
    if engine.features is not None:  # [[features]] (docs/features.md): only then, so other runs' specs are unchanged
        from .features import describe

        spec["features"] = describe(scenario)
    return spec


def scalar_keeping(trials, keep_samples) -> tuple[bool, int | None]:
    """How a run holds its scalar outputs, as ``Accumulator(keep, ..., keep_until)`` takes it; one rule for a run and
    its replay, so that a replay states the intervals the run stated (the same method on the same values).

    Every scalar value is kept up to ``KEEP_SAMPLES_TRIALS`` trials (exact order statistics), histogrammed beyond: a
    fixed run (``trials`` asked for) knows from its start, an adaptive run (``trials`` None) switches at the block that
    takes it past them (its stopping rule needs only the current batch); ``keep_samples`` True or False overrides."""
    keep = keep_samples if keep_samples is not None else (trials is None or int(trials) <= KEEP_SAMPLES_TRIALS)
    keep_until = KEEP_SAMPLES_TRIALS if trials is None and keep_samples is None else None
    return keep, keep_until


def run(config: SimulationConfig | Scenario | str | None = None, settings: RunSettings | None = None, *,
        on_chunk=None, resume_blocks: list | None = None, engine: Engine | None = None,
        host: PluginHost | None = None, resume_histogram: dict | None = None, **overrides) -> RunResult:
    """Run the Monte Carlo of a verification (see :class:`RunSettings`; keyword overrides are settings fields).

    on_chunk(blocks, result) is called after each chunk of blocks is merged
    (the run log hooks in here).  resume_blocks: block results already
    computed (from a log); they are merged first and not recomputed.
    resume_histogram: a logged histogram checkpoint (runlog.histogram_state) of a run that histograms its
    per-point errors; it holds the resumed blocks' per-point errors, which the log does not.  The
    whole run uses one BLAS thread (executors.one_blas_thread): the results
    are bit-identical whatever the machine's BLAS threading and executor.
    """
    with one_blas_thread():
        return _run(config, settings, on_chunk=on_chunk, resume_blocks=resume_blocks, engine=engine, host=host,
                    resume_histogram=resume_histogram, **overrides)


def _run(config, settings, *, on_chunk, resume_blocks, engine, host, resume_histogram=None, **overrides) -> RunResult:
    settings = replace(settings or RunSettings(), **overrides).validate()
    if engine is None:
        scenario = config if isinstance(config, Scenario) else build_scenario(
            config if isinstance(config, SimulationConfig) else load_config(config), host, settings.sources)
        engine = Engine(scenario, block=settings.block, seed=settings.seed)
    settings.check_limit(engine.block)
    scenario = engine.scenario
    spec = make_spec(scenario, engine, settings)
    trials = settings.trials
    keep, keep_until = scalar_keeping(trials, settings.keep_samples)
    acc = Accumulator(keep, keep_vector_samples(settings, len(scenario.mesh_rows)), keep_until)
    if resume_histogram is not None:
        from .runlog import histogram_from_state, moments_from_state

        if acc.keep_vectors:
            raise RunLogError("a histogram checkpoint was given to a run that keeps every trial's per-point errors")
        acc.vector_hist["components"] = histogram_from_state(resume_histogram)
        moments = moments_from_state(resume_histogram)
        if moments is not None:  # format 2: the moments of the resumed blocks' vector outputs (they hold none)
            if any(b.vector_moments() for b in (resume_blocks or [])):
                raise RunLogError("resumed blocks carry their moments and the checkpoint holds them too")
            acc.moments.update(moments)
    result = RunResult(spec, 0, settings.coverage, acc, engine.parameter_names, engine.parameter_units,
                       weights=scenario.weights_report(), mesh=scenario.mesh_points, commanded=scenario.commanded,
                       angles=scenario.commanded_angles or None, to_machine=_to_machine(scenario), guf=point_guf(scenario))
    done = {b.block: b for b in (resume_blocks or [])}
    resumed = set(done)
    # the budget's "all sources" row is this run's first attribution_trials trials: collected as they are merged
    prefix = RunPrefix(engine, settings.attribution_trials) if settings.attribution_trials else None
    result.prefix = prefix
    work = None if trials is None else int(trials) + settings.attribution_trials * (len(engine.sources) + 1)
    ex = Executor(engine, spec, settings.executor, settings.workers, settings.address, work=work)
    # what ran the trials (auto: what it chose), said with the run's conditions and logged with its result
    result.executor = {"kind": ex.kind, "workers": ex.n_workers, "requested": settings.executor}
    bar = progress_bar(trials, "Monte Carlo", "trial", settings.progress)
    chunk_blocks = chunk_blocks_for(settings, engine.block, len(scenario.plan))
    try:
        # adaptive: the current batch's per-point components and scalar outputs (name -> values), when collected
        batch: dict = {"parts": None, "scalars": None}

        def merge(b, target_n):
            """Merge block b, cut to the trials the run still needs; the merged (cut) block is what gets logged."""
            left = target_n - acc.n
            t = b if left >= b.n else b.truncated(left)
            accumulate_block(acc, t)
            if batch["parts"] is not None:
                batch["parts"].append(None if t.components is None else t.components.reshape(t.n, -1))
            if batch["scalars"] is not None:
                for o, vals in batch["scalars"].items():
                    vals.append(np.asarray(t.scalars[o])[:t.n])
            if spec.get("features"):  # [[features]]: every trial's feature errors, for their intervals
                result.feature_blocks.append(t.features)
            if prefix is not None:
                prefix.add(t, computed=t.block not in resumed)
            return t

        def consume(block_ids, target_n):
            # chunks of chunk_blocks consecutive blocks, each without the blocks resumed from a log: a convergence row
            # after each such group, so a resumed run has every row of the uninterrupted run (the same numbers)
            groups = [block_ids[i:i + chunk_blocks] for i in range(0, len(block_ids), chunk_blocks)]
            chunks = [c for c in ([b for b in g if b not in done] for g in groups) if c]
            gen = ex.map(chunks)
            # blocks computed or resumed and not yet merged; a block is released once merged (a resumed one too),
            # so the run holds only what waits for an earlier block: memory bounded by the executor's window
            cache = {b: done.pop(b) for b in block_ids if b in done}
            pending = deque(block_ids)
            last = {g[-1] for g in groups}

            def drain():
                merged = []  # every block now available, in block order, a row after each group
                while pending and pending[0] in cache:
                    b = pending.popleft()
                    merged.append(merge(cache.pop(b), target_n))  # merged blocks are not kept
                    if b in last:
                        _record(result)
                        bar.update(sum(m.n for m in merged))
                        if on_chunk:
                            on_chunk(merged, result)
                        merged = []

            for _ in chunks:
                for r in next(gen):
                    cache[r.block] = r
                drain()
            drain()  # groups that were all resumed from a log

        if trials is not None:
            consume(list(range(math.ceil(int(trials) / engine.block))), int(trials))
        else:
            _adaptive(settings, engine, acc, result, consume, batch, bar)
        result.trials = acc.n
        bar.close()
        if settings.attribution_trials:
            # on the run's executor: its workers have built the engine already (a new pool would build it again)
            result.budget = attribution(engine, result, min(settings.attribution_trials, result.trials),
                                        ex_kind=settings.executor, workers=settings.workers, address=settings.address,
                                        chunk_blocks=chunk_blocks, progress=settings.progress, executor=ex)
    finally:
        bar.close()
        ex.close()
        result.prefix = None  # the run's first trials, kept for the budget only
    return result


def _adaptive(settings: RunSettings, engine: Engine, acc: Accumulator, result: RunResult, consume, batch: dict, bar):
    """The adaptive Monte Carlo procedure (JCGM 101 7.9) on the per-point measurand and the scalar outputs asked for.

    After each batch of h trials: per scalar output and, with "points", per point-axis of the measurand, the
    batch's mean, standard deviation and interval ends; the run stops when twice the standard deviation of the batch
    values of every one of them is within the numerical tolerance of its standard uncertainty (two significant
    digits).  The rule reads the current batch's values (collected as its blocks are merged) and the running
    moments, never every trial's: the run keeps what a fixed run of as many trials keeps (memory bounded).  The bar
    shows how many point-axes are stable; ``result.adaptive`` says what stabilised and at how many trials and, for a
    run stopped at ``max_trials``, which quantities were not stable (:func:`_not_stable`).  Resumed blocks without
    their components (a log that histograms them) drop the per-point rule, said in ``result.adaptive["note"]``.
    """
    per = settings.adaptive_batch_trials(engine.block) // engine.block
    scal = [o for o in settings.adaptive_outputs if o != "points"]
    points = "points" in settings.adaptive_outputs
    stop_s, stop_p = AdaptiveStop(settings.ndig), AdaptiveStop(settings.ndig)
    note, k = None, 0
    ok_s, ok_p = np.zeros(len(scal), bool), None
    u_s, u_p = [], None
    while True:
        before = acc.n
        batch["parts"] = [] if points else None
        batch["scalars"] = {o: [] for o in scal} if scal else None
        consume(list(range(k * per, (k + 1) * per)), before + per * engine.block)
        k += 1
        parts, batch["parts"] = batch["parts"], None
        values, batch["scalars"] = batch["scalars"], None
        if scal:
            stop_s.add([batch_row(np.concatenate(values[o]), settings.coverage) for o in scal])
            u_s = [float(acc.scalar_moments_of(o).std[0]) for o in scal]
            ok_s = stop_s.stable(u_s)
        if points and (not parts or any(p is None for p in parts) or "components" not in acc.moments):
            points, note = False, ("the per-point rule was not applied: resumed blocks do not hold their per-point "
                                   "components; the run stopped on the scalar outputs alone")
        if points:
            stop_p.add(batch_rows(np.concatenate(parts), settings.coverage))
            u_p = acc.moments["components"].std.reshape(-1)
            ok_p = stop_p.stable(u_p)
        status = (f"stable: {int(ok_p.sum())} of {ok_p.size} point-axes" if points and ok_p is not None else "") + \
            "".join(f", {o} {'stable' if ok else 'not yet'}" for o, ok in zip(scal, ok_s))
        bar.set_postfix_str(status.lstrip(", "), refresh=True)
        done = len(stop_s.batches if scal else stop_p.batches) >= 2 and bool(ok_s.all()) and \
            (not points or bool(ok_p.all()))
        if done:
            break
        if acc.n >= settings.max_trials and k >= 2:
            result.stopped_at_limit = True
            break
    result.adaptive = {"trials": acc.n, "batches": k, "batch_trials": per * engine.block, "ndig": settings.ndig,
                       "coverage": settings.coverage, "stopped_at_limit": result.stopped_at_limit,
                       "max_trials": settings.max_trials,
                       "point_axes_stable": None if not points or ok_p is None else int(ok_p.sum()),
                       "point_axes": None if not points or ok_p is None else int(ok_p.size),
                       "outputs_stable": {o: bool(ok) for o, ok in zip(scal, ok_s)}, "note": note}
    if result.stopped_at_limit:
        rules = [(stop_s, u_s, ok_s, [(o, SCALARS[o][0]) for o in scal])] if scal else []
        if points and ok_p is not None:
            rules.append((stop_p, u_p, ok_p, _point_axis_names(result, ok_p.size)))
        result.adaptive.update(_not_stable(rules, acc.n, per * engine.block))


def _point_axis_names(result: RunResult, n: int) -> list:
    """(name, unit) of each point-axis of the per-point measurand, in the order of its components."""
    angles = result.angles or {}

    def where(i):
        if result.commanded is None:
            return ""
        at = "".join(f", {r} = {float(v[i]):g} deg" for r, v in sorted(angles.items()))
        return f" at x, y, z = ({', '.join(f'{v:g}' for v in result.commanded[i])}) mm{at}"

    fw = frame_word(result)
    return [(f"point #{j // 3}{where(j // 3)}, axis {'xyz'[j % 3]}{fw}", POINT_UNIT) for j in range(n)]


#: quantities not stable that an adaptive run stopped at its limit names (the worst first)
NOT_STABLE_SHOWN = 5


def _not_stable(rules: list, trials: int, batch_trials: int) -> dict:
    """What an adaptive run stopped at its trial limit did not stabilise: ``not_stable`` (how many of the outputs and
    point-axes), ``worst`` (the :data:`NOT_STABLE_SHOWN` farthest from their tolerance, each with the quantity that
    is, its 2 s, its numerical tolerance delta, its last change and its unit) and ``trials_needed``: about how many
    trials the worst would need at the rate seen (2 s falls as 1/sqrt(trials): trials (2 s / delta)^2, in whole
    batches; an estimate).  ``rules``: (AdaptiveStop, u per output, stable per output, (name, unit) per output)."""
    rows = []
    for stop, u, ok, names in rules:
        if len(stop.batches) < 2:
            continue
        two_s, delta, change = stop.spread(u)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = two_s / delta[:, None]
        for i in np.flatnonzero(~np.asarray(ok)):
            q = int(np.nanargmax(ratio[i])) if np.isfinite(ratio[i]).any() else 0
            rows.append({"quantity": names[i][0], "statistic": AdaptiveStop.QUANTITIES[q], "unit": names[i][1],
                         "two_s": float(two_s[i, q]), "delta": float(delta[i]), "u": float(u[i]),
                         "last_change": float(change[i, q]),
                         "ratio": float(ratio[i, q]) if math.isfinite(ratio[i, q]) else None})  # None: u = 0
    rows.sort(key=lambda r: -r["ratio"] if r["ratio"] is not None else math.inf)
    worst = max((r["ratio"] for r in rows if r["ratio"] is not None), default=None)
    needed = None if worst is None else int(math.ceil(trials * worst**2 / batch_trials) * batch_trials)
    return {"not_stable": len(rows), "worst": rows[:NOT_STABLE_SHOWN], "trials_needed": needed}


def _record(result: RunResult):
    result.convergence.append(result.convergence_row())
    result.trials = result.acc.n


# ------------------------------------------------------------------ the run command, logged
#: settings that change a run's numbers beyond trials, seed, coverage, block and sources; logged so a resume reuses them
RESUMED_SETTINGS = ("keep_samples", "adaptive_batch", "max_trials", "ndig", "adaptive_outputs", "chunk_blocks",
                    "attribution_trials")


def execute(config=None, settings: RunSettings | None = None, *, log_path=None, resume_path=None, force: bool = False,
            histogram_every: float = 60.0, **overrides) -> RunResult:
    """Run (or resume) a Monte Carlo study and log it to MCAP; what ``mtbudget run`` does.

    The log is written as ``LOG.partial`` and renamed to ``LOG`` when the run
    completes; a lock (``LOG.lock``) refuses a second run on the same log.
    ``resume_path`` (``LOG`` or ``LOG.partial``): the verified blocks of the
    interrupted run are copied into a new file, which replaces ``LOG.partial``
    only once it is on disk, and the missing blocks are computed; the result
    is bit-identical to an uninterrupted run.  A write error while logging
    (a full disk) does not stop the run: ``result.log_problem`` says what
    happened and ``LOG.partial`` keeps every block written before it.
    """
    from .runlog import RunLogLock, final_path

    settings = replace(settings or RunSettings(), **overrides)
    if resume_path is not None:
        source = final_path(resume_path)
        target = final_path(log_path) if log_path is not None else source
    else:
        source, target = None, final_path(log_path or DEFAULT_LOG)
    locks = [RunLogLock(target)]
    try:
        if source is not None and source.resolve() != target.resolve():
            locks.append(RunLogLock(source))
        with one_blas_thread():
            return _execute(config, settings, source=source, target=target, force=force,
                            histogram_every=histogram_every)
    finally:
        for lock in locks:
            lock.release()


def _saved_run(source: Path):
    """The interrupted run at ``source``: (base log, verified blocks as logged, notes).

    ``LOG.partial`` is the interrupted run when it exists; the blocks of ``LOG``
    (a log left by an older mtbudget, or a damaged one) are added when it is
    the same run.  Damaged records are never used; they are recomputed.
    """
    from .runlog import partial_path, read_runlog

    logs, errors = [], []
    for p in (partial_path(source), source):
        if p.exists():
            try:
                logs.append(read_runlog(p))
            except RunLogError as exc:
                errors.append(exc)
    if not logs:
        if errors:
            raise errors[0]
        raise RunLogError(f"{source}: no such file (nor {partial_path(source).name}); nothing to resume")
    base = logs[0]
    if base.complete and base.path == source:
        raise RunLogError(f"{source}: the run is complete; nothing to resume (use mtbudget replay)")
    blocks, notes = {}, []
    for log in logs:
        if log is not base and log.header.get("spec") != base.header.get("spec"):
            notes.append(f"{log.path} is another run (its spec differs); not used")
            continue
        for b in log.blocks:
            blocks.setdefault(b["block"], b)
        for d in log.damaged:
            notes.append(f"{log.path}: {d}; recomputed")
    return base, [blocks[k] for k in sorted(blocks)], notes


def _refuse_existing(target, force):
    """A run never overwrites another run's log (finished or interrupted) unless --force says so."""
    from .runlog import partial_path

    if not force and Path(target).exists():
        raise RunLogError(f"{target}: a run log is already there; choose another --log path or pass --force "
                          "to overwrite it")
    if not force and partial_path(target).exists():
        raise RunLogError(f"{partial_path(target)}: an interrupted run is there; finish it with "
                          f"`mtbudget run --resume {target}` or pass --force to start over")


def _execute(config, settings, *, source, target, force, histogram_every) -> RunResult:
    from .report import result_json
    from .runlog import RunLogWriter, final_path

    copy, hist, notes, resumed, overridden = None, None, [], None, {}
    if source is not None:
        old, copy, notes = _saved_run(source)
        spec = old.header["spec"]
        cfg = parse_config(spec["config"], spec.get("config_path"))
        kept = {k: (tuple(v) if k == "adaptive_outputs" else v) for k, v in old.header.get("settings", {}).items()
                if k in RESUMED_SETTINGS}
        logged = dict(trials=old.header["trials"], seed=spec["seed"], coverage=spec.get("coverage", settings.coverage),
                      block=spec["block"], **kept)
        overridden = {k: v for k, v in logged.items() if getattr(settings, k) is not None and getattr(settings, k) != v}
        settings = replace(settings, sources=spec.get("sources"), **logged)
        config_text = old.config_text or ""
        resumed = old.path
        own = {Path(source).resolve(), Path(old.path).resolve()}
        own |= {final_path(x).resolve() for x in list(own)}
        if Path(target).resolve() not in own:
            # a resume written to another path: what is there belongs to another run and is never overwritten
            _refuse_existing(target, force)
    else:
        cfg = config if isinstance(config, SimulationConfig) else load_config(config)  # a bad config is said first
        _refuse_existing(target, force)
        config_text = cfg.text if cfg.text is not None else cfg.path.read_text() if cfg.path else json.dumps(cfg.source)
    settings.validate().check_limit(settings.block)  # before the log is opened
    # the chunk size the run uses, logged as such (not None for "automatic"): a resume reuses the same value; a log
    # from before this recorded null, and a resume of it applies the same rule again (chunk_blocks_for)
    scenario = build_scenario(cfg, sources=settings.sources)
    settings = replace(settings, chunk_blocks=chunk_blocks_for(settings, settings.block, len(scenario.plan)))
    eng = Engine(scenario, block=settings.block, seed=settings.seed)
    spec = make_spec(scenario, eng, settings)
    keep_vectors = keep_vector_samples(settings, len(scenario.mesh_rows))
    if copy is not None and not keep_vectors:
        # the per-point intervals come from histograms of every trial's per-point errors, which the log does not
        # hold: restore the last histogram checkpoint and recompute the blocks logged after it
        # a checkpoint of format 2 holds the moments of the vector outputs (its blocks do not); one of 1.1 does not
        # (its blocks do)
        verified = {b["block"]: b for b in copy}
        states = [h for h in old.histograms if all(k in verified for k in range(h["blocks"])) and
                  ("moments" in h or all("point_error_moments" in verified[k] for k in range(h["blocks"])))]
        state = max(states, key=lambda h: h["blocks"], default=None)
        upto = state["blocks"] if state is not None else 0
        dropped = sum(1 for b in copy if b["block"] >= upto)
        copy = [b for b in copy if b["block"] < upto]
        if state is not None and "moments" in state:  # the checkpoint's moments, never the blocks' again
            copy = [{k: v for k, v in b.items() if not k.endswith("_moments")} for b in copy]
        if state is not None:
            hist = state
        if dropped:
            notes.append(f"{dropped} logged blocks after the last histogram checkpoint ({upto} blocks) are recomputed, "
                         "so that the per-point intervals cover every trial")
    plugins = [{"name": s.plugin, "source": s.name, "package": s.dist_name, "version": s.dist_version}
               for s in eng.sources]
    to_machine = _to_machine(scenario)
    header = {"spec": spec, "trials": settings.trials, "plugins": plugins, "sources": [s.name for s in eng.sources],
              "outputs": {k: v[0] for k, v in {**SCALARS, **MACHINE_SCALARS}.items()}, "parameter_names": eng.parameter_names,
              "parameter_units": eng.parameter_units, "mesh": scenario.mesh_points.tolist(),
              "mesh_unit": "mm", "commanded": scenario.commanded.tolist(), "weights": scenario.weights_report(),
              **({"commanded_angles": {r: v.tolist() for r, v in scenario.commanded_angles.items()},
                  "commanded_angles_unit": "deg"} if scenario.commanded_angles else {}),
              **({"workpiece_to_machine": to_machine.tolist()} if to_machine is not None else {}),
              "settings": {k: (list(getattr(settings, k)) if k == "adaptive_outputs" else getattr(settings, k))
                           for k in RESUMED_SETTINGS}}
    writer = RunLogWriter(target, header, config_text, log_components=keep_vectors, copy=copy, histogram=hist,
                          histogram_every=histogram_every)
    if resumed is not None:
        writer.log(2, f"resumed from {resumed}: {sum(b['n'] for b in copy)} trials in {len(copy)} blocks taken from "
                      "the log" + ("; the per-point histograms restored from its checkpoint" if hist else ""))
        for n in notes:
            writer.log(3, n)
    result = None
    try:
        result = run(engine=eng, settings=settings, resume_blocks=_block_results(copy), resume_histogram=hist,
                     on_chunk=lambda blocks, res: writer.blocks(blocks, res.convergence[-1], res.acc))
        pm, cm = result.acc.moments.get("point_error"), result.acc.moments.get("components")
        if pm is not None:
            writer.points(scenario.mesh_points, np.asarray(pm.mean), None if cm is None else cm.std)
        if not keep_vectors:  # format 2: the last checkpoint holds the moments of every block, for replay
            writer.checkpoint(result.acc, flush=False)
        writer.finish(result_json(result), True, result.trials)
    except BaseException as exc:
        writer.log(4, f"run stopped: {type(exc).__name__}: {exc}")
        writer.close()
        raise
    result.log_path = target
    result.resume_notes = notes
    #: a resume: the run's logged settings that differ from the ones this call was given (the logged ones were kept)
    result.resume_kept = overridden
    if writer.failed is not None:
        result.log_problem = (f"the run log could not be written ({writer.failed}); {writer.partial} keeps the blocks "
                              f"written before; make room and run `mtbudget run --resume {target}` to complete it")
    return result


def _block_results(raw: list | None) -> list | None:
    """Logged (verified) block messages as BlockResults."""
    if not raw:
        return None
    from .runlog import RunLog

    return RunLog(Path("."), blocks=raw).block_results()


def replay(path) -> RunResult:
    """The results of a logged run, rebuilt from the log without recomputing any trial."""
    from .runlog import read_runlog

    log = read_runlog(path)
    log.require_intact()
    h = log.header
    blocks = sorted(log.block_results(), key=lambda b: b.block)
    logged = log.result or {}
    state = None
    if any(not b.vector_moments() for b in blocks):
        # format 2 (a run that histograms its per-point errors): the moments of the vector outputs are those of the
        # last checkpoint; an interrupted run is replayed up to it (the trials a resume keeps), a finished run's
        # last checkpoint holds every block
        from .runlog import moments_from_state

        state = log.moment_state()
        # its moments, never those of blocks copied from a 1.1 log by a resume again; without a checkpoint (a run cut
        # before its first), the scalars only
        blocks = [replace(b, point_moments=None, parameter_moments=None, component_moments=None)
                  for b in blocks if state is None or b.block < state["blocks"]]
    # the scalars held as the run held them (its trials and keep_samples, logged in the header), so the intervals are
    # the run's: a fixed run of more than KEEP_SAMPLES_TRIALS trials stated histogram intervals, and so does its replay
    keep, keep_until = scalar_keeping(h.get("trials"), (h.get("settings") or {}).get("keep_samples"))
    acc = Accumulator(keep, all(b.components is not None for b in blocks), keep_until)
    if state is not None:
        acc.moments.update(moments_from_state(state))
    for b in blocks:
        accumulate_block(acc, b)
    guf = logged.get("guf_points")
    res = RunResult(h["spec"], acc.n, h["spec"].get("coverage", 0.95), acc, h.get("parameter_names", []),
                    h.get("parameter_units", []), convergence=list(log.convergence),
                    budget=logged.get("budget", {}), complete=log.complete, weights=h.get("weights"),
                    mesh=np.asarray(h["mesh"]) if h.get("mesh") else None,
                    commanded=np.asarray(h["commanded"]) if h.get("commanded") else None,
                    angles={r: np.asarray(v) for r, v in h["commanded_angles"].items()} if h.get("commanded_angles")
                    else None,
                    to_machine=logged_to_machine(h),
                    guf=None if guf is None else {"estimate": np.asarray(guf["estimate"]), "cov": np.asarray(guf["cov"]),
                                                  **({"basis": guf["basis"]} if guf.get("basis") else {})},
                    logged_points=logged.get("points"))
    if acc.n == 0:  # a run killed after its header and before its first block: nothing to state
        raise RunLogError(f"holds no trial ({log.problem or 'no block was saved'}): the run was stopped before its "
                          f"first block of trials was saved; `mtbudget run --resume {path}` runs it again from its "
                          "configuration and seed", path=path)
    if not acc.keep and MAIN_OUTPUT in acc.scalar_names:
        # the log holds every value the run histogrammed: the exact order statistics of the main output, beside
        y = np.concatenate([np.asarray(b.scalars[MAIN_OUTPUT], float) for b in blocks])
        y.sort()
        res.exact_from_log = {"output": MAIN_OUTPUT, "unit": SCALARS[MAIN_OUTPUT][0], "n": int(y.size),
                              "coverage": res.coverage, "symmetric": symmetric_interval(y, res.coverage),
                              "shortest": shortest_interval(y, res.coverage),
                              "method": "order statistics of every logged trial (JCGM 101 7.7.1, 7.7.2)"}
    res.adaptive = logged.get("adaptive")
    res.executor = logged.get("executor")
    res.logged_features = logged.get("features")
    res.log = log
    return res


def verify(path, progress: bool = False) -> dict:
    """Re-run a logged run from its config and seed and compare, bit for bit."""
    from .runlog import read_runlog

    log = read_runlog(path)
    log.require_intact()
    h = log.header
    notes = []
    installed = {s.name: (s.dist_name, s.dist_version) for s in PluginHost().sources()}
    for p in h.get("plugins", []):
        now = installed.get(p["source"])
        if now is None:
            notes.append(f"source {p['source']!r} (plugin {p['name']}, {p['package']} {p['version']}) is not installed now")
        elif now[1] != p["version"]:
            notes.append(f"source {p['source']!r}: logged with {p['package']} {p['version']}, installed now {now[0]} {now[1]}")
    logged_with = h.get("mtbudget_version")
    if logged_with and logged_with != __version__:
        notes.append(f"logged with mtbudget {logged_with}, recomputed with {__version__}: where the computation changed "
                     "between them (docs/performance.md says what changed in which round), the numbers differ")
    with one_blas_thread():
        return _verify(log, h, notes, progress)


def _verify(log, h, notes, progress) -> dict:
    from .executors import engine_from_spec

    eng = engine_from_spec(h["spec"])
    logged = sorted(log.block_results(), key=lambda b: b.block)
    mismatches = []
    bar = progress_bar(len(logged), "verify", "block", progress)
    for lb in logged:
        b = eng.run_block(lb.block)
        for k, v in lb.scalars.items():
            if not np.array_equal(b.scalars[k][: lb.n], v):
                mismatches.append(f"block {lb.block}, output {k}: differs (largest difference "
                                  f"{np.abs(b.scalars[k][:lb.n] - v).max():.3g})")
        bar.update(1)
    bar.close()
    if not log.complete:
        mismatches.append(f"the log is incomplete ({log.problem}): only the {sum(b.n for b in logged)} trials it holds "
                          "were recomputed; finish it with mtbudget run --resume")
    return {"notes": notes, "blocks": len(logged), "trials": sum(b.n for b in logged), "identical": not mismatches,
            "mismatches": mismatches, "complete": log.complete, "mtbudget_version": __version__}

