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


def compiled(f):
    """numba's ``njit`` (no Python objects, no division checks: IEEE results, as numpy's), cached on disk; where
    numba finds no writable cache location (a read-only installation and home), compiled in memory instead (once
    per process).  No ``fastmath``: sums keep their order, so the numbers are the same on every CPU."""
    try:
        return njit(cache=True, nogil=True, error_model="numpy")(f)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return njit(cache=False, nogil=True, error_model="numpy")(f)


@compiled
def _rotate(k, c, s, v0, v1, v2):  # pragma: no cover - compiled
    """(v0, v1, v2) turned right-handed about the axis e_k by the angle whose cosine is c and sine s."""
    if k == 0:
        return v0, c * v1 - s * v2, s * v1 + c * v2
    if k == 1:
        return c * v0 + s * v2, v1, c * v2 - s * v0
    return c * v0 - s * v1, s * v0 + c * v1, v2


@compiled
def _rot2(f0, f1, f2, u0, u1, u2, sgn):  # pragma: no cover - compiled
    """A rotary axis' error rotation to second order, ``u + sgn f x u + (f (f . u) - |f|^2 u) / 2`` (sgn +1: the
    rotation by f; -1: by -f, its inverse to second order; the transposes are the same with -sgn)."""
    d = f0 * u0 + f1 * u1 + f2 * u2
    q = f0 * f0 + f1 * f1 + f2 * f2
    return (u0 + sgn * (f1 * u2 - f2 * u1) + 0.5 * (f0 * d - q * u0),
            u1 + sgn * (f2 * u0 - f0 * u2) + 0.5 * (f1 * d - q * u1),
            u2 + sgn * (f0 * u1 - f1 * u0) + 0.5 * (f2 * d - q * u2))


@compiled
def _forward(n, tool_axes, wp_axes, side, px, py, pz, toolT, coef, L, sq, rdir, pivot, rcos, rsin, comp, t, v, vin,
             wout, keep):  # pragma: no cover
    """Trial n of the small-angle chain: its points into ``v`` (3, M), each axis' component errors into
    ``comp`` (A, 6, M) and translations into ``t`` (A, 3, M); what enters each tool-side axis' error motion into
    ``vin`` (A, 3, M) and what leaves each workpiece-side axis' error motion into ``wout`` (A, 3, M) (for the
    adjoint; a linear axis writes them only when ``keep``).  Axes 0, 1, 2 are X, Y, Z; axes 3 .. A-1 the rotary axes (row a - 3 of rdir, pivot, rcos, rsin).

    Every step is a loop over the points on contiguous (M,) rows (which the compiler vectorises)."""
    K = coef.shape[3]
    M = v.shape[1]
    A = coef.shape[1]
    pos = (px[n if px.shape[0] > 1 else 0], py[n if py.shape[0] > 1 else 0], pz[n if pz.shape[0] > 1 else 0])
    for a in range(A):
        La = L[a]
        for c in range(6):
            row = comp[a, c]
            cf = coef[n, a, c]
            if K == 3:  # the usual orders (constant, linear, quadratic): one pass, the same sum in the same order
                k0, k1, k2 = cf[0], cf[1], cf[2]
                l0, l1, l2 = La[0], La[1], La[2]
                for m in range(M):
                    row[m] = k0 * l0[m] + k1 * l1[m] + k2 * l2[m]
                continue
            k0, l0 = cf[0], La[0]
            for m in range(M):
                row[m] = k0 * l0[m]
            for k in range(1, K):
                ck, lk = cf[k], La[k]
                for m in range(M):
                    row[m] += ck * lk[m]
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
        if keep:
            for m in range(M):
                v0, v1, v2 = v[0, m], v[1, m], v[2, m]
                va[0, m], va[1, m], va[2, m] = v0, v1, v2
                v[0, m] = v0 + (e1[m] * v2 - e2[m] * v1) + ta[0, m]
                v[1, m] = v1 + (e2[m] * v0 - e0[m] * v2) + ta[1, m]
                v[2, m] = v2 + (e0[m] * v1 - e1[m] * v0) + ta[2, m]
            continue
        for m in range(M):  # the same without what the adjoint keeps
            v0, v1, v2 = v[0, m], v[1, m], v[2, m]
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
        if keep:
            for m in range(M):
                wa[0, m], wa[1, m], wa[2, m] = v[0, m], v[1, m], v[2, m]


@compiled
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
                 vin[k], wout[k], keep)
        eps[k] = comp[:, 3:]
        for m in range(M):
            out[n, m, 0] = v[0, m]
            out[n, m, 1] = v[1, m]
            out[n, m, 2] = v[2, m]
    return out


@compiled
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
    for q in range(rows.shape[0]):
        _vjp_row(rows[q], tool_order, wp_axes, side, px, py, pz, rdir, rcos, rsin, eps, vin, wout, vec[q], params,
                 basis, g, gd, h, u, out[q])
    return out


@compiled
def _vjp_row(n, tool_order, wp_axes, side, px, py, pz, rdir, rcos, rsin, eps, vin, wout, vec, params, basis, g, gd, h,
             u, out):  # pragma: no cover - compiled
    """One trial of :func:`chain_vjp`: trial n's (row of eps, vin, wout) J^T v for vec (M, 3) into out (p,); g, gd,
    h, u: scratch as :func:`chain_vjp` allocates it."""
    M = vec.shape[0]
    A = eps.shape[1]
    pos = (px, py, pz)
    for m in range(M):
        u[0, m], u[1, m], u[2, m] = vec[m, 0], vec[m, 1], vec[m, 2]
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
    # each parameter's sum over the points, in the points' order; four parameters at once (four independent sums
    # in flight instead of one chain of additions)
    n_p = params.shape[0]
    j = 0
    while j + 4 <= n_p:
        h0 = h[params[j, 0], params[j, 1], params[j, 2]]
        h1 = h[params[j + 1, 0], params[j + 1, 1], params[j + 1, 2]]
        h2 = h[params[j + 2, 0], params[j + 2, 1], params[j + 2, 2]]
        h3 = h[params[j + 3, 0], params[j + 3, 1], params[j + 3, 2]]
        b0, b1, b2, b3 = basis[j], basis[j + 1], basis[j + 2], basis[j + 3]
        a0 = a1 = a2 = a3 = 0.0
        for m in range(M):
            a0 += h0[m] * b0[m]
            a1 += h1[m] * b1[m]
            a2 += h2[m] * b2[m]
            a3 += h3[m] * b3[m]
        out[j], out[j + 1], out[j + 2], out[j + 3] = a0, a1, a2, a3
        j += 4
    while j < n_p:
        hr, br = h[params[j, 0], params[j, 1], params[j, 2]], basis[j]
        acc = 0.0
        for m in range(M):
            acc += hr[m] * br[m]
        out[j] = acc
        j += 1


@compiled
def _residual_row(P, x, WLc, i, Rn, t0, t1, t2, c0, vout, G, r, u):  # pragma: no cover - compiled
    """One trial of :func:`chord_residual`: machine points P (3, M) and measured x (3, M) (component-major: each
    pass below runs on contiguous rows), information matrices ``WLc[:, :, i]``, pose Rn (3, 3), (t0, t1, t2); the
    machine-frame weighted residual into vout (M, 3), the rigid gradient (unscaled) into G[:6]; returns the cost.
    r, u: (3, M) scratch."""
    M = P.shape[1]
    P0, P1, P2, x0, x1, x2 = P[0], P[1], P[2], x[0], x[1], x[2]
    r0, r1, r2 = r[0], r[1], r[2]
    a00, a01, a02 = Rn[0, 0], Rn[0, 1], Rn[0, 2]
    a10, a11, a12 = Rn[1, 0], Rn[1, 1], Rn[1, 2]
    a20, a21, a22 = Rn[2, 0], Rn[2, 1], Rn[2, 2]
    for m in range(M):  # r = x - (P - T) R
        d0, d1, d2 = P0[m] - t0, P1[m] - t1, P2[m] - t2
        r0[m] = x0[m] - (d0 * a00 + d1 * a10 + d2 * a20)
        r1[m] = x1[m] - (d0 * a01 + d1 * a11 + d2 * a21)
        r2[m] = x2[m] - (d0 * a02 + d1 * a12 + d2 * a22)
    for a in range(3):  # u = C^-1 r, each point's information matrix (symmetric)
        w0, w1, w2 = WLc[a, 0, i], WLc[a, 1, i], WLc[a, 2, i]
        ua = u[a]
        for m in range(M):
            ua[m] = w0[m] * r0[m] + w1[m] * r1[m] + w2[m] * r2[m]
    u0s, u1s, u2s = u[0], u[1], u[2]
    e0, e1, e2 = c0[0], c0[1], c0[2]
    c = 0.0
    g0 = g1 = g2 = 0.0
    s01 = s10 = s02 = s20 = s12 = s21 = 0.0
    for m in range(M):
        u0, u1, u2 = u0s[m], u1s[m], u2s[m]
        c += r0[m] * u0 + r1[m] * u1 + r2[m] * u2
        v0 = a00 * u0 + a01 * u1 + a02 * u2
        v1 = a10 * u0 + a11 * u1 + a12 * u2
        v2 = a20 * u0 + a21 * u1 + a22 * u2
        vout[m, 0] = v0
        vout[m, 1] = v1
        vout[m, 2] = v2
        g0 += v0
        g1 += v1
        g2 += v2
        q0, q1, q2 = P0[m] - e0, P1[m] - e1, P2[m] - e2
        s12 += q1 * v2
        s21 += q2 * v1
        s20 += q2 * v0
        s02 += q0 * v2
        s01 += q0 * v1
        s10 += q1 * v0
    G[0] = g0
    G[1] = g1
    G[2] = g2
    G[3] = s12 - s21
    G[4] = s20 - s02
    G[5] = s01 - s10
    return c


@compiled
def _transpose_into(a, out):  # pragma: no cover - compiled
    """out (3, M) = a (M, 3) transposed (an exact copy)."""
    for m in range(a.shape[0]):
        out[0, m], out[1, m], out[2, m] = a[m, 0], a[m, 1], a[m, 2]


@compiled
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
    P3, x3 = np.empty((3, M)), np.empty((3, M))
    for n in range(n_rows):
        i = idx[n]
        _transpose_into(P[n], P3)
        _transpose_into(meas[i], x3)
        cost[n] = _residual_row(P3, x3, WL, i, R[n], T[n, 0], T[n, 1], T[n, 2], c0, v[n], G[n], r, u)


@compiled
def rodrigues(o0, o1, o2, Rot):  # pragma: no cover - compiled
    """The exact rotation expm([o]x) into Rot (3, 3): ``identify._rotation`` for one rotation vector."""
    t2 = o0 * o0 + o1 * o1 + o2 * o2
    if t2 < 1e-12:  # series: exact to double precision below |o| = 1e-6 rad
        a = 1.0 - t2 / 6.0
        b = 0.5 - t2 / 24.0
    else:
        t = np.sqrt(t2)
        a = np.sin(t) / t
        b = (1.0 - np.cos(t)) / t2
    d = 1.0 - b * t2
    Rot[0, 0], Rot[0, 1], Rot[0, 2] = o0 * o0 * b + d, -o2 * a + o0 * o1 * b, o1 * a + o0 * o2 * b
    Rot[1, 0], Rot[1, 1], Rot[1, 2] = o2 * a + o1 * o0 * b, o1 * o1 * b + d, -o0 * a + o1 * o2 * b
    Rot[2, 0], Rot[2, 1], Rot[2, 2] = -o1 * a + o2 * o0 * b, o0 * a + o2 * o1 * b, o2 * o2 * b + d


@compiled
def _minus_vecmat(x, A, out):  # pragma: no cover - compiled
    """out = -(x A) for a vector x (n,) and a matrix A (n, k), as a sum of A's rows (contiguous: vectorised)."""
    n, k = x.shape[0], out.shape[0]
    out[:] = 0.0
    i = 0
    while i + 4 <= n:  # four rows per pass over out (fewer loads and stores of it; each column's sum in row order)
        x0, x1, x2, x3 = x[i], x[i + 1], x[i + 2], x[i + 3]
        r0, r1, r2, r3 = A[i], A[i + 1], A[i + 2], A[i + 3]
        for j in range(k):
            out[j] = (((out[j] - x0 * r0[j]) - x1 * r1[j]) - x2 * r2[j]) - x3 * r3[j]
        i += 4
    while i < n:
        xi, row = x[i], A[i]
        for j in range(k):
            out[j] -= xi * row[j]
        i += 1


@compiled
def _all_zero(x):  # pragma: no cover - compiled
    """Whether every entry of x is zero (either sign)."""
    for k in range(x.shape[0]):
        if x[k] != 0.0:
            return False
    return True


@compiled
def _vecmat(x, A, out):  # pragma: no cover - compiled
    """out = x A for a vector x (n,) and a matrix A (n, k): :func:`_minus_vecmat`'s sums with the other sign (each
    column's sum from 0 in the order of the rows, four rows per pass over out)."""
    n, k = x.shape[0], out.shape[0]
    out[:] = 0.0
    i = 0
    while i + 4 <= n:
        x0, x1, x2, x3 = x[i], x[i + 1], x[i + 2], x[i + 3]
        r0, r1, r2, r3 = A[i], A[i + 1], A[i + 2], A[i + 3]
        for j in range(k):
            out[j] = (((out[j] + x0 * r0[j]) + x1 * r1[j]) + x2 * r2[j]) + x3 * r3[j]
        i += 4
    while i < n:
        xi, row = x[i], A[i]
        for j in range(k):
            out[j] += xi * row[j]
        i += 1


@compiled
def chord_stage(mode, rows, label, theta, Rs, Ts, meas, WLc, c0, inv_ps, Hinv, Qs, J, first, Pfix,
                tool_axes, wp_axes, side, px, py, pz, toolT, L, src, dst, sqi, rdir, pivot, rcos, rsin, poff, gfix,
                tool_order, params, basis, tol, ftol, chord_iter, predict, max_rate, ok):  # pragma: no cover - compiled
    """One stage of the chord solver (``identify._chord``), every iteration of a trial in one compiled pass.

    For each trial n = rows[q] until it converges, stops contracting or has had ``chord_iter`` iterations: the
    machine points (mode 0: fixed, ``Pfix``; otherwise the chain at ``theta[n]``, :func:`_forward`, or ``first[q]``
    on the first iteration when given), the weighted residual and rigid gradient (:func:`_residual_row`), the
    geometric gradient along the scaled directions Qs (p, r) (mode 1: the shared Jacobian J (3M, r); mode 2: the
    trial's own J[q] (3M, r); mode 3: the trial's J^T v (:func:`_vjp_row`) from what its own forward pass at the
    stage's start kept, times Qs: the Jacobian held at the start, as chain_adjoint's operator), the step ``z = -G Hinv[label[n]]``, the small rigid
    motion about c0 applied to ``Rs[n]``, ``Ts[n]`` and the step along Qs to ``theta[n]`` (in place).  ok[q]:
    whether the trial converged.  Returns the largest number of iterations any trial took.

    Chain inputs as :func:`chain_points` (``toolT`` (3, M), the coefficient table filled from ``theta[n] + gfix``
    through ``src``/``dst``, squareness through ``sqi`` (-1: not modelled)), ``poff`` (1 or N, M, 3) added to the
    points.  Every number of a trial depends on that trial's inputs only (no sum across trials).
    """
    N, p = theta.shape[0], theta.shape[1]
    M = meas.shape[1]
    A, K = L.shape[0], L.shape[1]
    b = Hinv.shape[1]
    nr = b - 6
    coef = np.zeros((N, A, 6, K))
    sq = np.zeros((N, 3))
    comp, t, v = np.empty((A, 6, M)), np.empty((A, 3, M)), np.empty((3, M))
    vin_s, wout_s = np.empty((A, 3, M)), np.empty((A, 3, M))
    eps1, vin1, wout1 = np.empty((1, A, 3, M)), np.empty((1, A, 3, M)), np.empty((1, A, 3, M))  # mode 3: kept
    g, gd, h = np.zeros((A, 3, M)), np.zeros((A, 3, M)), np.zeros((A, 3, 3, M))
    r, u, u2 = np.empty((3, M)), np.empty((3, M)), np.empty((3, M))
    P3, x3, po3 = np.empty((3, M)), np.empty((3, M)), np.empty((3, M))  # component-major (_residual_row)
    if mode == 0 and Pfix.shape[0] == 1:  # the fixed points of every trial, once
        _transpose_into(Pfix[0], P3)
    if poff.shape[0] == 1:
        _transpose_into(poff[0], po3)
    # the pose alone from theta = 0 (a multi-phase identification's first phase) with inputs shared by every trial:
    # the chain's points are the same for each such trial, evaluated once
    zero_shared = (mode == 1 and nr == 0 and gfix.shape[0] == 1 and poff.shape[0] == 1 and px.shape[0] == 1
                   and py.shape[0] == 1 and pz.shape[0] == 1 and rcos.shape[1] <= 1 and rsin.shape[1] <= 1)
    P3_zero = np.empty((3, M))
    have_zero = False
    vout = np.empty((M, 3))
    G = np.empty(b)
    z = np.empty(b)
    zz, gg, dth = np.empty(b), np.empty(nr), np.empty(p)
    QsT = np.ascontiguousarray(Qs.T)
    Av = np.empty(p)
    th = np.empty(p)
    Rot = np.empty((3, 3))
    Rn = np.empty((3, 3))
    iters = 0
    for q in range(rows.shape[0]):
        n = rows[q]
        Hk = Hinv[label[n]]
        _transpose_into(meas[n], x3)
        if poff.shape[0] > 1:
            _transpose_into(poff[n], po3)
        for i in range(3):
            for j in range(3):
                Rn[i, j] = Rs[n, i, j]
        t0, t1, t2 = Ts[n, 0], Ts[n, 1], Ts[n, 2]
        prev = np.inf
        its = 0
        for it in range(1, chord_iter + 1):
            its = it
            if mode == 0:
                if Pfix.shape[0] > 1 and it == 1:
                    _transpose_into(Pfix[n], P3)
            elif it == 1 and first.shape[0] > 0:
                _transpose_into(first[q], P3)
            elif mode == 1 and nr == 0 and it > 1:
                pass  # the pose alone (a multi-phase identification's first phase): theta, so the points, unchanged
            elif zero_shared and it == 1 and have_zero and _all_zero(theta[n]):
                for i in range(3):  # the chain at theta = 0 with shared inputs: the same points for every trial
                    P3[i, :] = P3_zero[i]
            else:  # the chain at theta[n] (+ the fixed inputs)
                gf = gfix[n if gfix.shape[0] > 1 else 0]
                for k in range(p):
                    th[k] = theta[n, k] + gf[k]
                cf = coef[n].reshape(A * 6 * K)
                for k in range(src.shape[0]):
                    cf[dst[k]] = th[src[k]]
                for c in range(3):
                    sq[n, c] = th[sqi[c]] if sqi[c] >= 0 else 0.0
                keep = mode == 3 and it == 1
                _forward(n, tool_axes, wp_axes, side, px, py, pz, toolT, coef, L, sq, rdir, pivot, rcos, rsin, comp,
                         t, v, vin1[0] if keep else vin_s, wout1[0] if keep else wout_s, keep)
                if keep:
                    for a in range(A):
                        for c in range(3):
                            for m in range(M):
                                eps1[0, a, c, m] = comp[a, 3 + c, m]
                for i in range(3):
                    vi, pi, Pi = v[i], po3[i], P3[i]
                    for m in range(M):
                        Pi[m] = vi[m] + pi[m]
                if zero_shared and it == 1 and not have_zero and _all_zero(theta[n]):
                    P3_zero[:, :] = P3
                    have_zero = True
            cost = _residual_row(P3, x3, WLc, n, Rn, t0, t1, t2, c0, vout, G, r, u)
            for j in range(6):
                G[j] *= inv_ps[j]
            if mode == 1 or mode == 2:  # the geometric gradient -(v J) along the directions
                _minus_vecmat(vout.reshape(3 * M), J[0] if mode == 1 else J[q], gg)
                G[6:] = gg
            elif mode == 3:  # -(J^T v) Qs, J^T v from the trial's kept forward pass
                _vjp_row(0, tool_order, wp_axes, side, px, py, pz, rdir, rcos, rsin, eps1, vin1, wout1, vout, params,
                         basis, g, gd, h, u2, Av)
                _minus_vecmat(Av, Qs, gg)
                G[6:] = gg
            # z = -G Hinv, the step's largest component and its energy sqrt(-G.z)
            _minus_vecmat(G, Hk, zz)
            z[:] = zz
            step = 0.0
            gz = 0.0
            for j in range(b):
                step = max(step, abs(z[j]))
                gz += G[j] * z[j]
            if gz != gz:  # a NaN step (numba's max skips NaN): never converged, as numpy's max says
                step = np.nan
            energy = np.sqrt(max(-gz, 0.0))
            # the step, applied: a small rigid motion about c0, then the parameters along Qs
            rodrigues(z[3] * inv_ps[3], z[4] * inv_ps[4], z[5] * inv_ps[5], Rot)
            d0, d1, d2 = t0 - c0[0], t1 - c0[1], t2 - c0[2]
            t0 = Rot[0, 0] * d0 + Rot[0, 1] * d1 + Rot[0, 2] * d2 + c0[0] + z[0] * inv_ps[0]
            t1 = Rot[1, 0] * d0 + Rot[1, 1] * d1 + Rot[1, 2] * d2 + c0[1] + z[1] * inv_ps[1]
            t2 = Rot[2, 0] * d0 + Rot[2, 1] * d1 + Rot[2, 2] * d2 + c0[2] + z[2] * inv_ps[2]
            for j in range(3):
                a0, a1, a2 = Rn[0, j], Rn[1, j], Rn[2, j]
                for i in range(3):
                    Rs[n, i, j] = Rot[i, 0] * a0 + Rot[i, 1] * a1 + Rot[i, 2] * a2
            for i in range(3):
                for j in range(3):
                    Rn[i, j] = Rs[n, i, j]
            if mode > 0:
                _vecmat(z[6:], QsT, dth)
                for k in range(p):
                    theta[n, k] += dth[k]
            rate = energy / prev if np.isfinite(prev) else np.inf
            done = step < tol or energy * energy <= ftol * cost
            if predict and step * rate < tol:
                done = True
            if done:
                ok[q] = True
                break
            prev = energy
            if np.isfinite(rate) and rate > max_rate:
                break
        Ts[n, 0], Ts[n, 1], Ts[n, 2] = t0, t1, t2
        iters = max(iters, its)
    return iters


@compiled
def point_weights(P, angular, distance, distance_per_length, repeatability, Wh, WLc):  # pragma: no cover - compiled
    """Each tracker point's whitener and information matrix from the stated noise, in one pass: the covariance of
    ``tracker.covariance`` (Eq. 23, from the coordinates) plus the repeatability on the diagonal
    (``MeasurementModel.covariance``), its inverse Cholesky factor ``Wh[n, m]`` (``identify.whitener``'s closed
    form) and ``WLc[:, :, n, m]`` = Wh^T Wh = C^-1 (``identify._gram33``, component-major).  P (N, M, 3), scalar
    noise.  Returns False where a covariance is not positive definite (nothing is then to be trusted: the caller
    takes numpy's path, which says so).

    A trial's points are computed on contiguous (M,) rows (the compiler vectorises the square roots and divisions),
    then scattered into the (M, 3, 3) whiteners: the same operations in the same order as point by point."""
    N, M = P.shape[0], P.shape[1]
    rep2 = repeatability * repeatability
    good = True
    xs, ys, zs = np.empty(M), np.empty(M), np.empty(M)
    Wt = np.empty((6, M))  # the whitener's lower triangle, row by row
    for n in range(N):
        for m in range(M):
            xs[m], ys[m], zs[m] = P[n, m, 0], P[n, m, 1], P[n, m, 2]
        w00, w10, w11, w20, w21, w22 = Wt[0], Wt[1], Wt[2], Wt[3], Wt[4], Wt[5]
        q00, q01, q02, q11, q12, q22 = WLc[0, 0, n], WLc[0, 1, n], WLc[0, 2, n], WLc[1, 1, n], WLc[1, 2, n], WLc[2, 2, n]
        for m in range(M):
            x, y, z = xs[m], ys[m], zs[m]
            rho = np.sqrt(x * x + y * y)  # hypot's overflow guard is not needed at a tracker's ranges (mm)
            r = np.sqrt(rho * rho + z * z)
            ca = x / rho if rho > 0 else 1.0
            sa = y / rho if rho > 0 else 0.0
            ce = rho / r if r > 0 else 1.0
            se = z / r if r > 0 else 0.0
            ur = distance + distance_per_length * r
            A = ur * ur
            arho, ar = angular * rho, angular * r
            Bv = arho * arho
            Cv = ar * ar
            rx, ry = ce * ca, ce * sa
            ex, ey = se * ca, se * sa
            c00 = A * rx * rx + Bv * sa * sa + Cv * ex * ex + rep2
            c11 = A * ry * ry + Bv * ca * ca + Cv * ey * ey + rep2
            c22 = A * se * se + Cv * ce * ce + rep2
            c10 = A * rx * ry - Bv * sa * ca + Cv * ex * ey
            c20 = A * rx * se - Cv * ex * ce
            c21 = A * ry * se - Cv * ey * ce
            l00 = np.sqrt(c00)
            l10, l20 = c10 / l00, c20 / l00
            l11 = np.sqrt(c11 - l10 * l10)
            l21 = (c21 - l20 * l10) / l11
            l22 = np.sqrt(c22 - l20 * l20 - l21 * l21)
            i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
            a10 = -l10 * i00 * i11
            a21 = -l21 * i11 * i22
            a20 = (l10 * l21 - l20 * l11) * i00 * i11 * i22
            w00[m], w10[m], w11[m], w20[m], w21[m], w22[m] = i00, a10, i11, a20, a21, i22
            # Wh^T Wh, (i, j) = sum_k Wh[k, i] Wh[k, j] over k = 0, 1, 2 (the zeros of the triangle included)
            q00[m] = i00 * i00 + a10 * a10 + a20 * a20
            q01[m] = i00 * 0.0 + a10 * i11 + a20 * a21
            q02[m] = i00 * 0.0 + a10 * 0.0 + a20 * i22
            q11[m] = 0.0 * 0.0 + i11 * i11 + a21 * a21
            q12[m] = 0.0 * 0.0 + i11 * 0.0 + a21 * i22
            q22[m] = 0.0 * 0.0 + 0.0 * 0.0 + i22 * i22
        for m in range(M):
            a, b, c, d, e, f = w00[m], w10[m], w11[m], w20[m], w21[m], w22[m]
            if not (np.isfinite(a) and np.isfinite(c) and np.isfinite(f) and np.isfinite(b) and np.isfinite(e)
                    and np.isfinite(d)):
                good = False
            W = Wh[n, m]
            W[0, 0], W[0, 1], W[0, 2] = a, 0.0, 0.0
            W[1, 0], W[1, 1], W[1, 2] = b, c, 0.0
            W[2, 0], W[2, 1], W[2, 2] = d, e, f
            WLc[1, 0, n, m] = q01[m]
            WLc[2, 0, n, m] = q02[m]
            WLc[2, 1, n, m] = q12[m]
    return good


@compiled
def chord_final(P, meas, Wh, R, T, Pnom, Rnom, Tnom, res, res_machine, w, chi2, initial):  # pragma: no cover
    """The chord solver's results, trial by trial: the tracker-frame residual ``res`` = x - R^T (P - T), its
    machine-frame ``res_machine`` = R res, the whitened ``w`` = Wh res and ``chi2`` = |w|^2; and Eq. 27's
    ``initial`` = Rnom x + Tnom - Pnom (the pose-only fit of the nominal points Pnom (1 or N, M, 3))."""
    N, M = P.shape[0], P.shape[1]
    for n in range(N):
        Rn, Qn, Pn = R[n], Rnom[n], Pnom[n if Pnom.shape[0] > 1 else 0]
        c = 0.0
        for m in range(M):
            d0, d1, d2 = P[n, m, 0] - T[n, 0], P[n, m, 1] - T[n, 1], P[n, m, 2] - T[n, 2]
            x0, x1, x2 = meas[n, m, 0], meas[n, m, 1], meas[n, m, 2]
            r0 = x0 - (Rn[0, 0] * d0 + Rn[1, 0] * d1 + Rn[2, 0] * d2)
            r1 = x1 - (Rn[0, 1] * d0 + Rn[1, 1] * d1 + Rn[2, 1] * d2)
            r2 = x2 - (Rn[0, 2] * d0 + Rn[1, 2] * d1 + Rn[2, 2] * d2)
            res[n, m, 0], res[n, m, 1], res[n, m, 2] = r0, r1, r2
            for i in range(3):
                res_machine[n, m, i] = Rn[i, 0] * r0 + Rn[i, 1] * r1 + Rn[i, 2] * r2
                wi = Wh[n, m, i, 0] * r0 + Wh[n, m, i, 1] * r1 + Wh[n, m, i, 2] * r2
                w[n, m, i] = wi
                c += wi * wi
                initial[n, m, i] = (Qn[i, 0] * x0 + Qn[i, 1] * x1 + Qn[i, 2] * x2) + Tnom[n, i] - Pn[m, i]
        chi2[n] = c


@compiled
def tracker_points(P_W, R, T, noise, out):  # pragma: no cover - compiled
    """What the tracker reads of the machine points P_W (N, M, 3), in one pass: ``tracker.to_tracker`` with the
    pose R (1 or N, 3, 3), T (1 or N, 3) (R^T (P - T)), then ``tracker.add_spherical_noise`` with the offsets
    noise (N, M, 3) (range, azimuth, elevation; an empty (0, M, 3) array: none), exactly as those functions
    compute it (spherical coordinates, offsets added, back to Cartesian), round-off apart: the angles' cosines
    and sines are taken from the coordinates and the offsets added by the addition theorems, without trigonometry
    (a point on the tracker's vertical axis, whose azimuth is undefined, gets azimuth 0)."""
    N, M = P_W.shape[0], P_W.shape[1]
    noisy = noise.shape[0] > 0
    for n in range(N):
        Rn = R[n if R.shape[0] > 1 else 0]
        Tn = T[n if T.shape[0] > 1 else 0]
        for m in range(M):
            d0, d1, d2 = P_W[n, m, 0] - Tn[0], P_W[n, m, 1] - Tn[1], P_W[n, m, 2] - Tn[2]
            x = d0 * Rn[0, 0] + d1 * Rn[1, 0] + d2 * Rn[2, 0]
            y = d0 * Rn[0, 1] + d1 * Rn[1, 1] + d2 * Rn[2, 1]
            z = d0 * Rn[0, 2] + d1 * Rn[1, 2] + d2 * Rn[2, 2]
            if noisy:  # the angles' cosines and sines from the coordinates, the offsets by the addition theorems
                rho = np.sqrt(x * x + y * y)
                r = np.sqrt(rho * rho + z * z)
                ca, sa = (x / rho, y / rho) if rho > 0 else (1.0, 0.0)  # arctan2(0, 0) = 0
                ce, se = (rho / r, z / r) if r > 0 else (1.0, 0.0)
                cda, sda = _cos_sin(noise[n, m, 1])
                cde, sde = _cos_sin(noise[n, m, 2])
                ca, sa = ca * cda - sa * sda, sa * cda + ca * sda  # azimuth + its offset
                ce, se = ce * cde - se * sde, se * cde + ce * sde  # elevation + its offset
                r += noise[n, m, 0]
                x, y, z = r * ce * ca, r * ce * sa, r * se
            out[n, m, 0], out[n, m, 1], out[n, m, 2] = x, y, z
    return out


@compiled
def _cos_sin(d):  # pragma: no cover - compiled
    """(cos d, sin d): by their series below 1e-3 rad (the terms left out are below 1e-22 relative: exact in double
    precision), by the functions above."""
    if abs(d) < 1e-3:
        d2 = d * d
        return 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 / 720.0)), d * (1.0 - d2 * (1.0 / 6.0 - d2 / 120.0))
    return np.cos(d), np.sin(d)


#: the kernels a run of the engine compiles (what :func:`compiled_here` looks for)
KERNELS = (chain_points, chord_stage, point_weights, chord_final, tracker_points)


def compiled_here(kernels: tuple = KERNELS) -> bool | None:
    """Whether numba's cache already holds ``kernels`` (default: the engine's) on this machine (False: the first call
    compiles them, several seconds); None when that cannot be told (numba's cache layout is not public API)."""
    import os

    try:
        return all(os.path.exists(k._cache._cache_file._index_path) for k in kernels)
    except AttributeError:  # pragma: no cover - another numba, or compiled in memory (no cache)
        return None
