"""Compiled kernels of the several-station identification's chord iterations (numba; issue 31).

:func:`mtbudget.multistation._batch_chord` iterates every trial with one shared matrix; what is left per
iteration is, per station, the whitened residual of its rows (a laser tracker's R^T (P - T) against its
measured points, an interferometer's |P - S| + o against its ranges), the trial's gradient A^T w: the
machine-frame vectors the chain's ``J^T v`` takes (:func:`mtbudget.kernels.chain_vjp`) plus the columns of the
station's own unknowns (a laser tracker's pose as a small rigid motion of the station), and the step of a laser
tracker's pose (:func:`rigid_step`).  In numpy these are a dozen passes over (trials, rows, 3, 3) arrays each;
here one pass per trial and row.

Every number a trial gets depends on that trial's inputs only (no reduction across trials): results do not
depend on how trials are grouped.  The references they are tested against (``tests/test_scale.py``):
``multistation.identify_stations_batch``'s ``evaluate`` for the residuals, the exact Jacobian for the chain's and an
interferometer's gradient, central differences along :func:`rigid_step` for a tracker's pose, scipy's rotation
of a rotation vector for :func:`rigid_step`.  Only plain float64 and int64 arrays cross this boundary.
"""

from __future__ import annotations

import math

import numpy as np

from .kernels import compiled, rodrigues  # one njit rule for every kernel module


@compiled
def xyz_residual(P, pidx, x, c0, R, meas, W, t, off, w, e, cen, q, s):  # pragma: no cover
    """A laser tracker's rows for trials ``t``: e = meas - R^T (P - T) (m, 3) into ``e`` and W e into the whitened
    residuals ``w`` from column ``off``, and what the trial's next gradient takes of them (:func:`xyz_gradient`),
    while they are at hand: b = W^T w per row, q = R b into ``q`` (N, m, 3) and, the pose as a small rigid motion
    of the station about ``cen`` (translation t, then rotation w: the chord's coordinates), the pose's six gradient
    columns into ``s`` (N, 6): -R b summed over the rows for the translation and (R b) x (P - cen) for the rotation
    (the prediction R^T (P - T) moves by R^T (-t + (P - cen) x w)), each from zero in the rows' order.  P (k, Mu, 3)
    the trials' machine points, row j for trial t[j]; pidx (m,) the station's rows among P's points; everything else
    indexed by the trial itself, row t[j]: x (N, n) the unknowns, the pose's translation at columns c0..c0+2; R (N,
    3, 3) the pose's rotation; meas (N, m, 3) and W (N, m, 3, 3) the station's measurements and whiteners; e (N, m,
    3), w (N, n_res), q and s written."""
    k, m = P.shape[0], pidx.shape[0]
    for j in range(k):
        i = t[j]
        T0, T1, T2 = x[i, c0], x[i, c0 + 1], x[i, c0 + 2]
        R00, R01, R02 = R[i, 0, 0], R[i, 0, 1], R[i, 0, 2]
        R10, R11, R12 = R[i, 1, 0], R[i, 1, 1], R[i, 1, 2]
        R20, R21, R22 = R[i, 2, 0], R[i, 2, 1], R[i, 2, 2]
        s0 = s1 = s2 = s3 = s4 = s5 = 0.0
        for r in range(m):
            p = pidx[r]
            P0, P1, P2 = P[j, p, 0], P[j, p, 1], P[j, p, 2]
            d0, d1, d2 = P0 - T0, P1 - T1, P2 - T2
            e0 = meas[i, r, 0] - (R00 * d0 + R10 * d1 + R20 * d2)
            e1 = meas[i, r, 1] - (R01 * d0 + R11 * d1 + R21 * d2)
            e2 = meas[i, r, 2] - (R02 * d0 + R12 * d1 + R22 * d2)
            e[i, r, 0], e[i, r, 1], e[i, r, 2] = e0, e1, e2
            w0 = W[i, r, 0, 0] * e0 + W[i, r, 0, 1] * e1 + W[i, r, 0, 2] * e2
            w1 = W[i, r, 1, 0] * e0 + W[i, r, 1, 1] * e1 + W[i, r, 1, 2] * e2
            w2 = W[i, r, 2, 0] * e0 + W[i, r, 2, 1] * e1 + W[i, r, 2, 2] * e2
            w[i, off + 3 * r], w[i, off + 3 * r + 1], w[i, off + 3 * r + 2] = w0, w1, w2
            b0 = W[i, r, 0, 0] * w0 + W[i, r, 1, 0] * w1 + W[i, r, 2, 0] * w2
            b1 = W[i, r, 0, 1] * w0 + W[i, r, 1, 1] * w1 + W[i, r, 2, 1] * w2
            b2 = W[i, r, 0, 2] * w0 + W[i, r, 1, 2] * w1 + W[i, r, 2, 2] * w2
            q0 = R00 * b0 + R01 * b1 + R02 * b2
            q1 = R10 * b0 + R11 * b1 + R12 * b2
            q2 = R20 * b0 + R21 * b1 + R22 * b2
            q[i, r, 0], q[i, r, 1], q[i, r, 2] = q0, q1, q2
            f0, f1, f2 = P0 - cen[0], P1 - cen[1], P2 - cen[2]
            s0 -= q0
            s1 -= q1
            s2 -= q2
            s3 += q1 * f2 - q2 * f1
            s4 += q2 * f0 - q0 * f2
            s5 += q0 * f1 - q1 * f0
        s[i, 0], s[i, 1], s[i, 2], s[i, 3], s[i, 4], s[i, 5] = s0, s1, s2, s3, s4, s5


@compiled
def range_residual(P, pidx, x, c0, meas, W, t, off, w, e):  # pragma: no cover
    """An interferometer's rows for trials ``t``: e = meas - (|P - S| + o) into ``e`` and W e into ``w`` from column
    ``off``; S at columns c0..c0+2 of x, o at c0+3; P (k, Mu, 3) row j, pidx as :func:`xyz_residual`; x, meas and
    W (N, m), e (N, m) and w row t[j]."""
    k, m = P.shape[0], pidx.shape[0]
    for j in range(k):
        i = t[j]
        S0, S1, S2, o = x[i, c0], x[i, c0 + 1], x[i, c0 + 2], x[i, c0 + 3]
        for r in range(m):
            p = pidx[r]
            d0, d1, d2 = P[j, p, 0] - S0, P[j, p, 1] - S1, P[j, p, 2] - S2
            er = meas[i, r] - (math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) + o)
            e[i, r] = er
            w[i, off + r] = W[i, r] * er


@compiled
def xyz_gradient(q, s, t, idx, c0, v, g):  # pragma: no cover
    """A laser tracker's part of A^T w for trials ``t``, from what :func:`xyz_residual` left at their current unknowns
    (row t[j] of q (N, m, 3) and s (N, 6)): R b added to the machine-frame vectors ``v`` (k, M, 3) at the station's
    rows ``idx`` (the chain's J^T v takes them), the pose's six columns c0..c0+5 of ``g`` (k, n) set to s (they start
    at zero: the sums over the rows are s); v and g row j."""
    k, m = v.shape[0], idx.shape[0]
    for j in range(k):
        i = t[j]
        for r in range(m):
            p = idx[r]
            v[j, p, 0] += q[i, r, 0]
            v[j, p, 1] += q[i, r, 1]
            v[j, p, 2] += q[i, r, 2]
        for c in range(6):
            g[j, c0 + c] = s[i, c]


@compiled
def rigid_step(R, x, z, c0, cen, t):  # pragma: no cover
    """A laser tracker's pose moved by the chord's step, for trials ``t``: z (k, n) the steps, row j for trial t[j],
    its columns c0..c0+2 the translation t (mm) and c0+3..c0+5 the rotation vector w (rad) about ``cen``; R (N, 3, 3)
    and x (N, n), row t[j], in place: R <- Rot(w) R and T = x[:, c0:c0+3] <- Rot(w) (T - cen) + cen + t, Rot(w) the
    exact rotation (Rodrigues, its series below |w| = 1e-6 rad)."""
    k = t.shape[0]
    Rot = np.empty((3, 3))
    Rn = np.empty((3, 3))
    for j in range(k):
        i = t[j]
        rodrigues(z[j, c0 + 3], z[j, c0 + 4], z[j, c0 + 5], Rot)  # the one-tracker chord's rotation of its step
        for r in range(3):
            for c in range(3):
                Rn[r, c] = Rot[r, 0] * R[i, 0, c] + Rot[r, 1] * R[i, 1, c] + Rot[r, 2] * R[i, 2, c]
        for r in range(3):
            for c in range(3):
                R[i, r, c] = Rn[r, c]
        e0, e1, e2 = x[i, c0] - cen[0], x[i, c0 + 1] - cen[1], x[i, c0 + 2] - cen[2]
        for r in range(3):
            x[i, c0 + r] = Rot[r, 0] * e0 + Rot[r, 1] * e1 + Rot[r, 2] * e2 + cen[r] + z[j, c0 + r]


@compiled
def range_gradient(w, off, W, t, U, pos, idx, c0, v, g):  # pragma: no cover
    """An interferometer's part of A^T w for trials ``t``: c = W w per row; u c added to ``v`` at its rows, -u c
    summed into S's columns c0..c0+2 of ``g`` and c into o's (c0+3), each column over the rows in their order from
    its value on entry; v and g row j for trial t[j], w (N, n_res) and W (N, m) row t[j].  U (K, m, 3): the unit
    beam vectors where the stage began, row pos[j] for trial t[j]."""
    k, m = v.shape[0], idx.shape[0]
    for j in range(k):
        i, s = t[j], pos[j]
        s0, s1, s2, s3 = g[j, c0], g[j, c0 + 1], g[j, c0 + 2], g[j, c0 + 3]
        for r in range(m):
            c = W[i, r] * w[i, off + r]
            p = idx[r]
            u0, u1, u2 = U[s, r, 0] * c, U[s, r, 1] * c, U[s, r, 2] * c
            v[j, p, 0] += u0
            v[j, p, 1] += u1
            v[j, p, 2] += u2
            s0 -= u0
            s1 -= u1
            s2 -= u2
            s3 += c
        g[j, c0], g[j, c0 + 1], g[j, c0 + 2], g[j, c0 + 3] = s0, s1, s2, s3


@compiled
def registered_distances(P0, meas, out):  # pragma: no cover
    """For each trial j, the distances |meas_j - R_j^T (P0 - T_j)| (m,) after the unweighted closed-form rigid fit
    (Kabsch) of its station-frame points meas (k, m, 3) onto the machine points P0 (m, 3): what
    :func:`mtbudget.tracker.register` then :func:`mtbudget.tracker.to_tracker` give, one trial at a time, without
    numpy's per-call cost (the Eq. 27 error before compensation of a laser tracker's rows, every trial)."""
    k, m = meas.shape[0], meas.shape[1]
    cw = np.zeros(3)
    for r in range(m):
        for c in range(3):
            cw[c] += P0[r, c]
    cw /= m
    for j in range(k):
        cl = np.zeros(3)
        for r in range(m):
            for c in range(3):
                cl[c] += meas[j, r, c]
        cl /= m
        H = np.zeros((3, 3))  # sum_r a_r b_r^T, a = meas - cl, b = P0 - cw
        for r in range(m):
            for a in range(3):
                for b in range(3):
                    H[a, b] += (meas[j, r, a] - cl[a]) * (P0[r, b] - cw[b])
        U, _, Vt = np.linalg.svd(H)
        d = 1.0 if np.linalg.det(U @ Vt) >= 0 else -1.0
        R = np.zeros((3, 3))  # V diag(1, 1, d) U^T: tracker-frame vectors to the machine frame
        for a in range(3):
            for b in range(3):
                R[a, b] = Vt[0, a] * U[b, 0] + Vt[1, a] * U[b, 1] + d * Vt[2, a] * U[b, 2]
        T = cw - R @ cl
        for r in range(m):
            s = 0.0
            for c in range(3):  # R^T (P0 - T): component c
                q = R[0, c] * (P0[r, 0] - T[0]) + R[1, c] * (P0[r, 1] - T[1]) + R[2, c] * (P0[r, 2] - T[2])
                s += (meas[j, r, c] - q) ** 2
            out[j, r] = math.sqrt(s)


@compiled
def tracker_whiteners(P, angular, distance, distance_per_length, rep2, out):  # pragma: no cover
    """Each laser-tracker point's whitener (the inverse of C's Cholesky factor) into ``out`` (N, m, 3, 3), P (N, m, 3)
    the measured points: C the covariance of :func:`mtbudget.tracker.covariance` (Eq. 23, from the coordinates) plus
    ``rep2`` (the repeatability squared) times the identity, then :func:`mtbudget.identify.whitener`'s closed form;
    the same operations in the same order as those numpy passes, point by point (``hypot`` is the C library's, as
    numpy's).  Returns False where a whitener is not finite (C not positive definite): the caller then takes numpy's
    path, which says so."""
    N, m = P.shape[0], P.shape[1]
    good = True
    for n in range(N):
        for r in range(m):
            x, y, z = P[n, r, 0], P[n, r, 1], P[n, r, 2]
            rho = math.hypot(x, y)
            rr = math.hypot(rho, z)
            ca = x / rho if rho > 0 else 1.0
            sa = y / rho if rho > 0 else 0.0
            ce = rho / rr if rr > 0 else 1.0
            se = z / rr if rr > 0 else 0.0
            ur = distance + distance_per_length * rr
            A = ur * ur
            arho, ar = angular * rho, angular * rr
            Bv = arho * arho
            Cv = ar * ar
            rx, ry = ce * ca, ce * sa
            ex, ey = se * ca, se * sa
            c00 = (A * rx * rx + Bv * sa * sa + Cv * ex * ex) + rep2
            c11 = (A * ry * ry + Bv * ca * ca + Cv * ey * ey) + rep2
            c22 = (A * se * se + Cv * ce * ce) + rep2
            c10 = (A * rx * ry - Bv * sa * ca + Cv * ex * ey) + 0.0  # the identity's zeros, added as numpy adds them
            c20 = (A * rx * se - Cv * ex * ce) + 0.0
            c21 = (A * ry * se - Cv * ey * ce) + 0.0
            l00 = math.sqrt(c00) if c00 >= 0 else math.nan
            l10, l20 = c10 / l00, c20 / l00
            d11 = c11 - l10 * l10
            l11 = math.sqrt(d11) if d11 >= 0 else math.nan
            l21 = (c21 - l20 * l10) / l11
            d22 = c22 - l20 * l20 - l21 * l21
            l22 = math.sqrt(d22) if d22 >= 0 else math.nan
            i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
            a10 = -l10 * i00 * i11
            a21 = -l21 * i11 * i22
            a20 = (l10 * l21 - l20 * l11) * i00 * i11 * i22
            W = out[n, r]
            W[0, 0], W[0, 1], W[0, 2] = i00, 0.0, 0.0
            W[1, 0], W[1, 1], W[1, 2] = a10, i11, 0.0
            W[2, 0], W[2, 1], W[2, 2] = a20, a21, i22
            if not (math.isfinite(i00) and math.isfinite(i11) and math.isfinite(i22) and math.isfinite(a10)
                    and math.isfinite(a21) and math.isfinite(a20)):
                good = False
    return good
