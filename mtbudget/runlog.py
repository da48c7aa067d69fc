"""MCAP run logs: write as the run goes, read (even truncated), replay, resume, verify.

Layout (docs/runlog.md has every schema):

* attachment ``config.toml``: the configuration as given (its raw TOML);
* metadata ``mtbudget.run``: format version, mtbudget version, seed, trials,
  plugins with versions, host, start time;
* ``/mtbudget/run`` (one message): the run spec, so a file cut short still
  says what it was;
* ``/mtbudget/blocks``: one message per block of trials with the scalar
  outputs of every trial (float64, base64) and the moments of the vector
  outputs -- everything replay needs, nothing executable;
* ``/mtbudget/convergence``: trials, mean, std and interval ends of the main
  output after each chunk (Foxglove's Plot panel reads it);
* ``/mtbudget/points``: ``foxglove.PointCloud`` of the mesh coloured by the
  mean error left after compensation;
* ``/mtbudget/log``: ``foxglove.Log`` warnings and errors;
* ``/mtbudget/result``: the final outputs and budget; ``/mtbudget/end``.

The file is written without chunking and flushed after every chunk of
trials, so a run killed at any moment leaves a file that reads up to its last
complete record.
"""

from __future__ import annotations

import base64
import json
import os
import platform
import socket
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .config import SimulationConfig, load_config, parse_config
from .engine import SCALARS, Accumulator, BlockResult, Engine, RunResult, run
from .errors import RunLogError
from .stats import Moments

FORMAT = "mtbudget-runlog/1"
FORMAT_MAJOR = 1



# ------------------------------------------------------------------ schemas
def _arr_schema(desc):
    return {"type": "object", "description": desc,
            "properties": {"dtype": {"type": "string"}, "shape": {"type": "array", "items": {"type": "integer"}},
                           "data": {"type": "string", "contentEncoding": "base64"}}}


SCHEMAS = {
    "mtbudget.RunSpec": {"type": "object", "title": "mtbudget.RunSpec", "properties": {
        "format": {"type": "string"}, "spec": {"type": "object"}, "trials": {"type": ["integer", "null"]},
        "plugins": {"type": "array"}, "sources": {"type": "array"}, "outputs": {"type": "object"},
        "parameter_names": {"type": "array"}, "parameter_units": {"type": "array"}}},
    "mtbudget.Block": {"type": "object", "title": "mtbudget.Block", "properties": {
        "block": {"type": "integer"}, "n": {"type": "integer"},
        "scalars": {"type": "object", "additionalProperties": _arr_schema("per-trial values of one scalar output")},
        "point_error_moments": {"type": "object"}, "parameter_moments": {"type": "object"}}},
    "mtbudget.Convergence": {"type": "object", "title": "mtbudget.Convergence", "properties": {
        "trials": {"type": "integer"}, "mean": {"type": "number"}, "std": {"type": "number"},
        "low": {"type": "number"}, "high": {"type": "number"}}},
    "mtbudget.Result": {"type": "object", "title": "mtbudget.Result"},
    "mtbudget.End": {"type": "object", "title": "mtbudget.End", "properties": {"trials": {"type": "integer"}, "complete": {"type": "boolean"}}},
    "foxglove.Log": {"title": "foxglove.Log", "type": "object", "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "level": {"type": "integer", "description": "0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal"},
        "message": {"type": "string"}, "name": {"type": "string"}, "file": {"type": "string"}, "line": {"type": "integer"}}},
    "foxglove.PointCloud": {"title": "foxglove.PointCloud", "type": "object", "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "pose": {"type": "object", "properties": {
            "position": {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}},
            "orientation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}}},
        "point_stride": {"type": "integer"},
        "fields": {"type": "array", "items": {"type": "object", "properties": {
            "name": {"type": "string"}, "offset": {"type": "integer"}, "type": {"type": "integer"}}}},
        "data": {"type": "string", "contentEncoding": "base64"}}},
}
TOPICS = {
    "/mtbudget/run": "mtbudget.RunSpec", "/mtbudget/blocks": "mtbudget.Block", "/mtbudget/convergence": "mtbudget.Convergence",
    "/mtbudget/points": "foxglove.PointCloud", "/mtbudget/log": "foxglove.Log", "/mtbudget/result": "mtbudget.Result",
    "/mtbudget/end": "mtbudget.End",
}


def _enc(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a, dtype="<f8")
    return {"dtype": "<f8", "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode()}


def _dec(d: dict) -> np.ndarray:
    if d.get("dtype") != "<f8":
        raise RunLogError(f"unsupported array dtype {d.get('dtype')!r} in run log")
    return np.frombuffer(base64.b64decode(d["data"]), dtype="<f8").reshape(d["shape"]).copy()


def _moments_enc(m: Moments) -> dict:
    return {"n": m.n, "mean": _enc(np.asarray(m.mean)), "m2": _enc(np.asarray(m.m2)),
            "min": _enc(np.asarray(m.minimum)), "max": _enc(np.asarray(m.maximum))}


def _moments_dec(d) -> Moments:
    return Moments(int(d["n"]), _dec(d["mean"]), _dec(d["m2"]), _dec(d["min"]), _dec(d["max"]))


# ------------------------------------------------------------------ writing
class RunLogWriter:
    def __init__(self, path, spec: dict, engine: Engine, trials, config_text: str):
        from mcap.writer import Writer

        self.path = Path(path)
        self.fh = open(self.path, "wb")
        self.w = Writer(self.fh, use_chunking=False, use_statistics=True)
        self.w.start(profile="", library=f"mtbudget {__version__}")
        self.ch = {}
        sids = {name: self.w.register_schema(name=name, encoding="jsonschema", data=json.dumps(s).encode())
                for name, s in SCHEMAS.items()}
        for topic, schema in TOPICS.items():
            self.ch[topic] = self.w.register_channel(topic=topic, message_encoding="json", schema_id=sids[schema])
        now = time.time_ns()
        self.w.add_attachment(create_time=now, log_time=now, name="config.toml", media_type="application/toml",
                              data=config_text.encode())
        plugins = [{"name": s.plugin, "source": s.name, "package": s.dist_name, "version": s.dist_version}
                   for s in engine.sources]
        self.w.add_metadata("mtbudget.run", {
            "format": FORMAT, "mtbudget_version": __version__, "seed": str(spec["seed"]), "trials": str(trials),
            "host": socket.gethostname(), "platform": platform.platform(), "start_time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "plugins": json.dumps(plugins)})
        self.write("/mtbudget/run", {"format": FORMAT, "mtbudget_version": __version__, "spec": spec, "trials": trials,
                                     "plugins": plugins, "sources": [s.name for s in engine.sources],
                                     "outputs": {k: v[0] for k, v in SCALARS.items()},
                                     "parameter_names": engine.parameter_names, "parameter_units": engine.parameter_units,
                                     "mesh": engine.truth.machine_points(np.zeros(engine.truth.n_params))[0][engine.mesh_rows].tolist()})
        self.mesh = engine.truth.machine_points(np.zeros(engine.truth.n_params))[0][engine.mesh_rows]
        self.flush()

    def write(self, topic, obj):
        t = time.time_ns()
        self.w.add_message(channel_id=self.ch[topic], log_time=t, publish_time=t, data=json.dumps(obj).encode())

    def flush(self):
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def blocks(self, blocks: list, result: RunResult):
        for b in blocks:
            self.write("/mtbudget/blocks", {
                "block": b.block, "n": b.n, "scalars": {k: _enc(v) for k, v in b.scalars.items()},
                "point_error_moments": _moments_enc(getattr(b, "point_moments", None) or Moments.of(b.point_error)),
                "parameter_moments": _moments_enc(getattr(b, "parameter_moments", None) or Moments.of(b.parameters))})
        c = result.convergence[-1]
        self.write("/mtbudget/convergence", c)
        self.flush()

    def log(self, level: int, message: str):
        t = time.time_ns()
        self.write("/mtbudget/log", {"timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "level": level,
                                     "message": message, "name": "mtbudget", "file": "", "line": 0})

    def points(self, mean_error: np.ndarray):
        pts = np.column_stack([self.mesh, mean_error]).astype("<f4")
        t = time.time_ns()
        self.write("/mtbudget/points", {
            "timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "frame_id": "machine",
            "pose": {"position": {"x": 0, "y": 0, "z": 0}, "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}},
            "point_stride": 16,
            "fields": [{"name": "x", "offset": 0, "type": 7}, {"name": "y", "offset": 4, "type": 7},
                       {"name": "z", "offset": 8, "type": 7}, {"name": "error_um", "offset": 12, "type": 7}],
            "data": base64.b64encode(pts.tobytes()).decode()})

    def finish(self, result_obj: dict | None, complete: bool, trials: int):
        if result_obj is not None:
            self.write("/mtbudget/result", result_obj)
        self.write("/mtbudget/end", {"trials": trials, "complete": complete})
        self.w.finish()
        self.fh.close()


# ------------------------------------------------------------------ reading
@dataclass
class RunLog:
    path: Path
    header: dict | None = None
    metadata: dict = field(default_factory=dict)
    config_text: str | None = None
    blocks: list = field(default_factory=list)
    convergence: list = field(default_factory=list)
    result: dict | None = None
    end: dict | None = None
    logs: list = field(default_factory=list)
    truncated: bool = False
    problem: str | None = None

    @property
    def complete(self) -> bool:
        return bool(self.end and self.end.get("complete")) and not self.truncated

    def block_results(self) -> list:
        """Logged blocks as BlockResults (vector outputs as their moments)."""
        out = []
        for b in self.blocks:
            out.append(LoggedBlock(b["block"], b["n"], {k: _dec(v) for k, v in b["scalars"].items()},
                                   _moments_dec(b["point_error_moments"]), _moments_dec(b["parameter_moments"])))
        return out


class LoggedBlock(BlockResult):
    """A block read back from a log: scalars exact, the vector outputs known by their moments.

    It merges into an Accumulator (replay, resume) exactly as the block it was written from.
    """

    def __init__(self, block: int, n: int, scalars: dict, point_moments: Moments, parameter_moments: Moments):
        super().__init__(block, n, scalars, None, None)
        self.point_moments, self.parameter_moments = point_moments, parameter_moments


def read_runlog(path) -> RunLog:
    """Read a run log record by record; a truncated or damaged tail is reported, not raised."""
    from mcap.exceptions import McapError
    from mcap.records import Attachment, Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    path = Path(path)
    if not path.exists():
        raise RunLogError(f"{path}: no such file")
    log = RunLog(path)
    channels, schemas = {}, {}
    with open(path, "rb") as fh:
        head = fh.read(8)
        if head != b"\x89MCAP0\r\n":
            raise RunLogError(f"{path}: not an MCAP file (bad magic bytes)")
        fh.seek(0)
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Attachment) and rec.name == "config.toml":
                    log.config_text = rec.data.decode()
                elif isinstance(rec, Metadata) and rec.name == "mtbudget.run":
                    log.metadata = dict(rec.metadata)
                    _check_format(path, log.metadata.get("format"))
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None:
                        continue
                    sch = schemas.get(ch.schema_id)
                    if ch.topic in TOPICS and (sch is None or sch.name != TOPICS[ch.topic]):
                        raise RunLogError(f"{path}: topic {ch.topic} has unknown schema {getattr(sch, 'name', None)!r}")
                    if ch.topic not in TOPICS:
                        continue  # other tools' topics are kept and ignored
                    obj = json.loads(rec.data)
                    if ch.topic == "/mtbudget/run":
                        _check_format(path, obj.get("format"))
                        log.header = obj
                    elif ch.topic == "/mtbudget/blocks":
                        log.blocks.append(obj)
                    elif ch.topic == "/mtbudget/convergence":
                        log.convergence.append(obj)
                    elif ch.topic == "/mtbudget/result":
                        log.result = obj
                    elif ch.topic == "/mtbudget/end":
                        log.end = obj
                    elif ch.topic == "/mtbudget/log":
                        log.logs.append(obj)
        except RunLogError:
            raise
        except (McapError, struct.error, EOFError, ValueError, json.JSONDecodeError, KeyError) as exc:
            log.truncated = True
            log.problem = f"{type(exc).__name__}: {exc}"
    if log.header is None:
        raise RunLogError(f"{path}: no run header; the file is not an mtbudget run log or was cut before its first record")
    if log.end is None:
        log.truncated = True
        log.problem = log.problem or "the run did not finish (no end record)"
    return log


def _check_format(path, fmt):
    if fmt is None:
        return
    try:
        name, ver = fmt.split("/")
        major = int(ver.split(".")[0])
    except Exception:
        raise RunLogError(f"{path}: unreadable format tag {fmt!r}") from None
    if name != "mtbudget-runlog":
        raise RunLogError(f"{path}: format {fmt!r} is not an mtbudget run log")
    if major > FORMAT_MAJOR:
        raise RunLogError(f"{path}: written by a newer mtbudget (format {fmt}); this version reads {FORMAT}. Upgrade mtbudget.")


def accumulate(log: RunLog, keep_samples: bool = True) -> Accumulator:
    """Rebuild the statistics of a run from its logged blocks, in the same merge order as the run."""
    acc = Accumulator(keep_samples)
    for b in sorted(log.block_results(), key=lambda b: b.block):
        acc.add(b)
    return acc


def replay(path) -> RunResult:
    """The results of a logged run, rebuilt from the log without recomputing any trial."""
    log = read_runlog(path)
    h = log.header
    acc = accumulate(log)
    res = RunResult(h["spec"], acc.n, h["spec"].get("coverage", 0.95), acc, h.get("parameter_names", []),
                    h.get("parameter_units", []), convergence=list(log.convergence),
                    budget=(log.result or {}).get("budget", {}), complete=log.complete)
    res.log = log
    return res


# ------------------------------------------------------------------ the run command
def execute(config=None, *, trials=1000, seed=None, coverage=0.95, executor="inline", workers=None, address=None,
            attribution_trials=512, log_path=None, resume_path=None, progress=True, block=64, chunk_blocks=4,
            sources=None, adaptive_batch=None) -> RunResult:
    """Run (or resume) a Monte Carlo study and log it to MCAP; what ``mtbudget run`` does."""
    resume_blocks = None
    if resume_path is not None:
        old = read_runlog(resume_path)
        if old.complete:
            raise RunLogError(f"{resume_path}: the run is complete; nothing to resume (use mtbudget replay)")
        spec = old.header["spec"]
        cfg = parse_config(spec["config"], spec.get("config_path"))
        trials, seed, coverage, block = old.header["trials"], spec["seed"], spec.get("coverage", coverage), spec["block"]
        sources = spec.get("sources")
        config_text = old.config_text or ""
        resume_blocks = old.block_results()
        log_path = Path(log_path or resume_path)
        if log_path.resolve() == Path(resume_path).resolve():
            partial = Path(str(resume_path) + ".partial")
            os.replace(resume_path, partial)
    else:
        cfg = config if isinstance(config, SimulationConfig) else load_config(config)
        config_text = cfg.path.read_text() if cfg.path else json.dumps(cfg.source)
        log_path = Path(log_path or "mtbudget-run.mcap")
    eng = Engine(cfg, block=block, sources=sources, seed=seed)
    from .engine import make_spec

    spec = make_spec(cfg, seed=eng.seed, block=eng.block, sources=[s.name for s in eng.sources], coverage=coverage)
    writer = RunLogWriter(log_path, spec, eng, trials, config_text)
    if resume_blocks:
        writer.log(2, f"resumed from {resume_path}: {sum(b.n for b in resume_blocks)} trials in "
                      f"{len(resume_blocks)} blocks taken from the log")

    def on_chunk(blocks, result):
        writer.blocks(blocks, result)

    result = None
    try:
        result = run(cfg, trials=trials, seed=eng.seed, coverage=coverage, engine=eng, executor=executor,
                     workers=workers, address=address, progress=progress, attribution_trials=attribution_trials,
                     chunk_blocks=chunk_blocks, on_chunk=on_chunk, resume_blocks=resume_blocks,
                     adaptive_batch=adaptive_batch)
        from .report import result_json

        pm = result.acc.moments.get("point_error")
        if pm is not None:
            writer.points(np.asarray(pm.mean))
        writer.finish(result_json(result), True, result.trials)
        if resume_path is not None and Path(str(resume_path) + ".partial").exists():
            os.remove(str(resume_path) + ".partial")
    except BaseException as exc:
        try:
            writer.log(4, f"run stopped: {type(exc).__name__}: {exc}")
            writer.finish(None, False, result.trials if result else 0)
        except Exception:
            pass
        raise
    result.log_path = log_path
    return result


def verify(path) -> dict:
    """Re-run a logged run from its config and seed and compare, bit for bit."""
    from .plugins import PluginHost

    log = read_runlog(path)
    h = log.header
    notes = []
    host = PluginHost()
    installed = {s.name: (s.dist_name, s.dist_version) for s in host.sources()}
    for p in h.get("plugins", []):
        now = installed.get(p["source"])
        if now is None:
            notes.append(f"source {p['source']!r} (plugin {p['name']}, {p['package']} {p['version']}) is not installed now")
        elif now[1] != p["version"]:
            notes.append(f"source {p['source']!r}: logged with {p['package']} {p['version']}, installed now {now[0]} {now[1]}")
    spec = h["spec"]
    cfg = parse_config(spec["config"], spec.get("config_path"))
    eng = Engine(cfg, block=spec["block"], sources=spec.get("sources"), seed=spec["seed"])
    logged = sorted(log.block_results(), key=lambda b: b.block)
    mismatches = []
    for lb in logged:
        b = eng.run_block(lb.block)
        for k, v in lb.scalars.items():
            if not np.array_equal(b.scalars[k][: lb.n], v):
                mismatches.append(f"block {lb.block}, output {k}: differs (largest difference "
                                  f"{np.abs(b.scalars[k][:lb.n] - v).max():.3g})")
    return {"notes": notes, "blocks": len(logged), "trials": sum(b.n for b in logged), "identical": not mismatches,
            "mismatches": mismatches, "complete": log.complete}
