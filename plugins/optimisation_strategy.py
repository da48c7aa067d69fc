"""Built-in sources of the optimisation-strategy group (paper Section 2.2.4, Figs. 5-6).

Each draws, per trial, one of several equally plausible identification
settings; the spread of the results between them is its contribution.
"""

from __future__ import annotations

from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_

from .machine_tool import COUPLING_PAIRS, axis_unit_positions

# Every source draws in ``sample_internal`` (float64 arrays in the targets' internal units; see
# plugins/machine_tool.py); ``sample`` wraps them as quantities.


class _Choice(Source):
    group = Group.OPTIMISATION_STRATEGY
    distribution = "uniform over the options"
    targets = ("strategy",)

    def sample_internal(self, n, rng, ctx):
        return {"strategy": rng.integers(0, self._count(ctx), n).astype(float)}

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
    verification of higher degree (``[sources.model_form] translational = "3 um"``).  The machine's periodic errors
    and the couplings of two axes are the sources ``model_form_periodic`` and ``model_form_coupling``.
    """

    name = "model_form"
    group = Group.OPTIMISATION_STRATEGY
    distribution = "normal, per coefficient of the next Legendre degree"
    targets = ("geometry.translational", "geometry.angular")
    parameters = {"translational": Q_(2.0, "um"), "angular": Q_(10.0, "urad")}
    plausible = {"translational": Q_(500.0, "um"), "angular": Q_(1000.0, "urad")}  # 0.5-100 um, 2-200 urad
    nonnegative = ("translational", "angular")
    #: it makes the simulated machine one degree richer: off unless enabled (docs/measurand.md, "Model form")
    opt_in = True
    #: shown in the budget as a systematic contribution of this kind, with the sentence of :meth:`bounded`
    systematic = "model form"

    def bounded(self, ctx):
        """One sentence: how the contribution was bounded."""
        top = ctx.config.max_degree + 1 if ctx.config is not None else "max_degree + 1"
        return (f"the next Legendre term (degree {top}) of every error function, normal with standard deviation "
                f"{self.parameters['translational'].to('um').magnitude:g} um and "
                f"{self.parameters['angular'].to('urad').magnitude:g} urad (the halving per order of the generation "
                "functions continued); set [sources.model_form] translational and angular from a verification of "
                "higher degree.")

    def standard_uncertainty(self):
        return self.parameters["translational"].to("um")

    def _prepare(self, ctx):
        import numpy as np

        top = ctx.config.max_degree + 1
        extra = np.array([p.order == top and not p.is_squareness for p in ctx.model.errors.params])
        return extra, ctx.parameter_mask("mm"), ctx.parameter_mask("rad"), self.value("translational", "mm"), \
            self.value("angular", "rad")

    def sample_internal(self, n, rng, ctx):
        key = (*self.parameters.values(), ctx, ctx.config, ctx.model, ctx.config.max_degree)
        extra, mm, rad, tr, ang = self.remembered(key, lambda: self._prepare(ctx))
        z = rng.standard_normal((n, len(extra))) * extra
        return {"geometry.translational": z * mm * tr, "geometry.angular": z * rad * ang}


class ModelFormPeriodic(Source):
    """A periodic positioning error of each axis with the lead of its ball screw (the nut and screw, the rotary
    encoder's phase), which no polynomial of the identification represents.  Per trial and axis
    e_a(p) = c cos(2 pi p / lead_a) + s sin(2 pi p / lead_a), with c and s normal (standard deviation u_a): the phase
    is uniform, and u_a is the standard uncertainty of the error at any position (its amplitude sqrt(c^2 + s^2) has
    E[A^2] = 2 u_a^2).  It displaces the tool point along that axis at every measured point (``point_offset``) and the
    compensated machine by the same amount at the same axis positions (``measurand_offset``): the verification sees
    it but cannot model it, and the compensated machine keeps what the polynomials do not absorb.  A positioning
    error depends on the axis position only, never on the tool.

    How it is bounded: by default leads of 10, 10 and 5 mm and u = 1 um per axis (an RMS amplitude of 1.4 um, a
    judgement for a ground ball screw of a 1 m class machining centre, not a measurement).  State
    your own: ``[sources.model_form_periodic] lead_x = "16 mm"``, and ``u_x = A / sqrt(2)`` for an amplitude A that
    an ISO 230-2 positioning test with steps finer than the lead (for example lead / 8 over two leads) measured or
    bounds.  A mesh whose positions on an axis are a whole number of leads apart sees one phase on that axis (a
    translation the rigid-body part absorbs): nothing is left at the mesh points, all of it between them.  The
    budget row says so (``bounded``).
    """

    name = "model_form_periodic"
    group = Group.OPTIMISATION_STRATEGY
    distribution = "normal per sine and cosine coefficient (uniform phase), per trial and axis"
    targets = ("point_offset", "measurand_offset")
    parameters = {"lead_x": Q_(10.0, "mm"), "lead_y": Q_(10.0, "mm"), "lead_z": Q_(5.0, "mm"),
                  "u_x": Q_(1.0, "um"), "u_y": Q_(1.0, "um"), "u_z": Q_(1.0, "um")}
    #: a ball screw's lead is 5-50 mm, a rack-and-pinion's period pi m z 300-500 mm
    plausible = {**{f"lead_{a}": Q_(2000.0, "mm") for a in "xyz"}, **{f"u_{a}": Q_(100.0, "um") for a in "xyz"}}
    nonnegative = ("u_x", "u_y", "u_z")
    #: it makes the simulated machine richer than any identification model: off unless enabled (docs/measurand.md)
    opt_in = True
    #: shown in the budget as a systematic contribution of this kind, with the sentence of :meth:`bounded`
    systematic = "model form"

    def check(self):
        for a in "xyz":
            if not self.parameters[f"lead_{a}"].magnitude > 0:
                return f"parameter 'lead_{a}' must be positive, got {self.parameters[f'lead_{a}']:~P}"
        return super().check()

    def standard_uncertainty(self):
        return max((self.parameters[f"u_{a}"].to("um") for a in "xyz"), key=lambda q: q.magnitude)

    def displacement(self, nominal, c, s):
        """(n, M, 3) mm: the periodic error at axis positions ``nominal`` (M, 3, mm) for cosine and sine coefficients
        ``c``, ``s`` (n, 3, mm)."""
        import numpy as np

        lead = np.array([self.value(f"lead_{a}", "mm") for a in "xyz"])
        w = 2.0 * np.pi * np.asarray(nominal, float) / lead  # (M, 3)
        return c[:, None, :] * np.cos(w)[None] + s[:, None, :] * np.sin(w)[None]

    def sample_internal(self, n, rng, ctx):
        import numpy as np

        u = np.array([self.value(f"u_{a}", "mm") for a in "xyz"])
        c, s = rng.standard_normal((2, n, 3)) * u
        d = self.displacement(ctx.plan.nominal, c, s)
        return {"point_offset": d, "measurand_offset": d.copy()}

    def bounded(self, ctx):
        """One sentence: how the contribution was bounded, and what this plan's mesh lets it show."""
        import numpy as np

        parts = ", ".join(f"{a} {self.parameters[f'lead_{a}'].to('mm').magnitude:g} mm" for a in "xyz")
        us = ", ".join(f"{self.parameters[f'u_{a}'].to('um').magnitude:g}" for a in "xyz")
        text = (f"a periodic positioning error with the lead of each axis' screw ({parts}), standard uncertainty "
                f"{us} um at any position (x, y, z), uniform phase; set [sources.model_form_periodic] lead_x and "
                f"u_x = A / sqrt(2) for a measured amplitude A.")
        aliased, fitted = [], []
        rows = np.asarray(ctx.plan.nominal, float)
        degree = ctx.config.max_degree if ctx.config is not None else None
        for i, a in enumerate("xyz"):
            pos = np.unique(rows[:, i])
            turns = (pos - pos[0]) / self.value(f"lead_{a}", "mm")
            if np.allclose(turns, np.round(turns), rtol=0.0, atol=1e-9):
                aliased.append(a)
            elif degree is not None and len(pos) <= degree + 1:
                fitted.append(a)
        notes = []
        if aliased:
            notes.append(f"{', '.join(aliased)}: the plan's positions are whole leads apart, so every point sees one "
                         "phase, a translation the rigid-body part of the verification absorbs (the tracker pose, or "
                         "the stations' datum)")
        if fitted:
            npos = {a: len(np.unique(rows[:, "xyz".index(a)])) for a in fitted}
            notes.append("; ".join(f"{a}: a polynomial of degree {npos[a] - 1} passes through the error at each of the "
                                   f"plan's {npos[a]} positions" for a in fitted))
        if notes:
            text += (f" On this plan nothing of the {', '.join(aliased + fitted)} error is left at the mesh points, all "
                     "of it between them, where the measurand is not evaluated (" + "; ".join(notes) + ").")
        return text


class ModelFormCoupling(Source):
    """Errors that depend on two axes together beyond what the rigid-body model represents (a z error that grows with
    x and y together, a structure that twists): per trial and pair of axes, the error along the third axis is
    sum over 1 <= i, j <= degree of c_ij P_i(u_a) P_j(u_b), the P Legendre polynomials and u the axis positions
    scaled to [-1, 1] over the plan's range (the shapes of the simulated-physics source ``axis_coupling``, whose
    ``xy`` term is c_11), each c_ij normal with the pair's standard deviation (``xy`` for the z error, ``xz`` for the
    y error, ``yz`` for the x error).  Like ``model_form_periodic`` it acts on the measured points (``point_offset``)
    and on the compensated machine at the same axis positions (``measurand_offset``); what the identification's
    products of angular errors and lever arms absorb (a bilinear x y term partly, a y z term along x entirely) is not
    left, and the budget shows only the rest.

    How it is bounded: by default 1 um per cross term and pair, degree 2 (bilinear and biquadratic), a quarter of the
    paper configuration's P3 generation function (4 um): a judgement, not a measurement.  State your own:
    ``[sources.model_form_coupling] xy = "2 um"`` from a verification with a finer mesh, from the ISO 230-6 diagonal
    displacements or from the builder's data, and ``degree = 1`` for bilinear couplings only.
    """

    name = "model_form_coupling"
    group = Group.OPTIMISATION_STRATEGY
    distribution = "normal per coefficient of the cross terms P_i(u_a) P_j(u_b), per trial and pair"
    targets = ("point_offset", "measurand_offset")
    parameters = {"xy": Q_(1.0, "um"), "xz": Q_(1.0, "um"), "yz": Q_(1.0, "um"), "degree": Q_(2)}
    plausible = {k: Q_(500.0, "um") for k in ("xy", "xz", "yz")}  # coupling errors of 1-100 um
    nonnegative = ("xy", "xz", "yz")
    opt_in = True
    systematic = "model form"

    def check(self):
        d = float(self.parameters["degree"].magnitude)
        if d != round(d) or not 1 <= d <= 4:
            return f"parameter 'degree' must be a whole number from 1 to 4, got {d:g}"
        return super().check()

    def standard_uncertainty(self):
        return max((self.parameters[p].to("um") for p in COUPLING_PAIRS), key=lambda q: q.magnitude)

    def shapes(self, nominal):
        """{pair: (third axis index, (k, M) shapes P_i(u_a) P_j(u_b), i, j = 1..degree)} at axis positions ``nominal``."""
        import numpy as np
        from numpy.polynomial import legendre

        deg = int(round(float(self.parameters["degree"].magnitude)))
        u = axis_unit_positions(nominal)
        out = {}
        for pair, (a, b, third) in COUPLING_PAIRS.items():
            Pa = [legendre.legval(u[:, a], np.eye(deg + 1)[i]) for i in range(1, deg + 1)]
            Pb = [legendre.legval(u[:, b], np.eye(deg + 1)[j]) for j in range(1, deg + 1)]
            out[pair] = (third, np.array([pa * pb for pa in Pa for pb in Pb]))
        return out

    def sample_internal(self, n, rng, ctx):
        import numpy as np

        nominal = ctx.plan.nominal
        shapes = self.shapes(nominal)
        k = len(next(iter(shapes.values()))[1])
        z = rng.standard_normal((n, len(COUPLING_PAIRS), k))  # every pair drawn, so one pair's setting never moves another's
        d = np.zeros((n, len(nominal), 3))
        for j, (pair, (third, S)) in enumerate(shapes.items()):
            d[:, :, third] += (z[:, j] * self.value(pair, "mm")) @ S
        return {"point_offset": d, "measurand_offset": d.copy()}

    def bounded(self, ctx):
        deg = int(round(float(self.parameters["degree"].magnitude)))
        sd = ", ".join(f"{p} {self.parameters[p].to('um').magnitude:g}" for p in COUPLING_PAIRS)
        return (f"couplings of two axes along the third, the cross terms P_i P_j (i, j <= {deg}) of the axis positions, "
                f"each normal with standard deviation {sd} um (pair); set [sources.model_form_coupling] xy, xz, yz and "
                "degree from a finer verification or the ISO 230-6 diagonals; what the model's angular errors absorb is "
                "not counted.")


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
    for cls in (ApproximationDegree, ModelForm, ModelFormPeriodic, ModelFormCoupling, ConvergenceCriteria,
                PhaseSequence):
        register(cls())
