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
from .errors import RunLogError
from .outputs import BlockResult
from .stats import CoMoments, Moments
from .units import factor

FORMAT = "mtbudget-runlog/1"
FORMAT_MAJOR = 1



# ------------------------------------------------------------------ schemas
def _arr_schema(desc):
    return {"type": "object", "description": desc,
            "properties": {"dtype": {"type": "string"}, "shape": {"type": "array", "items": {"type": "integer"}},
                           "data": {"type": "string", "contentEncoding": "base64"}}}


SCHEMAS = {
    "mtbudget.RunSpec": {"type": "object", "title": "mtbudget.RunSpec", "description": "what the run is; written first",
                         "properties": {
        "format": {"type": "string", "description": "mtbudget-runlog/MAJOR"}, "mtbudget_version": {"type": "string"},
        "spec": {"type": "object", "description": "config (the TOML as a table), config_path, seed, block (trials per block), "
                                                  "sources (names), coverage"},
        "trials": {"type": ["integer", "null"], "description": "trials asked for; null for an adaptive run"},
        "plugins": {"type": "array", "description": "per source: plugin, package and version"},
        "sources": {"type": "array", "items": {"type": "string"}},
        "outputs": {"type": "object", "description": "scalar output -> its unit"},
        "parameter_names": {"type": "array"}, "parameter_units": {"type": "array", "description": "um or urad"},
        "mesh": {"type": "array", "description": "(M0, 3) nominal tool points of the mesh, machine frame", "unit": "mm"},
        "commanded": {"type": "array", "description": "(M0, 3) commanded axis positions of the mesh points", "unit": "mm"},
        "weights": {"type": ["object", "null"], "description": "identification weights stated apart from the drawn noise"}}},
    "mtbudget.Block": {"type": "object", "title": "mtbudget.Block", "description": "one block of trials, in block order",
                       "properties": {
        "block": {"type": "integer"}, "n": {"type": "integer", "description": "trials in the block"},
        "scalars": {"type": "object", "description": "output -> per-trial values in the unit of RunSpec.outputs",
                    "additionalProperties": _arr_schema("per-trial values of one scalar output")},
        "point_error_moments": {"type": "object", "description": "moments (n, mean, m2, min, max) of the 3-D error per point, um"},
        "parameter_moments": {"type": "object", "description": "moments of the identified parameters, um or urad"},
        "component_moments": {"type": "object", "description": "n, mean (M0, 3) and co-moments C (M0, 3, 3) of the per-point "
                                                                "errors per axis, um and um^2"},
        "components": _arr_schema("(n, 3 M0) per-trial errors per point and axis, um (absent for runs too long to log them)"),
        "not_converged": {"type": "integer", "description": "trials whose identification did not converge"},
        "fallbacks": {"type": "integer", "description": "trials the fast identification handed to full Gauss-Newton"}}},
    "mtbudget.Convergence": {"type": "object", "title": "mtbudget.Convergence",
                             "description": "the main output after each chunk (Foxglove's Plot panel reads it)", "properties": {
        "trials": {"type": "integer"}, "output": {"type": "string", "description": "which output"},
        "unit": {"type": "string"}, "mean": {"type": "number"}, "std": {"type": "number", "description": "standard deviation over trials"},
        "low": {"type": "number", "description": "symmetric coverage interval, low end"},
        "high": {"type": "number", "description": "symmetric coverage interval, high end"}}},
    "mtbudget.Result": {"type": "object", "title": "mtbudget.Result",
                        "description": "the final results, as `mtbudget run --json` prints them", "properties": {
        "trials": {"type": "integer"}, "coverage": {"type": "number"}, "complete": {"type": "boolean"},
        "seed": {"type": "integer"}, "not_converged": {"type": "integer"},
        "outputs": {"type": "object", "description": "scalar output -> unit, description, mean, std, symmetric, shortest"},
        "budget": {"type": "object", "description": "output -> one-source-at-a-time budget; 'points': the per-point budget"},
        "measurand": {"type": "string"},
        "points": {"type": "array", "description": "per mesh point: nominal (mm), mean, u, covariance, interval, guf_u, clause8 (um)"},
        "points_summary": {"type": "object"}, "guf_points": {"type": "object"},
        "convergence": {"type": "array"}, "validation": {"type": ["object", "null"]}}},
    "mtbudget.End": {"type": "object", "title": "mtbudget.End", "description": "written last; absent when the run was cut",
                     "properties": {"trials": {"type": "integer"}, "complete": {"type": "boolean"}}},
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


def _comoments_enc(m: CoMoments) -> dict:
    return {"n": m.n, "mean": _enc(m.mean), "C": _enc(m.C)}


def _comoments_dec(d) -> CoMoments:
    return CoMoments(int(d["n"]), _dec(d["mean"]), _dec(d["C"]))


def _moments_dec(d) -> Moments:
    return Moments(int(d["n"]), _dec(d["mean"]), _dec(d["m2"]), _dec(d["min"]), _dec(d["max"]))


# ------------------------------------------------------------------ writing
class RunLogWriter:
    """Writes a run log as the run goes: header first, then blocks (flushed and fsynced per chunk), then the end."""

    def __init__(self, path, header: dict, config_text: str, force: bool = False, log_components: bool = True):
        from mcap.writer import Writer

        self.path = Path(path)
        if self.path.exists() and not force:
            raise RunLogError(f"{self.path}: a run log is already there; choose another --log path or pass --force "
                              "to overwrite it")
        try:
            self.fh = open(self.path, "wb")
        except OSError as exc:
            raise RunLogError(f"{self.path}: cannot write the run log ({exc.strerror})") from None
        self.log_components = log_components
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
        spec = header["spec"]
        self.w.add_metadata("mtbudget.run", {
            "format": FORMAT, "mtbudget_version": __version__, "seed": str(spec["seed"]), "trials": str(header["trials"]),
            "host": socket.gethostname(), "platform": platform.platform(), "start_time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "plugins": json.dumps(header.get("plugins", []))})
        self.write("/mtbudget/run", {"format": FORMAT, "mtbudget_version": __version__, **header})
        self.flush()

    def write(self, topic, obj):
        t = time.time_ns()
        self.w.add_message(channel_id=self.ch[topic], log_time=t, publish_time=t, data=json.dumps(obj).encode())

    def flush(self):
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def blocks(self, blocks: list, convergence: dict):
        """Log merged blocks and the convergence row after them; flushed to disk before returning."""
        for b in blocks:
            vm = b.vector_moments()
            self.write("/mtbudget/blocks", {
                "block": b.block, "n": b.n, "scalars": {k: _enc(v) for k, v in b.scalars.items()},
                "point_error_moments": _moments_enc(vm["point_error"]),
                "parameter_moments": _moments_enc(vm["parameters"]), "not_converged": int(b.not_converged), "fallbacks": int(b.fallbacks),
                **({"component_moments": _comoments_enc(vm["components"])} if "components" in vm else {}),
                **({"components": _enc(b.components.reshape(b.n, -1))}
                   if self.log_components and b.components is not None else {})})
        self.write("/mtbudget/convergence", convergence)
        self.flush()

    def log(self, level: int, message: str):
        t = time.time_ns()
        self.write("/mtbudget/log", {"timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "level": level,
                                     "message": message, "name": "mtbudget", "file": "", "line": 0})

    def points(self, mesh_mm: np.ndarray, mean_error: np.ndarray, u: np.ndarray | None = None):
        """The mesh as a foxglove.PointCloud (metres, as Foxglove reads them): fields error_um (mean error left
        after compensation) and, when given, u_x_um, u_y_um, u_z_um (standard uncertainty per axis) to colour by."""
        cols = [mesh_mm * factor("mm", "m"), mean_error[:, None]] + ([u] if u is not None else [])
        pts = np.column_stack(cols).astype("<f4")
        t = time.time_ns()
        self.write("/mtbudget/points", {
            "timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "frame_id": "machine",
            "pose": {"position": {"x": 0, "y": 0, "z": 0}, "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}},
            "point_stride": 4 * pts.shape[1],
            "fields": [{"name": name, "offset": 4 * i, "type": 7} for i, name in
                       enumerate(["x", "y", "z", "error_um"] + (["u_x_um", "u_y_um", "u_z_um"] if u is not None else []))],
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
        """Logged blocks as BlockResults: scalars exact, the vector outputs known by their moments.

        They merge into a run's statistics (replay, resume) exactly as the blocks they were written from.
        """
        out = []
        for b in self.blocks:
            comp = _dec(b["components"]).reshape(b["n"], -1, 3) if "components" in b else None
            cm = _comoments_dec(b["component_moments"]) if "component_moments" in b else None
            out.append(BlockResult(b["block"], b["n"], {k: _dec(v) for k, v in b["scalars"].items()}, None, None,
                                   int(b.get("not_converged", 0)), _moments_dec(b["point_error_moments"]),
                                   _moments_dec(b["parameter_moments"]), components=comp, component_moments=cm,
                                   fallbacks=int(b.get("fallbacks", 0))))
        return out


def read_runlog(path) -> RunLog:
    """Read a run log record by record; a truncated or damaged tail is reported, not raised."""
    from mcap.exceptions import McapError
    from mcap.records import Attachment, Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    path = Path(path)
    if not path.exists():
        raise RunLogError(f"{path}: no such file")
    log = RunLog(path)
    placement = False
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
                elif isinstance(rec, Metadata) and rec.name == "mtbudget.placement":
                    placement = True
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
        if log.metadata.get("format", "").startswith("mtbudget-placement/") or placement:
            raise RunLogError(f"{path}: a placement study log, not a run log; `mtbudget replay {path}` prints its summary")
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


# ------------------------------------------------------------------ placement study logs
PLACEMENT_FORMAT = "mtbudget-placement/1"
PLACEMENT_SCHEMA = {"type": "object", "title": "mtbudget.PlacementStudy", "properties": {
    "settings": {"type": "object", "description": "tests, candidate stations per test, tracker noise (units in the key names)"},
    "reduction": {"type": "object", "description": "the better direction and its reduction of the mean maximum error"},
    "directions": {"type": "object", "description": "per direction: the station space (mm) and statistics of the maximum u_p (um)"},
    "fits": {"type": "object"}, "seconds": {"type": "number"},
    "arrays": {"type": "object", "description": "per direction: best_location (tests, 3) in mm and max_error_um (tests,) in um",
               "additionalProperties": {"type": "object", "additionalProperties": _arr_schema("float64 array")}}}}


def write_placement_log(body: dict, arrays: dict, path: Path, config_text: str | None, seed: int):
    """Log the placement study to MCAP: its summary (``body``) and per-test arrays (float64, base64)."""
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh, use_chunking=False)
        w.start(profile="", library=f"mtbudget {__version__}")
        sid = w.register_schema(name="mtbudget.PlacementStudy", encoding="jsonschema",
                                data=json.dumps(PLACEMENT_SCHEMA).encode())
        ch = w.register_channel(topic="/mtbudget/placement", message_encoding="json", schema_id=sid)
        t = time.time_ns()
        if config_text:
            w.add_attachment(create_time=t, log_time=t, name="config.toml", media_type="application/toml",
                             data=config_text.encode())
        w.add_metadata("mtbudget.placement", {"format": PLACEMENT_FORMAT, "mtbudget_version": __version__,
                                              "seed": str(seed)})
        body = dict(body)
        body["arrays"] = {k: {name: _enc(a) for name, a in d.items()} for k, d in arrays.items()}
        w.add_message(channel_id=ch, log_time=t, publish_time=t, data=json.dumps(body).encode())
        w.finish()


def log_kind(path) -> str:
    """"run" or "placement", from the file's metadata (RunLogError when it is neither or not MCAP)."""
    from mcap.records import Metadata
    from mcap.stream_reader import StreamReader

    path = Path(path)
    if not path.exists():
        raise RunLogError(f"{path}: no such file")
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89MCAP0\r\n":
            raise RunLogError(f"{path}: not an MCAP file (bad magic bytes)")
        fh.seek(0)
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, Metadata) and rec.name == "mtbudget.placement":
                    return "placement"
                if isinstance(rec, Metadata) and rec.name == "mtbudget.run":
                    return "run"
        except Exception:
            pass
    return "run"


def read_placement_log(path) -> dict:
    """The summary of a placement study log (as placement.json holds it), with its per-test arrays."""
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, Message):
                    body = json.loads(rec.data)
                    body["arrays"] = {k: {name: _dec(a) for name, a in d.items()} for k, d in body.get("arrays", {}).items()}
                    return body
        except Exception as exc:
            raise RunLogError(f"{path}: damaged placement log ({type(exc).__name__}: {exc})") from None
    raise RunLogError(f"{path}: the placement log holds no study (cut before its only record)")
