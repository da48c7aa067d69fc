"""Identification over several stations at once: multi-station verification and multilateration.

One recording measured from several stations (format 2 of docs/recording-format.md): laser
trackers (``xyz``: a point in the station's own frame) and tracking interferometers
(``range``: a distance plus an unknown dead-path offset).  The unknowns are

* the geometric error parameters theta of the machine (the error model of :mod:`mtbudget.model`),
* for every xyz station its pose (D, L, H in mm, a, b, d in rad; the paper's Eq. 21-22),
* for every range station its position S (mm, machine/workpiece frame) and dead-path offset o (mm),

and all of them are estimated together by weighted least squares:

    xyz row i of station s:    x_i = R_s^T (P_W(theta)_i - T_s)             covariance Eq. 23 + repeatability
    range row i of station s:  l_i = |P_W(theta)_i - S_s| + o_s             variance (a + b r)^2 + repeatability^2

(each row is its own positioning of the machine: the repeatability is independent from row to row).

Algorithm: closed-form starts (Kabsch for an xyz station, the linearised multilateration
|P|^2 - l^2 = 2 P.S - 2 l o + (o^2 - |S|^2) for a range station, theta = 0), then Gauss-Newton
with the exact analytic Jacobian (the chain's dP_W/dtheta, :func:`mtbudget.tracker.pose_jacobian`,
the unit beam vector for a range), in scaled unknowns (um and urad), with step halving where the
cost rises.

Datum (gauge): a rigid motion of the machine points together with every station leaves every
measurement unchanged.  Whether it is a freedom of the unknowns depends on whether the error model
can move the machine points rigidly: mtbudget's default model cannot (no constant terms fix the
origin; the ISO 230-1 convention, no P1 term of a straightness, fixes the orientation), so the datum
is fixed by the error model's convention, and :attr:`MultiIdentification.gauge` says so for each of the
six freedoms, tested on the Jacobian.  Every direction the data cannot see (a rigid freedom the
model can produce, or what the stations' geometry leaves unseen, as a roll that no tool offset shows)
is a null direction of the whitened Jacobian: it is held at its start value (minimum norm), named
(ISO 230-1 names), and counted in the rank; the condition number is that of the column-equilibrated
Jacobian on the identifiable directions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import tracker as lt
from .errors import IdentificationError
from .identify import POSE_SCALE, Identifiability, phase_actives, range_basis, scale_vector, whitener
from .model import MeasurementModel, iso_parameter
from .recording import Recording, read_recording
from .units import display, shown_unit

#: scaled unknowns: a station position and a dead-path offset in um (mm -> um)
UM_PER_MM = 1e3
#: the most trials one call of the several-station chord iterates together: its working set (every trial's machine
#: points, whiteners and the chain's adjoint) then stays in cache (measured on one station: 0.101 ms per trial in
#: calls of 256 trials, 0.108 in calls of 1024, 0.127 in calls of 64); a trial's result does not depend on it
CHORD_CHUNK = 256
#: the several-station identification's own step tolerance (um, urad): its batch iterates until a step of every
#: scaled unknown is below it (the tests hold it to 1e-7 um in the compensated field), as the one-tracker chord
#: iterates to ``Strategy.chord_tol``; a strategy's xtol can tighten it, not loosen it (:func:`strategy_settings`)
STATIONS_XTOL = 1e-7
RIGID_FREEDOMS = ("translation along X", "translation along Y", "translation along Z", "rotation about X",
                  "rotation about Y", "rotation about Z")


@dataclass
class MultiIdentification:
    """The result of one identification over several stations (internal units: mm, rad)."""

    model: MeasurementModel
    stations: list  # [recording.Station], in the order of the unknowns
    names: list  # every unknown's name: theta's (internal), then "station 1: D", ...
    units: list  # "mm" or "rad" per unknown
    x: np.ndarray  # (n,) all unknowns at the solution
    cov: np.ndarray  # (n, n) their covariance from the stated uncertainties (not scaled by chi2/dof)
    chi2: float
    dof: int
    rank: int
    condition: float  # of the column-equilibrated whitened Jacobian on the identifiable directions
    singular_values: np.ndarray
    null_space: np.ndarray  # (n, k) orthonormal, scaled unknowns (um, urad)
    gauge: list  # [{freedom, fixed_by}] the six rigid freedoms of the whole
    converged: bool
    iterations: int
    row_station: np.ndarray  # (M,) station id of every row
    residual_xyz: np.ndarray  # (M, 3) measured - predicted in the station's frame, mm (NaN on range rows)
    residual_range: np.ndarray  # (M,) measured - predicted range, mm (NaN on xyz rows)
    whitened: np.ndarray  # (n_res,) whitened residuals
    station_chi2: dict = field(default_factory=dict)  # id -> (chi2, number of residuals)

    @property
    def n_params(self) -> int:
        return self.model.n_params

    @property
    def n_unknowns(self) -> int:
        return len(self.x)

    @property
    def theta(self) -> np.ndarray:
        return self.x[: self.n_params]

    @property
    def cov_theta(self) -> np.ndarray:
        return self.cov[: self.n_params, : self.n_params]

    @property
    def u(self) -> np.ndarray:
        """Standard uncertainty (k = 1) of every unknown (mm, rad)."""
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def u_theta(self) -> np.ndarray:
        return self.u[: self.n_params]

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    @property
    def iso_names(self) -> list:
        return [iso_parameter(n) for n in self.names]

    def _slice(self, sid):
        k = self.n_params
        for st in self.stations:
            if st.id == sid:
                return slice(k, k + st.unknowns), st
            k += st.unknowns
        raise KeyError(f"no station {sid}")

    def station_values(self, sid) -> tuple[np.ndarray, np.ndarray]:
        """(values, standard uncertainties) of a station's own unknowns: an xyz pose (D, L, H mm; a, b, d rad) or a
        range station's (S_x, S_y, S_z, dead path) in mm."""
        sl, _ = self._slice(sid)
        return self.x[sl].copy(), self.u[sl].copy()

    def identifiable(self, threshold: float = 1e-6) -> np.ndarray:
        """(n,) False for the unknowns that take part in a non-identifiable direction (held at their start, u = 0)."""
        if self.null_space.size == 0:
            return np.ones(self.n_unknowns, bool)
        return np.linalg.norm(self.null_space, axis=1) <= threshold

    def combinations(self, threshold: float = 0.2, top: int = 6) -> list:
        """Each non-identifiable direction as [(ISO 230-1 name, weight), ...] (scaled unknowns, unit norm)."""
        ident = Identifiability(self.iso_names, self.rank, self.n_unknowns, self.singular_values, self.null_space,
                                True)
        return ident.combinations(threshold, top)


def _names(model: MeasurementModel, stations) -> tuple[list, list]:
    names, units = list(model.errors.names), list(model.errors.units)
    for st in stations:
        if st.kind == "xyz":
            names += [f"station {st.id}: {n}" for n in lt.POSE_NAMES]
            units += list(lt.POSE_UNITS)
        else:
            names += [f"station {st.id}: {n}" for n in ("S_x", "S_y", "S_z", "dead path")]
            units += ["mm"] * 4
    return names, units


def _scales(model: MeasurementModel, stations) -> np.ndarray:
    parts = [scale_vector(model)]
    for st in stations:
        parts.append(POSE_SCALE if st.kind == "xyz" else np.full(4, UM_PER_MM))
    return np.concatenate(parts)


def phase_masks(model: MeasurementModel, phases) -> list | None:
    """The geometric parameters each phase of an optimisation strategy frees ((p,) bool per phase; ``Strategy.phases``:
    lists of groups from :data:`mtbudget.identify.GROUPS`), or None for one phase of every group (the default).  Every
    phase frees every station's own unknowns (a tracker's pose, an interferometer's position and dead path): they are
    the ``pose`` of the one-tracker strategy, which every phase must name."""
    masks = phase_actives(model, phases, "every station's pose or position is unknown")
    if len(masks) == 1 and masks[0].all():
        return None
    return masks


def strategy_settings(model: MeasurementModel, strategy) -> dict:
    """An optimisation strategy (:class:`mtbudget.identify.Strategy`) as the several-station identification takes it,
    with the meaning the one-tracker identification gives it:

    * ``phases``: :func:`phase_masks` (None: one phase); each phase iterates over its parameters and every station's
      unknowns, the next starting where it stopped, the last on the datum of the whole (:func:`_phase_bases`);
    * ``chord``: the engine's batched solver (:func:`identify_stations_batch`) iterates to min(xtol, STATIONS_XTOL)
      within its own step limit, as the one-tracker chord iterates to min(xtol, ``chord_tol``) within ``chord_iter``:
      a loose xtol does not loosen it, and ``max_iter`` is not its limit;
    * ``reference``: the Gauss-Newton reference (:func:`identify_stations`, which solves a trial the batch gives up on)
      takes xtol and max_iter as they are, as the one-tracker's Gauss-Newton (its fallback) does.
    """
    masks = phase_masks(model, strategy.phases)
    return {"batch": {"xtol": min(float(strategy.xtol), STATIONS_XTOL), "phases": masks},
            "reference": {"xtol": float(strategy.xtol), "max_iter": int(strategy.max_iter), "phases": masks}}


def _phase_bases(Q: np.ndarray, masks: list | None, p: int) -> list:
    """Per phase, the directions Y (r, r_k) (orthonormal, None: all of them) in the coordinates of the basis Q (n, r) of
    the directions the whole identification iterates along whose geometric part lies on the phase's parameters
    (``masks``, :func:`phase_masks`): Q Y spans what the phase moves.  A phase moves within the datum of the whole (the
    directions held at their start stay there), so the last phase ends on that datum with no correction (the
    one-tracker identification analyses each phase alone and puts the solution on its last phase's datum after)."""
    if masks is None:
        return [None]
    out = []
    for mask in masks:
        off = Q[:p][~mask]
        if not off.size:
            out.append(None)
            continue
        _, s, Vt = np.linalg.svd(off, full_matrices=True)
        rank = int((s > 1e-10 * max(s.max(), 1.0)).sum())
        out.append(np.ascontiguousarray(Vt[rank:].T))
    return out


def multilaterate(points: np.ndarray, ranges: np.ndarray) -> tuple[np.ndarray, float]:
    """Closed-form position S (3,) and dead-path offset o of a range station from points (n, 3) and ranges (n,).

    Linearised: |P - c|^2 - l^2 = 2 (P - c).(S - c) - 2 l o + (o^2 - |S - c|^2), linear least squares in
    (S - c, o, k) about the centroid c; needs 5 points off one plane and one sphere.  Exact for exact data.
    """
    P = np.asarray(points, float)
    rho = np.asarray(ranges, float)
    c = P.mean(axis=0)
    Q = P - c
    A = np.column_stack([2.0 * Q, -2.0 * rho, np.ones(len(rho))])
    b = (Q * Q).sum(axis=1) - rho * rho
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    sol, _, rank, sv = np.linalg.lstsq(A / scale, b, rcond=None)
    if rank < 5 or sv[-1] < 1e-10 * sv[0]:
        raise IdentificationError(_NOT_MULTILATERATED)
    sol = sol / scale
    return sol[:3] + c, float(sol[3])


_NOT_MULTILATERATED = ("the ranges of a station do not fix its position and dead path in closed form (its points lie "
                       "on one plane or one sphere, or there are fewer than 5)")


def multilaterate_trials(points: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """:func:`multilaterate` of N trials at once (the same points, ranges (N, n)): (N, 4), each row (S, o).  The same
    least squares, by one batched SVD of the N scaled systems (each solved alone: a trial's numbers do not depend on
    the others); :func:`multilaterate` is the reference it is tested against."""
    P = np.asarray(points, float)
    rho = np.asarray(ranges, float)
    N, n = rho.shape
    c = P.mean(axis=0)
    Q = P - c
    A = np.empty((N, n, 5))
    A[:, :, :3] = 2.0 * Q
    A[:, :, 3] = -2.0 * rho
    A[:, :, 4] = 1.0
    b = (Q * Q).sum(axis=1) - rho * rho  # (N, n)
    scale = np.sqrt((A * A).sum(axis=1))  # (N, 5)
    scale[scale == 0] = 1.0
    U, sv, Vt = np.linalg.svd(A / scale[:, None, :], full_matrices=False)
    if n < 5 or ((sv[:, -1] < 1e-10 * sv[:, 0]) | (sv[:, -1] <= 0)).any():
        raise IdentificationError(_NOT_MULTILATERATED)
    sol = np.einsum("nji,nj->ni", Vt, np.einsum("nmj,nm->nj", U, b) / sv) / scale  # V diag(1/s) U^T b, unscaled
    out = np.empty((N, 4))
    out[:, :3] = sol[:, :3] + c
    out[:, 3] = sol[:, 3]
    return out


@dataclass
class _Rows:
    """One station's rows and what stays fixed during the iterations (whiteners, sigmas)."""

    station: object
    idx: np.ndarray
    meas: np.ndarray  # (n, 3) or (n,)
    weight: np.ndarray  # (n, 3, 3) whiteners or (n,) 1/sigma


def _mv(W: np.ndarray, e: np.ndarray) -> np.ndarray:
    """W e for stacks of 3 x 3 matrices and 3-vectors (..., 3, 3), (..., 3): elementwise, so each row's numbers do
    not depend on the others (and 10x faster than numpy's stacked matmul of tiny matrices)."""
    return W[..., :, 0] * e[..., None, 0] + W[..., :, 1] * e[..., None, 1] + W[..., :, 2] * e[..., None, 2]


def _mtv(W: np.ndarray, e: np.ndarray) -> np.ndarray:
    """W^T e, as :func:`_mv`."""
    return W[..., 0, :] * e[..., 0, None] + W[..., 1, :] * e[..., 1, None] + W[..., 2, :] * e[..., 2, None]


def _evaluate(model, fixed, rows, x, sv, jacobian=True):
    """Whitened residuals (n_res,) and, optionally, the whitened Jacobian of the predictions in scaled unknowns."""
    p = model.n_params
    theta = x[:p]
    if jacobian:
        P_W, J_W = model.machine_points(theta[None], fixed, jacobian=True)
        P_W, J_W = P_W[0], J_W[0]
    else:
        P_W = model.machine_points(theta[None], fixed)[0]
    res, jac, raw = [], [], []
    k = p
    n = len(x)
    for r in rows:
        st = r.station
        P = P_W[r.idx]
        if st.kind == "xyz":
            pose = x[k:k + 6]
            R = lt.rotation(pose[3], pose[4], pose[5])
            pred = (P - pose[:3]) @ R  # R^T (P - T), row by row
            e = r.meas - pred
            raw.append(e)
            res.append(np.einsum("nij,nj->ni", r.weight, e).ravel())
            if jacobian:
                J = np.zeros((len(r.idx), 3, n))
                J[:, :, :p] = np.einsum("ji,njk->nik", R, J_W[r.idx])
                J[:, :, k:k + 6] = lt.pose_jacobian(P[None], pose[None])[0]
                jac.append(np.einsum("nij,njk->nik", r.weight, J).reshape(-1, n))
            k += 6
        else:
            S, o = x[k:k + 3], x[k + 3]
            d = P - S
            dist = np.linalg.norm(d, axis=1)
            e = r.meas - (dist + o)
            raw.append(e)
            res.append(r.weight * e)
            if jacobian:
                u = d / dist[:, None]
                J = np.zeros((len(r.idx), n))
                J[:, :p] = np.einsum("ni,nik->nk", u, J_W[r.idx])
                J[:, k:k + 3] = -u
                J[:, k + 3] = 1.0
                jac.append(r.weight[:, None] * J)
            k += 4
    w = np.concatenate(res)
    if not jacobian:
        return w, raw, None
    return w, raw, np.concatenate(jac, axis=0) / sv  # d(whitened prediction)/d(scaled unknowns)


def _null_space(A: np.ndarray, rank_tol: float):
    """rank, singular values, condition number and orthonormal null space (scaled unknowns) of A."""
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    _, s, Vt = np.linalg.svd(A / norms, full_matrices=A.shape[0] < A.shape[1])
    s_full = np.zeros(A.shape[1])
    s_full[:s.size] = s
    rank = int((s_full > rank_tol * s_full[0]).sum())
    V = Vt.T / norms[:, None]
    null = V[:, rank:]
    if null.shape[1]:
        q, rr = np.linalg.qr(null)
        null = q[:, np.abs(np.diag(rr)) > 1e-14 * max(np.abs(np.diag(rr)).max(), 1e-300)]
    return rank, s_full, float(s_full[0] / s_full[rank - 1]) if rank else float("inf"), null


def _free_basis(A: np.ndarray, null: np.ndarray, hold: np.ndarray | None, rank_tol: float) -> np.ndarray:
    """Orthonormal basis (n, r) of the directions the iterations move the scaled unknowns along: every direction but
    the null space ``null`` of the whitened Jacobian A (minimum norm: they stay at their start), or, with ``hold``
    (p, h) directions of the geometric parameters, every direction but those (held at their start) and what else A
    cannot see among the rest.  A rigid motion of the machine points together with every station changes no
    measurement, so a geometric direction that moves the points rigidly is null only together with the stations:
    holding its geometric part fixes the same datum as holding the combination, and the minimum reached is the
    same, but the geometric parameters then never move along it (as with one tracker, whose pose absorbs it)."""
    n = A.shape[1]
    if hold is None or hold.size == 0:
        return range_basis(np.ones(n, bool), null)
    H = np.zeros((n, hold.shape[1]))
    H[:hold.shape[0]] = hold
    Q0 = range_basis(np.ones(n, bool), np.linalg.qr(H)[0])
    AQ = A @ Q0
    norms = np.linalg.norm(AQ, axis=0)
    norms[norms == 0] = 1.0
    _, sv, Vt = np.linalg.svd(AQ / norms, full_matrices=False)
    keep = sv > rank_tol * sv[0]
    V = Vt[keep].T / norms[:, None]
    return np.linalg.qr(Q0 @ V)[0]


def _gauge(model, fixed, stations, P0, J_W) -> list:
    """The six rigid freedoms of the whole (machine points and every station together): for each, whether the
    error model can move the machine points that way (then the data cannot see it: a null direction, held at the
    start by minimum norm) or not (then the error model's convention fixes it)."""
    M = P0.shape[0]
    c = P0.mean(axis=0)
    G = np.zeros((M, 3, 6))
    G[:, :, :3] = np.eye(3)[None]
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1.0
        G[:, :, 3 + a] = np.cross(e, P0 - c)
    A = J_W.reshape(3 * M, -1)
    Gm = G.reshape(3 * M, 6)
    if A.shape[1]:
        coef = np.linalg.lstsq(A, Gm, rcond=None)[0]  # the closest the geometric parameters come to each motion
        left = np.linalg.norm(A @ coef - Gm, axis=0) / np.linalg.norm(Gm, axis=0)
    else:
        left = np.ones(6)
    out = []
    for k, name in enumerate(RIGID_FREEDOMS):
        null = bool(left[k] <= 1e-6)
        out.append({
            "freedom": f"{name} of the machine points and every station together",
            "fixed_by": ("minimum norm: the error model can move the machine points this way, so the data cannot see "
                         "it (a null direction, named under 'not identifiable'), held at its start" if null else
                         f"the error model's convention: no combination of its parameters moves the machine points "
                         f"this way (the closest leaves {left[k]:.0%} of it)"),
            "null_direction": null})
    return out


def _range_start(st, points: np.ndarray, ranges: np.ndarray):
    """:func:`multilaterate` of one range station (ranges (n,)), or :func:`multilaterate_trials` of N trials (ranges
    (N, n)), its failure naming the station and what to change."""
    try:
        return multilaterate(points, ranges) if np.ndim(ranges) == 1 else multilaterate_trials(points, ranges)
    except IdentificationError as exc:
        raise IdentificationError(f"{st.label}: {exc.reason}; measure points on more than one plane (the mesh's z "
                                  "range) and at different distances from it") from None


def _tracker_whiteners(meas: np.ndarray, st, repeatability: float) -> np.ndarray:
    """The whiteners (N, m, 3, 3) of a laser tracker's measured points meas (N, m, 3): ``whitener(covariance +
    repeatability^2 I)``, in one compiled pass for stated scalar noise (:func:`mtbudget.kernels_stations.
    tracker_whiteners`, the same bits), else (or where a covariance is not positive definite) with numpy."""
    stated = (st.angular, st.distance, st.distance_per_length)
    if all(np.ndim(v) == 0 for v in stated) and np.ndim(repeatability) == 0:
        from .kernels_stations import tracker_whiteners

        out = np.empty(meas.shape + (3,))
        if tracker_whiteners(np.ascontiguousarray(meas, float), *(float(v) for v in stated),
                             float(repeatability**2), out):
            return out
    C = lt.covariance(meas, st.angular, st.distance, st.distance_per_length) + repeatability**2 * np.eye(3)
    return whitener(C)


def _station_rows(model, stations, row_station, lt_xyz, lt_range, repeatability, P0):
    """Every station's rows with their fixed whiteners, and the closed-form start of the unknowns (theta = 0)."""
    M = model.n_points
    x0 = [np.zeros(model.n_params)]
    rows = []
    for st in stations:
        idx = np.flatnonzero(row_station == st.id)
        if st.kind == "xyz":
            meas = lt_xyz[idx]
            if len(idx) < 3 or not np.isfinite(meas).all():
                raise IdentificationError(f"{st.label}: needs at least 3 rows with finite lt_x, lt_y, lt_z")
            C = lt.covariance(meas, st.angular, st.distance, st.distance_per_length) + repeatability**2 * np.eye(3)
            rows.append(_Rows(st, idx, meas, whitener(C)))
            x0.append(lt.register(P0[idx], meas[None])[0])
        elif st.kind == "range":
            meas = lt_range[idx]
            if len(idx) < 5 or not np.isfinite(meas).all():
                raise IdentificationError(f"{st.label}: needs at least 5 rows with a finite lt_range for a start "
                                          "position")
            S, o = _range_start(st, P0[idx], meas)
            r = np.linalg.norm(P0[idx] - S, axis=1)  # the length-proportional part at the start's distances
            sigma = np.sqrt((st.distance + st.distance_per_length * r) ** 2 + repeatability**2)
            rows.append(_Rows(st, idx, meas, 1.0 / sigma))
            x0.append(np.concatenate([S, [o]]))
        else:
            raise IdentificationError(f"station {st.id}: unknown kind {st.kind!r}; expected 'xyz' or 'range'")
    if not np.isin(np.arange(M), np.concatenate([r.idx for r in rows])).all():
        raise IdentificationError("some rows belong to no station")
    return rows, x0


def identify_stations(model: MeasurementModel, stations: list, row_station, lt_xyz, lt_range, repeatability: float,
                      *, fixed: dict | None = None, max_iter: int = 50, xtol: float = STATIONS_XTOL,
                      rank_tol: float = 1e-7, hold: np.ndarray | None = None,
                      phases: list | None = None) -> MultiIdentification:
    """Identify the geometric errors and every station's own unknowns from all stations at once.

    stations: :class:`mtbudget.recording.Station` (id, kind, stated uncertainties); row_station (M,) the station of
    every row of ``model.plan``; lt_xyz (M, 3) the xyz rows in their station's frame (mm, NaN elsewhere); lt_range
    (M,) the range rows (mm, NaN elsewhere); repeatability (mm) of the machine; fixed: known perturbations
    (``MODEL_INPUTS`` keys, e.g. ``Recording.fixed_inputs()``).  xtol: convergence, largest step of a scaled
    unknown (um, urad).  hold: (p, h) directions of the geometric parameters (scaled, orthonormal) held at their
    start instead of the minimum-norm datum, e.g. what one tracker cannot identify
    (:meth:`mtbudget.scenario.Scenario.unidentifiable`): see :func:`_free_basis`.  phases: the parameters each phase
    of a multi-phase identification frees (:func:`phase_masks`; None: one phase): Gauss-Newton to xtol or max_iter in
    each, the next from where it stopped (``converged``: every phase converged; ``iterations``: summed).
    """
    row_station = np.asarray(row_station)
    M = model.n_points
    if row_station.shape != (M,):
        raise IdentificationError(f"row_station has shape {row_station.shape}; the plan has {M} points")
    lt_xyz = np.asarray(lt_xyz, float).reshape(M, 3) if lt_xyz is not None else np.full((M, 3), np.nan)
    lt_range = np.asarray(lt_range, float).reshape(M) if lt_range is not None else np.full(M, np.nan)
    fixed = dict(fixed or {})
    ids = [st.id for st in stations]
    if len(set(ids)) != len(ids):
        raise IdentificationError(f"station ids must be unique, got {ids}")
    if not np.isin(row_station, ids).all():
        bad = int(row_station[~np.isin(row_station, ids)][0])
        raise IdentificationError(f"rows of station {bad}, which is not among the stations {ids}")
    P0, J0 = model.machine_points(np.zeros((1, model.n_params)), fixed, jacobian=True)
    P0, J0 = P0[0], J0[0]
    rows, x0 = _station_rows(model, stations, row_station, lt_xyz, lt_range, repeatability, P0)
    x = np.concatenate(x0)
    sv = _scales(model, stations)
    names, units = _names(model, stations)
    n = len(x)

    w, raw, A = _evaluate(model, fixed, rows, x, sv)
    if A.shape[0] <= n:
        raise IdentificationError(f"too few measurements: {A.shape[0]} residuals for {n} unknowns")
    rank, s, cond, null = _null_space(A, rank_tol)
    Q = _free_basis(A, null, hold, rank_tol)
    if A.shape[0] <= Q.shape[1]:
        raise IdentificationError(f"too few measurements: {A.shape[0]} residuals for {Q.shape[1]} identifiable "
                                  "unknowns (no redundancy left)")
    cost = float(w @ w)
    converged_all = True
    iterations = 0
    for Y in _phase_bases(Q, phases, model.n_params):
        Qk = Q if Y is None else Q @ Y
        converged = False
        it = 0
        for it in range(1, max_iter + 1):
            y = np.linalg.lstsq(A @ Qk, w, rcond=None)[0]
            z = Qk @ y
            step = 1.0
            for _ in range(40):
                x_new = x + step * z / sv
                w_new, raw_new, A_new = _evaluate(model, fixed, rows, x_new, sv)
                c_new = float(w_new @ w_new)
                if c_new <= cost * (1 + 1e-10) + 1e-300:
                    break
                step *= 0.5
            else:
                break
            small = np.abs(z).max() * step < xtol or cost - c_new <= 1e-15 * cost
            x, w, raw, A, cost = x_new, w_new, raw_new, A_new, c_new
            if small:
                converged = True
                break
        converged_all &= converged
        iterations += it
    converged, it = converged_all, iterations
    AQ = A @ Q
    H = AQ.T @ AQ
    cov_z = Q @ np.linalg.solve(H, Q.T)
    cov = cov_z / np.outer(sv, sv)
    res_xyz = np.full((M, 3), np.nan)
    res_rng = np.full(M, np.nan)
    station_chi2 = {}
    k = 0
    for r, e in zip(rows, raw):
        m = e.size
        station_chi2[r.station.id] = (float(w[k:k + m] @ w[k:k + m]), m)
        k += m
        if r.station.kind == "xyz":
            res_xyz[r.idx] = e
        else:
            res_rng[r.idx] = e
    return MultiIdentification(
        model=model, stations=list(stations), names=names, units=units, x=x, cov=cov, chi2=cost,
        dof=int(A.shape[0] - rank), rank=rank, condition=cond, singular_values=s, null_space=null,
        gauge=_gauge(model, fixed, stations, P0, J0), converged=converged, iterations=it, row_station=row_station,
        residual_xyz=res_xyz, residual_range=res_rng, whitened=w, station_chi2=station_chi2)


@dataclass
class Linearisation:
    """The whitened linear model around a :class:`MultiIdentification`'s solution, for nested tests on it
    (:mod:`mtbudget.diagnose`).  Internal units: mm.

    The whitened residuals are ordered as :attr:`MultiIdentification.whitened`: station by station, each
    station's rows in plan order, three entries per xyz row (its whitener applied to the station-frame residual)
    and one per range row (the range residual over its standard deviation).
    """

    design: np.ndarray  # (n_res, r) whitened Jacobian on the identifiable directions (scaled unknowns)
    whitened: np.ndarray  # (n_res,) whitened residuals (measured - predicted)
    row: np.ndarray  # (n_res,) the plan row of every whitened residual
    machine: np.ndarray  # (n_res, 3) whitened residual per mm of displacement of its row's point, machine frame
    station: np.ndarray  # (n_res, 3) the same per mm of displacement in its row's station frame
    rotation: np.ndarray  # (M, 3, 3) R of each row's station (machine <- station frame; identity for a range station)
    beam: np.ndarray  # (M, 3) unit vector from the row's station to its point, in the station's frame
    P_W: np.ndarray  # (M, 3) predicted machine-frame points
    P_station: np.ndarray  # (M, 3) predicted point in its station's frame (a range station: P_W - S)
    residual_machine: np.ndarray  # (M, 3) residual in the machine frame (a range row: along its beam only)
    residual_size: np.ndarray  # (M,) |residual| of every row, mm (xyz: 3-D; range: the range residual's size)
    residuals_per_row: np.ndarray  # (M,) 3 for an xyz row, 1 for a range row


def identify_stations_batch(model: MeasurementModel, stations: list, row_station, lt_xyz, lt_range,
                            repeatability: float, *, fixed: dict | None = None, max_iter: int = 50,
                            xtol: float = STATIONS_XTOL, rank_tol: float = 1e-7, hold: np.ndarray | None = None,
                            basis: tuple | None = None, chord_bias: float = 1e-3, phases: list | None = None) -> dict:
    """:func:`identify_stations` for N trials of one plan at once (the engine's): lt_xyz (N, M, 3), lt_range (N, M).

    The same weighted least squares, the same closed-form starts, the same whiteners and the same convergence
    test (a Gauss-Newton step below ``xtol``), vectorised over the trials.  What the trials share is computed once:
    the nominal machine points, and the directions the data cannot see (the null space of the whitened Jacobian at
    the first trial's start: what a plan and a set of stations identify does not depend on the noise).  The
    Jacobian is evaluated only when the chord iterations on the last one have converged (each chord step costs a
    residual evaluation): a trial has converged when the first step after a fresh Jacobian, a full Gauss-Newton
    step, is below ``xtol``.  A trial whose cost rises on such a step (where Gauss-Newton would halve it) is
    ``failed``: the caller solves it again with :func:`identify_stations`, the reference.

    basis: (Q, rank) the directions to iterate along and the Jacobian's rank, as a previous call returned them
    (``"basis"``); without it they come from the first trial's Jacobian, so the last bits of every trial depend on
    which trials are identified together: the engine passes the basis of the noise-free verification.  With
    (Q, rank, Qr, Hinv, nominal) (:func:`chord_basis`) and no ``fixed`` inputs, the trials iterate with that one shared
    matrix and never form a Jacobian (:func:`_batch_chord`; ``chord_bias``: its acceptance test).

    Returns a dict: theta (N, p), x (N, n), converged (N,), failed (N,), iterations (N,), chi2 (N,), dof,
    residual_xyz (N, M, 3) mm (NaN on range rows), residual_range (N, M) mm (NaN on xyz rows), basis, jacobian and
    start (the first trial's whitened Jacobian and unknowns at its start when no basis was given, for
    :func:`chord_basis`).

    A trial gives the same bits whatever trials are identified with it, as long as ``basis`` is given: numpy's
    small products round a lone row differently (a matrix-vector path), so a single trial is evaluated as two.

    phases: the parameters each phase of a multi-phase identification frees (:func:`phase_masks`; None: one phase of
    everything).  Each phase iterates along its own directions (:func:`_phase_bases`) from where the previous one
    stopped; as in the one-tracker chord, the chord runs its first stage alone in the earlier phases (they only give the
    last its start) and the last phase to xtol; the Gauss-Newton path runs every phase to xtol.
    """
    if np.shape(lt_xyz)[0] == 1:  # one trial: as two (see above), the first returned
        two = identify_stations_batch(model, stations, row_station, np.repeat(lt_xyz, 2, axis=0),
                                      np.repeat(lt_range, 2, axis=0), repeatability, fixed=fixed, max_iter=max_iter,
                                      xtol=xtol, rank_tol=rank_tol, hold=hold, basis=basis, chord_bias=chord_bias,
                                      phases=phases)
        return {k: (v[:1] if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == 2 else v) for k, v in two.items()}
    N = np.shape(lt_xyz)[0]
    if basis is not None and len(basis) == 5 and not fixed and N > CHORD_CHUNK:  # the chord's working set in cache
        parts = [identify_stations_batch(model, stations, row_station, lt_xyz[lo:lo + CHORD_CHUNK],
                                         lt_range[lo:lo + CHORD_CHUNK], repeatability, max_iter=max_iter, xtol=xtol,
                                         rank_tol=rank_tol, hold=hold, basis=basis, chord_bias=chord_bias,
                                         phases=phases)
                 for lo in range(0, N, CHORD_CHUNK)]
        return {k: (np.concatenate([q[k] for q in parts]) if isinstance(v, np.ndarray) and v.ndim and
                    v.shape[0] == len(lt_xyz[:CHORD_CHUNK]) else v) for k, v in parts[0].items()}
    fixed = dict(fixed or {})
    lt_xyz = np.asarray(lt_xyz, float)
    lt_range = np.asarray(lt_range, float)
    N, M = lt_xyz.shape[:2]
    p = model.n_params
    row_station = np.asarray(row_station)
    P0 = model.machine_points(np.zeros((1, p)), fixed)[0]
    blocks = []  # (station, rows, weight (N, m, 3, 3) or (N, m), slice of x)
    x0 = [np.zeros((N, p))]
    k = p
    for st in stations:
        idx = np.flatnonzero(row_station == st.id)
        if st.kind == "xyz":
            meas = lt_xyz[:, idx]
            blocks.append((st, idx, _tracker_whiteners(meas, st, repeatability), slice(k, k + 6)))
            x0.append(lt.register(np.broadcast_to(P0[idx], meas.shape), meas))
            k += 6
        else:
            meas = lt_range[:, idx]
            starts = _range_start(st, P0[idx], meas)  # (N, 4): every trial's closed-form start at once
            r = lt.norm3(P0[idx][None] - starts[:, None, :3])  # sqrt(((...) ** 2).sum(-1)): the same order
            sigma = np.sqrt((st.distance + st.distance_per_length * r) ** 2 + repeatability**2)
            blocks.append((st, idx, 1.0 / sigma, slice(k, k + 4)))
            x0.append(starts)
            k += 4
    n = k
    x = np.concatenate(x0, axis=1)
    sv = _scales(model, stations)

    def evaluate(x, t, jacobian=True):
        """Whitened residuals (k, n_res), raw residuals per block and the whitened Jacobian (k, n_res, n) in scaled
        unknowns of trials ``t`` at their unknowns ``x`` (k, n); a lone trial evaluated as two."""
        if len(t) == 1:
            w2, raw2, A2 = evaluate(np.repeat(x, 2, axis=0), np.repeat(t, 2), jacobian)
            return w2[:1], [r[:1] for r in raw2], None if A2 is None else A2[:1]
        N = len(t)
        theta = x[:, :p]
        if jacobian:
            P_W, J_W = model.machine_points(theta, fixed, jacobian=True)
        else:
            P_W, J_W = model.machine_points(theta, fixed), None
        res, jac, raw = [], [], []
        for st, idx, W, sl in blocks:
            P = P_W[:, idx]
            if st.kind == "xyz":
                pose = x[:, sl]
                R = lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5])  # (N, 3, 3)
                pred = _mtv(R[:, None], P - pose[:, None, :3])  # R^T (P - T)
                e = lt_xyz[t][:, idx] - pred
                W = W[t]
                raw.append(e)
                res.append(_mv(W, e).reshape(N, -1))
                if jacobian:
                    J = np.zeros((N, len(idx), 3, n))
                    WR = W @ np.swapaxes(R, 1, 2)[:, None]  # (N, m, 3, 3): whitener times R^T
                    J[..., :p] = WR @ J_W[:, idx]
                    J[..., sl] = W @ lt.pose_jacobian(P, pose)
                    jac.append(J.reshape(N, -1, n))
            else:
                Sx, o = x[:, sl][:, :3], x[:, sl][:, 3]
                d = P - Sx[:, None, :]
                dist = np.sqrt((d * d).sum(-1))
                e = lt_range[t][:, idx] - (dist + o[:, None])
                W = W[t]
                raw.append(e)
                res.append(W * e)
                if jacobian:
                    u = d / dist[..., None]
                    J = np.zeros((N, len(idx), n))
                    J[..., :p] = (u[..., None, :] @ J_W[:, idx])[..., 0, :]
                    J[..., sl.start:sl.start + 3] = -u
                    J[..., sl.start + 3] = 1.0
                    jac.append(W[..., None] * J)
        w = np.concatenate(res, axis=1)
        A = np.concatenate(jac, axis=1) / sv if jacobian else None
        return w, raw, A

    all_trials = np.arange(N)
    if basis is not None and len(basis) == 5 and not fixed:  # the shared chord matrix: no Jacobian per trial
        return _batch_chord(model, blocks, x, evaluate, sv, basis, lt_xyz, lt_range, M, N, p, max_iter, xtol,
                            chord_bias, phases)
    x_first = x[0].copy() if basis is None else None  # the first trial's start, where A_first is taken
    w, raw, A = evaluate(x, all_trials)
    A_first = A[0] if basis is None else None
    if basis is None:
        rank, _, _, null = _null_space(A[0], rank_tol)
        Q = _free_basis(A[0], null, hold, rank_tol)
    else:  # given: the same for any grouping of the trials (the engine's, from the noise-free verification)
        Q, rank = basis[:2]
    cost = (w * w).sum(axis=1)
    failed = np.zeros(N, bool)
    iterations = np.zeros(N, int)
    converged_all = np.ones(N, bool)
    # Gauss-Newton with the Jacobian refreshed only when the chord iterations on it have converged: a trial is
    # converged when the first step after a refresh (a full Gauss-Newton step) is below xtol, which is
    # identify_stations' criterion; the chord steps in between cost a residual evaluation each, not a Jacobian
    Q_all = Q
    for k, Y in enumerate(_phase_bases(Q_all, phases, p)):
        Q = Q_all if Y is None else Q_all @ Y
        converged = np.zeros(N, bool)
        a = np.flatnonzero(~failed) if k else all_trials
        _refreshes(a, k, Q, converged, failed, iterations, x, w, raw, A, cost, evaluate, sv, max_iter, xtol)
        converged_all &= converged
    converged = converged_all
    res_xyz, res_rng = _split_residuals(blocks, raw, N, M)
    return {"theta": x[:, :p], "x": x, "converged": converged, "iterations": iterations, "chi2": cost,
            "dof": int(w.shape[1] - rank), "failed": failed, "residual_xyz": res_xyz, "residual_range": res_rng,
            "basis": (Q_all, rank), "jacobian": A_first, "start": x_first,
            "whiteners": None if A_first is None else [W[0] for _, _, W, _ in blocks]}


def _refreshes(a, phase, Q, converged, failed, iterations, x, w, raw, A, cost, evaluate, sv, max_iter, xtol):
    """:func:`identify_stations_batch`'s Gauss-Newton path on the trials ``a`` along the directions Q, in place (x, w,
    raw, cost, converged, failed, iterations); A: the Jacobian of every trial at its start (read in the first phase
    only, later phases evaluate their own)."""
    for refresh in range(max_iter):
        if refresh or phase:
            w_a, raw_a, A_a = evaluate(x[a], a)
            w[a], A = w_a, A_a
            for r_all, r_new in zip(raw, raw_a):
                r_all[a] = r_new
        else:
            A = A[a]
        AQ = A @ Q
        AQt = np.swapaxes(AQ, 1, 2)
        L = np.linalg.cholesky(AQt @ AQ)  # (na, q, q): the normal matrix of this Jacobian, factorised once
        first = np.ones(len(a), bool)
        inner = np.ones(len(a), bool)
        for it in range(max_iter):
            b = np.flatnonzero(inner)
            if not len(b):
                break
            t = a[b]
            g = (AQt[b] @ w[t][..., None])
            y = np.linalg.solve(L[b], g)
            y = np.linalg.solve(np.swapaxes(L[b], 1, 2), y)[..., 0]
            z = (Q @ y[..., None])[..., 0]  # trial by trial: a product over all of them rounds by their count
            x_new = x[t] + z / sv
            w_new, raw_new, _ = evaluate(x_new, t, jacobian=False)
            c_new = (w_new * w_new).sum(axis=1)
            rose = ~(c_new <= cost[t] * (1 + 1e-10) + 1e-300)
            keep = ~rose
            tk = t[keep]
            x[tk], w[tk], cost[tk] = x_new[keep], w_new[keep], c_new[keep]
            for r_all, r_new in zip(raw, raw_new):
                r_all[tk] = r_new[keep]
            iterations[t] += 1
            small = np.abs(z).max(axis=1) < xtol
            converged[t[keep & small & first[b]]] = True
            # a chord step that raises the cost ends this Jacobian: refresh (a Gauss-Newton step from here); one that
            # raises it right after a refresh is where Gauss-Newton would halve its step: given up here, counted
            failed[t[rose & first[b]]] = True
            inner[b[rose | small]] = False
            first[b] = False
        a = np.flatnonzero(~converged & ~failed)
        if not len(a):
            break


def chord_basis(batch: dict, model: MeasurementModel, stations: list, row_station, *, hold: np.ndarray | None = None,
                fixed: dict | None = None, rank_tol: float = 1e-7) -> tuple:
    """(Q, rank, Qr, Hinv, J0): the basis (Q, rank) of an :func:`identify_stations_batch` result without a basis given
    (the engine's: the noise-free verification), with the chord's shared matrices from its whitened Jacobian A0
    (n_res, n) at its start, computed once per scenario and shared by every trial (:func:`identify_stations_batch`
    with this basis).  The chord moves a laser tracker's pose by a small rigid motion of the station (translation,
    then rotation about the centroid of its rows' nominal points; :func:`_batch_chord`), as the one-tracker chord
    does, not by its Euler angles: A0's pose columns are replaced by those of that motion, Qr is the basis of the
    directions to iterate along in these coordinates (:func:`_free_basis`, the same ``hold``), Hinv the inverse of
    H0 = (A0 Qr)^T A0 Qr, and J0 (M, 3, p) the chain's nominal Jacobian in the machine frame; the fifth element is
    (J0, the interferometers' nominal beams, H0), H0 for the phases of a multi-phase identification."""
    Q, rank = batch["basis"]
    A0 = batch["jacobian"].copy()
    x0 = batch["start"]
    sv = _scales(model, stations)
    p = model.n_params
    P0, J0 = model.machine_points(np.zeros((1, p)), dict(fixed or {}), jacobian=True)
    P0, J0 = P0[0], J0[0]
    row_station = np.asarray(row_station)
    off, k = 0, p
    beams = {}  # a range station's first column -> (1, m, 3) its nominal beam directions
    for st, W in zip(stations, batch["whiteners"]):
        idx = np.flatnonzero(row_station == st.id)
        m = len(idx)
        if st.kind == "xyz":  # W R^T [-I, [d]x] per row, d = P - c: the prediction's change with the rigid motion
            R = lt.rotation(*x0[k + 3:k + 6])
            d = P0[idx] - P0[idx].mean(axis=0)
            C = np.zeros((m, 3, 6))
            C[:, :, :3] = -np.eye(3)
            C[:, 0, 4], C[:, 0, 5] = -d[:, 2], d[:, 1]
            C[:, 1, 3], C[:, 1, 5] = d[:, 2], -d[:, 0]
            C[:, 2, 3], C[:, 2, 4] = -d[:, 1], d[:, 0]
            A0[off:off + 3 * m, k:k + 6] = (W @ (R.T @ C)).reshape(3 * m, 6) / sv[k:k + 6]
            off, k = off + 3 * m, k + 6
        else:  # the unit vectors from the station to its points there
            d = P0[idx] - x0[k:k + 3]
            beams[k] = np.ascontiguousarray((d / np.sqrt((d * d).sum(-1))[:, None])[None])
            off, k = off + m, k + 4
    _, _, _, null = _null_space(A0, rank_tol)
    Qr = _free_basis(A0, null, hold, rank_tol)
    G0 = A0 @ Qr
    H0 = G0.T @ G0
    return Q, rank, Qr, np.linalg.inv(H0), (np.ascontiguousarray(J0.reshape(3 * model.n_points, p)), beams, H0)


def _distinct_rows_chain(model: MeasurementModel):
    """(chain_at, inv): ``chain_at(theta)`` the compiled chain's points (k, Mu, 3) of the parameters theta (k, p) at
    the plan's distinct rows only (rows whose inputs to the chain are the same bits: several stations measuring the
    same poses), in the order of their first row, and inv (M,) the distinct row of each of the plan's rows.  A
    point's numbers depend on its own inputs only (:func:`mtbudget.kernels.chain_points`), so
    ``chain_at(theta)[:, inv]`` is ``model.machine_points(theta)`` bit for bit (no perturbations: the chord's case).
    Remembered on the model (with its plan and basis values)."""
    from .kernels import chain_points
    from .machine import kernel_chain, kernel_parameters

    hit = model.__dict__.get("_distinct_rows_chain")
    if hit is not None and hit[0] is model.plan and hit[1] is model.B and hit[2] is model.errors.params:
        return hit[3]
    k = kernel_chain(model.config, model.errors, model.chain_inputs({}), model.B, 1)
    M = model.n_points
    px, py, pz, tool, L, rcos, rsin = k["px"], k["py"], k["pz"], k["tool"], k["L"], k["rcos"], k["rsin"]
    if px.shape[0] == 1 and py.shape[0] == 1 and pz.shape[0] == 1 and rcos.shape[1] == 1 and rsin.shape[1] == 1:
        rows = np.concatenate([px, py, pz, tool.T, L.reshape(-1, M), rcos.reshape(-1, M), rsin.reshape(-1, M)]).T
        _, first, inv = np.unique(np.ascontiguousarray(rows).view(np.uint64), axis=0, return_index=True,
                                  return_inverse=True)
        order = np.argsort(first)
        u = first[order]
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        inv = rank[inv.reshape(-1)]
    else:  # per-trial positions or angles: every row its own
        u = inv = np.arange(M)
    fixed = tuple(np.ascontiguousarray(a) for a in (
        px[:, u], py[:, u], pz[:, u], tool[u], L[:, :, u], rcos[:, :, u], rsin[:, :, u]))

    def chain_at(theta):
        coef, sq = kernel_parameters(k, theta)
        ux, uy, uz, utool, uL, ucos, usin = fixed
        scratch = np.empty((1, uL.shape[0], 3, len(u)))  # nothing kept for an adjoint (per call: threads share it)
        return chain_points(k["tool_axes"], k["wp_axes"], k["side"], ux, uy, uz, utool, coef, uL, sq, k["rdir"],
                            k["pivot"], ucos, usin, np.empty((theta.shape[0], len(u), 3)), scratch, scratch, scratch)

    hit = (chain_at, np.ascontiguousarray(inv, np.int64))
    model.__dict__["_distinct_rows_chain"] = (model.plan, model.B, model.errors.params, hit)
    return hit


def _batch_chord(model, blocks, x, evaluate, sv, basis, lt_xyz, lt_range, M, N, p, max_iter, xtol, chord_bias,
                 phases=None):
    """:func:`identify_stations_batch` with one iteration matrix shared by every trial (``basis`` from
    :func:`chord_basis`), as the one-tracker identification (:func:`mtbudget.identify.identify`) does.

    A laser tracker's pose moves by a small rigid motion of the station per step (translation, then rotation about
    the centroid of its rows' nominal points: ``kernels_stations.rigid_step``), whose columns of the Jacobian do not
    depend on where the station stands; an interferometer's position and dead path move as they are.  Each step is
    z = Qr Hinv g with g the trial's gradient A^T w at its current unknowns, its stations' columns exact and the
    chain's ``J^T v`` taken from a Jacobian held for a stage: stage 1 the noise-free verification's (J0), then
    stage 2 twice each trial's own where the previous stage stopped (:func:`mtbudget.machine.chain_adjoint`,
    compiled, J never formed), to ``xtol``.  A trial whose steps do not contract (by 2x per step after the first
    two, in the energy norm of the step: the weakest directions converge more slowly and change the fit least),
    that needs more than ``max_iter`` steps in a stage, or whose estimated remaining bias (the distance stage 2
    moved, squared, over the distance from the start: its Jacobian was that far from the minimum) exceeds
    ``chord_bias`` (um or urad) is ``failed``: the caller solves it with :func:`identify_stations`.  Every product is
    taken trial by trial (a trial's bits do not depend on the trials identified with it).  The residuals and
    gradients are compiled (:mod:`mtbudget.kernels_stations`); ``evaluate`` (the batch's numpy residuals) is their
    reference in the tests.

    phases (:func:`phase_masks`): a multi-phase identification, as the one-tracker chord runs it: each earlier phase
    runs stage 1 alone along its own directions Qr Y (:func:`_phase_bases`), with the shared matrix restricted to them
    (Y (Y^T H0 Y)^-1 Y^T, in the coordinates of Qr), and gives the next its start; the last runs every stage."""
    from . import kernels_stations as ks
    from .machine import chain_adjoint

    _, rank, Qr, Hinv, (J0, beams0, H0) = basis
    # each phase's iteration matrix in the coordinates of Qr: the shared one (one phase of everything: Hinv itself)
    mats = [Hinv if Y is None else Y @ np.linalg.solve(Y.T @ H0 @ Y, Y.T) for Y in _phase_bases(Qr, phases, p)]
    n_res = sum(3 * len(idx) if st.kind == "xyz" else len(idx) for st, idx, _, _ in blocks)
    P0 = model.machine_points(np.zeros((1, p)))[0]
    chain_at, inv = _distinct_rows_chain(model)  # the chain on the plan's distinct rows; row r is inv[r] of them
    # per station, once: its rows, its measurements and whiteners of every trial (contiguous), its first column
    # among the unknowns and among the whitened residuals, an xyz station's centre of rotation, and its rows among
    # the distinct rows the chain evaluates
    plan, off = [], 0
    for st, idx, W, sl in blocks:
        meas = lt_xyz[:, idx] if st.kind == "xyz" else lt_range[:, idx]
        plan.append((st.kind == "xyz", np.ascontiguousarray(idx, np.int64), np.ascontiguousarray(meas),
                     np.ascontiguousarray(W), sl.start, off, np.ascontiguousarray(P0[idx].mean(axis=0)),
                     np.ascontiguousarray(inv[idx], np.int64)))
        off += 3 * len(idx) if st.kind == "xyz" else len(idx)
    # the rotation of every xyz station of every trial, moved by the steps (x keeps its Euler angles, read back)
    rot = {c0: np.ascontiguousarray(lt.rotation(x[:, c0 + 3], x[:, c0 + 4], x[:, c0 + 5]))
           for xyz, _, _, _, c0, _, _, _ in plan if xyz}
    angles0 = {c0: x[:, c0 + 3:c0 + 6].copy() for c0 in rot}
    centres = {c0: cen for xyz, _, _, _, c0, _, cen, _ in plan if xyz}
    # every trial's whitened residuals and each station's raw residuals at its current unknowns, written in place
    w = np.empty((N, n_res))
    raw = [np.empty((N, len(idx), 3) if xyz else (N, len(idx))) for xyz, idx, *_ in plan]
    # a laser tracker's part of every trial's next gradient, left by its residuals (kernels_stations.xyz_residual):
    # the machine-frame vectors of its rows and its pose's six columns
    ahead = {c0: (np.empty((N, len(idx), 3)), np.empty((N, 6))) for xyz, idx, _, _, c0, *_ in plan if xyz}

    def residuals(a):
        """The whitened and raw residuals of trials ``a`` at their unknowns x[a], into w and raw."""
        P = chain_at(x[a, :p])
        for (xyz, idx, meas, W, c0, o, cen, pidx), e in zip(plan, raw):
            if xyz:
                ks.xyz_residual(P, pidx, x, c0, rot[c0], meas, W, a, o, w, e, cen, *ahead[c0])
            else:
                ks.range_residual(P, pidx, x, c0, meas, W, a, o, w, e)

    all_trials = np.arange(N)
    residuals(all_trials)
    failed = np.zeros(N, bool)
    iterations = np.zeros(N, int)
    x_start = x.copy()

    def gradient(a, chain, beams, pos):
        """The trials' A^T w in the directions Qr: a laser tracker's columns at its current pose, an interferometer's
        with the beams the stage holds (``beams``: first column -> (K, m, 3), row pos[j] for trial j), the chain's
        ``chain(v, a)`` = J^T v with the Jacobian the stage holds."""
        v = np.zeros((len(a), M, 3))
        gx = np.zeros((len(a), x.shape[1]))
        for xyz, idx, meas, W, c0, o, cen, pidx in plan:
            if xyz:
                ks.xyz_gradient(*ahead[c0], a, idx, c0, v, gx)
            else:
                ks.range_gradient(w, o, W, a, beams[c0], pos(a), idx, c0, v, gx)
        gx[:, :p] = chain(v, a)
        return ((gx / sv)[:, None, :] @ Qr)[:, 0]

    stepped = np.zeros(N, bool)  # the trials whose trackers' rotations moved since the start

    def step(a, z):
        """Move the trials ``a`` by the steps z (scaled unknowns, coordinates of Qr); a laser tracker's rotation in
        ``rot`` (its Euler angles in x are read back by :func:`angles` where x's are needed)."""
        dx = z / sv
        xa = x[a]
        xa[:, :p] += dx[:, :p]
        for xyz, idx, meas, W, c0, o, cen, _ in plan:
            if not xyz:
                xa[:, c0:c0 + 4] += dx[:, c0:c0 + 4]
        x[a] = xa
        for c0, cen in centres.items():
            ks.rigid_step(rot[c0], x, dx, c0, cen, a)
        stepped[a] = True

    def angles(t):
        """x's Euler angles of every laser tracker of the trials ``t`` from their rotations now (the branch nearest
        the start): what each step read back before, read where x's angles are used (the same numbers)."""
        t = t[stepped[t]]
        for c0 in rot:
            ang = lt.euler_from_rotation(rot[c0][t])
            a0 = angles0[c0][t]
            x[t, c0 + 3:c0 + 6] = a0 + (ang - a0 + np.pi) % (2 * np.pi) - np.pi

    def iterate(chain, beams, pos, tol, predict=False, mat=mats[-1]):
        """Chord steps on the trials not failed, until each one's step is below tol (``predict``: or the next step,
        predicted from the contraction of the last two in the energy norm, as the one-tracker chord's first stage);
        ``mat``: the phase's iteration matrix (the last phase's by default)."""
        a = np.flatnonzero(~failed)
        last = np.full(N, np.inf)
        for it in range(max_iter):
            if not len(a):
                return
            g = gradient(a, chain, beams, pos)  # (na, q)
            y = (mat @ g[..., None])[..., 0]  # trial by trial
            z = (Qr @ y[..., None])[..., 0]
            step(a, z)
            residuals(a)
            iterations[a] += 1
            size = np.abs(z).max(axis=1)
            # the step's energy norm (what it changes in the fit): y^T H0 y = y^T g, as H0 y = g (H0 = Hinv^-1)
            energy = np.sqrt(np.maximum((y * g).sum(axis=1), 0.0))
            rate = energy / last[a]  # 0 before the second step (last = inf): no prediction from one step
            slow = (it >= 2) & (rate > 0.5) & (size >= tol)
            failed[a[slow]] = True
            last[a] = energy
            done = (size < tol) | (predict & (size * rate < tol) & (it >= 1))
            a = a[~done & ~slow]
        failed[a] = True  # still moving after max_iter steps

    def nominal(v, a):
        """J0^T v, trial by trial: the noise-free verification's chain Jacobian."""
        return (v.reshape(len(a), 1, -1) @ J0)[:, 0]

    # stage 1 stops near its own fixed point (where J0, not each trial's Jacobian, is orthogonal to the residual),
    # the first stage 2 near its own (b^2 / distance from it); only the last goes to xtol.  Stage 1 to 1e-2 or a
    # predicted next step below it, the first stage 2 to 1e-3 (measured on 256 trials of one, three and four stations:
    # every trial within 2.3e-7 of identify_stations' unknowns and 7e-9 um of its compensated field; 6, 13 and 11
    # steps per trial, 10, 14 and 12 with the Euler angles' steps)
    # stage 1: the shared Jacobian (the chain's and the interferometers' beams of the noise-free verification); the
    # earlier phases of a multi-phase identification run it alone, each along its own directions
    for mat in mats:
        iterate(nominal, beams0, lambda a: np.zeros(len(a), np.int64), max(xtol, 1e-2), predict=True, mat=mat)
    todo = np.flatnonzero(~failed)
    for tol in (max(xtol, 1e-3), xtol):  # stage 2, twice: the second from each trial's Jacobian where the first stopped
        todo = np.flatnonzero(~failed)
        if not len(todo):
            break
        angles(todo)
        xs = x[todo].copy()
        P_s, adjoint = chain_adjoint(model.config, model.errors, xs[:, :p], model.inputs, B=model.B)
        beams = {}  # the interferometers' beams where the stage began
        for xyz, idx, meas, W, c0, o, cen, _ in plan:
            if not xyz:
                d = P_s[:, idx] - xs[:, None, c0:c0 + 3]
                beams[c0] = d / lt.norm3(d)[..., None]  # norm3: numpy's sum over the last axis, in its order
        where = np.full(N, -1)
        where[todo] = np.arange(len(todo))
        iterate(lambda v, a, adjoint=adjoint, where=where: adjoint(v, where[a]), beams, lambda a, where=where: where[a],
                tol)
        angles(todo)
        moved = np.abs((x[todo] - xs) * sv).max(axis=1)
    if len(todo):  # what the last stage moved, against the distance from the start: its own bias is about
        dist = np.maximum(np.abs((xs - x_start[todo]) * sv).max(axis=1), 1.0)  # moved * (moved / distance)
        failed[todo[moved * moved / dist > chord_bias]] = True
    angles(all_trials)
    cost = (w * w).sum(axis=1)
    res_xyz, res_rng = _split_residuals(blocks, raw, N, M)
    return {"theta": x[:, :p], "x": x, "converged": ~failed, "iterations": iterations, "chi2": cost,
            "dof": int(w.shape[1] - rank), "failed": failed, "residual_xyz": res_xyz, "residual_range": res_rng,
            "basis": basis, "jacobian": None}




def linearise(res: MultiIdentification, lt_xyz, lt_range, repeatability: float, *, fixed: dict | None = None
              ) -> Linearisation:
    """The whitened design and residuals of :func:`identify_stations` at its solution ``res`` (the same
    measurements, repeatability and fixed inputs it was given), with the per-row maps from a displacement of a
    point to its whitened residuals.  Nothing is re-estimated."""
    model = res.model
    M = model.n_points
    lt_xyz = np.asarray(lt_xyz, float).reshape(M, 3) if lt_xyz is not None else np.full((M, 3), np.nan)
    lt_range = np.asarray(lt_range, float).reshape(M) if lt_range is not None else np.full(M, np.nan)
    fixed = dict(fixed or {})
    P0 = model.machine_points(np.zeros((1, model.n_params)), fixed)[0]
    rows, _ = _station_rows(model, res.stations, res.row_station, lt_xyz, lt_range, repeatability, P0)
    sv = _scales(model, res.stations)
    w, raw, A = _evaluate(model, fixed, rows, res.x, sv)
    Q = range_basis(np.ones(res.n_unknowns, bool), res.null_space)
    P_W = model.machine_points(res.theta[None], fixed)[0]
    R_all = np.tile(np.eye(3), (M, 1, 1))
    P_st = np.zeros((M, 3))
    res_m = np.zeros((M, 3))
    size = np.zeros(M)
    n_per = np.zeros(M, int)
    row_idx, mach, stat = [], [], []
    k = model.n_params
    for r, e in zip(rows, raw):
        st = r.station
        P = P_W[r.idx]
        if st.kind == "xyz":
            pose = res.x[k:k + 6]
            R = lt.rotation(pose[3], pose[4], pose[5])
            R_all[r.idx] = R
            P_st[r.idx] = (P - pose[:3]) @ R
            res_m[r.idx] = e @ R.T  # R e, row by row
            size[r.idx] = np.linalg.norm(e, axis=1)
            n_per[r.idx] = 3
            row_idx.append(np.repeat(r.idx, 3))
            stat.append(r.weight.reshape(-1, 3))  # W_i: rows of the whitener
            mach.append(np.einsum("nij,kj->nik", r.weight, R).reshape(-1, 3))  # W_i R^T
            k += 6
        else:
            S = res.x[k:k + 3]
            d = P - S
            u = d / np.linalg.norm(d, axis=1, keepdims=True)
            P_st[r.idx] = d
            res_m[r.idx] = e[:, None] * u
            size[r.idx] = np.abs(e)
            n_per[r.idx] = 1
            row_idx.append(r.idx)
            stat.append(r.weight[:, None] * u)
            mach.append(r.weight[:, None] * u)
            k += 4
    beam = P_st / np.linalg.norm(P_st, axis=1, keepdims=True)
    return Linearisation(design=A @ Q, whitened=w, row=np.concatenate(row_idx), machine=np.concatenate(mach),
                         station=np.concatenate(stat), rotation=R_all, beam=beam, P_W=P_W, P_station=P_st,
                         residual_machine=res_m, residual_size=size, residuals_per_row=n_per)


def identify_recording_any(rec, max_degree: int = 3, strategy=None) -> tuple[Recording, MultiIdentification]:
    """Read (a folder) or take a :class:`Recording` of any format and identify it over all its stations.

    A format 1 recording is one xyz station (the same minimum as :func:`mtbudget.identify.identify`).  The stated
    scales' expansion (``[scales]``) is taken as known, as ``compensate`` does.  strategy: an optimisation strategy
    (:class:`mtbudget.identify.Strategy`; its phases, with this identification's own tolerance: the same minimum);
    None: one phase.  Returns (recording, result).
    """
    if not isinstance(rec, Recording):
        rec = read_recording(rec, several_stations=True)
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree)
    phases = None if strategy is None else phase_masks(model, strategy.phases)
    res = identify_stations(model, rec.station_list(), rec.station_ids(), rec.lt, rec.lt_range, rec.repeatability,
                            fixed=rec.fixed_inputs(), phases=phases)
    return rec, res


def summary(rec: Recording, res: MultiIdentification) -> dict:
    """One JSON-able summary: every value with its unit and its standard uncertainty (k = 1)."""
    def shown(v, unit):
        return float(display(v, unit, shown_unit(unit)))

    stations = []
    for st in res.stations:
        vals, us = res.station_values(st.id)
        names = lt.POSE_NAMES if st.kind == "xyz" else ("S_x", "S_y", "S_z", "dead path")
        units = lt.POSE_UNITS if st.kind == "xyz" else ("mm",) * 4
        chi2, m = res.station_chi2[st.id]
        stations.append({
            "id": st.id, "kind": st.kind, "rows": int(np.count_nonzero(res.row_station == st.id)),
            "chi2": chi2, "residuals": m,
            "values": [{"name": nm, "value": float(v), "uncertainty": float(u), "unit": un, "identifiable": bool(o)}
                       for nm, v, u, un, o in zip(names, vals, us, units, res.identifiable()[res._slice(st.id)[0]])],
        })
    p = res.n_params
    ok = res.identifiable()
    return {
        "recording": rec.name, "format": rec.format_version, "points": len(rec),
        "chi2_per_dof": float(res.chi2_per_dof), "dof": res.dof, "converged": bool(res.converged),
        "rank": res.rank, "unknowns": res.n_unknowns, "condition_number": res.condition,
        "coverage": "uncertainties are standard uncertainties (k = 1) from the stated ones, not scaled by chi2/dof",
        "stations": stations,
        "parameters": [{"name": res.iso_names[j], "internal_name": res.names[j],
                        "value": shown(res.x[j], res.units[j]), "uncertainty": shown(res.u[j], res.units[j]),
                        "unit": shown_unit(res.units[j]), "identifiable": bool(ok[j])} for j in range(p)],
        "gauge": res.gauge,
        "not_identifiable": [[{"parameter": nm, "weight": w} for nm, w in combo] for combo in res.combinations()],
    }


def summary_text(rec: Recording, res: MultiIdentification) -> list[str]:
    """The text ``mtbudget identify`` prints for a recording of several stations."""
    kinds = ", ".join(f"{st.id} {st.kind}" for st in res.stations)
    out = [f"identified {rec.name!r} over {len(res.stations)} station(s) ({kinds}): {len(rec)} rows, "
           f"{res.n_unknowns} unknowns, rank {res.rank}, {res.dof} degrees of freedom",
           f"  chi-square per dof        {res.chi2_per_dof:.3f}  (1 = residuals match the stated uncertainties)",
           f"  condition number          {res.condition:.3g}  (column-equilibrated whitened Jacobian, identifiable "
           "directions)",
           "  stations (standard uncertainties, k = 1):"]
    ok = res.identifiable()
    datum = False
    for st in res.stations:
        vals, us = res.station_values(st.id)
        held = ["" if o else "*" for o in ok[res._slice(st.id)[0]]]
        datum |= "*" in held
        chi2, m = res.station_chi2[st.id]
        if st.kind == "xyz":
            pos = ", ".join(f"{v:.4f} mm{h} (u {u * 1e3:.2f} µm)" for v, u, h in zip(vals[:3], us[:3], held[:3]))
            ang = ", ".join(f"{v:.6f} rad{h} (u {u * 1e6:.2f} µrad)" for v, u, h in zip(vals[3:], us[3:], held[3:]))
            out.append(f"    station {st.id} (xyz)   D, L, H = {pos}; a, b, d = {ang};  chi2 {chi2:.1f} over {m}")
        else:
            pos = ", ".join(f"{v:.4f} mm{h} (u {u * 1e3:.2f} µm)" for v, u, h in zip(vals[:3], us[:3], held[:3]))
            out.append(f"    station {st.id} (range) S = {pos}; dead path {vals[3]:.4f} mm{held[3]} (u {us[3] * 1e3:.2f} "
                       f"µm);  chi2 {chi2:.1f} over {m}")
    if datum:
        out.append("    * takes part in a combination the data cannot see (below): where the station stands along it "
                   "is fixed by the datum, not measured, and its u is relative to that datum")
    out.append("  datum (the six rigid freedoms of the whole):")
    for g in res.gauge:
        out.append(f"    {g['freedom']}: fixed by {g['fixed_by']}")
    combos = res.combinations()
    if combos:
        out.append("  not identifiable from these stations and this plan (held at their initial value):")
        for combo in combos:
            out.append("    " + " ".join(f"{w:+.2f}*{nm}" for nm, w in combo))
    return out


def _split_residuals(blocks, raw, N: int, M: int):
    """Each station's residuals into the rows it measured: (N, M, 3) of the xyz stations and (N, M) of the range
    stations, NaN elsewhere."""
    res_xyz = np.full((N, M, 3), np.nan)
    res_rng = np.full((N, M), np.nan)
    for (st, idx, _, _), e in zip(blocks, raw):
        if st.kind == "xyz":
            res_xyz[:, idx] = e
        else:
            res_rng[:, idx] = e
    return res_xyz, res_rng
