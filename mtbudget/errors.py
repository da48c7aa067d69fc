"""Every error mtbudget raises on purpose: one base class, structured fields, one-line messages.

Each error carries *where* it happened as fields (``path``, ``line``,
``column``, ``key`` for files; ``plugin``, ``source``, ``hook``, ``method``
for plugins) and its ``reason``; the message joins them into one line.
Subclasses also inherit the matching builtin (``ValueError``,
``RuntimeError``) so generic handlers keep working.  All errors pickle with
their fields, so they cross process-pool and Dask boundaries intact.
"""

from __future__ import annotations


def _rebuild(cls, reason, fields):
    return cls(reason, **fields)


class MtbudgetError(Exception):
    """Base class of every error mtbudget raises on purpose.

    ``MtbudgetError(reason, path=None, line=None, column=None, key=None)``; the
    location fields may also be given positionally in that order.
    """

    FIELDS: tuple = ("path", "line", "column", "key")

    def __init__(self, reason: str = "", *args, **where):
        if len(args) > len(self.FIELDS):
            raise TypeError(f"{type(self).__name__} takes at most {len(self.FIELDS)} location fields")
        values = dict(zip(self.FIELDS, args))
        for k, v in where.items():
            if k not in self.FIELDS:
                raise TypeError(f"{type(self).__name__} has no field {k!r}; fields: {', '.join(self.FIELDS)}")
            values[k] = v
        self.reason = str(reason)
        for f in self.FIELDS:
            setattr(self, f, values.get(f))
        super().__init__(self._compose())

    def _location(self) -> list:
        parts = []
        if getattr(self, "path", None) is not None:
            parts.append(str(self.path))
        if getattr(self, "line", None) is not None:
            parts.append(f"line {self.line}")
        if getattr(self, "column", None) is not None:
            parts.append(f"column {self.column!r}")
        if getattr(self, "key", None) is not None:
            parts.append(str(self.key))
        return parts

    def _compose(self) -> str:
        where = self._location()
        return ", ".join(where) + ": " + self.reason if where else self.reason

    @property
    def fields(self) -> dict:
        return {f: getattr(self, f) for f in self.FIELDS if getattr(self, f) is not None}

    def __reduce__(self):
        return (_rebuild, (type(self), self.reason, self.fields))


class UnitError(MtbudgetError, ValueError):
    """A quantity has the wrong dimension, no unit where one is needed, or cannot be parsed."""


class ConfigError(MtbudgetError, ValueError):
    """A configuration file (or option) is missing a key or has a bad value; ``path`` and ``key`` say where."""


class RecordingError(MtbudgetError, ValueError):
    """A recording folder does not follow the interchange format.

    ``path``, ``line`` and ``column`` say where (line numbers are 1-based and
    count the header as line 1).
    """


class IdentificationError(MtbudgetError, ValueError):
    """The identification problem is ill-posed or did not converge."""


class DiagnosisError(MtbudgetError, ValueError):
    """The recording cannot be diagnosed (too small, nothing to identify)."""


class DistributionError(MtbudgetError, ValueError):
    """Bad parameters of a probability distribution."""


class ModelError(MtbudgetError, ValueError):
    """A model given to :func:`mtbudget.mcm.propagate` returned something unusable."""


class RunLogError(MtbudgetError, ValueError):
    """A run log cannot be read or written (not MCAP, newer format, unknown schema, damaged)."""


class PluginError(MtbudgetError, RuntimeError):
    """A plugin misbehaved; the message names plugin, source (or candidate), hook and method."""

    FIELDS = ("plugin", "source", "hook", "method")

    def _location(self) -> list:
        parts = []
        if self.plugin:
            parts.append(f"plugin {self.plugin!r}")
        if self.source:
            parts.append(f"source {self.source!r}")
        if self.hook:
            parts.append(f"hook {self.hook}")
        if self.method:
            parts.append(f"method {self.method}()")
        return parts

    def _compose(self) -> str:
        where = self._location()
        return "; ".join(where) + ": " + self.reason if where else self.reason


class OutputError(MtbudgetError, ValueError):
    """An output folder or file cannot be created where the user asked (a parent that is a file, a read-only or
    missing file system): one line naming the option and the path, never a traceback."""


def _named(path, what: str | None) -> str:
    return f"{what} {str(path)!r}" if what else repr(str(path))


def check_folder(path, what: str | None = None) -> None:
    """Refuse, before any computation and without creating anything, a folder ``path`` that cannot be created or
    written: one of its existing ancestors is a file, or the nearest existing one is not writable.  ``what``: the
    option that names it ("--out"), said in the message.  :func:`make_folder` creates it when the output is ready."""
    import os
    from pathlib import Path

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{_named(p, what)}: cannot create the folder: a file of that name is there")
    node = p
    while not node.exists():
        parent = node.parent
        if parent == node:
            break
        node = parent
    if node.exists() and not node.is_dir():
        raise OutputError(f"{_named(p, what)}: cannot create the folder: {str(node)!r} is a file, not a folder")
    if node.exists() and not os.access(node, os.W_OK | os.X_OK):
        raise OutputError(f"{_named(p, what)}: cannot create the folder: {str(node)!r} is not writable")


def make_folder(path, what: str | None = None):
    """Create the folder ``path`` (and its parents) for an output; an OSError (a parent that is a file, a read-only
    or special file system such as /proc) becomes one :class:`OutputError` line naming ``what`` and the path.  The
    one place every command creates an output folder (simulate, run --log, report, posterior, compensate, diagnose
    --report, the studies)."""
    from pathlib import Path

    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{_named(p, what)}: cannot create the folder ({exc.strerror or type(exc).__name__})") from None
    return p
