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
