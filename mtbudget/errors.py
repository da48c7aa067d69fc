"""Errors of mtbudget: one base class, subclasses that also inherit the builtin.

Messages are one line and name the file, line, column, plugin or unit at
fault.  All errors are picklable (plain ``args``) so they cross process
boundaries.
"""

from __future__ import annotations


class MtbudgetError(Exception):
    """Base class of every error mtbudget raises on purpose."""


class UnitError(MtbudgetError, ValueError):
    """A quantity has the wrong dimension or cannot be parsed."""


class ConfigError(MtbudgetError, ValueError):
    """A configuration file is missing a key or has a bad value."""


class RecordingError(MtbudgetError, ValueError):
    """A recording folder does not follow the interchange format.

    ``path``, ``line`` and ``column`` say where (line numbers are 1-based and
    count the header as line 1).
    """

    def __init__(self, message: str, path=None, line: int | None = None, column: str | None = None):
        where = []
        if path is not None:
            where.append(str(path))
        if line is not None:
            where.append(f"line {line}")
        if column is not None:
            where.append(f"column {column!r}")
        full = (": ".join([", ".join(where), message])) if where else message
        super().__init__(full)
        self.path, self.line, self.column, self.reason = path, line, column, message

    def __reduce__(self):
        return (RecordingError, (self.reason, self.path, self.line, self.column))


class IdentificationError(MtbudgetError, ValueError):
    """The identification problem is ill-posed or did not converge."""


class PluginError(MtbudgetError, RuntimeError):
    """A plugin misbehaved; the message names plugin, source and hook."""

    def __init__(self, message: str, plugin: str | None = None, source: str | None = None, hook: str | None = None):
        parts = []
        if plugin:
            parts.append(f"plugin {plugin!r}")
        if source:
            parts.append(f"source {source!r}")
        if hook:
            parts.append(f"hook {hook}")
        super().__init__(("; ".join(parts) + ": " + message) if parts else message)
        self.plugin, self.source, self.hook, self.reason = plugin, source, hook, message

    def __reduce__(self):
        return (PluginError, (self.reason, self.plugin, self.source, self.hook))
