"""Built-in diagnosis candidates: physics a rigid-body verification model leaves out.

Each candidate gives the displacement of every measured point per unit of
its parameters (internal units), in the machine or the tracker frame.  The
effect names are fixed: thermal_expansion, reversal, tracker_drift,
tracker_range_offset, tracker_range_scale, air_temperature_drift,
approximation_degree, axis_coupling.
"""

from __future__ import annotations

import numpy as np

from mtbudget.contracts import Candidate
from mtbudget.hookspecs import hookimpl
from mtbudget.machine import AXES, AXIS_INDEX, ChainInputs, ErrorModel, chain
from mtbudget.model import drift_offset, reversal_offset, thermal_scale
from mtbudget.units import Q_

MIN_TEMPERATURE_RANGE = 0.01  # K: below this an axis temperature carries no information


def _e(axis):
    v = np.zeros(3)
    v[AXIS_INDEX[axis]] = 1.0
    return v


def thermal(axis):
    def requires(ctx):
        T = ctx.axis_temperature_column(axis)
        if T is None:
            return f"no temperature sensor is attached to the {axis} axis"
        if np.ptp(T) < MIN_TEMPERATURE_RANGE:
            return f"the {axis}-axis temperature varies by only {np.ptp(T):.3f} K"
        return None

    def columns(ctx):
        T = ctx.axis_temperature_column(axis) - ctx.recording.reference_temperature
        p = ctx.plan.nominal[:, AXIS_INDEX[axis]]
        return (p * T)[:, None, None] * _e(axis)[None, :, None]

    return Candidate(
        "thermal_expansion", axis,
        f"the {axis} axis scale follows its temperature: it moves to p (1 + CTE (T - T_ref)) about the axis zero",
        [("cte", "um/(m*K)", "1/K")], columns, "machine",
        perturbation=lambda ctx, b: thermal_scale(ctx.plan, {axis: float(b[0])}, ctx.recording.reference_temperature),
        requires=requires)


def reversal(axis):
    i = AXIS_INDEX[axis]

    def requires(ctx):
        d = ctx.plan.direction[:, i]
        return None if (d > 0).any() and (d < 0).any() else f"the {axis} axis is approached from one side only"

    def columns(ctx):
        return (-ctx.plan.direction[:, i] / 2.0)[:, None, None] * _e(axis)[None, :, None]

    return Candidate(
        "reversal", axis, f"lost motion of the {axis} axis: approaching from either side it stops B/2 short of the target",
        [("B", "um", "mm")], columns, "machine",
        perturbation=lambda ctx, b: reversal_offset(ctx.plan, {axis: float(b[0])}), requires=requires)


def _vector_summary(display, internal):
    def summary(beta, cov):
        f = Q_(1.0, internal).to(display).magnitude
        return [float(x * f) for x in beta], [float(s * f) for s in np.sqrt(np.maximum(np.diag(cov), 0))], display

    return summary


def tracker_drift():
    def columns(ctx):
        t = ctx.plan.time
        return t[:, None, None] * np.eye(3)[None]

    return Candidate(
        "tracker_drift", None, "the tracker creeps relative to the machine during the test (apparent velocity of the points)",
        [("velocity", "um/h", "mm/s")], columns, "machine",
        perturbation=lambda ctx, b: drift_offset(ctx.plan, np.asarray(b, float)),
        requires=lambda ctx: None if np.ptp(ctx.plan.time) > 0 else "all points have the same time",
        summary=_vector_summary("um/h", "mm/s"))


def range_offset():
    def columns(ctx):
        u = ctx.P_LT / np.linalg.norm(ctx.P_LT, axis=1, keepdims=True)
        return u[:, :, None]

    return Candidate("tracker_range_offset", None,
                     "a constant error of every tracker distance (ADM zero, reflector of another type or size)",
                     [("offset", "um", "mm")], columns, "tracker")


def range_scale():
    return Candidate("tracker_range_scale", None,
                     "tracker distances scaled (wrong air refractive index or weather-station reading)",
                     [("scale", "um/m", "")], lambda ctx: ctx.P_LT[:, :, None], "tracker")


def air_drift():
    def requires(ctx):
        T = ctx.air_temperature()
        if T is None:
            return "no air temperature sensor"
        if np.ptp(T) < MIN_TEMPERATURE_RANGE:
            return f"the air temperature varies by only {np.ptp(T):.3f} K"
        return None

    def columns(ctx):
        T = ctx.air_temperature()
        return (T - T[0])[:, None, None] * np.eye(3)[None]

    return Candidate("air_temperature_drift", None,
                     "the points move with the air temperature (tracker stand, bed or beam path warming), not with time",
                     [("sensitivity", "um/K", "mm/K")], columns, "machine", requires=requires,
                     summary=_vector_summary("um/K", "mm/K"))


def degree(axis):
    def next_degree(ctx):
        """One more than the highest degree the baseline gives this axis' errors."""
        return max(int(v) for k, v in ctx.model.errors.degrees.items() if k[3] == axis) + 1

    def extra_model(ctx):
        top = next_degree(ctx)
        return ErrorModel(ranges=ctx.model.errors.ranges, degrees={f"{k}{c}({axis})": top for k in "de" for c in AXES},
                          squareness=False, straightness_convention="free"), top

    def requires(ctx):
        npos = len(np.unique(np.round(ctx.plan.nominal[:, AXIS_INDEX[axis]], 6)))
        top = next_degree(ctx)
        return None if npos > top else f"the {axis} axis has {npos} positions: degree {top} cannot be told from the lower ones"

    def columns(ctx):
        em, top = extra_model(ctx)
        keep = [j for j, p in enumerate(em.params) if p.order == top]
        _, J = chain(ctx.model.config, em, np.zeros(len(em.params)), ChainInputs(ctx.plan.nominal, ctx.plan.tool), jacobian=True)
        Jk = J[0][:, :, keep]
        # scale: translational per um, angular per urad on 1 m, so the RMS summary is in um either way
        return Jk

    def summary(beta, cov):
        return [float(np.sqrt(np.mean(beta**2)) * 1e3)], [float(np.sqrt(np.trace(cov) / max(len(beta), 1)) * 1e3)], "um"

    return Candidate("approximation_degree", axis,
                     f"the error functions of the {axis} axis need a higher degree than the model gives them",
                     [("coefficients", "um", "mm")], columns, "machine", requires=requires, summary=summary)


def coupling(pair):
    a, b = pair

    def columns(ctx):
        em = ctx.model.errors
        ua = em.normalised(a, ctx.plan.nominal[:, AXIS_INDEX[a]])
        ub = em.normalised(b, ctx.plan.nominal[:, AXIS_INDEX[b]])
        return (ua * ub)[:, None, None] * np.eye(3)[None]

    return Candidate("axis_coupling", pair,
                     f"a non-rigid coupling: the error depends on the {a} and {b} positions together (sag, twist of the structure)",
                     [("amplitude", "um", "mm")], columns, "machine",
                     requires=lambda ctx: None if all(np.ptp(ctx.plan.nominal[:, AXIS_INDEX[x]]) > 0 for x in pair)
                     else f"the {pair} positions do not vary", summary=_vector_summary("um", "mm"))


def all_candidates():
    out = [thermal(a) for a in AXES] + [reversal(a) for a in AXES]
    out += [tracker_drift(), range_offset(), range_scale(), air_drift()]
    out += [degree(a) for a in AXES] + [coupling(p) for p in ("xy", "xz", "yz")]
    return out


@hookimpl
def mtbudget_register_candidates(register):
    for c in all_candidates():
        register(c)
