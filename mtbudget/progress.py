"""Feedback on long work: progress bars on stderr (so ``--json`` on stdout stays clean), silent when asked."""

from __future__ import annotations

import sys


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


def progress_bar(total: int | None, desc: str, unit: str = "it", enabled: bool = True):
    """A tqdm bar on stderr, or an object with the same methods that prints nothing."""
    if not enabled:
        return _Silent()
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
    if enabled:
        print(message, file=sys.stderr, flush=True)
