"""Built-in sources of the measurement-strategy group (paper Section 2.2.3, Eq. 25-26)."""

from __future__ import annotations

from mtbudget.hookspecs import hookimpl
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_


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
    parameters = {"u_position": Q_(0.5, "mm"), "u_orientation": Q_(100.0, "urad")}
    plausible = {"u_position": Q_(10.0, "mm"), "u_orientation": Q_(10.0, "mrad")}  # 0.1-2 mm, 20-2000 urad
    nonnegative = ("u_position", "u_orientation")

    def standard_uncertainty(self):
        return self.parameters["u_position"]

    def sample_internal(self, n, rng, ctx):  # float64 arrays in the internal units, mm and rad
        return {"pose.position": rng.normal(0.0, self.value("u_position", "mm"), (n, 3)),
                "pose.orientation": rng.normal(0.0, self.value("u_orientation", "rad"), (n, 3))}

    def drawn(self, sample, ctx):
        return {"position_offset": {"value": [float(v) for v in sample["pose.position"]], "unit": "mm",
                                    "meaning": "what the registration drew on the tracker's position D, L, H (the "
                                               "identification estimates the pose anew: no diagnosis names it)"},
                "orientation_offset": {"value": [float(v) * 1e6 for v in sample["pose.orientation"]], "unit": "urad",
                                       "meaning": "what the registration drew on the tracker's Euler angles a, b, d"}}


@hookimpl
def mtbudget_register_sources(register):
    register(Registration())
