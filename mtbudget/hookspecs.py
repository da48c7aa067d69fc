"""Every hook of mtbudget, with its contract.

Plugins implement hooks with the ``hookimpl`` marker::

    from mtbudget.hookspecs import hookimpl

    @hookimpl
    def mtbudget_register_sources(register):
        register(MySource())

Plugins are found through the entry-point group ``mtbudget``
(``[project.entry-points.mtbudget] name = "package.module"``); mtbudget's
own built-in plugins are registered the same way.  docs/plugins.md has one
heading per hook below.
"""

from __future__ import annotations

import pluggy

hookspec = pluggy.HookspecMarker("mtbudget")
hookimpl = pluggy.HookimplMarker("mtbudget")


@hookspec
def mtbudget_register_sources(register):
    """Register uncertainty sources for the Monte Carlo engine.

    :param register: call ``register(source)`` once per source, with an
        instance of :class:`mtbudget.contracts.Source`.  mtbudget stamps each
        source with the plugin that registered it, checks its name is unique,
        its group one of the paper's four, its parameters pint quantities, and
        (when a run is built) that a probe sample has the declared keys,
        shapes and dimensions.
    :return: nothing; the return value is ignored.
    """


@hookspec
def mtbudget_register_candidates(register):
    """Register candidate physics terms for ``mtbudget diagnose``.

    :param register: call ``register(candidate)`` once per candidate, with an
        instance of :class:`mtbudget.diagnose.Candidate`: an effect that a
        rigid-body model leaves out (thermal expansion, reversal, tracker
        drift, ...), with its name, axis, the recording columns it needs and
        the columns it adds to the identification's design.
    :return: nothing; the return value is ignored.
    """
