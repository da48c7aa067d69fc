"""Crash-safe run logs: checksums (byte flips, truncations), kills during runs and resumes, a full disk, locks.

Every outcome must be a clean one-line error or an exact result: the exact
result is the uninterrupted run with the same seed (computed in this
process, never read from a log), or, for a damaged log, the blocks of the
undamaged original.  The large campaign is ``-m slow`` (MTBUDGET_CRASH_REPORT=FILE
writes its counts as JSON; docs/reliability.md has them).
"""

import errno
import json
import os
import random
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.config import load_config
from mtbudget.errors import RunLogError
from mtbudget.outputs import SCALARS
from mtbudget.report import result_json
from mtbudget.runlog import RunLogLock, partial_path, read_runlog
from mtbudget.runner import execute, replay, run, verify

SMALL = Path(__file__).parent / "data" / "small.toml"


def same_run(a, b):
    """Bit-for-bit equality of two runs' statistics (every scalar trial, moments, per-point statement)."""
    assert a.trials == b.trials
    for k in SCALARS:
        assert np.array_equal(a.acc.scalar_samples(k), b.acc.scalar_samples(k)), k
        assert a.summary(k) == b.summary(k), k
    for k in ("point_error", "parameters"):
        assert np.array_equal(a.acc.moments[k].mean, b.acc.moments[k].mean), k
        assert np.array_equal(a.acc.moments[k].m2, b.acc.moments[k].m2), k
    assert json.dumps(a.points()) == json.dumps(b.points())  # NaN-aware: an interval may be NaN in histogram mode


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A finished log of 20 trials in blocks of 8 (the last block cut to 4), with a small budget."""
    path = tmp_path_factory.mktemp("tiny") / "tiny.mcap"
    execute(SMALL, trials=20, block=8, attribution_trials=4, log_path=path, progress=False)
    data = path.read_bytes()
    return path, data, json.dumps(result_json(replay(path)), sort_keys=True), \
        {b["block"]: b for b in read_runlog(path).blocks}


def flip_outcome(path: Path, ref_json: str, ref_blocks: dict):
    """'error' (one clean line), 'exact' (every number as the original) or 'incomplete-exact' (a cut file whose
    blocks all equal the original's); anything else fails."""
    try:
        r = replay(path)
    except RunLogError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc), str(exc)
        return "error"
    blocks = r.log.blocks
    assert all(b == ref_blocks[b["block"]] for b in blocks), "a damaged block was used"
    if r.complete:
        assert json.dumps(result_json(r), sort_keys=True) == ref_json, "a flipped byte changed a result silently"
        return "exact"
    return "incomplete-exact"


def test_a_finished_log_states_its_checksums(tiny):
    from mcap.reader import make_reader

    path, data, _, _ = tiny
    with open(path, "rb") as fh:
        r = make_reader(fh)
        assert r.get_summary() is not None
    # the data-section CRC the file states is the CRC-32 of every byte before its DataEnd record (MCAP spec)
    import zlib

    i = data.rfind(b"\x0f\x04\x00\x00\x00\x00\x00\x00\x00")  # DataEnd: opcode 0x0f, length 4
    stated = int.from_bytes(data[i + 9:i + 13], "little")
    assert stated != 0 and stated == zlib.crc32(data[:i])
    log = read_runlog(path)
    assert log.complete and not log.damaged and len(log.blocks) == 3 and log.blocks[-1]["n"] == 4


def test_byte_flips_give_a_clean_error_or_the_exact_result(tiny, tmp_path):
    path, data, ref, blocks = tiny
    rng = random.Random(19)
    seen = Counter()
    for i in rng.sample(range(len(data)), 120) + [len(data) - 1, 0, 8, 9]:
        d = bytearray(data)
        d[i] ^= 1 << rng.randrange(8)
        bad = tmp_path / "flip.mcap"
        bad.write_bytes(bytes(d))
        seen[flip_outcome(bad, ref, blocks)] += 1
    assert sum(seen.values()) == 124 and seen["error"] > 0


def unfinished(data: bytes) -> bytes:
    """The log without its DataEnd record and summary: what a killed run leaves, with no file-wide CRC to lean on."""
    return data[: data.rfind(b"\x0f\x04\x00\x00\x00\x00\x00\x00\x00")]


def test_byte_flips_in_an_unfinished_log_are_caught_by_the_message_checksums(tiny, tmp_path):
    path, data, ref, blocks = tiny
    cut = unfinished(data)
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(cut)
    assert flip_outcome(bad, ref, blocks) == "incomplete-exact" and len(read_runlog(bad).blocks) == 3
    rng = random.Random(20)
    seen = Counter()
    for i in rng.sample(range(len(cut)), 120):
        d = bytearray(cut)
        d[i] ^= 1 << rng.randrange(8)
        bad.write_bytes(bytes(d))
        seen[flip_outcome(bad, ref, blocks)] += 1
    assert seen["error"] > 0 and seen["exact"] == 0


def test_a_damaged_block_is_named_and_never_used(tiny, tmp_path):
    path, data, ref, blocks = tiny
    # change one digit inside the second block's message: the JSON still parses, the checksum does not match
    at = [i for i in range(len(data)) if data.startswith(b'"block": 1,', i)][0]
    d = bytearray(data)
    j = data.index(b'"data": "', at) + 12
    d[j] = ord("A") if d[j] != ord("A") else ord("B")
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(d))
    log = read_runlog(bad)
    assert not log.complete and any("block message #1" in x and "checksum" in x for x in log.damaged), log.damaged
    assert [b["block"] for b in log.blocks] == [0, 2]  # the damaged block is not among the usable ones
    for args in (["replay", str(bad)], ["replay", str(bad), "--verify"], ["report", str(bad), "--out", str(tmp_path / "r")]):
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 2, res.output
        assert "damaged run log" in res.output and "byte offset" in res.output and "Traceback" not in res.output
        assert len(res.output.strip().splitlines()) == 1, res.output
    # --resume rebuilds it: the damaged block recomputed, the result the original's
    again = execute(resume_path=bad, progress=False, attribution_trials=4)
    assert json.dumps(result_json(replay(bad)), sort_keys=True) == ref
    assert again.resume_notes and "recomputed" in again.resume_notes[0]


def test_truncations_give_a_clean_error_or_the_blocks_they_hold(tiny, tmp_path):
    path, data, ref, blocks = tiny
    rng = random.Random(7)
    seen = Counter()
    for cut in sorted(rng.sample(range(len(data)), 60)) + [len(data) - 1, len(data) - 8]:
        bad = tmp_path / "cut.mcap"
        bad.write_bytes(data[:cut])
        outcome = flip_outcome(bad, ref, blocks)
        seen[outcome] += 1
        assert outcome != "exact" or cut >= len(data) - 8  # a cut file never reads as complete ...
        if outcome == "incomplete-exact":  # ... and verify refuses it
            v = verify(bad)
            assert not v["identical"] and "incomplete" in v["mismatches"][-1]
    assert seen["incomplete-exact"] > 0 and seen["error"] > 0


# ------------------------------------------------------------------ kills
def _start(args):
    return subprocess.Popen([sys.executable, "-m", "mtbudget", "run", *args, "--quiet", "--attribution-trials", "0"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _kill_after(proc, log: Path, blocks: int, timeout=120) -> int:
    """SIGKILL ``proc`` once its log holds at least ``blocks`` blocks; the number it held then (-1: it finished)."""
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        try:
            n = len(read_runlog(log).blocks)
        except (RunLogError, OSError):
            n = 0
        if n >= blocks:
            break
        time.sleep(0.05)
    if proc.poll() is not None:
        return -1
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return n


def test_kills_during_a_run_and_a_resume_then_resume_is_bit_identical(tmp_path):
    log = tmp_path / "run.mcap"
    trials = 2000  # enough blocks that the resume is still running when it is killed (chunks of up to 16 blocks)
    args = [str(SMALL), "--trials", str(trials), "--block", "8", "--log", str(log)]
    held = _kill_after(_start(args), log, 3)
    assert held >= 3 and not log.exists() and partial_path(log).exists()
    first = read_runlog(log)  # reads LOG.partial
    assert first.truncated and not first.damaged
    # kill the resume too, after it has added blocks
    held2 = _kill_after(_start(["--resume", str(log)]), log, held + 8)
    assert held2 == -1 or held2 >= held + 8
    # the saved blocks are all still there, equal to what the first run saved
    second = {b["block"]: b for b in read_runlog(log).blocks}
    assert all(second[b["block"]] == b for b in first.blocks)
    res = CliRunner().invoke(main, ["run", "--resume", str(partial_path(log)), "--quiet", "--attribution-trials", "0"])
    assert res.exit_code == 0, res.output
    full = run(load_config(SMALL), trials=trials, block=8, attribution_trials=0)
    same_run(replay(log), full)
    assert read_runlog(log).complete and not partial_path(log).exists()
    assert verify(log)["identical"]


def test_a_second_run_on_the_same_log_is_refused_with_the_holders_pid(tmp_path):
    log = tmp_path / "busy.mcap"
    with RunLogLock(log):
        for extra in ([], ["--force"], ["--resume", str(log)]):
            res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "20", "--log", str(log), "--quiet", *extra])
            assert res.exit_code == 2, res.output
            assert f"PID {os.getpid()}" in res.output and len(res.output.strip().splitlines()) == 1
    assert not log.exists()
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "20", "--block", "8", "--log", str(log), "--quiet",
                                    "--attribution-trials", "0"])
    assert res.exit_code == 0 and log.exists()


def test_an_interrupted_log_is_neither_overwritten_nor_ignored_without_force(tmp_path):
    log = tmp_path / "cut.mcap"
    execute(SMALL, trials=40, block=8, attribution_trials=0, log_path=log)
    data = log.read_bytes()
    os.remove(log)
    partial_path(log).write_bytes(data[: len(data) // 2])
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "40", "--log", str(log), "--quiet"])
    assert res.exit_code == 2 and "--resume" in res.output and partial_path(log).read_bytes() == data[: len(data) // 2]
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "40", "--block", "8", "--log", str(log), "--quiet",
                                    "--attribution-trials", "0", "--force"])
    assert res.exit_code == 0 and read_runlog(log).complete and not partial_path(log).exists()


def test_a_log_left_by_an_old_resume_is_not_lost(tmp_path):
    """The old bug: a header-only LOG beside LOG.partial; resume now takes the union of their verified blocks."""
    log = tmp_path / "old.mcap"
    execute(SMALL, trials=48, block=8, attribution_trials=0, log_path=log)
    data = log.read_bytes()
    first = read_runlog(log)
    ends = [i for i in range(len(data)) if data.startswith(b'"block": 4,', i)]  # cut inside block 4
    partial_path(log).write_bytes(data[: ends[0]])
    header_only = data[: data.index(b'"block": 0,')]
    log.write_bytes(header_only)
    execute(resume_path=log, attribution_trials=0)
    said = [m["message"] for m in read_runlog(log).logs if m["message"].startswith("resumed from")]
    assert said and "32 trials in 4 blocks taken from the log" in said[0], said  # the saved trials were reused
    full = run(load_config(SMALL), trials=48, block=8, attribution_trials=0)
    same_run(replay(log), full)
    assert [b["block"] for b in read_runlog(log).blocks] == [b["block"] for b in first.blocks]


# ------------------------------------------------------------------ a full disk
def test_a_full_disk_still_prints_results_and_leaves_a_resumable_log(tmp_path, monkeypatch):
    import mtbudget.runlog as runlog

    log = tmp_path / "full.mcap"
    real = os.fsync
    calls = {"n": 0}

    def fsync(fd):
        calls["n"] += 1
        if calls["n"] >= 4:  # the header (file and folder), one chunk; the second chunk's fsync fails
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd)

    monkeypatch.setattr(runlog.os, "fsync", fsync)
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "96", "--block", "8", "--log", str(log),
                                    "--attribution-trials", "0", "--quiet"])
    monkeypatch.setattr(runlog.os, "fsync", real)
    assert res.exit_code == 1, res.output
    assert "compensation_rms" in res.stdout  # the results are printed
    warn = [x for x in res.stderr.splitlines() if x.startswith("warning:")]
    assert len(warn) == 1 and "ENOSPC" in warn[0] and "--resume" in warn[0]
    saved = read_runlog(log)
    assert not log.exists() and saved.truncated and not saved.damaged and len(saved.blocks) >= 8
    execute(resume_path=log, attribution_trials=0)
    same_run(replay(log), run(load_config(SMALL), trials=96, block=8, attribution_trials=0))


# ------------------------------------------------------------------ histogram mode
def test_resuming_a_histogram_run_restores_its_per_point_histograms(tmp_path):
    """keep_samples=False: per-point intervals from histograms; a resume restores them from the log's checkpoint."""
    log = tmp_path / "hist.mcap"
    kw = dict(trials=96, block=8, chunk_blocks=2, attribution_trials=0, keep_samples=False)
    full = run(load_config(SMALL), **kw)
    assert full.acc.vector_hist.get("components") is not None  # the run is in histogram mode
    execute(SMALL, log_path=log, histogram_every=0.0, **kw)
    data = log.read_bytes()
    os.remove(log)
    at = [i for i in range(len(data)) if data.startswith(b'"block": 7,', i)][0]  # cut inside block 7
    partial_path(log).write_bytes(data[:at])
    cut = read_runlog(log)
    assert cut.histograms and max(h["blocks"] for h in cut.histograms) == 6
    res = execute(resume_path=log, histogram_every=0.0)
    got, want = res.points(), full.points()
    assert json.dumps(got) == json.dumps(want)  # intervals from every trial's per-point errors, as the uninterrupted run
    h, w = res.acc.vector_hist["components"], full.acc.vector_hist["components"]
    assert np.array_equal(h.counts, w.counts) and h.counts.sum() + h.under.sum() + h.over.sum() == 96 * h.counts.shape[0]
    # without a checkpoint the resume recomputes every block and says so
    partial_path(log).write_bytes(data[: data.index(b'{"blocks": ', data.index(b'"block": 0,'))])
    os.remove(log)
    res = execute(resume_path=log)
    assert json.dumps(res.points()) == json.dumps(want) and any("histogram" in n for n in res.resume_notes)


# ------------------------------------------------------------------ the large campaign
@pytest.mark.slow
def test_crash_campaign(tmp_path, tiny):
    """Many kills (during runs and resumes, at random moments), byte flips and truncations; counts reported."""
    rng = random.Random(2026)
    path, data, ref, blocks = tiny
    report = {"byte_flips": Counter(), "truncations": Counter(), "kills": Counter()}
    flips = int(os.environ.get("MTBUDGET_CRASH_FLIPS", "3000"))
    for i in rng.sample(range(len(data)), min(flips, len(data))):
        d = bytearray(data)
        d[i] ^= 1 << rng.randrange(8)
        (tmp_path / "f.mcap").write_bytes(bytes(d))
        report["byte_flips"][flip_outcome(tmp_path / "f.mcap", ref, blocks)] += 1
    report["byte_flips_unfinished"] = Counter()
    cut_data = unfinished(data)
    for i in rng.sample(range(len(cut_data)), min(flips, len(cut_data))):
        d = bytearray(cut_data)
        d[i] ^= 1 << rng.randrange(8)
        (tmp_path / "u.mcap").write_bytes(bytes(d))
        report["byte_flips_unfinished"][flip_outcome(tmp_path / "u.mcap", ref, blocks)] += 1
    for cut in rng.sample(range(len(data)), min(int(os.environ.get("MTBUDGET_CRASH_CUTS", "1000")), len(data))):
        (tmp_path / "c.mcap").write_bytes(data[:cut])
        report["truncations"][flip_outcome(tmp_path / "c.mcap", ref, blocks)] += 1
    trials, runs = 640, int(os.environ.get("MTBUDGET_CRASH_RUNS", "6"))
    full = run(load_config(SMALL), trials=trials, block=8, attribution_trials=0)
    for r in range(runs):
        log = tmp_path / f"k{r}.mcap"
        fresh = [str(SMALL), "--trials", str(trials), "--block", "8", "--log", str(log)]
        kind, proc = "during a run", _start(fresh)
        time.sleep(rng.uniform(1.0, 4.0))
        kills = 0
        while True:
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
                kills += 1
                saved = log.exists() or partial_path(log).exists()
                report["kills"][kind + ("" if saved else ", before the log existed")] += 1
            if kills >= 3 or proc.returncode == 0:
                break
            if log.exists() or partial_path(log).exists():
                kind, proc = "during a resume", _start(["--resume", str(log)])
            else:  # killed before its header was on disk: nothing to resume, start again
                kind, proc = "during a run", _start(fresh)
            time.sleep(rng.uniform(1.5, 4.0))
        if not (log.exists() and read_runlog(log).complete):
            if log.exists() or partial_path(log).exists():
                execute(resume_path=log, attribution_trials=0)
            else:
                execute(SMALL, trials=trials, block=8, attribution_trials=0, log_path=log)
        try:
            same_run(replay(log), full)
        except AssertionError:
            if not np.array_equal(run(load_config(SMALL), trials=trials, block=8, attribution_trials=0)
                                  .acc.scalar_samples("compensation_rms"), full.acc.scalar_samples("compensation_rms")):
                pytest.skip("the simulation code changed while the campaign ran (a shared checkout being edited)")
            raise
        report["kills"]["resumed bit-identical"] += 1
    out = {k: dict(v) for k, v in report.items()}
    print(json.dumps(out, indent=1))
    if os.environ.get("MTBUDGET_CRASH_REPORT"):
        Path(os.environ["MTBUDGET_CRASH_REPORT"]).write_text(json.dumps(out, indent=1))


def test_a_log_killed_before_its_first_block_gives_one_line_and_resumes(tmp_path):
    """Issue 29: a run killed after its header and before its first block made replay --json and report raise
    KeyError 'compensation_rms'; now one line naming the log and the way to resume it, and the resume works."""
    log = tmp_path / "h.mcap"
    execute(SMALL, trials=16, block=8, attribution_trials=0, log_path=log)
    data = log.read_bytes()
    os.remove(log)
    partial_path(log).write_bytes(data[: data.index(b'"block": 0,')])
    for args in (["replay", str(log), "--json"], ["replay", str(log)], ["report", str(log), "--out", str(tmp_path / "r")]):
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 2, (args, res.output)
        assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1, res.output
        assert str(log) in res.output and "no trial" in res.output and "--resume" in res.output
    execute(resume_path=log, attribution_trials=0)
    same_run(replay(log), run(load_config(SMALL), trials=16, block=8, attribution_trials=0))


def test_a_resume_keeps_the_runs_settings_and_every_convergence_row(tmp_path):
    """Issue 29: the resumed log ignored --attribution-trials 0 (it computed a budget the run had not asked for) and
    lost the convergence rows from before the kill. Now its settings, rows and budget are the uninterrupted run's."""
    full_log, log = tmp_path / "full.mcap", tmp_path / "cut.mcap"
    execute(SMALL, trials=96, block=8, chunk_blocks=2, attribution_trials=0, log_path=full_log)
    data = full_log.read_bytes()
    at = [i for i in range(len(data)) if data.startswith(b'"block": 5,', i)][0]  # killed inside block 5
    partial_path(log).write_bytes(data[:at])
    assert len(read_runlog(log).convergence) == 2  # rows after blocks 0-1 and 2-3 were saved
    res = execute(resume_path=log)  # the defaults of a new run (attribution_trials 512) must not apply
    resumed, full = read_runlog(log), read_runlog(full_log)
    assert resumed.header["settings"]["attribution_trials"] == 0 and res.budget == {}
    assert resumed.result["budget"] == {} == full.result["budget"]
    assert resumed.convergence == full.convergence and len(full.convergence) == 6
    same_run(replay(log), replay(full_log))


def test_an_option_given_with_resume_that_the_log_overrides_is_said(tmp_path):
    """The resumed run keeps its logged --attribution-trials 0; an --attribution-trials 32 given with --resume is said
    to be unused, not silently dropped (nor silently applied)."""
    full_log, log = tmp_path / "full.mcap", tmp_path / "cut.mcap"
    execute(SMALL, trials=48, block=8, chunk_blocks=2, attribution_trials=0, log_path=full_log)
    data = full_log.read_bytes()
    partial_path(log).write_bytes(data[:[i for i in range(len(data)) if data.startswith(b'"block": 3,', i)][0]])
    res = CliRunner().invoke(main, ["run", "--resume", str(log), "--quiet", "--attribution-trials", "32", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["budget"] == {}
    assert "note: resume: the run keeps its logged settings: --attribution-trials 0" in res.stderr
