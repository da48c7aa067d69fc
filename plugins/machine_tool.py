"""Built-in sources of the machine-tool group (paper Section 2.2.1, Eq. 3, 10, 14-20)."""

from __future__ import annotations

import math

import numpy as np

from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_

# Every source draws in ``sample_internal``: float64 arrays already in each target's internal unit (mm, rad,
# dimensionless), so the engine builds no pint quantity per block; ``sample`` (the contract) wraps them as quantities.
# What a source derives from its parameters and the plan is remembered (``Source.remembered``), and the draws of
# the three axes are one call where NumPy gives the same numbers that way (consecutive draws of one generator).

AXES = ("x", "y", "z")


def _axis_temperatures(ctx):
    return {a: ctx.plan.axis_temperature(a, ctx.reference_temperature) for a in AXES}


def normal0(rng, scale: float, size) -> np.ndarray:
    """``rng.normal(0.0, scale, size)``, bit for bit and faster: NumPy draws ``0.0 + scale * z`` from the same standard
    normal ``z`` that ``standard_normal`` gives (the ``+ 0.0`` only turns a -0.0 into 0.0).  A scale that is not
    positive goes to ``rng.normal`` itself (which refuses a negative one)."""
    if not scale > 0.0:
        return rng.normal(0.0, scale, size)
    z = rng.standard_normal(size)
    z *= scale
    z += 0.0
    return z


def _key(src, ctx) -> tuple:
    """What a source's remembered values of the plan depend on: its parameters and the context's plan."""
    return (*src.parameters.values(), ctx, ctx.plan, ctx.reference_temperature)


def _axis_ctes(src, ctx) -> dict:
    """The nominal CTE (1/K) of each axis scale: the stated scale's ([scales.<axis>] of the configuration, the plan's
    ``scales``) where there is one, else the source's ``cte`` ([machine_tool] cte, the axes without a stated scale).

    Where a scale is stated the simulated machine has its nominal expansion and the verification corrects it at the
    read temperature (mtbudget.scenario.Scenario.truth_inputs); these sources then draw what the correction cannot
    know, the deviation of the true expansion from the corrected one, and it acts about the scale's fixed point.
    Without a stated scale the nominal expansion is taken as perfectly corrected and the deviation acts about the
    axis zero (the paper's Eq. 7-9)."""
    scales = getattr(ctx.plan, "scales", None) or {}
    default = src.value("cte", "1/K")
    return {a: scales[a].cte if a in scales else default for a in AXES}


def _at(values, weights) -> float:
    """The scalar ``s`` of ``values = s * weights`` (a source's per-point array of one trial, a known per-point factor):
    least squares over the points where the factor is not zero; NaN where it is zero everywhere (nothing drawn shows)."""
    values, weights = np.asarray(values, float).ravel(), np.broadcast_to(np.asarray(weights, float), np.shape(values)).ravel()
    m = weights != 0
    if not m.any():
        return math.nan
    return float(values[m] @ weights[m] / (weights[m] @ weights[m]))


class TemperatureSensorCalibration(Source):
    """Each axis sensor reads with a calibration offset (Eq. 3: u_device = u_calibration / k).

    The compensation uses the reading, so the scale of each axis is off by
    CTE * offset for the whole test.
    """

    name = "temperature_sensor_calibration"
    group = Group.MACHINE_TOOL
    distribution = "normal (Type B, Eq. 3)"
    targets = ("axis_scale.x", "axis_scale.y", "axis_scale.z")
    parameters = {"u_calibration": Q_(0.1, "K"), "k": Q_(2.0), "cte": Q_(11.5, "um/(m*K)")}
    plausible = {"u_calibration": Q_(2.0, "K")}  # sensors are calibrated to 0.01-0.3 K
    links = {"cte": "machine_tool.cte"}
    nonnegative = ("u_calibration", "k")

    def standard_uncertainty(self):
        return (self.parameters["u_calibration"] / self.parameters["k"]).to("K")

    def _prepare(self, ctx):
        cte = _axis_ctes(self, ctx)
        return (self.value("u_calibration", "K") / float(self.parameters["k"].magnitude),
                np.array([cte[a] for a in AXES], float)[:, None, None])

    def sample_internal(self, n, rng, ctx):
        # the true axis temperature is the reading plus the sensor's calibration error dT: the scale is off by
        # CTE dT against the correction made at the reading (about the fixed point of a stated scale)
        u, cte = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        dT = rng.normal(0.0, u, (3, n, 1))  # x, y, z: the numbers of three (n, 1) draws in turn
        out = np.empty((3, n, ctx.n_points))
        np.multiply(cte, dT, out=out)
        return {"axis_scale.x": out[0], "axis_scale.y": out[1], "axis_scale.z": out[2]}

    def drawn(self, sample, ctx):
        cte = _axis_ctes(self, ctx)
        return {f"sensor_error_{a}": {
            "value": _at(sample[f"axis_scale.{a}"], cte[a]), "unit": "K",
            "meaning": f"the true {a}-axis temperature minus what its sensor reads (its calibration error): the {a} "
                       "scale is off by CTE times it for the whole test, a constant scale error the identified "
                       "positioning error takes"} for a in AXES}


class CTEUncertainty(Source):
    """Uncertainty of each axis' expansion coefficient (Eq. 10).

    The full width is 10 % of the nominal CTE but never below 0.002 um/(mm K);
    the coefficient error is rectangular over it (u = width / (2 sqrt 3)) and
    scales each axis by dalpha * (T_axis - T_ref).
    """

    name = "cte_uncertainty"
    group = Group.MACHINE_TOOL
    distribution = "rectangular (Eq. 10)"
    targets = ("axis_scale.x", "axis_scale.y", "axis_scale.z")
    parameters = {"cte": Q_(11.5, "um/(m*K)"), "fraction": Q_(0.10), "floor": Q_(0.002, "um/(mm*K)")}
    plausible = {"fraction": Q_(1.0), "floor": Q_(50.0, "um/(m*K)")}  # a CTE known to 1-30 %; 2 um/(m*K)
    links = {"cte": "machine_tool.cte"}
    nonnegative = ("fraction", "floor")

    def width(self, cte: float | None = None) -> float:
        """Full width (1/K) for a nominal CTE (default: the ``cte`` parameter, [machine_tool] cte)."""
        cte = self.value("cte", "1/K") if cte is None else cte
        return max(float(self.parameters["fraction"].magnitude) * abs(cte), self.value("floor", "1/K"))

    def standard_uncertainty(self):
        return Q_(self.width() / (2 * math.sqrt(3)), "1/K").to("um/(m*K)")

    def _prepare(self, ctx):
        cte = _axis_ctes(self, ctx)
        T = _axis_temperatures(ctx)
        w = np.array([self.width(cte[a]) for a in AXES], float)
        dT = np.stack([T[a] - ctx.reference_temperature for a in AXES])[:, None, :]
        return [(float(lo), float(hi)) for lo, hi in zip(-w / 2, w / 2)], dT

    def sample_internal(self, n, rng, ctx):
        # the true CTE is the nominal one plus dalpha: against the correction made with the nominal CTE the scale is
        # off by dalpha (T_axis - T_ref), about the fixed point of a stated scale
        bounds, dT = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        dalpha = np.empty((3, n, 1))
        for i, (low, high) in enumerate(bounds):  # three (n, 1) draws in turn, each with NumPy's scalar bounds
            dalpha[i] = rng.uniform(low, high, (n, 1))
        out = np.empty((3, n, ctx.n_points))
        np.multiply(dalpha, dT, out=out)
        return {"axis_scale.x": out[0], "axis_scale.y": out[1], "axis_scale.z": out[2]}

    def drawn(self, sample, ctx):
        T = _axis_temperatures(ctx)
        return {f"cte_deviation_{a}": {
            "value": _at(sample[f"axis_scale.{a}"], T[a] - ctx.reference_temperature) * 1e6, "unit": "um/(m*K)",
            "meaning": f"the true CTE of the {a} scale minus the nominal one the correction uses: the scale moves by "
                       f"it times (T_{a} - T_ref) beyond the correction, following its sensor (null: the axis "
                       "temperature never leaves the reference, nothing of it shows)",
            "effect": f"thermal_expansion[{a}]"} for a in AXES}


class EnvironmentalVariation(Source):
    """ISO/TR 230-9 environmental variation error E_VE (Eq. 14: u = E_VE / (2 sqrt 3)).

    Modelled as a drift of the measured points that grows linearly over the
    test and reaches a rectangularly distributed value in [-E_VE/2, E_VE/2]
    per axis at its end.
    """

    name = "environmental_variation"
    group = Group.MACHINE_TOOL
    distribution = "rectangular (Eq. 14)"
    targets = ("point_offset",)
    parameters = {"E_VE": Q_(2.0, "um")}
    plausible = {"E_VE": Q_(1000.0, "um")}  # ISO 230-3 EVE: 1-20 um; steel over 10 m at 2 K: 230 um
    nonnegative = ("E_VE",)

    def standard_uncertainty(self):
        return (self.parameters["E_VE"] / (2 * math.sqrt(3))).to("um")

    def _prepare(self, ctx):
        t = ctx.plan.time
        frac = t / t[-1] if t[-1] > 0 else np.zeros_like(t)
        return self.value("E_VE", "mm"), frac[None, :]

    def sample_internal(self, n, rng, ctx):
        e, frac = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        end = rng.uniform(-e / 2, e / 2, (n, 1, 3))
        out = np.empty((n, ctx.n_points, 3))  # end * frac, one coordinate at a time (rows of M, not a last axis of 3)
        for c in range(3):
            np.multiply(end[:, :, c], frac, out=out[:, :, c])
        return {"point_offset": out}

    def drawn(self, sample, ctx):
        t = ctx.plan.time
        v = [_at(sample["point_offset"][:, c], t) * 3600.0 * 1e3 for c in range(3)]
        return {"velocity": {"value": v, "unit": "um/h",
                             "meaning": "the measured points drift steadily in the machine frame (x, y, z) from the "
                                        "start of the test: E_VE's share of the environment",
                             "effect": "tracker_drift"}}


class TemperatureDrift(Source):
    """Temperature drift of each axis during the test, not followed by the compensation.

    A drift rate per axis, normal with standard deviation ``rate``, applied
    over the measurement times of Eq. 4: the axis scale changes by
    CTE * rate * t.
    """

    name = "temperature_drift"
    group = Group.MACHINE_TOOL
    distribution = "normal rate"
    targets = ("axis_scale.x", "axis_scale.y", "axis_scale.z")
    parameters = {"rate": Q_(0.2, "K/h"), "cte": Q_(11.5, "um/(m*K)")}
    plausible = {"rate": Q_(5.0, "K/h")}  # a workshop drifts by 0.1-1 K/h
    links = {"cte": "machine_tool.cte"}
    nonnegative = ("rate",)

    def standard_uncertainty(self):
        return self.parameters["rate"]

    def _prepare(self, ctx):
        cte = _axis_ctes(self, ctx)
        return (self.value("rate", "K/s"), np.array([cte[a] for a in AXES], float)[:, None, None],
                ctx.plan.time[None, None, :])

    def sample_internal(self, n, rng, ctx):
        # the true axis temperature drifts by rate t away from what the correction reads
        rate, cte, t = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        out = np.empty((3, n, ctx.n_points))
        np.multiply(cte * rng.normal(0.0, rate, (3, n, 1)), t, out=out)  # the numbers of three (n, 1) draws in turn
        return {"axis_scale.x": out[0], "axis_scale.y": out[1], "axis_scale.z": out[2]}

    def drawn(self, sample, ctx):
        cte = _axis_ctes(self, ctx)
        out = {}
        for a in AXES:
            scale = _at(sample[f"axis_scale.{a}"], ctx.plan.time)  # 1/s
            out[f"rate_{a}"] = {"value": scale / cte[a] * 3600.0 if cte[a] else math.nan, "unit": "K/h",
                                "meaning": f"the rate at which the true {a}-axis temperature drifts away from what "
                                           "its sensor reads (the sensor does not see it)"}
            out[f"scale_rate_{a}"] = {
                "value": scale * 3600.0 * 1e6, "unit": "um/(m*h)",
                "meaning": f"the {a} scale changing with time by CTE times that rate, about the axis zero: what "
                           f"thermal_expansion[{a}] declares as its alternative outside the library, the {a} scale "
                           "following time (p (t - t0) along the axis)",
                "effect": f"scale_following_time[{a}]"}
        return out


class Backlash(Source):
    """Reversal (backlash) of each axis, rectangular in [0, B_max] (Eq. 15-17): the axis stops B/2 short."""

    name = "backlash"
    group = Group.MACHINE_TOOL
    distribution = "rectangular [0, B_max]"
    targets = ("axis_offset.x", "axis_offset.y", "axis_offset.z")
    parameters = {"B_max": Q_(3.0, "um")}
    nonnegative = ("B_max",)
    plausible = {"B_max": Q_(500.0, "um")}  # a linear axis' backlash: 1-50 um, 250 um on a large gantry

    def standard_uncertainty(self):
        return (self.parameters["B_max"] / math.sqrt(12)).to("um")

    def _prepare(self, ctx):
        minus_direction = -np.ascontiguousarray(ctx.plan.direction.T)[:, None, :]
        # (-d * B) / 2 is (-d / 2) * B, bit for bit, when d is +-1 or +-0 (-d * B is exact, and / 2 and * 0.5 round
        # the same value): one pass fewer; any other direction keeps the division
        halved = bool(np.isin(np.abs(minus_direction), (0.0, 1.0)).all())
        return self.value("B_max", "mm"), (minus_direction / 2 if halved else minus_direction), halved

    def sample_internal(self, n, rng, ctx):
        bmax, minus_direction, halved = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        out = np.empty((3, n, ctx.n_points))
        np.multiply(minus_direction, rng.uniform(0, bmax, (3, n, 1)), out=out)  # three (n, 1) draws in turn
        if not halved:
            out /= 2
        return {"axis_offset.x": out[0], "axis_offset.y": out[1], "axis_offset.z": out[2]}

    def drawn(self, sample, ctx):
        return {f"B_{a}": {"value": _at(sample[f"axis_offset.{a}"], -ctx.plan.direction[:, i] / 2) * 1e3, "unit": "um",
                           "meaning": f"the lost motion of the {a} axis: approaching from either side it stops B/2 "
                                      "short of the target (null: the axis is never approached)",
                           "effect": f"reversal[{a}]"} for i, a in enumerate(AXES)}


class _PerPointNormal(Source):
    distribution = "normal"
    targets = ("axis_offset.x", "axis_offset.y", "axis_offset.z")
    key = "u"

    def standard_uncertainty(self):
        return self.parameters[self.key].to("um")

    def sample_internal(self, n, rng, ctx):
        out = normal0(rng, self.value(self.key, "mm"), (3, n, ctx.n_points))  # three (n, M) draws in turn
        return {"axis_offset.x": out[0], "axis_offset.y": out[1], "axis_offset.z": out[2]}


class Repeatability(_PerPointNormal):
    """Positioning repeatability R of each axis at every point (Eq. 15-17)."""

    name = "repeatability"
    group = Group.MACHINE_TOOL
    key = "R"
    parameters = {"R": Q_(1.5, "um")}
    links = {"R": "machine_tool.repeatability"}
    nonnegative = ("R",)


class ControlError(_PerPointNormal):
    """Control (servo, interpolation) error C of each axis at every point (Eq. 15-17)."""

    name = "control_error"
    group = Group.MACHINE_TOOL
    key = "C"
    parameters = {"C": Q_(0.5, "um")}
    plausible = {"C": Q_(100.0, "um")}  # a servo error of 0.1-10 um
    nonnegative = ("C",)


class GeometricErrorUncertainty(Source):
    """Each geometric error coefficient varies about its value (Eq. 18-20), normal or beta.

    The beta option is symmetric Beta(a, a) on +-sqrt(2a + 1) u, which has
    standard deviation u.
    """

    name = "geometric_error_uncertainty"
    group = Group.MACHINE_TOOL
    distribution = "normal or beta (Eq. 18-20)"
    targets = ("geometry.translational", "geometry.angular")
    parameters = {"translational": Q_(0.5, "um"), "angular": Q_(0.5, "urad"), "shape": "normal", "beta_a": Q_(2.0)}
    plausible = {"translational": Q_(100.0, "um"), "angular": Q_(200.0, "urad")}  # 0.1-20 um, 0.1-40 urad
    nonnegative = ("translational", "angular", "beta_a")

    def check(self):
        if self.parameters["shape"] not in ("normal", "beta"):
            return f"parameter 'shape' must be 'normal' or 'beta', got {self.parameters['shape']!r}"
        return super().check()

    def standard_uncertainty(self):
        return self.parameters["translational"].to("um")

    def _draw(self, rng, size):
        if self.parameters["shape"] == "beta":
            a = float(self.parameters["beta_a"].magnitude)
            half = math.sqrt(2 * a + 1)
            return (rng.beta(a, a, size) * 2 - 1) * half
        if self.parameters["shape"] != "normal":
            from mtbudget.errors import PluginError

            raise PluginError(f"shape must be 'normal' or 'beta', got {self.parameters['shape']!r}", self.plugin, self.name)
        return rng.standard_normal(size)

    def _prepare(self, ctx):
        # the machine's own parameters only, in their order: a richer truth (model_form's next-degree terms) draws
        # the same numbers for them, and its extra terms are model_form's to draw
        base = np.array([p.order <= ctx.config.max_degree for p in ctx.model.errors.params]) if ctx.config is not None \
            else np.ones(len(ctx.theta), bool)
        # z * mask * u as z * (mask * u): the same numbers (u where the mask is 1, a zero of the same sign where it
        # is 0: signs multiply associatively), one product fewer
        return (None if base.all() else np.flatnonzero(base), int(base.sum()), len(ctx.theta),
                ctx.parameter_mask("mm") * self.value("translational", "mm"),
                ctx.parameter_mask("rad") * self.value("angular", "rad"))

    def sample_internal(self, n, rng, ctx):
        key = (*self.parameters.values(), ctx, ctx.config, ctx.model, ctx.theta,
               None if ctx.config is None else ctx.config.max_degree)
        base, k, p, tr, ang = self.remembered(key, lambda: self._prepare(ctx))
        if base is None:  # every parameter is the machine's own
            z = self._draw(rng, (n, k))
        else:
            z = np.zeros((n, p))
            z[:, base] = self._draw(rng, (n, k))
        return {"geometry.translational": z * tr, "geometry.angular": z * ang}


# ----------------------------------------------------------------------------- simulated physics (opt-in)
# Effects a verification does not know about, for simulating recordings that show them (mtbudget simulate,
# the diagnosis calibration).  Each is fixed (the same in every trial), off unless the configuration enables
# it ([effects] or [sources] add), and written independently of the diagnosis candidates that look for it.


class ThermalExpansionEffect(Source):
    """Simulated thermal expansion: each axis scale moves to p (1 + CTE (T_axis - T_ref)) about the axis zero."""

    name = "thermal_expansion"
    group = Group.MACHINE_TOOL
    distribution = "fixed (simulated physics)"
    targets = ("axis_scale.x", "axis_scale.y", "axis_scale.z")
    parameters = {f"cte_{a}": Q_(0.0, "um/(m*K)") for a in AXES}
    plausible = {f"cte_{a}": Q_(100.0, "um/(m*K)") for a in AXES}  # steel 11.5, aluminium 23
    opt_in = True

    def _prepare(self, ctx):
        out = {}
        for a in AXES:
            cte = self.value(f"cte_{a}", "1/K")
            if cte:
                dT = ctx.plan.axis_temperature(a, ctx.reference_temperature) - ctx.reference_temperature
                out[f"axis_scale.{a}"] = cte * dT
        return out

    def sample_internal(self, n, rng, ctx):
        rows = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {k: np.tile(v, (n, 1)) for k, v in rows.items()}

    def drawn(self, sample, ctx):
        return {f"cte_{a}": {"value": self.value(f"cte_{a}", "1/K") * 1e6, "unit": "um/(m*K)",
                             "meaning": f"the {a} scale moves to p (1 + CTE (T_{a} - T_ref)) about the axis zero "
                                        "(fixed: simulated physics)", "effect": f"thermal_expansion[{a}]"}
                for a in AXES if self.value(f"cte_{a}", "1/K")}


class ReversalEffect(Source):
    """Simulated reversal (lost motion) B of each axis: approaching from either side it stops B/2 short."""

    name = "reversal"
    group = Group.MACHINE_TOOL
    distribution = "fixed (simulated physics)"
    targets = ("axis_offset.x", "axis_offset.y", "axis_offset.z")
    parameters = {f"B_{a}": Q_(0.0, "um") for a in AXES}
    plausible = {f"B_{a}": Q_(500.0, "um") for a in AXES}  # a reversal of 1-50 um, 250 um on a large gantry
    opt_in = True

    def _prepare(self, ctx):
        out = {}
        for i, a in enumerate(AXES):
            B = self.value(f"B_{a}", "mm")
            if B:
                out[f"axis_offset.{a}"] = -0.5 * B * ctx.plan.direction[:, i]
        return out

    def sample_internal(self, n, rng, ctx):
        rows = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {k: np.tile(v, (n, 1)) for k, v in rows.items()}

    def drawn(self, sample, ctx):
        return {f"B_{a}": {"value": self.value(f"B_{a}", "um"), "unit": "um",
                           "meaning": f"the lost motion of the {a} axis: from either side it stops B/2 short (fixed: "
                                      "simulated physics)", "effect": f"reversal[{a}]"}
                for a in AXES if self.value(f"B_{a}", "um")}


#: a pair of axes -> (index of each, index of the third axis, along which their coupling acts): ``xy`` is a z error
#: that depends on x and y together (axis_coupling here, model_form_coupling in plugins/optimisation_strategy.py)
COUPLING_PAIRS = {"xy": (0, 1, 2), "xz": (0, 2, 1), "yz": (1, 2, 0)}


def axis_unit_positions(nominal) -> np.ndarray:
    """(M, 3) each axis position of ``nominal`` (M, 3, mm) scaled to [-1, 1] over the plan's own range of that axis
    (0 for an axis that does not move): the variable of the coupling shapes of :data:`COUPLING_PAIRS`."""
    nominal = np.asarray(nominal, float)
    u = np.zeros(nominal.shape)
    for i in range(3):
        lo, hi = nominal[:, i].min(), nominal[:, i].max()
        if hi > lo:
            u[:, i] = (nominal[:, i] - 0.5 * (lo + hi)) / (0.5 * (hi - lo))
    return u


class AxisCouplingEffect(Source):
    """Simulated error along the third axis that grows with the product of two axis positions.

    ``xy`` is the amplitude (at the corners of the measured range) of a z
    error proportional to u_x u_y, with u the axis position normalised to
    [-1, 1] over the measured range; likewise ``xz`` (along y) and ``yz`` (along x).
    """

    name = "axis_coupling"
    group = Group.MACHINE_TOOL
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {"xy": Q_(0.0, "um"), "xz": Q_(0.0, "um"), "yz": Q_(0.0, "um")}
    plausible = {k: Q_(500.0, "um") for k in ("xy", "xz", "yz")}  # coupling errors of 1-100 um
    opt_in = True

    def _prepare(self, ctx):
        nominal = ctx.plan.nominal
        u = axis_unit_positions(nominal)
        disp = np.zeros((len(nominal), 3))
        for pair, (a, b, third) in COUPLING_PAIRS.items():
            amp = self.value(pair, "mm")
            if not amp:
                continue
            disp[:, third] += amp * u[:, a] * u[:, b]
        return disp

    def sample_internal(self, n, rng, ctx):
        disp = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {"point_offset": np.tile(disp, (n, 1, 1))}


EFFECTS = (ThermalExpansionEffect, ReversalEffect, AxisCouplingEffect)



class UnidentifiedAtTool(Source):
    """At a tool the verification did not use ([measurand] tool): the combinations of geometric errors it cannot
    identify that act there, drawn from the prior of the generation functions (their covariance on the null
    directions of the identification).  Switched on by [measurand] tool (docs/measurand.md, "At another tool");
    the truth's own part along those directions is taken out, so it is counted once."""

    name = "unidentified_at_tool"
    group = Group.MACHINE_TOOL
    distribution = "normal: the generation functions' prior on what the verification cannot identify"
    targets = ("measurand_offset",)
    parameters = {}
    opt_in = True

    def sample_internal(self, n, rng, ctx):
        field = (ctx.measurand or {}).get("unidentified_field")
        if field is None:  # at the verification's own tool nothing it cannot identify shows
            return {"measurand_offset": np.zeros((n, ctx.n_points, 3))}
        z = rng.standard_normal((n, field.shape[0]))
        return {"measurand_offset": np.tensordot(z, field, axes=1)}


class InUse(Source):
    """The compensated machine *in use*, not only as the verification saw it (issue 14): at every point, per axis,
    its repeatability, its reversal from an unknown approach direction, and the residual of its thermal
    compensation at a workshop temperature other than 20 degC.  Added to the measurand only (the verification's
    measurements do not see the machine's later use), so a tolerance on positioning in use compares like with like.

    repeatability: normal, standard deviation R (the machine's, [machine_tool] repeatability);
    reversal: +-B/2 with the direction of approach random per point and axis, B ~ rectangular [0, B_max] per trial
    and axis; thermal: (CTE - nominal) x (T_use - 20 degC) x position, the CTE error normal (u_cte), T_use - 20 degC
    rectangular within +-temperature_range, one per trial.
    """

    name = "in_use"
    group = Group.MACHINE_TOOL
    distribution = "normal + rectangular reversal + CTE error x rectangular temperature"
    targets = ("measurand_offset",)
    parameters = {"R": Q_(1.5, "um"), "B_max": Q_(3.0, "um"), "u_cte": Q_(0.577, "um/(m*K)"),
                  "temperature_range": Q_(2.0, "K")}
    plausible = {"B_max": Q_(200.0, "um"), "u_cte": Q_(50.0, "um/(m*K)"), "temperature_range": Q_(50.0, "K")}
    links = {"R": "machine_tool.repeatability"}
    nonnegative = ("R", "B_max", "u_cte", "temperature_range")
    #: it changes the measurand (the machine in use): off unless enabled (docs/measurand.md, "In use")
    opt_in = True

    def standard_uncertainty(self):
        return self.parameters["R"].to("um")

    def sample_internal(self, n, rng, ctx):
        M = ctx.n_points
        R = self.value("R", "mm")
        B = rng.uniform(0.0, self.value("B_max", "mm"), (n, 1, 3))
        side = rng.choice((-1.0, 1.0), (n, M, 3))
        dcte = rng.standard_normal((n, 1, 3)) * self.value("u_cte", "1/K")
        dT = rng.uniform(-1.0, 1.0, (n, 1, 1)) * self.value("temperature_range", "K")
        pos = np.asarray(ctx.plan.nominal, float)[None]  # (1, M, 3) mm, about the axis zero
        off = rng.standard_normal((n, M, 3)) * R - side * B / 2.0 + dcte * dT * pos
        return {"measurand_offset": off}


# ----------------------------------------------------------------------------- rotary axes (five-axis machines)
#: the model inputs of the rotary axes: added to each one's commanded angle (rad)
ROTARY_TARGETS = ("axis_offset.a", "axis_offset.b", "axis_offset.c")


def _rotary_letters(ctx) -> list:
    """The rotary axes of the context's plan (a, b, c that the machine has), in that order."""
    return sorted(getattr(ctx.plan, "angles", {}) or {})


class RotaryRepeatability(Source):
    """Angular positioning repeatability of each rotary axis at every point: normal, u = R (ISO 230-2 applied to a
    rotary axis, one standard deviation of repeated positioning).  Default 10 urad (about 2 arcsec), a
    direct-drive table of a 1 m-class machining centre."""

    name = "rotary_repeatability"
    group = Group.MACHINE_TOOL
    distribution = "normal"
    targets = ROTARY_TARGETS
    parameters = {"R": Q_(10.0, "urad")}
    plausible = {"R": Q_(500.0, "urad")}  # a rotary axis repeats within 1-50 urad ([[features]] the same)
    nonnegative = ("R",)

    def standard_uncertainty(self):
        return self.parameters["R"].to("urad")

    def sample_internal(self, n, rng, ctx):
        u = self.value("R", "rad")
        return {f"axis_offset.{r}": normal0(rng, u, (n, ctx.n_points)) for r in _rotary_letters(ctx)}


def _rotary_axes_on(src, ctx) -> list:
    """The rotary axes of the plan a rotary source acts on: its ``axes`` parameter ("all", or letters such as "c" or
    "a, c"); the others draw as usual (the same random numbers) and get nothing."""
    want = str(src.parameters.get("axes", "all")).strip().lower()
    letters = _rotary_letters(ctx)
    if want in ("", "all"):
        return letters
    missing = sorted(set(want) & set("abc") - set(letters))
    if missing:  # a letter the machine does not have: the source would act on nothing, said as a mistake
        from mtbudget.errors import ConfigError

        raise ConfigError(f"sources.{src.name}.axes: the machine has no rotary axis {', '.join(m.upper() for m in missing)} "
                          f"(its rotary axes: {', '.join(r.upper() for r in letters) or 'none'})")
    return [r for r in letters if r in want]


def _axes_problem(src) -> str | None:
    """None when the ``axes`` parameter is "all" or rotary letters (a, b, c, separated by commas or spaces)."""
    want = str(src.parameters.get("axes", "all")).strip().lower()
    if want in ("", "all") or (set(want) <= set("abc, ") and set(want) & set("abc")):
        return None
    return f"parameter 'axes' must be \"all\" or rotary axis letters such as \"c\" or \"a, c\", got {want!r}"


class RotaryReversal(Source):
    """Reversal (lost motion) of each rotary axis, rectangular in [0, B_max] per verification: approaching from
    either side the axis stops B/2 short of its commanded angle (the rotary counterpart of ``backlash``).  Default
    B_max 20 urad (about 4 arcsec).  ``axes``: the rotary axes it acts on ("all", or letters such as "c")."""

    name = "rotary_reversal"
    group = Group.MACHINE_TOOL
    distribution = "rectangular [0, B_max]"
    targets = ROTARY_TARGETS
    parameters = {"B_max": Q_(20.0, "urad"), "axes": "all"}
    plausible = {"B_max": Q_(1000.0, "urad")}  # a rotary axis' reversal: 2-200 urad
    nonnegative = ("B_max",)

    def check(self):
        return super().check() or _axes_problem(self)

    def standard_uncertainty(self):
        return (self.parameters["B_max"] / math.sqrt(12)).to("urad")

    def _prepare(self, ctx):
        on = _rotary_axes_on(self, ctx)
        return self.value("B_max", "rad"), {r: -ctx.plan.direction_of(r)[None, :] * (r in on)
                                            for r in _rotary_letters(ctx)}

    def sample_internal(self, n, rng, ctx):
        bmax, minus_direction = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {f"axis_offset.{r}": md * (rng.uniform(0, bmax, (n, 1)) / 2) for r, md in minus_direction.items()}

    def drawn(self, sample, ctx):
        return {f"B_{r}": {"value": _at(sample[f"axis_offset.{r}"], -ctx.plan.direction_of(r) / 2) * 1e6,
                           "unit": "urad",
                           "meaning": f"the lost motion of the rotary axis {r.upper()}: approaching from either side "
                                      "it stops B/2 short of its commanded angle (0: the source does not act on "
                                      "it, its `axes`; null: the axis is never approached)",
                           "effect": f"rotary_reversal[{r}]"} for r in _rotary_letters(ctx)}


#: the Fourier terms of a rotary axis' angular positioning error that ``rotary_encoder`` draws (once and twice per
#: revolution), in the order and by the names of the error model's ``[c1] [s1] [c2] [s2]`` terms
ENCODER_TERMS = (("c1", np.cos, 1), ("s1", np.sin, 1), ("c2", np.cos, 2), ("s2", np.sin, 2))


def encoder_coefficients(values, angles, sign: float = 1.0) -> list:
    """The coefficients [c1, s1, c2, s2] (the unit of ``values``) of ``values = sum c_n cos(n theta) + s_n sin(n
    theta)`` at the commanded ``angles`` (rad), as the angular positioning error about +X, +Y or +Z (ISO 230-1's EAA,
    EBB, ECC, times ``sign``, the sense of the axis' direction: a source's angle offset turns about the axis'
    direction): least squares over the points.  NaN for a term the angles do not see (zero at every one of them:
    sin 2 theta at 0, 90, 180, 270 deg) and for all of them when the angles cannot tell the terms apart (fewer
    distinct angles than terms)."""
    th = np.asarray(angles, float).ravel()
    v = np.asarray(values, float).ravel()
    X = np.stack([f(n * th) for _, f, n in ENCODER_TERMS], axis=1)
    X[np.abs(X) < 1e-12] = 0.0
    seen = np.abs(X).max(axis=0) > 0
    out = np.full(len(ENCODER_TERMS), math.nan)
    if not seen.any() or np.linalg.matrix_rank(X[:, seen]) < seen.sum():
        return out.tolist()
    beta, *_ = np.linalg.lstsq(X[:, seen], v, rcond=None)
    out[seen] = beta * sign
    return out.tolist()


class RotaryEncoder(Source):
    """Angular positioning error of each rotary axis left by its encoder and its mounting (eccentricity: once per
    revolution; ellipticity: twice): ``E1 sin(theta + phi1) + E2 sin(2 theta + phi2)``, each amplitude rectangular
    in [0, E_max] and each phase uniform, drawn per verification.  A constant part is the zero error the
    verification identifies; what varies with the angle is not (unless ``rotary_harmonics`` models it).  Default
    E_max 10 urad (about 2 arcsec).  ``axes``: the rotary axes it acts on ("all", or letters such as "c")."""

    name = "rotary_encoder"
    group = Group.MACHINE_TOOL
    distribution = "two harmonics, amplitudes rectangular [0, E_max], uniform phases"
    targets = ROTARY_TARGETS
    parameters = {"E_max": Q_(10.0, "urad"), "axes": "all"}
    plausible = {"E_max": Q_(1000.0, "urad")}  # an angle encoder's error: 1-200 urad
    nonnegative = ("E_max",)

    def check(self):
        return super().check() or _axes_problem(self)

    def standard_uncertainty(self):
        # the error at a random angle: each harmonic's amplitude E (rectangular [0, E_max], E[E^2] = E_max^2 / 3)
        # times a sine of uniform phase (mean square 1/2), two of them
        return (self.parameters["E_max"] * math.sqrt(2 / 6)).to("urad")

    def _prepare(self, ctx):
        on = _rotary_axes_on(self, ctx)
        return self.value("E_max", "rad"), {r: (ctx.plan.angles[r][None, :], float(r in on))
                                            for r in _rotary_letters(ctx)}

    def sample_internal(self, n, rng, ctx):
        emax, angles = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        out = {}
        for r, (th, on) in angles.items():
            amp = rng.uniform(0, emax, (2, n, 1))
            phase = rng.uniform(0, 2 * np.pi, (2, n, 1))
            out[f"axis_offset.{r}"] = (amp[0] * np.sin(th + phase[0]) + amp[1] * np.sin(2 * th + phase[1])) * on
        return out

    def drawn(self, sample, ctx):
        out = {}
        for r in _rotary_letters(ctx):
            sign = float(ctx.plan.rotary[r].sign) if r in (ctx.plan.rotary or {}) else 1.0
            iso = "E" + "ABC"["abc".index(r)] + r.upper()
            out[f"harmonics_{r}"] = {
                "value": [x * 1e6 for x in encoder_coefficients(sample[f"axis_offset.{r}"], ctx.plan.angles[r], sign)],
                "unit": "urad",
                "meaning": f"the angular positioning error of the rotary axis {r.upper()} that varies with its angle "
                           f"(encoder eccentricity and ellipticity) as the coefficients c1, s1, c2, s2 of cos and sin of "
                           f"once and twice its commanded angle, about +{'XYZ'['abc'.index(r)]} ({iso}[c1] ... as "
                           "`identify --rotary-harmonics 2` names them); null where the plan's angles do not see a "
                           "term (sin 2C at 0, 90, 180, 270 deg) or cannot tell the terms apart",
                "effect": f"rotary_periodic_error[{r}]"}
        return out

SOURCES = (TemperatureSensorCalibration, CTEUncertainty, EnvironmentalVariation, TemperatureDrift, Backlash,
           Repeatability, ControlError, GeometricErrorUncertainty) + EFFECTS


# ----------------------------------------------------------------------------- more simulated physics (opt-in)
# Written for the diagnosis calibration, independently of the candidates in plugins/physics.py: they read the
# sensor by its column name, use the raw tool vector, and normalise positions over the plan's own range.


def _sensor_change(ctx, column):
    """Change (K) of a temperature column since the first point; zeros when the plan has no such column."""
    T = ctx.plan.temperature.get(column)
    return np.zeros(ctx.n_points) if T is None else np.asarray(T, float) - float(T[0])


class SpindleGrowthEffect(Source):
    """Simulated spindle thermal growth (ISO 230-3): the tool tip moves along its tool vector by ``growth``
    per kelvin of the ``sensor`` column's change since the first point, plus ``rate`` per hour."""

    name = "spindle_thermal_growth"
    group = Group.MACHINE_TOOL
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {"growth": Q_(0.0, "um/K"), "rate": Q_(0.0, "um/h"), "sensor": "T_z"}
    plausible = {"growth": Q_(200.0, "um/K"), "rate": Q_(500.0, "um/h")}  # a spindle grows 1-50 um/K
    opt_in = True

    def _prepare(self, ctx):
        tool = np.asarray(ctx.plan.tool, float)
        length = np.linalg.norm(tool, axis=1)
        along = np.where(length[:, None] > 0, tool / np.maximum(length, 1e-12)[:, None], [0.0, 0.0, -1.0])
        amount = self.value("growth", "mm/K") * _sensor_change(ctx, self.parameters["sensor"])
        amount = amount + self.value("rate", "mm/s") * (ctx.plan.time - ctx.plan.time[0])
        return amount[:, None] * along

    def sample_internal(self, n, rng, ctx):
        disp = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {"point_offset": np.tile(disp, (n, 1, 1))}


class ColumnTiltEffect(Source):
    """Simulated column tilt: the structure leans by ``tilt_x`` (towards +x) and ``tilt_y`` (towards +y) per kelvin
    of the ``sensor`` column's change, so the tool tip moves sideways by the angle times its height (z + tool z)."""

    name = "column_tilt"
    group = Group.MACHINE_TOOL
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {"tilt_x": Q_(0.0, "urad/K"), "tilt_y": Q_(0.0, "urad/K"), "sensor": "T_z"}
    plausible = {"tilt_x": Q_(200.0, "urad/K"), "tilt_y": Q_(200.0, "urad/K")}  # a column tilts 1-50 urad/K
    opt_in = True

    def _prepare(self, ctx):
        dT = _sensor_change(ctx, self.parameters["sensor"])
        height = ctx.plan.nominal[:, 2] + ctx.plan.tool[:, 2]
        disp = np.zeros((ctx.n_points, 3))
        disp[:, 0] = self.value("tilt_x", "rad/K") * dT * height
        disp[:, 1] = self.value("tilt_y", "rad/K") * dT * height
        return disp

    def sample_internal(self, n, rng, ctx):
        disp = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {"point_offset": np.tile(disp, (n, 1, 1))}


class ToolLengthErrorEffect(Source):
    """Simulated reflector holder of the wrong length: the points measured with tool number ``tool`` (1-based, in the
    order the tools first appear) lie ``error`` further along that tool's vector than stated."""

    name = "tool_length_error"
    group = Group.MACHINE_TOOL
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {"error": Q_(0.0, "um"), "tool": Q_(2.0)}
    plausible = {"error": Q_(2000.0, "um")}  # a tool length error of 1-500 um
    opt_in = True

    def _prepare(self, ctx):
        tool = np.asarray(ctx.plan.tool, float)
        seen = []
        for row in tool:
            if not any(np.allclose(row, s) for s in seen):
                seen.append(row)
        k = int(round(float(self.parameters["tool"].magnitude))) - 1
        disp = np.zeros((ctx.n_points, 3))
        if 0 <= k < len(seen) and np.linalg.norm(seen[k]) > 0:
            mine = np.all(np.isclose(tool, seen[k]), axis=1)
            disp[mine] = self.value("error", "mm") * seen[k] / np.linalg.norm(seen[k])
        return disp

    def sample_internal(self, n, rng, ctx):
        disp = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {"point_offset": np.tile(disp, (n, 1, 1))}


class AxisPolynomialEffect(Source):
    """Simulated non-rigid error along ``direction``: ``amplitude`` times u_x^px u_y^py u_z^pz, each u the axis
    position scaled to [-1, 1] over the plan's range (x y^2 with px = 1, py = 2, pz = 0)."""

    name = "axis_polynomial"
    group = Group.MACHINE_TOOL
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {"amplitude": Q_(0.0, "um"), "direction": "z", "px": Q_(1.0), "py": Q_(2.0), "pz": Q_(0.0)}
    plausible = {"amplitude": Q_(500.0, "um")}  # errors of 1-100 um
    opt_in = True

    def _prepare(self, ctx):
        f = np.ones(ctx.n_points)
        for i, a in enumerate(AXES):
            power = int(round(float(self.parameters[f"p{a}"].magnitude)))
            p = ctx.plan.nominal[:, i]
            span = np.ptp(p)
            u = 2.0 * (p - p.min()) / span - 1.0 if span > 0 else np.zeros_like(p)
            f = f * u**power
        disp = np.zeros((ctx.n_points, 3))
        disp[:, AXES.index(self.parameters["direction"].strip().lower())] = self.value("amplitude", "mm") * f
        return disp

    def sample_internal(self, n, rng, ctx):
        disp = self.remembered(_key(self, ctx), lambda: self._prepare(ctx))
        return {"point_offset": np.tile(disp, (n, 1, 1))}


SOURCES = SOURCES + (SpindleGrowthEffect, ColumnTiltEffect, ToolLengthErrorEffect, AxisPolynomialEffect, InUse, UnidentifiedAtTool,
                     RotaryRepeatability, RotaryReversal, RotaryEncoder)


@hookimpl
def mtbudget_register_sources(register):
    for cls in SOURCES:
        register(cls())
