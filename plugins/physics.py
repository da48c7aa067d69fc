"""Built-in diagnosis candidates: physics a rigid-body verification model leaves out.

Each candidate is a :class:`mtbudget.contracts.Candidate` subclass: it gives
the displacement of every measured point per internal unit of its
parameters, in the machine or the tracker frame, and says which measurement
would tell it from the effects it is easily confused with.  The effect names
are fixed: thermal_expansion, reversal, tracker_drift, tracker_range_offset,
tracker_range_scale, air_temperature_drift, approximation_degree,
axis_coupling.
"""

from __future__ import annotations

import numpy as np

from mtbudget.contracts import Candidate
from mtbudget.hookspecs import hookimpl
from mtbudget.machine import AXES, AXIS_INDEX, ChainInputs, ErrorModel, chain
from mtbudget.model import drift_offset, reversal_offset, thermal_scale
from mtbudget.units import factor, internal_unit_of

MIN_TEMPERATURE_RANGE = 0.01  # K: below this a temperature carries no information


def _e(axis):
    v = np.zeros(3)
    v[AXIS_INDEX[axis]] = 1.0
    return v


def _varies(T, what):
    """None when the temperature T varies enough to test with, else why not."""
    if np.ptp(T) < MIN_TEMPERATURE_RANGE:
        return f"{what} varies by only {np.ptp(T):.3f} K"
    return None


class ThermalExpansion(Candidate):
    effect = "thermal_expansion"
    parameters = {"cte": "um/(m*K)"}
    hints = {
        "tracker_drift": "Measure while the temperature goes up and then down (not steadily one way).",
        "air_temperature_drift": "Add a sensor on the structure away from the air stream, or repeat at another temperature.",
    }

    def __init__(self, axis):
        super().__init__(axis)
        self.description = (f"the {axis} axis scale follows its temperature: it moves to p (1 + CTE (T - T_ref)) "
                            "about the axis zero")

    def requires(self, ctx):
        T = ctx.axis_temperature_column(self.axis)
        if T is None:
            return f"no temperature sensor is attached to the {self.axis} axis"
        return _varies(T, f"the {self.axis}-axis temperature")

    def columns(self, ctx):
        T = ctx.axis_temperature_column(self.axis) - ctx.recording.reference_temperature
        p = ctx.plan.nominal[:, AXIS_INDEX[self.axis]]
        return (p * T)[:, None, None] * _e(self.axis)[None, :, None]

    def perturbation(self, ctx, beta):
        return thermal_scale(ctx.plan, {self.axis: float(beta[0])}, ctx.recording.reference_temperature)


class Reversal(Candidate):
    effect = "reversal"
    parameters = {"B": "um"}

    def __init__(self, axis):
        super().__init__(axis)
        self.description = f"lost motion of the {axis} axis: approaching from either side it stops B/2 short of the target"

    def requires(self, ctx):
        d = ctx.plan.direction[:, AXIS_INDEX[self.axis]]
        return None if (d > 0).any() and (d < 0).any() else f"the {self.axis} axis is approached from one side only"

    def columns(self, ctx):
        return (-ctx.plan.direction[:, AXIS_INDEX[self.axis]] / 2.0)[:, None, None] * _e(self.axis)[None, :, None]

    def perturbation(self, ctx, beta):
        return reversal_offset(ctx.plan, {self.axis: float(beta[0])})


class TrackerDrift(Candidate):
    effect = "tracker_drift"
    description = "the tracker creeps relative to the machine during the test (apparent velocity of the points)"
    parameters = {"velocity": "um/h"}  # a vector: one column per machine axis
    hints = {"air_temperature_drift": "Repeat the test with the air temperature held, or measure a fixed reference "
                                      "point every few minutes."}

    def requires(self, ctx):
        return None if np.ptp(ctx.plan.time) > 0 else "all points have the same time"

    def columns(self, ctx):
        return ctx.plan.time[:, None, None] * np.eye(3)[None]

    def perturbation(self, ctx, beta):
        return drift_offset(ctx.plan, np.asarray(beta, float))


class TrackerRangeOffset(Candidate):
    effect = "tracker_range_offset"
    description = "a constant error of every tracker distance (ADM zero, reflector of another type or size)"
    parameters = {"offset": "um"}
    frame = "tracker"
    hints = {"tracker_range_scale": "Measure a calibrated length, or the same points from a second tracker station."}

    def columns(self, ctx):
        u = ctx.P_LT / np.linalg.norm(ctx.P_LT, axis=1, keepdims=True)
        return u[:, :, None]


class TrackerRangeScale(Candidate):
    effect = "tracker_range_scale"
    description = "tracker distances scaled (wrong air refractive index or weather-station reading)"
    parameters = {"scale": "um/m"}
    frame = "tracker"

    def columns(self, ctx):
        return ctx.P_LT[:, :, None]


class AirTemperatureDrift(Candidate):
    effect = "air_temperature_drift"
    description = "the points move with the air temperature (tracker stand, bed or beam path warming), not with time"
    parameters = {"sensitivity": "um/K"}  # a vector: one column per machine axis

    def requires(self, ctx):
        T = ctx.air_temperature()
        if T is None:
            return "no air temperature sensor"
        return _varies(T, "the air temperature")

    def columns(self, ctx):
        T = ctx.air_temperature()
        return (T - T[0])[:, None, None] * np.eye(3)[None]


class ApproximationDegree(Candidate):
    """The next Legendre term of each of the six error functions of one axis."""

    effect = "approximation_degree"
    #: one column per error function of the axis: translational in um, angular in urad
    #: (on a 1 m lever an urad moves a point by 1 um, so the summary's RMS is in um either way)
    parameters = {"dx": "um", "dy": "um", "dz": "um", "ex": "urad", "ey": "urad", "ez": "urad"}

    def __init__(self, axis):
        super().__init__(axis)
        self.description = f"the error functions of the {axis} axis need a higher degree than the model gives them"

    def _next_degree(self, ctx):
        """One more than the highest degree the baseline gives this axis' errors."""
        return max(int(v) for k, v in ctx.model.errors.degrees.items() if k[3] == self.axis) + 1

    def requires(self, ctx):
        npos = len(np.unique(np.round(ctx.plan.nominal[:, AXIS_INDEX[self.axis]], 6)))
        top = self._next_degree(ctx)
        return None if npos > top else f"the {self.axis} axis has {npos} positions: degree {top} cannot be told from the lower ones"

    def columns(self, ctx):
        top = self._next_degree(ctx)
        errors = [f"{e}({self.axis})" for e in self.parameters]
        em = ErrorModel(ranges=ctx.model.errors.ranges, degrees={e: top for e in errors},
                        squareness=False, straightness_convention="free")
        column = {p.error: j for j, p in enumerate(em.params) if p.order == top}
        _, J = chain(ctx.model.config, em, np.zeros(len(em.params)), ChainInputs(ctx.plan.nominal, ctx.plan.tool), jacobian=True)
        return J[0][:, :, [column[e] for e in errors]]

    def summary(self, beta, cov):
        """RMS of the six coefficients (um and urad) and the RMS of their standard uncertainties."""
        f = np.array([factor(internal_unit_of(u), u) for u in self.parameters.values()])
        b, c = np.asarray(beta) * f, np.asarray(cov) * np.outer(f, f)
        return [float(np.sqrt(np.mean(b**2)))], [float(np.sqrt(np.trace(c) / max(len(b), 1)))], "um"


class AxisCoupling(Candidate):
    effect = "axis_coupling"
    parameters = {"amplitude": "um"}  # a vector: one column per machine axis

    def __init__(self, pair):
        super().__init__(pair)
        a, b = pair
        self.description = (f"a non-rigid coupling: the error depends on the {a} and {b} positions together "
                            "(sag, twist of the structure)")

    def requires(self, ctx):
        if all(np.ptp(ctx.plan.nominal[:, AXIS_INDEX[x]]) > 0 for x in self.axis):
            return None
        return f"the {self.axis} positions do not vary"

    def columns(self, ctx):
        a, b = self.axis
        em = ctx.model.errors
        ua = em.normalised(a, ctx.plan.nominal[:, AXIS_INDEX[a]])
        ub = em.normalised(b, ctx.plan.nominal[:, AXIS_INDEX[b]])
        return (ua * ub)[:, None, None] * np.eye(3)[None]


def all_candidates():
    out = [ThermalExpansion(a) for a in AXES] + [Reversal(a) for a in AXES]
    out += [TrackerDrift(), TrackerRangeOffset(), TrackerRangeScale(), AirTemperatureDrift()]
    out += [ApproximationDegree(a) for a in AXES] + [AxisCoupling(p) for p in ("xy", "xz", "yz")]
    return out


@hookimpl
def mtbudget_register_candidates(register):
    for c in all_candidates():
        register(c)
