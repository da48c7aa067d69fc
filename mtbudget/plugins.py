"""The plugin host: one typed facade over pluggy.

Plugins come from the entry-point group ``mtbudget`` (mtbudget's own
built-ins included, through the same path).  The rest of the code asks this
host for sources and candidates and never calls ``pm.hook`` directly.  An
exception inside a plugin becomes a :class:`~mtbudget.errors.PluginError`
that names the plugin, the hook and the distribution it came from.

Environment switches:

* ``MTBUDGET_DISABLE_PLUGINS=name,name``: do not load these plugins.
* ``MTBUDGET_PLUGINS=name,name``: load only these (an allow-list).

Names are entry-point names (``mtbudget plugins`` lists them).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from importlib import metadata

import pluggy

from . import hookspecs
from .errors import PluginError
from .contracts import Candidate, Group, Source, TARGETS

ENTRY_POINT_GROUP = "mtbudget"


@dataclass
class PluginInfo:
    name: str
    module: str
    distribution: str
    version: str


def _env_list(name: str) -> set | None:
    v = os.environ.get(name)
    if v is None:
        return None
    return {x.strip() for x in v.split(",") if x.strip()}


class PluginHost:
    """Loads plugins and collects what they register."""

    def __init__(self, *, entry_points: bool = True, plugins: tuple = ()):
        self.pm = pluggy.PluginManager("mtbudget")
        self.pm.add_hookspecs(hookspecs)
        self.info: dict[str, PluginInfo] = {}
        disabled = _env_list("MTBUDGET_DISABLE_PLUGINS") or set()
        allowed = _env_list("MTBUDGET_PLUGINS")
        if entry_points:
            for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
                if ep.name in disabled or (allowed is not None and ep.name not in allowed):
                    continue
                dist = getattr(ep, "dist", None)
                dname = dist.metadata["Name"] if dist is not None else "?"
                dver = dist.version if dist is not None else "?"
                try:
                    module = ep.load()
                except Exception as exc:
                    raise PluginError(f"failed to load entry point {ep.value!r} from {dname} {dver}: "
                                      f"{type(exc).__name__}: {exc}", ep.name, hook="load") from exc
                self._register(module, ep.name, ep.value, dname, dver)
        for obj in plugins:
            name = getattr(obj, "__name__", type(obj).__name__)
            if name in disabled:
                continue
            self._register(obj, name, getattr(obj, "__module__", name), "(registered in code)", "")

    def _register(self, obj, name, module, dist, version):
        if self.pm.has_plugin(name):
            raise PluginError(f"a plugin named {name!r} is already registered", name, hook="register")
        try:
            self.pm.register(obj, name=name)
        except pluggy.PluginValidationError as exc:
            raise PluginError(f"invalid hook implementation: {exc}".replace("\n", " "), name, hook="register") from None
        self.info[name] = PluginInfo(name, module, dist, version)

    # ---------------------------------------------------------------- calling hooks
    def _collect(self, hook_name: str, kind: type, check):
        hook = getattr(self.pm.hook, hook_name)
        found, names = [], {}
        for impl in hook.get_hookimpls():  # registration order
            plugin = impl.plugin_name
            info = self.info.get(plugin, PluginInfo(plugin, "?", "?", "?"))

            def register(obj, _plugin=plugin, _info=info):
                if not isinstance(obj, kind):
                    raise PluginError(f"register() needs a {kind.__module__}.{kind.__name__}, got {type(obj).__name__}",
                                      _plugin, getattr(obj, "name", None), hook_name)
                obj.plugin, obj.dist_name, obj.dist_version = _plugin, _info.distribution, _info.version
                key = check(obj)
                if key in names:
                    raise PluginError(f"duplicate name {key!r}: already registered by plugin {names[key]!r}",
                                      _plugin, getattr(obj, "name", None), hook_name)
                names[key] = _plugin
                found.append(obj)

            try:
                impl.function(register=register)
            except PluginError:
                raise
            except Exception as exc:
                raise PluginError(f"raised {type(exc).__name__}: {exc} (from {info.distribution} {info.version})",
                                  plugin, hook=hook_name) from exc
        return found

    def sources(self) -> list[Source]:
        """Every registered uncertainty source, validated."""

        def check(src: Source):
            where = dict(plugin=src.plugin, source=src.name or None, hook="mtbudget_register_sources")
            if not src.name or not isinstance(src.name, str):
                raise PluginError("a source needs a non-empty string name", **where)
            try:
                Group(src.group)
            except ValueError:
                raise PluginError(f"group {src.group!r} is not one of {[g.value for g in Group]}", **where) from None
            bad = [t for t in src.targets if t not in TARGETS]
            if bad:
                raise PluginError(f"unknown target(s) {bad}; expected keys of mtbudget.contracts.TARGETS", **where)
            if not src.targets:
                raise PluginError("declares no targets", **where)
            import pint

            for k, v in src.parameters.items():
                if not isinstance(v, (pint.Quantity, int, float, str, bool)):
                    raise PluginError(f"parameter {k!r} must be a pint Quantity (or a plain number or word), got {type(v).__name__}", **where)
            return src.name

        return self._collect("mtbudget_register_sources", Source, check)

    def candidates(self) -> list:
        """Every registered diagnosis candidate, validated."""
        def check(c):
            if not c.effect:
                raise PluginError("a candidate needs an effect name", c.plugin, None, "mtbudget_register_candidates")
            return (c.effect, c.axis)

        return self._collect("mtbudget_register_candidates", Candidate, check)

    def plugins(self) -> list[PluginInfo]:
        return [self.info[n] for n in sorted(self.info)]


def _hook_of(obj) -> str | None:
    if isinstance(obj, Source):
        return "mtbudget_register_sources"
    if isinstance(obj, Candidate):
        return "mtbudget_register_candidates"
    return None


def call(obj, method: str, *args, **kwargs):
    """Call ``obj.method(*args, **kwargs)`` on a registered plugin object (a source, a candidate).

    Every call into plugin code goes through here: an exception inside it
    becomes one :class:`~mtbudget.errors.PluginError` that names the plugin,
    the object, the hook it was registered by and the method.
    """
    try:
        return getattr(obj, method)(*args, **kwargs)
    except PluginError as exc:
        if exc.method is None and exc.plugin in (None, getattr(obj, "plugin", None)):
            raise PluginError(exc.reason, exc.plugin or getattr(obj, "plugin", None) or None,
                              exc.source or _label(obj), exc.hook or _hook_of(obj), method) from exc
        raise
    except Exception as exc:
        raise PluginError(f"raised {type(exc).__name__}: {exc}", getattr(obj, "plugin", None) or None, _label(obj),
                          _hook_of(obj), method) from exc


def _label(obj):
    return getattr(obj, "label", None) or getattr(obj, "name", None) or type(obj).__name__


_default: PluginHost | None = None


def default_host() -> PluginHost:
    """The process-wide host built from the entry points (cached)."""
    global _default
    if _default is None:
        _default = PluginHost()
    return _default
