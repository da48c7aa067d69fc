"""Every hook of mtbudget, with its contract.

Plugins implement hooks with the ``hookimpl`` marker (re-exported as
``mtbudget.hookimpl``)::

    from mtbudget import hookimpl

    @hookimpl
    def mtbudget_register_sources(register):
        register(MySource())

Plugins are found through the entry-point group ``mtbudget``
(``[project.entry-points.mtbudget] name = "package.module"``); mtbudget's
own built-in plugins are registered the same way.  A function named like a
hook that is not one below is refused when plugins load (with the closest
hook name).  docs/plugins.md has one heading per hook below, and
tests/ one test named ``test_hook_<name>`` per hook.

The annotations name the contract classes of :mod:`mtbudget.contracts`
(``Source``, ``Candidate``) without importing them: that module sits a layer
above this one (docs/architecture.md), and the annotations are never
evaluated (``from __future__ import annotations``); pluggy matches hook
implementations by argument name only.
"""

from __future__ import annotations

from collections.abc import Callable

import pluggy

hookspec = pluggy.HookspecMarker("mtbudget")
hookimpl = pluggy.HookimplMarker("mtbudget")


@hookspec
def mtbudget_register_sources(register: Callable[[Source], None]) -> None:  # noqa: F821 (mtbudget.contracts)
    """Register uncertainty sources for the Monte Carlo engine.

    Called once per plugin each time the host collects sources (``PluginHost.sources()``);
    register fresh instances every time.

    :param register: a callback; call ``register(source)`` once per source,
        with an instance of :class:`mtbudget.contracts.Source`.  mtbudget
        stamps each source with the plugin, distribution and version that
        registered it, and checks that its name is unique across all plugins
        (a duplicate names both plugins and blames the later, never a
        built-in), its group is one of the paper's four, its targets are keys
        of :data:`mtbudget.contracts.TARGETS` and its parameters pint
        quantities; when a run is built, that a probe sample has the
        declared keys, shapes and dimensions.  ``register`` raises
        :class:`mtbudget.errors.PluginError` on the first violation.
    :return: nothing; the return value is ignored.  An exception raised
        inside the hook becomes a :class:`~mtbudget.errors.PluginError`
        naming the plugin, this hook and the package version.
    """


@hookspec
def mtbudget_register_candidates(register: Callable[[Candidate], None]) -> None:  # noqa: F821 (mtbudget.contracts)
    """Register candidate physics terms for ``mtbudget diagnose``.

    Called once per plugin each time the host collects candidates (``PluginHost.candidates()``);
    register fresh instances every time.

    :param register: a callback; call ``register(candidate)`` once per
        candidate, with an instance of :class:`mtbudget.contracts.Candidate`:
        an effect that a rigid-body model leaves out (thermal expansion,
        reversal, tracker drift, ...), with its name, axis, the recording
        columns it needs and the columns it adds to the identification's
        design.  mtbudget stamps it with the plugin that registered it and
        checks that its (effect, axis) pair is unique across all plugins.
    :return: nothing; the return value is ignored.  An exception raised
        inside the hook becomes a :class:`~mtbudget.errors.PluginError`
        naming the plugin, this hook and the package version.
    """


@hookspec
def mtbudget_register_exporters(register: Callable[[Exporter], None]) -> None:  # noqa: F821 (mtbudget.contracts)
    """Register compensation-table exporters for ``mtbudget compensate --format NAME``.

    Called once per plugin each time the host collects exporters (``PluginHost.exporters()``);
    register fresh instances every time.

    :param register: a callback; call ``register(exporter)`` once per exporter, with an
        instance of a subclass of :class:`mtbudget.contracts.Exporter`: its name, description,
        file suffix, the documented convention it follows (a citation) and ``write(table, path)``.
        mtbudget stamps it with the plugin, distribution and version that registered it and
        checks that its name is unique across all plugins and that it states a suffix and a
        convention.  ``register`` raises :class:`mtbudget.errors.PluginError` on the first violation.
    :return: nothing; the return value is ignored.  An exception raised
        inside the hook becomes a :class:`~mtbudget.errors.PluginError`
        naming the plugin, this hook and the package version.
    """
