"""The uncertainty-source contract: Group, Source, Context.

A source belongs to one of the paper's four groups, declares its parameters
as pint quantities and the model inputs it perturbs, and draws perturbations
for N trials at once.  The engine converts what ``sample`` returns to the
internal units once per call and checks shapes, dimensions and NaN.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import pint

from .errors import PluginError
from .model import MODEL_INPUTS
from .units import Q_, ureg


class Group(str, enum.Enum):
    """The paper's four groups of uncertainty sources (Section 2.2, Fig. 3)."""

    MACHINE_TOOL = "machine tool"
    MEASUREMENT_SYSTEM = "measurement system"
    MEASUREMENT_STRATEGY = "measurement strategy"
    OPTIMISATION_STRATEGY = "optimisation strategy"


#: what a source may perturb: key -> (unit, shape after the trial axis)
#: "M" = measured points of the plan, "p" = geometric parameters of the machine model.
#: Inputs the model takes as they are come from MODEL_INPUTS; the model's mixed-unit
#: inputs (geometry, pose, spherical noise) are split here so each key has one unit.
TARGETS = {
    **{k: v for k, v in MODEL_INPUTS.items() if k not in ("geometry", "pose", "spherical_noise")},
    "geometry.translational": ("mm", ("p",)),
    "geometry.angular": ("rad", ("p",)),
    "pose.position": ("mm", (3,)),
    "pose.orientation": ("rad", (3,)),
    "spherical_noise.range": ("mm", ("M",)),
    "spherical_noise.angles": ("rad", ("M", 2)),
    "strategy": ("", ()),  # index into Source.options(context), optimisation-strategy sources
}


@dataclass
class Context:
    """What a source may use when sampling (internal units, read-only by convention).

    plan: the verification plan (times, nominal positions, directions, temperatures).
    model: the machine model that simulates (its ``errors.params`` name the geometry vector).
    nominal_tracker_points: (M, 3) error-free tracker coordinates of the plan.
    theta: (p,) the simulated machine's geometric parameters.
    reference_temperature: K.
    config: the run's configuration.
    """

    plan: object
    model: object
    nominal_tracker_points: np.ndarray
    theta: np.ndarray
    reference_temperature: float
    config: object = None

    @property
    def n_points(self) -> int:
        return len(self.plan)

    def parameter_mask(self, unit: str) -> np.ndarray:
        """Boolean mask of the geometric parameters in ``unit`` ("mm" or "rad")."""
        return np.array([p.unit == unit for p in self.model.errors.params])


class Source:
    """Base class of an uncertainty source.

    Subclasses set ``name``, ``group``, ``distribution`` (a short text such as
    "normal" or "rectangular"), ``parameters`` (name -> pint Quantity),
    ``targets`` (keys of :data:`TARGETS`) and implement :meth:`sample`.
    """

    name: str = ""
    group: Group = Group.MACHINE_TOOL
    distribution: str = ""
    description: str = ""
    targets: tuple = ()
    parameters: dict = {}

    # stamped by the plugin host
    plugin: str = ""
    dist_name: str = ""
    dist_version: str = ""

    def __init__(self, **overrides):
        self.parameters = dict(type(self).parameters)
        if overrides:
            self.configure(overrides)

    def configure(self, values: dict):
        """Override parameters; each new value must have the dimension of the default."""
        for k, v in values.items():
            if k not in self.parameters:
                raise PluginError(f"unknown parameter {k!r}; it has {', '.join(self.parameters) or 'none'}",
                                  self.plugin or None, self.name)
            old = self.parameters[k]
            if isinstance(old, str):  # a word-valued parameter (a choice), kept as text
                self.parameters[k] = str(v)
                continue
            try:
                new = v if isinstance(v, pint.Quantity) else (ureg.Quantity(v) if isinstance(v, str) else v)
            except Exception:
                raise PluginError(f"parameter {k!r}: cannot parse {v!r} as a quantity", self.plugin or None, self.name) from None
            if isinstance(old, pint.Quantity):
                if not isinstance(new, pint.Quantity):
                    new = Q_(float(new))
                if new.dimensionality != old.dimensionality:
                    raise PluginError(f"parameter {k!r}: {new:~P} does not have the dimension of {old:~P}",
                                      self.plugin or None, self.name)
            self.parameters[k] = new
        return self

    def value(self, key: str, unit: str) -> float:
        """A parameter as a float in ``unit``."""
        return float(self.parameters[key].to(unit).magnitude)

    def sample(self, n: int, rng: np.random.Generator, context: Context) -> dict:
        """Perturbations for ``n`` trials: {target key: Quantity array of shape (n, *shape)}."""
        raise NotImplementedError

    def options(self, context: Context) -> list:
        """For the ``strategy`` target: the alternative identification settings (list of dicts)."""
        return []

    def standard_uncertainty(self) -> pint.Quantity | None:
        """The source's characteristic standard uncertainty u(x_i) for the GUM-style budget, if it has one."""
        return None


def check_sample(source: Source, out: dict, n: int, shapes: dict) -> dict:
    """Validate a sample and convert it to internal float arrays (one conversion per call)."""
    if not isinstance(out, dict):
        raise PluginError(f"sample() must return a dict of target -> Quantity, got {type(out).__name__}",
                          source.plugin, source.name, "sample")
    conv = {}
    for key, q in out.items():
        if key not in source.targets:
            raise PluginError(f"sample() returned {key!r}, which is not among its declared targets {source.targets}",
                              source.plugin, source.name, "sample")
        unit, _ = TARGETS[key]
        if not isinstance(q, pint.Quantity):
            if unit:
                raise PluginError(f"{key!r} must be a pint Quantity in a unit of {ureg.Unit(unit).dimensionality}",
                                  source.plugin, source.name, "sample")
            q = Q_(np.asarray(q))
        target = ureg.Unit(unit) if unit else ureg.dimensionless
        if q.dimensionality != target.dimensionality:
            raise PluginError(f"{key!r} has dimension {q.dimensionality} ({q.units:~}), expected {target.dimensionality}"
                              f" (e.g. {unit or 'dimensionless'})", source.plugin, source.name, "sample")
        arr = np.asarray(q.to(target).magnitude, dtype=float)
        want = (n,) + shapes[key]
        if arr.shape != want:
            raise PluginError(f"{key!r} has shape {arr.shape}, expected {want}", source.plugin, source.name, "sample")
        if not np.all(np.isfinite(arr)):
            raise PluginError(f"{key!r} contains NaN or infinity ({int((~np.isfinite(arr)).sum())} values)",
                              source.plugin, source.name, "sample")
        conv[key] = arr
    return conv
