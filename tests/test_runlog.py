"""MCAP run logs: replay without recomputing, survive SIGKILL, resume bit for bit, refuse bad files clearly."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.config import load_config
from mtbudget.outputs import SCALARS
from mtbudget.runner import run
from mtbudget.errors import RunLogError
from mtbudget.runlog import read_runlog
from mtbudget.runner import execute, replay, verify

SMALL = Path(__file__).parent / "data" / "small.toml"


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    path = tmp_path_factory.mktemp("log") / "run.mcap"
    res = execute(SMALL, trials=80, log_path=path, progress=False, attribution_trials=32, block=16)
    return path, res


def test_replay_rebuilds_every_number_without_recomputing(logged):
    path, res = logged
    rep = replay(path)
    assert rep.complete and rep.trials == 80
    for k in SCALARS:
        assert np.array_equal(rep.acc.scalar_samples(k), res.acc.scalar_samples(k))
        assert rep.summary(k) == res.summary(k)
    assert rep.budget == json.loads(json.dumps(res.budget))
    assert np.array_equal(rep.acc.moments["point_error"].mean, res.acc.moments["point_error"].mean)


def test_log_contents_and_foxglove_topics(logged):
    from mcap.reader import make_reader

    path, _ = logged
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        schemas = {s.name for s in summary.schemas.values()}
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        attachments = list(reader.iter_attachments())
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert {"foxglove.PointCloud", "foxglove.Log", "mtbudget.Convergence"} <= schemas
    assert topics["/mtbudget/points"] == "foxglove.PointCloud"
    assert attachments[0].name == "config.toml" and b"small" in attachments[0].data
    meta = metadata["mtbudget.run"]
    assert meta["format"] == "mtbudget-runlog/1.1" and meta["seed"] == "5"
    assert "tracker_noise" in meta["plugins"]
    log = read_runlog(path)
    assert len(log.convergence) >= 1 and {"trials", "mean", "std", "low", "high"} <= set(log.convergence[-1])
    # no pickle anywhere: every message is JSON
    assert b"pickle" not in path.read_bytes()


def test_verify_recomputes_bit_for_bit(logged):
    path, _ = logged
    v = verify(path)
    assert v["identical"] and v["trials"] == 80 and v["notes"] == []


def test_verify_says_when_another_mtbudget_recomputes(logged, monkeypatch):
    """A log recomputed by another mtbudget version is compared all the same, with a note saying whose numbers
    are whose (a version that changed the computation gives other numbers, and verify must not leave that unsaid)."""
    import mtbudget.runner as runner

    path, _ = logged
    monkeypatch.setattr(runner, "__version__", "9.9.9")
    v = verify(path)
    assert any("recomputed with 9.9.9" in n and "logged with mtbudget" in n for n in v["notes"]), v["notes"]


def test_killed_run_is_readable_and_resumes_bit_identical(tmp_path):
    path = tmp_path / "killed.mcap"
    # long enough that it cannot end between two looks at its log (chunks of 6 blocks at 1600 trials sometimes did;
    # 6400 trials sometimes did once the identification was compiled)
    cmd = [sys.executable, "-m", "mtbudget", "run", str(SMALL), "--trials", "25600", "--log", str(path),
           "--attribution-trials", "0", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    blocks = 0
    while time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
        try:
            blocks = len(read_runlog(path).blocks)
        except (RunLogError, OSError):
            continue
        if blocks >= 8:
            break
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    log = read_runlog(path)
    assert not log.complete and log.truncated and len(log.blocks) >= 8
    res = CliRunner().invoke(main, ["replay", str(path)])
    assert res.exit_code == 0 and "INCOMPLETE" in res.output
    resumed = execute(resume_path=path, progress=False, attribution_trials=0)
    full = run(load_config(SMALL), trials=25600, attribution_trials=0)
    assert resumed.trials == 25600
    for k in SCALARS:
        assert np.array_equal(resumed.acc.scalar_samples(k), full.acc.scalar_samples(k)), k
        assert resumed.summary(k) == full.summary(k)
    assert np.array_equal(resumed.acc.moments["parameters"].m2, full.acc.moments["parameters"].m2)
    assert read_runlog(path).complete


def test_bad_files_give_clear_errors(tmp_path, logged):
    path, _ = logged
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello, not mcap at all")
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    res = CliRunner().invoke(main, ["replay", str(junk)])
    assert res.exit_code == 2 and "not an MCAP file" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, ["replay", str(cut)])
    assert res.exit_code == 0 and "INCOMPLETE" in res.output
    # a file from a newer format version
    newer = tmp_path / "newer.mcap"
    newer.write_bytes(data.replace(b"mtbudget-runlog/1", b"mtbudget-runlog/9"))
    res = CliRunner().invoke(main, ["replay", str(newer)])
    assert res.exit_code == 2 and "newer mtbudget" in res.output
    # our topic with a schema we do not know
    odd = tmp_path / "odd.mcap"
    odd.write_bytes(data.replace(b"mtbudget.Convergence", b"mtbudget.Convergencf"))
    res = CliRunner().invoke(main, ["replay", str(odd)])
    assert res.exit_code == 2 and "unknown schema" in res.output


def test_replay_reads_a_placement_log_and_refuses_to_verify_it(tmp_path):
    from click.testing import CliRunner

    from mtbudget.cli import main

    r = CliRunner().invoke(main, ["study", "placement", "--tests", "300", "--out", str(tmp_path), "--quiet"])
    assert r.exit_code == 0, r.output
    log = tmp_path / "placement.mcap"
    r = CliRunner().invoke(main, ["replay", str(log), "--json"])
    assert r.exit_code == 0, r.output
    body = json.loads(r.stdout)
    on_disk = json.loads((tmp_path / "placement.json").read_text())
    assert body["directions"]["Y"]["max_error_um"] == on_disk["directions"]["Y"]["max_error_um"]
    r = CliRunner().invoke(main, ["replay", str(log), "--verify"])
    assert r.exit_code == 2 and "placement study log" in r.output
    with pytest.raises(RunLogError, match="a placement study log, not a run log"):
        read_runlog(log)


def test_every_logged_message_type_describes_its_fields():
    from mtbudget.runlog import PLACEMENT_SCHEMA, SCHEMAS

    for name, schema in list(SCHEMAS.items()) + [("mtbudget.PlacementStudy", PLACEMENT_SCHEMA)]:
        assert schema.get("properties"), f"{name} has no properties"
    assert {"output", "unit"} <= set(SCHEMAS["mtbudget.Convergence"]["properties"])
    assert "points" in SCHEMAS["mtbudget.Result"]["properties"]


def test_the_log_holds_exactly_the_trials_the_run_used(tmp_path):
    """20 trials in blocks of 16: the log keeps the second block cut to 4 trials, so replay states what the run did."""
    res = execute(SMALL, trials=20, block=16, attribution_trials=0, log_path=tmp_path / "cut.mcap")
    again = replay(tmp_path / "cut.mcap")
    assert again.trials == res.trials == 20
    for k in SCALARS:
        assert np.array_equal(again.acc.scalar_samples(k), res.acc.scalar_samples(k)), k
    assert again.points() == res.points()


def test_a_log_from_before_checksums_still_reads(tmp_path, monkeypatch):
    """Format mtbudget-runlog/1 had no crc32 in its messages: read unverified; in a 1.1 log a missing crc32 is damage."""
    import mtbudget.runlog as runlog

    monkeypatch.setattr(runlog, "_with_crc", lambda topic, obj: json.dumps(obj).encode())
    monkeypatch.setattr(runlog, "FORMAT", runlog.LEGACY_FORMAT)
    res = execute(SMALL, trials=20, block=8, attribution_trials=0, log_path=tmp_path / "old.mcap")
    again = replay(tmp_path / "old.mcap")
    assert again.complete and np.array_equal(again.acc.scalar_samples("compensation_rms"),
                                             res.acc.scalar_samples("compensation_rms"))
    monkeypatch.setattr(runlog, "FORMAT", "mtbudget-runlog/1.1")
    execute(SMALL, trials=20, block=8, attribution_trials=0, log_path=tmp_path / "new.mcap")
    with pytest.raises(RunLogError, match="damaged run log: byte offset [0-9]+: the /mtbudget/run message has no checksum"):
        read_runlog(tmp_path / "new.mcap")


def test_a_resume_written_to_another_path_never_overwrites_another_runs_log(tmp_path):
    """--resume A --log B, with B a finished log of another run: refused unless --force (B unchanged)."""
    from mtbudget.runlog import partial_path

    A, B = tmp_path / "a.mcap", tmp_path / "b.mcap"
    execute(SMALL, trials=16, block=8, attribution_trials=4, log_path=B, progress=False, seed=7)
    before = B.read_bytes()
    execute(SMALL, trials=24, block=8, attribution_trials=4, log_path=A, progress=False, seed=1)
    data = A.read_bytes()
    A.unlink()
    partial_path(A).write_bytes(data[: len(data) // 2])
    with pytest.raises(RunLogError, match="already there"):
        execute(SMALL, resume_path=A, log_path=B, progress=False)
    assert B.read_bytes() == before
    partial_path(B).write_bytes(b"")  # another run's interrupted log at the target: refused too
    B.unlink()
    with pytest.raises(RunLogError, match="interrupted run is there"):
        execute(SMALL, resume_path=A, log_path=B, progress=False)


def test_the_log_records_the_chunk_size_the_run_used(tmp_path, monkeypatch):
    """Not null for "automatic": the value used (auto_chunk_blocks of the run's blocks), which a resume reuses; a log
    that recorded null (before this) resumes with the same rule, to the same numbers and convergence rows."""
    import mtbudget.runlog as runlog
    from mtbudget.runlog import partial_path

    res = execute(SMALL, trials=80, block=8, attribution_trials=0, log_path=tmp_path / "auto.mcap")
    assert read_runlog(tmp_path / "auto.mcap").header["settings"]["chunk_blocks"] == 4  # 10 blocks: chunks of 4
    assert [r["trials"] for r in res.convergence] == [32, 64, 80]
    execute(SMALL, trials=80, block=8, attribution_trials=0, chunk_blocks=3, log_path=tmp_path / "three.mcap")
    assert read_runlog(tmp_path / "three.mcap").header["settings"]["chunk_blocks"] == 3

    orig = runlog.RunLogWriter.__init__

    def as_before(self, path, header, *args, **kwargs):  # what an older mtbudget wrote
        header = {**header, "settings": {**header["settings"], "chunk_blocks": None}}
        orig(self, path, header, *args, **kwargs)

    monkeypatch.setattr(runlog.RunLogWriter, "__init__", as_before)
    old = tmp_path / "old.mcap"
    execute(SMALL, trials=80, block=8, attribution_trials=0, log_path=old)
    monkeypatch.setattr(runlog.RunLogWriter, "__init__", orig)
    data = old.read_bytes()
    old.unlink()
    partial_path(old).write_bytes(data[: len(data) // 2])
    assert read_runlog(old).header["settings"]["chunk_blocks"] is None
    resumed = execute(resume_path=old, progress=False, attribution_trials=0)
    assert read_runlog(old).header["settings"]["chunk_blocks"] == 4
    for k in SCALARS:
        assert np.array_equal(resumed.acc.scalar_samples(k), res.acc.scalar_samples(k)), k
    assert resumed.convergence[-1] == res.convergence[-1]


def _moments_equal(a, b):
    for k in ("point_error", "parameters", "components"):
        x, y = a.acc.moments[k], b.acc.moments[k]
        for f in ("mean", "m2", "C"):
            if hasattr(x, f):
                assert np.array_equal(getattr(x, f), getattr(y, f)), (k, f)
        assert x.n == y.n


def _cut_inside_block(path, k):
    from mtbudget.runlog import partial_path

    data = path.read_bytes()
    at = [i for i in range(len(data)) if data.startswith(b'"block": %d,' % k, i)][0]
    path.unlink()
    partial_path(path).write_bytes(data[:at])


def _old_histogram_layout(monkeypatch):
    """Write logs as format 1.1 did for a run that histograms its per-point errors: every block with its moments,
    checkpoints without them."""
    import mtbudget.runlog as runlog

    orig = runlog.RunLogWriter.__init__

    def init(self, *args, **kwargs):
        orig(self, *args, **kwargs)
        self.block_moments = True

    monkeypatch.setattr(runlog, "HISTOGRAM_FORMAT", runlog.FORMAT)
    monkeypatch.setattr(runlog.RunLogWriter, "__init__", init)


HIST = dict(trials=96, block=8, chunk_blocks=2, attribution_trials=0, keep_samples=False)


def test_a_histogram_run_logs_its_moments_with_its_checkpoints(tmp_path, monkeypatch):
    """Format 2: blocks without moments (about 4x smaller for the paper's mesh), the moments of the run so far in each
    histogram checkpoint; replay gives the numbers a format-1.1 log of the same run gives, and the run's own."""
    new, old = tmp_path / "new.mcap", tmp_path / "old.mcap"
    full = execute(SMALL, log_path=new, histogram_every=0.0, **HIST)
    log = read_runlog(new)
    assert log.metadata["format"] == log.header["format"] == "mtbudget-runlog/2"
    assert all(not any(k.endswith("moments") for k in b) for b in log.blocks)
    assert log.histograms[-1]["blocks"] == 12 and "moments" in log.histograms[-1]
    with monkeypatch.context() as m:
        _old_histogram_layout(m)
        execute(SMALL, log_path=old, histogram_every=0.0, **HIST)
    assert read_runlog(old).header["format"] == "mtbudget-runlog/1.1"
    assert all("point_error_moments" in b for b in read_runlog(old).blocks)
    a, b = replay(new), replay(old)
    assert a.complete and a.trials == b.trials == 96
    _moments_equal(a, full)
    _moments_equal(b, full)
    from mtbudget.report import result_json

    assert json.dumps(result_json(a)) == json.dumps(result_json(b))
    assert verify(new)["identical"]
    assert new.stat().st_size < old.stat().st_size


@pytest.mark.parametrize("layout", ["format 2", "format 1.1"])
def test_a_histogram_run_resumes_bit_for_bit_from_either_layout(tmp_path, monkeypatch, layout):
    from mtbudget.report import result_json

    path = tmp_path / "h.mcap"
    full = run(load_config(SMALL), **HIST)
    with monkeypatch.context() as m:
        if layout == "format 1.1":
            _old_histogram_layout(m)
        execute(SMALL, log_path=path, histogram_every=0.0, **HIST)
    _cut_inside_block(path, 7)
    cut = read_runlog(path)
    if layout == "format 2":  # an interrupted run is replayed up to its last checkpoint (what a resume keeps)
        assert replay(path).trials == 6 * 8 and not replay(path).complete
    res = execute(resume_path=path, histogram_every=0.0)
    assert max(h["blocks"] for h in cut.histograms) == 6
    _moments_equal(res, full)
    assert json.dumps(res.points()) == json.dumps(full.points())
    again = replay(path)
    assert again.complete and read_runlog(path).header["format"] == "mtbudget-runlog/2"
    _moments_equal(again, full)
    assert json.dumps(result_json(again)["points"]) == json.dumps(result_json(res)["points"])


def test_checkpoints_come_early_then_once_a_minute(tmp_path, monkeypatch):
    """An interrupted histogram run resumes from its last checkpoint: the first comes with the first chunk, the next
    ones at least FIRST_CHECKPOINT (5 s) apart and then at half the run's age, never more than ``histogram_every``
    apart (a new user's Ctrl-C at 30 s had kept only the first chunk, the next checkpoint being due at 60 s).  The
    clock is a fake one that advances 4 s per chunk merged; the expected ages are worked out here by hand."""
    from mtbudget import runlog

    class Clock:  # runlog's time module: monotonic() advances by 4 s at each call of blocks()
        t = 0.0

        @staticmethod
        def monotonic():
            return Clock.t

        time_ns = staticmethod(time.time_ns)
        strftime = staticmethod(time.strftime)

    orig = runlog.RunLogWriter.blocks

    def blocks(self, *a, **k):
        Clock.t += 4.0
        return orig(self, *a, **k)

    monkeypatch.setattr(runlog, "time", Clock)
    monkeypatch.setattr(runlog.RunLogWriter, "blocks", blocks)
    path = tmp_path / "h.mcap"
    execute(SMALL, log_path=path, histogram_every=12.0, **{**HIST, "trials": 8 * 2 * 12})  # 12 chunks: ages 4..48 s
    # chunk k merged at age 4k s with 2k blocks; a checkpoint when the time since the last >= min(12, max(5, age / 2)):
    # 4 s (the first); 8 s: 4 < 5; 12 s: 8 >= 6; 16 s: 4 < 8; 20 s: 8 < 10; 24 s: 12 >= 12; then every 12 s (the
    # cap): 36 s, 48 s; and the end's own, covering every block
    got = [h["blocks"] for h in read_runlog(path).histograms]
    assert got == [2, 6, 12, 18, 24, 24], got


def test_an_interrupted_log_is_verified_for_what_it_holds_and_said_unfinished(tmp_path):
    """`replay --verify` of an interrupted histogram run: every logged block recomputed bit for bit, and the verdict
    says the log is not a whole run (exit 1) rather than counting that as a difference; plain replay says its figures
    are those up to the last checkpoint and how many trials the log holds (a new user read both as corruption)."""
    path = tmp_path / "h.mcap"
    execute(SMALL, log_path=path, histogram_every=0.0, **HIST)
    _cut_inside_block(path, 7)
    res = CliRunner().invoke(main, ["replay", str(path), "--verify"])
    assert res.exit_code == 1, res.output
    assert "NOT verified as a whole run: its 56 trials in 7 blocks recomputed, bit for bit identical" in res.output
    assert "differences" not in res.output
    out = CliRunner().invoke(main, ["replay", str(path)]).output
    assert "results from the 48 trials up to its last histogram checkpoint (56 trials logged" in out, out[:400]


def test_a_log_in_a_missing_folder_is_one_line_naming_the_folder(tmp_path):
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "16", "--block", "8", "--attribution-trials", "0",
                                    "--log", str(tmp_path / "nodir" / "x.mcap")])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1, res.output
    assert f"the folder {tmp_path / 'nodir'} does not exist" in res.output and ".lock" not in res.output
