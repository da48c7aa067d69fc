"""Feedback on long work: progress bars on stderr (so ``--json`` on stdout stays clean), silent when asked."""

from __future__ import annotations

import sys
import threading
from contextlib import contextmanager


class _Silent:
    total = None

    def update(self, n: int = 1):
        pass

    def close(self):
        pass

    def refresh(self):
        pass

    def set_postfix_str(self, s: str = "", refresh: bool = True):
        pass


_QUIET = False  # --quiet of a command that has no progress option of its own: silence every bar, note and heartbeat


def set_quiet(quiet: bool = True):
    """Silence (or not) every bar, note and heartbeat of this process: a command's ``--quiet``."""
    global _QUIET
    _QUIET = bool(quiet)
    if _QUIET:
        stop_starting()


def progress_bar(total: int | None, desc: str, unit: str = "it", enabled: bool = True):
    """A tqdm bar on stderr, or an object with the same methods that prints nothing."""
    if not enabled or _QUIET:
        return _Silent()
    stop_starting()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=True, file=sys.stderr, dynamic_ncols=True)


class Steps:
    """The named steps of one long piece of work on one bar (stderr): ``begin`` shows the step running,
    ``done`` counts it; ``more`` adds steps found on the way (the data-driven search of a diagnosis)."""

    def __init__(self, total: int, desc: str, enabled: bool = True):
        self.bar = progress_bar(total, desc, "step", enabled)

    def begin(self, name: str):
        self.bar.set_postfix_str(name, refresh=True)

    def done(self, n: int = 1):
        self.bar.update(n)

    def more(self, n: int):
        if self.bar.total is not None:
            self.bar.total += n
            self.bar.refresh()

    def close(self):
        self.bar.close()


def note(message: str, enabled: bool = True):
    """One line of feedback on stderr (a step that starts), unless silenced."""
    if enabled and not _QUIET:
        stop_starting()
        print(message, file=sys.stderr, flush=True)


def _real_stream(stream) -> bool:
    """A terminal, a pipe or a file (it has a file descriptor); not an in-memory stream (a test's CliRunner, a
    program that captures the output), which gets no heartbeat."""
    try:
        stream.fileno()
        return True
    except (AttributeError, OSError, ValueError):
        return False


class _Heartbeat:
    """After ``after`` s of work, a bar on stderr with the elapsed time, redrawn every second until stopped: no
    computing command is silent for more than 2 s, on a terminal or a pipe alike."""

    def __init__(self, desc: str, after: float = 1.0):
        self.desc, self.after = desc, after
        self.done = threading.Event()
        self.bar = None
        self.thread = threading.Thread(target=self._run, name="mtbudget-heartbeat", daemon=True)
        self.thread.start()

    def _run(self):
        if self.done.wait(self.after):
            return
        from tqdm import tqdm

        self.bar = tqdm(total=None, desc=self.desc, bar_format="{desc}: {elapsed}", leave=False, file=sys.stderr,
                        dynamic_ncols=True, initial=0)
        while not self.done.wait(1.0):
            self.bar.refresh()

    def stop(self):
        self.done.set()
        if threading.current_thread() is not self.thread:
            self.thread.join()
        if self.bar is not None:
            self.bar.close()
            self.bar = None
            if not _tty(sys.stderr):  # a pipe or a file keeps the bar's text: end its line, so that what follows
                print(file=sys.stderr, flush=True)  # (an error, a note) starts a line of its own


def _tty(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, OSError, ValueError):
        return False


_starting: _Heartbeat | None = None


def start_starting(desc: str = "starting (loading, reading the configuration, building the model)", after: float = 0.5):
    """The heartbeat of a command's start-up, on a real stderr: stopped by the command's first bar or note, or its
    end (:func:`stop_starting`)."""
    global _starting
    stop_starting()
    if _real_stream(sys.stderr) and not _QUIET:
        _starting = _Heartbeat(desc, after)


def stop_starting():
    global _starting
    if _starting is not None:
        hb, _starting = _starting, None
        hb.stop()


@contextmanager
def working(desc: str, enabled: bool = True, after: float = 0.5):
    """A heartbeat on stderr while the block runs (writing a report and its figures, a log): after ``after`` s, the
    elapsed time, redrawn every second; nothing when disabled or when stderr is an in-memory stream."""
    if not enabled or _QUIET or not _real_stream(sys.stderr):
        yield
        return
    stop_starting()
    hb = _Heartbeat(desc, after)
    try:
        yield
    finally:
        hb.stop()
