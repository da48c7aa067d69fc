"""Data-driven physics terms of the diagnosis: periodic errors and local reversals, found by a calibrated scan.

docs/diagnose.md, "Periodic and local terms".  What the library's candidates cannot name because their shape has
a free parameter (a period, a region), searched over that parameter with a family-wise calibrated test:

* **periodic error along an axis** (ISO 230-2 periodic positioning error: a lead screw's pitch error, a rack's
  tooth error, a scale's interpolation error): a sin + cos pair in the axis position, acting along that axis, for
  every period between 2.5 times the mesh spacing and two thirds of the travel;
* **periodic error of the tracker's distance** (the cyclic error of an ADM or interferometer): a sin + cos pair in
  the measured distance, acting along the beam, periods from 2.5 times the typical gap between distances (at least
  5 mm) to two thirds of their span;
* **local reversal**: the approach-direction term of one axis only above (or below) a position c, for every c
  between the mesh positions with at least two positions either side (a worn section of a nut).

Each term is a column block of the whitened model; its F statistic against what the model (baseline and the
chosen effects) leaves is computed for every term at once.  The test statistic is the smallest nominal p-value
over every term of every family (a max-statistic); its distribution under "only noise" is simulated by drawing
whitened Gaussian noise, projecting out the same model and taking the same minimum (the noise covariance is the
one selection uses, stated or estimated; F ratios make it independent of the overall level).  Sequential Monte
Carlo (Besag & Clifford 1991): stop once 10 simulated minima beat the observed one.  A term is found when the
family-wise p-value is below the scan's share of the diagnosis' family-wise level.

A found term becomes a candidate (:class:`PeriodicError`, :class:`PiecewiseReversal`) and enters selection like
every other, so it is refitted, tested against other candidates and alternatives outside the library, and the fit
after it shows the improvement.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from .contracts import Candidate
from .machine import AXES, AXIS_INDEX
from .model import between_runs_columns
from .units import factor

#: periods: from this many mesh spacings (or gaps between distances) ...
MIN_PERIOD_SPACINGS = 2.5
#: ... to this fraction of the travel (or of the span of distances): longer ones are the error functions' polynomials
MAX_PERIOD_FRACTION = 1 / 1.5
#: the shortest period of the tracker's distance searched, mm
MIN_RANGE_PERIOD = 5.0
#: frequency grid: this many steps per 1/travel (oversampling of the periodogram)
OVERSAMPLE = 5
#: fewer distinct positions than this along an axis: no periodic search there
MIN_POSITIONS = 8
#: sequential Monte Carlo: stop after this many simulated minima at or below the observed one, or after MAX_SIMS
EXCEEDANCES, MAX_SIMS, BATCH = 10, 2000, 100
#: plausible amplitude of a periodic error: a ball screw's lead deviation within one turn (ISO 3408-3, v_2pi) is
#: 3-8 um for classes 1-5, 8-12 um for a transport screw; an ADM's cyclic error a few um; a rack's tooth error
#: 10-20 um: 0 to 25 um
PLAUSIBLE_AMPLITUDE = (0.0, 25.0)


class PeriodicError(Candidate):
    """A periodic error found by the scan: A sin(2 pi u / P + phi) along the axis (u its position), or along the beam
    (u the measured distance).  Parameters: the sin and cos coefficients; the summary gives the amplitude."""

    effect = "periodic_error"
    parameters = {"amplitude": "um"}  # a vector: the sin and the cos coefficient
    quantity_names = {"amplitude": "a periodic amplitude"}
    hints = {"approximation_degree": "Measure a finer mesh of that axis (a periodic error repeats, a polynomial "
                                     "does not)."}

    def __init__(self, axis, period, origin=0.0):
        super().__init__(axis)
        self.period = float(period)  # mm
        self.origin = float(origin)
        self.frame = "tracker" if axis == "range" else "machine"
        self.details: dict = {}
        where = "the tracker's distance (cyclic error of its ADM)" if axis == "range" else \
            f"the {axis} position (ISO 230-2 periodic positioning error: lead screw, rack, scale)"
        self.description = (f"a periodic error of {where}, period {self.period:.4g} mm, acting "
                            + ("along the beam" if axis == "range" else f"along {axis}"))

    def variable(self, ctx):
        if self.axis == "range":
            return np.linalg.norm(ctx.P_LT, axis=1)
        return ctx.plan.nominal[:, AXIS_INDEX[self.axis]]

    def direction(self, ctx):
        if self.axis == "range":
            return ctx.P_LT / np.linalg.norm(ctx.P_LT, axis=1, keepdims=True)
        return np.broadcast_to(np.eye(3)[AXIS_INDEX[self.axis]], (len(ctx.plan), 3))

    def columns(self, ctx):
        return periodic_columns(self.variable(ctx) - self.origin, self.direction(ctx), np.array([1 / self.period]))

    def variables(self, ctx):
        return [] if self.axis == "range" else [self.axis]

    def summary(self, beta, cov):
        """The amplitude sqrt(a^2 + b^2) (um) and its standard uncertainty (first order)."""
        f = factor("mm", "um")
        a, b = float(beta[0]), float(beta[1])
        A = math.hypot(a, b)
        g = np.array([a, b]) / A if A > 0 else np.array([1.0, 0.0]) / math.sqrt(2)
        return [A * f], [float(math.sqrt(max(g @ np.asarray(cov)[:2, :2] @ g, 0.0))) * f], "um"

    def implausible(self, beta, cov):
        (A,), (u,), _ = self.summary(beta, cov)
        lo, hi = PLAUSIBLE_AMPLITUDE
        if A - 2 * u > hi:
            return f"would need a periodic amplitude of {A:.3g} um; plausible is {lo:g} to {hi:g} um"
        return None


class PiecewiseReversal(Candidate):
    """A reversal (lost motion) that differs below and above a position of its axis: B1 for p < c, B2 for p > c."""

    effect = "reversal"
    parameters = {"B": "um"}  # a vector: below and above the boundary
    plausible = {"B": (-20.0, 100.0)}
    quantity_names = {"B": "a lost motion B"}
    hints = {"reversal": "Measure the reversal at several positions along the axis (ISO 230-2 bidirectional)."}

    def __init__(self, axis, boundary, span):
        super().__init__(axis)
        self.boundary = float(boundary)  # mm
        self.span = (float(span[0]), float(span[1]))
        self.details: dict = {}
        self.description = (f"lost motion of the {axis} axis that is not uniform along it (a worn section of the nut "
                            f"or rack): B below {axis} = {self.boundary:.6g} mm, and another B above; from either side "
                            "the axis stops B/2 short of the target")

    def columns(self, ctx):
        i = AXIS_INDEX[self.axis]
        p = ctx.plan.nominal[:, i]
        d = -ctx.plan.direction[:, i] / 2.0
        low = (p < self.boundary).astype(float)
        C = np.zeros((len(p), 3, 2))
        C[:, i, 0] = d * low
        C[:, i, 1] = d * (1 - low)
        return C

    def variables(self, ctx):
        return [f"dir_{self.axis}"]

    def alternatives(self, ctx):
        C = between_runs_columns(ctx.plan, self.axis)
        if C is None:
            return []
        return [{"name": "a change between runs",
                 "description": f"anything that changes along {self.axis} between the plan's runs",
                 "separate": "Repeat a run in the same direction as the one before it.",
                 "columns": C}]


def periodic_columns(u, direction, freqs) -> np.ndarray:
    """(M, 3, 2F): sin and cos of 2 pi f u for every frequency f (1/mm), acting along ``direction`` (M, 3)."""
    ph = 2 * np.pi * np.asarray(u, float)[:, None] * np.asarray(freqs, float)[None, :]  # (M, F)
    sc = np.stack([np.sin(ph), np.cos(ph)], axis=2).reshape(len(u), -1)  # (M, 2F): sin f1, cos f1, sin f2, ...
    return np.asarray(direction, float)[:, :, None] * sc[:, None, :]


def _grid(values, min_period):
    """Frequencies (1/mm) of a periodogram over ``values`` (mm), or (None, why not)."""
    v = np.unique(np.round(np.asarray(values, float), 3))
    span = float(np.ptp(v)) if len(v) else 0.0
    if len(v) < MIN_POSITIONS or span <= 0:
        return None, f"{len(v)} distinct positions (at least {MIN_POSITIONS} are needed)"
    gap = float(np.median(np.diff(v)))
    p_min = max(MIN_PERIOD_SPACINGS * gap, min_period)
    p_max = span * MAX_PERIOD_FRACTION
    if p_min >= p_max:
        return None, f"the shortest period the spacing allows ({p_min:.4g} mm) exceeds two thirds of the span"
    return np.arange(1 / p_max, 1 / p_min, 1 / (span * OVERSAMPLE)), (p_min, p_max)


def families(ctx, with_range=True):
    """The scan's term families: [(kind, axis, grid values, raw columns (M, 3, k*T), k, frame)], and what was left
    out and why."""
    plan = ctx.plan
    out, skipped = [], []
    for a in AXES:
        i = AXIS_INDEX[a]
        freqs, info = _grid(plan.nominal[:, i], 0.0)
        if freqs is None:
            skipped.append({"term": f"periodic_error[{a}]", "reason": info})
        else:
            e = np.broadcast_to(np.eye(3)[i], (len(plan), 3))
            out.append(("periodic", a, freqs, periodic_columns(plan.nominal[:, i], e, freqs), 2, "machine", info))
    if with_range:
        r = np.linalg.norm(ctx.P_LT, axis=1)
        freqs, info = _grid(r, MIN_RANGE_PERIOD)
        if freqs is None:
            skipped.append({"term": "periodic_error[range]", "reason": info})
        else:
            u = ctx.P_LT / r[:, None]
            out.append(("periodic", "range", freqs, periodic_columns(r, u, freqs), 2, "tracker", info))
    for a in AXES:
        i = AXIS_INDEX[a]
        d = plan.direction[:, i]
        if not ((d > 0).any() and (d < 0).any()):
            continue
        p = plan.nominal[:, i]
        pos = np.unique(np.round(p, 6))
        if len(pos) < 4:
            skipped.append({"term": f"local reversal[{a}]", "reason": f"{len(pos)} positions (at least 4 are needed)"})
            continue
        cuts = 0.5 * (pos[1:-2] + pos[2:-1])  # at least two positions either side
        cols = []
        for c in cuts:
            for side in (p > c, p < c):
                col = np.zeros((len(p), 3))
                col[:, i] = -d / 2.0 * side
                cols.append(col)
        vals = np.repeat(cuts, 2)
        out.append(("local_reversal", a, vals, np.stack(cols, axis=2), 1, "machine", (float(pos[0]), float(pos[-1]))))
    return out, skipped


def _orthonormal_blocks(T, k):
    """Orthonormalise each block of k columns of T (n, k*B) (Gram-Schmidt within the block); degenerate ones -> 0."""
    n, m = T.shape
    B = m // k
    U = T.reshape(n, B, k).copy()
    ok = np.ones(B, bool)
    for j in range(k):
        for i in range(j):
            U[:, :, j] -= U[:, :, i] * np.einsum("nb,nb->b", U[:, :, i], U[:, :, j])[None]
        nrm = np.linalg.norm(U[:, :, j], axis=0)
        ref = np.linalg.norm(T.reshape(n, B, k)[:, :, j], axis=0)
        bad = nrm <= 1e-6 * np.maximum(ref, 1e-300)
        ok &= ~bad
        U[:, :, j] /= np.where(bad, 1.0, nrm)[None]
        U[:, bad, j] = 0.0
    return U.reshape(n, m), ok


def _min_p(Us, ks, oks, R, dof_model):
    """The smallest nominal p-value over all terms, for each column of R (n, S) of residuals (already projected)."""
    chi = np.sum(R * R, axis=0)  # (S,)
    best = np.ones(R.shape[1])
    arg = np.zeros(R.shape[1], int)
    per = []
    off = 0
    for U, k, ok in zip(Us, ks, oks):
        proj = U.T @ R  # (k*B, S)
        d = (proj**2).reshape(-1, k, R.shape[1]).sum(axis=1)  # (B, S)
        dof = dof_model - k
        F = (d / k) / np.maximum((chi[None] - d) / dof, 1e-300)
        p = stats.f.sf(F, k, dof)
        p[~ok] = 1.0
        per.append(p)
        j = np.argmin(p, axis=0)
        pm = p[j, np.arange(R.shape[1])]
        better = pm < best
        best = np.where(better, pm, best)
        arg = np.where(better, j + off, arg)
        off += p.shape[0]
    return best, arg, per


def scan(ctx, X, w, whiten, level, seed=20261125, with_range=True) -> dict:
    """The family-wise calibrated scan of the periodic and local terms against what the model ``X`` (whitened,
    (n, p)) leaves of ``w``.  Returns a dict: the best term, its family-wise p-value, whether it is found at
    ``level``, every family's best term, and the families left out."""
    fams, skipped = families(ctx, with_range)
    Qx, _ = np.linalg.qr(X)
    rank = int(np.sum(np.abs(np.diag(_)) > 1e-10 * max(np.abs(np.diag(_)).max(), 1e-300))) if X.shape[1] else 0
    n = len(w)
    dof_model = n - rank
    Us, ks, oks = [], [], []
    for kind, axis, vals, raw, k, frame, info in fams:
        C = whiten(raw, frame)
        C = C - Qx @ (Qx.T @ C)
        U, ok = _orthonormal_blocks(C, k)
        Us.append(U)
        ks.append(k)
        oks.append(ok)
    out = {"level": level, "families": [], "skipped": skipped, "found": False}
    if not fams:
        out["p_value"] = 1.0
        return out
    r = w - Qx @ (Qx.T @ w)
    p_obs, arg, per = _min_p(Us, ks, oks, r[:, None], dof_model)
    p_obs = float(p_obs[0])
    n_terms = int(sum(len(p) for p in per))
    # family-wise p-value of the smallest p: Bonferroni bounds it from above, the smallest p itself from below
    bound = None
    if p_obs * n_terms < level:
        p_fw, sims, how = p_obs * n_terms, 0, "Bonferroni bound over the terms (below the level: no simulation needed)"
        bound = "upper"
    elif p_obs >= level:
        p_fw, sims, how = p_obs, 0, "the smallest nominal p-value (above the level: no simulation needed)"
        bound = "lower"
    else:
        rng = np.random.default_rng(seed)
        hits, sims = 0, 0
        while hits < EXCEEDANCES and sims < MAX_SIMS:
            Z = rng.standard_normal((n, BATCH))
            Z -= Qx @ (Qx.T @ Z)
            m, _, _ = _min_p(Us, ks, oks, Z, dof_model)
            hits += int(np.sum(m <= p_obs))
            sims += BATCH
        p_fw = (hits + 1) / (sims + 1) if hits < EXCEEDANCES else hits / sims
        how = (f"sequential Monte Carlo of the smallest p-value under noise alone ({sims} simulations, {hits} at or "
               "below the observed one)")
    out.update(p_value=float(min(p_fw, 1.0)), p_value_bound=bound, method=how, simulations=sims, terms=n_terms,
               smallest_nominal_p=p_obs, found=bool(p_fw < level))
    off = 0
    best_term = None
    for (kind, axis, vals, raw, k, frame, info), p in zip(fams, per):
        j = int(np.argmin(p[:, 0]))
        entry = {"term": kind, "axis": axis, "nominal_p": float(p[j, 0]), "terms": int(len(p))}
        if kind == "periodic":
            entry.update(period={"value": float(1 / vals[j]), "unit": "mm"},
                         searched={"from": float(info[0]), "to": float(info[1]), "unit": "mm"})
        else:
            entry.update(boundary={"value": float(vals[j]), "unit": "mm"}, side="above" if j % 2 == 0 else "below")
        out["families"].append(entry)
        if off <= arg[0] < off + len(p):
            best_term = (kind, axis, vals, j, k, frame, info, entry)
        off += len(p)
    out["best"] = best_term[-1] if best_term else None
    out["_best"] = best_term
    return out


def refine_period(ctx, X, w, whiten, axis, period, span):
    """The period (mm) that fits best near ``period`` (a fine search over +-1 grid step), and the fit there."""
    u = (np.linalg.norm(ctx.P_LT, axis=1) if axis == "range" else ctx.plan.nominal[:, AXIS_INDEX[axis]])
    e = (ctx.P_LT / u[:, None]) if axis == "range" else np.broadcast_to(np.eye(3)[AXIS_INDEX[axis]], (len(u), 3))
    frame = "tracker" if axis == "range" else "machine"
    df = 1 / (span * OVERSAMPLE)
    f0 = 1 / period
    freqs = np.linspace(f0 - df, f0 + df, 41)
    freqs = freqs[freqs > 0]
    Qx, _ = np.linalg.qr(X)
    C = whiten(periodic_columns(u, e, freqs), frame)
    C = C - Qx @ (Qx.T @ C)
    U, ok = _orthonormal_blocks(C, 2)
    r = w - Qx @ (Qx.T @ w)
    d = ((U.T @ r) ** 2).reshape(-1, 2).sum(axis=1)
    d[~ok] = -1
    return float(1 / freqs[int(np.argmax(d))])


def period_uncertainty(ctx, X, w, whiten, cand: PeriodicError, dof_scale=True):
    """(a, b, period) and their covariance from the linearised three-parameter fit (sin, cos, frequency), with the
    rest of the model ``X``; the covariance inflated by chi2/dof when above one.  Returns (period u (mm), amplitude
    (mm), its u, phase (rad))."""
    u = cand.variable(ctx)
    e = cand.direction(ctx)
    frame = cand.frame
    f0 = 1 / cand.period
    S = whiten(periodic_columns(u, e, np.array([f0])), frame)  # (n, 2)
    Qx, _ = np.linalg.qr(X)
    Sp = S - Qx @ (Qx.T @ S)
    r = w - Qx @ (Qx.T @ w)
    ab, *_ = np.linalg.lstsq(Sp, r, rcond=None)
    a, b = ab
    ph = 2 * np.pi * u * f0
    # d/df of a sin(2 pi f u) + b cos(2 pi f u) = 2 pi u (a cos - b sin)
    dcol = (2 * np.pi * u * (a * np.cos(ph) - b * np.sin(ph)))[:, None] * e
    D = whiten(dcol[:, :, None], frame)
    J = np.concatenate([S, D], axis=1)
    Jp = J - Qx @ (Qx.T @ J)
    res = r - Sp @ ab
    dof = len(r) - X.shape[1] - 3
    s2 = max(float(res @ res) / dof, 1.0) if (dof > 0 and dof_scale) else 1.0
    cov = np.linalg.pinv(Jp.T @ Jp) * s2
    uf = math.sqrt(max(cov[2, 2], 0.0))
    return uf / f0**2, math.hypot(a, b), float(math.atan2(b, a))
