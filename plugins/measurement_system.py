"""Built-in sources of the measurement-system group (paper Section 2.2.2, Eq. 21-24)."""

from __future__ import annotations

import numpy as np

from mtbudget import tracker as lt
from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_, ureg

_MM, _RAD, _ONE = ureg.Unit("mm"), ureg.Unit("rad"), ureg.Unit("")  # built once: Q_(x, "mm") parses the unit on every call



class TrackerNoise(Source):
    """Range and angle noise of the tracker (Eq. 23-24).

    As in the paper's Section 3, the angular standard uncertainty of each
    verification is itself drawn from N(angular_mean, angular_sd) (one value
    per angle and trial, kept positive); the range has u_d = distance +
    distance_per_length * r.
    """

    name = "tracker_noise"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal, u_angle ~ N(mean, sd)"
    targets = ("spherical_noise.range", "spherical_noise.angles")
    parameters = {"angular_mean": Q_(20.0, "urad"), "angular_sd": Q_(3.0, "urad"), "distance": Q_(4.0, "um"),
                  "distance_per_length": Q_(0.8, "um/m")}
    links = {"angular_mean": "tracker.angular", "distance": "tracker.distance",
             "distance_per_length": "tracker.distance_per_length"}
    nonnegative = ("angular_mean", "angular_sd", "distance", "distance_per_length")

    def standard_uncertainty(self):
        return self.parameters["angular_mean"]

    def sample(self, n, rng, ctx):
        r = np.linalg.norm(ctx.nominal_tracker_points, axis=1)
        mean = self.value("angular_mean", "rad")
        ua = np.abs(rng.normal(mean, self.value("angular_sd", "rad"), (n, 1, 2)))
        if ctx.row_noise is None:
            ur = self.value("distance", "mm") + self.value("distance_per_length", "") * r
        else:  # several stations, each with its own stated noise: the drawn angular u scales each one's alike
            ur = ctx.row_noise["distance"] + ctx.row_noise["distance_per_length"] * r
            ua = ua * (ctx.row_noise["angular"] / mean if mean > 0 else 0.0)[None, :, None]
        return {"spherical_noise.range": Q_(rng.standard_normal((n, ctx.n_points)) * ur[None, :], _MM),
                "spherical_noise.angles": Q_(rng.standard_normal((n, ctx.n_points, 2)) * ua, _RAD)}


class SMRCentring(Source):
    """Off-centre reflector (u_SMR): the beam hits the SMR off its centre, perpendicular to the beam."""

    name = "smr_centring"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal, perpendicular to the beam"
    targets = ("tracker_offset",)
    parameters = {"u_SMR": Q_(2.0, "um")}
    nonnegative = ("u_SMR",)

    def standard_uncertainty(self):
        return self.parameters["u_SMR"]

    def sample(self, n, rng, ctx):
        lateral = rng.normal(0.0, self.value("u_SMR", "mm"), (n, ctx.n_points, 2))
        # the beam's azimuth and elevation directions at the nominal points (the same in every trial): once
        pts = ctx.nominal_tracker_points
        hit = self.__dict__.get("_directions")
        if hit is None or hit[0] is not pts:
            hit = (pts, lt.smr_offset(pts, np.array([1.0, 0.0])), lt.smr_offset(pts, np.array([0.0, 1.0])))
            self.__dict__["_directions"] = hit
        _, e_az, e_el = hit
        return {"tracker_offset": Q_(lateral[..., :1] * e_az + lateral[..., 1:2] * e_el, _MM)}


class SoftwarePointUncertainty(Source):
    """Point uncertainty the metrology software states (u_MS,x, u_MS,y, u_MS,z)."""

    name = "software_point_uncertainty"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal"
    targets = ("tracker_offset",)
    parameters = {"u_MS": Q_(1.0, "um")}
    nonnegative = ("u_MS",)

    def standard_uncertainty(self):
        return self.parameters["u_MS"]

    def sample(self, n, rng, ctx):
        return {"tracker_offset": Q_(rng.normal(0.0, self.value("u_MS", "mm"), (n, ctx.n_points, 3)), _MM)}


# ----------------------------------------------------------------------------- simulated physics (opt-in)
class TrackerDriftEffect(Source):
    """Simulated drift of the tracker: the measured points move at a constant velocity (machine frame) from the start."""

    name = "tracker_drift"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {f"v_{a}": Q_(0.0, "um/h") for a in "xyz"}
    opt_in = True

    def sample(self, n, rng, ctx):
        v = np.array([self.value(f"v_{a}", "mm/s") for a in "xyz"])
        return {"point_offset": Q_(np.tile(ctx.plan.time[:, None] * v[None, :], (n, 1, 1)), _MM)}


class TrackerRangeOffsetEffect(Source):
    """Simulated zero error of the tracker's distance meter: every range reads ``offset`` long."""

    name = "tracker_range_offset"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "fixed (simulated physics)"
    targets = ("spherical_noise.range",)
    parameters = {"offset": Q_(0.0, "um")}
    opt_in = True

    def sample(self, n, rng, ctx):
        return {"spherical_noise.range": Q_(np.full((n, ctx.n_points), self.value("offset", "mm")), _MM)}


class AirTemperatureDriftEffect(Source):
    """Simulated apparent vertical shift that follows the air temperature (refraction, a warming stand).

    The measured points move along the machine's z by ``sensitivity`` times
    the change of the mean air temperature since the first point.
    """

    name = "air_temperature_drift"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {"sensitivity": Q_(0.0, "um/K")}
    opt_in = True

    def sample(self, n, rng, ctx):
        cols = [s.column for s in ctx.plan.sensors if s.attached_to.strip().lower() == "air"
                and s.column in ctx.plan.temperature]
        disp = np.zeros((ctx.n_points, 3))
        if cols:
            T = np.mean([ctx.plan.temperature[c] for c in cols], axis=0)
            disp[:, 2] = self.value("sensitivity", "mm/K") * (T - T[0])
        return {"point_offset": Q_(np.tile(disp, (n, 1, 1)), _MM)}


@hookimpl
def mtbudget_register_sources(register):
    for cls in (TrackerNoise, SMRCentring, SoftwarePointUncertainty, TrackerDriftEffect, TrackerRangeOffsetEffect,
                AirTemperatureDriftEffect):
        register(cls())
