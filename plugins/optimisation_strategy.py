"""Built-in sources of the optimisation-strategy group (paper Section 2.2.4, Figs. 5-6).

Each draws, per trial, one of several equally plausible identification
settings; the spread of the results between them is its contribution.
"""

from __future__ import annotations

from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_, ureg

_ONE = ureg.Unit("")  # built once: Q_(x, "") parses the unit on every call


class _Choice(Source):
    group = Group.OPTIMISATION_STRATEGY
    distribution = "uniform over the options"
    targets = ("strategy",)

    def sample(self, n, rng, ctx):
        return {"strategy": Q_(rng.integers(0, self._count(ctx), n).astype(float), _ONE)}

    def _count(self, ctx) -> int:
        """``len(self.options(ctx))``, remembered while the parameters are the same objects (sampled once per block)."""
        params = tuple(self.parameters.values())
        hit = self.__dict__.get("_count_cache")
        if hit is None or len(hit[0]) != len(params) or any(a is not b for a, b in zip(hit[0], params)):
            hit = (params, len(self.options(ctx)))
            self.__dict__["_count_cache"] = hit
        return hit[1]


class ApproximationDegree(_Choice):
    """Legendre degree of the error functions: ``low`` or ``high`` (capped by the mesh)."""

    name = "approximation_degree"
    #: a lower degree than the machine needs is a bias, not an uncertainty: off unless enabled
    opt_in = True
    parameters = {"low": Q_(2), "high": Q_(3)}

    def options(self, ctx):
        return [{"max_degree": int(self.parameters["low"].magnitude)}, {"max_degree": int(self.parameters["high"].magnitude)}]


class ModelForm(Source):
    """The machine's error functions are richer than the identification's polynomials (GUM 3.2.4, 6.3.1; the paper's
    approximation function, Section 2.2.4): every error function gets a next Legendre term, degree max_degree + 1,
    drawn afresh in every trial, which the identification cannot represent.  Its effect on the compensated machine
    is the model-form contribution of the budget.

    How it is bounded: the standard deviation of the next term continues the halving per order of the paper
    configuration's generation functions (15, 8, 4 um -> 2 um; 80, 40, 20 urad -> 10 urad); state your own from a
    verification of higher degree or from the machine's known periodic errors.
    """

    name = "model_form"
    group = Group.OPTIMISATION_STRATEGY
    distribution = "normal, per coefficient of the next Legendre degree"
    targets = ("geometry.translational", "geometry.angular")
    parameters = {"translational": Q_(2.0, "um"), "angular": Q_(10.0, "urad")}
    nonnegative = ("translational", "angular")
    #: it makes the simulated machine one degree richer: off unless enabled (docs/measurand.md, "Model form")
    opt_in = True

    def standard_uncertainty(self):
        return self.parameters["translational"].to("um")

    def sample(self, n, rng, ctx):
        import numpy as np

        top = ctx.config.max_degree + 1
        extra = np.array([p.order == top and not p.is_squareness for p in ctx.model.errors.params])
        z = rng.standard_normal((n, len(extra))) * extra
        mm, rad = ctx.parameter_mask("mm"), ctx.parameter_mask("rad")
        return {"geometry.translational": Q_(z * mm * self.parameters["translational"].to("mm").magnitude, "mm"),
                "geometry.angular": Q_(z * rad * self.parameters["angular"].to("rad").magnitude, "rad")}


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
    for cls in (ApproximationDegree, ModelForm, ConvergenceCriteria, PhaseSequence):
        register(cls())
