"""The plugin contracts: what a plugin implements and what it is given.

* :class:`Source` (hook ``mtbudget_register_sources``): an uncertainty source
  of one of the paper's four :class:`Group` s.  It declares its parameters as
  pint quantities and the model inputs it perturbs (:data:`TARGETS`), and
  draws perturbations for N trials at once from a :class:`Context`.  The
  engine converts what ``sample`` returns to the internal units once per call
  and checks shapes, dimensions and NaN.  A source may instead implement
  ``sample_internal``, which returns plain float64 arrays already in each
  target's internal unit (the built-ins do): the engine then builds no pint
  quantity per block, and ``sample`` wraps those arrays as quantities.
* :class:`Candidate` (hook ``mtbudget_register_candidates``): a physics term
  a rigid-body verification model leaves out, for ``mtbudget diagnose``.  It
  gives the displacement of every measured point per unit of its parameters
  from a :class:`DiagnosisContext`.

Both are plain classes with declared parameters (with units) and methods;
the plugin host calls every method through :func:`mtbudget.plugins.call`, so
an exception inside a plugin names the plugin, the hook and the method.
"""

from __future__ import annotations

import enum
import operator
from dataclasses import dataclass

import numpy as np
import pint

from typing import TYPE_CHECKING

from .errors import PluginError
from .model import MODEL_INPUTS
from .units import ABSOLUTE_TEMPERATURE, Q_, angle_or_ratio_problem, is_offset_temperature, is_temperature_difference_unit, parse_quantity, ureg

if TYPE_CHECKING:  # annotations only: the contract does not import the layers that use it
    from .model import MeasurementModel
    from .recording import Recording


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
    # added to the compensated machine's error only, never to the verification's measurements (machine frame): the
    # machine in use, what the verification cannot identify at another tool
    "measurand_offset": ("mm", ("M", 3)),
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
    #: at a [measurand] tool the verification did not use: {"unidentified_field": (k, M, 3) mm}, the field at the mesh
    #: rows of each unit draw of the error combinations it cannot identify (their prior); None otherwise
    measurand: dict | None = None
    #: several stations ([[stations]]): what each plan row's station states of its noise, {"angular" (rad),
    #: "distance" (mm), "distance_per_length"}: (M,) arrays (a station's own, else the tracker's); None for one tracker
    row_noise: dict | None = None

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
    #: an opt-in source is off unless the configuration enables it (simulated physics such as a
    #: thermal expansion the verification does not know about); the others are on by default
    opt_in: bool = False
    #: parameter -> the configuration key of the physical input it draws (for example
    #: ``{"R": "machine_tool.repeatability"}``): one key per physical input, see mtbudget.scenario
    links: dict = {}
    #: names of other sources that model the same thing differently: both cannot be enabled
    excludes: tuple = ()
    #: parameters that must not be negative (standard uncertainties, widths, bounds)
    nonnegative: tuple = ()
    #: parameter -> the largest plausible magnitude of its value (a pint Quantity of its dimension, shown in the
    #: bound's unit), by the rule of every stated value (mtbudget.recording.UNCERTAINTIES and MAGNITUDES): several
    #: times the poorest machine or instrument in use and below a thousand times the smallest value in use, so a value
    #: written in the next unit up ("20 mrad" for "20 urad", "3 mm" for "3 um") is refused where it is set
    #: (:meth:`configure`), in one line naming the parameter.  Leave out a parameter ``links`` ties to a physical
    #: input: the configuration's key bounds it.
    plausible: dict = {}
    #: temperature parameters that are absolute temperatures (a default in degC or degF alone is one too);
    #: every other temperature parameter is a difference, which refuses "0.1 degC" (pint: 273.25 K)
    absolute_temperatures: tuple = ()
    #: a systematic effect of unknown size the source draws (for example "model form": the machine richer than the
    #: identification's model); the budget labels its rows and sums each kind.  Such a source also says how its size
    #: was bounded, in one sentence for the plan at hand: ``bounded(context) -> str``
    systematic: str = ""

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
            new = parse_quantity(v, where=f"parameter {k!r}",
                                 error=lambda m: PluginError(m, self.plugin or None, self.name))
            if isinstance(old, pint.Quantity):
                if not isinstance(new, pint.Quantity):
                    new = Q_(float(new))
                if old.dimensionless and not old.unitless and not dict(new.unit_items()):
                    raise PluginError(f"parameter {k!r}: {v!r} needs an explicit unit (for example \"{v} {old.units:~P}\"); "
                                      "a bare number is ambiguous for an angle", self.plugin or None, self.name)
                if new.dimensionality != old.dimensionality:
                    raise PluginError(f"parameter {k!r}: {new:~P} does not have the dimension of {old:~P}",
                                      self.plugin or None, self.name)
                if old.dimensionless and dict(old.unit_items()) and (problem := angle_or_ratio_problem(new, old)):
                    raise PluginError(f"parameter {k!r}: {v!r} {problem}", self.plugin or None, self.name)
                if old.dimensionality == ureg.kelvin.dimensionality:
                    if is_offset_temperature(old) or k in self.absolute_temperatures:
                        if is_temperature_difference_unit(new):
                            raise PluginError(f"parameter {k!r}: {v!r} is a temperature difference; it is an absolute "
                                              "temperature: write for example \"20 degC\"", self.plugin or None, self.name)
                        kelvin, (lo, hi) = float(new.to("K").magnitude), ABSOLUTE_TEMPERATURE
                        if not lo <= kelvin <= hi:
                            raise PluginError(f"parameter {k!r}: {v!r} ({kelvin:.6g} K) is not a plausible absolute "
                                              f"temperature; expected {lo:g} K to {hi:g} K", self.plugin or None, self.name)
                    elif is_offset_temperature(new):
                        delta = "delta_degF" if "Fahrenheit" in next(iter(new.unit_items()))[0] else "delta_degC"
                        raise PluginError(f"parameter {k!r}: {v!r} is a temperature difference written on an offset "
                                          f"scale (read as {new.to('K').magnitude:.6g} K); write \"{new.magnitude:g} "
                                          f"{delta}\" or give it in K", self.plugin or None, self.name)
            self.parameters[k] = new
            problem = self.plausibility_problem(k)
            if problem:
                err = PluginError(f"parameter {k!r}: {problem}", self.plugin or None, self.name)
                err.parameter, err.problem = k, problem  # the scenario names the key sources.<name>.<parameter>
                raise err
        return self

    def plausibility_problem(self, key: str) -> str | None:
        """None when parameter ``key`` is within its :attr:`plausible` bound (or has none), otherwise what is wrong:
        the value, the plausible range and why, in the bound's unit."""
        bound, v = self.plausible.get(key), self.parameters.get(key)
        if bound is None or not isinstance(v, pint.Quantity):
            return None
        unit = bound.units
        value = float(v.to(unit).magnitude)
        high = float(bound.magnitude)
        if np.isfinite(value) and abs(value) <= high:
            return None
        shown = f"{unit:~P}".replace("µ", "u") if str(unit) != "dimensionless" else ""  # as the user types it
        return (f"{value:g} {shown} is not plausible; expected at most {high:g} {shown} in magnitude (several times "
                f"the poorest in use; a value in the next unit up?)").replace("  ", " ").replace(" )", ")")

    def check(self) -> str | None:
        """None when the parameters are valid, otherwise what is wrong (one sentence, naming the parameter)."""
        for k in self.nonnegative:
            v = self.parameters.get(k)
            if isinstance(v, pint.Quantity) and v.magnitude < 0:
                return f"parameter {k!r} must not be negative, got {v:~P}"
        return None

    def value(self, key: str, unit: str) -> float:
        """A parameter as a float in ``unit``, remembered per parameter object: sources are sampled once per block,
        and a unit conversion costs more than drawing a block's numbers (a parameter that ``configure`` replaces
        is converted anew)."""
        q = self.parameters[key]
        cache = self.__dict__.setdefault("_value_cache", {})
        hit = cache.get((key, unit))
        if hit is None or hit[0] is not q:
            hit = (q, float(q.to(unit).magnitude))
            cache[(key, unit)] = hit
        return hit[1]

    def remembered(self, key: tuple, build):
        """``build()``, remembered while ``key`` holds the same objects (compared by identity): what a source derives
        from its parameters and the context (converted values, masks, per-point factors) once instead of once per
        block.  Put in ``key`` every object ``build`` reads, the parameter values included
        (``*self.parameters.values()``), so a parameter that ``configure`` replaces or another context builds anew.
        One entry per source (the last key)."""
        hit = self.__dict__.get("_remembered")
        if hit is not None and len(hit[0]) == len(key) and all(map(operator.is_, hit[0], key)):
            return hit[1]
        value = build()
        self.__dict__["_remembered"] = (key, value)
        return value

    def sample(self, n: int, rng: np.random.Generator, context: Context) -> dict:
        """Perturbations for ``n`` trials: {target key: Quantity array of shape (n, *shape)}.

        A source implements this or :meth:`sample_internal`; by default this is :meth:`sample_internal`'s arrays as
        quantities in their targets' internal units."""
        if type(self).sample_internal is _SAMPLE_INTERNAL:  # neither implemented
            raise NotImplementedError
        return {k: Q_(v, internal_unit(k)) for k, v in self.sample_internal(n, rng, context).items()}

    def sample_internal(self, n: int, rng: np.random.Generator, context: Context) -> dict:
        """Optional, instead of :meth:`sample`: the same perturbations as float64 arrays of shape (n, *shape), each
        already in its target's internal unit (:data:`TARGETS`: mm, rad, dimensionless).  The engine calls it
        directly when the source does not override :meth:`sample` (no pint quantity per block) and checks keys,
        shapes and NaN as it does for :meth:`sample`."""
        raise NotImplementedError

    def options(self, context: Context) -> list:
        """For the ``strategy`` target: the alternative identification settings (list of dicts)."""
        return []

    def standard_uncertainty(self) -> pint.Quantity | None:
        """The source's characteristic standard uncertainty u(x_i) for the GUM-style budget, if it has one."""
        return None

    # Optional: ``drawn(self, sample, context) -> dict``: what this source drew in one trial, for the truth.json of a
    # simulated recording (mtbudget.simulate.truth_dict).  ``sample`` holds the source's own arrays of that trial
    # ({target key: float array of the target's shape, internal unit}, what sample_internal gave without the trial
    # axis); the answer maps a name to {"value": float or list, "unit": display unit, "meaning": one sentence}, and
    # "effect": the diagnosis candidate's label ("reversal[x]", "tracker_drift") where the draw is a physical effect
    # a diagnosis can name in the candidate's own parameter and unit, so a diagnosis can be checked against it.


_SAMPLE, _SAMPLE_INTERNAL = Source.sample, Source.sample_internal


def check_sample(source: Source, out: dict, n: int, shapes: dict, method: str = "sample") -> dict:
    """Validate a sample and convert it to internal float arrays (one conversion per call); ``method`` names what
    returned it in the errors."""
    if not isinstance(out, dict):
        raise PluginError(f"{method}() must return a dict of target -> Quantity, got {type(out).__name__}",
                          source.plugin, source.name, method)
    conv = {}
    for key, q in out.items():
        if key not in source.targets:
            raise PluginError(f"{method}() returned {key!r}, which is not among its declared targets "
                              f"{source.targets}", source.plugin, source.name, method)
        unit, _ = TARGETS[key]
        if not isinstance(q, pint.Quantity):
            if unit:
                raise PluginError(f"{key!r} must be a pint Quantity in a unit of {ureg.Unit(unit).dimensionality}",
                                  source.plugin, source.name, method)
            q = Q_(np.asarray(q))
        target = ureg.Unit(unit) if unit else ureg.dimensionless
        if q.dimensionality != target.dimensionality:
            raise PluginError(f"{key!r} has dimension {q.dimensionality} ({q.units:~}), expected {target.dimensionality}"
                              f" (e.g. {unit or 'dimensionless'})", source.plugin, source.name, method)
        arr = np.asarray(q.to(target).magnitude, dtype=float)
        want = (n,) + shapes[key]
        if arr.shape != want:
            raise PluginError(f"{key!r} has shape {arr.shape}, expected {want}", source.plugin, source.name, method)
        if not np.all(np.isfinite(arr)):
            raise PluginError(f"{key!r} contains NaN or infinity ({int((~np.isfinite(arr)).sum())} values)",
                              source.plugin, source.name, method)
        conv[key] = arr
    return conv


#: the largest magnitude a perturbation may have, per internal unit: beyond it a sample is absurd for a machine tool
#: verified with a laser tracker (10 m of offset, half a turn, a scale error of 100 %) and is refused, naming the
#: plugin and the source, before it can overflow into inf/nan results ("strategy": option indices, checked apart)
PLAUSIBLE_PERTURBATION = {"mm": 1e4, "rad": np.pi, "": 1.0}


def check_plausible(source: Source, out, method: str = "sample") -> None:
    """Refuse a sample holding a finite but absurd perturbation (:data:`PLAUSIBLE_PERTURBATION`), naming the plugin,
    the source and the target.  Values that are not finite, not quantities or of the wrong dimension are left to
    :func:`check_sample`, which says what is wrong with them.  One pass of ``abs().max()`` per array."""
    if not isinstance(out, dict):
        return
    for key, v in out.items():
        if key not in TARGETS or key == "strategy" or key not in source.targets:
            continue
        unit = TARGETS[key][0]
        try:
            if isinstance(v, pint.Quantity):
                mag = np.asarray(v.magnitude, dtype=float)
                f = 1.0 if v.units == internal_unit(key) else float(Q_(1.0, v.units).to(internal_unit(key)).magnitude)
            else:
                mag, f = np.asarray(v, dtype=float), 1.0
            if not mag.size:
                continue
            limit = PLAUSIBLE_PERTURBATION[unit] / abs(f)  # in the array's own unit
            if mag.max() <= limit and mag.min() >= -limit:  # two passes, no temporary (NaN fails: looked at below)
                continue
            if not np.isfinite(mag).all():
                continue  # NaN or infinity: check_sample says so
            big = float(np.abs(mag).max()) * abs(f)
        except (TypeError, ValueError, ZeroDivisionError, pint.errors.PintError):
            continue
        limit = PLAUSIBLE_PERTURBATION[unit]
        if big > limit:
            shown = f"{big:.3g} {unit}" if unit else f"{big:.3g}"
            raise PluginError(f"{method}() returned {key!r} of magnitude up to {shown}, beyond the plausible "
                              f"{limit:g} {unit or '(dimensionless)'} of a perturbation: a unit mistake or an overflow "
                              "in the plugin?", source.plugin or None, source.name, "mtbudget_register_sources", method)


#: target key -> its internal unit as a pint Unit (built once)
_INTERNAL_UNITS: dict = {}


def internal_unit(key: str):
    """The internal unit of a target of :data:`TARGETS` as a pint Unit (dimensionless for "")."""
    unit = _INTERNAL_UNITS.get(key)
    if unit is None:
        name = TARGETS[key][0]
        unit = _INTERNAL_UNITS[key] = ureg.Unit(name) if name else ureg.dimensionless
    return unit


def has_internal_sample(source: Source) -> bool:
    """True when ``source`` implements :meth:`Source.sample_internal` and does not override :meth:`Source.sample`
    (a subclass that overrides ``sample`` is sampled through it)."""
    cls = type(source)
    return getattr(cls, "sample", None) is _SAMPLE and getattr(cls, "sample_internal", None) is not _SAMPLE_INTERNAL


_FLOAT = np.dtype(float)
_all = np.logical_and.reduce  # ndarray.all without its Python wrapper (numpy's _methods._all)


def check_internal(source: Source, out: dict, n: int, shapes: dict) -> dict:
    """Validate what :meth:`Source.sample_internal` returned: float64 arrays, in the targets' internal units by
    contract, of the right shapes and finite.  Returns ``out`` itself when it is all that (the common case);
    anything else goes through :func:`check_sample` as quantities in the internal units, which converts what it
    can and says what is wrong."""
    if type(out) is dict:
        targets = source.targets
        for key, arr in out.items():
            if (key not in targets or type(arr) is not np.ndarray or arr.dtype != _FLOAT
                    or arr.shape != (n,) + shapes[key] or not _all(np.isfinite(arr), axis=None)):
                break
        else:
            return out
    if not isinstance(out, dict):
        raise PluginError(f"sample_internal() must return a dict of target -> float array, got {type(out).__name__}",
                          source.plugin, source.name, "sample_internal")
    return check_sample(source, {k: _as_quantity(k, v) for k, v in out.items()}, n, shapes, "sample_internal")


def _as_quantity(key, value):
    """What sample_internal returned for ``key`` as a quantity in its internal unit, for check_sample to judge."""
    if key not in TARGETS or isinstance(value, pint.Quantity):
        return value
    try:
        return Q_(np.asarray(value, dtype=float), internal_unit(key))
    except (TypeError, ValueError):
        return value


# ----------------------------------------------------------------------------- diagnosis candidates
class Candidate:
    """Base class of a diagnosis candidate: a physics term a rigid-body model leaves out.

    Subclasses set the class attributes below and implement :meth:`columns`;
    the other methods have defaults.  An instance is one candidate, for
    example ``ThermalExpansion("x")``.

    effect: fixed name of the effect (``thermal_expansion``, ``reversal``, ...).
    axis: "x", "y", "z", a pair such as "yz", or None (given to the constructor).
    description: one sentence on the physics (a subclass may set it per instance).
    parameters: name -> display unit (for example ``{"cte": "um/(m*K)"}``), in the order of the
        columns: one entry per column, or one entry for a vector parameter whose components are
        all the columns (``{"velocity": "um/h"}`` with three columns).  The columns and the
        parameter values the diagnosis passes back are in the internal unit of each
        (:func:`mtbudget.units.internal_unit_of`: 1/K for um/(m*K), mm for um, mm/s for um/h).
    frame: "machine" (workpiece frame) or "tracker": the frame of the columns' displacements.
    hints: other effect -> one sentence on the measurement that would tell the two apart, shown
        when the diagnosis cannot tell this candidate from that one.

    The diagnosis calls every method through :func:`mtbudget.plugins.call`, so an exception
    inside one names the plugin, the candidate, the hook and the method.
    """

    effect: str = ""
    axis: str | None = None
    description: str = ""
    parameters: dict = {}
    frame: str = "machine"
    hints: dict = {}
    #: parameter -> (low, high) in its display unit: the physically plausible range (for a vector
    #: parameter, of each component).  An estimate outside it is reported as implausible, never as a
    #: finding.  A parameter without an entry is not checked.
    plausible: dict = {}
    #: parameter -> how a sentence names it ("a CTE"): "would need a CTE of -27 um/(m*K)"
    quantity_names: dict = {}

    # stamped by the plugin host
    plugin: str = ""
    dist_name: str = ""
    dist_version: str = ""

    def __init__(self, axis: str | None = None):
        if axis is not None:
            self.axis = axis

    @property
    def label(self) -> str:
        return self.effect if not self.axis else f"{self.effect}[{self.axis}]"

    def units(self) -> list:
        """[(parameter, display unit, internal unit)] in the order of :attr:`parameters`."""
        from .units import internal_unit_of

        return [(name, unit, internal_unit_of(unit)) for name, unit in self.parameters.items()]

    def requires(self, ctx: DiagnosisContext) -> str | None:
        """None, or the reason this recording cannot test the candidate (a missing sensor, one approach side)."""
        return None

    def columns(self, ctx: DiagnosisContext) -> np.ndarray:
        """(M, 3, k): displacement (mm) of each measured point per internal unit of each parameter, in ``frame``."""
        raise NotImplementedError

    def variables(self, ctx: DiagnosisContext) -> list:
        """The recording columns the effect names as its cause, as the diagnosis's data-driven feature names (for
        example ``["T_x"]``, ``["dir_x"]``): an alternative explanation built from them is the effect in other words
        and is not held against it.  Default: none."""
        return []

    def alternatives(self, ctx: DiagnosisContext) -> list:
        """Physical explanations outside the library that could look like this effect, each a dict: ``name``,
        ``description``, ``separate`` (the measurement that tells them apart) and optionally ``columns`` ((M, 3, k) mm
        in ``frame``, or None for the same displacement of every point).  A finding that is not significant given one
        of them is reported as confounded with it, never named alone.  Default: none."""
        return []

    def perturbation(self, ctx: DiagnosisContext, beta: np.ndarray) -> dict | None:
        """Model perturbations (``MODEL_INPUTS`` keys) that put the effect into the full model at ``beta``
        (internal units), for the refit; None: the columns times ``beta`` as a displacement in ``frame``."""
        return None

    def implausible(self, beta: np.ndarray, cov: np.ndarray) -> str | None:
        """None when the fitted parameters are physically plausible, else what they would need (one sentence).

        The default checks every column against :attr:`plausible` (display units), allowing two
        standard uncertainties of slack: an estimate whose interval est +- 2u misses the range.
        """
        from .units import factor

        if not self.plausible:
            return None
        units = self.units()
        beta = np.atleast_1d(np.asarray(beta, float))
        u = np.sqrt(np.maximum(np.diag(np.atleast_2d(cov)), 0.0))
        for j in range(len(beta)):
            name, disp, internal = units[j] if len(units) == len(beta) else units[0]
            if name not in self.plausible:
                continue
            lo, hi = self.plausible[name]
            f = factor(internal, disp)
            est, unc = beta[j] * f, u[j] * abs(f)
            if est + 2 * unc < lo or est - 2 * unc > hi:
                what = self.quantity_names.get(name, f"a {name}")
                comp = f" (component {j + 1})" if len(units) != len(beta) else ""
                return (f"would need {what}{comp} of {est:.3g} {disp}; plausible is {lo:g} to {hi:g} {disp}")
        return None

    def summary(self, beta: np.ndarray, cov: np.ndarray) -> tuple[list, list, str] | None:
        """(estimates, standard uncertainties, display unit) of the fitted parameters ``beta`` with covariance ``cov``.

        The default gives every column in its parameter's display unit (all parameters must share
        one); override it for anything else (for example an RMS of several coefficients).
        """
        from .units import factor

        units = self.units()
        if len({disp for _, disp, _ in units}) != 1:
            raise ValueError(f"parameters in several display units ({', '.join(d for _, d, _ in units)}): "
                             "the candidate must override summary()")
        f = np.array([factor(i, d) for _, d, i in units]) if len(units) == len(beta) else factor(units[0][2], units[0][1])
        u = np.sqrt(np.maximum(np.diag(cov), 0.0))
        return [float(b) for b in beta * f], [float(s) for s in u * f], units[0][1]


@dataclass
class DiagnosisContext:
    """What a candidate may use (internal units): the recording and the baseline fitted to it."""

    recording: Recording
    model: MeasurementModel
    pose: np.ndarray  # (6,)
    theta: np.ndarray  # (p,)
    P_W: np.ndarray  # (M, 3) predicted machine-frame points of the baseline
    P_LT: np.ndarray  # (M, 3) predicted tracker points

    @property
    def plan(self):
        return self.recording.plan

    def axis_temperature_column(self, axis: str):
        """Temperature (K) of an axis at each point, or None when no sensor is attached to it."""
        sens = [s for s in self.plan.sensors if s.axis == axis and s.column in self.plan.temperature]
        if not sens:
            return None
        return self.plan.axis_temperature(axis, self.recording.reference_temperature)

    def air_temperature(self):
        cols = [s.column for s in self.plan.sensors if s.attached_to.strip().lower() == "air" and s.column in self.plan.temperature]
        if not cols:
            return None
        return np.mean([self.plan.temperature[c] for c in cols], axis=0)


# ----------------------------------------------------------------------------- compensation exporters
class Exporter:
    """Base class of a compensation-table exporter (hook ``mtbudget_register_exporters``).

    An exporter writes a :class:`mtbudget.compensate.CompensationTable` (the identified error
    functions, the per-axis positioning tables with their standard uncertainties) in one file
    format.  Subclasses set the class attributes below and implement :meth:`write`.

    name: unique across all plugins; what ``mtbudget compensate --format`` takes.
    description: one sentence for ``mtbudget plugins``.
    suffix: the file suffix the format uses (".csv", ".comp", ".lis").
    convention: where the format's conventions are documented (a citation: document, section,
        version): its grid, units, sign (what a positive entry does), behaviour beyond the
        table and backlash.  ``docs/compensation.md`` repeats it for the built-ins.
    per_axis: True when the format holds one axis per file: ``write`` then writes one file per
        axis, named by :meth:`axis_path`.
    max_entries: the most table entries per axis the controller accepts (None: no limit); the
        command refuses a grid step that would need more, before anything is written.
    """

    name: str = ""
    description: str = ""
    suffix: str = ""
    convention: str = ""
    per_axis: bool = False
    max_entries: int | None = None

    # stamped by the plugin host
    plugin: str = ""
    dist_name: str = ""
    dist_version: str = ""

    def axis_path(self, path, axis: str):
        """The file of one axis for a per-axis format: ``comp.txt`` -> ``comp_x.txt``."""
        from pathlib import Path

        path = Path(path)
        return path.with_name(f"{path.stem}_{axis}{path.suffix or self.suffix}")

    def write(self, table, path) -> list:
        """Write ``table`` (a :class:`mtbudget.compensate.CompensationTable`) to ``path``; return the paths written."""
        raise NotImplementedError
