"""Diagnose a recording: locate the mismatch, name the physics left out, model it, show the fit improve.

Method (docs/diagnose.md has the reasoning and the calibration):

1. **Baseline.** The recording is identified exactly as a simulated
   verification would be (same model, same weights from its stated tracker
   and machine uncertainties).  Its whitened residuals ``w`` and whitened
   design ``A0`` (pose + identifiable geometric directions) are kept.
2. **Locate.** The residuals are summarised by run, time, approach
   direction, axis position and temperature: where the structure lives.
3. **Candidates.** Every candidate physics term (a
   :class:`~mtbudget.contracts.Candidate` from a plugin, hook
   ``mtbudget_register_candidates``) gives the displacement of every measured
   point per unit of each of its parameters; every call into a candidate goes
   through :func:`mtbudget.plugins.call`, so its errors name the plugin and
   the method.  Only the part of those columns
   that the baseline cannot absorb (``C - P_A0 C``) can explain anything; a
   candidate with nothing left is *not testable* with this plan (for example
   thermal expansion with a constant temperature, indistinguishable from a
   positioning error).
4. **Selection.** The model is linear in the candidate parameters to
   ~1e-5, so nested fits are exact projections.  Each addition is tested with
   an F-test (robust to a misstated overall noise level) at a family-wise
   level ``alpha`` with a Bonferroni correction over all candidates; sets are
   compared by BIC among all subsets (up to three) of the individually
   significant candidates, not only greedily, because two effects can
   masquerade as a third; every member of the chosen set must remain
   significant given the others.  A candidate that fits (nearly) as well as a
   chosen one in its place is reported as *confounded* with it.
5. **After.** The chosen effects are put into the model at their estimates
   and the recording is identified again: chi-square and RMS before and after.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from . import tracker as lt
from .contracts import Candidate, DiagnosisContext
from .errors import DiagnosisError, MtbudgetError, PluginError
from .identify import Noise, identify
from .machine import AXES
from .model import MODEL_INPUTS, MeasurementModel, merge
from .recording import Recording
from .units import display, internal_unit_of, ureg

HOOK = "mtbudget_register_candidates"
#: a candidate of which less than this fraction (whitened norm) is left once the baseline has absorbed
#: what it can is not testable with the plan
ABSORBED = 1e-3


def _call(c: Candidate, method: str, *args):
    """A candidate's method through the plugin host, so an error names the plugin, the candidate and the method."""
    from .plugins import call  # plugins imports contracts; imported here to keep the layers apart

    return call(c, method, *args)


def _fail(c: Candidate, reason: str, method: str | None = None):
    raise PluginError(reason, c.plugin or None, c.label, HOOK, method)


# --------------------------------------------------------------------- fitting
@dataclass
class _Fit:
    chi2: float
    beta: np.ndarray
    cov: np.ndarray


class _Linear:
    """Exact nested least squares in the whitened space around the baseline solution."""

    def __init__(self, A0: np.ndarray, w: np.ndarray):
        self.Q0, _ = np.linalg.qr(A0)
        self.w = w
        self.chi2_0 = float(w @ w)
        self.n, self.p0 = A0.shape

    def project(self, C: np.ndarray) -> np.ndarray:
        return C - self.Q0 @ (self.Q0.T @ C)

    def fit(self, Cs: list) -> _Fit:
        if not Cs:
            return _Fit(self.chi2_0, np.zeros(0), np.zeros((0, 0)))
        C = np.concatenate(Cs, axis=1)
        Cp = self.project(C)
        # scale columns for conditioning
        s = np.linalg.norm(Cp, axis=0)
        s[s == 0] = 1.0
        G = (Cp / s)
        beta_s, *_ = np.linalg.lstsq(G, self.w, rcond=1e-10)
        r = self.w - G @ beta_s
        cov_s = np.linalg.pinv(G.T @ G, rcond=1e-12)
        return _Fit(float(r @ r), beta_s / s, cov_s / np.outer(s, s))

    @property
    def dof0(self):
        return self.n - self.p0


def _check_declaration(c: Candidate):
    """The candidate's declared attributes: parameters with units mtbudget knows, a frame, hints."""
    params = c.parameters
    if not isinstance(params, dict) or not params:
        _fail(c, f"parameters must be a non-empty dict of name -> display unit (for example {{'cte': 'um/(m*K)'}}), "
                 f"got {params!r}")
    for name, unit in params.items():
        try:
            internal_unit_of(unit)
        except Exception:
            _fail(c, f"parameter {name!r}: {unit!r} is not a unit of a dimension mtbudget has an internal unit for")
    if c.frame not in ("machine", "tracker"):
        _fail(c, f"frame must be 'machine' or 'tracker', got {c.frame!r}")
    if not isinstance(c.hints, dict):
        _fail(c, f"hints must be a dict of other effect -> sentence, got {type(c.hints).__name__}")


def _columns(c: Candidate, ctx: DiagnosisContext) -> np.ndarray:
    """The candidate's columns (M, 3, k), checked."""
    raw = _call(c, "columns", ctx)
    try:
        C = np.asarray(raw, float)
    except (TypeError, ValueError):
        _fail(c, f"must return a numeric array, got {type(raw).__name__}", "columns")
    M = len(ctx.plan)
    if C.ndim != 3 or C.shape[:2] != (M, 3) or C.shape[2] == 0:
        _fail(c, f"must return shape ({M}, 3, k) with k >= 1, got {C.shape}", "columns")
    if not np.all(np.isfinite(C)):
        _fail(c, "returned NaN or infinity", "columns")
    k, n_par = C.shape[2], len(c.parameters)
    if k != n_par and n_par != 1:
        _fail(c, f"returned {k} columns for {n_par} parameters; give one column per parameter, "
                 "or declare one (vector) parameter", "columns")
    return C


def _whitened(C: np.ndarray, frame: str, ctx: DiagnosisContext, Wh: np.ndarray) -> np.ndarray:
    """Columns (M, 3, k) in ``frame`` -> whitened tracker-frame columns (3M, k)."""
    if frame == "machine":
        R = lt.rotation(*ctx.pose[3:])
        C = np.einsum("ji,mjk->mik", R, C)  # R^T applied to each column: into the tracker frame
    return np.einsum("mij,mjk->mik", Wh, C).reshape(3 * C.shape[0], -1)


# --------------------------------------------------------------------- locate
def locate(ctx: DiagnosisContext, residual_machine: np.ndarray, whitened: np.ndarray) -> dict:
    """Where the baseline residuals are structured (machine frame, um)."""
    plan = ctx.plan
    r = display(residual_machine, "mm", "um")
    out: dict = {"unit": "um"}
    chi_pt = (whitened**2).sum(axis=1)
    n = len(plan)
    # by run
    runs = {}
    for k in np.unique(plan.run):
        m = plan.run == k
        runs[int(k)] = {"points": int(m.sum()), "rms": float(np.sqrt((r[m] ** 2).sum(1).mean())),
                        "mean": r[m].mean(0).round(3).tolist(), "chi2_per_point": float(chi_pt[m].mean() / 3)}
    out["by_run"] = runs
    # by time: slope of each component (um/h) with its standard error
    t = display(plan.time, "s", "h")
    trend = {}
    if np.ptp(t) > 0:
        X = np.column_stack([np.ones(n), t - t.mean()])
        for i, a in enumerate(AXES):
            coef, res, *_ = np.linalg.lstsq(X, r[:, i], rcond=None)
            s2 = float(((r[:, i] - X @ coef) ** 2).sum() / max(n - 2, 1))
            se = math.sqrt(s2 / ((t - t.mean()) ** 2).sum())
            trend[a] = {"slope_um_per_h": float(coef[1]), "stderr": se, "z": float(coef[1] / se) if se > 0 else 0.0}
    out["by_time"] = trend
    # by approach direction: mean residual along each axis for + and - approaches
    dirs = {}
    for i, a in enumerate(AXES):
        d = plan.direction[:, i]
        if (d > 0).any() and (d < 0).any():
            plus, minus = r[d > 0, i], r[d < 0, i]
            diff = plus.mean() - minus.mean()
            se = math.sqrt(plus.var(ddof=1) / len(plus) + minus.var(ddof=1) / len(minus)) if len(plus) > 1 and len(minus) > 1 else math.inf
            dirs[a] = {"plus_mean": float(plus.mean()), "minus_mean": float(minus.mean()), "difference": float(diff),
                       "stderr": se, "z": float(diff / se) if se > 0 else 0.0}
    out["by_direction"] = dirs
    # by axis position: residual along each axis vs its position (what a rigid model should have absorbed)
    pos = {}
    for i, a in enumerate(AXES):
        p = plan.nominal[:, i]
        if np.ptp(p) > 0:
            corr = [float(np.corrcoef(p, r[:, j])[0, 1]) if np.std(r[:, j]) > 0 else 0.0 for j in range(3)]
            pos[a] = {"correlation_with_residual_xyz": corr}
    out["by_position"] = pos
    # by temperature
    temp = {}
    for i, a in enumerate(AXES):
        T = ctx.axis_temperature_column(a)
        if T is not None and np.ptp(T) > 0:
            x = (T - ctx.recording.reference_temperature) * plan.nominal[:, i]
            if np.std(x) > 0:
                temp[a] = {"correlation": float(np.corrcoef(x, r[:, i])[0, 1]), "range_K": float(np.ptp(T))}
    out["by_temperature"] = temp
    worst = np.argsort(-chi_pt)[:5]
    out["worst_points"] = [{"row": int(k), "point": int(plan.point[k]), "run": int(plan.run[k]),
                            "residual": r[k].round(3).tolist(), "chi2": float(chi_pt[k])} for k in worst]
    return out


# --------------------------------------------------------------------- the diagnosis
@dataclass
class Finding:
    candidate: Candidate
    estimate: list
    uncertainty: list
    unit: str
    evidence: dict
    after: dict
    confounded_with: list = field(default_factory=list)
    hints: list = field(default_factory=list)  # measurements that would tell it from the confounded ones

    def to_dict(self) -> dict:
        scalar = len(self.estimate) == 1
        return {
            "effect": self.candidate.effect, "axis": self.candidate.axis, "plugin": self.candidate.plugin,
            "description": self.candidate.description,
            "estimate": {"value": self.estimate[0] if scalar else self.estimate, "unit": self.unit},
            "uncertainty": {"value": self.uncertainty[0] if scalar else self.uncertainty, "unit": self.unit},
            "evidence": self.evidence, "after": self.after, "confounded_with": self.confounded_with,
        }


@dataclass
class Diagnosis:
    recording: str
    baseline: dict
    mismatch: dict
    findings: list
    final: dict
    skipped: list
    untestable: list
    considered: list
    settings: dict
    residuals_before: np.ndarray | None = None
    residuals_after: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {"recording": self.recording, "baseline": self.baseline, "mismatch": self.mismatch,
                "findings": [f.to_dict() for f in self.findings], "final": self.final,
                "skipped": self.skipped, "not_testable": self.untestable, "considered": self.considered,
                "settings": self.settings}


def _quality(res) -> dict:
    return {"chi2_per_dof": float(res.chi2_per_dof[0]), "dof": int(res.dof),
            "rms": {"value": float(display(res.rms[0], "mm", "um")), "unit": "um"},
            "converged": res.n_not_converged == 0}


def diagnose(rec: Recording, candidates: list | None = None, *, alpha: float = 0.01, max_set: int = 3,
             confound_margin: float = 6.0, max_degree: int = 3, host=None) -> Diagnosis:
    """Diagnose a recording (see the module docstring)."""
    from .plugins import default_host

    if candidates is None:
        candidates = (host or default_host()).candidates()
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree)
    noise = Noise.of(rec)
    try:
        base = identify(model, rec.lt, noise)
    except MtbudgetError as exc:
        raise DiagnosisError(f"{rec.path or rec.name}: the baseline cannot be identified: {exc}") from None
    if base.dof < 10:
        raise DiagnosisError(f"{rec.path or rec.name}: only {base.dof} degrees of freedom are left after the baseline "
                             f"({len(rec)} points); measure more points or lower the error-function degrees")
    P_W = model.machine_points(base.theta)[0]
    ctx = DiagnosisContext(rec, model, base.pose[0], base.theta[0], P_W, lt.to_tracker(P_W[None], base.pose)[0])
    Wh = base.whitener[0]
    # the baseline's whitened design at its solution (pose + identifiable directions) and whitened residuals
    lin = _Linear(base.design[0], base.whitened[0].reshape(-1))
    n_obs = lin.n

    mismatch = locate(ctx, base.residual_machine[0], base.whitened[0])
    skipped, untestable, usable = [], [], []
    for c in candidates:
        _check_declaration(c)
        reason = _call(c, "requires", ctx)
        if reason is not None and not isinstance(reason, str):
            _fail(c, f"must return None or a reason (str), got {type(reason).__name__}", "requires")
        if reason:
            skipped.append({"effect": c.effect, "axis": c.axis, "reason": reason})
            continue
        raw = _columns(c, ctx)
        col = _whitened(raw, c.frame, ctx, Wh)
        left = np.linalg.norm(lin.project(col), axis=0) / np.maximum(np.linalg.norm(col, axis=0), 1e-300)
        if left.max() < ABSORBED:
            untestable.append({"effect": c.effect, "axis": c.axis,
                               "reason": "the baseline geometric errors absorb it completely with this plan "
                                         f"(what is left of it: {left.max():.1e})"})
            continue
        usable.append((c, col, raw))
    K = max(len(usable), 1)
    level = alpha / K  # Bonferroni over the candidates tested

    def fit(idx):
        return lin.fit([usable[i][1] for i in idx])

    def ftest(chi_small, chi_big, k, dof_big):
        if k <= 0 or dof_big <= 0:
            return 0.0, 1.0
        F = max(chi_small - chi_big, 0.0) / k / (chi_big / dof_big)
        return F, float(stats.f.sf(F, k, dof_big))

    def kcols(idx):
        return sum(usable[i][1].shape[1] for i in idx)

    def bic(idx, f):
        return f.chi2 + kcols(idx) * math.log(n_obs)

    considered = []
    single_sig = []
    for i, (c, col, _) in enumerate(usable):
        f = fit([i])
        k = col.shape[1]
        F, p = ftest(lin.chi2_0, f.chi2, k, lin.dof0 - k)
        considered.append({"effect": c.effect, "axis": c.axis, "delta_chi2": lin.chi2_0 - f.chi2, "F": F, "p_value": p,
                           "significant": p < level})
        if p < level:
            single_sig.append(i)
    # candidate sets: all subsets up to max_set of the individually significant ones, chosen by BIC,
    # each member significant given the others
    best, best_bic = (), bic((), fit(()))
    for size in range(1, min(max_set, len(single_sig)) + 1):
        for idx in itertools.combinations(single_sig, size):
            f = fit(list(idx))
            b = bic(idx, f)
            if b >= best_bic:
                continue
            ok = True
            for j in idx:
                rest = [i for i in idx if i != j]
                f_rest = fit(rest)
                dof = lin.dof0 - kcols(idx)
                _, p = ftest(f_rest.chi2, f.chi2, usable[j][1].shape[1], dof)
                if p >= level:
                    ok = False
                    break
            if ok:
                best, best_bic = idx, b
    # findings, each with its evidence, estimate and confounding alternatives
    chosen = list(best)
    f_all = fit(chosen)
    findings = []
    offsets = np.cumsum([0] + [usable[i][1].shape[1] for i in chosen])
    dof_all = lin.dof0 - kcols(chosen)
    for pos, i in enumerate(chosen):
        c = usable[i][0]
        sl = slice(offsets[pos], offsets[pos + 1])
        beta, cov = f_all.beta[sl], f_all.cov[sl, sl]
        scale = max(f_all.chi2 / dof_all, 1.0) if dof_all > 0 else 1.0  # inflate when the noise is understated
        rest = [j for j in chosen if j != i]
        f_rest = fit(rest)
        F, p = ftest(f_rest.chi2, f_all.chi2, len(beta), dof_all)
        d_bic = bic(rest, f_rest) - bic(chosen, f_all)
        conf, hints = [], []
        for j, (a, _, _) in enumerate(usable):
            if j in chosen:
                continue
            alt = rest + [j]
            f_alt = fit(alt)
            if bic(alt, f_alt) - bic(chosen, f_all) < confound_margin:
                conf.append({"effect": a.effect, "axis": a.axis, "delta_bic": bic(alt, f_alt) - bic(chosen, f_all)})
                hint = c.hints.get(a.effect) or a.hints.get(c.effect)
                if hint and hint not in hints:
                    hints.append(hint)
        est, unc, unit = _present(c, beta, cov * scale)
        stab = _stability(lin, usable, chosen, pos, ctx)
        findings.append(Finding(c, est, unc, unit, {
            "F": F, "p_value": p, "p_value_bonferroni": min(1.0, p * K), "delta_chi2": f_rest.chi2 - f_all.chi2,
            "delta_bic": d_bic, "candidates_tested": len(usable), "alpha": alpha, "by_run": stab}, {}, conf, hints))
    # refit the full model with the effects in it at their estimates: "after" each finding (cumulative)
    pert_parts, after = [], []
    for pos, i in enumerate(chosen):
        c, _, raw = usable[i]
        beta_int = f_all.beta[offsets[pos]:offsets[pos + 1]]
        pert_parts.append(_perturbation(c, ctx, beta_int, raw))
        res = identify(model, rec.lt, noise, fixed=merge(*pert_parts))
        findings[pos].after = _quality(res)
        after.append(findings[pos].after)
    final = after[-1] if after else _quality(base)
    res_after = res.residual_machine[0] if pert_parts else None
    return Diagnosis(rec.name, _quality(base), mismatch, findings, final, skipped, untestable, considered,
                     {"alpha": alpha, "bonferroni_level": level, "max_set": max_set, "confound_margin_bic": confound_margin,
                      "candidates": [c.label for c in candidates]},
                     residuals_before=base.residual_machine[0], residuals_after=res_after)


def _perturbation(c: Candidate, ctx: DiagnosisContext, beta: np.ndarray, columns: np.ndarray) -> dict:
    """The candidate's effect at ``beta`` as model perturbations (its own, or its ``columns`` times ``beta``
    as a displacement in its frame)."""
    pert = _call(c, "perturbation", ctx, beta)
    if pert is None:
        disp = columns @ beta  # (M, 3)
        return {("point_offset" if c.frame == "machine" else "tracker_offset"): disp[None]}
    if not isinstance(pert, dict) or not set(pert) <= set(MODEL_INPUTS):
        _fail(c, f"must return None or a dict with keys among {', '.join(MODEL_INPUTS)}, got "
                 f"{sorted(pert) if isinstance(pert, dict) else type(pert).__name__}", "perturbation")
    return pert


def _present(c: Candidate, beta, cov):
    """Estimate and standard uncertainty in the candidate's display unit: (list, list, unit)."""
    out = _call(c, "summary", beta, cov)
    if out is None:  # the default presentation: every column in its parameter's display unit
        try:
            out = Candidate.summary(c, beta, cov)
        except ValueError as exc:
            _fail(c, f"returned None, and the default cannot present it: {exc}", "summary")
    try:
        est, unc, unit = out
        est, unc = [float(x) for x in np.atleast_1d(est)], [float(x) for x in np.atleast_1d(unc)]
        ureg.Unit(unit)
    except Exception:
        _fail(c, f"must return (estimates, uncertainties, unit), got {out!r}", "summary")
    if len(est) != len(unc):
        _fail(c, f"returned {len(est)} estimates and {len(unc)} uncertainties", "summary")
    return est, unc, str(unit)


def _stability(lin, usable, chosen, pos, ctx):
    """The estimate from each run alone (the other runs' rows given no weight), in display units."""
    runs = np.unique(ctx.plan.run)
    if len(runs) < 2:
        return None
    out = {}
    c = usable[chosen[pos]][0]
    for k in runs:
        keep = np.repeat(ctx.plan.run == k, 3)
        A = lin.Q0[keep]
        Cs = [usable[i][1][keep] for i in chosen]
        Cm = np.concatenate(Cs, axis=1)
        Qk, _ = np.linalg.qr(A)
        Cp = Cm - Qk @ (Qk.T @ Cm)
        wk = lin.w[keep] - Qk @ (Qk.T @ lin.w[keep])
        beta, *_ = np.linalg.lstsq(Cp, wk, rcond=1e-10)
        cov = np.linalg.pinv(Cp.T @ Cp, rcond=1e-12)
        offsets = np.cumsum([0] + [usable[i][1].shape[1] for i in chosen])
        sl = slice(offsets[pos], offsets[pos + 1])
        est, unc, unit = _present(c, beta[sl], cov[sl, sl])
        out[int(k)] = {"estimate": est[0] if len(est) == 1 else est, "uncertainty": unc[0] if len(unc) == 1 else unc}
    return out
