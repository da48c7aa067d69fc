"""The plugin host: one typed facade over pluggy.

Plugins come from the entry-point group ``mtbudget`` (mtbudget's own
built-ins included, through the same path).  The rest of the code asks this
host for sources and candidates and never calls ``pm.hook`` directly; every
call into plugin code goes through the host (hooks through pluggy, methods of
registered objects through :func:`call`).  An exception inside a plugin
becomes a :class:`~mtbudget.errors.PluginError` that names the plugin, the
hook (and the method) and the distribution it came from.

After loading, the host checks every plugin against the hook specifications
(:meth:`PluginHost.check_pending`): a function named like a hook that does
not exist is an error that suggests the closest real hook, instead of being
ignored.

A third-party plugin (an entry point of another distribution) that fails is
isolated: when it fails to import, cannot be registered (it reuses a
plugin's name, a hook implementation is invalid), misspells a hook, raises in
a registration hook, or registers a name another plugin already has
(a built-in's name, or the name of a plugin that sorts first), it is skipped
with a one-line warning that names it and says why (logger
``mtbudget.plugins``, shown on stderr by the CLI; ``mtbudget plugins``
lists it); the built-ins and the other plugins keep working.  mtbudget's own
plugins and plugins registered in code (``PluginHost(plugins=...)``) are
never skipped: their failure is an error.  ``MTBUDGET_STRICT_PLUGINS=1``
makes every plugin failure an error (for a plugin's own tests).

From a source checkout that is not installed (``PYTHONPATH=checkout``), the
entry points of mtbudget are absent: the host then registers the built-ins
declared in the checkout's ``pyproject.toml`` from its ``plugins/`` folder,
under their usual import names ``mtbudget_plugins.<module>``.

Environment switches:

* ``MTBUDGET_DISABLE_PLUGINS=name,name``: do not load these plugins.
* ``MTBUDGET_PLUGINS=name,name``: load only these (an allow-list).
* ``MTBUDGET_STRICT_PLUGINS=1``: a failing third-party plugin is an error instead of being skipped.
* ``MTBUDGET_TRACE_PLUGINS=1``: print every hook call and every call into a
  registered plugin object to stderr (hook or method, plugin, arguments,
  outcome, duration), through pluggy's hook-call monitoring.

Names are entry-point names (``mtbudget plugins`` lists them).
"""

from __future__ import annotations

import difflib
import importlib.util
import logging
import os
import sys
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import pluggy

from . import hookspecs
from .contracts import TARGETS, Candidate, Exporter, Group, Source, check_plausible
from .errors import PluginError

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

ENTRY_POINT_GROUP = "mtbudget"
#: the distribution whose plugins are mtbudget's built-ins
BUILTIN_DISTRIBUTION = "mtbudget"
#: the folder holding the ``mtbudget`` package: a source checkout when it has mtbudget's pyproject.toml
CHECKOUT = Path(__file__).resolve().parent.parent
_PROJECT = "mtbudget"  # pluggy project name: markers set the attributes mtbudget_impl / mtbudget_spec

log = logging.getLogger(__name__)


@dataclass
class PluginInfo:
    name: str
    module: str
    distribution: str
    version: str


def hook_names() -> list[str]:
    """The names of every hook mtbudget specifies (:mod:`mtbudget.hookspecs`), sorted."""
    return sorted(n for n, f in vars(hookspecs).items()
                  if n.startswith(_PROJECT + "_") and hasattr(f, _PROJECT + "_spec"))


def _env_list(name: str) -> set | None:
    v = os.environ.get(name)
    if v is None:
        return None
    return {x.strip() for x in v.split(",") if x.strip()}


def _env_flag(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() not in ("", "0", "false", "no", "off")


def tracing() -> bool:
    """Whether ``MTBUDGET_TRACE_PLUGINS`` asks for a trace of every call into plugin code."""
    return _env_flag("MTBUDGET_TRACE_PLUGINS")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _dist_of(ep) -> tuple[str, str]:
    dist = getattr(ep, "dist", None)
    if dist is None:
        return "?", "?"
    return dist.metadata["Name"] or "?", dist.version or "?"


def _where(module: str, dist: str, version: str) -> str:
    """``module (distribution version)``, for messages."""
    return f"{module} ({dist.strip('()')} {version}".strip() + ")"


def _is_builtin_dist(name: str) -> bool:
    return name.lower().replace("_", "-") == BUILTIN_DISTRIBUTION


def checkout_builtins(root: Path | None = None) -> dict[str, str]:
    """The built-in plugins declared by a source checkout: entry-point name -> object reference.

    Read from the ``[project.entry-points.mtbudget]`` table of ``root/pyproject.toml``
    (default: the folder that holds this ``mtbudget`` package); empty when that is not
    mtbudget's source checkout (an installed wheel has no pyproject.toml next to it).
    """
    project = _checkout_project(CHECKOUT if root is None else Path(root))
    return dict(project.get("project", {}).get("entry-points", {}).get(ENTRY_POINT_GROUP, {}))


def _checkout_project(root: Path) -> dict:
    path = root / "pyproject.toml"
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if data.get("project", {}).get("name") == BUILTIN_DISTRIBUTION else {}


def _load_from_checkout(name: str, value: str, root: Path):
    """Load a built-in ``package.module[:attr]`` even when its package is not installed.

    When ``package`` is not importable, it is loaded from the checkout folder that
    ``[tool.setuptools.package-dir]`` maps it to (``mtbudget_plugins`` -> ``plugins/``) and
    entered in ``sys.modules`` under its import name, so its modules import (and pickle,
    in this process) as ``mtbudget_plugins.<module>``.
    """
    ep = metadata.EntryPoint(name=name, value=value, group=ENTRY_POINT_GROUP)
    try:
        return ep.load()
    except ModuleNotFoundError as exc:
        top = ep.module.split(".")[0]
        if exc.name != top:
            raise
    package_dir = _checkout_project(root).get("tool", {}).get("setuptools", {}).get("package-dir", {}).get(top, top)
    init = root / package_dir / "__init__.py"
    spec = importlib.util.spec_from_file_location(top, init, submodule_search_locations=[str(init.parent)])
    if spec is None or not init.is_file():
        raise ModuleNotFoundError(f"no module named {top!r}, and the checkout has no {init}", name=top)
    module = importlib.util.module_from_spec(spec)
    sys.modules[top] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(top, None)
        raise
    return ep.load()


# ----------------------------------------------------------------------------- tracing
def _summary(value, width: int = 40) -> str:
    """A short, cheap description of an argument for the trace (no reprs of big objects)."""
    if isinstance(value, (str, int, float, bool, type(None))):
        r = repr(value)
        return r if len(r) <= width else r[: width - 3] + "..."
    shape = getattr(value, "shape", None) if hasattr(value, "__array__") or hasattr(value, "magnitude") else None
    if shape is not None:
        units = getattr(value, "units", None)
        return f"{type(value).__name__}{tuple(shape)}" + (f"[{units}]" if units is not None else "")
    if isinstance(value, (list, tuple, set, dict)):
        return f"{type(value).__name__}[{len(value)}]"
    if callable(value):
        return f"<{getattr(value, '__name__', type(value).__name__)}()>"
    return f"<{type(value).__name__}>"


def _trace(line: str) -> None:
    print(f"mtbudget trace: {line}", file=sys.stderr, flush=True)


class PluginHost:
    """Loads plugins and collects what they register.

    ``entry_points``: ``True`` discovers the entry-point group ``mtbudget`` (and, from a
    source checkout that is not installed, the built-ins declared in its pyproject.toml);
    an iterable of :class:`importlib.metadata.EntryPoint` is used as if discovered (tests);
    ``False`` loads none (not even the built-ins).  ``plugins``: objects registered in code,
    named by their ``__name__``.
    """

    def __init__(self, *, entry_points=True, plugins: tuple = ()):
        self.pm = pluggy.PluginManager(_PROJECT)
        self.pm.add_hookspecs(hookspecs)
        self.info: dict[str, PluginInfo] = {}
        #: names of the registered plugins that are mtbudget's own
        self.builtin: set[str] = set()
        #: one-line messages of the third-party plugins skipped because they failed (import, registration, a hook)
        self.skipped: list[str] = []
        #: names of the registered third-party plugins from entry points: a failure skips them (module docstring)
        self.isolated: set[str] = set()
        self.strict = _env_flag("MTBUDGET_STRICT_PLUGINS")
        self._trace_started: list[float] = []
        if tracing():
            self.pm.add_hookcall_monitoring(self._trace_before, self._trace_after)
        disabled = _env_list("MTBUDGET_DISABLE_PLUGINS") or set()
        allowed = _env_list("MTBUDGET_PLUGINS")
        known: set[str] = set()

        def wanted(name):
            known.add(name)
            return name not in disabled and (allowed is None or name in allowed)

        if entry_points is not False:
            eps = list(metadata.entry_points(group=ENTRY_POINT_GROUP) if entry_points is True else entry_points)
            installed = {ep.name for ep in eps if _is_builtin_dist(_dist_of(ep)[0])}
            # the built-ins of a source checkout that is not installed (or lacks a newer entry point)
            fallback = {n: v for n, v in checkout_builtins().items() if n not in installed}
            todo = [(ep.name, not _is_builtin_dist(_dist_of(ep)[0]), "entry point", ep) for ep in eps]
            todo += [(n, False, "checkout", v) for n, v in fallback.items()]
            # by name, as always; among plugins of the same name the built-in comes first, so a
            # clash blames the other one
            for name, _, kind, what in sorted(todo, key=lambda t: t[:2]):
                if not wanted(name):
                    continue
                if kind == "entry point":
                    self._load_entry_point(what)
                else:
                    self._load_checkout_builtin(name, what)
            self._warn_unknown_names(disabled, allowed, known)
        for obj in plugins:
            name = getattr(obj, "__name__", type(obj).__name__)
            if name in disabled:
                continue
            self._register(obj, name, getattr(obj, "__module__", name), "(registered in code)", "")
        self.check_pending()

    # ---------------------------------------------------------------- loading
    def _load_entry_point(self, ep):
        dist, version = _dist_of(ep)
        try:
            module = ep.load()
        except Exception as exc:
            self._import_failed(ep.name, ep.value, dist, version, exc, builtin=_is_builtin_dist(dist))
            return
        builtin = _is_builtin_dist(dist)
        try:
            self._register(module, ep.name, ep.value, dist, version, builtin=builtin)
        except PluginError as exc:
            if builtin or self.strict:
                raise
            if self.pm.get_plugin(ep.name) is module:  # pluggy may have added some of its hooks before failing
                self.pm.unregister(name=ep.name)
            self._warn_skipped(ep.name, ep.value, dist, version, f"it cannot be registered: {exc.reason}")
            return
        if not builtin:
            self.isolated.add(ep.name)

    def _load_checkout_builtin(self, name: str, value: str):
        from . import __version__

        try:
            module = _load_from_checkout(name, value, CHECKOUT)
        except Exception as exc:
            self._import_failed(name, value, BUILTIN_DISTRIBUTION, __version__, exc, builtin=True)
            return
        self._register(module, name, value, BUILTIN_DISTRIBUTION, __version__, builtin=True)

    def _import_failed(self, name, value, dist, version, exc, *, builtin):
        reason = _one_line(f"{type(exc).__name__}: {exc}")
        if builtin:  # mtbudget itself is broken: a run without one of its groups would be wrong, not smaller
            raise PluginError(f"built-in plugin {value!r} ({dist} {version}) failed to import: {reason}; "
                              f"reinstall mtbudget, or skip it with MTBUDGET_DISABLE_PLUGINS={name}",
                              name, hook="load") from exc
        self._warn_skipped(name, value, dist, version, f"it failed to import: {reason}")

    def _warn_skipped(self, name, value, dist, version, why: str):
        msg = (f"mtbudget: skipping plugin {name!r} ({value}, from {dist} {version}): {_one_line(why)}; "
               f"set MTBUDGET_DISABLE_PLUGINS={name} to silence this warning")
        self.skipped.append(msg)
        log.warning(msg)

    def _isolate(self, name: str, exc: PluginError) -> None:
        """Skip the registered third-party plugin ``name`` after ``exc``, or raise ``exc`` when it may not be
        skipped (a built-in, a plugin registered in code, MTBUDGET_STRICT_PLUGINS)."""
        if name not in self.isolated or self.strict:
            raise exc
        self.isolated.discard(name)
        info = self.info.pop(name)
        if self.pm.get_plugin(name) is not None:
            self.pm.unregister(name=name)
        hook = f"hook {exc.hook}: " if exc.hook and exc.hook != "register" and not exc.reason.startswith(exc.hook) else ""
        reason = exc.reason.split(", or skip that plugin with MTBUDGET_DISABLE_PLUGINS=")[0]  # said once, below
        self._warn_skipped(name, info.module, info.distribution, info.version, hook + reason)

    def _warn_unknown_names(self, disabled, allowed, known):
        for var, names in (("MTBUDGET_DISABLE_PLUGINS", disabled), ("MTBUDGET_PLUGINS", allowed or set())):
            for n in sorted(names - known):
                close = difflib.get_close_matches(n, sorted(known), 1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                log.warning(f"mtbudget: {var} names {n!r}, which is not an installed plugin{hint} "
                            f"(installed: {', '.join(sorted(known)) or 'none'})")

    def _register(self, obj, name, module, dist, version, *, builtin: bool = False):
        where = _where(module, dist, version)
        if name in self.info or self.pm.has_plugin(name):
            first = self.info.get(name, PluginInfo(name, "?", "?", "?"))
            first_where = _where(first.module, first.distribution, first.version)
            blamed = first_where if (builtin and name not in self.builtin) else where
            raise PluginError(f"two plugins are named {name!r}: {first_where} and {where}; the one from {blamed} "
                              "must be renamed (or its package uninstalled)", name, hook="register")
        try:
            self.pm.register(obj, name=name)
        except pluggy.PluginValidationError as exc:
            raise PluginError(_one_line(f"invalid hook implementation in {where}: {exc}"), name, hook="register") from None
        except ValueError as exc:  # the same object under two names
            raise PluginError(_one_line(f"cannot register {where}: {exc}"), name, hook="register") from None
        self.info[name] = PluginInfo(name, module, dist, version)
        if builtin:
            self.builtin.add(name)

    def check_pending(self) -> None:
        """Refuse functions named like hooks that mtbudget does not specify (pluggy's ``check_pending``).

        pluggy registers every ``@hookimpl`` function, whatever its name, and ignores
        unmarked ones; so a misspelled hook would never be called.  This raises a
        :class:`PluginError` naming the plugin and the function, with the closest real
        hook name: for a marked function whose hook does not exist (unless
        ``@hookimpl(optionalhook=True)``), for an unmarked function named exactly like a
        hook, and for an unmarked one that looks like a misspelled hook.
        """
        hooks = hook_names()
        for name, obj in list(self.pm.list_name_plugin()):
            if obj is None:
                continue
            try:
                self._check_plugin(name, obj, hooks)
            except PluginError as exc:
                self._isolate(name, exc)
        try:
            self.pm.check_pending()  # pluggy's own check, in case it knows more than the loop above
        except pluggy.PluginValidationError as exc:
            raise PluginError(_one_line(str(exc)), self.pm.get_name(exc.plugin), hook="register") from None

    def _check_plugin(self, name: str, obj, hooks: list) -> None:
        """check_pending for one plugin: raise the PluginError of its first function named like no hook."""
        callers = self.pm.get_hookcallers(obj) or []
        for caller in callers:
            if caller.has_spec():
                continue
            if any(impl.plugin is obj and not impl.optionalhook for impl in caller.get_hookimpls()):
                raise self._unknown_hook(name, caller.name, hooks)
        implemented = {c.name for c in callers}
        for attr in dir(obj):
            if not attr.startswith(_PROJECT + "_") or attr in implemented:
                continue
            fn = getattr(obj, attr, None)
            if not callable(fn) or isinstance(fn, type) or hasattr(fn, _PROJECT + "_spec") \
                    or hasattr(fn, _PROJECT + "_impl"):
                continue
            if attr in hooks:
                raise PluginError(f"{attr}() is not marked with @hookimpl, so it would never be called; "
                                  "decorate it (from mtbudget import hookimpl)", name, hook=attr)
            if difflib.get_close_matches(attr, hooks, 1, 0.8):
                raise self._unknown_hook(name, attr, hooks)

    def _unknown_hook(self, plugin: str, hook: str, hooks: list) -> PluginError:
        info = self.info.get(plugin)
        origin = f" (in {info.module}, {self._origin(plugin)})" if info else ""
        close = difflib.get_close_matches(hook, hooks, 1, 0.0)
        hint = f"did you mean {close[0]!r}? " if close else ""
        return PluginError(f"{hook}{origin} is not a hook of mtbudget, so it would never be called; {hint}"
                           f"the hooks are {', '.join(hooks)} (mtbudget.hookspecs)", plugin, hook=hook)

    def _origin(self, plugin: str) -> str:
        info = self.info.get(plugin)
        if info is None:
            return "?"
        return _where("", info.distribution, info.version).strip("() ")

    # ---------------------------------------------------------------- tracing (MTBUDGET_TRACE_PLUGINS)
    def _trace_before(self, hook_name, hook_impls, kwargs):
        self._trace_started.append(time.perf_counter())

    def _trace_after(self, outcome, hook_name, hook_impls, kwargs):
        ms = (time.perf_counter() - self._trace_started.pop()) * 1e3
        plugins = ", ".join(f"{i.plugin_name} ({self._origin(i.plugin_name)})" for i in hook_impls) or "none"
        args = ", ".join(f"{k}={_summary(v)}" for k, v in kwargs.items())
        exc = outcome.exception
        if exc is not None:
            result = _one_line(f"raised {type(exc).__name__}: {exc}")
        else:
            result = "ok"
            for v in kwargs.values():
                got = getattr(v, "registered", None)
                if isinstance(got, list):
                    result += f", registered {len(got)}" + (f": {', '.join(got)}" if got else "")
        _trace(f"hook {hook_name}({args}), plugin {plugins}: {result}, {ms:.3f} ms")

    # ---------------------------------------------------------------- calling hooks
    def _collect(self, hook_name: str, kind: type, check):
        hook = getattr(self.pm.hook, hook_name)
        found, owners = [], {}
        everyone = self.pm.get_plugins()

        def drop(plugin):  # what a skipped plugin registered in this call
            found[:] = [o for o in found if o.plugin != plugin]
            for key in [k for k, p in owners.items() if p == plugin]:
                del owners[key]

        for impl in hook.get_hookimpls():  # registration order
            plugin = impl.plugin_name
            if self.pm.get_plugin(plugin) is None:  # skipped while collecting (it clashed with a later plugin)
                continue
            info = self.info.get(plugin, PluginInfo(plugin, "?", "?", "?"))

            got: list[str] = []

            def register(obj, _plugin=plugin, _info=info, _got=got):
                if not isinstance(obj, kind):
                    raise PluginError(f"register() needs a {kind.__module__}.{kind.__name__}, got {type(obj).__name__}",
                                      _plugin, getattr(obj, "name", None), hook_name)
                obj.plugin, obj.dist_name, obj.dist_version = _plugin, _info.distribution, _info.version
                key = check(obj)
                if key in owners:
                    err = self._duplicate(hook_name, key, owners[key], _plugin, obj)
                    if err.plugin == _plugin:
                        raise err
                    drop(err.plugin)  # an earlier third-party plugin took a built-in's name: it goes, or it raises
                    self._isolate(err.plugin, err)
                owners[key] = _plugin
                found.append(obj)
                _got.append(_label(obj))

            register.registered = got  # shown by the trace
            # one plugin at a time, through pluggy (so hook-call monitoring sees each call)
            only = self.pm.subset_hook_caller(hook_name, remove_plugins=[p for p in everyone if p is not impl.plugin])
            try:
                only(register=register)
            except Exception as exc:
                err = exc if isinstance(exc, PluginError) else PluginError(
                    f"raised {type(exc).__name__}: {_one_line(exc)} (from {info.distribution} {info.version})",
                    plugin, hook=hook_name)
                if plugin not in self.isolated or self.strict:
                    if err is exc:
                        raise
                    raise err from exc
                drop(plugin)
                self._isolate(plugin, err)
        return found

    def _duplicate(self, hook_name: str, key, first: str, second: str, obj) -> PluginError:
        """Two plugins registered the same name: name both, blame the later one, never a built-in."""
        blamed = first if second in self.builtin and first not in self.builtin else second
        what = "source" if isinstance(obj, Source) else "exporter" if isinstance(obj, Exporter) else "candidate"
        shown = key if isinstance(key, str) else _label(obj)
        return PluginError(f"duplicate {what} name {shown!r}: already registered by plugin {first!r} ({self._origin(first)}), "
                           f"registered again by plugin {second!r} ({self._origin(second)}); plugin {blamed!r} must rename "
                           f"it, or skip that plugin with MTBUDGET_DISABLE_PLUGINS={blamed}",
                           blamed, shown if what == "source" else None, hook_name)

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

    def exporters(self) -> list[Exporter]:
        """Every registered compensation-table exporter, validated (mtbudget compensate --format)."""
        def check(e: Exporter):
            where = dict(plugin=e.plugin, hook="mtbudget_register_exporters")
            if not e.name or not isinstance(e.name, str):
                raise PluginError("an exporter needs a non-empty string name", **where)
            if not isinstance(e.suffix, str) or not e.suffix.startswith("."):
                raise PluginError(f"exporter {e.name!r}: suffix must be a file suffix such as '.csv', got {e.suffix!r}",
                                  **where)
            if not isinstance(e.convention, str) or not e.convention.strip():
                raise PluginError(f"exporter {e.name!r} must cite the convention it follows (attribute 'convention')",
                                  **where)
            return e.name

        return self._collect("mtbudget_register_exporters", Exporter, check)

    def plugins(self) -> list[PluginInfo]:
        return [self.info[n] for n in sorted(self.info)]


def _hook_of(obj) -> str | None:
    if isinstance(obj, Source):
        return "mtbudget_register_sources"
    if isinstance(obj, Candidate):
        return "mtbudget_register_candidates"
    if isinstance(obj, Exporter):
        return "mtbudget_register_exporters"
    return None


def call(obj, method: str, *args, **kwargs):
    """Call ``obj.method(*args, **kwargs)`` on a registered plugin object (a source, a candidate).

    Every call into plugin code goes through here: an exception inside it
    becomes one :class:`~mtbudget.errors.PluginError` that names the plugin,
    the object, the hook it was registered by and the method.  With
    ``MTBUDGET_TRACE_PLUGINS=1`` each call is traced to stderr.
    """
    if not tracing():
        return _call(obj, method, args, kwargs)
    start, result = time.perf_counter(), "ok"
    try:
        return _call(obj, method, args, kwargs)
    except BaseException as exc:
        result = _one_line(f"raised {type(exc).__name__}: {exc}")
        raise
    finally:
        ms = (time.perf_counter() - start) * 1e3
        shown = ", ".join([_summary(a) for a in args] + [f"{k}={_summary(v)}" for k, v in kwargs.items()])
        origin = _where("", getattr(obj, "dist_name", "") or "?", getattr(obj, "dist_version", "") or "").strip()
        _trace(f"method {_label(obj)}.{method}({shown}), plugin {getattr(obj, 'plugin', '') or '?'} {origin}, "
               f"hook {_hook_of(obj) or '?'}: {result}, {ms:.3f} ms")


def caller():
    """:func:`call` with ``MTBUDGET_TRACE_PLUGINS`` read once, for a run of calls (a block's sources): the environment
    is read when this is asked, not at each call."""
    return call if tracing() else _untraced


def _untraced(obj, method: str, *args, **kwargs):
    return _call(obj, method, args, kwargs)


def _call(obj, method: str, args, kwargs):
    try:
        out = getattr(obj, method)(*args, **kwargs)
        if method in _SAMPLES and isinstance(obj, Source) and obj.dist_name != BUILTIN_DISTRIBUTION:
            # finite but absurd (1e300 mm) would overflow into inf/nan results; mtbudget's own sources are tested
            # (and spared the 2 % of a run the check costs them)
            check_plausible(obj, out, method)
        return out
    except PluginError as exc:
        if exc.method is None and exc.plugin in (None, getattr(obj, "plugin", None)):
            raise PluginError(exc.reason, exc.plugin or getattr(obj, "plugin", None) or None,
                              exc.source or _label(obj), exc.hook or _hook_of(obj), method) from exc
        raise
    except Exception as exc:
        raise PluginError(f"raised {type(exc).__name__}: {exc}", getattr(obj, "plugin", None) or None, _label(obj),
                          _hook_of(obj), method) from exc


_SAMPLES = ("sample", "sample_internal")


def _label(obj):
    return getattr(obj, "label", None) or getattr(obj, "name", None) or type(obj).__name__


_default: PluginHost | None = None


def default_host() -> PluginHost:
    """The process-wide host built from the entry points (cached)."""
    global _default
    if _default is None:
        _default = PluginHost()
    return _default
