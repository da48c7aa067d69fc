"""From verification to compensation: identified errors -> tables, ISO 230-1 names, ISO 230-2 figures.

:func:`build_table` identifies a recording (exactly like ``mtbudget identify``) and samples
what a controller or a report needs on a grid the user sets:

* every identified error function under its ISO 230-1 name (``EXX``, ``EYX``, ... and the
  squareness errors ``EC(0X)Y``, ``EB(0X)Z``, ``EA(0Y)Z``), in the ISO sign convention (the
  tool relative to the workpiece), with the standard uncertainty of each entry from the
  identification covariance: ``cov(f) = B cov_theta B^T`` through the Legendre basis ``B``;
* per axis, the positioning deviation along the axis on a reference line (the other axes at the
  centre of their measured range, the plan's first tool), from the kinematic chain (so the
  Abbe effect of the angular errors on that line is in it), zero at the axis' reference point,
  with its standard uncertainty ``(J - J_0) cov_theta (J - J_0)^T``; and the mean reversal
  value of the axis (ISO 230-2 ``B``, from the recording's bidirectional approaches), which the
  directional controller tables carry;
* ISO 230-2 figures per axis (A, E, M, R, B, unidirectional and bidirectional) from the
  recording's approaches and from the identified model.

Exporters (plugins, hook ``mtbudget_register_exporters``) write a table in one format.
:func:`check_export` reads the written files back with the readers of this module (written from
the formats' documentation, independently of the exporters) and applies them to the simulated
machine of a recording's ``truth.json``: the positioning error left after compensation on each
axis line, against the uncertainty the table states.  See docs/compensation.md.
"""

from __future__ import annotations

import difflib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import MtbudgetError, make_folder
from .machine import AXES, AXIS_INDEX, COMPONENT_ERRORS, ChainInputs, Configuration, chain, parse_error_name
from .model import SQUARENESS_ISO, iso_name, iso_parameter  # noqa: F401  (the one map lives in model; re-exported)

DEFAULT_STEP_MM = 50.0
MAX_GRID = 100_000  # entries per axis of the neutral table (controller limits are the exporters')
MODEL_DRAWS = 4000  # Monte Carlo draws over cov_theta for the uncertainty of the model's E, M, A
MAX_ROUNDING_UM = 0.1  # --check: a read-back entry further than this from the table is a mismatch, not a rounding
GRID_RESOLUTION_MM = 1e-3  # grid positions and steps are whole micrometres, so a printed MIN + N STEP = MAX exactly
STATED_COVERAGE = 0.95  # --check: at least this fraction of a line's points within 2u (k = 2) or it is under-covered
#: sources of a simulated recording whose effect a table's u contains or that do not act on the table: the stated noise
#: (tracker_noise, repeatability: the identification's weights and covariance), the tracker pose (registration: an
#: unknown of the identification), the machine itself (geometric_error_uncertainty: truth.json holds the trial's
#: machine) and the Monte Carlo's own identification settings (compensate identifies with its own).  Any other source
#: a simulation drew is physics the identification does not model: --check names it (``not_in_u``)
IN_TABLE_U = frozenset({"tracker_noise", "repeatability", "registration", "geometric_error_uncertainty",
                        "convergence_criteria", "phase_sequence"})

CONVENTIONS = {
    "names": "ISO 230-1: E<error direction><axis>: EXX positioning of X, EYX/EZX straightness of X in Y/Z, "
             "EAX/EBX/ECX rotations of X about X (roll), Y, Z; EC(0X)Y, EB(0X)Z, EA(0Y)Z squareness",
    "sign": "error = actual - nominal, of the tool relative to the workpiece (ISO 230-1 / ISO 230-2); "
            "a compensation subtracts it. For an axis that moves the workpiece this is minus mtbudget's "
            "carriage error (dx(x) -> EXX = -dx(x) on XFYZ)",
    "units": "lengths in um, angles in urad, positions in mm",
    "error_functions": "Legendre P1..Pn of the axis position over the measured range, no constant term "
                       "(a constant is a rigid-body offset no verification sees); straightness without its "
                       "linear term (ISO 230-1: straightness about a reference line whose slope is squareness); "
                       "the angular errors of the axis carrying the tool include a constant P0 (tool-holder tilt)",
    "positioning": "per axis, the deviation along the axis on the reference line (other axes at the centre of "
                   "their range, the plan's first tool), from the kinematic chain (Abbe effects on that line "
                   "included), zero at the axis' reference point (--reference, default the machine zero 0 mm; a "
                   "reference point outside the table: zero at the nearest end, whose value the controller holds "
                   "there); forward = approach in the + direction",
    "reversal": "ISO 230-2 reversal value B = mean deviation approaching in + minus in -, averaged over the "
                "targets of the recording; forward = mean + B/2, reverse = mean - B/2",
    "uncertainty": "standard uncertainty (k = 1): identification covariance through the basis "
                   "(B cov B^T) or the chain Jacobian on the line relative to the datum ((J - J0) cov (J - J0)^T); "
                   "directional entries add u(B)/2 in quadrature; empty where the plan cannot identify the function. "
                   "It is the identification's covariance from the recording's stated tracker noise and repeatability: "
                   "it shrinks as 1/sqrt(points) and does not contain what the identification does not model (a "
                   "reversal on a plan approaching from one side, temperatures drifting without [scales] or beyond "
                   "them, reflector centring ...: docs/compensation.md). Between two entries the controller "
                   "interpolates linearly: the identified line's deviation from that chord (largest per table: "
                   "interpolation_um) is left there besides u; a finer --step reduces it",
}


class CompensationError(MtbudgetError, ValueError):
    """A compensation request that cannot be met (format, step, recording): one line, what to do."""


# ----------------------------------------------------------------------------- ISO 230-1 names
def iso_kind(internal: str) -> str:
    kind, comp, axis = parse_error_name(internal)
    if kind == "e":
        return "angular"
    return "positioning" if comp == axis else "straightness"


def iso_sign(config: Configuration, axis: str) -> float:
    """ISO value / mtbudget value of a component error of ``axis``: -1 when the axis moves the workpiece."""
    return float(config.side(axis))


# ----------------------------------------------------------------------------- the table
@dataclass
class ErrorFunction:
    """One error function sampled on its axis' grid (display units)."""

    iso: str
    internal: str
    axis: str
    kind: str  # positioning, straightness, angular
    unit: str  # um or urad
    positions: np.ndarray  # mm
    value: np.ndarray
    u: np.ndarray  # NaN where not identifiable
    identifiable: bool = True


@dataclass
class Squareness:
    iso: str
    internal: str
    value: float  # urad
    u: float
    meaning: str
    identifiable: bool = True


@dataclass
class Iso230_2:
    """ISO 230-2 figures of one axis from a set of approaches (um)."""

    axis: str
    source: str  # "recording", "model", "compensated"
    targets: np.ndarray  # (m,) mm
    n_up: np.ndarray
    n_down: np.ndarray
    mean_up: np.ndarray
    mean_down: np.ndarray
    s_up: np.ndarray
    s_down: np.ndarray
    figures: dict  # A_up, A_down, A, E_up, E_down, E, M, R_up, R_down, R, B, B_mean
    uncertainty: dict = field(default_factory=dict)  # figure -> standard uncertainty (model figures)
    note: str = ""

    @property
    def reversal(self):
        return self.mean_up - self.mean_down

    @property
    def mean_bidirectional(self):
        return 0.5 * (self.mean_up + self.mean_down)

    def to_dict(self) -> dict:
        d = {"axis": self.axis, "source": self.source, "unit": "um", "targets_mm": self.targets.tolist(),
             "n_up": self.n_up.tolist(), "n_down": self.n_down.tolist(),
             "mean_up": _list(self.mean_up), "mean_down": _list(self.mean_down),
             "s_up": _list(self.s_up), "s_down": _list(self.s_down), "reversal": _list(self.reversal),
             "figures": {k: _num(v) for k, v in self.figures.items()}}
        if self.uncertainty:
            d["uncertainty"] = {k: _num(v) for k, v in self.uncertainty.items()}
        if self.note:
            d["note"] = self.note
        return d


@dataclass
class AxisTable:
    """The positioning table of one axis (um, positions in mm), zero at the axis' reference point (``zero_at``)."""

    axis: str
    positions: np.ndarray
    deviation: np.ndarray  # mean bidirectional deviation along the axis on the reference line
    u: np.ndarray
    reversal: float  # ISO 230-2 mean reversal value B (x_up - x_down), um
    u_reversal: float
    reversal_source: str
    reference: dict  # other axis -> mm
    tool: np.ndarray  # (3,) mm
    note: str = ""
    zero_at: float = float("nan")  # mm: where the table is zero (the reference point, clamped to the table)
    #: um: the largest deviation of the identified line from the chord between two entries (the controller interpolates
    #: linearly): what the table leaves between its entries besides its u, reduced by a finer --step
    interpolation: float = 0.0

    @property
    def forward(self):
        """Deviation approaching in the + direction (ISO 230-2 up arrow)."""
        return self.deviation + 0.5 * self.reversal

    @property
    def reverse(self):
        return self.deviation - 0.5 * self.reversal

    @property
    def u_directional(self):
        return np.sqrt(self.u**2 + (0.5 * self.u_reversal) ** 2)


@dataclass
class CrossTable:
    """Deviation of the line of ``axis`` in the direction of ``output`` (um), zero at ``axis``' reference point.

    ISO sign (tool relative to workpiece, actual - nominal); through the chain, so straightness, squareness
    (X the reference) and the Abbe effect of the angular errors on that line are in it.  What a sag / cross
    compensation table (Siemens $AN_CEC, Heidenhain .COM columns) carries."""

    iso: str  # EYX: deviation in Y along the X line
    axis: str  # input (base) axis
    output: str  # compensated axis
    positions: np.ndarray
    deviation: np.ndarray
    u: np.ndarray
    note: str = ""
    interpolation: float = 0.0  # um, as AxisTable.interpolation


@dataclass
class ResidualAxis:
    """The compensated machine at the recording's points, one axis: residual against its stated U (k = 2).

    residual = measured - identified model (machine frame, um): the fit residual at the recording's own points,
    the error the identified model leaves there, measurement noise included.  U = 2 u(residual), u from the
    recording's stated tracker noise and repeatability net of the part the fit absorbs,
    u^2 = diag(R L (I - H_ii) L^T R^T), H the hat matrix.  It is not the reading of a new verification of the
    compensated machine (whose noise is fresh: C (I + H)), nor the machine after the exported tables, which
    carry the error functions on the reference lines only (that is what ``--check`` tests)."""

    axis: str
    positions: np.ndarray  # (M,) mm, commanded position along this axis
    residual: np.ndarray  # (M,) um
    U: np.ndarray  # (M,) um, k = 2

    def summary(self) -> dict:
        r, U = self.residual, self.U
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.abs(r) / U
        return {"axis": self.axis, "points": int(r.size), "unit": "um", "k": 2.0,
                "rms_residual": float(np.sqrt(np.mean(r**2))), "max_abs_residual": float(np.abs(r).max()),
                "median_U": float(np.median(U)), "max_U": float(U.max()), "max_abs_residual_over_U": float(np.nanmax(z)),
                "within_U": float(np.mean(np.abs(r) <= U)),
                "expected_within_U": 0.9545}


@dataclass
class CompensationTable:
    recording: str
    machine: str
    step: float  # mm (the largest step asked for; each axis' own spacing is positions[1] - positions[0])
    functions: list
    squareness: list
    axes: dict  # axis -> AxisTable
    iso230_2: dict  # axis -> {"recording": Iso230_2 | None, "model": Iso230_2}
    identification: dict  # chi2_per_dof, dof, points, converged, not_identifiable
    conventions: dict = field(default_factory=lambda: dict(CONVENTIONS))
    notes: list = field(default_factory=list)
    cross: dict = field(default_factory=dict)  # ISO name (EYX ...) -> CrossTable
    reference_point: dict = field(default_factory=dict)  # axis -> mm, where the tables are zero (as asked)
    options: dict = field(default_factory=dict)  # exporter options (siemens_cec_sign ...), docs/compensation.md
    residual: dict = field(default_factory=dict)  # axis -> ResidualAxis (the compensated machine at the recording)
    #: five-axis: the rotary axes' location and zero errors (ISO 230-7) with u (k = 1); held ones by the datum
    rotary: list = field(default_factory=list)
    # the identification behind the table (internal units: mm, rad), for the check and for propagation
    model: object = field(default=None, repr=False)
    theta: np.ndarray | None = field(default=None, repr=False)
    cov_theta: np.ndarray | None = field(default=None, repr=False)

    def function(self, iso: str) -> ErrorFunction:
        for f in self.functions:
            if f.iso == iso:
                return f
        raise KeyError(iso)

    def to_dict(self) -> dict:
        return {
            "format": "mtbudget-compensation/1",
            "recording": self.recording,
            "machine": self.machine,
            "grid_step_mm": self.step,
            "reference_point_mm": self.reference_point,
            "conventions": self.conventions,
            "identification": self.identification,
            "iso230_1_names": {f.internal: f.iso for f in self.functions} | {s.internal: s.iso for s in self.squareness},
            "error_functions": [
                {"iso": f.iso, "mtbudget": f.internal, "axis": f.axis, "kind": f.kind, "unit": f.unit,
                 "identifiable": f.identifiable, "positions_mm": f.positions.tolist(), "value": _list(f.value),
                 "u": _list(f.u)} for f in self.functions],
            "squareness": [{"iso": s.iso, "mtbudget": s.internal, "unit": "urad", "value": _num(s.value), "u": _num(s.u),
                            "identifiable": s.identifiable, "positive_means": s.meaning} for s in self.squareness],
            "positioning": {a: {"unit": "um", "positions_mm": t.positions.tolist(), "mean": _list(t.deviation),
                                "u": _list(t.u), "forward": _list(t.forward), "reverse": _list(t.reverse),
                                "u_directional": _list(t.u_directional), "reversal_B": _num(t.reversal),
                                "u_reversal_B": _num(t.u_reversal), "reversal_source": t.reversal_source,
                                "reference_mm": t.reference, "zero_at_mm": t.zero_at, "tool_mm": t.tool.tolist(),
                                "interpolation_um": _num(t.interpolation), "note": t.note}
                            for a, t in self.axes.items()},
            "iso230_2": {a: {k: (v.to_dict() if v is not None else None) for k, v in d.items()}
                         for a, d in self.iso230_2.items()},
            "cross": {k: {"iso": c.iso, "input_axis": c.axis, "output_axis": c.output, "unit": "um",
                          "positions_mm": c.positions.tolist(), "deviation": _list(c.deviation), "u": _list(c.u),
                          "interpolation_um": _num(c.interpolation), "note": c.note} for k, c in self.cross.items()},
            "residual_against_U": {
                "what": "residual = measured - identified model at the recording's points (machine frame), against "
                        "U = 2 u of that residual from the stated tracker noise and repeatability (k = 2, about 95 %)",
                "axes": {a: r.summary() for a, r in self.residual.items()}},
            **({"rotary_location_errors": {
                "what": "each rotary axis' location and zero errors (ISO 230-7), in its carrier's frame (the machine "
                        "frame with every axis at zero): the offsets of its average line (um) and its orientation and "
                        "zero errors (urad, rotations about +X, +Y, +Z); u is the standard uncertainty (k = 1); a "
                        "parameter held by the datum is 0 with no u (docs/model.md)",
                "values": self.rotary}} if self.rotary else {}),
            "notes": self.notes,
        }


def _num(v):
    v = float(v)
    return None if not np.isfinite(v) else v


def _list(a):
    return [_num(v) for v in np.asarray(a, float)]


# ----------------------------------------------------------------------------- ISO 230-2
def iso230_2(axis: str, targets, direction, deviation, *, source: str = "recording", s=None,
             min_approaches: int = 2) -> Iso230_2:
    """ISO 230-2 figures from approaches: target position (mm), direction (+1 up, -1 down), deviation (um).

    Statistics are per target position i and per direction, over that target's approaches j
    in that direction only (never across targets, never mixing the directions):
    mean x_i(up), x_i(down); s_i (n - 1 in the denominator); B_i = x_i(up) - x_i(down);
    x_i = (x_i(up) + x_i(down)) / 2; R_i(up) = 4 s_i(up); R_i = max(2 s_i(up) + 2 s_i(down) + |B_i|,
    R_i(up), R_i(down)); E(up) = max x_i(up) - min x_i(up); E = max over both - min over both;
    M = max x_i - min x_i; A(up) = max(x_i(up) + 2 s_i(up)) - min(x_i(up) - 2 s_i(up));
    A over both directions; R = max R_i; B = max |B_i|; B_mean = mean B_i.
    ``s`` replaces the sample standard deviations by one stated value (the model's figures).
    """
    targets = np.asarray(targets, float)
    direction = np.asarray(direction)
    deviation = np.asarray(deviation, float)
    keys = np.round(targets, 6)
    uniq = np.unique(keys)
    m = len(uniq)
    n_up, n_down = np.zeros(m, int), np.zeros(m, int)
    mu, md, su, sd = (np.full(m, np.nan) for _ in range(4))
    for i, t in enumerate(uniq):
        at = keys == t
        up, down = deviation[at & (direction > 0)], deviation[at & (direction < 0)]
        n_up[i], n_down[i] = len(up), len(down)
        if len(up):
            mu[i] = up.mean()
            su[i] = up.std(ddof=1) if len(up) > 1 else np.nan
        if len(down):
            md[i] = down.mean()
            sd[i] = down.std(ddof=1) if len(down) > 1 else np.nan
    if s is not None:
        su[:] = s
        sd[:] = s
    need = 1 if s is not None else min_approaches
    keep = np.minimum(n_up, n_down) >= need
    missing = [f"{t:g} mm" for t, k in zip(uniq, keep) if not k]
    res = Iso230_2(axis, source, uniq[keep], n_up[keep], n_down[keep], mu[keep], md[keep], su[keep], sd[keep], {})
    if missing:
        res.note = (f"{len(missing)} of {m} targets left out, fewer than {need} approaches from a side "
                    f"({', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''})")
    if keep.sum() < 2:
        res.note = "not bidirectional: fewer than two targets approached from both sides" + \
            (f"; {res.note}" if res.note else "")
        return res
    mu, md, su, sd = mu[keep], md[keep], su[keep], sd[keep]
    Bi = mu - md
    xi = 0.5 * (mu + md)
    Rup, Rdn = 4 * su, 4 * sd
    Ri = np.maximum(2 * su + 2 * sd + np.abs(Bi), np.maximum(Rup, Rdn))
    both_hi = np.concatenate([mu + 2 * su, md + 2 * sd])
    both_lo = np.concatenate([mu - 2 * su, md - 2 * sd])
    res.figures = {
        "A_up": float(np.max(mu + 2 * su) - np.min(mu - 2 * su)),
        "A_down": float(np.max(md + 2 * sd) - np.min(md - 2 * sd)),
        "A": float(both_hi.max() - both_lo.min()),
        "E_up": float(np.ptp(mu)),
        "E_down": float(np.ptp(md)),
        "E": float(max(mu.max(), md.max()) - min(mu.min(), md.min())),
        "M": float(np.ptp(xi)),
        "R_up": float(Rup.max()),
        "R_down": float(Rdn.max()),
        "R": float(Ri.max()),
        "B": float(np.max(np.abs(Bi))),
        "B_mean": float(Bi.mean()),
    }
    return res


def _reversal_estimate(r: Iso230_2) -> tuple[float, float]:
    """Mean reversal value and its standard uncertainty (targets independent) from a recording's figures."""
    if not r.figures:
        return 0.0, 0.0
    Bi = r.reversal
    var = r.s_up**2 / r.n_up + r.s_down**2 / r.n_down
    return float(Bi.mean()), float(np.sqrt(var.sum()) / len(Bi))


# ----------------------------------------------------------------------------- building blocks
def identify_recording(rec, max_degree: int = 3, strategy: str = "one-phase"):
    """(model, identification) of one recording, as ``mtbudget identify`` does it: corrected to the reference
    temperature where the recording states its scales' nominal expansion (``Recording.fixed_inputs``)."""
    from .identify import Noise, Strategy, identify
    from .model import MeasurementModel

    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree)
    strat = Strategy.one_phase() if strategy == "one-phase" else Strategy.multi_phase()
    return model, identify(model, rec.lt, Noise.of(rec), strat, fixed=rec.fixed_inputs())


def refuse_implausible(rec, res) -> None:
    """Refuse, in one line, an identification no machine tool can give (``identify.implausible``: a chi-square per
    dof, an error function or a pose-only error beyond what a machine shows): a controller table is never written
    from one.  The line names the worst figure (and the next) and what to check."""
    from .identify import implausible

    problems = implausible(res)
    if problems:
        more = f"; also {problems[1]}" if len(problems) > 1 else ""
        raise CompensationError(f"{rec.path or rec.name}: not an identification of the machine, no table is written: "
                                f"{problems[0]}{more}; check the recording's units (the column headers of points.csv), "
                                "its stated noise ([tracker], [machine_tool]) and the machine code")


def parse_step(text) -> float:
    """The grid step in mm from a quantity such as "50 mm"; a one-line error otherwise."""
    from .units import to_internal

    step = to_internal(text, "mm", where="--step", error=CompensationError)
    if not np.ndim(step) == 0 or not step > 0:
        raise CompensationError(f"--step: {text!r} must be one positive length, for example \"50 mm\"")
    return float(step)


def grid(lo: float, hi: float, step: float) -> np.ndarray:
    """Equidistant points covering lo..hi, spaced at most ``step``, on whole micrometres.

    n = ceil((hi - lo) / step) equal intervals; their spacing is (hi - lo) / n rounded up to a whole micrometre and
    the first point is lo rounded down to one, so every position and the spacing have at most three decimals in mm:
    printed with three decimals, MIN + n STEP = MAX holds exactly (the equidistant controller tables, Siemens
    ``$AA_ENC_COMP_STEP`` and ``$AN_CEC_STEP``, need (MAX - MIN) / STEP to be an integer).  The last point lies at
    most n um beyond hi."""
    if not step > 0:
        raise CompensationError(f"grid step must be positive, got {step} mm")
    n = max(1, int(np.ceil((hi - lo) / step - 1e-9)))
    if n + 1 > MAX_GRID:
        raise CompensationError(f"a step of {step:g} mm gives {n + 1} points over {hi - lo:g} mm; at most {MAX_GRID}")
    um = round(1.0 / GRID_RESOLUTION_MM)
    start = int(np.floor(lo * um + 1e-6))
    spacing = max(1, int(np.ceil((hi * um - start) / n - 1e-6)))
    return (start + spacing * np.arange(n + 1)) / um


def chain_inputs(config, pts, tool, offset=None) -> ChainInputs:
    """The chain's inputs on a line of the linear axes; a five-axis machine's rotary axes at their zero angle (the
    tables of the linear axes are those of the machine with every rotary axis at zero)."""
    M = len(pts)
    return ChainInputs(pts, tool, offset=offset or {}, angles={r: np.zeros(M) for r in config.rotary_letters})


def line_points(axis: str, positions, reference: dict) -> np.ndarray:
    pts = np.zeros((len(positions), 3))
    for b in AXES:
        pts[:, AXIS_INDEX[b]] = positions if b == axis else reference[b]
    return pts


def line_deviation(config, errors, theta, cov, axis: str, positions, reference: dict, tool, datum=None,
                   component: str | None = None):
    """Deviation along ``component`` (default: ``axis``) on the line of ``axis`` (mm), relative to ``datum``
    (default: the first position).

    Returns (e (G,), u (G,), D (G, p)): e = [P_W(theta) - P_W(0)]_component minus its value at the datum,
    D its Jacobian with respect to theta (relative to the datum), u = sqrt(diag(D cov D^T)).
    """
    positions = np.asarray(positions, float)
    datum = positions[0] if datum is None else float(datum)
    pos = np.concatenate([[datum], positions])
    pts = line_points(axis, pos, reference)
    inp = chain_inputs(config, pts, np.broadcast_to(np.asarray(tool, float), pts.shape).copy())
    P, J = chain(config, errors, np.asarray(theta, float)[None], inp, jacobian=True)
    P0 = chain(config, errors, np.zeros((1, len(errors.params))), inp)
    k = AXIS_INDEX[component or axis]
    e = (P - P0)[0, :, k]
    D = J[0, :, k, :]
    e, D = e[1:] - e[0], D[1:] - D[0]
    u = np.sqrt(np.maximum(np.einsum("gp,pq,gq->g", D, cov, D), 0.0)) if cov is not None else np.zeros(len(e))
    return e, u, D


def interpolation_error(config, errors, theta, axis: str, grid_mm, positions, reference: dict, tool,
                        component: str | None = None) -> np.ndarray:
    """What a table on ``grid_mm`` leaves at ``positions`` (mm, within the grid) because the controller interpolates
    it linearly: the identified line (``line_deviation`` with ``theta``) minus the chord through its values at the
    grid points (mm; zero at the grid points).  A straight line (a rigid rotation, a scale) leaves nothing."""
    g = np.asarray(grid_mm, float)
    x = np.asarray(positions, float)
    e, _, _ = line_deviation(config, errors, theta, None, axis, np.concatenate([g, x]), reference, tool, datum=g[0],
                             component=component)
    return e[len(g):] - np.interp(x, g, e[:len(g)])


def _between(g) -> np.ndarray:
    """The points midway between the entries of a grid (where the chord is furthest from a smooth line)."""
    g = np.asarray(g, float)
    return 0.5 * (g[1:] + g[:-1])


# ----------------------------------------------------------------------------- the table from a recording
def _at(g, M, x):
    """The rows of ``M`` (G, ...) linearly interpolated at ``x`` on the ascending positions ``g`` (as a controller
    interpolates a table), ``x`` within g[0]..g[-1]."""
    j = int(np.clip(np.searchsorted(g, x, side="right") - 1, 0, len(g) - 2))
    w = (x - g[j]) / (g[j + 1] - g[j])
    return (1.0 - w) * M[j] + w * M[j + 1]


def parse_reference(items) -> dict:
    """``--reference`` values such as ``"x=500 mm"`` -> {axis: mm}; a one-line error otherwise."""
    from .units import to_internal

    out = {}
    for item in items or ():
        axis, sep, value = str(item).partition("=")
        axis = axis.strip().lower()
        if not sep or axis not in AXES:
            raise CompensationError(f"--reference: {item!r} must be AXIS=LENGTH with AXIS one of x, y, z, "
                                    "for example \"x=500 mm\"")
        v = to_internal(value.strip(), "mm", where=f"--reference {axis}", error=CompensationError)
        if np.ndim(v) != 0 or not np.isfinite(v):
            raise CompensationError(f"--reference: {item!r} must be one finite length")
        out[axis] = float(v)
    return out


def build_table(rec, step: float = DEFAULT_STEP_MM, max_degree: int = 3, reference: dict | None = None,
                identified=None, reference_point: dict | None = None) -> CompensationTable:
    """Identify ``rec`` and sample its error functions and positioning tables on a grid of ``step`` mm.

    ``reference``: the positions of the other axes on each axis' reference line (default: the centre of their
    range).  ``reference_point``: axis -> mm where that axis' tables (positioning and the cross tables along it)
    are zero, the position the controller references the axis at (default 0 mm, the machine zero, for every axis:
    a recording states no home position); outside the table, zero at the nearest end (the value a controller
    holds beyond its table)."""
    from .units import display

    model, res = identified if identified is not None else identify_recording(rec, max_degree)
    if not bool(res.converged[0]):
        raise CompensationError(f"the identification of {rec.name!r} did not converge; no table is written")
    refuse_implausible(rec, res)
    errors, config = model.errors, model.config
    theta, cov = res.theta[0], res.cov_theta[0]
    ident = res.identifiability
    unident = set(ident.unidentifiable_parameters())
    grids = {a: grid(*errors.ranges[a], step) for a in AXES}
    centre = {a: 0.5 * sum(errors.ranges[a]) for a in AXES}
    reference = {**centre, **(reference or {})}
    tool = np.asarray(rec.plan.tool[0], float)
    notes = [rec.thermal_correction]
    ref_point = {a: 0.0 for a in AXES} | dict(reference_point or {})
    zero_at = {a: float(np.clip(ref_point[a], grids[a][0], grids[a][-1])) for a in AXES}
    for a in AXES:
        if zero_at[a] != ref_point[a]:
            notes.append(f"the reference point of {a.upper()} ({ref_point[a]:g} mm) is outside its table "
                         f"({grids[a][0]:g}..{grids[a][-1]:g} mm): its tables are zero at {zero_at[a]:g} mm, whose "
                         "value the controller holds at the reference point")

    # error functions: f = B theta_g, cov f = B cov_gg B^T, ISO sign per axis side
    functions = []
    for name in COMPONENT_ERRORS:
        idx = [j for j, p in enumerate(errors.params) if p.error == name]
        if not idx:
            continue
        axis = name[3]
        pts = line_points(axis, grids[axis], reference)
        B = errors.basis(pts)[:, idx]
        sgn = iso_sign(config, axis)
        unit_i, unit_d = ("mm", "um") if name[0] == "d" else ("rad", "urad")
        val = sgn * (B @ theta[idx])
        u = np.sqrt(np.maximum(np.einsum("gi,ij,gj->g", B, cov[np.ix_(idx, idx)], B), 0.0))
        ok = not any(errors.params[j].name in unident for j in idx)
        functions.append(ErrorFunction(iso_name(name), name, axis, iso_kind(name), unit_d, grids[axis],
                                       display(val, unit_i, unit_d), display(u, unit_i, unit_d) if ok else
                                       np.full(len(val), np.nan), ok))
    squareness = []
    for s, (iso, sgn, meaning) in SQUARENESS_ISO.items():
        if s not in errors.names:
            continue
        j = errors.index(s)
        ok = errors.params[j].name not in unident
        squareness.append(Squareness(iso, s, float(display(sgn * theta[j], "rad", "urad")),
                                     float(display(np.sqrt(max(cov[j, j], 0.0)), "rad", "urad")) if ok else np.nan,
                                     meaning, ok))

    # positioning per axis: the chain on the reference line, and the ISO 230-2 figures
    scale = _scale(errors)
    null = ident.null_space / scale[:, None] if ident.null_space.size else np.zeros((len(theta), 0))
    resid = display(res.residual_machine[0], "mm", "um")
    axes, iso, cross, raw = {}, {}, {}, {}
    for a in AXES:
        others = {b: reference[b] for b in AXES if b != a}
        e, u, D = line_deviation(config, errors, theta, cov, a, grids[a], reference, tool)
        ED = np.column_stack([e, D])
        ED = ED - _at(grids[a], ED, zero_at[a])  # zero at the reference point, as the controller interpolates
        e, D = ED[:, 0], ED[:, 1:]
        u = np.sqrt(np.maximum(np.einsum("gp,pq,gq->g", D, cov, D), 0.0))
        note = ""
        if null.shape[1] and np.max(np.abs(D @ null)) > 1e-6:  # > 1 nm per um or urad of a null direction
            note = "depends on a combination the plan cannot identify: its uncertainty is understated"
            notes.append(f"positioning table of {a.upper()}: {note}")
        # recording: every measured point's deviation along the axis, reduced to the reference line
        pa = rec.plan.nominal[:, AXIS_INDEX[a]]
        e_pts, _, _ = line_deviation(config, errors, theta, None, a, pa, reference, tool, datum=grids[a][0])
        dev = display(e_pts, "mm", "um") + resid[:, AXIS_INDEX[a]]
        r_rec = iso230_2(a, pa, rec.plan.direction[:, AXIS_INDEX[a]], dev, source="recording")
        B, uB = _reversal_estimate(r_rec)
        src = ("ISO 230-2 mean reversal value of the recording" if r_rec.figures else
               f"none: {r_rec.note}; the directional entries equal the mean")
        interp = interpolation_error(config, errors, theta, a, grids[a], _between(grids[a]), reference, tool)
        axes[a] = AxisTable(a, grids[a], display(e, "mm", "um"), display(u, "mm", "um"), B, uB, src, others, tool, note,
                            zero_at[a], float(display(np.abs(interp).max(), "mm", "um")))
        # model: the identified line at the recording's targets, the table's reversal, the stated repeatability
        targets = r_rec.targets
        if len(targets) < 2:  # not bidirectional (a plan approaching from one side): the model at all its targets
            targets = np.unique(np.round(pa, 6))
        e_t, _, D_t = line_deviation(config, errors, theta, cov, a, targets, reference, tool, datum=grids[a][0])
        e_t = display(e_t, "mm", "um")
        s_stated = float(display(rec.repeatability, "mm", "um"))
        tt = np.concatenate([targets, targets])
        dd = np.concatenate([np.ones(len(targets)), -np.ones(len(targets))])
        r_mod = iso230_2(a, tt, dd, np.concatenate([e_t + B / 2, e_t - B / 2]), source="model", s=s_stated)
        if r_mod.figures:
            r_mod.uncertainty = _model_uncertainty(D_t, cov, theta, B, uB, s_stated, a, targets)
            r_mod.note = (f"identified model on the reference line; reversal = the table's B; s = the stated "
                          f"repeatability {s_stated:g} um")
            if not r_rec.figures:
                r_mod.note += ("; at every target of the recording (approached from one side only): B not measured, "
                               "taken as 0 in A, E and M")
        iso[a] = {"recording": r_rec, "model": r_mod}
        # cross (sag) tables: the deviation of a's line in the other two directions
        for b in AXES:
            if b == a:
                continue
            eb, _, Db = line_deviation(config, errors, theta, cov, a, grids[a], reference, tool, component=b)
            raw[(a, b)] = (grids[a], np.column_stack([eb, Db]))
    raw = frame_convention(raw)
    for (a, b), (g, ED) in raw.items():
        ED = ED - _at(g, ED, zero_at[a])  # zero at the input axis' reference point
        eb, Db = ED[:, 0], ED[:, 1:]
        ub = np.sqrt(np.maximum(np.einsum("gp,pq,gq->g", Db, cov, Db), 0.0))
        cnote = ""
        if null.shape[1] and np.max(np.abs(Db @ null)) > 1e-6:
            cnote = "depends on a combination the plan cannot identify: its uncertainty is understated"
            notes.append(f"cross table E{b.upper()}{a.upper()}: {cnote}")
        ib = interpolation_error(config, errors, theta, a, g, _between(g), reference, tool, component=b)
        cross[f"E{b.upper()}{a.upper()}"] = CrossTable(f"E{b.upper()}{a.upper()}", a, b, g,
                                                       display(eb, "mm", "um"), display(ub, "mm", "um"), cnote,
                                                       float(display(np.abs(ib).max(), "mm", "um")))

    rotary = []
    held = set(ident.held or [])
    for j, p in enumerate(errors.params):
        if p.name.endswith("[O]"):
            unit_i, unit_d = ("mm", "um") if p.unit == "mm" else ("rad", "urad")
            kind = ("location" if p.name[0] == "d" else
                    "zero" if AXIS_INDEX[p.error[1]] == "abc".index(p.error[3]) else "orientation")
            rotary.append({"iso": iso_parameter(p.name), "mtbudget": p.name, "axis": p.error[3].upper(), "kind": kind,
                           "unit": unit_d, "value": _num(display(theta[j], unit_i, unit_d)),
                           "u": None if j in held else _num(display(np.sqrt(max(cov[j, j], 0.0)), unit_i, unit_d)),
                           "identifiable": j not in held, **({"datum": True} if j in held else {})})
    if rotary:
        notes.append("five-axis: the linear axes' tables are those of the machine with every rotary axis at zero; the "
                     "rotary axes' location and zero errors (ISO 230-7: " + ", ".join(r["iso"] for r in rotary) +
                     ") are not axis tables: enter them in the controller's kinematic description (neutral-json and "
                     "neutral-csv list them with u)")
    from .identify import fit_test

    ident_summary = {"chi2_per_dof": float(res.chi2_per_dof[0]), "dof": int(res.dof), "points": len(rec),
                     "converged": bool(res.converged[0]),
                     # the posterior's chi-square test of the fit: a table's u holds only what the model holds
                     "fit_test": fit_test(float(res.chi2_per_dof[0]), int(res.dof), "estimated", rec.name,
                                          what="the tables' u", then="before entering the tables"),
                     "not_identifiable": [[{"parameter": n, "iso": iso_name(n.split("[")[0]) if "(" in n else n,
                                            "weight": w} for n, w in c] for c in ident.combinations()]}
    return CompensationTable(rec.name, rec.machine, float(step), functions, squareness, axes, iso, ident_summary,
                             notes=notes, cross=cross, residual=residual_against_u(rec, res), reference_point=ref_point,
                             model=model, theta=theta, cov_theta=cov, rotary=rotary)


#: the rigid rotation of a small-angle frame change omega on the line of axis a, direction b: slope (omega x e_a)_b
_ROTATION_SLOPE = {("x", "y"): ("z", 1.0), ("x", "z"): ("y", -1.0), ("y", "x"): ("z", -1.0),
                   ("y", "z"): ("x", 1.0), ("z", "x"): ("y", 1.0), ("z", "y"): ("x", -1.0)}


def frame_convention(lines: dict) -> dict:
    """The ISO 230-1 frame of the cross deviations: X's line defines the X direction, X and Y the XY plane.

    ``lines``: (axis, direction) -> (positions (G,), values (G, k)), each relative to its first position.  A
    tracker verification does not see the orientation of the machine frame (the pose absorbs it), so the slope
    of a line in a perpendicular direction is defined only relative to the others.  The small rotation omega
    that makes the least-squares slopes of EYX, EZX and EZY zero is removed from all six lines (each column of
    ``values`` alike, so a Jacobian can ride along): the remaining slopes of EXY, EXZ, EYZ are the squareness
    errors of Y to X, Z to X and Z to Y."""
    def slope(key):
        g, v = lines[key]
        x = g - g.mean()
        return (x @ v) / (x @ x)

    omega = {"z": slope(("x", "y")), "y": -slope(("x", "z")), "x": slope(("y", "z"))}
    out = {}
    for (a, b), (g, v) in lines.items():
        about, sign = _ROTATION_SLOPE[(a, b)]
        out[(a, b)] = (g, v - sign * np.outer(g - g[0], omega[about]).reshape(v.shape))
    return out


def residual_against_u(rec, res, k: float = 2.0) -> dict:
    """axis -> :class:`ResidualAxis`: the residual of the identification at the recording's points (machine frame,
    um) against U = k u(residual), u from the stated point covariances net of the fitted part.

    In whitened coordinates the residual is (I - H) w with H = A (A^T A)^+ A^T the hat matrix of the design A,
    so cov(residual_i) = L_i (I - H_ii) L_i^T in the tracker frame (C_i = L_i L_i^T), R_LT that in the machine
    frame (P_W = R_LT P_LT + T_LT)."""
    from .tracker import rotation

    A = res.design[0]
    m = A.shape[0] // 3
    G = np.linalg.pinv(A.T @ A)
    Ab = A.reshape(m, 3, -1)
    H = np.einsum("mia,ab,mjb->mij", Ab, G, Ab)
    L = np.linalg.inv(res.whitener[0])
    C = L @ (np.eye(3)[None] - H) @ np.swapaxes(L, 1, 2)
    R = rotation(*res.pose[0, 3:])
    Cm = R[None] @ C @ R.T[None]
    u = np.sqrt(np.clip(np.einsum("mii->mi", Cm), 0.0, None)) * 1e3
    r = res.residual_machine[0] * 1e3
    return {a: ResidualAxis(a, rec.plan.nominal[:, AXIS_INDEX[a]], r[:, AXIS_INDEX[a]], k * u[:, AXIS_INDEX[a]])
            for a in AXES}


def _scale(errors) -> np.ndarray:
    from .units import factor, shown_unit

    return np.array([factor(u, shown_unit(u)) for u in errors.units])


def _model_uncertainty(D, cov, theta, B, uB, s, axis, targets, draws: int = MODEL_DRAWS) -> dict:
    """Standard uncertainties of the model's E, M, A, B by Monte Carlo over cov_theta (linearised on the line)."""
    rng = np.random.default_rng(230_2)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    dth = rng.standard_normal((draws, len(w))) @ L.T
    e = (D @ (theta[:, None] + dth.T)).T * 1e3  # (draws, m) um
    Bd = B + uB * rng.standard_normal(draws)
    up, dn = e + Bd[:, None] / 2, e - Bd[:, None] / 2
    E = np.maximum(up.max(1), dn.max(1)) - np.minimum(up.min(1), dn.min(1))
    M = np.ptp(e, axis=1)
    A = E + 4 * s
    return {"E": float(E.std(ddof=1)), "M": float(M.std(ddof=1)), "A": float(A.std(ddof=1)), "B": float(uB),
            "B_mean": float(uB)}


# ----------------------------------------------------------------------------- exporters
def exporters(host=None) -> dict:
    from .plugins import default_host

    host = host or default_host()
    return {e.name: e for e in host.exporters()}


def find_exporter(name: str, host=None):
    found = exporters(host)
    if name not in found:
        close = difflib.get_close_matches(name, list(found), 1, 0.5)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise CompensationError(f"unknown format {name!r}; {hint}the formats are {', '.join(sorted(found))} "
                                "(docs/compensation.md)")
    return found[name]


def export(table: CompensationTable, exporter, path) -> list:
    """Write ``table`` with ``exporter`` (through the plugin host's call(), so a failure names the plugin)."""
    from .plugins import call

    if exporter.max_entries is not None:
        for a, t in table.axes.items():
            if len(t.positions) > exporter.max_entries:
                why = getattr(exporter, "max_entries_source", "")
                raise CompensationError(
                    f"--step {table.step:g} mm gives {len(t.positions)} entries on axis {a.upper()}; format "
                    f"{exporter.name!r} accepts at most {exporter.max_entries} per axis" + (f" ({why})" if why else "") +
                    ": use a larger --step")
    # a built-in exporter's further limits and required options: one line naming the limit, before anything is written
    refusal = call(exporter, "limit_error", table) if callable(getattr(exporter, "limit_error", None)) else None
    if refusal:
        raise CompensationError(f"format {exporter.name!r}: {refusal}")
    path = Path(path)
    make_folder(path.parent, "--out")  # as report, diagnose --report and simulate do
    written = call(exporter, "write", table, path)
    return [Path(p) for p in (written or [])]


# ----------------------------------------------------------------------------- independent readers (for --check)
# Written from the formats' documentation (docs/compensation.md), not from the exporters: each returns, per axis,
# (commanded positions mm, trim forward mm, trim reverse mm), the trim being what the controller ADDS to the
# commanded axis position when moving in that direction.

def read_linuxcnc(path) -> tuple:
    """LinuxCNC COMP_FILE_TYPE 1: 'nominal forward_trim reverse_trim' per line, machine units (mm here).

    The loader (src/emc/motion/usrmotintf.cc, usrmotLoadComp) stops at the first line that is
    not three numbers; trims are added to the joint command (control.c, motor_pos_cmd)."""
    rows = []
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        try:
            if len(parts) < 3:
                raise ValueError
            rows.append([float(p) for p in parts[:3]])
        except ValueError:
            break
    a = np.array(rows, float).reshape(-1, 3)
    return a[:, 0], a[:, 1], a[:, 2]


def read_beckhoff(path) -> tuple:
    """Beckhoff TwinCAT CNC leadscrew error compensation list (kw.ssfk.*), kw.ssfk.unit = 1 (0.1 um).

    table[i].pos / .neg = actual - setpoint (the error), so the controller's trim is minus it."""
    kv = {}
    for line in Path(path).read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) >= 2:
            kv[parts[0]] = parts[1]
    if kv.get("kw.ssfk.unit") != "1":
        raise CompensationError(f"{path}: kw.ssfk.unit must be 1 (0.1 um) for this reader")
    n = int(kv["kw.ssfk.kw_nr_max"])
    interval = float(kv.get("kw.ssfk.interval", "0"))
    if interval:
        setp = float(kv["kw.ssfk.kw_startpos"]) + interval * np.arange(n)
    else:
        setp = np.array([float(kv[f"kw.ssfk.table[{i}].setpoint"]) for i in range(n)])
    pos = np.array([float(kv[f"kw.ssfk.table[{i}].pos"]) for i in range(n)])
    neg = np.array([float(kv.get(f"kw.ssfk.table[{i}].neg", kv[f"kw.ssfk.table[{i}].pos"])) for i in range(n)])
    return setp * 1e-4, -pos * 1e-4, -neg * 1e-4


def read_neutral_csv(path) -> dict:
    rows = {}
    lines = [ln for ln in Path(path).read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    header = lines[0].split(",")
    for ln in lines[1:]:
        r = dict(zip(header, ln.split(",")))
        if r["kind"] in ("positioning_forward", "positioning_reverse"):
            rows.setdefault(r["axis"], {}).setdefault(r["kind"], []).append((float(r["position_mm"]), float(r["value"])))
    out = {}
    for a, d in rows.items():
        f, r = np.array(d["positioning_forward"]), np.array(d["positioning_reverse"])
        out[a] = (f[:, 0], -f[:, 1] * 1e-3, -r[:, 1] * 1e-3)
    return out


def read_neutral_json(path) -> dict:
    d = json.loads(Path(path).read_text())
    return {a: (np.array(t["positions_mm"]), -np.array(t["forward"]) * 1e-3, -np.array(t["reverse"]) * 1e-3)
            for a, t in d["positioning"].items()}


_SIEMENS_AXES = {"AX1": "x", "AX2": "y", "AX3": "z", "X1": "x", "Y1": "y", "Z1": "z"}
_SIEMENS_LINE = re.compile(r"^\$(AA_ENC_COMP|AN_CEC)(_[A-Z_]+)?\[([^\]]*)\]\s*=\s*(\S+)")


def read_siemens(paths, cec_sign: str = "error") -> dict:
    """SINUMERIK 840D sl / 828D LEC ($AA_ENC_COMP...) and sag compensation ($AN_CEC...) programs (K3 function manual).

    Equidistant tables: position of interpolation point N = MIN + N STEP, MIN..MAX; values in mm; the LEC
    compensation value acts like a measured error ("a positive compensation value causes the machine axis to
    move in the negative direction"), so the trim added to the command is minus it.  A $AN_CEC entry is applied
    with the sign the user declared the control uses (``cec_sign``: "error" as the LEC, "correction": added to
    the output axis' setpoint as it is); no Siemens text found states it.  CEC tables with
    $AN_CEC_DIRECTION = 1 / -1 act in one direction of travel of the base axis only; 0 in both; the output
    axis gets the value at the base axis' setpoint; a table with input = output axis adds to that axis."""
    lec, cec = {}, {}
    for path in paths:
        for line in Path(path).read_text().splitlines():
            m = _SIEMENS_LINE.match(line.split(";")[0].strip())
            if not m:
                continue
            group, attr, idx, value = m.group(1), m.group(2) or "", [i.strip() for i in m.group(3).split(",")], m.group(4)
            if group == "AA_ENC_COMP":
                axis = _SIEMENS_AXES[idx[-1]]
                d = lec.setdefault(axis, {"values": {}})
                if attr == "":
                    d["values"][int(idx[1])] = float(value)
                else:
                    d[attr] = value
            else:
                d = cec.setdefault(int(idx[0]), {"values": {}})
                if attr == "":
                    d["values"][int(idx[1])] = float(value)
                else:
                    d[attr] = value

    if cec_sign not in ("error", "correction"):
        raise CompensationError(f"--check: the $AN_CEC sign must be 'error' or 'correction', not {cec_sign!r}")
    cec_trim = -1.0 if cec_sign == "error" else 1.0

    def points(d, prefix):
        from decimal import Decimal

        step, lo, hi = (Decimal(d[f"{prefix}{k}"]) for k in ("_STEP", "_MIN", "_MAX"))
        n = (hi - lo) / step
        if n != n.to_integral_value():  # the control needs MIN + N STEP = MAX
            raise CompensationError(f"{paths[0]}: (MAX - MIN) / STEP = ({hi} - {lo}) / {step} is not an integer")
        n, step, lo = int(n), float(step), float(lo)
        vals = np.array([d["values"].get(i, 0.0) for i in range(n + 1)])
        return lo + step * np.arange(n + 1), vals

    out = {}
    for a, d in lec.items():
        pos, v = points(d, "")
        out[a] = [pos, -v, -v]
    cross = {}
    for t, d in sorted(cec.items()):
        pos, v = points(d, "")
        a, b = (_SIEMENS_AXES[d[k].strip("\"'() ")] for k in ("_INPUT_AXIS", "_OUTPUT_AXIS"))  # =(AX1) or =AX1
        direction = int(d.get("_DIRECTION", "0"))
        if a == b:
            base = out.setdefault(a, [pos, np.zeros(len(pos)), np.zeros(len(pos))])
            add = cec_trim * np.interp(base[0], pos, v)
            if direction >= 0:
                base[1] = base[1] + add
            if direction <= 0:
                base[2] = base[2] + add
        else:
            if direction != 0:
                raise CompensationError(f"{paths[0]}: a direction-dependent cross table ({a} -> {b}) is not read here")
            cross[(a, b)] = (pos, cec_trim * v)
    res = {a: tuple(v) for a, v in out.items()}
    res["cross"] = cross
    return res


def read_heidenhain(paths) -> dict:
    """HEIDENHAIN TNC nonlinear axis error compensation: the .CMA assignment and its .COM tables.

    .CMA: one column per axis, a .COM file name in it, '*' in ACTIVE on the active line; the .COM entered in
    the column of axis A holds F(A): AXISPOS (positions of A, mm, from the machine datum), one column per
    compensated axis (its compensation value at AXISPOS, mm) and BACKLASH (the value measured moving in the
    negative direction, for A's own column).  Values are the error (entry = actual - nominal), so the trim is
    minus it; the BACKLASH reading is an interpretation (docs/compensation.md)."""
    paths = [Path(p) for p in paths]
    cma = [p for p in paths if p.suffix.lower() == ".cma"]
    if len(cma) != 1:
        raise CompensationError("--check: the heidenhain files must include exactly one .CMA assignment table")

    def table(path):
        lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
        if not lines[0].startswith("BEGIN") or not lines[-1].startswith("[END]"):
            raise CompensationError(f"{path}: a TNC table starts with BEGIN and ends with [END]")
        head = lines[1].split()
        return lines[0].split(), [dict(zip(head, ln.split())) for ln in lines[2:-1]]

    _, rows = table(cma[0])
    active = [r for r in rows if r.get("ACTIVE") == "*"]
    if len(active) != 1:
        raise CompensationError(f"{cma[0]}: exactly one line must be active ('*' in ACTIVE)")
    by_name = {p.name.upper(): p for p in paths}
    out, cross = {}, {}
    for col, fname in active[0].items():
        if col in ("NR", "ACTIVE") or fname in ("", "-"):
            continue
        a = col.lower()
        begin, rows_c = table(by_name[fname.upper()])
        if begin[-1] != "MM":
            raise CompensationError(f"{fname}: only metric (MM) tables are read here")
        pos = np.array([float(r["AXISPOS"]) for r in rows_c])
        for b in AXES:
            if b.upper() not in rows_c[0]:
                continue
            v = np.array([float(r[b.upper()]) for r in rows_c])
            if b == a:
                back = np.array([float(r.get("BACKLASH", r[b.upper()])) for r in rows_c])
                out[a] = (pos, -v, -back)
            else:
                cross[(a, b)] = (pos, -v)
    out["cross"] = cross
    return out


#: format -> reader of the written files: ("axis", fn(path) -> tuple) per axis file, ("all", fn(path) -> dict)
#: for one file, ("files", fn(paths) -> dict) for a set; a dict may hold "cross": {(input, output): (pos, trim)}
READERS = {
    "linuxcnc": ("axis", read_linuxcnc),
    "beckhoff-lsec": ("axis", read_beckhoff),
    "neutral-csv": ("all", read_neutral_csv),
    "neutral-json": ("all", read_neutral_json),
    "siemens-840d": ("files", read_siemens),
    "siemens-828d": ("files", read_siemens),
    "heidenhain-tnc": ("files", read_heidenhain),
}


def read_back(exporter, written: list, options: dict | None = None) -> dict:
    """axis -> (positions mm, trim forward mm, trim reverse mm) from the files an exporter wrote; ``options``: the
    table's exporter options (the Siemens $AN_CEC sign the user declared)."""
    if exporter.name not in READERS:
        raise CompensationError(f"--check has no independent reader for format {exporter.name!r}; "
                                f"it can check {', '.join(sorted(READERS))}")
    kind, fn = READERS[exporter.name]
    if kind == "all":
        return fn(written[0])
    if kind == "files":
        if fn is read_siemens:
            return fn(list(written), (options or {}).get("siemens_cec_sign") or "error")
        return fn(list(written))
    out = {}
    for p in written:
        m = re.search(r"_([xyz])\.[^.]+$", Path(p).name)
        if m:
            out[m.group(1)] = fn(p)
    return out


def interpolate(positions, values, at):
    """Linear between entries, the end value held beyond the table (LinuxCNC control.c; assumed for the others)."""
    return np.interp(at, positions, values)


# ----------------------------------------------------------------------------- the round trip
@dataclass
class AxisCheck:
    axis: str
    positions: np.ndarray  # mm, grid points and midpoints
    before: np.ndarray  # (2, G) um, forward and reverse, relative to the datum
    after: np.ndarray  # (2, G) um
    u: np.ndarray  # (2, G) um, the table's stated standard uncertainty there
    iso_before: Iso230_2
    iso_after: Iso230_2
    rounding: float = 0.0  # um: largest difference between the read-back entries and the table (the format's resolution)

    @property
    def z(self):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.u > 0, self.after / self.u, np.where(np.abs(self.after) < 1e-3, 0.0, np.inf))

    @property
    def verdict(self) -> str:
        """worse: ISO 230-2 E after > before; under-covered: fewer than 95 % of the points within 2u; else improved."""
        return verdict(self.iso_before.figures["E"], self.iso_after.figures["E"], self.z, self.rounding)

    def to_dict(self) -> dict:
        z = self.z
        return {"axis": self.axis, "verdict": self.verdict, "points": int(self.positions.size),
                "max_abs_before_um": float(np.abs(self.before).max()),
                "max_abs_after_um": float(np.abs(self.after).max()), "max_abs_z": float(np.abs(z).max()),
                "rms_z": float(np.sqrt(np.mean(z**2))), "within_2u": float(np.mean(np.abs(z) <= 2)),
                "format_rounding_um": self.rounding,
                "iso230_2_before": self.iso_before.figures, "iso230_2_after": self.iso_after.figures}


@dataclass
class CrossCheck:
    """--check of one cross (sag) table: the deviation of a's line in direction b before and after (um)."""

    iso: str
    axis: str
    output: str
    positions: np.ndarray
    before: np.ndarray
    after: np.ndarray
    u: np.ndarray
    rounding: float = 0.0

    @property
    def z(self):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.u > 0, self.after / self.u, np.where(np.abs(self.after) < 1e-3, 0.0, np.inf))

    @property
    def verdict(self) -> str:
        """worse: largest |deviation| after > before; under-covered: fewer than 95 % within 2u; else improved."""
        return verdict(np.abs(self.before).max(), np.abs(self.after).max(), self.z, self.rounding)

    def to_dict(self) -> dict:
        z = self.z
        return {"iso": self.iso, "verdict": self.verdict, "input_axis": self.axis, "output_axis": self.output,
                "points": int(self.positions.size),
                "max_abs_before_um": float(np.abs(self.before).max()), "max_abs_after_um": float(np.abs(self.after).max()),
                "max_abs_z": float(np.abs(z).max()), "within_2u": float(np.mean(np.abs(z) <= 2)),
                "format_rounding_um": self.rounding}


VERDICTS = ("improved", "worse", "under-covered")


def verdict(before: float, after: float, z, rounding: float = 0.0) -> str:
    """One line's verdict in --check: "worse" when its error figure after compensation exceeds the one before
    (by more than the format's rounding), "under-covered" when fewer than :data:`STATED_COVERAGE` of its points
    lie within 2u (k = 2, the coverage the table's uncertainty claims), "improved" otherwise."""
    if after > before + rounding + 1e-6:
        return "worse"
    if np.mean(np.abs(np.asarray(z)) <= 2.0) < STATED_COVERAGE:
        return "under-covered"
    return "improved"


def check_worse(check: dict) -> list:
    """The lines (axes and cross tables) --check found worse after compensation."""
    return [k for group in ("axes", "cross") for k, c in check.get(group, {}).items() if c.verdict == "worse"]


def _truth_frame(table, config, terr, theta_t) -> dict:
    """(a, b) -> (positions, the rigid rotation's part of the true machine's deviation on that line (um)): what
    :func:`frame_convention` removes from the truth, so truth and tables share the ISO 230-1 frame."""
    lines = {}
    for a, t in table.axes.items():
        g = t.positions
        lp = line_points(a, g, t.reference)
        inp = chain_inputs(config, lp, np.broadcast_to(t.tool, lp.shape).copy())
        dev = (chain(config, terr, theta_t[None], inp) - chain(config, terr, np.zeros((1, len(terr.params))), inp))[0]
        for b in AXES:
            if b != a:
                lines[(a, b)] = (g, (dev[:, AXIS_INDEX[b]] - dev[0, AXIS_INDEX[b]]) * 1e3)
    conv = frame_convention(lines)
    return {k: (lines[k][0], lines[k][1] - conv[k][1]) for k in lines}


def _present_effect(v) -> bool:
    """Whether a truth.json effect is there: a non-empty mapping, or an array/number with a non-zero entry."""
    if v is None:
        return False
    if isinstance(v, dict):
        return any(_present_effect(x) for x in v.values())
    return bool(np.any(np.asarray(v, dtype=float) != 0))


def _check_line(config, terr, axis: str, t: AxisTable, grid: np.ndarray, component: int):
    """Where --check looks along ``axis``'s reference line: the grid points and midway between them, their tool
    points and tools, and the error-free machine's ``component`` there (mm)."""
    pts = np.unique(np.concatenate([grid, 0.5 * (grid[1:] + grid[:-1]), [t.zero_at]]))
    lp = line_points(axis, pts, t.reference)
    tool = np.broadcast_to(t.tool, lp.shape).copy()
    nominal = chain(config, terr, np.zeros((1, len(terr.params))), chain_inputs(config, lp, tool))[0, :, component]
    return pts, lp, tool, nominal


def check_export(table: CompensationTable, rec, exporter, written: list) -> dict:
    """Apply the exported tables (read back independently) to the simulated machine of ``truth.json``.

    On each axis' reference line, at the grid points and midway between them, in both directions:
    the positioning deviation of the true machine (its errors and its reversal; at the reference
    temperature) before and after adding the tables' trims to the commanded position, relative to
    the bidirectional mean at the datum, against the table's stated standard uncertainty.
    """
    from .simulate import parameters_from_truth, truth_error_model

    truth_path = Path(rec.path or ".") / "truth.json"
    if rec.path is None or not truth_path.is_file():
        raise CompensationError("--check needs the truth.json of a simulated recording (mtbudget simulate writes it); "
                                f"{str(rec.path or rec.name)!r} has none")
    try:
        truth = json.loads(truth_path.read_text())
        terr = truth_error_model(rec.plan, truth["geometric_errors"]["coefficients"],
                                 (truth.get("rotary_axes") or {}).get("errors"))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise CompensationError(f"{truth_path}: not a truth.json mtbudget simulate writes ({type(exc).__name__}: "
                                f"{str(exc)[:80]}); --check needs one") from None

    class _M:  # parameters_from_truth reads model.errors only
        errors = terr

    theta_t, _, effects = parameters_from_truth(truth, _M)
    reversal = effects.get("reversal", {})
    config = Configuration.parse(rec.machine, rec.plan.rotary or None)
    tables = dict(read_back(exporter, written, table.options))
    cross_tables = tables.pop("cross", {})
    truth_lines = None
    out = {"format": exporter.name, "files": [str(p) for p in written], "axes": {}, "cross": {},
           "ignored": [k for k in ("thermal", "drift") if _present_effect(effects.get(k))],
           "not_in_u": sorted(k for k in (truth.get("sources") or {}) if k not in IN_TABLE_U)}
    for (a, b), (pos_tab, trim) in cross_tables.items():
        c = table.cross.get(f"E{b.upper()}{a.upper()}")
        if c is None:
            continue
        t = table.axes[a]
        g = c.positions
        kb = AXIS_INDEX[b]
        pts, lp, tool, nominal = _check_line(config, terr, a, t, g, kb)
        rows = []
        for comp in (np.zeros(len(pts)), interpolate(pos_tab, trim, pts)):
            P = chain(config, terr, theta_t[None], chain_inputs(config, lp, tool, offset={b: comp[None, :]}))
            rows.append((P[0, :, kb] - nominal) * 1e3)
        datum = int(np.argmin(np.abs(pts - t.zero_at)))  # the reference point, where the tables are zero
        before, after = (r - r[datum] for r in rows)
        if truth_lines is None:  # the true machine in the same frame convention as the tables
            truth_lines = _truth_frame(table, config, terr, theta_t)
        pts_g, rot = truth_lines[(a, b)]
        shift = np.interp(pts, pts_g, rot)
        before, after = before - (shift - shift[datum]), after - (shift - shift[datum])
        _, u_line, _ = line_deviation(table.model.config, table.model.errors, table.theta, table.cov_theta, a, pts,
                                      {**t.reference, a: 0.0}, t.tool, datum=t.zero_at, component=b)
        q = float(np.max(np.abs(interpolate(pos_tab, trim, g) * 1e3 + c.deviation)))
        if q > MAX_ROUNDING_UM:
            out.setdefault("mismatch", {})[c.iso] = q
        # the table's own interpolation between its entries (the identified line minus its chord there), stated
        i_line = interpolation_error(table.model.config, table.model.errors, table.theta, a, g, pts,
                                     {**t.reference, a: 0.0}, t.tool, component=b)
        u = np.sqrt((u_line * 1e3) ** 2 + (i_line * 1e3) ** 2 + min(q, MAX_ROUNDING_UM) ** 2 / 3.0)
        out["cross"][c.iso] = CrossCheck(c.iso, a, b, pts, before, after, u, q)
    for a, t in table.axes.items():
        if a not in tables:
            raise CompensationError(f"--check: the files written by {exporter.name!r} hold no table for axis {a.upper()}")
        pos_tab, trim_f, trim_r = tables[a]
        g = t.positions
        k = AXIS_INDEX[a]
        pts, lp, tool, nominal = _check_line(config, terr, a, t, g, k)
        B_true = float(reversal.get(a, 0.0))
        before, after = np.zeros((2, len(pts))), np.zeros((2, len(pts)))
        for row, d, trim in ((0, 1.0, trim_f), (1, -1.0, trim_r)):
            lost = -d * B_true / 2.0  # the simulator's reversal: the axis stops B/2 short of its target
            for arr, comp in ((before, 0.0), (after, interpolate(pos_tab, trim, pts))):
                P = chain(config, terr, theta_t[None], chain_inputs(config, lp, tool, offset={
                    a: (lost + np.broadcast_to(comp, pts.shape))[None, :]}))
                arr[row] = (P[0, :, k] - nominal) * 1e3
        datum = int(np.argmin(np.abs(pts - t.zero_at)))  # the reference point, where the table is zero
        for arr in (before, after):
            arr -= 0.5 * (arr[0, datum] + arr[1, datum])
        # the table's stated uncertainty at these points (relative to its reference point), directional
        _, u_line, _ = line_deviation(table.model.config, table.model.errors, table.theta, table.cov_theta, a, pts,
                                      {**t.reference, a: 0.0}, t.tool, datum=t.zero_at)
        # the format's own rounding, measured on the read-back at the grid points (rectangular, half-width q)
        q = max(float(np.max(np.abs(interpolate(pos_tab, trim_f, g) * 1e3 + t.forward))),
                float(np.max(np.abs(interpolate(pos_tab, trim_r, g) * 1e3 + t.reverse))))
        if q > MAX_ROUNDING_UM:  # not a rounding: the file does not say what the table says (a sign, a unit)
            out.setdefault("mismatch", {})[a] = q
        # between the entries the controller's linear interpolation leaves the identified line's deviation from the
        # chord (known, not correctable by the table: taken as a standard uncertainty of its size, conservative)
        i_line = interpolation_error(table.model.config, table.model.errors, table.theta, a, g, pts,
                                     {**t.reference, a: 0.0}, t.tool)
        u = np.sqrt((u_line * 1e3) ** 2 + (i_line * 1e3) ** 2 + (0.5 * t.u_reversal) ** 2 +
                    min(q, MAX_ROUNDING_UM) ** 2 / 3.0)
        u2 = np.vstack([u, u])
        dirs = np.concatenate([np.ones(len(pts)), -np.ones(len(pts))])
        tt = np.concatenate([pts, pts])
        ib = iso230_2(a, tt, dirs, before.ravel(), source="true machine before compensation", s=0.0)
        ia = iso230_2(a, tt, dirs, after.ravel(), source="true machine after compensation", s=0.0)
        out["axes"][a] = AxisCheck(a, pts, before, after, u2, ib, ia, q)
    return out


# ----------------------------------------------------------------------------- text
def _fig(r: Iso230_2, keys=("A", "E", "M", "R", "B", "B_mean")) -> str:
    if not r.figures:
        return r.note
    parts = []
    one_sided = "approached from one side only" in (r.note or "")  # the model of a recording that measured no B
    for k in keys:
        v = r.figures[k]
        u = r.uncertainty.get(k)
        if one_sided and k in ("B", "B_mean"):
            parts.append(f"{k} not measured")
            continue
        parts.append(f"{k} {v:6.2f}" + (f" ({u:.2f})" if u is not None else ""))
    return "  ".join(parts) + (f"  [{r.note}]" if r.note else "")


def residual_lines(table: CompensationTable) -> list:
    """The compensated machine at the recording's points: residual against U (k = 2), per axis (text)."""
    if not table.residual:
        return []
    lines = ["fit residual at the recording's points: residual = measured - identified model (machine frame), "
             "against U = 2 u of that residual (k = 2, about 95 % for a normal; u from the stated tracker noise and "
             "repeatability, net of the fitted part); um:"]
    for a, r in table.residual.items():
        d = r.summary()
        lines.append(f"  {a.upper()}: {d['points']} points, RMS residual {d['rms_residual']:6.2f}, max |residual| "
                     f"{d['max_abs_residual']:6.2f}, median U {d['median_U']:6.2f}, max |residual|/U "
                     f"{d['max_abs_residual_over_U']:4.2f}, within U {d['within_U']:.1%} (expected 95.4 %)")
    return lines


def table_text(table: CompensationTable, written: list, exporter, check: dict | None = None) -> str:
    idn = table.identification
    lines = [f"compensation tables of {table.recording!r} ({table.machine}): chi-square per dof "
             f"{idn['chi2_per_dof']:.3f}, {idn['points']} points, grid step {table.step:g} mm",
             *([f"WARNING: {idn['fit_test']['warning']}"] if (idn.get("fit_test") or {}).get("warning") else []),
             f"  format {exporter.name}: {exporter.description}",
             *[f"  wrote {p}" for p in written],
             "", ("positioning tables (um, k = 1; zero at the axis' reference point; forward = approach in +; "
                  "reversal B as ISO 230-2: mean up minus mean down, -1 x the lost motion diagnose reports):")]
    for a, t in table.axes.items():
        ref = ", ".join(f"{b} = {v:g} mm" for b, v in t.reference.items())
        lines.append(f"  {a.upper()}: {len(t.positions)} entries {t.positions[0]:g}..{t.positions[-1]:g} mm, zero at "
                     f"{t.zero_at:g} mm, on the line {ref}; range of the mean deviation {np.ptp(t.deviation):.2f} um, largest u {t.u.max():.2f} um; "
                     + (f"reversal B {t.reversal:+.2f} ({t.u_reversal:.2f}) um" if not t.reversal_source.startswith("none")
                        else "reversal B not measured (the recording approaches its targets from one side only: the "
                             "directional entries equal the mean)")
                     + f"; between entries (linear interpolation) up to {t.interpolation:.2f} um")
        if t.note:
            lines.append(f"     note: {t.note}")
    lines += ["", "ISO 230-2 per axis (um; model figures with their standard uncertainty in brackets):"]
    for a, d in table.iso230_2.items():
        lines.append(f"  {a.upper()} recording  {_fig(d['recording'])}")
        lines.append(f"  {a.upper()} model      {_fig(d['model'])}")
    lines += ["", "ISO 230-1 error functions (largest |value| over the grid, largest u):"]
    for f in table.functions:
        uu = f"{np.nanmax(f.u):.2f}" if f.identifiable else "not identifiable"
        lines.append(f"  {f.iso:<4} ({f.internal:<6}) {f.kind:<12} {np.abs(f.value).max():8.2f} {f.unit:<4} u {uu}")
    for s in table.squareness:
        uu = f"{s.u:.2f}" if s.identifiable else "not identifiable"
        lines.append(f"  {s.iso:<8} ({s.internal}) squareness {s.value:+8.2f} urad u {uu}")
    if table.cross:
        lines += ["", "cross (sag) tables: deviation of each axis' line in the other directions (um, k = 1; zero at the "
                      "input axis' reference point; squareness and Abbe effects on the line included):"]
        for c in table.cross.values():
            lines.append(f"  {c.iso} ({c.output.upper()} as a function of {c.axis.upper()}): range {np.ptp(c.deviation):6.2f} um, "
                         f"largest u {c.u.max():5.2f} um, between entries up to {c.interpolation:.2f} um" +
                         (f"  [{c.note}]" if c.note else ""))
    lines += ["", *residual_lines(table)]
    for n in table.notes:
        lines.append(f"note: {n}")
    if check is not None:
        lines += ["", f"check: the written {check['format']} tables, read back independently, applied to the simulated "
                      "machine of truth.json (positioning on each table's line, grid points and midpoints, both "
                      "directions; um):"]
        for a, c in check["axes"].items():
            d = c.to_dict()
            lines.append(f"  {a.upper()}: before max |e| {d['max_abs_before_um']:6.2f}  after max |e| "
                         f"{d['max_abs_after_um']:5.2f}  max |e|/u {d['max_abs_z']:4.2f}  rms e/u {d['rms_z']:4.2f}  "
                         f"within 2u {d['within_2u']:.0%}  | ISO 230-2 E {c.iso_before.figures['E']:.2f} -> "
                         f"{c.iso_after.figures['E']:.2f}, B {c.iso_before.figures['B']:.2f} -> "
                         f"{c.iso_after.figures['B']:.2f}  | {c.verdict.upper()}")
        for k, c in check.get("cross", {}).items():
            d = c.to_dict()
            lines.append(f"  {k} ({c.output.upper()} on the {c.axis.upper()} line): before max |e| {d['max_abs_before_um']:6.2f}  "
                         f"after max |e| {d['max_abs_after_um']:5.2f}  max |e|/u {d['max_abs_z']:4.2f}  "
                         f"within 2u {d['within_2u']:.0%}  | {c.verdict.upper()}")
        for a, q in check.get("mismatch", {}).items():
            lines.append(f"  MISMATCH on {a.upper()}: the read-back entries differ from the table by up to {q:.3g} um")
        if check["ignored"]:
            lines.append(f"  (truth.json also has {', '.join(check['ignored'])}: not applied, the check is at the "
                         "reference temperature and in the machine frame)")
        if check.get("not_in_u"):
            lines.append(not_in_u_line(check))
        lines += ["", verdict_line(check)]
    return "\n".join(lines)


def not_in_u_line(check: dict) -> str:
    """What the tables' u cannot cover on this simulated recording: the sources it drew that the identification does
    not model."""
    return ("note: the simulation behind truth.json also drew " + ", ".join(check["not_in_u"]) + ": physics the "
            "identification does not model, which it takes for geometry; the tables carry it and their u (the "
            "identification's, from the stated tracker noise and repeatability) does not contain it, so a line can be "
            "under-covered by it. A simulation that draws only what the u contains ([sources] enable = "
            "[\"tracker_noise\", \"repeatability\", \"geometric_error_uncertainty\"]) checks the tables' own statement "
            "(docs/compensation.md)")


def verdict_line(check: dict) -> str:
    """The check's last line: the verdict of every line, and what the verdicts mean."""
    per = [f"{k.upper() if len(k) == 1 else k} {c.verdict}" for group in ("axes", "cross")
           for k, c in check.get(group, {}).items()]
    return ("verdict: " + ", ".join(per) + " (worse: the error figure after compensation, ISO 230-2 E for an axis, "
            "the largest |deviation| for a cross table, exceeds the one before; under-covered: fewer than 95 % of "
            "the points within 2u, k = 2; improved: neither)")


def check_json(check: dict) -> dict:
    return {"format": check["format"], "files": check["files"], "ignored": check["ignored"],
            "not_in_u": check.get("not_in_u", []),
            "mismatch": check.get("mismatch", {}), "worse": check_worse(check),
            "axes": {a: c.to_dict() for a, c in check["axes"].items()},
            "cross": {k: c.to_dict() for k, c in check.get("cross", {}).items()}}
