"""Built-in diagnosis candidates: physics a rigid-body verification model leaves out.

Each candidate is a :class:`mtbudget.contracts.Candidate` subclass: it gives
the displacement of every measured point per internal unit of its
parameters, in the machine or the tracker frame, and says which measurement
would tell it from the effects it is easily confused with.  The effect names
are fixed: thermal_expansion, reversal, tracker_drift, tracker_range_offset,
tracker_rotation_drift, tracker_range_scale, air_temperature_drift, approximation_degree,
axis_coupling, spindle_growth, column_tilt, tool_length, axis_coupling_quadratic,
station_range_offset, rotary_reversal, rotary_periodic_error (one per rotary axis of a five-axis recording).

On a recording of several stations (``ctx.stations``, ``ctx.row_station``:
:class:`mtbudget.diagnose.StationsDiagnosisContext`) a "tracker" frame
column acts in each row's own station frame (``ctx.P_LT`` holds each row's
point in it; a range station's "frame" has the machine's axes and sees a
displacement along its beam only).

Every candidate declares the physically plausible range of its parameters
(``plausible``, display units): an estimate outside it is reported as
implausible, never as a finding.  Each range is derived from the physics the
candidate stands for, with its source in the comment above it (and in the
table of plausible ranges in docs/diagnose.md): the refractive index of air
for the range scale, the materials' CTE for thermal expansion, a tripod's
differential expansion for a tracker drift...  They bound what a shop can
meet with a setup error included (a weather station's altitude not entered),
so they only reject physics that is not there.
"""

from __future__ import annotations

import copy

import numpy as np

from mtbudget.contracts import Candidate
from mtbudget.hookspecs import hookimpl
from mtbudget.machine import AXES, AXIS_INDEX, ROTARY_INDEX, ChainInputs, ErrorModel, chain
from mtbudget.model import between_runs_columns, drift_offset, reversal_offset, thermal_scale
from mtbudget.units import factor, internal_unit_of

MIN_TEMPERATURE_RANGE = 0.01  # K: below this a temperature carries no information


def _e(axis):
    v = np.zeros(3)
    v[AXIS_INDEX[axis]] = 1.0
    return v


def _sensor_columns(ctx, axis=None, air=False):
    """The temperature columns of the sensors on ``axis`` (or in the air): the names of those data-driven features."""
    out = []
    for s in getattr(ctx.plan, "sensors", []) or []:
        on = s.attached_to.strip().lower() == "air" if air else getattr(s, "axis", None) == axis
        if on and s.column in ctx.plan.temperature:
            out.append(s.column)
    return out


def _tool_features(ctx):
    """The data-driven features of the tools after the first ("tool2", ...)."""
    tools, _ = _tools(ctx)
    return [f"tool{k}" for k in range(2, len(tools) + 1)]


def _varies(T, what):
    """None when the temperature T varies enough to test with, else why not."""
    if np.ptp(T) < MIN_TEMPERATURE_RANGE:
        return f"{what} varies by only {np.ptp(T):.3f} K"
    return None


class ThermalExpansion(Candidate):
    effect = "thermal_expansion"
    parameters = {"cte": "um/(m*K)"}
    #: materials (e.g. Kaye & Laby, ISO 1:2016 annex): glass-ceramic scales ~0, Invar 1.2, granite 5-8, cast iron
    #: 9-11, steel 11-13, brass 19, aluminium 23 um/(m*K); an axis follows its scale or its structure, so 0 to 30
    plausible = {"cte": (0.0, 30.0)}
    quantity_names = {"cte": "a CTE"}
    hints = {
        "tracker_drift": "Measure while the temperature goes up and then down (not steadily one way).",
        "air_temperature_drift": "Add a sensor on the structure away from the air stream, or repeat at another temperature.",
        "spindle_growth": "Measure with two tool lengths at the same temperature, or put a sensor on the spindle housing.",
    }

    def __init__(self, axis):
        super().__init__(axis)
        self.description = (f"the {axis} axis scale follows its temperature: it moves to p (1 + CTE (T - T_ref)) "
                            "about the axis zero")

    def requires(self, ctx):
        T = ctx.axis_temperature_column(self.axis)
        if T is None:
            return f"no temperature sensor is attached to the {self.axis} axis"
        # where recording.toml states the scale's expansion, the baseline corrects it: what is left to find is
        # the deviation from the stated CTE, plausible as long as the total stays within the physical range
        sc = getattr(ctx.plan, "scales", {}).get(self.axis)
        stated = sc.cte * 1e6 if sc else 0.0
        self.fixed_point = sc.fixed_point if sc else 0.0  # mm: the deviation expands the scale about it too
        lo, hi = type(self).plausible["cte"]
        self.plausible = {"cte": (lo - stated, hi - stated)}
        self.quantity_names = {"cte": f"a deviation from the stated CTE ({stated:g} um/(m*K))" if sc else "a CTE"}
        return _varies(T, f"the {self.axis}-axis temperature")

    def columns(self, ctx):
        T = ctx.axis_temperature_column(self.axis) - ctx.recording.reference_temperature
        p = ctx.plan.nominal[:, AXIS_INDEX[self.axis]] - getattr(self, "fixed_point", 0.0)
        return (p * T)[:, None, None] * _e(self.axis)[None, :, None]

    def variables(self, ctx):
        """The cause: the axis' temperature (a term that involves it is this effect with another shape)."""
        return _sensor_columns(ctx, self.axis)

    def alternatives(self, ctx):
        """The axis scale following time rather than its sensor (anything that warms steadily)."""
        t = ctx.plan.time - ctx.plan.time.mean()
        p = ctx.plan.nominal[:, AXIS_INDEX[self.axis]] - getattr(self, "fixed_point", 0.0)
        return [{"name": f"the {self.axis} scale following time",
                 "description": f"the {self.axis} axis scale changing steadily with time, not with its own temperature "
                                "(another part of the machine, or the scale itself, warming steadily)",
                 "separate": "Measure while the temperature goes up and then down (not steadily one way).",
                 "columns": (p * t)[:, None, None] * _e(self.axis)[None, :, None]}]

    def perturbation(self, ctx, beta):
        return thermal_scale(ctx.plan, {self.axis: float(beta[0])}, ctx.recording.reference_temperature,
                             {self.axis: getattr(self, "fixed_point", 0.0)})  # about the scale's fixed point


class Reversal(Candidate):
    effect = "reversal"
    parameters = {"B": "um"}
    #: lost motion is positive (ISO 230-2 reversal values of a few um on a preloaded ball screw, tens of um on a
    #: worn one or a rack); a servo overshoot can make it slightly negative
    plausible = {"B": (-20.0, 100.0)}
    quantity_names = {"B": "a lost motion B"}

    def __init__(self, axis):
        super().__init__(axis)
        self.description = (f"lost motion of the {axis} axis: approaching from either side it stops B/2 short of the "
                            f"target (B > 0; the ISO 230-2 reversal value, mean up minus mean down, is -B)")

    def requires(self, ctx):
        d = ctx.plan.direction[:, AXIS_INDEX[self.axis]]
        return None if (d > 0).any() and (d < 0).any() else f"the {self.axis} axis is approached from one side only"

    def columns(self, ctx):
        return (-ctx.plan.direction[:, AXIS_INDEX[self.axis]] / 2.0)[:, None, None] * _e(self.axis)[None, :, None]

    def variables(self, ctx):
        return [f"dir_{self.axis}"]

    def alternatives(self, ctx):
        """Anything that changes between the plan's runs: the runs alternate the approach direction with time."""
        C = between_runs_columns(ctx.plan, self.axis)
        if C is None:
            return []
        return [{"name": "a change between runs",
                 "description": f"anything that changes along {self.axis} between the plan's runs (a thermal state, a "
                                "re-clamping), since the runs alternate the approach direction with time",
                 "separate": "Repeat a run in the same direction as the one before it (a reversal needs the direction "
                             "to change, a change between runs does not).",
                 "columns": C}]

    def perturbation(self, ctx, beta):
        return reversal_offset(ctx.plan, {self.axis: float(beta[0])})


class TrackerDrift(Candidate):
    effect = "tracker_drift"
    description = "the tracker creeps relative to the machine during the test (apparent velocity of the points)"
    parameters = {"velocity": "um/h"}  # a vector: one column per machine axis
    #: a 1.5 m steel tripod (11.5 um/(m*K)) whose temperature changes by 1 K/h grows 17 um/h; a stand on a floor
    #: that settles a few um/h: +-30 um/h per component is a stand moving, beyond it a stand not set up
    plausible = {"velocity": (-30.0, 30.0)}
    quantity_names = {"velocity": "a tracker drift"}
    hints = {"air_temperature_drift": "Repeat the test with the air temperature held, or measure a fixed reference "
                                      "point every few minutes.",
             "tracker_rotation_drift": "Measure two fixed reflectors on the table, one near the tracker and one far, "
                                       "at the start and at the end (a rotation moves the far one more; a "
                                       "translation moves both alike).",
             "spindle_growth": "Measure a fixed reference point on the table every few minutes (a drift moves it, a "
                               "spindle growth does not)."}

    def requires(self, ctx):
        return None if np.ptp(ctx.plan.time) > 0 else "all points have the same time"

    def columns(self, ctx):
        return ctx.plan.time[:, None, None] * np.eye(3)[None]

    def variables(self, ctx):
        return ["t"]

    def alternatives(self, ctx):
        """The machine drifting as a whole: the same displacement of every measured point."""
        return [{"name": "machine thermal drift",
                 "description": "the machine drifting as a whole during the test (ISO 230-3 thermal drift: spindle "
                                "growth, column growth): the tool point moves against the table as a creeping tracker "
                                "would make it appear to",
                 "separate": "Measure a fixed reflector on the table at the start and at the end of the test (a "
                             "tracker drift moves it, a machine drift does not).",
                 "columns": None}]

    def perturbation(self, ctx, beta):
        return drift_offset(ctx.plan, np.asarray(beta, float))


class TrackerRotationDrift(Candidate):
    """The tracker's azimuth and elevation zeros turning in time (the base twisting on its stand, the head's encoders
    drifting as it warms): a point at distance r moves by rate * t * r across the beam, in the azimuth or the
    elevation direction.  Beside :class:`TrackerDrift` (a translation): the two differ where the points span a
    range of azimuths and elevations (a rotation moves near points less than far ones, and in another direction on
    either side); when they do not, the diagnosis declares them confounded (BIC margin) and says what would separate
    them."""

    effect = "tracker_rotation_drift"
    description = ("the tracker's azimuth and elevation zeros turn in time (base twisting on its stand, encoders "
                   "warming): each point moves across the beam by rate x time x its distance")
    parameters = {"rate": "urad/h"}  # a vector: azimuth zero, elevation zero
    frame = "tracker"
    #: a tripod whose legs (1 m steel, 0.6 m apart) differ by 0.5 K/h tilts 10 urad/h; a tracker's stated angular
    #: stability is a few urad over hours: +-40 urad/h (80 um at 1 m over a 2 h test) is a stand not set up
    plausible = {"rate": (-40.0, 40.0)}
    quantity_names = {"rate": "a tracker rotation drift"}
    hints = {"tracker_drift": "Measure two fixed reflectors on the table, one near the tracker and one far, at the "
                              "start and at the end (a rotation moves the far one more; a translation moves both "
                              "alike), or place the tracker so the points span a wider angle."}

    def requires(self, ctx):
        return None if np.ptp(ctx.plan.time) > 0 else "all points have the same time"

    def columns(self, ctx):
        P = np.asarray(ctx.P_LT, float)
        t = (ctx.plan.time - ctx.plan.time[0])[:, None]
        r_xy = np.hypot(P[:, 0], P[:, 1])
        az = np.arctan2(P[:, 1], P[:, 0])
        el = np.arctan2(P[:, 2], r_xy)
        r = np.linalg.norm(P, axis=1)
        d_az = np.stack([-P[:, 1], P[:, 0], np.zeros(len(P))], axis=1)  # d P / d azimuth = e_z x P
        d_el = r[:, None] * np.stack([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)], axis=1)
        return np.stack([d_az * t, d_el * t], axis=2)

    def variables(self, ctx):
        return ["t"]

    def summary(self, beta, cov):
        """The azimuth and elevation rates, urad/h."""
        f = factor("1/s", "urad/h")
        return ([float(x) * f for x in beta], [float(np.sqrt(max(cov[k, k], 0.0))) * f for k in range(len(beta))],
                "urad/h")


def _xyz_rows(ctx):
    """(M,) True on the rows of laser-tracker (xyz) stations (every row of a one-station recording)."""
    stations = getattr(ctx, "stations", None)
    if not stations or getattr(ctx, "row_station", None) is None:
        return np.ones(len(ctx.plan), bool)
    return np.isin(ctx.row_station, [st.id for st in stations if st.kind == "xyz"])


class TrackerRangeOffset(Candidate):
    """A constant error of every tracker distance.  On several stations: the same offset on every laser-tracker
    (xyz) station, as when one tracker is moved from station to station; a range station's own offset is its dead
    path, an unknown of the baseline, so its rows carry nothing of it."""

    effect = "tracker_range_offset"
    description = "a constant error of every tracker distance (ADM zero, reflector of another type or size)"
    parameters = {"offset": "um"}
    frame = "tracker"
    #: an ADM zero error is a few um (bounded by the tracker's stated distance uncertainty, 4-10 um); a reflector of
    #: another size or type than the one compensated tens of um; beyond 50 um a gross setup error
    plausible = {"offset": (-50.0, 50.0)}
    quantity_names = {"offset": "a range offset"}
    hints = {"tracker_range_scale": "Measure a calibrated length, or the same points from a second tracker station.",
             "tool_length": "Measure the reflector holders on a tool presetter, or repeat with the tools swapped.",
             "station_range_offset": "Measure with each tracker's own reflector at a calibrated length, or repeat "
                                     "a station with the tracker of another."}

    def requires(self, ctx):
        return None if _xyz_rows(ctx).any() else "no laser-tracker (xyz) station: a range station's offset is its dead path"

    def columns(self, ctx):
        u = ctx.P_LT / np.linalg.norm(ctx.P_LT, axis=1, keepdims=True)
        return (u * _xyz_rows(ctx)[:, None])[:, :, None]


class StationRangeOffset(Candidate):
    """A constant error of the distances of one laser-tracker (xyz) station: its ADM zero error, or the offset of
    the reflector it measures (another type or size of SMR than its compensation assumes).

    Registered once; on a recording of several stations it stands for one candidate per station
    (:meth:`per_station`), named ``station_range_offset[<station id>]``.  The plausible range, |c| <= 50 um: an
    ADM zero error of a tracker in calibration is a few um (the tracker's own stated distance uncertainty,
    typically 4-10 um, bounds it); a reflector of another type or size than the one compensated (a 1.5 in SMR
    for a 0.5 in, a broken-corner for a hollow one) shifts every distance by ten to a few tens of um; beyond
    50 um it is a gross setup error (a wrong SMR offset, a reflector in a nest), not a range offset that a
    verification should absorb, and the same |c| <= 50 um as ``tracker_range_offset``.

    From one station the pose absorbs almost all of an offset (docs/diagnose.md: found in 3 % of single-station
    cases); from several, the other stations fix the points, and what the station's pose cannot absorb (the
    offset along each beam, varying in direction over the points) is seen.  On a one-station recording it is
    skipped (that offset is ``tracker_range_offset``); a range station's offset is its dead path, already an
    unknown of the baseline, so it is skipped there with that reason.
    """

    effect = "station_range_offset"
    description = ("a constant error of the distances of one laser-tracker station (its ADM zero error, or the "
                   "offset of the reflector it measures)")
    parameters = {"offset": "um"}
    frame = "tracker"  # each row's own station frame
    plausible = {"offset": (-50.0, 50.0)}
    quantity_names = {"offset": "a station range offset"}
    hints = {"tracker_range_offset": "Measure each tracker's reflector at a calibrated length (a common offset "
                                     "moves every station, a station's offset only its own).",
             "tracker_range_scale": "Measure a calibrated length from that station."}

    def per_station(self, ctx):
        """One candidate per station of the recording (``axis`` is the station id); the host's stamps are kept."""
        out = []
        for st in getattr(ctx, "stations", None) or []:
            c = copy.copy(self)
            c.axis = str(st.id)
            c.description = (f"a constant error of the distances of station {st.id} (its ADM zero error, or the "
                             "offset of the reflector it measures)")
            out.append(c)
        return out

    def _station(self, ctx):
        for st in getattr(ctx, "stations", None) or []:
            if str(st.id) == str(self.axis):
                return st
        return None

    def requires(self, ctx):
        stations = getattr(ctx, "stations", None) or []
        if len(stations) < 2:
            return ("one station: its range offset is tracker_range_offset (the pose absorbs most of it; a second "
                    "station or a calibrated length separates it)")
        st = self._station(ctx)
        if st is None:
            return f"no station {self.axis} in this recording"
        if st.kind != "xyz":
            return (f"station {st.id} is a range station (tracking interferometer): a constant offset of its "
                    "distances is its dead path, already an unknown of the baseline")
        return None

    def columns(self, ctx):
        u = ctx.P_LT / np.linalg.norm(ctx.P_LT, axis=1, keepdims=True)
        on = np.asarray(ctx.row_station) == self._station(ctx).id
        return (u * on[:, None])[:, :, None]


class TrackerRangeScale(Candidate):
    effect = "tracker_range_scale"
    description = "tracker distances scaled (wrong air refractive index or weather-station reading)"
    parameters = {"scale": "um/m"}
    frame = "tracker"
    #: the refractive index of air (Edlen 1966, Birch & Downs 1993/94, Ciddor 1996; sensitivities at 20 degC,
    #: 1013 hPa, 50 %RH): -0.93 um/m per K of air temperature, +0.27 um/m per hPa of pressure, -0.0085 um/m per %RH
    #: (0.9 um/m from dry to saturated air), +0.015 um/m per 100 ppm CO2; the pressure falls about 12 hPa per 100 m
    #: near sea level, so a weather station's altitude not entered (or a sea-level pressure read for the station's)
    #: gives about 3.2 um/m per 100 m.  Bound: an air temperature wrong by up to 10 K (9.3, a sensor in the sun or
    #: far from the beam), a pressure wrong by up to 100 hPa (27, about 850 m of altitude), humidity (0.9) and the
    #: ADM's own frequency (about 1): +-40 um/m.  Beyond: refraction compensation switched off (about 270 um/m).
    plausible = {"scale": (-40.0, 40.0)}
    quantity_names = {"scale": "a range scale error"}
    hints = {"tool_length": "Measure the reflector holders on a tool presetter, or repeat with the tools swapped.",
             "tracker_range_offset": "Measure a calibrated length, or check the weather station's temperature, "
                                     "pressure and altitude against a reference barometer and thermometer."}

    def columns(self, ctx):
        return ctx.P_LT[:, :, None]


class AirTemperatureDrift(Candidate):
    effect = "air_temperature_drift"
    description = "the points move with the air temperature (tracker stand, bed or beam path warming), not with time"
    parameters = {"sensitivity": "um/K"}  # a vector: one column per machine axis
    #: a 1.5 m steel tracker stand grows 17 um/K (11.5 um/(m*K)); the beam path's refraction adds about 1 um/K per m
    plausible = {"sensitivity": (-30.0, 30.0)}
    quantity_names = {"sensitivity": "an air-temperature sensitivity"}

    def requires(self, ctx):
        T = ctx.air_temperature()
        if T is None:
            return "no air temperature sensor"
        return _varies(T, "the air temperature")

    def columns(self, ctx):
        T = ctx.air_temperature()
        return (T - T[0])[:, None, None] * np.eye(3)[None]

    def variables(self, ctx):
        return _sensor_columns(ctx, air=True)


class ApproximationDegree(Candidate):
    """The next Legendre term of each of the six error functions of one axis."""

    effect = "approximation_degree"
    #: one column per error function of the axis: translational in um, angular in urad
    #: (on a 1 m lever an urad moves a point by 1 um, so the summary's RMS is in um either way)
    parameters = {"dx": "um", "dy": "um", "dz": "um", "ex": "urad", "ey": "urad", "ez": "urad"}
    plausible = {k: (-50.0, 50.0) for k in parameters}

    def __init__(self, axis):
        super().__init__(axis)
        self.description = f"the error functions of the {axis} axis need a higher degree than the model gives them"

    def variables(self, ctx):
        return [self.axis]

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
    plausible = {"amplitude": (-50.0, 50.0)}
    quantity_names = {"amplitude": "a coupling amplitude"}

    def __init__(self, pair):
        super().__init__(pair)
        a, b = pair
        self.description = (f"a non-rigid coupling: the error depends on the {a} and {b} positions together "
                            "(sag, twist of the structure)")

    def variables(self, ctx):
        return list(self.axis)

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


def _tool_direction(ctx):
    """(M, 3) unit vector of each point's tool offset (spindle -> reflector); -z where there is none."""
    t = np.asarray(ctx.plan.tool, float)
    n = np.linalg.norm(t, axis=1, keepdims=True)
    return np.where(n > 0, t / np.where(n > 0, n, 1.0), np.array([0.0, 0.0, -1.0]))


def _tool_axis_temperature(ctx):
    """(T, axis) of the sensor on the axis that carries the spindle (the last axis of the chain), or (None, axis)."""
    axis = getattr(ctx.model.config, "tool", "") or "z"
    axis = axis[-1] if axis[-1] in AXES else "z"
    return ctx.axis_temperature_column(axis), axis


class SpindleGrowth(Candidate):
    """ISO 230-3 spindle thermal growth: the tool point moves along the tool axis as the spindle head warms."""

    effect = "spindle_growth"
    description = ("the spindle and tool grow along the tool axis as the spindle head warms (ISO 230-3): the tool point "
                   "moves along its tool vector by G (T - T_start), T of the sensor on the spindle-carrying axis")
    parameters = {"growth": "um/K"}
    #: ISO 230-3 tests of spindles: a few to about 20 um/K of housing temperature (a 300 mm steel spindle head
    #: alone, 3.5 um/K); a negative growth is not physical
    plausible = {"growth": (-2.0, 50.0)}
    quantity_names = {"growth": "a spindle growth"}
    hints = {"tracker_drift": "Measure a fixed reference point on the table every few minutes (a drift moves it, a "
                              "spindle growth does not).",
             "thermal_expansion": "Measure with two tool lengths at the same temperature, or put a sensor on the "
                                  "spindle housing.",
             "column_tilt": "Measure at two heights of the tool at the same temperature."}

    def requires(self, ctx):
        T, axis = _tool_axis_temperature(ctx)
        if T is None:
            return (f"no temperature sensor on the {axis} axis (the spindle head); a growth that follows time alone "
                    "cannot be told from a tracker drift")
        return _varies(T, f"the {axis}-axis temperature")

    def columns(self, ctx):
        T, _ = _tool_axis_temperature(ctx)
        return ((T - T[0])[:, None] * _tool_direction(ctx))[:, :, None]

    def variables(self, ctx):
        _, axis = _tool_axis_temperature(ctx)
        return _sensor_columns(ctx, axis)


class ColumnTilt(Candidate):
    """A column (or ram) that tilts as it warms: the tool point moves sideways in proportion to its height."""

    effect = "column_tilt"
    parameters = {"tilt": "urad/K"}
    #: a column of depth d bends by alpha dT_front-back / d: 11.5 um/(m*K) over 0.5 m is 23 urad per K of gradient,
    #: and the gradient is a fraction of the sensor's change; beyond 50 urad/K is not a machine tool
    plausible = {"tilt": (-50.0, 50.0)}
    quantity_names = {"tilt": "a column tilt"}
    hints = {"thermal_expansion": "Measure at two tool lengths (a tilt grows with the lever, an expansion does not).",
             "tracker_drift": "Measure a fixed reference point every few minutes at two heights.",
             "spindle_growth": "Measure at two heights of the tool at the same temperature."}

    def __init__(self, direction):
        super().__init__(direction)
        self.description = (f"the column tilts towards {direction} as it warms: the tool point moves along {direction} by "
                            "tilt (T - T_start) times its height, T of the sensor on the spindle-carrying axis")

    def requires(self, ctx):
        T, axis = _tool_axis_temperature(ctx)
        if T is None:
            return f"no temperature sensor on the {axis} axis (the column or ram)"
        return _varies(T, f"the {axis}-axis temperature")

    def variables(self, ctx):
        _, axis = _tool_axis_temperature(ctx)
        return _sensor_columns(ctx, axis)

    def columns(self, ctx):
        T, _ = _tool_axis_temperature(ctx)
        height = ctx.plan.nominal[:, 2] + ctx.plan.tool[:, 2]  # mm: lever of the tilt (its constant part is a squareness)
        return ((T - T[0]) * height)[:, None, None] * _e(self.axis)[None, :, None]


def _tools(ctx):
    """The distinct tool offsets in the order they first appear, and each point's index into them."""
    t = np.round(np.asarray(ctx.plan.tool, float), 6)
    _, first, inv = np.unique(t, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return t[first[order]], rank[np.asarray(inv).reshape(-1)]


class ToolLength(Candidate):
    """The length of each reflector holder (tool offset) is not what the recording states."""

    effect = "tool_length"
    description = ("a tool offset (reflector holder) is longer or shorter than stated: each tool's points move along "
                   "its tool vector by its length error (relative to the first tool; a common error is a tracker offset)")
    parameters = {"length_error": "um"}  # a vector: one per tool after the first
    #: a holder measured on a presetter is known to a few um; a wrong holder is hundreds of um off
    plausible = {"length_error": (-500.0, 500.0)}
    quantity_names = {"length_error": "a tool length error"}
    hints = {"tracker_range_scale": "Measure the reflector holders on a tool presetter, or repeat with the tools swapped.",
             "tracker_range_offset": "Measure the reflector holders on a tool presetter, or repeat with the tools swapped.",
             "spindle_growth": "Measure the tools in the other order (a growth follows the temperature, a length error "
                               "the tool)."}

    def variables(self, ctx):
        return _tool_features(ctx)

    def requires(self, ctx):
        tools, _ = _tools(ctx)
        return None if len(tools) >= 2 else "one tool offset only: its length error is a translation the pose absorbs"

    def columns(self, ctx):
        tools, idx = _tools(ctx)
        u = _tool_direction(ctx)
        C = np.zeros((len(ctx.plan), 3, len(tools) - 1))
        for k in range(1, len(tools)):
            C[idx == k, :, k - 1] = u[idx == k]
        return C


def _beyond_rigid(ctx, C, min_left=0.05):
    """The columns of C (M, 3, k) that the rigid-body model (pose and geometric errors, unweighted) leaves more than
    ``min_left`` of: a term the geometric errors nearly absorb gets a huge, meaningless coefficient."""
    P, J = ctx.model.machine_points(ctx.theta[None], jacobian=True)
    P, J = P[0], J[0]
    M = len(P)
    rigid = np.zeros((M, 3, 6))
    rigid[:, :, :3] = np.eye(3)[None]
    c = P - P.mean(0)
    for i in range(3):  # small rotations about each axis: e_i x c
        rigid[:, :, 3 + i] = np.cross(np.eye(3)[i][None], c)
    A = np.concatenate([rigid, J], axis=2).reshape(3 * M, -1)
    A = A[:, np.linalg.norm(A, axis=0) > 0]
    U, sv, _ = np.linalg.svd(A / np.linalg.norm(A, axis=0), full_matrices=False)
    U = U[:, sv > 1e-8 * sv[0]]
    X = C.reshape(3 * M, -1)
    left = np.linalg.norm(X - U @ (U.T @ X), axis=0) / np.maximum(np.linalg.norm(X, axis=0), 1e-300)
    keep = left > min_left
    return C[:, :, keep] if keep.any() else C[:, :, :1]


class AxisCouplingQuadratic(Candidate):
    """Errors that depend on two axis positions beyond the bilinear term: u_a u_b^2 and u_a^2 u_b."""

    effect = "axis_coupling_quadratic"
    parameters = {"amplitude": "um"}  # a vector: (u_a u_b^2, u_a^2 u_b) along x, y, z: six columns
    plausible = {"amplitude": (-50.0, 50.0)}
    quantity_names = {"amplitude": "a coupling amplitude"}
    hints = {"axis_coupling": "Measure a finer mesh in the two axes (at least four positions each)."}

    def __init__(self, pair):
        super().__init__(pair)
        a, b = pair
        self.description = (f"a non-rigid coupling of third order: the error grows with {a} {b}^2 or {a}^2 {b} "
                            "(a sagging beam, a twisting table), amplitude at the corners of the measured range")

    def variables(self, ctx):
        return list(self.axis)

    def requires(self, ctx):
        for x in self.axis:
            if len(np.unique(np.round(ctx.plan.nominal[:, AXIS_INDEX[x]], 6))) < 3:
                return f"the {x} axis has fewer than three positions: a quadratic term cannot be seen"
        return None

    def columns(self, ctx):
        a, b = self.axis
        em = ctx.model.errors
        ua = em.normalised(a, ctx.plan.nominal[:, AXIS_INDEX[a]])
        ub = em.normalised(b, ctx.plan.nominal[:, AXIS_INDEX[b]])
        f = np.stack([ua * ub**2, ua**2 * ub], axis=1)  # (M, 2)
        C = np.concatenate([f[:, None, :] * np.eye(3)[None, :, i:i + 1] for i in range(3)], axis=2)
        return _beyond_rigid(ctx, C)

    def summary(self, beta, cov):
        """RMS of the six amplitudes (um) and of their standard uncertainties."""
        f = factor("mm", "um")
        b = np.asarray(beta) * f
        return [float(np.sqrt(np.mean(b**2)))], [float(np.sqrt(np.trace(np.asarray(cov)) / max(len(b), 1)) * f)], "um"


# ----------------------------------------------------------------------------- rotary axes (five-axis machines)
#: the Fourier terms of a rotary axis' angular positioning error the periodic-error candidate fits: once and twice per
#: revolution, by the error model's names (``ez(c)[c1]`` = ECC[c1] ..., what ``identify --rotary-harmonics 2`` fits)
ROTARY_TERMS = ("c1", "s1", "c2", "s2")


class _PerRotaryAxis(Candidate):
    """A candidate that stands for one candidate per rotary axis of the recording (:meth:`per_rotary_axis`; none on a
    three-axis machine)."""

    def per_rotary_axis(self, ctx):
        out = []
        for r in sorted(getattr(ctx.plan, "angles", {}) or {}):
            c = copy.copy(self)
            c.axis = r
            c.description = self.describe(r)
            out.append(c)
        return out

    def describe(self, r):
        return self.description

    def _missing(self, ctx):
        r = self.axis
        if not r or r not in (getattr(ctx.plan, "angles", {}) or {}):
            return f"the machine has no rotary axis {(r or '?').upper()}"
        return None


def _positioning_name(r: str) -> str:
    """The error model's name of a rotary axis' angular positioning error: ez(c), ex(a), ey(b)."""
    return f"e{AXES[ROTARY_INDEX[r]]}({r})"


def _rotary_jacobian(ctx, r: str, harmonics: int):
    """(error model, J (M, 3, p)): the baseline's error model with ``harmonics`` Fourier terms on the rotary axis
    ``r`` (the model ``identify --rotary-harmonics`` fits), and the chain's Jacobian of the tool points (workpiece
    frame, mm per mm or rad) at the baseline's solution."""
    base = ctx.model.errors
    em = ErrorModel(ranges=base.ranges, degrees=dict(base.degrees), squareness=base.squareness,
                    straightness_convention=base.straightness_convention, tool_axis=base.tool_axis,
                    rotary={**base.rotary, r: max(int(harmonics), int(base.rotary.get(r, 0)))})
    theta = np.zeros(len(em.params))
    at = {n: j for j, n in enumerate(em.names)}
    for j, n in enumerate(base.names):
        theta[at[n]] = ctx.theta[j]
    inputs = ctx.model.chain_inputs(ctx.recording.fixed_inputs())
    _, J = chain(ctx.model.config, em, theta[None], inputs, jacobian=True)
    return em, J[0]


def _turn(ctx, r: str) -> np.ndarray:
    """(M, 3) displacement of every tool point (workpiece frame, mm) per rad added to the commanded angle of the
    rotary axis ``r`` (a source's ``axis_offset.<r>``): the chain's column of its zero error times the sense of its
    direction (the zero error turns about +X, +Y or +Z; an angle offset about the axis' direction)."""
    em, J = _rotary_jacobian(ctx, r, 0)
    return J[:, :, em.index(f"{_positioning_name(r)}[O]")] * ctx.model.config.rotary_axis(r).sign


def _distinct_angles(ctx, r: str) -> np.ndarray:
    """The distinct commanded angles (rad, modulo a turn) of the rotary axis ``r``."""
    th = np.mod(np.asarray(ctx.plan.angles[r], float), 2 * np.pi)
    return np.unique(np.round(th, 9) % np.round(2 * np.pi, 9))


class RotaryReversal(_PerRotaryAxis):
    """Lost motion of a rotary axis: approaching a commanded angle from either side, the axis stops B/2 short of it
    (the rotary counterpart of :class:`Reversal`; the approach direction is the recording's ``dir_<axis>`` column)."""

    effect = "rotary_reversal"
    description = "lost motion of a rotary axis: approaching from either side it stops B/2 short of its commanded angle"
    parameters = {"B": "urad"}
    #: a rotary axis' reversal (ISO 230-2 applied to a rotary axis): a direct-drive table a few urad, a new worm-gear
    #: table 5-15 arcsec (25-75 urad), a worn one or a gear train up to about 100 arcsec (500 urad); a servo
    #: overshoot slightly negative
    plausible = {"B": (-20.0, 500.0)}
    quantity_names = {"B": "a rotary lost motion B"}
    hints = {"rotary_periodic_error": "Approach the same angles of the rotary axis from both sides (a reversal "
                                      "changes with the approach direction, an encoder error with the angle only)."}

    def describe(self, r):
        return (f"lost motion of the rotary axis {r.upper()}: approaching from either side it stops B/2 short of its "
                "commanded angle (B > 0)")

    def requires(self, ctx):
        missing = self._missing(ctx)
        if missing:
            return missing
        d = ctx.plan.direction_of(self.axis)
        if not ((d > 0).any() and (d < 0).any()):
            return f"the rotary axis {self.axis.upper()} is approached from one side only (dir_{self.axis})"
        return None

    def columns(self, ctx):
        return (_turn(ctx, self.axis) * (-ctx.plan.direction_of(self.axis) / 2.0)[:, None])[:, :, None]

    def variables(self, ctx):
        return [f"dir_{self.axis}"]

    def alternatives(self, ctx):
        """An angular positioning error that depends on the commanded angle alone, any shape (a table over the
        plan's distinct angles): where the plan approaches an angle from one side only, that is a reversal too."""
        th = np.round(np.mod(np.asarray(ctx.plan.angles[self.axis], float), 2 * np.pi), 9)
        uniq = np.unique(th)
        if len(uniq) < 2:
            return []
        turn = _turn(ctx, self.axis)
        C = np.stack([turn * (th == a)[:, None] for a in uniq[1:]], axis=2)
        A = self.axis.upper()
        return [{"name": f"an angular positioning error of {A} at each angle",
                 "description": f"the angular positioning error of {A} at each commanded angle (any shape: a "
                                "calibration table of the axis), which looks like a reversal where an angle is "
                                "approached from one side only",
                 "separate": f"Approach the same angles of {A} from both sides.",
                 "columns": C}]

    def perturbation(self, ctx, beta):
        return {f"axis_offset.{self.axis}": (-ctx.plan.direction_of(self.axis) * float(beta[0]) / 2.0)[None, :]}


class RotaryPeriodicError(_PerRotaryAxis):
    """The angular positioning error of a rotary axis that varies once and twice per revolution (its encoder's
    eccentricity and ellipticity, ISO 230-1's ECC of a C axis as a function of the angle): the Fourier terms
    ``[c1] [s1] [c2] [s2]`` of the error model's angular positioning error, exactly the terms ``identify
    --rotary-harmonics 2`` adds for it (the chain's own columns; the baseline keeps only the constant, the zero
    error).  Terms the plan's angles do not see (sin 2C at 0, 90, 180, 270 deg) or cannot tell from the lower ones
    are left out (their estimate stays 0)."""

    effect = "rotary_periodic_error"
    description = "the angular positioning error of a rotary axis varies once and twice per revolution (encoder)"
    parameters = {k: "urad" for k in ROTARY_TERMS}
    #: a rotary table's positioning accuracy (ISO 230-2 on a rotary axis) 2-20 arcsec (10-100 urad) on a machining
    #: centre, 50 arcsec on a plain indexer; an encoder ring mounted 10 um eccentric on a 50 mm radius gives 200 urad
    #: once per revolution: +-250 urad per term
    plausible = {k: (-250.0, 250.0) for k in ROTARY_TERMS}
    quantity_names = {k: f"a {k} term of the angular positioning error" for k in ROTARY_TERMS}
    hints = {"rotary_reversal": "Approach the same angles of the rotary axis from both sides (a reversal changes "
                                "with the approach direction, an encoder error with the angle only)."}

    def describe(self, r):
        A, about = r.upper(), "XYZ"[ROTARY_INDEX[r]]
        return (f"the angular positioning error of the rotary axis {A} (about +{about}, E{'ABC'[ROTARY_INDEX[r]]}{A}) "
                "varies once and twice per revolution: c1 cos + s1 sin of its angle, c2 cos + s2 sin of twice it "
                "(encoder eccentricity and ellipticity)")

    def _terms(self, ctx):
        """(M, 4) the basis of the four terms at the commanded angles, the terms the plan's distinct angles tell
        apart from the constant and from each other kept, the others zero."""
        th = np.asarray(ctx.plan.angles[self.axis], float)
        X = np.stack([np.cos(th), np.sin(th), np.cos(2 * th), np.sin(2 * th)], axis=1)
        X[np.abs(X) < 1e-12] = 0.0
        kept = [np.ones(len(th))]
        for j in range(4):
            trial = np.stack(kept + [X[:, j]], axis=1)
            if np.abs(X[:, j]).max() > 0 and np.linalg.matrix_rank(trial, tol=1e-9 * np.sqrt(len(th))) == len(kept) + 1:
                kept.append(X[:, j])
            else:
                X[:, j] = 0.0
        return X

    def requires(self, ctx):
        missing = self._missing(ctx)
        if missing:
            return missing
        n = len(_distinct_angles(ctx, self.axis))
        if n < 3:
            return (f"the rotary axis {self.axis.upper()} is commanded to {n} distinct angle{'s' if n != 1 else ''}: "
                    "an error that varies once and twice per revolution needs at least 3")
        seen = np.abs(self._terms(ctx)).max(axis=0) > 0
        #: the terms this plan's angles tell apart (the summary gives those only)
        self.kept = [t for t, k in zip(ROTARY_TERMS, seen) if k]
        left = [t for t, k in zip(ROTARY_TERMS, seen) if not k]
        if left:
            self.description = (self.describe(self.axis) + f"; fitted: {', '.join(self.kept)} ({', '.join(left)} "
                                f"cannot be told from the others at the plan's {n} angles of {self.axis.upper()})")
        return None

    def summary(self, beta, cov):
        """The terms the plan's angles tell apart (c1, s1, c2, s2 or fewer), urad."""
        f = factor("rad", "urad")
        kept = getattr(self, "kept", list(ROTARY_TERMS))
        j = [ROTARY_TERMS.index(t) for t in kept]
        u = np.sqrt(np.maximum(np.diag(np.atleast_2d(cov)), 0.0))
        return [float(beta[k]) * f for k in j], [float(u[k]) * f for k in j], "urad"

    def columns(self, ctx):
        em, J = _rotary_jacobian(ctx, self.axis, 2)
        name = _positioning_name(self.axis)
        C = np.stack([J[:, :, em.index(f"{name}[{t}]")] for t in ROTARY_TERMS], axis=2)
        return C * (np.abs(self._terms(ctx)) > 0)[:, None, :]

    def variables(self, ctx):
        return []

    def alternatives(self, ctx):
        """The axis' other error motions once and twice per revolution (radial, axial and tilt motions, ISO 230-1's
        EXC, EYC, EZC, EAC, EBC of a C axis): terms of the same error model that the library has no candidate for."""
        em, J = _rotary_jacobian(ctx, self.axis, 2)
        name = _positioning_name(self.axis)
        cols = [j for j, p in enumerate(em.params)
                if p.error.endswith(f"({self.axis})") and p.order > 0 and p.error != name]
        if not cols:
            return []
        A = self.axis.upper()
        return [{"name": f"error motions of {A} with the angle",
                 "description": f"the radial, axial or tilt motions of {A} varying once and twice per revolution "
                                "(bearing run-out, a wobbling table), which can move the points as an angular "
                                "positioning error does",
                 "separate": f"Measure points at several radii and heights on the {A} table (an angular positioning "
                             "error moves them in proportion to their radius, a radial motion alike, a tilt with "
                             "their height), or calibrate the axis' angle with an autocollimator and polygon.",
                 "columns": J[:, :, cols]}]

    def perturbation(self, ctx, beta):
        sign = ctx.model.config.rotary_axis(self.axis).sign
        return {f"axis_offset.{self.axis}": (self._terms(ctx) @ np.asarray(beta, float) * sign)[None, :]}


def all_candidates():
    out = [ThermalExpansion(a) for a in AXES] + [Reversal(a) for a in AXES]
    out += [TrackerDrift(), TrackerRotationDrift(), TrackerRangeOffset(), TrackerRangeScale(), AirTemperatureDrift()]
    out += [ApproximationDegree(a) for a in AXES] + [AxisCoupling(p) for p in ("xy", "xz", "yz")]
    out += [SpindleGrowth(), ColumnTilt("x"), ColumnTilt("y"), ToolLength()]
    out += [AxisCouplingQuadratic(p) for p in ("xy", "xz", "yz")]
    out += [StationRangeOffset()]
    out += [RotaryReversal(), RotaryPeriodicError()]
    return out


@hookimpl
def mtbudget_register_candidates(register):
    for c in all_candidates():
        register(c)
