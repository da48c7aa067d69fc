"""Built-in sources of the measurement-system group (paper Section 2.2.2, Eq. 21-24)."""

from __future__ import annotations

import numpy as np

from mtbudget import tracker as lt
from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_


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

    def standard_uncertainty(self):
        return self.parameters["angular_mean"]

    def sample(self, n, rng, ctx):
        r = np.linalg.norm(ctx.nominal_tracker_points, axis=1)
        ur = self.value("distance", "mm") + self.value("distance_per_length", "") * r
        ua = np.abs(rng.normal(self.value("angular_mean", "rad"), self.value("angular_sd", "rad"), (n, 1, 2)))
        return {"spherical_noise.range": Q_(rng.standard_normal((n, ctx.n_points)) * ur[None, :], "mm"),
                "spherical_noise.angles": Q_(rng.standard_normal((n, ctx.n_points, 2)) * ua, "rad")}


class SMRCentring(Source):
    """Off-centre reflector (u_SMR): the beam hits the SMR off its centre, perpendicular to the beam."""

    name = "smr_centring"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal, perpendicular to the beam"
    targets = ("tracker_offset",)
    parameters = {"u_SMR": Q_(2.0, "um")}

    def standard_uncertainty(self):
        return self.parameters["u_SMR"]

    def sample(self, n, rng, ctx):
        lateral = rng.normal(0.0, self.value("u_SMR", "mm"), (n, ctx.n_points, 2))
        pts = np.broadcast_to(ctx.nominal_tracker_points, (n, ctx.n_points, 3))
        return {"tracker_offset": Q_(lt.smr_offset(pts, lateral), "mm")}


class SoftwarePointUncertainty(Source):
    """Point uncertainty the metrology software states (u_MS,x, u_MS,y, u_MS,z)."""

    name = "software_point_uncertainty"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal"
    targets = ("tracker_offset",)
    parameters = {"u_MS": Q_(1.0, "um")}

    def standard_uncertainty(self):
        return self.parameters["u_MS"]

    def sample(self, n, rng, ctx):
        return {"tracker_offset": Q_(rng.normal(0.0, self.value("u_MS", "mm"), (n, ctx.n_points, 3)), "mm")}


@hookimpl
def mtbudget_register_sources(register):
    for cls in (TrackerNoise, SMRCentring, SoftwarePointUncertainty):
        register(cls())
