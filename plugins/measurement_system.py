"""Built-in sources of the measurement-system group (paper Section 2.2.2, Eq. 21-24)."""

from __future__ import annotations

import numpy as np

from mtbudget import tracker as lt
from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_

from .machine_tool import normal0

# Every source draws in ``sample_internal`` (float64 arrays in the targets' internal units, mm and rad; see
# plugins/machine_tool.py); ``sample`` wraps them as quantities.


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
    plausible = {"angular_sd": Q_(200.0, "urad")}  # the spread of the angular u between trackers: 0.5-5 urad

    def standard_uncertainty(self):
        return self.parameters["angular_mean"]

    def _prepare(self, ctx):
        r = np.linalg.norm(ctx.nominal_tracker_points, axis=1)
        mean = self.value("angular_mean", "rad")
        if ctx.row_noise is None:
            ur, rows = self.value("distance", "mm") + self.value("distance_per_length", "") * r, None
        else:  # several stations, each with its own stated noise: the drawn angular u scales each one's alike
            ur = ctx.row_noise["distance"] + ctx.row_noise["distance_per_length"] * r
            rows = (ctx.row_noise["angular"] / mean if mean > 0 else 0.0)[None, :, None]
        return mean, self.value("angular_sd", "rad"), ur[None, :], rows

    def sample_internal(self, n, rng, ctx):
        key = (*self.parameters.values(), ctx, ctx.nominal_tracker_points, ctx.row_noise)
        mean, sd, ur, rows = self.remembered(key, lambda: self._prepare(ctx))
        ua = np.abs(rng.normal(mean, sd, (n, 1, 2)))
        M = ctx.n_points
        z = rng.standard_normal(3 * n * M)  # the numbers of a (n, M) draw, then of a (n, M, 2) one
        noise = z[:n * M].reshape(n, M)
        noise *= ur
        angles = z[n * M:].reshape(n, M, 2)
        if rows is not None:
            angles *= ua * rows
        else:  # each angle's column by its own u: the same products, in rows of M (a last axis of 2 is slow)
            angles[:, :, 0] *= ua[:, :, 0]
            angles[:, :, 1] *= ua[:, :, 1]
        return {"spherical_noise.range": noise, "spherical_noise.angles": angles}


class SMRCentring(Source):
    """Off-centre reflector (u_SMR): the beam hits the SMR off its centre, perpendicular to the beam."""

    name = "smr_centring"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal, perpendicular to the beam"
    targets = ("tracker_offset",)
    parameters = {"u_SMR": Q_(2.0, "um")}
    plausible = {"u_SMR": Q_(50.0, "um")}  # an SMR is centred to 0.5-12 um
    nonnegative = ("u_SMR",)

    def standard_uncertainty(self):
        return self.parameters["u_SMR"]

    def sample_internal(self, n, rng, ctx):
        u = self.value("u_SMR", "mm")
        if u > 0.0:  # rng.normal(0.0, u, (n, M, 2)) bit for bit (see normal0)
            lateral = rng.standard_normal((n, ctx.n_points, 2))
            lateral *= u
            lateral += 0.0
        else:
            lateral = rng.normal(0.0, u, (n, ctx.n_points, 2))
        a, b = lateral[..., 0], lateral[..., 1]
        # the beam's azimuth and elevation directions at the nominal points (the same in every trial): once
        pts = ctx.nominal_tracker_points
        hit = self.__dict__.get("_directions")
        if hit is None or hit[0] is not pts:  # (3, M) each: x, y, z of every point's direction
            hit = (pts, np.ascontiguousarray(lt.smr_offset(pts, np.array([1.0, 0.0])).T),
                   np.ascontiguousarray(lt.smr_offset(pts, np.array([0.0, 1.0])).T))
            self.__dict__["_directions"] = hit
        _, e_az, e_el = hit
        # lateral[..., :1] * e_az + lateral[..., 1:2] * e_el, one coordinate at a time (the same products and sums, in
        # rows of M instead of a last axis of 3)
        out = np.empty((n, ctx.n_points, 3))
        tmp = np.empty((n, ctx.n_points))
        for c in range(3):
            o = out[..., c]
            np.multiply(a, e_az[c], out=o)
            np.multiply(b, e_el[c], out=tmp)
            o += tmp
        return {"tracker_offset": out}


class SoftwarePointUncertainty(Source):
    """Point uncertainty the metrology software states (u_MS,x, u_MS,y, u_MS,z)."""

    name = "software_point_uncertainty"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal"
    targets = ("tracker_offset",)
    parameters = {"u_MS": Q_(1.0, "um")}
    plausible = {"u_MS": Q_(50.0, "um")}  # software: 0.1-5 um
    nonnegative = ("u_MS",)

    def standard_uncertainty(self):
        return self.parameters["u_MS"]

    def sample_internal(self, n, rng, ctx):
        return {"tracker_offset": normal0(rng, self.value("u_MS", "mm"), (n, ctx.n_points, 3))}


# ----------------------------------------------------------------------------- simulated physics (opt-in)
class TrackerDriftEffect(Source):
    """Simulated drift of the tracker: the measured points move at a constant velocity (machine frame) from the start."""

    name = "tracker_drift"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "fixed (simulated physics)"
    targets = ("point_offset",)
    parameters = {f"v_{a}": Q_(0.0, "um/h") for a in "xyz"}
    plausible = {f"v_{a}": Q_(200.0, "um/h") for a in "xyz"}  # a tracker drifts by 0-20 um/h
    opt_in = True

    def sample_internal(self, n, rng, ctx):
        v = np.array([self.value(f"v_{a}", "mm/s") for a in "xyz"])
        return {"point_offset": np.tile(ctx.plan.time[:, None] * v[None, :], (n, 1, 1))}

    def drawn(self, sample, ctx):
        return {"velocity": {"value": [self.value(f"v_{a}", "um/h") for a in "xyz"], "unit": "um/h",
                             "meaning": "the measured points move at this velocity in the machine frame from the start "
                                        "(fixed: simulated physics)", "effect": "tracker_drift"}}


class TrackerRangeOffsetEffect(Source):
    """Simulated zero error of the tracker's distance meter: every range reads ``offset`` long."""

    name = "tracker_range_offset"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "fixed (simulated physics)"
    targets = ("spherical_noise.range",)
    parameters = {"offset": Q_(0.0, "um")}
    plausible = {"offset": Q_(500.0, "um")}  # a range offset of 1-50 um
    opt_in = True

    def sample_internal(self, n, rng, ctx):
        return {"spherical_noise.range": np.full((n, ctx.n_points), self.value("offset", "mm"))}


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
    plausible = {"sensitivity": Q_(200.0, "um/K")}  # about 1 um/(m*K) of path: 1-30 um/K
    opt_in = True

    def sample_internal(self, n, rng, ctx):
        cols = [s.column for s in ctx.plan.sensors if s.attached_to.strip().lower() == "air"
                and s.column in ctx.plan.temperature]
        disp = np.zeros((ctx.n_points, 3))
        if cols:
            T = np.mean([ctx.plan.temperature[c] for c in cols], axis=0)
            disp[:, 2] = self.value("sensitivity", "mm/K") * (T - T[0])
        return {"point_offset": np.tile(disp, (n, 1, 1))}


@hookimpl
def mtbudget_register_sources(register):
    for cls in (TrackerNoise, SMRCentring, SoftwarePointUncertainty, TrackerDriftEffect, TrackerRangeOffsetEffect,
                AirTemperatureDriftEffect):
        register(cls())
