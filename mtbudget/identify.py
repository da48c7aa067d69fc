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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import tracker as lt
from .errors import IdentificationError
from .machine import AXES, AXIS_INDEX, skew_basis
from .model import MeasurementModel
from .units import factor

GROUPS = ("pose", "translational", "angular", "squareness")


@dataclass
class Strategy:
    """An optimisation strategy (paper Section 2.2.4, Figs. 5-6).

    phases: each phase is the list of parameter groups it frees, from
    ``pose``, ``translational``, ``angular``, ``squareness``; parameters of a
    later phase start from the values of the earlier phase.  ``[GROUPS]`` is
    the paper's one-phase identification.
    """

    phases: list = field(default_factory=lambda: [list(GROUPS)])
    max_iter: int = 30
    xtol: float = 1e-4  # convergence: largest step of any scaled parameter (um or urad; Gauss-Newton
    #                     converges quadratically here, so what remains after it is ~1e-10) ...
    ftol: float = 1e-12  # ... or a relative decrease of the weighted cost below this
    rank_tol: float = 1e-7  # singular values below rank_tol * largest are treated as null
    weighted: bool = True

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

    @property
    def identifiable(self) -> int:
        return self.n_params - self.null_space.shape[1]

    def combinations(self, threshold: float = 0.2, top: int = 6) -> list[list[tuple[str, float]]]:
        """Each non-identifiable direction as [(parameter, weight), ...] (scaled, unit norm)."""
        out = []
        if self.null_space.size == 0:
            return out
        # rotate the basis to something readable: reduced row echelon-like via QR with pivoting
        from scipy.linalg import qr

        N = self.null_space
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
    cov_theta: np.ndarray  # (N, p, p)
    cov_pose: np.ndarray  # (N, 6, 6)
    initial_error: np.ndarray  # (N, M, 3) machine-frame deviation after pose-only registration
    converged: np.ndarray  # (N,) bool
    iterations: int
    identifiability: Identifiability
    whitened: np.ndarray | None = None  # (N, M, 3) whitened residuals
    # at the solution (the last Gauss-Newton evaluation), for callers that continue from it (diagnosis):
    whitener: np.ndarray | None = None  # (N, M, 3, 3) L^-1 of each point's covariance C = L L^T (tracker frame)
    design: np.ndarray | None = None  # (N, 3M, 6 + r) whitened design in the scaled unknowns z, see below
    basis: np.ndarray | None = None  # (p, r) orthonormal basis Q of the free, identifiable directions (scaled)
    scale: np.ndarray | None = None  # (p,) scale_vector(model): um per mm, urad per rad

    # The unknowns of the design are z = (pose * POSE_SCALE, Q^T (theta * scale)): a step z moves the
    # pose by z[:6] / POSE_SCALE and theta by (Q z[6:]) / scale, and changes the whitened residual by
    # -design @ z.  cov_theta and cov_pose are (design^T design)^-1 mapped back to mm and rad.

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
        return np.linalg.norm(self.initial_error, axis=-1).mean(axis=-1)

    @property
    def mean_error_after(self):
        """Paper Eq. 27 after compensation (mm): mean residual distance."""
        return np.linalg.norm(self.residual, axis=-1).mean(axis=-1)

    @property
    def max_residual(self):
        return np.linalg.norm(self.residual, axis=-1).max(axis=-1)

    @property
    def rms(self):
        """Root mean square of the 3D residual distance (mm)."""
        return np.sqrt((self.residual**2).sum(-1).mean(-1))

    def u_theta(self):
        return np.sqrt(np.maximum(np.diagonal(self.cov_theta, axis1=1, axis2=2), 0))


#: the scaled parameter units: lengths in um, angles in urad (on a 1 m lever both are um of effect)
SCALED_UNIT = {"mm": "um", "rad": "urad"}


def scale_vector(model: MeasurementModel) -> np.ndarray:
    """um per mm and urad per rad: parameters in comparable effect units."""
    return np.array([factor(u, SCALED_UNIT[u]) for u in model.errors.units])


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
    U, s, Vt = np.linalg.svd(A / norms, full_matrices=True)
    tol = rank_tol * (s[0] if s.size else 1.0)
    rank = int((s > tol).sum())
    V = (Vt.T / norms[:, None])  # back to scaled (unequilibrated) coordinates
    null = V[:, rank:]
    # rigid-only rank
    sr = np.linalg.svd(rigid.reshape(3 * M, 6) / np.linalg.norm(rigid.reshape(3 * M, 6), axis=0), compute_uv=False)
    pose_ok = bool(sr[-1] > rank_tol * sr[0])
    null_geo = np.zeros((p, null.shape[1]))
    if null.shape[1]:
        # orthonormal basis of the geometric part of the null space
        ng = null[6:, :]
        q, r = np.linalg.qr(ng)
        keep = np.abs(np.diag(r)) > 1e-12 if r.size else np.zeros(0, bool)
        null_geo[active] = q[:, keep] if keep.size else q
        null_geo = null_geo[:, : int(keep.sum())] if keep.size else null_geo
    names = model.errors.names
    return Identifiability(names, rank, int(active.sum()), s, null_geo, pose_ok)


def whitener(C: np.ndarray) -> np.ndarray:
    """L^-1 with C = L L^T, batched (…, 3, 3): ``whitener(C) @ r`` has unit covariance."""
    L = np.linalg.cholesky(C)
    return np.linalg.inv(L)


def _check_inputs(model: MeasurementModel, meas: np.ndarray):
    if meas.shape[-2:] != (model.n_points, 3):
        raise IdentificationError(f"measured points have shape {meas.shape[-2:]}, the plan has {model.n_points} points x 3")
    bad = ~np.isfinite(meas).all(axis=-1)
    if bad.any():
        rows = np.unique(np.nonzero(bad)[-1])[:10]
        raise IdentificationError(
            f"measured coordinates are NaN or infinite at plan rows {rows.tolist()} "
            "(0-based); remove or repair those points before identifying")
    nominal = model.plan.nominal
    for a in AXES:
        npos = len(np.unique(np.round(nominal[:, AXIS_INDEX[a]], 6)))
        for name, deg in model.errors.degrees.items():
            if name[3] == a and deg and deg > npos - 1:
                raise IdentificationError(
                    f"{name} has degree {deg} but axis {a} is measured at only {npos} distinct position(s); "
                    f"at most degree {max(npos - 1, 0)} can be identified (lower it in the error model)")
    pts = nominal + model.plan.tool
    sv = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-12):
        raise IdentificationError("all measured points lie on one line: the tracker rotation about it cannot be identified")


def identify(
    model: MeasurementModel,
    measured: np.ndarray,
    noise: Noise,
    strategy: Strategy | None = None,
    theta0: np.ndarray | None = None,
    pose0: np.ndarray | None = None,
    fixed: dict | None = None,
    chunk: int | None = None,
) -> Identification:
    """Identify pose and geometric errors for one or N trials.

    measured: (M, 3) or (N, M, 3) tracker coordinates (mm).
    theta0: initial geometric parameters (p,) or (N, p); non-identifiable
    directions keep their initial value (zero by default).
    pose0: initial pose; by default the Kabsch registration of the predicted points.
    fixed: perturbations known a priori (``MODEL_INPUTS`` keys, broadcastable
    over trials), e.g. a thermal scale that a diagnosis candidate asserts.
    chunk: trials solved together (default: about 8 MB of Jacobian per chunk, which
    keeps the working set in cache; larger chunks are slower, not faster).
    """
    strategy = strategy or Strategy()
    meas = np.asarray(measured, float)
    if meas.ndim == 2:
        meas = meas[None]
    _check_inputs(model, meas)
    fixed = dict(fixed or {})
    if "spherical_noise" in fixed:
        raise IdentificationError("spherical_noise cannot be a fixed perturbation in identification")
    if "tracker_offset" in fixed:  # a known displacement in the tracker frame: take it off the measurement
        meas = meas - np.broadcast_to(fixed.pop("tracker_offset"), meas.shape)
    N, M = meas.shape[:2]
    p = model.n_params

    # identifiability of each phase (depends on the plan only, computed once)
    phases = []
    for phase in strategy.phases:
        unknown = set(phase) - set(GROUPS)
        if unknown:
            raise IdentificationError(f"unknown parameter group(s) {sorted(unknown)} in strategy phase; expected {GROUPS}")
        if "pose" not in phase:
            raise IdentificationError("every phase must include the pose (the tracker pose is always unknown)")
        active = np.array([group_of(par) in phase for par in model.errors.params])
        ident = analyse(model, active, strategy.rank_tol)
        if not ident.pose_identifiable:
            raise IdentificationError("the plan's points do not fix the tracker pose (all points on a line)")
        n_unknown = 6 + ident.identifiable
        if 3 * M <= n_unknown:
            raise IdentificationError(
                f"too few points: {M} points give {3 * M} coordinates for {n_unknown} identifiable unknowns "
                f"(no redundancy left); measure more points or lower the degrees of the error functions")
        phases.append((active, ident, range_basis(active, ident.null_space)))

    theta0 = np.zeros((N, p)) if theta0 is None else np.broadcast_to(np.asarray(theta0, float), (N, p))
    pose0 = None if pose0 is None else np.broadcast_to(np.asarray(pose0, float), (N, 6))
    if chunk is None:
        chunk = max(16, int(8e6 // (M * 3 * max(p, 1) * 8)))
    parts = []
    for lo in range(0, N, chunk):
        sl = slice(lo, min(N, lo + chunk))
        fx = {k: (v[sl] if np.ndim(v) and np.shape(v)[0] == N and N > 1 else v) for k, v in fixed.items()}
        parts.append(_identify_chunk(model, meas[sl], noise, strategy, theta0[sl].copy(),
                                     None if pose0 is None else pose0[sl].copy(), fx, phases))
    cat = lambda key: np.concatenate([q[key] for q in parts], axis=0)  # noqa: E731
    return Identification(
        model=model, theta=cat("theta"), pose=cat("pose"), residual=cat("residual"),
        residual_machine=cat("residual_machine"), chi2=cat("chi2"), dof=parts[0]["dof"],
        cov_theta=cat("cov_theta"), cov_pose=cat("cov_pose"), initial_error=cat("initial_error"),
        converged=cat("converged"), iterations=max(q["iterations"] for q in parts),
        identifiability=phases[-1][1], whitened=cat("whitened"), whitener=cat("whitener"), design=cat("design"),
        basis=phases[-1][2], scale=scale_vector(model),
    )


def _identify_chunk(model, meas, noise, strategy, theta, pose, fixed, phases):
    N, M = meas.shape[:2]
    p = model.n_params
    sv = scale_vector(model)
    # weights from the stated uncertainties, evaluated at the measured points
    if strategy.weighted:
        C = model.covariance(meas, noise.angular, noise.distance, noise.distance_per_length, noise.repeatability)
    else:
        C = np.broadcast_to(np.eye(3) * (noise.distance**2 + noise.repeatability**2), (N, M, 3, 3))
    Wh = whitener(C)

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

    # final quantities and covariance at the solution (the last Gauss-Newton evaluation)
    Q = phases[-1][2]
    res = meas - lt.to_tracker(P_W, pose)
    A = design_matrix(P_W, J, pose, Wh, Q, sv)
    wres = w.reshape(N, M, 3)
    chi2 = (w**2).sum(axis=1)
    n_unknown = 6 + Q.shape[1]
    AtA = np.swapaxes(A, 1, 2) @ A
    cov_z = np.linalg.inv(AtA)
    T = np.zeros((6 + p, n_unknown))
    T[:6, :6] = np.diag(1.0 / POSE_SCALE)
    T[6:, 6:] = Q / sv[:, None]
    cov_full = T @ cov_z @ T.T
    Rm = lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5])
    return {
        "theta": theta, "pose": pose, "residual": res, "residual_machine": np.einsum("nij,nmj->nmi", Rm, res),
        "chi2": chi2, "dof": 3 * M - n_unknown, "cov_theta": cov_full[:, 6:, 6:], "cov_pose": cov_full[:, :6, :6],
        "initial_error": initial_error, "converged": converged, "iterations": iters, "whitened": wres,
        "whitener": Wh, "design": A,
    }


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
