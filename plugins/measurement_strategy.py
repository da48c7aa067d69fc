"""Built-in sources of the measurement-strategy group (paper Section 2.2.3, Eq. 25-26)."""

from __future__ import annotations

import numpy as np

from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_, ureg

_MM, _RAD, _ONE = ureg.Unit("mm"), ureg.Unit("rad"), ureg.Unit("")  # built once: Q_(x, "mm") parses the unit on every call



class Registration(Source):
    """Uncertainty of the tracker pose (Eq. 25-26): random terms on T_LT and on the Euler angles.

    mtbudget identifies the pose together with the errors in every
    verification, so a pose offset is re-estimated from the data and this
    source's contribution is expected near zero; it becomes visible when the
    pose is held fixed (a separate registration), and it changes where the
    tracker's noise falls on the mesh.
    """

    name = "registration"
    group = Group.MEASUREMENT_STRATEGY
    distribution = "normal"
    targets = ("pose.position", "pose.orientation")
    parameters = {"u_position": Q_(0.5, _MM), "u_orientation": Q_(100.0, "urad")}
    nonnegative = ("u_position", "u_orientation")

    def standard_uncertainty(self):
        return self.parameters["u_position"]

    def sample(self, n, rng, ctx):
        return {"pose.position": Q_(rng.normal(0.0, self.value("u_position", "mm"), (n, 3)), _MM),
                "pose.orientation": Q_(rng.normal(0.0, self.value("u_orientation", "rad"), (n, 3)), _RAD)}


class Multilateration(Source):
    """Multilateration: the point from the distances of several tracker stations (ranges only).

    The paper leaves it unmodelled. Here ``stations`` stations stand on a
    circle of ``radius`` around the mesh centre at ``height`` above it, all
    in interferometer/ADM range mode: each distance has u_r = distance +
    distance_per_length * r, and each station's position is known from the
    network's self-calibration to ``u_station``. The point follows from the
    linearised least-squares trilateration, so its error is
    (E^T W E)^-1 E^T W (range noise + e_k . station error): angular noise is
    gone, geometry matters. Use it instead of ``tracker_noise``
    (``[sources] disable = ["tracker_noise"]``).
    """

    name = "multilateration"
    group = Group.MEASUREMENT_STRATEGY
    distribution = "normal (ranges and station positions)"
    targets = ("point_offset",)
    parameters = {"stations": Q_(4), "radius": Q_(2.0, "m"), "height": Q_(0.8, "m"), "distance": Q_(4.0, "um"),
                  "distance_per_length": Q_(0.8, "um/m"), "u_station": Q_(2.0, "um")}
    #: it replaces one station's tracker noise: off unless enabled, and never together with tracker_noise
    opt_in = True
    excludes = ("tracker_noise",)
    nonnegative = ("distance", "distance_per_length", "u_station", "radius")

    def check(self):
        k = self.parameters["stations"].magnitude
        if k != int(k) or k < 3:
            return f"parameter 'stations' must be a whole number of at least 3, got {k}"
        return super().check()

    def standard_uncertainty(self):
        return self.parameters["distance"]

    def station_positions(self, ctx):
        k = int(self.parameters["stations"].magnitude)
        if k < 3:
            from mtbudget.errors import PluginError

            raise PluginError("multilateration needs at least 3 stations", self.plugin, self.name)
        nominal = ctx.plan.nominal + ctx.plan.tool
        c = 0.5 * (nominal.min(0) + nominal.max(0))
        ang = 2 * np.pi * np.arange(k) / k + 0.3
        R, h = self.value("radius", "mm"), self.value("height", "mm")
        return np.column_stack([c[0] + R * np.cos(ang), c[1] + R * np.sin(ang), np.full(k, c[2] + h)])

    def sample(self, n, rng, ctx):
        S = self.station_positions(ctx)  # (K, 3)
        P = ctx.plan.nominal + ctx.plan.tool  # (M, 3) machine frame
        d = P[None, :, :] - S[:, None, :]  # (K, M, 3)
        r = np.linalg.norm(d, axis=2)
        E = np.transpose(d / r[..., None], (1, 0, 2))  # (M, K, 3): unit vectors station -> point
        ur = (self.value("distance", "mm") + self.value("distance_per_length", "") * r).T  # (M, K)
        W = 1.0 / ur**2
        N = np.einsum("mki,mk,mkj->mij", E, W, E)
        G = np.linalg.solve(N, np.transpose(E * W[..., None], (0, 2, 1)))  # (M, 3, K)
        eps = rng.standard_normal((n, ur.shape[0], ur.shape[1])) * ur[None]  # range noise (n, M, K)
        ds = rng.normal(0.0, self.value("u_station", "mm"), (n, S.shape[0], 3))  # station errors, fixed per trial
        # a station displaced by ds changes each measured range by -e . ds
        eps = eps - np.einsum("mki,nki->nmk", E, ds)
        return {"point_offset": Q_(np.einsum("mik,nmk->nmi", G, eps), _MM)}


@hookimpl
def mtbudget_register_sources(register):
    register(Registration())
    register(Multilateration())
