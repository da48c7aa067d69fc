"""Built-in sources of the optimisation-strategy group (paper Section 2.2.4, Figs. 5-6).

Each draws, per trial, one of several equally plausible identification
settings; the spread of the results between them is its contribution.
"""

from __future__ import annotations

from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_


class _Choice(Source):
    group = Group.OPTIMISATION_STRATEGY
    distribution = "uniform over the options"
    targets = ("strategy",)

    def sample(self, n, rng, ctx):
        return {"strategy": Q_(rng.integers(0, len(self.options(ctx)), n).astype(float), "")}


class ApproximationDegree(_Choice):
    """Legendre degree of the error functions: ``low`` or ``high`` (capped by the mesh)."""

    name = "approximation_degree"
    #: a lower degree than the machine needs is a bias, not an uncertainty: off unless enabled
    opt_in = True
    parameters = {"low": Q_(2), "high": Q_(3)}

    def options(self, ctx):
        return [{"max_degree": int(self.parameters["low"].magnitude)}, {"max_degree": int(self.parameters["high"].magnitude)}]


class ConvergenceCriteria(_Choice):
    """Convergence tolerance of the Gauss-Newton iterations: tight or loose, and the iteration limit."""

    name = "convergence_criteria"
    parameters = {"tight": Q_(1e-4, "um"), "loose": Q_(0.5, "um"), "max_iter_loose": Q_(2)}

    def options(self, ctx):
        return [{"xtol": float(self.parameters["tight"].to("um").magnitude)},
                {"xtol": float(self.parameters["loose"].to("um").magnitude),
                 "max_iter": int(self.parameters["max_iter_loose"].magnitude)}]


class PhaseSequence(_Choice):
    """One-phase identification (the paper's choice for XFYZ) or multi-phase (pose, translational, all)."""

    name = "phase_sequence"
    parameters = {}

    def options(self, ctx):
        return [{"phases": "one-phase"}, {"phases": "multi-phase"}]


@hookimpl
def mtbudget_register_sources(register):
    for cls in (ApproximationDegree, ConvergenceCriteria, PhaseSequence):
        register(cls())
