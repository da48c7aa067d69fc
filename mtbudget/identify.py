"""Batched weighted least-squares identification (the optimisation strategy).

From tracker points of one recording or of N simulated trials at once
(leading trial axis), identify the tracker pose (6 parameters) and the
coefficients of the geometric error functions by minimising

    sum_i r_i^T C_i^-1 r_i,   r_i = measured_i - predicted_i   (tracker frame)

the weighted form of the paper's Eq. 27 objective: ``C_i`` is each point's
tracker covariance (range vs transverse, :func:`mtbudget.tracker.covariance`)
plus the machine repeatability.

Algorithm: closed-form rigid registration (Kabsch) for the starting pose,
then Gauss-Newton on all trials at once with the exact analytic Jacobian of
the Eq. 6 chain.  Parameters are scaled (um for lengths, urad for angles,
which on a 1 m lever are both um) before any rank decision.

Identifiability: the structural null space of the plan is computed once,
from the machine-frame Jacobian of the rigid motions (the tracker pose) and
the geometric parameters.  Directions in it cannot be told from the data;
they are reported by name and fixed by the minimum-norm convention (in the
scaled parameters, from the initial parameters).  The remaining problem has
full rank, so every trial is solved by a Cholesky factorisation.

Solvers (``Strategy.solver``):

* ``"gauss-newton"`` -- the reference: Gauss-Newton with a fresh Jacobian of
  the chain, a fresh design matrix and a Cholesky factorisation per trial and
  iteration (step halving where the cost rises).
* ``"chord"`` (default) -- the fast path.  The unknowns are moved in the
  machine frame: the pose by a small rigid motion (translation, rotation
  about the centroid of the plan), the geometric parameters along the
  identifiable directions.  The whitened residuals are exact at every
  iterate (the exact chain, each trial's own whitener), and so is the rigid
  part of the gradient; the iteration matrix is one normal matrix per chunk
  of trials (per label, when the caller passes ``groups``: a trial's result
  then depends on its label's trials only, bit for bit), factorised once,
  built from the plan's Jacobian at the nominal (cached per model and phase)
  and the chunk's (label's) mean information matrix
  (machine frame).  Stage 1 iterates with the nominal Jacobian; because the
  fixed point of such chord iterations sits where the *nominal* Jacobian is
  orthogonal to the weighted residual (about 1e-5 mm from the least-squares
  minimum on the paper's configuration: too far for the 1e-6 mm the
  identification promises), stage 2 evaluates each trial's exact Jacobian
  once, where stage 1 stopped, and iterates with it to the tolerance.  What
  is left is of the order (stage-2 move)^2 / (distance from the nominal):
  estimated per trial, and a trial whose estimate exceeds
  ``Strategy.chord_bias``, or whose chord iterations contract by less than a
  factor 2 per iteration or do not reach the tolerance in
  ``Strategy.chord_iter`` iterations, is solved again with Gauss-Newton from
  its start (``Identification.fallback``, counted in ``n_fallback``).
  Covariances and the design at the solution are computed exactly, from the
  chain's Jacobian at the solution, when first asked for.  Each stage runs
  every iteration of a trial in one compiled pass
  (:func:`mtbudget.kernels.chord_stage`; the weights and the results too:
  ``point_weights``, ``chord_final``); :func:`_chord` is the numpy formulation
  it is tested against (``CHORD_KERNEL = False``).  With ``iteration_pose``
  (the engine) the pose-only fit starts at that pose, and Kabsch registers
  only the trials that do not converge from there.
"""

from __future__ import annotations

import itertools
import weakref
from dataclasses import dataclass, field

import numpy as np

from . import tracker as lt
from .errors import IdentificationError
from .machine import (AXES, AXIS_INDEX, chain_adjoint, kernel_array, kernel_chain, kernel_points, skew,
                      skew_basis, vjp_layout)
from .model import MeasurementModel
from .units import factor, shown_unit

GROUPS = ("pose", "translational", "angular", "squareness")


@dataclass
class Strategy:
    """An optimisation strategy (paper Section 2.2.4, Figs. 5-6).

    phases: each phase is the list of parameter groups it frees, from
    ``pose``, ``translational``, ``angular``, ``squareness``; parameters of a
    later phase start from the values of the earlier phase.  ``[GROUPS]`` is
    the paper's one-phase identification.

    solver: ``"chord"`` (the fast path, see the module docstring) or
    ``"gauss-newton"`` (the reference).  ``max_iter``, ``xtol`` and ``ftol``
    are Gauss-Newton's; the chord iterates to ``min(xtol, chord_tol)`` within
    ``chord_iter`` iterations per stage, and hands a trial it cannot finish
    to Gauss-Newton with those settings.
    """

    phases: list = field(default_factory=lambda: [list(GROUPS)])
    max_iter: int = 30
    xtol: float = 1e-4  # convergence: largest step of any scaled parameter (um or urad; Gauss-Newton
    #                     converges quadratically here, so what remains after it is ~1e-10) ...
    ftol: float = 1e-12  # ... or a relative decrease of the weighted cost below this
    rank_tol: float = 1e-7  # singular values below rank_tol * largest are treated as null
    weighted: bool = True
    solver: str = "chord"  # "chord": shared factorisation, the fast path; "gauss-newton": the reference
    chord_iter: int = 8  # chord iterations per stage before a trial falls back to Gauss-Newton
    chord_tol: float = 1e-4  # the chord's step tolerance (um, urad): min(xtol, chord_tol); chord iterations
    #                          converge linearly, so a loose xtol would leave more than Gauss-Newton does
    chord_bias: float = 1e-3  # largest estimated distance (um, urad) of the chord's fixed point from the
    #                           least-squares minimum (1e-6 mm on a 1 m lever); beyond it the trial falls back
    #                           to Gauss-Newton.  The estimate exceeds the distance measured against
    #                           Gauss-Newton by 10x or more where it matters (tests/test_identify_fast.py)

    @classmethod
    def one_phase(cls, **kw):
        return cls(phases=[list(GROUPS)], **kw)

    @classmethod
    def multi_phase(cls, **kw):
        return cls(phases=[["pose"], ["pose", "translational"], list(GROUPS)], **kw)


@dataclass
class Noise:
    """Stated standard uncertainties of one verification (internal units)."""

    angular: float  # rad
    distance: float  # mm
    distance_per_length: float  # mm/mm
    repeatability: float  # mm

    @classmethod
    def of(cls, rec):
        return cls(rec.angular, rec.distance, rec.distance_per_length, rec.repeatability)


@dataclass
class Identifiability:
    names: list  # parameter names (geometric)
    rank: int  # rank of [rigid | geometric] (scaled)
    n_params: int
    singular_values: np.ndarray
    null_space: np.ndarray  # (p, k) in scaled geometric parameters
    pose_identifiable: bool
    #: the datum of a machine with rotary axes: the parameters held at zero (indices), one per null direction
    #: (:func:`datum_parameters`); None: the minimum-norm convention (three-axis machines)
    held: list | None = None
    #: (6, k) the rigid motion of the machine points (scaled: translation then rotation about the plan's centroid, as
    #: :func:`analyse`'s columns) that each null direction's geometric part (a column of ``null_space``) brings with
    #: it; None where the geometric parts do not determine them (the pose itself not identifiable)
    null_rigid: np.ndarray | None = None

    @property
    def identifiable(self) -> int:
        return self.n_params - self.null_space.shape[1]

    def combinations(self, threshold: float = 0.2, top: int = 6) -> list[list[tuple[str, float]]]:
        """Each non-identifiable direction as [(parameter, weight), ...] (scaled: um and urad).  Under a datum
        (``held``) each direction has weight 1 on its held parameter and 0 on the other held ones, so it reads
        "what the held parameter would absorb"; otherwise unit norm."""
        out = []
        if self.null_space.size == 0:
            return out
        N = self.null_space
        if self.held is not None:
            B = N @ np.linalg.inv(N[self.held, :])
            for k in range(B.shape[1]):
                v = B[:, k]
                idx = [self.held[k]] + [i for i in np.argsort(-np.abs(v)) if i != self.held[k]
                                        and abs(v[i]) >= 0.02][: top - 1]
                out.append([(self.names[i], float(v[i])) for i in idx])
            return out
        # rotate the basis to something readable: reduced row echelon-like via QR with pivoting
        from scipy.linalg import qr

        _, _, piv = qr(N.T, pivoting=True)
        B = N @ np.linalg.inv(N[piv[: N.shape[1]], :])  # unit weight on pivot parameters
        for k in range(B.shape[1]):
            v = B[:, k] / np.linalg.norm(B[:, k])
            idx = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= threshold][:top]
            out.append([(self.names[i], float(v[i])) for i in idx])
        return out

    def unidentifiable_parameters(self, threshold: float = 1e-6) -> list[str]:
        """Parameters that take part in any non-identifiable direction."""
        if self.null_space.size == 0:
            return []
        w = np.linalg.norm(self.null_space, axis=1)
        return [n for n, x in zip(self.names, w) if x > threshold]


@dataclass
class Identification:
    """Result of identifying N trials (N = 1 for one recording)."""

    model: MeasurementModel
    theta: np.ndarray  # (N, p) geometric parameters (mm, rad)
    pose: np.ndarray  # (N, 6)
    residual: np.ndarray  # (N, M, 3) measured - predicted, tracker frame (mm)
    residual_machine: np.ndarray  # (N, M, 3) the same in the machine frame
    chi2: np.ndarray  # (N,)
    dof: int
    initial_error: np.ndarray  # (N, M, 3) machine-frame deviation after pose-only registration
    converged: np.ndarray  # (N,) bool
    iterations: int
    identifiability: Identifiability
    whitened: np.ndarray | None = None  # (N, M, 3) whitened residuals
    # at the solution, for callers that continue from it (diagnosis):
    whitener: np.ndarray | None = None  # (N, M, 3, 3) L^-1 of each point's covariance C = L L^T (tracker frame)
    basis: np.ndarray | None = None  # (p, r) orthonormal basis Q of the free, identifiable directions (scaled)
    scale: np.ndarray | None = None  # (p,) scale_vector(model): um per mm, urad per rad
    solver: str = "gauss-newton"
    fallback: np.ndarray | None = None  # (N,) bool: trials the chord solver handed to Gauss-Newton
    #: (N, M, 3) the machine points at the solution, ``model.machine_points(theta)`` (the same numbers, computed once
    #: by the chord solver for its residuals); None where the identification had fixed perturbations or another solver
    points: np.ndarray | None = None
    # design (N, 3M, 6 + r), cov_theta (N, p, p), cov_pose (N, 6, 6): properties below, at the solution
    _at_solution: dict = field(default_factory=dict, repr=False, compare=False)
    _solution_inputs: dict | None = field(default=None, repr=False, compare=False)

    # The unknowns of the design are z = (pose * POSE_SCALE, Q^T (theta * scale)): a step z moves the
    # pose by z[:6] / POSE_SCALE and theta by (Q z[6:]) / scale, and changes the whitened residual by
    # -design @ z.  cov_theta and cov_pose are (design^T design)^-1 mapped back to mm and rad.
    # Gauss-Newton keeps them from its last evaluation; the chord solver computes them from the exact
    # Jacobian at the solution the first time one of them is asked for (the engine never asks).

    @property
    def design(self) -> np.ndarray:
        """Whitened design in the scaled unknowns z at the solution: (N, 3M, 6 + r)."""
        return self._solution("design")

    @property
    def cov_theta(self) -> np.ndarray:
        """Covariance of the geometric parameters (N, p, p), mm and rad."""
        return self._solution("cov_theta")

    @property
    def cov_pose(self) -> np.ndarray:
        """Covariance of the pose (N, 6, 6), mm and rad."""
        return self._solution("cov_pose")

    def _solution(self, key):
        if key not in self._at_solution:
            self._at_solution.update(_solution_quantities(self, **self._solution_inputs))
        return self._at_solution[key]

    @property
    def n_fallback(self) -> int:
        """How many trials the chord solver could not finish and Gauss-Newton solved instead (0 for Gauss-Newton)."""
        return 0 if self.fallback is None else int(np.count_nonzero(self.fallback))

    @property
    def n_trials(self) -> int:
        return len(self.chi2)

    @property
    def n_not_converged(self) -> int:
        """How many trials did not converge (their results are not at the minimum: count them, do not average them in)."""
        return int(np.count_nonzero(~np.asarray(self.converged, bool)))

    @property
    def chi2_per_dof(self):
        return self.chi2 / self.dof

    @property
    def mean_error_before(self):
        """Paper Eq. 27 before compensation (mm): mean distance nominal vs measured after registration."""
        return lt.norm3(self.initial_error).mean(axis=-1)

    @property
    def mean_error_after(self):
        """Paper Eq. 27 after compensation (mm): mean residual distance."""
        return self._residual_distance().mean(axis=-1)

    @property
    def max_residual(self):
        return self._residual_distance().max(axis=-1)

    def _residual_distance(self) -> np.ndarray:
        """|residual| per point (N, M), computed once (the residuals are not changed after identification)."""
        hit = self._at_solution.get("residual_distance")
        if hit is None or hit[0] is not self.residual:
            hit = self._at_solution["residual_distance"] = (self.residual, lt.norm3(self.residual))
        return hit[1]

    @property
    def rms(self):
        """Root mean square of the 3D residual distance (mm)."""
        return np.sqrt((self.residual**2).sum(-1).mean(-1))

    def u_theta(self):
        return np.sqrt(np.maximum(np.diagonal(self.cov_theta, axis1=1, axis2=2), 0))


#: What an identification of a machine tool a laser tracker verifies can plausibly give.  Beyond these, the numbers
#: are not an identification of the machine but of a mistake (a column in inches labelled mm, degrees labelled rad,
#: a wrong machine code or stated noise), and no table may be written from them (docs/compensation.md,
#: "Implausible identifications"):
#: - chi-square per degree of freedom above ABSURD_CHI2_PER_DOF (residuals some 30 times the stated noise) with an
#:   RMS residual above ABSURD_RESIDUAL_RMS (0.1 mm), or above ABSURD_CHI2_ALONE (300 times the noise) whatever the
#:   residual: a real recording with an effect the model leaves out (thermal drift, reversal) stays within 1-100
#:   against a tracker's noise, but a tracking interferometer's 0.15 um makes 10 um of unmodelled drift a chi2/dof
#:   of 1000-10 000; no verification leaves 0.1 mm RMS after its geometric errors are identified, while a unit slip
#:   in a column leaves millimetres and one in the stated noise (nm for um) a chi2/dof near 10^6;
#: - a linear axis' positioning or straightness error changing by more than PLAUSIBLE_ERROR_PER_LENGTH (2 mm per
#:   metre) of its travel plus PLAUSIBLE_ERROR_FLOOR (0.1 mm): uncompensated machine tools show tens of um per
#:   metre, a steel scale 50 K off 20 degC 0.6 mm/m, so 2 mm/m is several times the worst and far below a unit
#:   slip (an inch read as a mm is 24 400 mm/m);
#: - an angular error (pitch, yaw, roll, a tool-holder tilt) or a squareness above PLAUSIBLE_ANGLE (2 mrad, the
#:   same 2 mm per metre of lever: machine tools show tens to hundreds of urad);
#: - the pose-only ("before") error larger than the measured volume itself (its diagonal plus the longest tool):
#:   a deviation the size of the machine is not a geometric error of it.
#: A value counts as beyond its bound only by more than 3 times its standard uncertainty (a short travel identifies
#: its higher orders loosely: noise is not a mistake).
ABSURD_CHI2_PER_DOF = 1e3
ABSURD_RESIDUAL_RMS = 0.1  # mm
ABSURD_CHI2_ALONE = 1e5
PLAUSIBLE_ERROR_PER_LENGTH = 2e-3
PLAUSIBLE_ERROR_FLOOR = 0.1  # mm
PLAUSIBLE_ANGLE = 2e-3  # rad
_PLAUSIBILITY_GRID = np.linspace(-1.0, 1.0, 41)


def _residual_rms(res, trial: int) -> float:
    """RMS of the fit's residuals (mm) of one trial of an identification, or of an identification over several
    stations (its xyz and range residuals; NaN where a row has none)."""
    if getattr(res, "residual_xyz", None) is not None:
        r = np.concatenate([np.asarray(res.residual_xyz, float).reshape(-1), np.asarray(res.residual_range, float)])
        r = r[np.isfinite(r)]
    else:
        r = np.asarray(res.residual, float)[trial].reshape(-1)
    return float(np.sqrt(np.mean(r ** 2))) if r.size else float("nan")


#: the level of the chi-square test of the fit against the recording's stated noise: below it, the statement warns
FIT_ALPHA = 1e-3


def fit_test(chi2_per_dof: float, dof: int, noise: str, recording: str, what: str = "this statement",
             then: str = "before signing") -> dict:
    """The chi-square test of the identification's fit against the recording's stated noise (upper and lower tails of
    chi2 with ``dof`` degrees of freedom) and, where either tail is below :data:`FIT_ALPHA`, the warning the statement
    carries: an a posteriori u (or a compensation table's, ``what``) assumes the model holds every physics the recording
    shows."""
    from scipy.special import gammainc, gammaincc

    x = chi2_per_dof * dof
    above, below = float(gammaincc(dof / 2, x / 2)), float(gammainc(dof / 2, x / 2))
    out = {"p_above": above, "p_below": below, "alpha": FIT_ALPHA, "warning": None}
    said = f"chi2/dof {chi2_per_dof:.3f} on {dof} degrees of freedom"
    if above < FIT_ALPHA:
        out["warning"] = (
            f"the identified model does not fit {recording} within its stated noise ({said}; P(chi2 >= that) = "
            f"{above:.2g} < {FIT_ALPHA:g}): the residuals hold more than the noise, most often a physics the model "
            f"leaves out (thermal, periodic, reversal ...), which {what} does not contain; find it with "
            f"`mtbudget diagnose {recording}` {then}" +
            ("" if noise == "estimated" else "; `--noise estimated` scales the noise by sqrt(chi2/dof), which treats "
                                             "what is left out as noise"))
    elif below < FIT_ALPHA:
        out["warning"] = (
            f"the residuals of {recording} are smaller than its stated noise allows ({said}; P(chi2 <= that) = "
            f"{below:.2g} < {FIT_ALPHA:g}): the stated noise is larger than the recording shows, so this u is "
            "conservative; check the stated tracker noise and repeatability")
    return out



def implausible(res: "Identification", trial: int = 0) -> list:
    """What in trial ``trial`` of ``res`` no machine tool can show (empty: nothing): one phrase per figure, naming
    it (the chi-square per dof, an ISO 230-1 error function with its value and bound, the pose-only error), worst
    first.  ``res`` may also be one identification over several stations (``multistation.MultiIdentification``:
    its chi-square and error functions; it has no pose-only registration).  ``mtbudget identify`` warns with them, ``mtbudget compensate`` refuses with them (see the bounds above)."""
    from numpy.polynomial import legendre as npleg

    from .model import iso_name

    out = []
    chi2 = float(np.atleast_1d(res.chi2_per_dof)[trial])
    rms = _residual_rms(res, trial)
    if not np.isfinite(chi2) or chi2 > ABSURD_CHI2_ALONE or (chi2 > ABSURD_CHI2_PER_DOF and not rms <= ABSURD_RESIDUAL_RMS):
        out.append((np.inf, f"chi-square per dof {chi2:.3g} (at most {ABSURD_CHI2_PER_DOF:g}, or "
                            f"{ABSURD_CHI2_ALONE:g} where the RMS residual, here {rms:.3g} mm, is under "
                            f"{ABSURD_RESIDUAL_RMS:g} mm)"))
    errors = res.model.errors
    theta = np.atleast_2d(np.asarray(res.theta, float))[trial]  # (N, p), or (p,): one identification of stations
    try:
        cov = np.asarray(res.cov_theta, float)
        cov = cov[trial] if cov.ndim == 3 else cov
    except Exception:  # no covariance at this solution (a singular design): the values alone
        cov = np.zeros((len(theta), len(theta)))
    if not np.all(np.isfinite(cov)):
        cov = np.zeros_like(cov)
    groups: dict = {}
    for j, p in enumerate(errors.params):
        if p.is_squareness:
            v, u = abs(theta[j]), np.sqrt(max(cov[j, j], 0.0))
            if not np.isfinite(v) or v - 3 * u > PLAUSIBLE_ANGLE:
                out.append((v / PLAUSIBLE_ANGLE, f"squareness {iso_name(p.error)} = {v * 1e3:.4g} mrad (at most "
                                                 f"{PLAUSIBLE_ANGLE * 1e3:g} mrad)"))
        elif p.error[3] in AXES:
            groups.setdefault(p.error, []).append(j)
    for err, idx in groups.items():
        axis = err[3]
        lo, hi = errors.ranges[axis]
        travel = hi - lo
        orders = [errors.params[j].order for j in idx]
        basis = np.stack([npleg.legval(_PLAUSIBILITY_GRID, np.eye(max(orders) + 1)[n]) for n in orders], axis=1)
        if err[0] == "d":  # a change along the travel, from its start: the constant term cancels
            basis = basis - basis[:1]
            bound = PLAUSIBLE_ERROR_PER_LENGTH * travel + PLAUSIBLE_ERROR_FLOOR
        else:
            bound = PLAUSIBLE_ANGLE
        values = basis @ theta[idx]
        u = np.sqrt(np.maximum(np.einsum("kj,jl,kl->k", basis, cov[np.ix_(idx, idx)], basis), 0.0))
        excess = np.where(np.isfinite(values), np.abs(values) - 3 * u, np.inf)
        k = int(np.argmax(excess))
        if excess[k] > bound:
            name = f"{iso_name(err)} ({err})"
            if err[0] == "d":
                per_m = PLAUSIBLE_ERROR_PER_LENGTH * 1e3
                out.append((abs(values[k]) / bound, f"{name} changes by {values[k]:.4g} mm over {travel:g} mm of "
                                                    f"travel (at most {bound:.3g} mm: {per_m:g} mm/m + "
                                                    f"{PLAUSIBLE_ERROR_FLOOR:g} mm)"))
            else:
                out.append((abs(values[k]) / bound, f"{name} reaches {values[k] * 1e3:.4g} mrad (at most "
                                                    f"{bound * 1e3:g} mrad)"))
    if getattr(res, "initial_error", None) is None:  # several stations: no pose-only registration to judge
        out.sort(key=lambda x: -x[0])
        return [text for _, text in out]
    before = float(res.mean_error_before[trial])
    extent = float(np.sqrt(sum((hi - lo) ** 2 for lo, hi in errors.ranges.values())))
    tool = np.asarray(res.model.plan.tool, float)
    extent += float(np.abs(tool).max()) if tool.size else 0.0
    extent = max(extent, PLAUSIBLE_ERROR_FLOOR)
    if not np.isfinite(before) or before > extent:
        out.append((before / extent if np.isfinite(before) else np.inf,
                    f"the mean error before compensation {before:.4g} mm is larger than the measured volume "
                    f"({extent:.4g} mm: its diagonal and the longest tool)"))
    out.sort(key=lambda x: -x[0])
    return [text for _, text in out]


#: the scaled parameter units: lengths in um, angles in urad (on a 1 m lever both are um of effect)


_SCALES: dict = {}


def scale_vector(model: MeasurementModel) -> np.ndarray:
    """um per mm and urad per rad: parameters in comparable effect units."""
    units = tuple(model.errors.units)
    for u in units:
        if u not in _SCALES:
            _SCALES[u] = factor(u, shown_unit(u))
    return np.array([_SCALES[u] for u in units])


#: scale of the pose (D, L, H in mm; a, b, d in rad), as :func:`scale_vector`
POSE_SCALE = np.array([factor("mm", "um")] * 3 + [factor("rad", "urad")] * 3)


def group_of(param) -> str:
    if param.is_squareness:
        return "squareness"
    return "translational" if param.error[0] == "d" else "angular"


def analyse(model: MeasurementModel, active: np.ndarray | None = None, rank_tol: float = 1e-7) -> Identifiability:
    """Structural identifiability of the plan for the active geometric parameters."""
    p = model.n_params
    active = np.ones(p, bool) if active is None else np.asarray(active, bool)
    P0, J = model.machine_points(np.zeros((1, p)), jacobian=True)
    P0, J = P0[0], J[0]  # (M,3), (M,3,p)
    M = P0.shape[0]
    rigid = np.zeros((M, 3, 6))
    rigid[:, :, :3] = np.eye(3)[None] / POSE_SCALE[:3]
    centred = P0 - P0.mean(axis=0)
    K = skew_basis()
    for c in range(3):
        rigid[:, :, 3 + c] = (centred @ K[c].T) / POSE_SCALE[3 + c]
    Js = J[:, :, active] / scale_vector(model)[active]
    A = np.concatenate([rigid, Js], axis=2).reshape(3 * M, -1)
    # equilibrate columns for the rank decision (scaling does not change the null space)
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    # the full V is needed only when there are fewer rows than unknowns (LAPACK's full U costs 10x more)
    _, s, Vt = np.linalg.svd(A / norms, full_matrices=A.shape[0] < A.shape[1])
    tol = rank_tol * (s[0] if s.size else 1.0)
    rank = int((s > tol).sum())
    V = (Vt.T / norms[:, None])  # back to scaled (unequilibrated) coordinates
    null = V[:, rank:]
    # rigid-only rank
    sr = np.linalg.svd(rigid.reshape(3 * M, 6) / np.linalg.norm(rigid.reshape(3 * M, 6), axis=0), compute_uv=False)
    pose_ok = bool(sr[-1] > rank_tol * sr[0])
    null_geo = np.zeros((p, null.shape[1]))
    null_rigid = np.zeros((6, 0))
    if null.shape[1]:
        # orthonormal basis of the geometric part of the null space
        ng = null[6:, :]
        q, r = np.linalg.qr(ng)
        keep = np.abs(np.diag(r)) > 1e-12 if r.size else np.zeros(0, bool)
        null_geo[active] = q[:, keep] if keep.size else q
        null_geo = null_geo[:, : int(keep.sum())] if keep.size else null_geo
        # q = ng r^-1: the same combinations of the joint null vectors carry the rigid motions null[:6] r^-1
        null_rigid = null[:6, :] @ np.linalg.inv(r) if keep.all() else None
    names = model.errors.names
    return Identifiability(names, rank, int(active.sum()), s, null_geo, pose_ok, null_rigid=null_rigid)


def whitener(C: np.ndarray) -> np.ndarray:
    """L^-1 with C = L L^T, batched (…, 3, 3): ``whitener(C) @ r`` has unit covariance.

    3 x 3 blocks are factorised and inverted in closed form, elementwise over the batch (the same
    numbers as ``inv(cholesky(C))`` to round-off, several times faster than LAPACK's batched calls on
    blocks this small); anything else, or a block that is not positive definite, goes through numpy.
    """
    C = np.asarray(C, float)
    if C.shape[-2:] != (3, 3):
        return np.linalg.inv(np.linalg.cholesky(C))
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = np.sqrt(C[..., 0, 0])
        l10, l20 = C[..., 1, 0] / l00, C[..., 2, 0] / l00
        l11 = np.sqrt(C[..., 1, 1] - l10 * l10)
        l21 = (C[..., 2, 1] - l20 * l10) / l11
        l22 = np.sqrt(C[..., 2, 2] - l20 * l20 - l21 * l21)
        out = np.zeros(C.shape)
        out[..., 0, 0] = i00 = 1.0 / l00
        out[..., 1, 1] = i11 = 1.0 / l11
        out[..., 2, 2] = i22 = 1.0 / l22
        out[..., 1, 0] = -l10 * i00 * i11
        out[..., 2, 1] = -l21 * i11 * i22
        out[..., 2, 0] = (l10 * l21 - l20 * l11) * i00 * i11 * i22
    if not np.isfinite(out).all():  # not positive definite (or not finite): numpy says so
        return np.linalg.inv(np.linalg.cholesky(C))
    return out


SOLVERS = ("chord", "gauss-newton")


# ----------------------------------------------------------------------------- what depends on the plan only
_PLAN_CACHE: dict = {}


def _fingerprint(model: MeasurementModel) -> tuple:
    """Everything the cached plan quantities depend on: configuration, parameters, ranges, plan points, tools; the
    values themselves (the arrays' shapes and bytes), compared whole rather than hashed: a comparison of the five-axis
    example's 430 kB is 20 us, its blake2b hash was 440 us, paid on every identification call (four per block of the
    engine: 27 us a trial, issue 31)."""
    parts = [model.config.code, "\0".join(model.errors.names),
             repr(sorted((a, tuple(map(float, r))) for a, r in model.errors.ranges.items()))]
    for a in (model.plan.nominal, model.plan.tool, model.B):
        a = np.ascontiguousarray(a, float)
        parts += [a.shape, a.tobytes()]
    return tuple(parts)


def _plan_cache(model: MeasurementModel) -> dict:
    """The cache of what identification computes from the plan and error model alone, for this model object.

    Keyed by the object's id, guarded by a weak reference (an id the interpreter reuses after the
    model is gone does not match, and the entry goes with the model) and by a fingerprint of what
    the entries depend on (a model changed in place gets a fresh entry).
    """
    key = id(model)
    fp = _fingerprint(model)
    entry = _PLAN_CACHE.get(key)
    if entry is not None and entry[0]() is model and entry[1] == fp:
        return entry[2]

    def drop(ref, key=key):
        e = _PLAN_CACHE.get(key)
        if e is not None and e[0] is ref:
            del _PLAN_CACHE[key]

    data: dict = {}
    _PLAN_CACHE[key] = (weakref.ref(model, drop), fp, data)
    return data


def _read_only(*arrays):
    for a in arrays:
        if isinstance(a, np.ndarray):
            a.flags.writeable = False
    return arrays


def null_coordinates(ident: Identifiability, theta_scaled: np.ndarray) -> np.ndarray:
    """The coordinates c of what the identification cannot see in scaled parameters ``theta_scaled`` (p,): the
    identified parameters are ``theta - null_space @ c`` (scaled).  Minimum norm: the orthogonal projection
    ``null_space^T theta``; under a datum (``ident.held``): the held parameters' values, ``solve(null_space[held],
    theta[held])``."""
    N = ident.null_space
    if ident.held is None:
        return N.T @ theta_scaled
    return np.linalg.solve(N[ident.held, :], theta_scaled[ident.held])


def datum_parameters(model: MeasurementModel, null: np.ndarray, active: np.ndarray | None = None) -> list:
    """The datum of a machine with rotary axes: which parameters are held at zero, one per direction of the null
    space ``null`` (p, k) the plan at hand leaves (computed, never assumed), chosen by the rule of
    docs/model.md ("Five-axis machines: the datum"), in this order of preference:

    1. the zero error of the workpiece-side rotary axis that carries the workpiece (and the tracker on it): the
       table's angular zero is the tracker's;
    2. a rotary axis' orientation error about the direction of the rotary axis that carries it: reported as the
       carrier's zero error, which a controller corrects;
    3. the location offsets of the rotary axes, the one nearest the bed first (a constant offset of the tool or
       of the linear axes' zero is theirs: the tool offsets are exact);
    4. any other parameter, in the model's order.

    A parameter is taken when it makes the held set see one more null direction (its row of ``null`` is not in
    the span of the rows taken), so the held parameters fix every null direction exactly once."""
    from .machine import AXES, ROTARY_INDEX

    p, k = null.shape
    if k == 0:
        return []
    names = model.errors.names
    where = {n: j for j, n in enumerate(names)}
    cfg = model.config
    order = []
    if cfg.workpiece and cfg.workpiece[-1] in ROTARY_INDEX:
        r = cfg.workpiece[-1]
        order.append(f"e{AXES[ROTARY_INDEX[r]]}({r})[O]")
    for side in (cfg.workpiece, cfg.tool):
        for carrier, carried in zip(side, side[1:]):
            if carrier in ROTARY_INDEX and carried in ROTARY_INDEX:
                order.append(f"e{AXES[ROTARY_INDEX[carrier]]}({carried})[O]")
    chain_order = list(cfg.workpiece) + list(cfg.tool)
    for r in sorted((a for a in chain_order if a in ROTARY_INDEX), key=lambda a: min(
            cfg.workpiece.index(a) if a in cfg.workpiece else 99, cfg.tool.index(a) if a in cfg.tool else 99)):
        order += [f"d{c}({r})[O]" for c in AXES]
    prefer = [where[n] for n in order if n in where]
    prefer += [j for j in range(p) if j not in prefer]
    if active is not None:
        prefer = [j for j in prefer if active[j]]
    held: list = []
    scale = np.abs(null).max()
    for j in prefer:
        rows = null[held + [j], :]
        if np.linalg.matrix_rank(rows, tol=1e-6 * scale) == len(held) + 1:
            held.append(j)
            if len(held) == k:
                break
    return held


def phase_actives(model, phases, pose_why: str) -> list:
    """The geometric parameters each phase of a strategy frees ((p,) bool per phase), each phase checked: its groups
    from :data:`GROUPS`, and the pose among them (``pose_why``: why it is always unknown).  The one reading of
    ``Strategy.phases`` for one tracker and several stations (``multistation.phase_masks``)."""
    out = []
    for phase in phases:
        unknown = set(phase) - set(GROUPS)
        if unknown:
            raise IdentificationError(f"unknown parameter group(s) {sorted(unknown)} in strategy phase; expected {GROUPS}")
        if "pose" not in phase:
            raise IdentificationError(f"every phase must include the pose ({pose_why})")
        out.append(np.array([group_of(par) in phase for par in model.errors.params], bool))
    return out


def _phase(model, cache, active, rank_tol):
    """(identifiability, basis Q) of the active parameters: the SVDs, once per model, mask and rank tolerance."""
    key = ("phase", active.tobytes(), float(rank_tol))
    if key not in cache:
        ident = analyse(model, active, rank_tol)
        if model.rotary:  # the datum rule: held parameters, the others free (docs/model.md)
            ident.held = datum_parameters(model, ident.null_space, active)
            free = active.copy()
            free[ident.held] = False
            Q = np.eye(active.size)[:, free]
        else:
            Q = range_basis(active, ident.null_space)
        _read_only(ident.null_space, ident.singular_values, Q)
        cache[key] = (ident, Q)
    return cache[key]


def _nominal(model, cache, Q):
    """Machine points at theta = 0 (M, 3) and their Jacobian along the scaled directions Q / scale (M, 3, r)."""
    key = ("nominal", Q.tobytes(), Q.shape)
    if key not in cache:
        P0, J0 = model.machine_points(np.zeros((1, model.n_params)), jacobian=True,
                                      project=Q / scale_vector(model)[:, None])
        cache[key] = _read_only(P0[0], J0[0])
    return cache[key]


def _check_inputs(model: MeasurementModel, meas: np.ndarray, cache: dict | None = None):
    if meas.shape[-2:] != (model.n_points, 3):
        raise IdentificationError(f"measured points have shape {meas.shape[-2:]}, the plan has {model.n_points} points x 3")
    if not np.isfinite(meas).all():  # (a reduction over the whole array first: the point-wise one is 25x slower)
        bad = ~np.isfinite(meas).all(axis=-1)
        rows = np.unique(np.nonzero(bad)[-1])[:10]
        raise IdentificationError(
            f"measured coordinates are NaN or infinite at plan rows {rows.tolist()} "
            "(0-based); remove or repair those points before identifying")
    if cache is not None and cache.get("plan_checked"):
        return
    nominal = model.plan.nominal
    for a in AXES:
        npos = len(np.unique(np.round(nominal[:, AXIS_INDEX[a]], 6)))
        for name, deg in model.errors.degrees.items():
            if name[3] == a and deg and deg > npos - 1:
                raise IdentificationError(
                    f"{name} has degree {deg} but axis {a} is measured at only {npos} distinct position(s); "
                    f"at most degree {max(npos - 1, 0)} can be identified (lower it in the error model)")
    # the nominal tool points in the tracker's (workpiece) frame: a five-axis plan turns them with its rotary axes
    pts = model.machine_points(np.zeros((1, model.n_params)))[0] if model.rotary else nominal + model.plan.tool
    sv = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-12):
        raise IdentificationError("all measured points lie on one line: the tracker rotation about it cannot be identified")
    if cache is not None:
        cache["plan_checked"] = True


def _rows(fixed: dict, idx, N: int) -> dict:
    """The fixed perturbations of the trials ``idx`` (those given per trial are indexed, the others broadcast)."""
    return {k: (v[idx] if np.ndim(v) and np.shape(v)[0] == N and N > 1 else v) for k, v in fixed.items()}


#: the most measured points one identification takes (a guard against a recording that would exhaust the memory)
MAX_POINTS = 100_000


def default_chunk(n_points: int, n_params: int) -> int:
    """The trials :func:`identify` solves together when not told (``chunk=None``, no ``groups``): about 8 MB of
    Jacobian per chunk, at least 16.  The chord solver's trials of one chunk share an iteration matrix (their mean
    information), so a trial's bits depend on the trials of its chunk: calls on pieces of the trials that are
    multiples of this give the numbers of one call."""
    return max(16, int(8e6 // (n_points * 3 * max(n_params, 1) * 8)))


def identify(
    model: MeasurementModel,
    measured: np.ndarray,
    noise: Noise,
    strategy: Strategy | None = None,
    theta0: np.ndarray | None = None,
    pose0: np.ndarray | None = None,
    fixed: dict | None = None,
    chunk: int | None = None,
    groups: np.ndarray | None = None,
    iteration_pose: np.ndarray | None = None,
) -> Identification:
    """Identify pose and geometric errors for one or N trials.

    measured: (M, 3) or (N, M, 3) tracker coordinates (mm).
    theta0: initial geometric parameters (p,) or (N, p); non-identifiable
    directions keep their initial value (zero by default).
    pose0: initial pose; by default the Kabsch registration of the predicted points.
    fixed: perturbations known a priori (``MODEL_INPUTS`` keys, broadcastable
    over trials), e.g. a thermal scale that a diagnosis candidate asserts.
    chunk: trials solved together (default: about 8 MB of Jacobian per chunk, which
    keeps the working set in cache; larger chunks are slower, not faster).  The chord
    solver shares one factorisation per chunk.

    groups: (N,) labels, chord solver only: the trials of a label share an iteration matrix, and a
    trial's result depends on the trials of its own label only, bit for bit, as if each label were
    identified alone (the engine passes one label per block; ``chunk`` is then ignored, the labels
    are the chunks).

    iteration_pose: (6,) the trials' nominal tracker pose, chord solver only: the iteration matrices are
    then computed once from the nominal points seen from it and shared by every trial (cached), instead
    of from each label's mean information; the solution does not depend on them (only how fast the
    iterations reach it), and a trial's result still depends on its own label only.

    The result says which solver ran (``solver``) and, for the chord solver, which
    trials it handed to Gauss-Newton (``fallback``, ``n_fallback``).
    """
    strategy = strategy or Strategy()
    if strategy.solver not in SOLVERS:
        raise IdentificationError(f"unknown solver {strategy.solver!r}; expected one of {', '.join(SOLVERS)}")
    meas = np.asarray(measured, float)
    if meas.ndim == 2:
        meas = meas[None]
    cache = _plan_cache(model)
    _check_inputs(model, meas, cache)
    fixed = dict(fixed or {})
    if "spherical_noise" in fixed:
        raise IdentificationError("spherical_noise cannot be a fixed perturbation in identification")
    if "tracker_offset" in fixed:  # a known displacement in the tracker frame: take it off the measurement
        meas = meas - np.broadcast_to(fixed.pop("tracker_offset"), meas.shape)
    N, M = meas.shape[:2]
    if M > MAX_POINTS:  # the working set grows with M (measured: 3.7 GB and 36 s for 1e5 points, docs/performance.md)
        raise IdentificationError(
            f"{M} measured points in one identification; at most {MAX_POINTS} (it holds about 37 kB per point: "
            f"{M * 37e3 / 1e9:.0f} GB here); a verification measures hundreds to a few thousand points: thin the "
            "recording or identify its runs apart")
    p = model.n_params

    # identifiability of each phase (depends on the plan only: computed once per model, see _plan_cache)
    phases = []
    for active in phase_actives(model, strategy.phases, "the tracker pose is always unknown"):
        ident, Q = _phase(model, cache, active, strategy.rank_tol)
        if not ident.pose_identifiable:
            raise IdentificationError("the plan's points do not fix the tracker pose (all points on a line)")
        n_unknown = 6 + ident.identifiable
        if 3 * M <= n_unknown:
            raise IdentificationError(
                f"too few points: {M} points give {3 * M} coordinates for {n_unknown} identifiable unknowns "
                f"(no redundancy left); measure more points or lower the degrees of the error functions")
        phases.append((active, ident, Q))

    theta0 = np.zeros((N, p)) if theta0 is None else np.broadcast_to(np.asarray(theta0, float), (N, p))
    pose0 = None if pose0 is None else np.broadcast_to(np.asarray(pose0, float), (N, 6))
    if chunk is None:
        chunk = default_chunk(M, p)
    chord = strategy.solver == "chord"
    parts = []
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (N,):
            raise IdentificationError(f"groups must hold one label per trial ({N}), got shape {groups.shape}")
        if chord:
            parts.append(_identify_chunk_chord(model, meas, noise, strategy, theta0.copy(),
                                               None if pose0 is None else pose0.copy(), fixed, phases, cache,
                                               labels=groups, iteration_pose=iteration_pose))
        else:  # Gauss-Newton treats every trial alone: the labels are the chunks
            for k in np.unique(groups):
                idx = np.flatnonzero(groups == k)
                parts.append(_identify_chunk(model, meas[idx], noise, strategy, theta0[idx].copy(),
                                             None if pose0 is None else pose0[idx].copy(), _rows(fixed, idx, N),
                                             phases))
            order = np.argsort(np.concatenate([np.flatnonzero(groups == k) for k in np.unique(groups)]), kind="stable")
            parts = [_reorder(parts, order)]
    for lo in range(0, N if groups is None else 0, chunk):
        sl = slice(lo, min(N, lo + chunk))
        args = (model, meas[sl], noise, strategy, theta0[sl].copy(), None if pose0 is None else pose0[sl].copy(),
                _rows(fixed, sl, N), phases)
        parts.append(_identify_chunk_chord(*args, cache, iteration_pose=iteration_pose) if chord
                     else _identify_chunk(*args))
    # one part (the engine's call: its labels are one chunk): its arrays as they are, no copy
    cat = (lambda key: parts[0][key]) if len(parts) == 1 else (  # noqa: E731
        lambda key: np.concatenate([q[key] for q in parts], axis=0))
    res = Identification(
        model=model, theta=cat("theta"), pose=cat("pose"), residual=cat("residual"),
        residual_machine=cat("residual_machine"), chi2=cat("chi2"), dof=parts[0]["dof"],
        initial_error=cat("initial_error"), converged=cat("converged"),
        iterations=max(q["iterations"] for q in parts), identifiability=phases[-1][1], whitened=cat("whitened"),
        whitener=cat("whitener"), basis=phases[-1][2], scale=scale_vector(model), solver=strategy.solver,
        fallback=cat("fallback") if chord else None,
        points=cat("points") if all(q.get("points") is not None for q in parts) else None)
    if chord:  # design and covariances at the solution: exact, computed when first asked for
        res._solution_inputs = {"measured": meas, "fixed": fixed, "chunk": chunk}
    else:
        res._at_solution.update(design=cat("design"), cov_theta=cat("cov_theta"), cov_pose=cat("cov_pose"))
    return res


def _reorder(parts: list, order: np.ndarray) -> dict:
    """The chunk results ``parts`` concatenated and put back in the trials' order."""
    out = dict(parts[0])
    for key, v in parts[0].items():
        if isinstance(v, np.ndarray) and v.ndim and key not in ("dof",):
            out[key] = np.concatenate([q[key] for q in parts], axis=0)[order]
    out["iterations"] = max(q["iterations"] for q in parts)
    return out


def _weights(model, meas, noise, strategy):
    """Each point's whitener (N, M, 3, 3) from the stated uncertainties, evaluated at the measured points."""
    N, M = meas.shape[:2]
    if strategy.weighted:
        C = model.covariance(meas, noise.angular, noise.distance, noise.distance_per_length, noise.repeatability)
    else:
        C = np.broadcast_to(np.eye(3) * (noise.distance**2 + noise.repeatability**2), (N, M, 3, 3))
    return whitener(C)


def _weights_information(model, meas, noise, strategy):
    """Each point's whitener Wh (N, M, 3, 3) (:func:`_weights`) and information matrix C^-1 = Wh^T Wh,
    component-major (3, 3, N, M): in one compiled pass (:func:`mtbudget.kernels.point_weights`) for the stated
    scalar noise, else (unweighted, noise given per point, or a covariance numpy must judge) with numpy."""
    N, M = meas.shape[:2]
    stated = [noise.angular, noise.distance, noise.distance_per_length, noise.repeatability]
    if CHORD_KERNEL and strategy.weighted and all(np.ndim(v) == 0 for v in stated):
        from .kernels import point_weights

        Wh, WLc = np.empty((N, M, 3, 3)), np.empty((3, 3, N, M))
        if point_weights(kernel_array(meas), *(float(v) for v in stated), Wh, WLc):
            return Wh, WLc
    Wh = _weights(model, meas, noise, strategy)
    return Wh, np.ascontiguousarray(_gram33(Wh).transpose(2, 3, 0, 1))


def _covariances(A, Q, sv):
    """cov_theta (N, p, p) and cov_pose (N, 6, 6) from the whitened design A (N, 3M, 6 + r) in the scaled unknowns."""
    p, n_unknown = Q.shape[0], A.shape[2]
    AtA = np.swapaxes(A, 1, 2) @ A
    cov_z = np.linalg.inv(AtA)
    T = np.zeros((6 + p, n_unknown))
    T[:6, :6] = np.diag(1.0 / POSE_SCALE)
    T[6:, 6:] = Q / sv[:, None]
    cov_full = T @ cov_z @ T.T
    return cov_full[:, 6:, 6:], cov_full[:, :6, :6]


def _solution_quantities(res: Identification, measured, fixed, chunk) -> dict:
    """Design and covariances at the solution, from the chain's exact Jacobian there (chord solver)."""
    model, Q, sv = res.model, res.basis, res.scale
    N = len(res.theta)
    designs, cth, cpo = [], [], []
    for lo in range(0, N, chunk):
        sl = slice(lo, min(N, lo + chunk))
        P_W, J = model.machine_points(res.theta[sl], _rows(fixed, sl, N), jacobian=True, project=Q / sv[:, None])
        A = design_matrix(P_W, J, res.pose[sl], res.whitener[sl], Q, sv)
        ct, cp = _covariances(A, Q, sv)
        designs.append(A)
        cth.append(ct)
        cpo.append(cp)
    return {"design": np.concatenate(designs), "cov_theta": np.concatenate(cth), "cov_pose": np.concatenate(cpo)}


def _identify_chunk(model, meas, noise, strategy, theta, pose, fixed, phases, with_covariance=True):
    N, M = meas.shape[:2]
    if M > MAX_POINTS:  # the working set grows with M (measured: 3.7 GB and 36 s for 1e5 points, docs/performance.md)
        raise IdentificationError(
            f"{M} measured points in one identification; at most {MAX_POINTS} (it holds about 37 kB per point: "
            f"{M * 37e3 / 1e9:.0f} GB here); a verification measures hundreds to a few thousand points: thin the "
            "recording or identify its runs apart")
    p = model.n_params
    sv = scale_vector(model)
    Wh = _weights(model, meas, noise, strategy)

    # registration: Kabsch start, then the weighted pose-only fit of the nominal points.
    # Its deviations are the "before compensation" errors of Eq. 27.
    P_nom = np.broadcast_to(model.machine_points(np.zeros((1, p)), fixed), (N, M, 3))
    if pose is None:
        pose = lt.register(model.machine_points(theta, fixed), meas)
    pose_nom = _fit_pose(P_nom, meas, Wh, lt.register(P_nom, meas), strategy)
    initial_error = lt.to_machine(meas, pose_nom) - P_nom

    iters = 0
    converged = np.ones(N, bool)
    for active, ident, Q in phases:
        theta, pose, conv, it, (P_W, J, w) = _gauss_newton(model, meas, Wh, theta, pose, Q, strategy, fixed)
        iters += it
        converged &= conv
    if len(phases) > 1:  # the solution on the last phase's datum (see _on_datum), evaluated there
        R = lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5])
        T = pose[:, :3].copy()
        c0 = model.machine_points(np.zeros((1, p)))[0].mean(axis=0)  # analyse's centroid
        theta = theta.copy()
        _on_datum(model, phases[-1][1], theta, R, T, c0)
        angles = lt.euler_from_rotation(R)
        angles = pose[:, 3:] + (angles - pose[:, 3:] + np.pi) % (2 * np.pi) - np.pi
        pose = np.concatenate([T, angles], axis=1)
        P_W, J = model.machine_points(theta, fixed, jacobian=True, project=phases[-1][2] / sv[:, None])
        w = _whitened_residual(meas, P_W, pose, Wh)

    # final quantities and covariance at the solution (the last Gauss-Newton evaluation)
    Q = phases[-1][2]
    res = meas - lt.to_tracker(P_W, pose)
    Rm = lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5])
    out = {
        "theta": theta, "pose": pose, "residual": res, "residual_machine": np.einsum("nij,nmj->nmi", Rm, res),
        "chi2": (w**2).sum(axis=1), "dof": 3 * M - (6 + Q.shape[1]), "initial_error": initial_error,
        "converged": converged, "iterations": iters, "whitened": w.reshape(N, M, 3), "whitener": Wh,
    }
    if with_covariance:
        A = design_matrix(P_W, J, pose, Wh, Q, sv)
        out["design"] = A
        out["cov_theta"], out["cov_pose"] = _covariances(A, Q, sv)
    return out


# ----------------------------------------------------------------------------- the chord solver
#: the chord's Jacobian refresh happens once the steps are below this (um, urad): near enough to the
#: minimum that the exact Jacobian there leaves a negligible bias (see the module docstring)
_REFRESH_STEP = 0.1
#: a chord iteration must shrink the step at least this much, or the trial goes to Gauss-Newton
_MAX_RATE = 0.5


def _spd_inverse(H: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix, equilibrated by its diagonal."""
    d = 1.0 / np.sqrt(H.diagonal())
    Li = np.linalg.inv(np.linalg.cholesky(H * d[:, None] * d[None, :]))
    return (Li.T @ Li) * d[:, None] * d[None, :]


def _rotation(om: np.ndarray) -> np.ndarray:
    """The exact rotation expm([om]x) (n, 3, 3) for rotation vectors om (n, 3): Rodrigues, with
    [om]x^2 = om om^T - |om|^2 I (the same as :func:`mtbudget.machine.rotation_exact`, in fewer operations)."""
    t2 = (om * om).sum(axis=1)
    small = t2 < 1e-12  # series: exact to double precision below |om| = 1e-6 rad
    t = np.sqrt(np.where(small, 1.0, t2))
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(t)) / np.where(small, 1.0, t2))
    n = om.shape[0]
    # [om]x as (n, 9) from one product with a constant 0/+-1 matrix (exact: one non-zero term per entry)
    R = (om @ _SKEW9) * a[:, None] + (om[:, :, None] * om[:, None, :]).reshape(n, 9) * b[:, None]
    R[:, ::4] += (1.0 - b * t2)[:, None]  # the diagonal
    return R.reshape(n, 3, 3)


#: [om]x = (om @ _SKEW9).reshape(3, 3)
_SKEW9 = np.stack([skew(e).reshape(9) for e in np.eye(3)])


def _rigid_columns(P: np.ndarray, c0: np.ndarray) -> np.ndarray:
    """d(machine-frame point)/d(small rigid motion): translation, then rotation about c0; scaled by POSE_SCALE."""
    G = np.zeros(P.shape[:-1] + (3, 6))
    G[..., :3] = np.eye(3)
    G[..., 3:] = -skew(P - c0)
    return G / POSE_SCALE


class _Labels:
    """Which trials share an iteration matrix, and the row positions of each label among any subset of trials.

    Everything that mixes trials in a BLAS product (the iteration matrices, products over the trial axis) is
    done label by label, on the same rows as if the label were identified alone: a trial's result then depends
    on the trials of its own label only, bit for bit (the engine identifies several blocks in one call, one
    label per block, and promises the numbers of each block alone).
    """

    def __init__(self, labels: np.ndarray | None, N: int):
        self.of = np.zeros(N, np.intp) if labels is None else np.unique(np.asarray(labels), return_inverse=True)[1]
        self.n = int(self.of.max()) + 1 if N else 0

    def split(self, rows: np.ndarray):
        """[(label, positions in ``rows``)] of the labels present among ``rows``: slices when each label's rows
        are contiguous (the engine's blocks, in order), index arrays otherwise."""
        if self.n == 1:
            return [(0, slice(None))]
        lab = self.of[rows]
        if lab.size and (lab[1:] >= lab[:-1]).all():
            bounds = [0, *(np.flatnonzero(lab[1:] != lab[:-1]) + 1).tolist(), lab.size]
            return [(int(lab[lo]), slice(lo, hi)) for lo, hi in itertools.pairwise(bounds)]
        return [(k, np.flatnonzero(lab == k)) for k in np.unique(lab)]


def _per_label(parts, rows, fn, width):
    """Rows of ``fn(label, positions)`` (each (len(positions), width)) gathered in the order of ``rows``."""
    if len(parts) == 1:
        return fn(*parts[0])
    out = np.empty((len(rows), width))
    for k, pos in parts:
        out[pos] = fn(k, pos)
    return out


def _identify_chunk_chord(model, meas, noise, strategy, theta, pose0, fixed, phases, cache, labels=None,
                          iteration_pose=None):
    """The chord solver on one chunk of trials (see the module docstring); falls back to Gauss-Newton per trial.

    labels: (N,) the trials that share an iteration matrix (default: all of them), see :class:`_Labels`.
    iteration_pose: (6,) the trials' nominal tracker pose: the iteration matrices are then those of the
    nominal points seen from it (the same for every trial and label, computed once per model, phase, pose
    and noise, and cached) instead of each label's mean information."""
    N, M = meas.shape[:2]
    if M > MAX_POINTS:  # the working set grows with M (measured: 3.7 GB and 36 s for 1e5 points, docs/performance.md)
        raise IdentificationError(
            f"{M} measured points in one identification; at most {MAX_POINTS} (it holds about 37 kB per point: "
            f"{M * 37e3 / 1e9:.0f} GB here); a verification measures hundreds to a few thousand points: thin the "
            "recording or identify its runs apart")
    p = model.n_params
    sv = scale_vector(model)
    lab = _Labels(labels, N)
    Wh, WLc = _weights_information(model, meas, noise, strategy)
    WL = WLc.transpose(2, 3, 0, 1)  # information matrix of each point, tracker frame (N, M, 3, 3): C^-1 = Wh^T Wh
    tol = min(strategy.xtol, strategy.chord_tol)
    refresh = max(tol, _REFRESH_STEP)
    theta_start = theta.copy()

    # the iteration matrices: the plan's nominal Jacobians with each label's mean information (machine frame)
    Q_last = phases[-1][2]
    P0, _ = _nominal(model, cache, Q_last)
    c0 = P0.mean(axis=0)
    # the nominal machine with the fixed inputs: one row, or one per trial where a fixed input is given per trial
    n_fix = max([np.shape(v)[0] for v in fixed.values() if np.ndim(v) >= 2 and np.shape(v)[0] > 1], default=1)
    P_fix = model.machine_points(np.zeros((n_fix, p)), fixed) if fixed else P0[None]  # (1 or N, M, 3)
    P_nom = np.broadcast_to(P_fix, (N, M, 3))
    all_rows = np.arange(N)
    shared = iteration_pose is not None and all(np.ndim(v) == 0 or np.shape(v)[0] == 1 for v in fixed.values())
    # the trials' nominal pose is known (the engine's simulated poses scatter about it): the pose-only fit starts
    # there, and Kabsch registers only the trials whose fit does not converge from it (the fit's minimum is then
    # the one next to the nominal pose; a tracker far from it is found by Kabsch, as without a nominal pose)
    if shared:
        pose_n = np.asarray(iteration_pose, float).reshape(1, 6)
        pose_k = np.repeat(pose_n, N, axis=0)
        Rk = np.repeat(lt.rotation(pose_n[:, 3], pose_n[:, 4], pose_n[:, 5]), N, axis=0)
        registered = np.zeros(N, bool)
    else:  # a Kabsch registration of every trial
        pose_k = lt.register(P_nom, meas)
        Rk = lt.rotation(pose_k[:, 3], pose_k[:, 4], pose_k[:, 5])
        registered = np.ones(N, bool)

    def register(idx):  # the Kabsch start of the trials idx, where the nominal pose was the start so far
        pk = lt.register(P_nom[idx], meas[idx])
        pose_k[idx], Rk[idx], registered[idx] = pk, lt.rotation(pk[:, 3], pk[:, 4], pk[:, 5]), True

    if shared:  # the nominal points' information seen from the nominal pose: one matrix for every trial
        key_n = ("iteration", pose_n.tobytes(), _noise_key(noise), strategy.weighted,
                 tuple(sorted((k, np.asarray(v).tobytes()) for k, v in fixed.items())))

        def nominal_information():  # R C^-1 R^T (M, 3, 3) of the nominal points, when first needed
            Rn = lt.rotation(pose_n[:, 3], pose_n[:, 4], pose_n[:, 5])[0]
            W_n = _gram33(_weights(model, lt.to_tracker(P_nom[:1], pose_n), noise, strategy))[0]
            return {0: Rn @ W_n @ Rn.T}
    else:  # mean over the label of R C^-1 R^T (two batched products rather than N M small ones)
        X = (WL.reshape(N, 3 * M, 3) @ np.swapaxes(Rk, 1, 2)).reshape(N, M, 3, 3)  # C^-1 R^T
        X = (Rk @ X.transpose(0, 2, 1, 3).reshape(N, 3, 3 * M)).reshape(N, 3, M, 3)  # R C^-1 R^T, axes (n, i, m, l)
        W_bars = {k: (X[pos] if lab.n > 1 else X).mean(axis=0).transpose(1, 0, 2) for k, pos in lab.split(all_rows)}
    hit = cache.get(("rigid_columns", id(P0)))  # P0 is the plan cache's (read-only, kept beside its columns)
    if hit is None or hit[0] is not P0:
        hit = cache[("rigid_columns", id(P0))] = (P0, _read_only(_rigid_columns(P0, c0))[0])
    G0 = hit[1]

    def matrix(J, Q=None):
        if shared:  # cached per model (the plan cache), phase, pose, noise and fixed inputs
            key = key_n + (None if Q is None else (Q.tobytes(), Q.shape),)
            if key not in cache:
                cache[key] = _iteration_matrices(G0, J, nominal_information())[0]
            return dict.fromkeys(range(lab.n), cache[key])  # one matrix, every label
        return _iteration_matrices(G0, J, W_bars)

    state = {"R": Rk.copy(), "T": pose_k[:, :3].copy(), "theta": theta}
    bad = np.zeros(N, bool)
    iters = 0

    # the weighted pose-only fit of the nominal points (Eq. 27 "before"); its gradient is exact, so is its minimum
    nom = {"R": Rk.copy(), "T": pose_k[:, :3].copy(), "theta": np.zeros((N, p))}
    kc = None
    if CHORD_KERNEL:  # nothing fixed (the engine's default): the same inputs for every chunk, built once per model
        kc = _chord_chain(model, fixed, N) if fixed else cache.get("chord_chain")
        if kc is None:
            kc = cache["chord_chain"] = _chord_chain(model, fixed, N)

    def chord(st, rows, evaluate, Hinv, J, Qs, tol_, first=None, predict=False, fixed_points=None):
        """A chord stage: compiled (:func:`_chord_compiled`) or the numpy reference (:func:`_chord`)."""
        if kc is None:
            return _chord(st, rows, evaluate, meas, WLc, Hinv, J, Qs, c0, tol_, strategy, lab, first=first,
                          predict=predict)
        adjoint = J is _ADJOINT
        return _chord_compiled(st, rows, meas, WLc, Hinv, None if adjoint else J, Qs, c0, tol_, strategy, lab, kc,
                               first=first, fixed_points=fixed_points, adjoint=model if adjoint else None,
                               predict=predict)

    ok, it = chord(nom, all_rows, lambda th, rows: P_nom[rows], matrix(None), None, None, tol, fixed_points=P_fix)
    again = np.flatnonzero(~ok & ~registered)
    if again.size:  # started at the nominal pose and not converged from there: again from a Kabsch registration
        register(again)
        nom["R"][again], nom["T"][again] = Rk[again], pose_k[again, :3]
        ok_again, it_again = chord(nom, again, lambda th, rows: P_nom[rows], matrix(None), None, None, tol,
                                   fixed_points=P_fix)
        ok[again] = ok_again
        it += it_again  # the trials fitted again ran both
    bad |= ~ok
    iters += it
    initial_error = None if kc is not None else _apply(nom["R"], meas) + nom["T"][:, None] - P_nom

    # the start of the identification: the given pose, else the pose-only fit (theta0 = 0) or a Kabsch registration
    if pose0 is not None:
        state["R"] = lt.rotation(pose0[:, 3], pose0[:, 4], pose0[:, 5])
        state["T"] = pose0[:, :3].copy()
        angles0 = pose0[:, 3:]
    else:
        at_zero = ~theta.any(axis=1)
        state["R"], state["T"] = nom["R"].copy(), nom["T"].copy()
        if not at_zero.all():
            idx = np.flatnonzero(~at_zero)
            pk = lt.register(model.machine_points(theta[idx], _rows(fixed, idx, N)), meas[idx])
            state["R"][idx] = lt.rotation(pk[:, 3], pk[:, 4], pk[:, 5])
            state["T"][idx] = pk[:, :3]
        angles0 = lt.euler_from_rotation(state["R"])

    def evaluate(th, rows):
        return model.machine_points(th, _rows(fixed, rows, N))

    for k, (active, ident, Q) in enumerate(phases):
        Qs = Q / sv[:, None]
        _, J0 = _nominal(model, cache, Q)
        Hinv = matrix(J0, Q)
        todo = np.flatnonzero(~bad)
        # stage 1: the nominal Jacobian (earlier phases only give the next one its start)
        ok, it = chord(state, todo, evaluate, Hinv, J0.reshape(3 * M, -1), Qs, refresh, predict=True)
        bad[todo[~ok]] = True
        iters += it
        if k < len(phases) - 1:
            continue
        # stage 2: each trial's exact Jacobian where stage 1 stopped, then chord iterations to the tolerance
        todo = np.flatnonzero(~bad)
        if todo.size:
            theta_c = state["theta"][todo].copy()
            P_c = None
            if not fixed and kc is not None:  # compiled: each trial's J^T v from its own forward pass at this start
                J_c = _ADJOINT
            elif not fixed:  # the Jacobian as an operator: J^T v propagated back through the chain, J never formed
                P_c, J_c = chain_adjoint(model.config, model.errors, theta_c, model.inputs, B=model.B)
            else:
                P_c = np.empty((len(todo), M, 3))
                J_c = np.empty((len(todo), M, 3, Qs.shape[1]))
                for _, pos in lab.split(todo):  # the Jacobian's product mixes trials: label by label
                    P_c[pos], J_c[pos] = model.machine_points(theta_c[pos], _rows(fixed, todo[pos], N),
                                                              jacobian=True, project=Qs)
                J_c = np.ascontiguousarray(J_c).reshape(len(todo), 3 * M, Qs.shape[1])  # trial-major, once
            ok, it = chord(state, todo, evaluate, Hinv, J_c, Qs, tol, first=P_c)
            iters += it
            # what stage 1's nominal Jacobian left (b1) against the distance it was used over: stage 2's own bias
            # is about b1 * (b1 / distance) (it used a Jacobian b1 away from the minimum)
            b1 = np.abs((state["theta"][todo] - theta_c) * sv).max(axis=1)
            dist = np.maximum(np.abs(theta_c * sv).max(axis=1), 1.0)
            ok &= b1 * b1 / dist <= strategy.chord_bias
            bad[todo[~ok]] = True

    # several phases: the solution on the last phase's datum (the earlier ones leave what it cannot see)
    if len(phases) > 1:
        ok_rows = np.flatnonzero(~bad)
        th, Rr, Tt = state["theta"][ok_rows], state["R"][ok_rows], state["T"][ok_rows]
        _on_datum(model, phases[-1][1], th, Rr, Tt, c0)
        state["theta"][ok_rows], state["R"][ok_rows], state["T"][ok_rows] = th, Rr, Tt
    # the solution: exact residuals at the final parameters (trials left to Gauss-Newton: at their start, for now)
    theta, R, T = state["theta"], state["R"], state["T"]
    if (bad & ~registered).any():
        register(np.flatnonzero(bad & ~registered))
    theta[bad], R[bad], T[bad] = theta_start[bad], Rk[bad], pose_k[bad, :3]
    angles = lt.euler_from_rotation(R)
    angles = angles0 + (angles - angles0 + np.pi) % (2 * np.pi) - np.pi  # the branch nearest the start
    pose = np.concatenate([T, angles], axis=1)
    Rm = lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5])
    if kc is not None:  # the points, then the residuals, whitened residuals, chi2 and Eq. 27's "before" in one
        from .kernels import chord_final  # compiled pass

        P_W = _chain_at(kc, theta, fixed)

        res, res_m, w, initial_error = (np.empty((N, M, 3)) for _ in range(4))
        chi2 = np.empty(N)
        chord_final(kernel_array(P_W), kernel_array(meas), Wh, Rm,
                    kernel_array(pose[:, :3]), kernel_array(P_fix), nom["R"], nom["T"],
                    res, res_m, w, chi2, initial_error)
    else:
        P_W = evaluate(theta, slice(None))
        res = meas - _apply_transposed(Rm, P_W - pose[:, None, :3])  # R^T (P_W - T): lt.to_tracker
        w = _apply(Wh, res)
        res_m, chi2 = _apply(Rm, res), (w**2).sum(axis=(1, 2))
    out = {
        "theta": theta, "pose": pose, "residual": res, "residual_machine": res_m,
        "chi2": chi2, "dof": 3 * M - (6 + Q_last.shape[1]), "initial_error": initial_error,
        "converged": ~bad, "iterations": iters, "whitened": w, "whitener": Wh, "fallback": bad.copy(),
        "points": None if fixed else P_W,
    }
    if bad.any():  # the reference path, from the same start, for the trials the chord could not finish (per label)
        for _, pos in lab.split(np.flatnonzero(bad)):
            idx = np.flatnonzero(bad)[pos]
            gn = _identify_chunk(model, meas[idx], noise, strategy, theta_start[idx],
                                 None if pose0 is None else pose0[idx], _rows(fixed, idx, N), phases,
                                 with_covariance=False)
            for key in ("theta", "pose", "residual", "residual_machine", "chi2", "initial_error", "converged",
                        "whitened"):
                out[key][idx] = gn[key]
            out["iterations"] += gn["iterations"]
            if out["points"] is not None:
                out["points"][idx] = evaluate(out["theta"][idx], idx)
    return out


def _on_datum(model, ident: Identifiability, theta, R, T, c0):
    """Put a solution on the datum of ``ident`` (the last phase of a multi-phase identification, whose earlier
    phases moved the parameters along directions the last one cannot see): theta (N, p), R (N, 3, 3), T (N, 3) in
    place.  The null combination c (:func:`null_coordinates`: minimum norm, or the held parameters at zero) is
    removed from the scaled parameters and the rigid motion it carries applied to the tracker pose, so that the
    predicted tracker points, the residuals and the compensated field stay the same (to second order in c, the
    size of the move: a few um or urad) and one-phase and multi-phase trials report their parameters on one datum."""
    N = ident.null_space
    if not N.size or ident.null_rigid is None or not len(theta):
        return
    sv = scale_vector(model)
    ts = theta * sv
    # every product trial by trial (einsum's own loops, not BLAS, which rounds a row differently with the number of
    # rows): a trial's numbers do not depend on the trials identified with it
    if ident.held is None:
        c = np.einsum("np,pk->nk", ts, N)  # (n, k)
    else:
        c = np.einsum("kh,nh->nk", np.linalg.inv(N[ident.held, :]), ts[:, ident.held])
    theta[:] = (ts - np.einsum("nk,pk->np", c, N)) / sv
    m = np.einsum("nk,jk->nj", c, ident.null_rigid)  # (n, 6): the machine points' rigid motion, scaled
    Rot = _rotation(m[:, 3:] / POSE_SCALE[3:])
    T[:] = (Rot @ (T - c0)[:, :, None])[:, :, 0] + c0 + m[:, :3] / POSE_SCALE[:3]
    R[:] = Rot @ R


def _iteration_matrices(G0, J, W_bars):
    """{label: inverse normal matrix} of the rigid columns G0 (M, 3, 6) and the geometric ones -J (M, 3, r)
    (None: the pose alone) with each label's information W_bar (M, 3, 3)."""
    M = G0.shape[0]
    K = G0 if J is None else np.concatenate([G0, -J], axis=2)
    K2 = K.reshape(3 * M, -1)
    out = {}
    for k, W_bar in W_bars.items():
        KW = W_bar @ K  # (M, 3, 3) @ (M, 3, b): each point's information times its rows
        out[k] = _spd_inverse(K2.T @ KW.reshape(3 * M, -1))
    return out


def _noise_key(noise) -> tuple:
    """The stated noise as a hashable key."""
    return tuple(np.asarray(getattr(noise, f), float).tobytes()
                 for f in ("angular", "distance", "distance_per_length", "repeatability"))


#: what the compiled kernels take: C-contiguous and writable (a read-only array is another numba type)
_CW = ["C", "W"]


def _apply(A, x):
    """A x for stacks of 3 x 3 matrices A (..., 3, 3) or (N, M, 3, 3) and points x (N, M, 3): elementwise."""
    if A.ndim == 3:  # one matrix per trial
        A = A[:, None]
    out = np.empty(np.broadcast_shapes(A.shape[:-1], x.shape))
    for i in range(3):
        out[..., i] = A[..., i, 0] * x[..., 0] + A[..., i, 1] * x[..., 1] + A[..., i, 2] * x[..., 2]
    return out


def _apply_transposed(A, x):
    """A^T x, as :func:`_apply`."""
    return _apply(np.swapaxes(A, -1, -2), x)


def _gram33(Wh):
    """Wh^T Wh for stacks of 3 x 3 matrices, elementwise."""
    out = np.empty(Wh.shape)
    for i in range(3):
        for j in range(i, 3):
            out[..., i, j] = Wh[..., 0, i] * Wh[..., 0, j] + Wh[..., 1, i] * Wh[..., 1, j] + Wh[..., 2, i] * Wh[..., 2, j]
            if j != i:
                out[..., j, i] = out[..., i, j]
    return out


def _chord(state, rows, evaluate, meas, WLc, Hinv, J, Qs, c0, tol, strategy, lab, first=None, predict=False):
    """Chord iterations for the trials ``rows`` (updated in place in ``state``: R, T, theta).

    evaluate(theta, rows) -> machine points (n, M, 3); WLc (3, 3, N, M) each point's information matrix
    (tracker frame), component-major; Hinv the shared inverse normal matrix of each label; J the geometric
    Jacobian along the scaled directions Qs: shared (3M, r), per trial (n, 3M, r), or each trial's as an
    operator (:func:`mtbudget.machine.chain_adjoint`: J(v, positions) = J^T v, (n, p)), None for the pose
    alone; lab the labels (:class:`_Labels`); first: the machine points at the start, when already known;
    predict: also stop when the next step, predicted from the contraction of the last two, is below ``tol``.
    Returns (converged per row, iterations).
    """
    n = len(rows)
    ok = np.zeros(n, bool)
    if not n:
        return ok, 0
    live = np.arange(n)  # positions in rows still iterating
    prev = np.full(n, np.inf)
    it = 0
    adjoint = callable(J)  # each trial's own Jacobian as an operator, J(v, positions) = J^T v (n, p)
    per_trial = not adjoint and J is not None and J.ndim == 3  # (n, 3M, r): each trial's own Jacobian
    from .kernels import chord_residual

    inv_ps = 1.0 / POSE_SCALE
    M = meas.shape[1]
    # C-contiguous writable float64 arrays: one compiled signature of the kernel (see mtbudget.kernels)
    meas, WLc, c0 = (np.require(x, np.float64, _CW) for x in (meas, WLc, c0))
    # every product below is per trial (stacked matrices of a fixed shape) or per label: see _Labels
    for it in range(1, strategy.chord_iter + 1):
        part = live.size < n
        r = rows[live]
        nr = len(r)
        parts = lab.split(r)
        R, T = state["R"][r], state["T"][r]
        P_W = first[live] if (first is not None and it == 1) else evaluate(state["theta"][r], r)
        # the weighted residual in the machine frame v = R C^-1 (x - R^T (P_W - T)), the cost and the rigid
        # part of the gradient (sum of v, torque about c0), trial by trial in one compiled pass
        G = np.empty((nr, 6 + (0 if J is None else Qs.shape[1])))
        v, cost = np.empty((nr, M, 3)), np.empty(nr)
        chord_residual(np.require(P_W, np.float64, _CW), meas, WLc, r.astype(np.int64, copy=False),
                       np.require(R, np.float64, _CW), np.require(T, np.float64, _CW), c0, v, G, cost)
        G[:, :6] *= inv_ps
        if J is not None:
            m3 = 3 * M
            V = v.reshape(nr, m3)
            if adjoint:  # J^T v of each trial (elementwise), then along the directions label by label
                A = J(v, live if part else None)
                G[:, 6:] = -_per_label(parts, r, lambda k, pos: A[pos] @ Qs, Qs.shape[1])
            elif per_trial:
                G[:, 6:] = -(V[:, None, :] @ (J[live] if part else J))[:, 0]
            else:
                G[:, 6:] = -_per_label(parts, r, lambda k, pos: V[pos] @ J, J.shape[1])
        z = -_per_label(parts, r, lambda k, pos: G[pos] @ Hinv[k], G.shape[1])
        step = np.abs(z).max(axis=1)
        # the step, applied
        Rot = _rotation(z[:, 3:6] * inv_ps[3:])
        state["R"][r] = Rot @ R
        state["T"][r] = (Rot @ (T - c0)[:, :, None])[:, :, 0] + c0 + z[:, :3] * inv_ps[:3]
        if J is not None:
            zg = z[:, 6:]
            state["theta"][r] += _per_label(parts, r, lambda k, pos: zg[pos] @ Qs.T, Qs.shape[0])
        # the contraction is judged in the energy norm of the step, |z|_H = sqrt(z^T H z) = sqrt(-g.z) (the
        # decrease of the cost the step predicts): there the chord contracts monotonically, while the largest
        # component may first grow along poorly determined combinations (pose rotation against the geometry)
        energy = np.sqrt(np.maximum(-(G * z).sum(axis=1), 0.0))
        rate = np.where(np.isfinite(prev[live]), energy / prev[live], np.inf)  # no rate before the second step
        done = (step < tol) | (energy**2 <= strategy.ftol * cost)
        if predict:  # the next step, predicted from the contraction, is below the tolerance
            done |= step * rate < tol
        slow = ~done & np.isfinite(rate) & (rate > _MAX_RATE)
        ok[live[done]] = True
        prev[live] = energy
        live = live[~done & ~slow]
        if not live.size:
            break
    return ok, it


#: the chord's stages as one compiled pass per trial (:func:`mtbudget.kernels.chord_stage`); False: :func:`_chord`,
#: the numpy formulation it is tested against (the same iteration, round-off apart)
CHORD_KERNEL = True


def _chord_chain(model, fixed: dict, N: int) -> dict:
    """The compiled chain's inputs for a chunk of N trials with its fixed perturbations (``kernels.chord_stage``):
    :func:`mtbudget.machine.kernel_chain` plus ``toolT`` (3, M), ``gfix`` (1 or N, p) the fixed geometry and
    ``poff`` (1 or N, M, 3) the fixed point offsets (zero when none).  Without fixed perturbations every array has
    one row for all trials (N does not enter): the plan cache keeps them (the kernels only read them)."""
    M, p = model.n_points, model.n_params
    k = kernel_chain(model.config, model.errors, model.chain_inputs(fixed), model.B, N)
    k["toolT"] = np.ascontiguousarray(k["tool"].T)
    g = np.asarray(fixed.get("geometry", np.zeros((1, p))), float)
    k["gfix"] = np.require(g.reshape(-1, p), np.float64, _CW)
    po = np.asarray(fixed.get("point_offset", np.zeros((1, M, 3))), float)
    k["poff"] = np.require(po.reshape(-1, M, 3), np.float64, _CW)
    return k


def _chain_at(kc: dict, theta: np.ndarray, fixed: dict) -> np.ndarray:
    """``model.machine_points(theta, fixed)`` (N, M, 3), the same numbers, from the chain's inputs ``kc``
    (:func:`_chord_chain`) instead of building them again: the fixed geometry added to theta, the compiled chain
    (:func:`mtbudget.machine.kernel_points`), the fixed point offsets added."""
    th = theta + fixed["geometry"] if "geometry" in fixed else theta
    out = kernel_points(kc, th)
    return out + fixed["point_offset"] if "point_offset" in fixed else out


#: stage 2 of the compiled chord: each trial's J^T v from its own forward pass at the stage's start
_ADJOINT = object()


def _chord_compiled(state, rows, meas, WLc, Hinv, J, Qs, c0, tol, strategy, lab, chain, first=None, fixed_points=None,
                    adjoint=None, predict=False):
    """:func:`_chord` (same arguments and result) in one compiled pass per trial: ``chain`` from :func:`_chord_chain`;
    ``fixed_points`` (1 or N, M, 3): the machine points when they do not move (the pose-only fit); ``adjoint``: the
    model whose chain's J^T v each trial takes at its start (the chain's Jacobian there as an operator, never
    formed: :func:`mtbudget.machine.chain_adjoint`'s, kept per trial inside the kernel)."""
    from .kernels import chord_stage

    n = len(rows)
    ok = np.zeros(n, bool)
    if not n:
        return ok, 0
    N, M = meas.shape[:2]
    p = state["theta"].shape[1]
    if fixed_points is not None:
        mode, J3 = 0, np.zeros((1, 1, 1))
    elif adjoint is not None:
        mode, J3 = 3, np.zeros((1, 1, 1))
    elif J.ndim == 2:
        mode, J3 = 1, J[None]
    else:
        mode, J3 = 2, J
    mats = [Hinv[k] for k in range(lab.n)]
    if all(m is mats[0] for m in mats):  # one matrix for every label (the engine's nominal iteration matrix)
        H3, label = mats[0][None], np.zeros(N, np.int64)
    else:
        H3, label = np.stack(mats), lab.of.astype(np.int64)
    Qs_ = np.zeros((p, 0)) if Qs is None else Qs
    if adjoint is not None:
        # the kernel's J^T v reads the chain's inputs of one trial for all (the engine's: nothing fixed per trial)
        if max(chain["px"].shape[0], chain["py"].shape[0], chain["pz"].shape[0], chain["rcos"].shape[1]) > 1:
            raise ValueError("the compiled stage 2 takes chain inputs shared by every trial; with per-trial inputs "
                             "the Jacobian is formed (mode 2)")
        tool_order, params, basis = vjp_layout(adjoint.config, adjoint.errors, adjoint.B)
    else:
        tool_order, params, basis = np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, M))
    for key in ("theta", "R", "T"):
        state[key] = kernel_array(state[key])
    c = chain
    req = kernel_array  # np.require(x, np.float64, _CW) without its Python when x is such an array already
    it = chord_stage(
        mode, np.asarray(rows, np.int64), label, state["theta"], state["R"], state["T"], req(meas), req(WLc), req(c0),
        1.0 / POSE_SCALE, req(H3), req(Qs_), req(J3),
        req(first) if first is not None else np.zeros((0, M, 3)),
        req(fixed_points) if fixed_points is not None else np.zeros((1, M, 3)),
        c["tool_axes"], c["wp_axes"], c["side"], c["px"], c["py"], c["pz"], c["toolT"], c["L"], c["src"], c["dst"],
        c["sqi"], c["rdir"], c["pivot"], c["rcos"], c["rsin"], c["poff"], c["gfix"],
        tool_order, np.require(params, np.int64, _CW), req(basis),
        float(tol), float(strategy.ftol), int(strategy.chord_iter), bool(predict), float(_MAX_RATE), ok)
    return ok, int(it)


def range_basis(active: np.ndarray, null: np.ndarray | None) -> np.ndarray:
    """Orthonormal basis (scaled coords) of the active parameters minus the null space: (p, r)."""
    p = active.size
    E = np.eye(p)[:, active]
    if null is None or null.size == 0:
        return E
    # project the active coordinate directions off the null space, then orthonormalise
    Pn = np.eye(p) - null @ null.T
    U, s, _ = np.linalg.svd(Pn @ E, full_matrices=False)
    r = int((s > 1e-8).sum())
    return U[:, :r]




def design_matrix(P_W, J, pose, Wh, Q, sv):
    """Whitened, scaled design matrix (N, 3M, 6 + r).

    P_W (N, M, 3) machine points, J (N, M, 3, r) their derivative along the scaled directions
    ``Q / sv`` (None: the pose alone), pose (N, 6), Wh (N, M, 3, 3) whiteners.
    """
    N, M = P_W.shape[:2]
    Jp = lt.pose_jacobian(P_W, pose) / POSE_SCALE  # (N,M,3,6)
    if J is None or Q.shape[1] == 0:
        return (Wh @ Jp).reshape(N, 3 * M, -1)
    Rm = lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5])
    # J is dP_W/dtheta already projected on the free directions (N,M,3,r): rotate into the tracker frame
    Jt = np.concatenate([Jp, np.swapaxes(Rm, 1, 2)[:, None] @ J], axis=3)
    return (Wh @ Jt).reshape(N, 3 * M, -1)


def _solve(A, w):
    """Least-squares step of each trial from the normal equations (full column rank by construction)."""
    At = np.swapaxes(A, 1, 2)
    AtA = At @ A
    Atr = (At @ w[..., None])[..., 0]
    try:
        L = np.linalg.cholesky(AtA)
        return np.linalg.solve(np.swapaxes(L, 1, 2), np.linalg.solve(L, Atr[..., None]))[..., 0]
    except np.linalg.LinAlgError:
        return np.stack([np.linalg.lstsq(AtA[n], Atr[n], rcond=None)[0] for n in range(len(A))])


def _whitened_residual(meas, P_W, pose, Wh):
    r = meas - lt.to_tracker(P_W, pose)
    return np.einsum("nmij,nmj->nmi", Wh, r).reshape(len(meas), -1)


def _fit_pose(P_W, meas, Wh, pose, strategy):
    """Weighted fit of the pose alone to fixed machine points (a few Gauss-Newton steps)."""
    pose = pose.copy()
    for _ in range(strategy.max_iter):
        w = _whitened_residual(meas, P_W, pose, Wh)
        z = _solve(design_matrix(P_W, None, pose, Wh, np.zeros((0, 0)), None), w)
        pose += z / POSE_SCALE
        if np.abs(z).max() < strategy.xtol:
            break
    return pose


def _gauss_newton(model, meas, Wh, theta, pose, Q, strategy, fixed):
    """Gauss-Newton over all trials of a chunk, with step halving where the cost rises.

    Returns (theta, pose, converged, iterations, (P_W, J, whitened residual) at the
    returned point).  Q (p, r) is the basis of
    the free, identifiable parameter directions (scaled coordinates).
    """
    N = meas.shape[0]
    sv = scale_vector(model)
    theta, pose = theta.copy(), pose.copy()
    conv = np.zeros(N, bool)

    def subset(fx, idx):
        return {k: (v[idx] if np.ndim(v) and np.shape(v)[0] == N and N > 1 else v) for k, v in fx.items()}

    proj = Q / sv[:, None]
    P_W, J = model.machine_points(theta, fixed, jacobian=True, project=proj)
    w = _whitened_residual(meas, P_W, pose, Wh)
    cost = (w**2).sum(axis=1)
    it = 0
    for it in range(1, strategy.max_iter + 1):
        todo = ~conv
        z = np.zeros((N, 6 + Q.shape[1]))
        z[todo] = _solve(design_matrix(P_W[todo], J[todo], pose[todo], Wh[todo], Q, sv), w[todo])
        step = np.ones(N)
        new_theta = theta + (z[:, 6:] @ Q.T) / sv
        new_pose = pose + z[:, :6] / POSE_SCALE
        P_new, J_new = model.machine_points(new_theta, fixed, jacobian=True, project=proj)
        w_new = _whitened_residual(meas, P_new, new_pose, Wh)
        c_new = (w_new**2).sum(axis=1)
        # step halving for the (rare) trials whose cost rose beyond round-off
        worse = c_new > cost * (1 + 1e-10) + 1e-300
        k = 0
        while worse.any() and k < 30:
            k += 1
            idx = np.flatnonzero(worse)
            step[idx] *= 0.5
            zz = z[idx] * step[idx, None]
            new_theta[idx] = theta[idx] + (zz[:, 6:] @ Q.T) / sv
            new_pose[idx] = pose[idx] + zz[:, :6] / POSE_SCALE
            P_i, J_i = model.machine_points(new_theta[idx], subset(fixed, idx), jacobian=True, project=proj)
            P_new[idx], J_new[idx] = P_i, J_i
            w_new[idx] = _whitened_residual(meas[idx], P_i, new_pose[idx], Wh[idx])
            c_new[idx] = (w_new[idx] ** 2).sum(axis=1)
            worse[idx] = c_new[idx] > cost[idx] * (1 + 1e-10) + 1e-300
        small = (np.abs(z).max(axis=1) * step < strategy.xtol) | (cost - c_new <= strategy.ftol * cost)
        conv |= small
        theta, pose, P_W, J, w, cost = new_theta, new_pose, P_new, J_new, w_new, c_new
        if conv.all():
            break
    return theta, pose, conv, it, (P_W, J, w)
