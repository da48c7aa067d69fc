"""MCAP run logs: write as the run goes, read (even truncated), replay, resume, verify.

Layout (docs/runlog.md has every schema):

* attachment ``config.toml``: the configuration as given (its raw TOML);
* metadata ``mtbudget.run``: format version, mtbudget version, seed, trials,
  plugins with versions, host, start time;
* ``/mtbudget/run`` (one message): the run spec, so a file cut short still
  says what it was;
* ``/mtbudget/blocks``: one message per block of trials with the scalar
  outputs of every trial (float64, base64) and the moments of the vector
  outputs -- everything replay needs, nothing executable (format 2, a run
  that histograms its per-point errors: the moments of the run so far are in
  its histogram checkpoints instead, docs/runlog.md);
* ``/mtbudget/convergence``: trials, mean, std and interval ends of the main
  output after each chunk (Foxglove's Plot panel reads it);
* ``/mtbudget/points``: ``foxglove.PointCloud`` of the mesh coloured by the
  mean error left after compensation;
* ``/mtbudget/log``: ``foxglove.Log`` warnings and errors;
* ``/mtbudget/result``: the final outputs and budget; ``/mtbudget/end``.

The file is written without chunking, under ``LOG.partial``, and flushed
(fsynced) after every chunk of trials, so a run killed at any moment leaves a
file that reads up to its last complete record; it is renamed to ``LOG``
when the run completes.  Every message on mtbudget's topics carries a
``crc32`` of its topic and body, and a finished file the MCAP data-section
and summary CRCs: a damaged record is reported (file, byte offset, block) and
never used.  ``RunLogLock`` keeps two runs off one log.
"""

from __future__ import annotations

import base64
import errno
import io
import json
import os
import platform
import re
import socket
import struct
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .errors import RunLogError
from .outputs import BlockResult
from .stats import CoMoments, Moments
from .units import factor

FORMAT = "mtbudget-runlog/1.1"  # 1.1: a crc32 in every message, histogram checkpoints
#: runs that histogram their per-point errors: blocks without the vector outputs' moments, which the histogram
#: checkpoints hold for the run so far (a major version: an mtbudget that reads only 1.x refuses it in one line)
HISTOGRAM_FORMAT = "mtbudget-runlog/2"
FORMAT_MAJOR = 2
LEGACY_FORMAT = "mtbudget-runlog/1"  # before checksums: read, unverified



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
        "point_error_moments": {"type": "object", "description": "moments (n, mean, m2, min, max) of the 3-D error per point, "
                                                                  "um (format 1.1; format 2: in the histogram checkpoints)"},
        "parameter_moments": {"type": "object", "description": "moments of the identified parameters, um or urad (format 1.1)"},
        "component_moments": {"type": "object", "description": "n, mean (M0, 3) and co-moments C (M0, 3, 3) of the per-point "
                                                                "errors per axis, um and um^2 (format 1.1)"},
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
        "outputs": {"type": "object", "description": "scalar output -> unit, description, mean, std, symmetric, shortest, "
                                                     "interval_method"},
        "executor": {"type": "object", "description": "what ran the trials: kind (inline, thread, process, dask), "
                                                      "workers, requested (the --executor given)"},
        "budget": {"type": "object", "description": "output -> one-source-at-a-time budget; 'points': the per-point budget"},
        "measurand": {"type": "string"},
        "points": {"type": "array", "description": "per mesh point: nominal (mm), mean, u, covariance, interval, guf_u, clause8 (um)"},
        "points_summary": {"type": "object"}, "guf_points": {"type": "object"},
        "convergence": {"type": "array"}, "validation": {"type": ["object", "null"]}}},
    "mtbudget.HistogramState": {"type": "object", "title": "mtbudget.HistogramState",
                                "description": "checkpoint of the per-point histograms of a run too long to log every "
                                               "trial's per-point errors; a resume restores it", "properties": {
        "blocks": {"type": "integer", "description": "blocks merged (0 .. blocks-1)"}, "trials": {"type": "integer"},
        "last_block": {"type": "integer"}, "bins": {"type": "integer"},
        "low": _arr_schema("(3 M0,) low end of each component's range, um"),
        "high": _arr_schema("(3 M0,) high end of each component's range, um"),
        "counts": {"type": "object", "description": "(3 M0, bins) int64 counts, zlib then base64"},
        "under": {"type": "object", "description": "(3 M0,) counts below the range"},
        "over": {"type": "object", "description": "(3 M0,) counts above the range"},
        "moments": {"type": "object", "description": "format 2: the moments of the vector outputs over blocks 0 .. blocks-1 "
                                                     "(point_error, parameters: n, mean, m2, min, max; components: n, mean, C)"}}},
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
    "/mtbudget/end": "mtbudget.End", "/mtbudget/histogram": "mtbudget.HistogramState",
}


class _B64(str):
    """Base64 text of an array: a string like any other to ``json``, which :func:`_with_crc` puts into the message's
    JSON text as it is (base64 has no character JSON escapes) instead of having ``json`` scan it."""

    __slots__ = ()


def _enc(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a, dtype="<f8")
    return {"dtype": "<f8", "shape": list(a.shape), "data": _B64(base64.b64encode(a.tobytes()).decode())}


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


# ------------------------------------------------------------------ checksums
def _body_crc(topic: str, obj: dict) -> int:
    """CRC-32 of a message's topic and its JSON body without the ``crc32`` key (written last)."""
    return zlib.crc32(json.dumps(obj).encode(), zlib.crc32(topic.encode() + b"\n"))


#: a base64 text's place in a serialised message: json.dumps renders the placeholder "\x00<i>" as "\u0000<i>"
_SLOT = re.compile(rb'"\\u0000(\d+)"')


def _dumps(body: dict) -> bytes:
    """``json.dumps(body).encode()``, the same bytes, with the base64 texts of the arrays at the body's top level (a
    block's per-trial components: 150 kB for 64 trials of the paper's mesh) copied in rather than scanned by ``json``:
    the body is serialised with a placeholder for each, and the texts are put in their place.  Arrays deeper down
    (the scalars, the moments) are small and serialised by ``json`` as the strings they are."""
    texts: list = []
    skeleton = body
    for k, v in body.items():
        if type(v) is dict and type(v.get("data")) is _B64:
            if skeleton is body:
                skeleton = dict(body)
            texts.append(v["data"])
            skeleton[k] = {**v, "data": f"\x00{len(texts) - 1}"}
    if not texts:
        return json.dumps(body).encode()
    parts = _SLOT.split(json.dumps(skeleton).encode())
    if len(parts) != 2 * len(texts) + 1 or [int(i) for i in parts[1::2]] != list(range(len(texts))):
        return json.dumps(body).encode()  # a placeholder that is not ours (never in mtbudget's messages)
    out = [parts[0]]
    for i, text in enumerate(texts):
        out += [b'"', text.encode("ascii"), b'"', parts[2 * i + 2]]
    return b"".join(out)


def _with_crc(topic: str, obj: dict) -> bytes:
    """The message's JSON with its ``crc32`` as the last field: ``json.dumps({**body, "crc32": crc})``, built from the
    one serialisation the checksum needs (the body is not serialised twice, its base64 texts not scanned)."""
    body = {k: v for k, v in obj.items() if k != "crc32"}
    text = _dumps(body)
    crc = zlib.crc32(text, zlib.crc32(topic.encode() + b"\n"))
    if not body:
        return b'{"crc32": %d}' % crc
    return text[:-1] + b', "crc32": %d}' % crc


def partial_path(path) -> Path:
    """Where a run log is written until the run completes: ``LOG.partial``."""
    return Path(str(path) + ".partial")


def final_path(path) -> Path:
    """The log a path names: ``LOG`` for ``LOG`` and for ``LOG.partial``."""
    path = Path(path)
    return path.with_name(path.name[: -len(".partial")]) if path.name.endswith(".partial") else path


def _fsync_dir(path: Path):
    try:
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# ------------------------------------------------------------------ locking
class RunLogLock:
    """An exclusive lock on a run log (``fcntl.flock`` on ``LOG.lock``, released when the process ends, even killed).

    A second run on the same log is refused with one line naming the holder's PID.
    """

    def __init__(self, path):
        self.log = final_path(path)
        self.path = Path(str(self.log) + ".lock")
        self.fd = None
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX: no lock
            return
        for _ in range(5):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                if not self.path.parent.is_dir():  # what the user can act on: the folder, not our lock file
                    raise RunLogError(f"{self.log}: the folder {self.path.parent} does not exist; create it or choose "
                                      "another --log") from None
                raise RunLogError(f"{self.path}: cannot create the run log's lock file ({exc.strerror})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                try:
                    pid = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
                finally:
                    os.close(fd)
                raise RunLogError(f"{self.log}: another mtbudget run (PID {pid}) is writing this log; wait for it, "
                                  "stop it, or choose another --log") from None
            try:  # the file we locked must still be the one at the path (another run may have removed it)
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except OSError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                self.fd = fd
                return
            os.close(fd)
        raise RunLogError(f"{self.path}: could not take the run log's lock")  # pragma: no cover

    def release(self):
        if self.fd is not None:
            try:
                os.unlink(self.path)
            except OSError:
                pass
            os.close(self.fd)
            self.fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


# ------------------------------------------------------------------ writing
#: seconds: the shortest interval between two histogram checkpoints of a run (``RunLogWriter.blocks``); the
#: interval then grows to half the run's age, up to the writer's ``histogram_every`` (a checkpoint of the paper mesh
#: is about 1 MB and 15 ms)
FIRST_CHECKPOINT = 5.0


class RunLogWriter:
    """Writes a run log as the run goes: header first, then blocks (flushed and fsynced per chunk), then the end.

    The file is built under ``LOG.partial``: first as ``LOG.resume.tmp`` with
    the header and the ``copy`` blocks (a resume's verified blocks), fsynced,
    then renamed over ``LOG.partial`` in one step, so the saved blocks are on
    disk in one file or the other at every moment.  ``finish`` renames the
    completed file to ``LOG``.  A write error after the start (a full disk)
    does not stop the run: ``failed`` says what happened and later writes are
    skipped; the ``.partial`` keeps every block written before.
    """

    def __init__(self, path, header: dict, config_text: str, force: bool = False, log_components: bool = True,
                 copy: list | None = None, histogram: dict | None = None, histogram_every: float = 60.0):
        from mcap.writer import Writer

        self.path = final_path(path)
        self.partial = partial_path(self.path)
        self.failed: str | None = None
        self.written: set = set()
        self.histogram_every = histogram_every
        self._last_hist = None
        self._opened = time.monotonic()  # the checkpoints' interval grows with the run's age (blocks())
        # a run that logs every trial's per-point errors logs each block's moments too (format 1.1); one that
        # histograms them (format 2) logs the moments of the run so far with each histogram checkpoint instead
        self.block_moments = log_components
        fmt = FORMAT if log_components else HISTOGRAM_FORMAT
        tmp = Path(str(self.path) + ".resume.tmp")
        try:
            self.fh = open(tmp, "wb")
        except OSError as exc:
            raise RunLogError(f"{self.path}: cannot write the run log ({exc.strerror})") from None
        try:
            self.log_components = log_components
            self.w = Writer(self.fh, use_chunking=False, use_statistics=True, enable_data_crcs=True)
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
                "format": fmt, "mtbudget_version": __version__, "seed": str(spec["seed"]), "trials": str(header["trials"]),
                "host": socket.gethostname(), "platform": platform.platform(), "start_time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "plugins": json.dumps(header.get("plugins", []))})
            self._write("/mtbudget/run", {"format": fmt, "mtbudget_version": __version__, **header})
            for b in copy or []:
                self._write("/mtbudget/blocks", b)
                self.written.add(int(b["block"]))
            if histogram is not None:
                self._write("/mtbudget/histogram", histogram)
            self.fh.flush()
            os.fsync(self.fh.fileno())
            os.replace(tmp, self.partial)
            _fsync_dir(self.partial)
        except OSError as exc:
            try:
                self.fh.close()
                os.remove(tmp)
            except OSError:
                pass
            raise RunLogError(f"{self.path}: cannot write the run log ({exc.strerror or exc})") from None

    # every write after the start goes through _guard: a write error is recorded, never raised
    def _guard(self, fn, *args):
        if self.failed is not None:
            return
        try:
            fn(*args)
        except OSError as exc:
            name = errno.errorcode.get(exc.errno, "OSError") if exc.errno else "OSError"
            self.failed = f"{name}: {exc.strerror or exc}"
            try:
                self.fh.close()
            except OSError:
                pass

    def _write(self, topic, obj):
        t = time.time_ns()
        self.w.add_message(channel_id=self.ch[topic], log_time=t, publish_time=t, data=_with_crc(topic, obj))

    def write(self, topic, obj):
        self._guard(self._write, topic, obj)

    def _flush(self):
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def flush(self):
        self._guard(self._flush)

    def blocks(self, blocks: list, convergence: dict, acc=None):
        """Log merged blocks (those not already in the file) and the convergence row after them; flushed to disk.

        ``acc``: the run's Accumulator; when it histograms the per-point components, its histogram and the moments
        of the vector outputs are checkpointed (at most every ``histogram_every`` seconds) so a resume can restore
        them.
        """
        for b in blocks:
            if b.block in self.written:
                continue
            msg = {"block": b.block, "n": b.n, "scalars": {k: _enc(v) for k, v in b.scalars.items()}}
            if self.block_moments:
                vm = b.vector_moments()
                msg.update({"point_error_moments": _moments_enc(vm["point_error"]),
                            "parameter_moments": _moments_enc(vm["parameters"])})
            msg.update({"not_converged": int(b.not_converged), "fallbacks": int(b.fallbacks)})
            if self.block_moments:
                if "components" in vm:
                    msg["component_moments"] = _comoments_enc(vm["components"])
                if self.log_components and b.components is not None:
                    msg["components"] = _enc(b.components.reshape(b.n, -1))
            self.write("/mtbudget/blocks", msg)
            self.written.add(b.block)
        self.write("/mtbudget/convergence", convergence)
        if acc is not None and acc.vector_hist.get("components") is not None:
            now = time.monotonic()
            # early checkpoints close together, then at most every histogram_every seconds: an interrupted run
            # loses the work since its last checkpoint: at most about half its age (each interval is about the age
            # at the last checkpoint), and at most histogram_every seconds once it is old
            every = min(self.histogram_every, max(FIRST_CHECKPOINT, 0.5 * (now - self._opened)))
            if self._last_hist is None or now - self._last_hist >= every:
                self.checkpoint(acc, flush=False)
        self.flush()

    def checkpoint(self, acc, flush: bool = True):
        """Log the run's histogram checkpoint now (:func:`histogram_state`): a finished run of format 2 ends with one
        covering every block, which is where replay reads the moments of its vector outputs."""
        if acc.vector_hist.get("components") is None:
            return
        self.write("/mtbudget/histogram", histogram_state(acc, moments=not self.block_moments))
        self._last_hist = time.monotonic()
        if flush:
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

    def _finish(self):
        self.w.finish()
        self._flush()
        self.fh.close()
        os.replace(self.partial, self.path)
        _fsync_dir(self.path)

    def finish(self, result_obj: dict | None, complete: bool, trials: int):
        """The result and end records; a complete run's file is fsynced and renamed from LOG.partial to LOG."""
        if result_obj is not None:
            self.write("/mtbudget/result", result_obj)
        if complete:
            self.write("/mtbudget/end", {"trials": trials, "complete": complete})
            self._guard(self._finish)
        else:
            self.close()

    def close(self):
        """Stop writing, leaving LOG.partial resumable (no end record)."""
        if self.failed is None:
            self._guard(self._flush)
        try:
            self.fh.close()
        except OSError:
            pass


def histogram_state(acc, moments: bool = True) -> dict:
    """The per-point histogram of a run (ranges, counts) after the blocks merged so far, as a log message; with
    ``moments``, also the moments of the vector outputs over those blocks (format 2: the blocks do not hold them)."""
    h = acc.vector_hist["components"]
    out = {"blocks": len(acc.blocks), "trials": int(acc.n), "last_block": int(acc.blocks[-1]) if acc.blocks else -1,
           "bins": int(h.bins), "low": _enc(h.low), "high": _enc(h.high), "counts": _enc_int(h.counts),
           "under": _enc_int(h.under), "over": _enc_int(h.over)}
    if moments:
        out["moments"] = {k: (_comoments_enc(m) if isinstance(m, CoMoments) else _moments_enc(m))
                          for k, m in acc.moments.items()}
    return out


def moments_from_state(state: dict) -> dict | None:
    """The moments of the vector outputs a histogram checkpoint holds (format 2), None when it holds none (1.1)."""
    if "moments" not in state:
        return None
    return {k: (_comoments_dec(d) if "C" in d else _moments_dec(d)) for k, d in state["moments"].items()}


def _enc_int(a: np.ndarray) -> dict:
    """An integer array (a histogram's counts) as zlib-compressed base64.  Level 1: a checkpoint of the paper mesh's
    histogram (225 x 4000 counts, 7.2 MB) compresses in 15 ms instead of 45 ms at level 6, 20 % larger (387 kB
    instead of 319 kB after 16 384 trials); a run of 16 384 trials writes two (issue 31).  Any level reads back the same."""
    a = np.ascontiguousarray(a, dtype="<i8")
    return {"dtype": "<i8", "shape": list(a.shape), "encoding": "zlib",
            "data": base64.b64encode(zlib.compress(a.tobytes(), 1)).decode()}


def _dec_int(d: dict) -> np.ndarray:
    if d.get("dtype") != "<i8" or d.get("encoding") != "zlib":
        raise RunLogError(f"unsupported integer array {d.get('dtype')!r}/{d.get('encoding')!r} in run log")
    return np.frombuffer(zlib.decompress(base64.b64decode(d["data"])), dtype="<i8").reshape(d["shape"]).copy()


def histogram_from_state(state: dict):
    """(VectorHistogram, trials it holds) from a logged histogram checkpoint."""
    from .stats import VectorHistogram

    h = VectorHistogram.__new__(VectorHistogram)
    h.low, h.high, h.bins = _dec(state["low"]), _dec(state["high"]), int(state["bins"])
    h.counts, h.under, h.over = _dec_int(state["counts"]), _dec_int(state["under"]), _dec_int(state["over"])
    return h


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
    damaged: list = field(default_factory=list)  # one sentence per damaged record: where (byte offset, block) and what
    histograms: list = field(default_factory=list)  # histogram checkpoints of a run that histograms per-point errors

    @property
    def complete(self) -> bool:
        return bool(self.end and self.end.get("complete")) and not self.truncated and not self.damaged

    def require_intact(self):
        """Raise a one-line RunLogError when any record of the log is damaged (its results are not used)."""
        if self.damaged:
            more = f" (and {len(self.damaged) - 1} more damaged records)" if len(self.damaged) > 1 else ""
            raise RunLogError(f"{self.path}: damaged run log: {self.damaged[0]}{more}; its results are not used. "
                              f"`mtbudget run --resume {final_path(self.path)}` rebuilds it from the verified blocks")

    def block_results(self) -> list:
        """Logged blocks as BlockResults: scalars exact, the vector outputs known by their moments.

        They merge into a run's statistics (replay, resume) exactly as the blocks they were written from.  A block of
        format 2 (a run that histograms its per-point errors) carries no moments: the run's so far are in its
        histogram checkpoints (:meth:`moment_state`).
        """
        out = []
        for b in self.blocks:
            comp = _dec(b["components"]).reshape(b["n"], -1, 3) if "components" in b else None
            cm = _comoments_dec(b["component_moments"]) if "component_moments" in b else None
            pm = _moments_dec(b["point_error_moments"]) if "point_error_moments" in b else None
            qm = _moments_dec(b["parameter_moments"]) if "parameter_moments" in b else None
            out.append(BlockResult(b["block"], b["n"], {k: _dec(v) for k, v in b["scalars"].items()}, None, None,
                                   int(b.get("not_converged", 0)), pm, qm, components=comp, component_moments=cm,
                                   fallbacks=int(b.get("fallbacks", 0))))
        return out

    def moment_state(self) -> dict | None:
        """The last histogram checkpoint that holds the run's moments (format 2) and whose blocks are all in the log,
        or None."""
        have = {int(b["block"]) for b in self.blocks}
        good = [h for h in self.histograms if "moments" in h and all(k in have for k in range(int(h["blocks"])))]
        return max(good, key=lambda h: h["blocks"], default=None)


MAGIC = b"\x89MCAP0\r\n"
_OP = {"header": 0x01, "footer": 0x02, "schema": 0x03, "channel": 0x04, "message": 0x05, "chunk": 0x06,
       "attachment": 0x09, "metadata": 0x0C, "data_end": 0x0F}
_SUMMARY_OPS = {0x03, 0x04, 0x07, 0x08, 0x0A, 0x0B, 0x0D, 0x0E}


class _Cut(Exception):
    """The record framing ends early at ``offset`` (a cut file, or a damaged length when the file is whole)."""

    def __init__(self, offset, reason):
        super().__init__(reason)
        self.offset = offset


def _frames(fh, size: int):
    """(offset, opcode, raw record bytes) of an MCAP file after its magic, up to and including the footer."""
    pos = len(MAGIC)
    while True:
        head = fh.read(9)
        if len(head) < 9:
            raise _Cut(pos, "the file ends inside a record header" if head else "the file ends after a whole record")
        op, length = struct.unpack("<BQ", head)
        if length > size - pos - 9:
            raise _Cut(pos, f"a record of {length} bytes runs past the end of the file")
        body = fh.read(length)
        if len(body) < length:
            raise _Cut(pos, "the file ends inside a record")
        yield pos, op, head + body
        pos += 9 + length
        if op == _OP["footer"]:
            return


def _parse(cls, content: bytes):
    from mcap.data_stream import ReadDataStream

    return cls.read(ReadDataStream(io.BytesIO(content)))


def read_runlog(path) -> RunLog:
    """Read a run log record by record, checking every checksum.

    A cut tail (a killed run) is reported as ``truncated``; a damaged record
    (a checksum that does not match, a message that does not parse, a
    framing error inside a finished file, blocks missing or repeated) goes
    into ``damaged`` with its byte offset and block, and is never used.
    ``LOG`` that does not exist is read from ``LOG.partial`` when that exists.
    """
    from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Metadata, Schema
    from mcap.stream_reader import breakup_chunk

    path = Path(path)
    if not path.exists() and partial_path(path).exists():
        path = partial_path(path)
    if not path.exists():
        raise RunLogError(f"{path}: no such file")
    log = RunLog(path)
    placement = False
    channels, schemas = {}, {}
    seen_blocks: dict = {}
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise RunLogError(f"{path}: cannot read the run log ({exc.strerror})") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        head = fh.read(8)
        if head != MAGIC:
            raise RunLogError(f"{path}: not an MCAP file (bad magic bytes)")
        fh.seek(size - 8)
        finished = size >= 16 and fh.read(8) == MAGIC
        fh.seek(8)
        data_crc = zlib.crc32(MAGIC)
        summary_crc = None  # started after the DataEnd record
        in_data = True
        block_msgs = 0
        legacy = False

        def damage(offset, what):
            log.damaged.append(f"byte offset {offset}: {what}")

        def message(offset, content):
            nonlocal block_msgs, legacy
            if len(content) < 22:
                return damage(offset, "a message record too short to hold its fields")
            channel_id = struct.unpack_from("<H", content, 0)[0]
            data = content[22:]
            ch = channels.get(channel_id)
            if ch is None:
                return damage(offset, f"a message on channel {channel_id}, which no channel record declares")
            sch = schemas.get(ch.schema_id)
            if ch.topic not in TOPICS:
                if sch is not None and sch.name in SCHEMAS:
                    damage(offset, f"channel {ch.topic!r} carries mtbudget's schema {sch.name} under an unknown topic")
                return  # other tools' topics are kept and ignored
            if sch is None or sch.name != TOPICS[ch.topic]:
                raise RunLogError(f"{path}: topic {ch.topic} has unknown schema {getattr(sch, 'name', None)!r}")
            is_block = ch.topic == "/mtbudget/blocks"
            where = f"block message #{block_msgs}" if is_block else f"the {ch.topic} message"
            block_msgs += is_block
            try:
                obj = json.loads(data)
            except (ValueError, UnicodeDecodeError):
                return damage(offset, f"{where} is not valid JSON")
            if not isinstance(obj, dict):
                return damage(offset, f"{where} is not a JSON object")
            if "crc32" not in obj:
                if not (legacy or ch.topic == "/mtbudget/run" and obj.get("format") == LEGACY_FORMAT):
                    return damage(offset, f"{where} has no checksum")
                legacy = True  # written by mtbudget before checksums (format mtbudget-runlog/1): read unverified
            elif obj.pop("crc32") != _body_crc(ch.topic, obj):
                blk = obj.get("block") if is_block else None
                label = f"{where} (it says block {blk}, unverified)" if isinstance(blk, int) else where
                return damage(offset, f"{label} fails its checksum")
            if ch.topic == "/mtbudget/run":
                _check_format(path, obj.get("format"))
                log.header = obj
            elif is_block:
                k = obj.get("block")
                if k in seen_blocks:
                    if seen_blocks[k] != obj:
                        damage(offset, f"block {k} is logged twice with different trials")
                    return
                seen_blocks[k] = obj
                log.blocks.append(obj)
            elif ch.topic == "/mtbudget/convergence":
                log.convergence.append(obj)
            elif ch.topic == "/mtbudget/result":
                log.result = obj
            elif ch.topic == "/mtbudget/end":
                log.end = obj
            elif ch.topic == "/mtbudget/log":
                log.logs.append(obj)
            elif ch.topic == "/mtbudget/histogram":
                log.histograms.append(obj)

        def record(offset, op, content):
            nonlocal placement
            if op == _OP["schema"]:
                s = _parse(Schema, content)
                schemas.setdefault(s.id, s)
            elif op == _OP["channel"]:
                c = _parse(Channel, content)
                channels.setdefault(c.id, c)
            elif op == _OP["message"]:
                message(offset, content)
            elif op == _OP["attachment"]:
                a = _parse(Attachment, content)
                crc = struct.unpack_from("<I", content, len(content) - 4)[0]
                if crc and crc != zlib.crc32(content[:-4]):
                    return damage(offset, f"attachment {a.name!r} fails its checksum")
                if a.name == "config.toml":
                    try:
                        log.config_text = a.data.decode()
                    except UnicodeDecodeError:
                        damage(offset, "attachment config.toml is not UTF-8")
            elif op == _OP["metadata"]:
                m = _parse(Metadata, content)
                if m.name == "mtbudget.run":
                    log.metadata = dict(m.metadata)
                    _check_format(path, log.metadata.get("format"))
                elif m.name == "mtbudget.placement":
                    placement = True
            elif op == _OP["chunk"]:
                for r in breakup_chunk(_parse(Chunk, content), validate_crc=True):
                    from mcap.records import Message

                    if isinstance(r, Message):
                        message(offset, struct.pack("<HIQQ", r.channel_id, r.sequence, r.log_time, r.publish_time)
                                + r.data)
                    elif isinstance(r, (Schema, Channel)):
                        (schemas if isinstance(r, Schema) else channels).setdefault(r.id, r)
            elif op != _OP["header"]:
                damage(offset, f"a record with opcode 0x{op:02x}, which mtbudget does not write in a log's data")

        try:
            for offset, op, raw in _frames(fh, size):
                content = raw[9:]
                if in_data and op == _OP["data_end"]:
                    stated = _parse(DataEnd, content).data_section_crc
                    if stated and stated != data_crc:
                        damage(offset, "the data section fails its CRC (a byte changed somewhere before this offset)")
                    in_data, summary_crc = False, 0
                    continue
                if in_data:
                    data_crc = zlib.crc32(raw, data_crc)
                    try:
                        record(offset, op, content)
                    except RunLogError:
                        raise
                    except Exception as exc:  # a record whose fields do not parse
                        damage(offset, f"a record (opcode 0x{op:02x}) does not parse ({type(exc).__name__})")
                    continue
                if op == _OP["footer"]:
                    f = _parse(Footer, content)
                    summary_crc = zlib.crc32(raw[:25], summary_crc)
                    if f.summary_crc and f.summary_crc != summary_crc:
                        damage(offset, "the summary section fails its CRC")
                    if fh.read(8) != MAGIC or fh.read(1):
                        damage(offset + len(raw), "the file does not end with the MCAP magic after its footer")
                    break
                summary_crc = zlib.crc32(raw, summary_crc)
                if op not in _SUMMARY_OPS:
                    damage(offset, f"a record with opcode 0x{op:02x} in the summary section")
            else:  # pragma: no cover - _frames returns only after a footer
                pass
        except _Cut as cut:
            if finished:
                damage(cut.offset, f"{cut} although the file was finished")
            else:
                log.truncated = True
                log.problem = (f"the file ends at byte {size} without the run's end record: the run was stopped or is "
                               "still running" if cut.offset >= size else f"the file is cut at byte {cut.offset} of {size}")
    if log.header is None:
        if log.metadata.get("format", "").startswith("mtbudget-placement/") or placement:
            raise RunLogError(f"{path}: a placement study log, not a run log; `mtbudget replay {path}` prints its summary")
        if log.damaged:
            log.require_intact()
        raise RunLogError(f"{path}: no run header; the file is not an mtbudget run log or was cut before its first record")
    _check_blocks(log)
    if log.end is None and not log.damaged:
        log.truncated = True
        log.problem = log.problem or "the run did not finish (no end record)"
    return log


def _check_blocks(log: RunLog):
    """Blocks are whole (``block`` trials each, the last may be shorter) and, in a finished log, all there."""
    size = int(log.header.get("spec", {}).get("block", 0) or 0)
    good = []
    for b in log.blocks:
        try:
            k, n = int(b["block"]), int(b["n"])
            ok = 0 <= k and 1 <= n <= size and all(len(v["shape"]) == 1 and v["shape"][0] == n
                                                  for v in b["scalars"].values())
        except (KeyError, TypeError, ValueError, AttributeError):
            ok = False
        if ok:
            good.append(b)
        else:
            log.damaged.append(f"block {b.get('block')!r}: its fields do not describe a block of at most {size} trials")
    log.blocks = sorted(good, key=lambda b: b["block"])
    if log.end is not None:
        ids = [b["block"] for b in log.blocks]
        missing = sorted(set(range(max(ids) + 1 if ids else 0)) - set(ids))
        total = sum(b["n"] for b in log.blocks)
        if missing:
            log.damaged.append(f"blocks {', '.join(map(str, missing[:5]))}{' ...' if len(missing) > 5 else ''} "
                               "are missing from a finished log")
        elif total != log.end.get("trials") or (log.result is not None and log.result.get("trials") != total):
            log.damaged.append(f"the blocks hold {total} trials, the end record says {log.end.get('trials')}")
        short = [b["block"] for b in log.blocks[:-1] if b["n"] != size]
        if short:
            log.damaged.append(f"block {short[0]} holds fewer than {size} trials but is not the last")


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
        raise RunLogError(f"{path}: written by a newer mtbudget (format {fmt}); this version reads up to "
                          f"{HISTOGRAM_FORMAT}. Upgrade mtbudget.")


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
        w = Writer(fh, use_chunking=False, enable_data_crcs=True)
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
    if not path.exists() and partial_path(path).exists():
        path = partial_path(path)
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
