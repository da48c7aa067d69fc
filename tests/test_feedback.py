"""Feedback (issue 29): no computing command silent for more than 2 s on any stream; Ctrl-C says how to resume."""

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from mtbudget import progress
from mtbudget.cli import main

SMALL = Path(__file__).parent / "data" / "small.toml"


def _stderr_to(monkeypatch, fh):
    monkeypatch.setattr(sys, "stderr", fh)


def test_a_heartbeat_redraws_every_second_on_a_pipe_and_stays_off_in_memory(monkeypatch, tmp_path):
    out = open(tmp_path / "err.txt", "w")  # a real file descriptor, like a pipe
    _stderr_to(monkeypatch, out)
    with progress.working("writing", after=0.2):
        time.sleep(2.6)
    out.close()
    text = (tmp_path / "err.txt").read_text()
    draws = [t for t in text.splitlines() if t.strip().startswith("writing:")]
    assert len(draws) >= 3 and "00:02" in text, text  # drawn at 0.2 s, then every second
    mem = io.StringIO()  # a CliRunner or a program capturing the output: nothing
    _stderr_to(monkeypatch, mem)
    with progress.working("writing", after=0.0):
        time.sleep(0.3)
    assert mem.getvalue() == ""


def test_the_start_up_heartbeat_stops_at_the_first_bar(monkeypatch, tmp_path):
    out = open(tmp_path / "err.txt", "w")
    _stderr_to(monkeypatch, out)
    progress.start_starting(after=0.1)
    time.sleep(1.3)
    bar = progress.progress_bar(3, "Monte Carlo", "trial")
    assert progress._starting is None  # stopped, its line cleared
    time.sleep(1.2)
    bar.close()
    out.close()
    text = (tmp_path / "err.txt").read_text()
    last_start = text.rfind("starting")
    assert last_start >= 0 and last_start < text.find("Monte Carlo"), text  # nothing of it after the bar began


def test_on_a_pipe_what_follows_the_start_up_heartbeat_begins_a_line_of_its_own(monkeypatch, tmp_path):
    """On a pipe or a file the heartbeat's text cannot be erased: its line is ended, so that an error after it starts
    a line of its own ("starting ...: 00:00 ... error: ..." was one line of a log, only carriage returns between)."""
    out = open(tmp_path / "err.txt", "w")  # a real file descriptor, like a pipe
    _stderr_to(monkeypatch, out)
    progress.start_starting(after=0.1)
    time.sleep(0.5)
    progress.stop_starting()  # what the CLI does before it prints an error
    print("error: something named here", file=sys.stderr, flush=True)
    out.close()
    # bytes: a text read would turn every carriage return into a line end and hide what this test looks for
    text = (tmp_path / "err.txt").read_bytes().decode()
    assert "starting" in text  # the heartbeat drew (else this test proves nothing)
    assert any(ln.startswith("error: something named here") for ln in text.split("\n")), repr(text)


def test_json_on_stdout_stays_pure_and_no_heartbeat_reaches_a_cli_runner(tmp_path):
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "16", "--block", "8", "--attribution-trials", "0",
                                    "--json", "--log", str(tmp_path / "r.mcap")])
    assert res.exit_code == 0
    json.loads(res.stdout)
    assert "starting (" not in res.stderr


def test_ctrl_c_says_where_the_partial_log_is_and_how_to_resume(tmp_path):
    log = tmp_path / "int.mcap"
    code = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            "from mtbudget.cli import main; "
            f"main(['run', {str(SMALL)!r}, '--trials', '100000', '--block', '8', '--log', {str(log)!r}, "
            "'--attribution-trials', '0'], prog_name='mtbudget')")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env=dict(os.environ, OPENBLAS_NUM_THREADS="1"), cwd=tmp_path)
    deadline = time.time() + 120
    while time.time() < deadline and not (tmp_path / "int.mcap.partial").exists():
        time.sleep(0.1)
    time.sleep(1.0)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    said = err.decode().strip().splitlines()[-1]
    assert p.returncode == 130, err.decode()[-2000:]
    assert f"saved in {log}.partial" in said and f"mtbudget run --resume {log}" in said, said


def test_sigterm_stops_a_run_as_ctrl_c_does_and_says_so(tmp_path):
    """What `timeout` and batch schedulers send: the run stops as on Ctrl-C, says where its blocks are and how to
    resume (a new user's run had ended silently, exit 143, its progress line left on screen)."""
    log = tmp_path / "t.mcap"
    p = subprocess.Popen([sys.executable, "-m", "mtbudget", "run", str(SMALL), "--trials", "100000", "--block", "8",
                          "--log", str(log), "--attribution-trials", "0"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=dict(os.environ, OPENBLAS_NUM_THREADS="1"), cwd=tmp_path)
    deadline = time.time() + 120
    while time.time() < deadline and not (tmp_path / "t.mcap.partial").exists():
        time.sleep(0.1)
    time.sleep(1.0)
    p.terminate()
    _, err = p.communicate(timeout=120)
    said = err.decode().strip().splitlines()[-1]
    assert p.returncode == 143, err.decode()[-2000:]
    assert said.startswith("terminated (SIGTERM): the blocks") and f"mtbudget run --resume {log}" in said, said


def longest_silence(args, cwd) -> tuple[float, int]:
    """(the longest time in s without a byte on stdout or stderr, both piped; the exit status) of mtbudget ARGS."""
    import selectors

    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "mtbudget", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         cwd=cwd)
    sel = selectors.DefaultSelector()
    sel.register(p.stdout, selectors.EVENT_READ)
    sel.register(p.stderr, selectors.EVENT_READ)
    last, worst, open_ = t0, 0.0, 2
    while open_:
        for key, _ in sel.select(timeout=300):
            data = os.read(key.fileobj.fileno(), 65536)
            now = time.monotonic()
            if not data:
                sel.unregister(key.fileobj)
                open_ -= 1
                continue
            worst, last = max(worst, now - last), now
    p.wait()
    return max(worst, time.monotonic() - last), p.returncode


@pytest.mark.slow
def test_the_newcomers_path_is_never_silent_for_more_than_2_s_on_a_pipe(tmp_path):
    """README line 1 and each command of the README table, stdout and stderr piped (issue 29: `study all` was silent
    17 s, `report` 14 s). The first run's kernel compilation is out of scope here (its note is tested apart)."""
    cmds = [["study", "all", "--out", "ps"], ["report", "ps/verification.mcap", "--out", "rep"],
            ["replay", "ps/verification.mcap"], ["run", str(SMALL), "--trials", "200", "--log", "r.mcap"],
            ["simulate", "--out", "sim"], ["identify", "sim"], ["diagnose", "--example", "null"], ["plugins"]]
    # (compensate: its traceback on a simulated recording is another item of issue 29; measured 1.3 s by hand)
    worst = {}
    for args in cmds:
        gap, rc = longest_silence(args, tmp_path)
        worst[" ".join(args[:2])] = round(gap, 2)
        assert rc == 0, (args, rc)
    assert max(worst.values()) <= 2.0, worst


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    log = tmp_path_factory.mktemp("quiet") / "r.mcap"
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "16", "--block", "8", "--attribution-trials", "0",
                                    "--log", str(log), "--quiet"])
    assert res.exit_code == 0, res.output
    return log


@pytest.mark.parametrize("argv", [["simulate", "--out", "{tmp}/sim", "--no-identify"], ["identify", "--example", "null"],
                                  ["report", "{log}", "--out", "{tmp}/rep"], ["replay", "{log}"]])
def test_quiet_silences_stderr_of_every_computing_command(tmp_path, argv, small_log):
    """The user guide says --quiet silences every bar, note and heartbeat: simulate, identify, report and replay had
    no --quiet at all (a usage error).  With it, stderr is empty on a real file; the results still reach stdout."""
    log = small_log
    args = [a.format(tmp=tmp_path, log=log) for a in argv] + ["--quiet"]
    with open(tmp_path / "err.txt", "wb") as err, open(tmp_path / "out.txt", "wb") as out:
        rc = subprocess.run([sys.executable, "-m", "mtbudget", *args], stderr=err, stdout=out, cwd=tmp_path).returncode
    assert rc == 0, (tmp_path / "err.txt").read_bytes()
    assert (tmp_path / "err.txt").read_bytes() == b""
    assert (tmp_path / "out.txt").read_bytes().strip()
