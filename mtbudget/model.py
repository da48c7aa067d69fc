"""The measurement model: machine chain + tracker, shared by simulation, identification and diagnosis.

:class:`MeasurementModel` binds a kinematic configuration, an error model and
a plan.  Its :meth:`predict` maps (geometric parameters, tracker pose,
perturbations) to tracker coordinates for N trials at once; every
uncertainty source, every simulated effect and every diagnosis candidate
acts through one of the :data:`MODEL_INPUTS` below.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import tracker as lt
from .errors import ConfigError
from .machine import (AXES, AXIS_INDEX, ROTARY, ROTARY_INDEX, ChainInputs, Configuration, ErrorModel, broadcast_shape,
                      chain, is_rotary, parse_error_name)
from .plan import Plan, Scale

# ----------------------------------------------------------------------------- ISO 230-1 names (the one map)
#: internal rotation letter -> ISO 230-1 rotation letter (A, B, C about X, Y, Z)
_ROTATION = {"x": "A", "y": "B", "z": "C"}
#: squareness: internal name -> (ISO 230-1 name, sign of ISO value / internal value, meaning of a positive value).
#: The long form names the reference axis in brackets: EC(0X)Y is the orientation about Z of the Y axis' reference
#: line relative to X (short form EC0Y).
SQUARENESS_ISO = {
    "sxy": ("EC(0X)Y", 1.0, "the angle between the +X and +Y motions exceeds 90 degrees (Y turned about +Z)"),
    "sxz": ("EB(0X)Z", -1.0, "the angle between the +X and +Z motions is below 90 degrees (Z turned about +Y)"),
    "syz": ("EA(0Y)Z", 1.0, "the angle between the +Y and +Z motions exceeds 90 degrees (Z turned about +X)"),
}


def iso_name(internal: str) -> str:
    """ISO 230-1 name of a component error: ``dy(x)`` -> ``EYX``, ``ez(y)`` -> ``ECY`` (yaw of Y), ``sxy`` -> ``EC(0X)Y``.

    ``E`` + the direction of the error (X, Y, Z for a translation, A, B, C for a rotation about X, Y, Z)
    + the moving axis.  The one map of mtbudget's names onto ISO 230-1's (docs/compensation.md).  A rotary
    axis' error motions likewise: ``dx(c)`` -> ``EXC`` (radial motion of C along X), ``ez(c)`` -> ``ECC``.
    """
    if internal in SQUARENESS_ISO:
        return SQUARENESS_ISO[internal][0]
    kind, comp, axis = parse_error_name(internal)
    return "E" + (comp.upper() if kind == "d" else _ROTATION[comp]) + axis.upper()


def iso_parameter(name: str) -> str:
    """ISO 230-1 name of a model parameter: ``dy(x)[P2]`` -> ``EYX[P2]``, ``sxy`` -> ``EC(0X)Y``; a rotary axis'
    location and zero errors by their ISO 230-7 names (``dx(c)[O]`` -> ``EXOC``, ``ez(c)[O]`` -> ``ECOC``) and its
    Fourier terms as ``EXC[c2]``; others unchanged."""
    base, sep, rest = name.partition("[")
    try:
        iso = iso_name(base)
    except ConfigError:  # not a component error (pose, a plugin's parameter): keep its own name
        return name
    if rest == "O]" and is_rotary(base[3]):
        return iso[:2] + "O" + iso[2:]
    return iso + sep + rest


def rotary_direction(letter: str, text) -> tuple:
    """A rotary axis' stated direction (recording.toml's and a configuration's ``[rotary.X] direction``): (sign, None),
    or (None, why it is refused) when it is not "+x"/"-x" for A, "+y"/"-y" for B, "+z"/"-z" for C."""
    want = AXES[ROTARY_INDEX[letter]]
    if not isinstance(text, str) or text.strip().lower() not in (f"+{want}", f"-{want}", want):
        A = letter.upper()
        return None, (f"{text!r:.40} does not match axis {A}: {A} turns about {want.upper()}, so its direction is "
                      f"\"+{want}\" or \"-{want}\"")
    return (-1.0 if text.strip().startswith("-") else 1.0), None


def one_angle_only(letter: str, angles) -> tuple | None:
    """(the angle in deg, the ISO names of the location and zero errors it loses) when a rotary axis is commanded to
    one angle only (modulo a turn): those errors then act as a rigid motion of the tracker; None otherwise."""
    from .machine import rotary_location_parameters

    turns = np.unique(np.round(np.mod(np.asarray(angles, float), 2 * np.pi), 9) % np.round(2 * np.pi, 9))
    if turns.size >= 2:
        return None
    return float(np.degrees(turns[0])), ", ".join(iso_parameter(q) for q in rotary_location_parameters(letter))


def parameter_from_iso(text: str) -> str | None:
    """The internal name of an ISO 230-1/230-7 parameter name (``EXOC`` -> ``dx(c)[O]``; ``E0C``-style zeros read as
    letter O too), or None."""
    t = str(text).strip()
    if len(t) == 4 and t[0].upper() == "E" and t[2] in "O0" and t[3].lower() in ROTARY_INDEX:
        d, ax = t[1].upper(), t[3].lower()
        comp = {"X": "dx", "Y": "dy", "Z": "dz", "A": "ex", "B": "ey", "C": "ez"}.get(d)
        return None if comp is None else f"{comp}({ax})[O]"
    return None

#: every model input a perturbation may target: key -> (internal unit, shape after the trial axis)
#: ("M" is the number of measured points, "p" the number of geometric parameters)
MODEL_INPUTS = {
    "axis_offset.x": ("mm", ("M",)),
    "axis_offset.y": ("mm", ("M",)),
    "axis_offset.z": ("mm", ("M",)),
    "axis_offset.a": ("rad", ("M",)),  # rotary axes (five-axis machines): added to the commanded angle
    "axis_offset.b": ("rad", ("M",)),
    "axis_offset.c": ("rad", ("M",)),
    "axis_scale.x": ("", ("M",)),
    "axis_scale.y": ("", ("M",)),
    "axis_scale.z": ("", ("M",)),
    "geometry": ("", ("p",)),  # parameter vector in mm / rad, see ErrorModel.params
    "pose": ("", (6,)),  # D, L, H (mm), a, b, d (rad)
    "point_offset": ("mm", ("M", 3)),  # machine (workpiece) frame
    "tracker_offset": ("mm", ("M", 3)),  # tracker frame
    "spherical_noise": ("", ("M", 3)),  # range (mm), azimuth (rad), elevation (rad)
}


@dataclass
class MeasurementModel:
    config: Configuration
    errors: ErrorModel
    plan: Plan

    def __post_init__(self):
        self.inputs = ChainInputs(self.plan.nominal, self.plan.tool, angles=self.plan.angles)
        self.B = self.errors.basis(self.plan.nominal, self.plan.angles)

    @classmethod
    def for_plan(cls, machine: str, plan: Plan, max_degree: int = 3, **kw) -> "MeasurementModel":
        """The model of ``machine`` (a code; a five-axis machine's rotary geometry comes with the plan,
        ``plan.rotary``) with the default error model of the plan."""
        config = Configuration.parse(machine, plan.rotary or None)
        kw.setdefault("tool_axis", config.tool[-1] if config.tool else None)
        if config.rotary:
            kw.setdefault("angles", plan.angles)
        return cls(config, ErrorModel.default(plan.nominal, max_degree=max_degree, **kw), plan)

    @property
    def rotary(self) -> bool:
        """Whether the machine has rotary axes."""
        return bool(self.config.rotary)

    @property
    def n_points(self) -> int:
        return len(self.plan)

    @property
    def n_params(self) -> int:
        return len(self.errors.params)

    def shape_of(self, key: str) -> tuple:
        unit, shape = MODEL_INPUTS[key]
        return tuple(self.n_points if s == "M" else self.n_params if s == "p" else s for s in shape)

    def machine_points(self, theta, perturbations: dict | None = None, *, exact=False, jacobian=False, project=None):
        """Tool points in the workpiece frame (N, M, 3) (and dP_W/dtheta, optionally times ``project``)."""
        pert = perturbations or {}
        theta = np.atleast_2d(np.asarray(theta, float))
        if "geometry" in pert:
            theta = theta + pert["geometry"]
        inp = self.chain_inputs(pert)
        out = chain(self.config, self.errors, theta, inp, exact=exact, jacobian=jacobian, B=self.B, project=project)
        if "point_offset" in pert:
            if jacobian:
                out = (out[0] + pert["point_offset"], out[1])
            else:
                out = _plus(out, pert["point_offset"])
        return out

    def chain_inputs(self, perturbations: dict | None = None) -> ChainInputs:
        """The chain's per-point inputs with the perturbations' axis offsets and scales (``geometry`` and
        ``point_offset`` are added by :meth:`machine_points`)."""
        pert = perturbations or {}
        return ChainInputs(
            self.plan.nominal, self.plan.tool,
            offset={a: pert[f"axis_offset.{a}"] for a in AXES + ROTARY if f"axis_offset.{a}" in pert},
            scale={a: pert[f"axis_scale.{a}"] for a in AXES if f"axis_scale.{a}" in pert},
            angles=self.plan.angles,
        )

    def predict(self, theta, pose, perturbations: dict | None = None, *, exact=False) -> np.ndarray:
        """Tracker coordinates (N, M, 3) of every point."""
        pert = perturbations or {}
        pose = np.atleast_2d(np.asarray(pose, float))
        if "pose" in pert:
            pose = pose + pert["pose"]
        P = lt.read(self.machine_points(theta, pert, exact=exact), pose, pert.get("spherical_noise"))
        if "tracker_offset" in pert:
            P = _plus(P, pert["tracker_offset"])
        return P

    def covariance(self, P_LT, angular, distance, distance_per_length, repeatability) -> np.ndarray:
        """Per-point covariance (…, M, 3, 3) in the tracker frame: tracker noise + machine repeatability."""
        C = lt.covariance(P_LT, angular, distance, distance_per_length)
        return C + (np.asarray(repeatability) ** 2)[..., None, None] * np.eye(3)


def _plus(a: np.ndarray, b) -> np.ndarray:
    """``a + b`` for an array ``a`` the caller made and no one else holds: added in place when the sum has its shape
    and type (the same numbers, no new array), else a new one."""
    b = np.asarray(b)
    if a.dtype == np.float64 and b.dtype == np.float64 and a.flags.writeable and broadcast_shape(a.shape, b.shape) == a.shape:
        a += b
        return a
    return a + b


def thermal_scale(plan: Plan, cte: dict, reference: float, fixed_point: dict | None = None) -> dict:
    """``axis_scale`` (and ``axis_offset``) perturbations of a thermal expansion ``{axis: CTE (1/K)}`` about each
    axis' ``fixed_point`` (mm, default the axis zero): :meth:`Plan.expansion`, one trial."""
    scales = {a: Scale(c, (fixed_point or {}).get(a, 0.0)) for a, c in cte.items() if c}
    return {k: v[None, :] for k, v in plan.expansion(scales, reference).items()}


def reversal_offset(plan: Plan, reversal: dict) -> dict:
    """``axis_offset`` of a reversal ``{axis: B (mm)}``: the axis stops B/2 short of its target."""
    return {f"axis_offset.{a}": (-plan.direction_of(a) * b / 2.0)[None, :] for a, b in reversal.items() if b}


def between_runs_columns(plan: Plan, axis: str) -> np.ndarray | None:
    """Columns (M, 3, runs - 1) of "anything that changes along ``axis`` between the plan's runs": one offset per run
    after the first (an indicator of its points along the axis), the alternative a diagnosis weighs against an
    effect that follows the approach direction (the runs alternate it with time); None with fewer than two runs."""
    runs = np.unique(plan.run)
    if len(runs) < 2:
        return None
    C = np.stack([(plan.run == k).astype(float) for k in runs[1:]], axis=1)  # (M, runs - 1)
    e = np.zeros(3)
    e[AXIS_INDEX[axis]] = 1.0
    return C[:, None, :] * e[None, :, None]


def drift_offset(plan: Plan, velocity) -> dict:
    """``point_offset`` of an apparent drift velocity (mm/s) in the machine frame."""
    v = np.asarray(velocity, float)
    return {"point_offset": (plan.time[:, None] * v[None, :])[None]}


def from_targets(arrays: dict) -> dict:
    """Model perturbations from source targets (internal float arrays keyed as in ``sources.TARGETS``).

    Sums what several sources contribute to one input; joins the split keys
    (geometry, pose, spherical noise) into the model's own: each part in its
    columns and zeros elsewhere, the two parts' sum where both are given
    (``x + 0.0`` in each column, written in place of two padded arrays and
    their sum: the same numbers).
    """
    out: dict = {}
    joined: dict = {}  # pose, spherical_noise -> [(columns, array)], filled in below at the place of its first part

    def add(k, v):
        out[k] = out[k] + v if k in out else v

    for key, v in arrays.items():
        if key in ("geometry.translational", "geometry.angular"):
            add("geometry", v)
        elif key in _JOINED:
            k, cols = _JOINED[key]
            if k not in joined:
                out[k] = None  # its place among the inputs
                joined[k] = []
            joined[k].append((cols, v))
        elif key == "strategy":
            continue
        else:
            add(key, v)
    for k, parts in joined.items():
        cols, v = parts[0]
        shape = (v.shape if isinstance(cols, int) else v.shape[:-1]) + (_JOINED_WIDTH[k],)
        if len(parts) == 1:  # the part in its columns, zeros in the others
            arr = np.zeros(shape)
            arr[..., cols] = v
        else:  # both parts: each plus the other's zeros
            arr = np.empty(shape)
            for cols, v in parts:
                np.add(v, 0.0, out=arr[..., cols])
        out[k] = arr
    return out


#: a split target -> (the model input it joins, its columns there: an index for a part without a last axis)
_JOINED = {"pose.position": ("pose", slice(0, 3)), "pose.orientation": ("pose", slice(3, 6)),
           "spherical_noise.range": ("spherical_noise", 0), "spherical_noise.angles": ("spherical_noise", slice(1, 3))}
_JOINED_WIDTH = {"pose": 6, "spherical_noise": 3}


def merge(*perts: dict) -> dict:
    """Sum perturbation dictionaries key by key (broadcasting over trials)."""
    out: dict = {}
    for p in perts:
        for k, v in p.items():
            if k not in MODEL_INPUTS:
                raise ConfigError(f"unknown model input {k!r}; expected one of {', '.join(MODEL_INPUTS)}")
            out[k] = out[k] + v if k in out else v
    return out
