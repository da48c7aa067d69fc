"""Spindle thermal growth: the tool point moves along -Z as the spindle warms up during the test."""

import numpy as np

from mtbudget import Q_, hookimpl
from mtbudget.contracts import Group, Source


class SpindleGrowth(Source):
    """Growth rate of the spindle, normal about zero; the tool point moves by rate * t along -Z."""

    name = "spindle_growth"
    group = Group.MACHINE_TOOL
    distribution = "normal rate"
    targets = ("point_offset",)
    parameters = {"rate": Q_(2.0, "um/h")}
    nonnegative = ("rate",)  # a standard deviation: a negative value in a configuration is an error

    def standard_uncertainty(self):
        return self.parameters["rate"]

    def sample(self, n, rng, context):
        rate = rng.normal(0.0, self.value("rate", "mm/s"), (n, 1))  # one rate per trial, in mm/s
        offset = np.zeros((n, context.n_points, 3))
        offset[:, :, 2] = -rate * context.plan.time[None, :]  # plan times are in s
        return {"point_offset": Q_(offset, "mm")}


@hookimpl
def mtbudget_register_sources(register):
    register(SpindleGrowth())
