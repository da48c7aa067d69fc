"""Compiled kernels of the verification Monte Carlo's hot path (numba).

The engine spends its time in two loops over (trials, points) that numpy can only run as dozens of
separate passes over (N, M) arrays: the small-angle chain (:func:`chain_points`) and the chord
iteration's weighted residual and gradient (:func:`chord_residual`).  Each is written here once as one
pass per trial and point, compiled by numba (``cache=True``: compiled once per machine, then loaded).
Every number a trial gets depends on that trial's inputs only (no reduction across trials), so the
results do not depend on how trials are grouped.

The numpy formulations stay beside them as the references they are tested against
(``machine._evaluate`` / ``machine.chain_reference`` and ``identify._chord_residual_numpy``): the
same arithmetic up to the order of a few sums (round-off, ~1e-16 relative).  Only plain float64 and
int64 arrays cross this boundary; no units, no Python objects.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def _compiled(f):
    """numba's ``njit`` (no Python objects, no division checks: IEEE results, as numpy's), cached on disk; where
    numba finds no writable cache location (a read-only installation and home), compiled in memory instead (once
    per process).  No ``fastmath``: sums keep their order, so the numbers are the same on every CPU."""
    try:
        return njit(cache=True, nogil=True, error_model="numpy")(f)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return njit(cache=False, nogil=True, error_model="numpy")(f)


@_compiled
def _rotate(k, c, s, v0, v1, v2):  # pragma: no cover - compiled
    """(v0, v1, v2) turned right-handed about the axis e_k by the angle whose cosine is c and sine s."""
    if k == 0:
        return v0, c * v1 - s * v2, s * v1 + c * v2
    if k == 1:
        return c * v0 + s * v2, v1, c * v2 - s * v0
    return c * v0 - s * v1, s * v0 + c * v1, v2


@_compiled
def _rot2(f0, f1, f2, u0, u1, u2, sgn):  # pragma: no cover - compiled
    """A rotary axis' error rotation to second order, ``u + sgn f x u + (f (f . u) - |f|^2 u) / 2`` (sgn +1: the
    rotation by f; -1: by -f, its inverse to second order; the transposes are the same with -sgn)."""
    d = f0 * u0 + f1 * u1 + f2 * u2
    q = f0 * f0 + f1 * f1 + f2 * f2
    return (u0 + sgn * (f1 * u2 - f2 * u1) + 0.5 * (f0 * d - q * u0),
            u1 + sgn * (f2 * u0 - f0 * u2) + 0.5 * (f1 * d - q * u1),
            u2 + sgn * (f0 * u1 - f1 * u0) + 0.5 * (f2 * d - q * u2))


@_compiled
def _forward(n, tool_axes, wp_axes, side, px, py, pz, toolT, coef, L, sq, rdir, pivot, rcos, rsin, comp, t, v, vin,
             wout):  # pragma: no cover
    """Trial n of the small-angle chain: its points into ``v`` (3, M), each axis' component errors into
    ``comp`` (A, 6, M) and translations into ``t`` (A, 3, M); what enters each tool-side axis' error motion into
    ``vin`` (A, 3, M) and what leaves each workpiece-side axis' error motion into ``wout`` (A, 3, M) (for the
    adjoint).  Axes 0, 1, 2 are X, Y, Z; axes 3 .. A-1 the rotary axes (row a - 3 of rdir, pivot, rcos, rsin).

    Every step is a loop over the points on contiguous (M,) rows (which the compiler vectorises)."""
    K = coef.shape[3]
    M = v.shape[1]
    A = coef.shape[1]
    pos = (px[n if px.shape[0] > 1 else 0], py[n if py.shape[0] > 1 else 0], pz[n if pz.shape[0] > 1 else 0])
    for a in range(A):
        for c in range(6):
            row = comp[a, c]
            c0 = coef[n, a, c, 0]
            for m in range(M):
                row[m] = c0 * L[a, 0, m]
            for k in range(1, K):
                ck = coef[n, a, c, k]
                for m in range(M):
                    row[m] += ck * L[a, k, m]
    # commanded displacement with squareness (Eq. 7-9, 16-17), then the carriage's own errors
    sxy, sxz, syz = sq[n, 0], sq[n, 1], sq[n, 2]
    for m in range(M):
        p0, p1, p2 = pos[0][m], pos[1][m], pos[2][m]
        t[0, 0, m] = side[0] * p0 + comp[0, 0, m]
        t[0, 1, m] = comp[0, 1, m]
        t[0, 2, m] = comp[0, 2, m]
        t[1, 0, m] = (p1 * sxy) * -side[1] + comp[1, 0, m]
        t[1, 1, m] = side[1] * p1 + comp[1, 1, m]
        t[1, 2, m] = comp[1, 2, m]
        t[2, 0, m] = (p2 * sxz) * -side[2] + comp[2, 0, m]
        t[2, 1, m] = (p2 * syz) * -side[2] + comp[2, 1, m]
        t[2, 2, m] = side[2] * p2 + comp[2, 2, m]
    # a rotary axis: G(v) = p + delta + R2(eps) R(theta) (v - p), R2 the rotation to second order (_rot2): its "translation" is p + delta
    for a in range(3, A):
        r = a - 3
        for i in range(3):
            for m in range(M):
                t[a, i, m] = pivot[r, i] + comp[a, i, m]
    for i in range(3):
        for m in range(M):
            v[i, m] = toolT[i, m]
    # tool side: A(v) = v + eps x v + t, innermost axis first (a rotary axis turns v about its pivot first)
    for a in tool_axes:
        e0, e1, e2, ta, va = comp[a, 3], comp[a, 4], comp[a, 5], t[a], vin[a]
        if a >= 3:
            r = a - 3
            k = rdir[r]
            cr, sr = rcos[r, n if rcos.shape[1] > 1 else 0], rsin[r, n if rsin.shape[1] > 1 else 0]
            q0, q1, q2 = pivot[r, 0], pivot[r, 1], pivot[r, 2]
            for m in range(M):
                v0, v1, v2 = _rotate(k, cr[m], sr[m], v[0, m] - q0, v[1, m] - q1, v[2, m] - q2)
                va[0, m], va[1, m], va[2, m] = v0, v1, v2
                w0, w1, w2 = _rot2(e0[m], e1[m], e2[m], v0, v1, v2, 1.0)
                v[0, m], v[1, m], v[2, m] = w0 + ta[0, m], w1 + ta[1, m], w2 + ta[2, m]
            continue
        for m in range(M):
            v0, v1, v2 = v[0, m], v[1, m], v[2, m]
            va[0, m], va[1, m], va[2, m] = v0, v1, v2
            v[0, m] = v0 + (e1[m] * v2 - e2[m] * v1) + ta[0, m]
            v[1, m] = v1 + (e2[m] * v0 - e0[m] * v2) + ta[1, m]
            v[2, m] = v2 + (e0[m] * v1 - e1[m] * v0) + ta[2, m]
    # workpiece side: B^-1(w) = R^-1 (w - t), R^-1 u = (u - eps x u + eps (eps . u)) / (1 + |eps|^2)
    # (a rotary axis then turns back about its pivot: p + R(theta)^T u)
    for a in wp_axes:
        e0, e1, e2, ta, wa = comp[a, 3], comp[a, 4], comp[a, 5], t[a], wout[a]
        if a >= 3:  # the error rotation's inverse to second order; what enters it is kept (for the adjoint)
            r = a - 3
            k = rdir[r]
            cr, sr = rcos[r, n if rcos.shape[1] > 1 else 0], rsin[r, n if rsin.shape[1] > 1 else 0]
            q0, q1, q2 = pivot[r, 0], pivot[r, 1], pivot[r, 2]
            for m in range(M):
                u0, u1, u2 = v[0, m] - ta[0, m], v[1, m] - ta[1, m], v[2, m] - ta[2, m]
                wa[0, m], wa[1, m], wa[2, m] = u0, u1, u2
                w0, w1, w2 = _rot2(e0[m], e1[m], e2[m], u0, u1, u2, -1.0)
                w0, w1, w2 = _rotate(k, cr[m], -sr[m], w0, w1, w2)
                v[0, m], v[1, m], v[2, m] = w0 + q0, w1 + q1, w2 + q2
            continue
        for m in range(M):
            u0, u1, u2 = v[0, m] - ta[0, m], v[1, m] - ta[1, m], v[2, m] - ta[2, m]
            f0, f1, f2 = e0[m], e1[m], e2[m]
            dot = f0 * u0 + f1 * u1 + f2 * u2
            den = 1.0 + (f0 * f0 + f1 * f1 + f2 * f2)
            v[0, m] = (u0 - (f1 * u2 - f2 * u1) + f0 * dot) / den
            v[1, m] = (u1 - (f2 * u0 - f0 * u2) + f1 * dot) / den
            v[2, m] = (u2 - (f0 * u1 - f1 * u0) + f2 * dot) / den
            wa[0, m], wa[1, m], wa[2, m] = v[0, m], v[1, m], v[2, m]


@_compiled
def chain_points(tool_axes, wp_axes, side, px, py, pz, tool, coef, L, sq, rdir, pivot, rcos, rsin, out, eps, vin,
                 wout):  # pragma: no cover
    """The small-angle chain (machine.py's module docstring) for N trials and M points, into ``out`` (N, M, 3).

    tool_axes: axis indices (0 x, 1 y, 2 z, 3.. the rotary axes) in the order the tool side is applied
    (innermost first); wp_axes: the workpiece side in order (the axis on the bed first); side: (A,) +1 tool
    side, -1 workpiece side; px, py, pz: effective positions of each linear axis, (1, M) or (N, M); tool:
    (M, 3); coef: (N, A, 6, K) coefficients of each axis' six component errors (dx, dy, dz, ex, ey, ez), zero
    where not modelled; L: (A, K, M) the basis values (Legendre of a linear axis' position, 1 / cos / sin of a
    rotary axis' angle) at the points; sq: (N, 3) the squareness errors sxy, sxz, syz (zero where not
    modelled); rdir: (R,) the direction component of each rotary axis (0 A, 1 B, 2 C), pivot: (R, 3) a point
    of its line; rcos, rsin: (R, 1 or N, M) cosine and sine of the angle each turns by (its effective angle
    times the sense of its direction).

    eps, vin, wout: (N, A, 3, M) to keep for :func:`chain_vjp` each trial's angular errors, what enters each
    tool-side axis and what leaves each workpiece-side axis; (1, A, 3, M) to keep nothing (scratch).
    """
    N = coef.shape[0]
    A = coef.shape[1]
    M = tool.shape[0]
    keep = eps.shape[0] == N
    comp, t, v = np.empty((A, 6, M)), np.empty((A, 3, M)), np.empty((3, M))
    toolT = np.ascontiguousarray(tool.T)
    for n in range(N):
        k = n if keep else 0
        _forward(n, tool_axes, wp_axes, side, px, py, pz, toolT, coef, L, sq, rdir, pivot, rcos, rsin, comp, t, v,
                 vin[k], wout[k])
        eps[k] = comp[:, 3:]
        for m in range(M):
            out[n, m, 0] = v[0, m]
            out[n, m, 1] = v[1, m]
            out[n, m, 2] = v[2, m]
    return out


@_compiled
def chain_vjp(tool_order, wp_axes, side, px, py, pz, rdir, rcos, rsin, eps, vin, wout, rows, vec, params, basis,
              out):  # pragma: no cover - compiled
    """J^T v of the small-angle chain (``machine._Adjoint``), trial by trial, into ``out`` (n, p).

    tool_order: the tool-side axes, the one on the bed first (the order the back-propagation visits
    them); wp_axes, side, px, py, pz, rdir, rcos, rsin as for :func:`chain_points`; eps, vin, wout: what
    :func:`chain_points` kept; rows: (n,) the trials (their rows in those arrays); vec: (n, M, 3)
    machine-frame vectors at the points; params: (p, 3) each parameter's axis, kind (0 translation,
    1 rotation, 2 squareness) and component; basis: (p, M) its basis values at the points.
    """
    M = vec.shape[1]
    A = eps.shape[1]
    g = np.zeros((A, 3, M))  # G_a^T v of each axis
    gd = np.zeros((A, 3, M))  # a workpiece-side rotary axis: the cotangent at its error rotation's output
    h = np.zeros((A, 3, 3, M))  # (axis, kind, component): what each parameter's basis values are summed against
    u = np.empty((3, M))
    pos = (px, py, pz)
    for q in range(rows.shape[0]):
        n = rows[q]
        for m in range(M):
            u[0, m], u[1, m], u[2, m] = vec[q, m, 0], vec[q, m, 1], vec[q, m, 2]
        # G_a^T v = Rinv_a^T ... Rinv_wm^T v, Rinv^T u = (u + eps x u + eps (eps . u)) / (1 + |eps|^2)
        # (a rotary axis' turn back, R(theta)^T, transposed: R(theta), first)
        for j in range(wp_axes.shape[0] - 1, -1, -1):
            a = wp_axes[j]
            e0, e1, e2, ga = eps[n, a, 0], eps[n, a, 1], eps[n, a, 2], g[a]
            if a >= 3:
                r = a - 3
                k = rdir[r]
                cr, sr = rcos[r, n if rcos.shape[1] > 1 else 0], rsin[r, n if rsin.shape[1] > 1 else 0]
                for m in range(M):
                    u0, u1, u2 = _rotate(k, cr[m], sr[m], u[0, m], u[1, m], u[2, m])
                    gd[a, 0, m], gd[a, 1, m], gd[a, 2, m] = u0, u1, u2
                    u0, u1, u2 = _rot2(e0[m], e1[m], e2[m], u0, u1, u2, 1.0)  # R2(-eps)^T
                    u[0, m], u[1, m], u[2, m] = u0, u1, u2
                    ga[0, m], ga[1, m], ga[2, m] = u0, u1, u2
                continue
            for m in range(M):
                f0, f1, f2 = e0[m], e1[m], e2[m]
                u0, u1, u2 = u[0, m], u[1, m], u[2, m]
                dot = f0 * u0 + f1 * u1 + f2 * u2
                den = 1.0 / (1.0 + (f0 * f0 + f1 * f1 + f2 * f2))
                u[0, m] = (u0 + (f1 * u2 - f2 * u1) + f0 * dot) * den
                u[1, m] = (u1 + (f2 * u0 - f0 * u2) + f1 * dot) * den
                u[2, m] = (u2 + (f0 * u1 - f1 * u0) + f2 * dot) * den
                ga[0, m], ga[1, m], ga[2, m] = u[0, m], u[1, m], u[2, m]
        # G_a^T v = R_a-1^T ... R_1^T MW^T v on the tool side, R^T u = u - eps x u (a rotary axis then R(theta)^T)
        for j in range(tool_order.shape[0]):
            a = tool_order[j]
            e0, e1, e2, ga = eps[n, a, 0], eps[n, a, 1], eps[n, a, 2], g[a]
            last = j == tool_order.shape[0] - 1
            for m in range(M):
                u0, u1, u2 = u[0, m], u[1, m], u[2, m]
                ga[0, m], ga[1, m], ga[2, m] = u0, u1, u2
                if not last:
                    f0, f1, f2 = e0[m], e1[m], e2[m]
                    if a >= 3:  # R2(eps)^T
                        u[0, m], u[1, m], u[2, m] = _rot2(f0, f1, f2, u0, u1, u2, -1.0)
                    else:
                        u[0, m] = u0 - (f1 * u2 - f2 * u1)
                        u[1, m] = u1 - (f2 * u0 - f0 * u2)
                        u[2, m] = u2 - (f0 * u1 - f1 * u0)
            if a >= 3 and not last:
                r = a - 3
                k = rdir[r]
                cr, sr = rcos[r, n if rcos.shape[1] > 1 else 0], rsin[r, n if rsin.shape[1] > 1 else 0]
                for m in range(M):
                    u[0, m], u[1, m], u[2, m] = _rotate(k, cr[m], -sr[m], u[0, m], u[1, m], u[2, m])
        for a in range(A):
            ga, s = g[a], side[a]
            w = vin[n, a] if s > 0 else wout[n, a]
            if a >= 3:  # a rotary axis' second-order error rotation: translation as above, rotation with its terms
                e0, e1, e2 = eps[n, a, 0], eps[n, a, 1], eps[n, a, 2]
                gg = ga if s > 0 else gd[a]
                for m in range(M):
                    g0, g1, g2 = ga[0, m], ga[1, m], ga[2, m]
                    h[a, 0, 0, m], h[a, 0, 1, m], h[a, 0, 2, m] = s * g0, s * g1, s * g2
                    c0, c1, c2 = gg[0, m], gg[1, m], gg[2, m]
                    w0, w1, w2 = w[0, m], w[1, m], w[2, m]
                    f0, f1, f2 = e0[m], e1[m], e2[m]
                    fg, fw, wg = f0 * c0 + f1 * c1 + f2 * c2, f0 * w0 + f1 * w1 + f2 * w2, w0 * c0 + w1 * c1 + w2 * c2
                    # d/deps of R2(+-eps) w, transposed, applied to g: +-(w x g) ... (tool: w x g; workpiece: g x w)
                    x0, x1, x2 = s * (w1 * c2 - w2 * c1), s * (w2 * c0 - w0 * c2), s * (w0 * c1 - w1 * c0)
                    h[a, 1, 0, m] = x0 + 0.5 * (fg * w0 + fw * c0 - 2.0 * wg * f0)
                    h[a, 1, 1, m] = x1 + 0.5 * (fg * w1 + fw * c1 - 2.0 * wg * f1)
                    h[a, 1, 2, m] = x2 + 0.5 * (fg * w2 + fw * c2 - 2.0 * wg * f2)
                continue
            for m in range(M):
                g0, g1, g2 = ga[0, m], ga[1, m], ga[2, m]
                # translation: dP/dt_a = +G (tool side) or -G (workpiece side)
                h[a, 0, 0, m], h[a, 0, 1, m], h[a, 0, 2, m] = s * g0, s * g1, s * g2
                w0, w1, w2 = w[0, m], w[1, m], w[2, m]
                if s > 0:  # rotation, tool side: d/deps of (v + eps x v) is -G [v_in]x; transposed: v_in x g
                    h[a, 1, 0, m] = w1 * g2 - w2 * g1
                    h[a, 1, 1, m] = w2 * g0 - w0 * g2
                    h[a, 1, 2, m] = w0 * g1 - w1 * g0
                else:  # workpiece side: + G [w_out]x; transposed: g x w_out
                    h[a, 1, 0, m] = g1 * w2 - g2 * w1
                    h[a, 1, 1, m] = g2 * w0 - g0 * w2
                    h[a, 1, 2, m] = g0 * w1 - g1 * w0
            if a < 3:
                # squareness: -position times the translation's column G
                pa = pos[a][n if pos[a].shape[0] > 1 else 0]
                for m in range(M):
                    pm = -pa[m]
                    h[a, 2, 0, m], h[a, 2, 1, m], h[a, 2, 2, m] = ga[0, m] * pm, ga[1, m] * pm, ga[2, m] * pm
        for j in range(params.shape[0]):
            hr, br = h[params[j, 0], params[j, 1], params[j, 2]], basis[j]
            acc = 0.0
            for m in range(M):
                acc += hr[m] * br[m]
            out[q, j] = acc
    return out


@_compiled
def chord_residual(P, meas, WL, idx, R, T, c0, v, G, cost):  # pragma: no cover - compiled
    """A chord iteration's weighted residual and rigid gradient, trial by trial (``identify._chord``).

    For trial n (the row ``idx[n]`` of ``meas`` (N, M, 3) and of the component-major information matrices
    ``WL`` (3, 3, N, M)), at machine points ``P[n]`` (M, 3) and pose ``R[n]`` (3, 3), ``T[n]`` (3,):
    the residual r = x - R^T (P - T) (tracker frame), u = C^-1 r, the machine-frame weighted residual
    ``v[n]`` = R u (M, 3), the cost ``cost[n]`` = sum r.u, and into ``G[n, :6]`` the sum of v over the points
    and the antisymmetric part of sum (P - c0) v^T (the torque about c0), unscaled.
    """
    n_rows, M = P.shape[0], P.shape[1]
    r = np.empty((3, M))
    u = np.empty((3, M))
    for n in range(n_rows):
        i = idx[n]
        Rn = R[n]
        t0, t1, t2 = T[n, 0], T[n, 1], T[n, 2]
        for m in range(M):  # r = x - (P - T) R
            d0, d1, d2 = P[n, m, 0] - t0, P[n, m, 1] - t1, P[n, m, 2] - t2
            r[0, m] = meas[i, m, 0] - (d0 * Rn[0, 0] + d1 * Rn[1, 0] + d2 * Rn[2, 0])
            r[1, m] = meas[i, m, 1] - (d0 * Rn[0, 1] + d1 * Rn[1, 1] + d2 * Rn[2, 1])
            r[2, m] = meas[i, m, 2] - (d0 * Rn[0, 2] + d1 * Rn[1, 2] + d2 * Rn[2, 2])
        for a in range(3):  # u = C^-1 r, each point's information matrix (symmetric)
            w0, w1, w2 = WL[a, 0, i], WL[a, 1, i], WL[a, 2, i]
            ua = u[a]
            for m in range(M):
                ua[m] = w0[m] * r[0, m] + w1[m] * r[1, m] + w2[m] * r[2, m]
        c = 0.0
        g0 = g1 = g2 = 0.0
        s01 = s10 = s02 = s20 = s12 = s21 = 0.0
        for m in range(M):
            u0, u1, u2 = u[0, m], u[1, m], u[2, m]
            c += r[0, m] * u0 + r[1, m] * u1 + r[2, m] * u2
            v0 = Rn[0, 0] * u0 + Rn[0, 1] * u1 + Rn[0, 2] * u2
            v1 = Rn[1, 0] * u0 + Rn[1, 1] * u1 + Rn[1, 2] * u2
            v2 = Rn[2, 0] * u0 + Rn[2, 1] * u1 + Rn[2, 2] * u2
            v[n, m, 0] = v0
            v[n, m, 1] = v1
            v[n, m, 2] = v2
            g0 += v0
            g1 += v1
            g2 += v2
            q0, q1, q2 = P[n, m, 0] - c0[0], P[n, m, 1] - c0[1], P[n, m, 2] - c0[2]
            s12 += q1 * v2
            s21 += q2 * v1
            s20 += q2 * v0
            s02 += q0 * v2
            s01 += q0 * v1
            s10 += q1 * v0
        cost[n] = c
        G[n, 0] = g0
        G[n, 1] = g1
        G[n, 2] = g2
        G[n, 3] = s12 - s21
        G[n, 4] = s20 - s02
        G[n, 5] = s01 - s10


KERNELS = (chain_points, chain_vjp, chord_residual)


def compiled_here() -> bool | None:
    """Whether numba's cache already holds the kernels on this machine (False: the first call compiles them,
    several seconds); None when that cannot be told (numba's cache layout is not public API)."""
    import os

    try:
        return all(os.path.exists(k._cache._cache_file._index_path) for k in KERNELS)
    except AttributeError:  # pragma: no cover - another numba, or compiled in memory (no cache)
        return None
