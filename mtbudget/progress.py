"""Feedback on long work: progress bars on stderr (so ``--json`` on stdout stays clean), silent when asked."""

from __future__ import annotations

import sys


class _Silent:
    def update(self, n: int = 1):
        pass

    def close(self):
        pass

    def set_postfix_str(self, s: str):
        pass


def progress_bar(total: int | None, desc: str, unit: str = "it", enabled: bool = True):
    """A tqdm bar on stderr, or an object with the same methods that prints nothing."""
    if not enabled:
        return _Silent()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, leave=True, file=sys.stderr, dynamic_ncols=True)


def note(message: str, enabled: bool = True):
    """One line of feedback on stderr (a step that starts), unless silenced."""
    if enabled:
        print(message, file=sys.stderr, flush=True)
