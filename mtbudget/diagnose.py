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
   A set in which any estimate is physically implausible (outside the
   candidate's declared ``plausible`` range), or whose members are large and
   cancel each other, is never chosen.
   Every finding is then tested against explanations *outside* the library
   (:func:`_outside_alternatives`): the physical alternatives its candidate
   declares, and data-driven terms (alone and in pairs) built from the
   recording's own columns.  When the finding is not significant (level
   ``alpha``) with an alternative in its place, it is reported as confounded
   with that alternative, not named alone (an intersection-union test: a
   finding named alone beat every alternative at level ``alpha``).
   A chosen effect whose fitted displacement lies (nearly) in the span of a
   candidate rejected as implausible is a *stand-in* (:func:`_stand_ins`):
   never a finding; the recording is then NOT EXPLAINED.
   Periodic errors (along each axis, along the tracker's distance) and local
   reversals are searched by a family-wise calibrated scan
   (:mod:`mtbudget.diagnose_scan`); a term it finds becomes a candidate.
5. **After.** The chosen effects are put into the model at their estimates
   and the recording is identified again: chi-square and RMS before and after.

Several stations (docs/diagnose.md, "Several stations"): the baseline is
:func:`mtbudget.multistation.identify_stations` over all stations at once, and
:func:`mtbudget.multistation.linearise` gives its whitened design and residuals and
the per-row maps of a displacement to whitened residuals (3 per xyz row, 1 per
range row); selection, gate and data-driven search run on them unchanged.  The
findings are refitted by taking them out of the measurements; the residuals are
also located by station.

Noise and the fit gate (docs/diagnose.md, "Noise and the fit gate"):

* **Noise is estimated.**  The three variance components (tracker range,
  tracker transverse, machine repeatability) are estimated by REML from the
  error contrasts left after a saturated static model (one free position per
  point and tool: what repeated measurements of the same point disagree by;
  the identification's model added where those groups do not span it, as on a
  five-axis plan whose groups hold every commanded angle)
  plus every testable candidate.  A static unmodelled error cannot inflate
  them.  When a component differs from the stated one (beyond 3 standard
  errors and by more than 25 %), selection and the gate use the estimate.
* **Global goodness-of-fit gate.**  After selection, the misfit of the final
  model beyond that pure error is tested (lack-of-fit F-test; a chi-square
  test against the stated noise when no point is repeated).  When it fails,
  ``unexplained`` says how large the misfit is, where it lives, which
  candidates would have explained it with implausible values, and the best
  data-driven description: a sparse regression over terms built from the
  recording's own columns, selected on one half of the points and confirmed
  on the other.
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
from .machine import AXES, AXIS_INDEX
from .model import MODEL_INPUTS, MeasurementModel, merge
from .progress import Steps
from .recording import Recording
from .units import display, internal_unit_of, pretty, ureg

HOOK = "mtbudget_register_candidates"
#: a candidate of which less than this fraction (whitened norm) is left once the baseline has absorbed
#: what it can is not testable with the plan
ABSORBED = 1e-3


def json_unit(unit: str) -> str:
    """The one spelling of a unit in JSON output (docs/diagnose.md, "Units in JSON"): ASCII, parsed by
    :func:`mtbudget.units.parse_unit`, the same symbols as :func:`mtbudget.units.pretty` with ``u`` for micro
    and ``*`` for a product: "um", "um/h", "um/(m*K)", "urad", "m"."""
    text = pretty(str(unit)) if str(unit).strip() else ""
    for a, b in (("Δ°C", "delta_degC"), ("Δ°F", "delta_degF"), ("°C", "degC"), ("°F", "degF"), ("µ", "u"), ("μ", "u"),
                 ("·", "*"), ("²", "**2"), ("³", "**3"), ("^", "**")):
        text = text.replace(a, b)
    return text


def _implausible_entry(c: Candidate, reason: str, est: list, unc: list, unit: str) -> dict:
    """A candidate that would fit only with implausible values: the values and the plausible range (display units)."""
    scalar = len(est) == 1
    return {"effect": c.effect, "axis": c.axis, "plugin": c.plugin, "reason": reason,
            "estimate": {"value": est[0] if scalar else est, "unit": unit},
            "uncertainty": {"value": unc[0] if scalar else unc, "unit": unit},
            "plausible": [{"parameter": name, "quantity": c.quantity_names.get(name, name), "low": float(lo),
                           "high": float(hi), "unit": json_unit(c.parameters[name])}
                          for name, (lo, hi) in c.plausible.items() if name in c.parameters]}


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

    def __init__(self, A0: np.ndarray, w: np.ndarray, rowpt: np.ndarray | None = None):
        self.Q0, _ = np.linalg.qr(A0)
        self.w = w
        self.chi2_0 = float(w @ w)
        self.n, self.p0 = A0.shape
        #: the plan row of every whitened residual (one station: three per point, in order)
        self.rowpt = np.repeat(np.arange(self.n // 3), 3) if rowpt is None else np.asarray(rowpt)

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
def locate(ctx: DiagnosisContext, residual_machine: np.ndarray, whitened: np.ndarray, stations=None) -> dict:
    """Where the baseline residuals are structured (machine frame, um).

    whitened: (M, 3) for one station; for several, (n_res,) the whitened residuals with ``stations`` a
    :class:`_Stations` (the plan row of each, the stations, and each row's size and residuals per row):
    the summaries then count a range row as one residual, and ``by_station`` is added."""
    plan = ctx.plan
    r = display(residual_machine, "mm", "um")
    out: dict = {"unit": "um"}
    n = len(plan)
    if stations is None:
        chi_pt = (whitened**2).sum(axis=1)
        per_row = np.full(n, 3)
    else:
        chi_pt = np.bincount(stations.row, weights=whitened**2, minlength=n)
        per_row = stations.per_row
    # by run
    runs = {}
    for k in np.unique(plan.run):
        m = plan.run == k
        runs[int(k)] = {"points": int(m.sum()), "rms": float(np.sqrt((r[m] ** 2).sum(1).mean())),
                        "mean": r[m].mean(0).round(3).tolist(), "chi2_per_point": _per_residual(chi_pt, per_row, m)}
    out["by_run"] = runs
    # by tool (reflector holder)
    tools = {}
    t_rows = np.round(plan.tool, 6)
    uniq, first = np.unique(t_rows, axis=0, return_index=True)
    for k, j in enumerate(sorted(first), start=1):
        m = np.all(t_rows == t_rows[j], axis=1)
        tools[k] = {"tool": display(plan.tool[j], "mm", "mm").round(3).tolist(), "tool_unit": "mm", "points": int(m.sum()),
                    "rms": float(np.sqrt((r[m] ** 2).sum(1).mean())), "mean": r[m].mean(0).round(3).tolist(),
                    "chi2_per_point": _per_residual(chi_pt, per_row, m)}
    out["by_tool"] = tools
    # by time: slope of each component (um/h) with its standard error
    t = display(plan.time, "s", "h")
    trend = {}
    if np.ptp(t) > 0:
        X = np.column_stack([np.ones(n), t - t.mean()])
        for i, a in enumerate(AXES):
            coef, res, *_ = np.linalg.lstsq(X, r[:, i], rcond=None)
            s2 = float(((r[:, i] - X @ coef) ** 2).sum() / max(n - 2, 1))
            se = math.sqrt(s2 / ((t - t.mean()) ** 2).sum())
            trend[a] = {"slope_um_per_h": float(coef[1]), "stderr": se, "z": float(coef[1] / se) if se > 0 else 0.0,
                        "unit": "um/h"}
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
    if stations is not None:
        sid = stations.row_station
        for w in out["worst_points"]:
            w["station"] = int(sid[w["row"]])
        out["by_station"] = _by_station(stations, chi_pt, residual_machine)
    return out


def _per_residual(chi_pt, per_row, m) -> float:
    """Chi-square per whitened residual of the rows ``m`` (three per xyz row, one per range row)."""
    return float(chi_pt[m].sum() / max(per_row[m].sum(), 1))


def _by_station(stations, chi_pt, residual_machine) -> dict:
    """Residual summaries per station, in um: RMS and mean along the beam (what a range offset of the station
    would shift), the mean residual in the station's own frame (xyz) and the chi-square per residual."""
    out = {}
    r_st = np.einsum("mji,mj->mi", stations.rotation, residual_machine)  # R^T r: into each row's station frame
    for st in stations.stations:
        m = stations.row_station == st.id
        along = (r_st[m] * stations.beam[m]).sum(axis=1)
        um = display(along, "mm", "um")
        entry = {"kind": st.kind, "rows": int(m.sum()),
                 "rms": float(display(np.sqrt(np.mean(stations.size[m] ** 2)), "mm", "um")),
                 "mean_along_beam": float(um.mean()),
                 "mean_along_beam_stderr": float(um.std(ddof=1) / math.sqrt(len(um))) if len(um) > 1 else None,
                 "chi2_per_residual": _per_residual(chi_pt, stations.per_row, m)}
        if st.kind == "xyz":
            entry["mean_station_frame"] = display(r_st[m].mean(0), "mm", "um").round(3).tolist()
        out[int(st.id)] = entry
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
    #: explanations outside the library that fit about as well (:func:`_outside_alternatives`)
    outside: list = field(default_factory=list)
    #: what a data-driven term adds (period and its uncertainty, the region of a local reversal) or whether a
    #: reversal is uniform along its axis (:mod:`mtbudget.diagnose_scan`)
    details: dict = field(default_factory=dict)

    @property
    def named_alone(self) -> bool:
        """Neither another candidate nor an alternative outside the library fits about as well."""
        return not self.confounded_with and not self.outside

    def to_dict(self) -> dict:
        scalar = len(self.estimate) == 1
        return {
            "effect": self.candidate.effect, "axis": self.candidate.axis, "plugin": self.candidate.plugin,
            "description": self.candidate.description,
            "estimate": {"value": self.estimate[0] if scalar else self.estimate, "unit": self.unit},
            "uncertainty": {"value": self.uncertainty[0] if scalar else self.uncertainty, "unit": self.unit},
            "evidence": self.evidence, "after": self.after, "confounded_with": self.confounded_with,
            "confounded_outside_library": self.outside, "named_alone": self.named_alone, "details": self.details,
            "status": ("named" if self.named_alone else
                       "confounded with an alternative outside the library" if self.outside else
                       "confounded with another candidate"),
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
    noise: dict = field(default_factory=dict)
    unexplained: dict | None = None
    #: effects that fit only like a candidate rejected as implausible (:func:`_stand_ins`): never findings
    stand_ins: list = field(default_factory=list)
    #: the scan of periodic and local terms (:mod:`mtbudget.diagnose_scan`): each pass, its test and its result
    scan: list = field(default_factory=list)
    #: every approach-direction difference the mismatch summary reports (|z| > :data:`DIRECTION_Z`) and what accounts
    #: for it (:func:`_direction_accounts`): never left unexplained silently
    directions: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"recording": self.recording, "baseline": self.baseline, "mismatch": self.mismatch,
                "findings": [f.to_dict() for f in self.findings], "final": self.final,
                "skipped": self.skipped, "not_testable": self.untestable, "considered": self.considered,
                "settings": self.settings, "noise": self.noise, "unexplained": self.unexplained,
                "stand_ins": self.stand_ins, "scan": self.scan, "direction_differences": self.directions}


def _quality(res) -> dict:
    return {"chi2_per_dof": float(res.chi2_per_dof[0]), "dof": int(res.dof),
            "rms": {"value": float(display(res.rms[0], "mm", "um")), "unit": "um"},
            "converged": res.n_not_converged == 0}


def diagnose(rec: Recording, candidates: list | None = None, *, alpha: float = 0.01, max_set: int = 3,
             confound_margin: float = 6.0, max_degree: int = 3, host=None, gate_alpha: float = 0.01,
             data_driven: bool = True, progress: bool = False) -> Diagnosis:
    """Diagnose a recording (see the module docstring).

    A recording of several stations (format 2: several xyz stations, or range stations; read with
    ``read_recording(folder, several_stations=True)``) is diagnosed over all of them at once: the baseline is
    :func:`mtbudget.multistation.identify_stations` (docs/diagnose.md, "Several stations").

    progress: a bar on stderr naming the running step (baseline fit, candidate columns, noise estimate,
    candidate scan, refit with the findings, fit gate, data-driven search); silent by default, and never on
    stdout, so ``--json`` stays one object.
    """
    from .plugins import default_host

    if candidates is None:
        candidates = (host or default_host()).candidates()
    steps = Steps(5 + len(candidates), f"diagnose {rec.name}", progress)
    run = _diagnose_stations if rec.several_stations else _diagnose
    try:
        return run(rec, candidates, alpha, max_set, confound_margin, max_degree, gate_alpha, data_driven, steps)
    finally:
        steps.close()


def _candidate_columns(candidates, ctx, lin0, whiten, steps):
    """Every candidate's whitened columns, or why it is skipped or not testable: (skipped, untestable, usable)."""
    skipped, untestable, usable = [], [], []
    for c in candidates:
        steps.begin(f"candidate columns: {c.label}")
        steps.done()
        _check_declaration(c)
        reason = _call(c, "requires", ctx)
        if reason is not None and not isinstance(reason, str):
            _fail(c, f"must return None or a reason (str), got {type(reason).__name__}", "requires")
        if reason:
            skipped.append({"effect": c.effect, "axis": c.axis, "reason": reason})
            continue
        raw = _columns(c, ctx)
        col = whiten(raw, c.frame)
        left = np.linalg.norm(lin0.project(col), axis=0) / np.maximum(np.linalg.norm(col, axis=0), 1e-300)
        if left.max() < ABSORBED:
            untestable.append({"effect": c.effect, "axis": c.axis,
                               "reason": "the baseline geometric errors absorb it completely with this plan "
                                         f"(what is left of it: {left.max():.1e})"})
            continue
        # a column the baseline absorbs (almost) completely carries no information: it is left out of the fit
        # (its parameter stays 0), or a noise-driven, physically absurd value would enter the refit
        raw = raw.copy()
        raw[:, :, left < ABSORBED] = 0.0
        col = col.copy()
        col[:, left < ABSORBED] = 0.0
        usable.append((c, col, raw))
    return skipped, untestable, usable


class _Selector:
    """Nested fits of candidate sets on one whitened linear model: F-tests, BIC, plausibility, cancellation."""

    def __init__(self, lin, usable, exclude=()):
        self.lin, self.usable = lin, usable
        #: candidates never chosen (stand-ins for an implausible one): still fitted, still listed in ``considered``
        self.exclude = dict(exclude) if isinstance(exclude, dict) else {i: "excluded" for i in exclude}

    def fit(self, idx):
        return self.lin.fit([self.usable[i][1] for i in idx])

    @staticmethod
    def ftest(chi_small, chi_big, k, dof_big):
        if k <= 0 or dof_big <= 0:
            return 0.0, 1.0
        F = max(chi_small - chi_big, 0.0) / k / (chi_big / dof_big)
        return F, float(stats.f.sf(F, k, dof_big))

    def kcols(self, idx):
        return sum(self.usable[i][1].shape[1] for i in idx)

    def bic(self, idx, f):
        return f.chi2 + self.kcols(idx) * math.log(self.lin.n)

    def members(self, idx, f):
        """(beta, cov) of each member of the set ``idx`` in the joint fit ``f`` (cov inflated by chi2/dof > 1)."""
        dof = self.lin.dof0 - self.kcols(idx)
        scale = max(f.chi2 / dof, 1.0) if dof > 0 else 1.0
        out, o = [], 0
        for i in idx:
            k = self.usable[i][1].shape[1]
            out.append((f.beta[o:o + k], f.cov[o:o + k, o:o + k] * scale))
            o += k
        return out

    def implausible(self, i, beta, cov):
        why = _call(self.usable[i][0], "implausible", beta, cov)
        if why is not None and not isinstance(why, str):
            _fail(self.usable[i][0], f"must return None or a sentence (str), got {type(why).__name__}", "implausible")
        return why

    def cancelling(self, idx, f):
        """Members that are large and cancel each other: the sum of their sizes far beyond the size of their sum."""
        if len(idx) < 2:
            return False
        parts, o = [], 0
        for i in idx:
            k = self.usable[i][1].shape[1]
            parts.append(self.lin.project(self.usable[i][1]) @ f.beta[o:o + k])
            o += k
        return sum(np.linalg.norm(x) for x in parts) > CANCEL * max(np.linalg.norm(sum(parts)), 1e-300)

    def scan(self, level, max_set):
        """Each candidate alone (F-test at ``level``), then all subsets up to ``max_set`` of the significant ones
        by BIC, each member significant given the others and plausible, the members not cancelling each other.

        Returns (considered, chosen, implausible_alone)."""
        lin, usable = self.lin, self.usable
        considered, single_sig, implausible_alone = [], [], {}
        for i, (c, col, _) in enumerate(usable):
            f = self.fit([i])
            k = col.shape[1]
            F, p = self.ftest(lin.chi2_0, f.chi2, k, lin.dof0 - k)
            why = self.implausible(i, *self.members([i], f)[0]) if p < level else None
            left = float(np.linalg.norm(lin.project(col)) / max(np.linalg.norm(col), 1e-300))
            considered.append({"effect": c.effect, "axis": c.axis, "delta_chi2": lin.chi2_0 - f.chi2, "F": F,
                               "p_value": p, "significant": p < level, "implausible": why,
                               "left_by_baseline": left})
            if i in self.exclude:
                considered[-1]["excluded"] = self.exclude[i]  # "stand-in", "replaced" (by a local reversal), ...
                considered[-1]["stand_in"] = self.exclude[i] == "stand-in"
                if p < level and why:
                    implausible_alone[i] = why
                continue
            if p < level:
                single_sig.append(i)
                if why:
                    implausible_alone[i] = why
        best, best_bic = (), self.bic((), self.fit(()))
        for size in range(1, min(max_set, len(single_sig)) + 1):
            for idx in itertools.combinations(single_sig, size):
                f = self.fit(list(idx))
                b = self.bic(idx, f)
                if b >= best_bic:
                    continue
                ok = True
                for j, (beta, cov) in zip(idx, self.members(idx, f)):
                    rest = [i for i in idx if i != j]
                    f_rest = self.fit(rest)
                    dof = lin.dof0 - self.kcols(idx)
                    _, p = self.ftest(f_rest.chi2, f.chi2, usable[j][1].shape[1], dof)
                    if p >= level or self.implausible(j, beta, cov):
                        ok = False
                        break
                if ok and not self.cancelling(idx, f):
                    best, best_bic = idx, b
        return considered, list(best), implausible_alone


def _unexplained(gate, est, where, sel, implausible_alone, chosen, notes) -> dict:
    usable = sel.usable
    return {
        "chi2_per_dof": gate["chi2_per_dof"], "dof": gate["dof"], "p_value": gate["p_value"], "test": gate["test"],
        "noise_used": est["used"], "lack_of_fit": gate.get("lack_of_fit"),
        "where": {k: where[k] for k in ("by_run", "by_tool", "by_time", "by_direction", "by_position",
                                        "by_temperature", "worst_points", "by_station") if k in where},
        "implausible": [_implausible_entry(usable[i][0], why, *_present(usable[i][0], *sel.members([i], sel.fit([i]))[0]))
                        for i, why in implausible_alone.items() if i not in chosen],
        "notes": notes, "data_driven": None,
    }


def _diagnose(rec, candidates, alpha, max_set, confound_margin, max_degree, gate_alpha, data_driven, steps):
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree)
    noise = Noise.of(rec)
    steps.begin("baseline fit")
    try:
        base = identify(model, rec.lt, noise, fixed=rec.fixed_inputs())  # the scales' stated expansion is known
    except MtbudgetError as exc:
        raise DiagnosisError(f"{rec.path or rec.name}: the baseline cannot be identified: {exc}") from None
    if base.dof < 10:
        raise DiagnosisError(f"{rec.path or rec.name}: only {base.dof} degrees of freedom are left after the baseline "
                             f"({len(rec)} points); measure more points or lower the error-function degrees")
    P_W = model.machine_points(base.theta, rec.fixed_inputs())[0]
    ctx = DiagnosisContext(rec, model, base.pose[0], base.theta[0], P_W, lt.to_tracker(P_W[None], base.pose)[0])
    Wh = base.whitener[0]
    # the baseline's whitened design at its solution (pose + identifiable directions) and whitened residuals
    lin0 = _Linear(base.design[0], base.whitened[0].reshape(-1))

    mismatch = locate(ctx, base.residual_machine[0], base.whitened[0])
    steps.done()
    expanded = _expand_per_rotary_axis(candidates, ctx)
    steps.more(len(expanded) - len(candidates))
    candidates = expanded
    skipped, untestable, usable = _candidate_columns(candidates, ctx, lin0,
                                                     lambda raw, frame: _whitened(raw, frame, ctx, Wh), steps)

    # the noise: estimated from the data, used for selection and the gate when the stated one does not match
    steps.begin("noise estimate (REML)")
    est = _estimate_noise(rec, ctx, Wh, base.design[0], lin0.w, [u[1] for u in usable])
    Wn = est.pop("whitener")  # (M, 3, 3) the whitener selection and the gate use
    groups_design = est.pop("groups")
    if est["used"] == "estimated":
        T = np.einsum("mij,mjk->mik", Wn, np.linalg.inv(Wh))

        def tr(v):
            return np.einsum("mij,mjk->mik", T, v.reshape(len(T), 3, -1)).reshape(3 * len(T), -1)

        lin = _Linear(tr(base.design[0]), tr(lin0.w)[:, 0])
        usable = [(c, _whitened(raw, c.frame, ctx, Wn), raw) for c, _, raw in usable]
    else:
        lin = lin0
    steps.done()
    steps.begin(f"candidate scan ({len(usable)} candidates, sets up to {max_set}; periodic and local terms)")
    whiten_n = lambda raw, frame: _whitened(raw, frame, ctx, Wn)  # noqa: E731
    usable, sel, considered, chosen, implausible_alone, level, K, scan_log, stand_ins = _select(
        ctx, lin, usable, alpha, max_set, whiten_n)
    steps.done()
    steps.begin(f"refit with the findings ({len(chosen)})")
    findings, f_all = _findings(chosen, sel, round(alpha / level), alpha, confound_margin, ctx, whiten_n)
    _scan_details(findings, chosen, sel, ctx, whiten_n, scan_log)
    # refit the full model with the effects in it at their estimates: "after" each finding (cumulative)
    offsets = np.cumsum([0] + [usable[i][1].shape[1] for i in chosen])
    pert_parts, after, res = [], [], base
    for pos, i in enumerate(chosen):
        c, _, raw = usable[i]
        beta_int = f_all.beta[offsets[pos]:offsets[pos + 1]]
        pert_parts.append(_perturbation(c, ctx, beta_int, raw))
        res = identify(model, rec.lt, noise, fixed=merge(rec.fixed_inputs(), *pert_parts))
        findings[pos].after = _quality(res)
        after.append(findings[pos].after)
    notes = []
    if findings and res.chi2[0] > base.chi2[0]:
        # the effects at their estimates fit worse than no effect: the linear selection was misled; claim nothing
        notes.append("the effects the selection chose fit worse than the baseline once put into the full model "
                     f"(chi-square per dof {float(res.chi2_per_dof[0]):.3f} vs {float(base.chi2_per_dof[0]):.3f}); "
                     "none is reported")
        chosen, findings, after, pert_parts, res = [], [], [], [], base
        f_all = sel.fit([])
    final = after[-1] if after else _quality(base)
    res_after = res.residual_machine[0] if pert_parts else None

    # the global goodness-of-fit gate, and what is left when it fails; `where` then describes the baseline's
    # residuals, as `final` does (what the partial effects leave is kept beside it)
    pure = _group_design(groups_design, Wn) if groups_design is not None else None
    unexplained, findings, final, res_after = _gate_and_unexplained(
        steps, ctx, lin, sel, f_all, chosen, usable, est, pure, gate_alpha, implausible_alone, notes, findings, final,
        res_after, where_now=lambda: locate(ctx, res.residual_machine[0], res.whitened[0]),
        base_quality=lambda: _quality(base), where_base=lambda: locate(ctx, base.residual_machine[0], base.whitened[0]),
        whiten=lambda raw, frame: _whitened(raw, frame, ctx, Wn), data_driven=data_driven, alpha=alpha)
    if stand_ins:
        unexplained, findings, final, res_after = _stand_in_verdict(
            unexplained, stand_ins, lin, sel, f_all, chosen, est, implausible_alone, notes, findings, final, res_after,
            where_base=lambda: locate(ctx, base.residual_machine[0], base.whitened[0]),
            base_quality=lambda: _quality(base))
    directions = _direction_accounts(
        ctx.plan, mismatch, sel, findings, skipped, untestable, unexplained, alpha, level,
        after=lambda: locate(ctx, res.residual_machine[0], res.whitened[0]) if findings else None)
    return Diagnosis(rec.name, _quality(base), mismatch, findings, final, skipped, untestable, considered,
                     _settings(rec, candidates, alpha, level, max_set, confound_margin, gate_alpha,
                               scan_level=alpha - level * K if scan_log else 0.0),
                     residuals_before=base.residual_machine[0], residuals_after=res_after,
                     noise=est, unexplained=unexplained, stand_ins=stand_ins, scan=scan_log, directions=directions)


#: a finding whose fitted displacement lies in the span of a candidate rejected as implausible to within this fraction
#: (whitened norm outside the span over its norm, both cleared of the rest of the model: 0.2 is 96 % of its energy
#: inside) stands in for it.  A looser rule (0.3, or "not significant given it") took true effects whose implausible
#: twin fits as well: thermal_expansion[z] for a negative spindle growth (27 % outside) in 4 of 30 calibration cases
NEARLY_IN_SPAN = 0.2
#: passes of the scan of periodic and local terms (each may add one term)
SCAN_PASSES = 2


def _select(ctx, lin, usable, alpha, max_set, whiten, scan_terms=True):
    """Selection over the library, the stand-in rule and the scan of periodic and local terms.

    The family-wise level ``alpha`` is shared by Bonferroni between the K library candidates and the F families of
    the scan (:mod:`mtbudget.diagnose_scan`): each candidate at alpha / (K + F), the scan (one max-statistic over all
    its families) at alpha F / (K + F).  A term the scan finds becomes a candidate and selection runs again (a local
    reversal replaces the uniform one of its axis); a chosen effect that stands in for a candidate rejected as
    implausible (:func:`_stand_ins`) is excluded and selection runs again.

    Returns (usable, selector, considered, chosen, implausible_alone, level, K, scan log, stand-ins)."""
    from . import diagnose_scan as ds

    fams = ds.families(ctx)[0] if scan_terms else []
    K = max(len(usable), 1)
    level = alpha / (K + len(fams))
    scan_level = alpha * len(fams) / (K + len(fams))
    usable = list(usable)
    exclude: dict = {}  # usable index -> "stand-in" or "replaced"
    log, stand_ins, passes, added = [], [], 0, None
    for _ in range(3 * (SCAN_PASSES + 2)):
        sel = _Selector(lin, usable, exclude)
        considered, chosen, implausible_alone = sel.scan(level, max_set)
        new = _stand_ins(sel, chosen, implausible_alone, alpha)
        if new:
            for i, entry in new:
                exclude[i] = "stand-in"
                stand_ins.append(entry)
            continue
        if added is not None and added not in chosen:
            log[-1]["note"] = "the term found was not chosen by selection (BIC, significance given the others, " \
                              "plausibility): the scan stops"
            restore = [m for m, why in exclude.items() if why == "replaced"]
            if restore:  # the uniform reversal it would have replaced comes back
                for m in restore:
                    del exclude[m]
                exclude[added] = "not chosen"
                sel = _Selector(lin, usable, exclude)
                considered, chosen, implausible_alone = sel.scan(level, max_set)
            break
        if not fams or passes >= SCAN_PASSES:
            break
        passes += 1
        X = np.concatenate([lin.Q0] + [usable[i][1] for i in chosen], axis=1)
        res = ds.scan(ctx, X, lin.w, whiten, scan_level)
        best = res.pop("_best")
        res["pass"] = passes
        res["model"] = [usable[i][0].label for i in chosen]
        log.append(res)
        if not res["found"] or best is None:
            break
        kind, axis, vals, j, k, frame, info, entry = best
        if kind == "periodic":
            span = float(np.ptp(np.linalg.norm(ctx.P_LT, axis=1) if axis == "range"
                                else ctx.plan.nominal[:, AXIS_INDEX[axis]]))
            period = ds.refine_period(ctx, X, lin.w, whiten, axis, 1 / vals[j], span)
            c = ds.PeriodicError(axis, period)
            res["added"] = f"periodic_error[{axis}], period {period:.4g} mm"
        else:
            c = ds.PiecewiseReversal(axis, vals[j], info)
            for m, (u, _, _) in enumerate(usable):  # the local reversal replaces the uniform one of its axis
                if u.effect == "reversal" and u.axis == axis and m not in exclude:
                    exclude[m] = "replaced"
            res["added"] = f"reversal[{axis}] local, boundary {axis} = {vals[j]:.6g} mm"
        c.plugin = "mtbudget (diagnosis scan)"
        _check_declaration(c)
        raw = _columns(c, ctx)
        usable.append((c, whiten(raw, c.frame), raw))
        added = len(usable) - 1
    return usable, sel, considered, chosen, implausible_alone, level, K, log, stand_ins


def _stand_ins(sel, chosen, implausible_alone, alpha) -> list:
    """Chosen effects that stand in for a candidate rejected as implausible: the finding's fitted displacement lies
    (nearly) in the span of that candidate's columns (less than :data:`NEARLY_IN_SPAN` of it outside, the rest of
    the chosen set cleared), and that candidate fits at least as well.  Such an effect is only "what fits like X,
    which would need an implausible size": never a finding.  The entry keeps the partial F-test of the finding given
    that candidate in its place (level ``alpha``) as evidence.
    Returns [(usable index, entry)]."""
    lin, usable = sel.lin, sel.usable
    out = []
    cand = [j for j in implausible_alone if j not in chosen]
    if not cand:
        return out
    for pos, i in enumerate(chosen):
        rest = [j for j in chosen if j != i]
        Qr = _orth(np.concatenate([lin.Q0] + [usable[j][1] for j in rest], axis=1))

        def clear(Y):
            return Y - Qr @ (Qr.T @ Y)

        w = clear(lin.w[:, None])[:, 0]
        Cc = clear(usable[i][1])
        QC = _orth(Cc)
        sig = QC @ (QC.T @ w)  # the finding's fitted displacement (whitened)
        dof_rest = lin.n - Qr.shape[1]
        for j in cand:
            A = clear(usable[j][1])
            QA = _orth(A)
            outside = float(np.linalg.norm(sig - QA @ (QA.T @ sig)) / max(np.linalg.norm(sig), 1e-300))
            chi_j, _, F, dof, p = _given(w, Cc, A, dof_rest)
            # j fits what is left at least as well as the finding does: the data look like j at least as much
            chi_i = float(w @ w - sig @ sig)
            as_well = chi_j <= chi_i + 1e-9 * max(chi_i, 1.0)
            if as_well and outside < NEARLY_IN_SPAN:
                c, x = usable[i][0], usable[j][0]
                est, unc, unit = _present(c, *sel.members(chosen, sel.fit(chosen))[pos])
                why = implausible_alone[j]
                out.append((i, {
                    "effect": c.effect, "axis": c.axis, "plugin": c.plugin, "description": c.description,
                    "estimate": {"value": est[0] if len(est) == 1 else est, "unit": unit},
                    "uncertainty": {"value": unc[0] if len(unc) == 1 else unc, "unit": unit},
                    "fits_like": {"effect": x.effect, "axis": x.axis, "reason": why},
                    "outside_span": outside,
                    "test": {"F": float(F), "dof": list(dof), "p_value": float(p), "level": alpha},
                    "separating_measurement": c.hints.get(x.effect) or x.hints.get(c.effect),
                    "sentence": f"fits like {x.label}, which would need an implausible size ({why}): not a finding"}))
                break
    return out


def _stand_in_verdict(unexplained, stand_ins, lin, sel, f_all, chosen, est, implausible_alone, notes, findings, final,
                      res_after, *, where_base, base_quality):
    """A recording with a significant effect that fits only like a candidate rejected as implausible is not
    explained, whatever the gate says: the structure is there, and no plausible candidate is named for it alone."""
    if unexplained is None:
        dof = lin.dof0 - sel.kcols(chosen)
        gate = {"chi2_per_dof": f_all.chi2 / dof if dof > 0 else math.nan, "dof": int(dof),
                "p_value": None,
                "test": "an effect significant at the family-wise level fits only like a candidate rejected as "
                        "implausible (stand_ins): the fit gate passed, but no plausible candidate is named for it"}
        unexplained = _unexplained(gate, est, where_base(), sel, implausible_alone, chosen, notes)
        if findings:
            findings, final, res_after = _demote(unexplained, findings, base_quality)
    unexplained["stand_ins"] = stand_ins
    unexplained["notes"].append(f"{len(stand_ins)} effect(s) fit only like a candidate rejected as implausible "
                                "(stand_ins); none is reported as a finding")
    return unexplained, findings, final, res_after


def _scan_details(findings, chosen, sel, ctx, whiten, scan_log):
    """What the scan adds to the findings: a periodic error's period with its uncertainty, amplitude and phase; a
    local reversal's region; a uniform reversal's test of uniformity along its axis."""
    from . import diagnose_scan as ds

    lin, usable = sel.lin, sel.usable
    last = scan_log[-1] if scan_log else None
    for pos, (f, i) in enumerate(zip(findings, chosen)):
        c = f.candidate
        if isinstance(c, ds.PeriodicError):
            rest = [j for j in chosen if j != i]
            X = np.concatenate([lin.Q0] + [usable[j][1] for j in rest], axis=1)
            u_p, amp, phase = ds.period_uncertainty(ctx, X, lin.w, whiten, c)
            f.details = {"kind": "periodic", "along": "the beam (tracker distance)" if c.axis == "range" else c.axis,
                         "period": {"value": c.period, "unit": "mm"},
                         "period_uncertainty": {"value": u_p, "unit": "mm"},
                         "amplitude": {"value": f.estimate[0], "unit": f.unit},
                         "amplitude_uncertainty": {"value": f.uncertainty[0], "unit": f.unit},
                         "phase": {"value": phase, "unit": "rad",
                                   "convention": "A sin(2 pi u / period + phase), u the position (mm) from 0"},
                         "scan": next((x for x in scan_log if x.get("added", "").startswith(c.label)), None)}
        elif isinstance(c, ds.PiecewiseReversal):
            lo, hi = c.span
            big = int(np.argmax(np.abs(f.estimate)))
            region = (f"{c.axis} from {lo:g} to {c.boundary:g} mm" if big == 0 else
                      f"{c.axis} from {c.boundary:g} to {hi:g} mm")
            sig = [abs(e) > 2 * u for e, u in zip(f.estimate, f.uncertainty)]
            f.details = {"kind": "local", "uniform": False, "boundary": {"value": c.boundary, "unit": "mm"},
                         "below": {"value": f.estimate[0], "uncertainty": f.uncertainty[0], "unit": f.unit},
                         "above": {"value": f.estimate[1], "uncertainty": f.uncertainty[1], "unit": f.unit},
                         "region": region,
                         "sentence": (f"local: the lost motion is {f.estimate[big]:.3g} +- {f.uncertainty[big]:.2g} "
                                      f"{f.unit} (k = 1) for {region}" +
                                      (f", {f.estimate[1 - big]:.3g} +- {f.uncertainty[1 - big]:.2g} {f.unit} "
                                       "elsewhere" + (" (not significant)" if not sig[1 - big] else ""))),
                         "scan": next((x for x in scan_log if x.get("added", "").startswith(f"reversal[{c.axis}]")),
                                      None)}
        elif c.effect == "reversal" and last is not None:
            fam = next((x for x in last["families"] if x["term"] == "local_reversal" and x["axis"] == c.axis), None)
            if fam is not None:
                f.details = {"kind": "uniform", "uniform": True,
                             "sentence": f"uniform along {c.axis}: the scan of local reversals found no part of the "
                                         f"axis that differs (family-wise p {'>=' if last.get('p_value_bound') == 'lower' else '='} {last['p_value']:.2g}, level "
                                         f"{last['level']:.2g})",
                             "local_scan": fam}


def _settings(rec, candidates, alpha, level, max_set, confound_margin, gate_alpha, **more) -> dict:
    """The ``settings`` of a diagnosis: the levels, the candidates, the correction applied, and ``more``."""
    return {"alpha": alpha, "bonferroni_level": level, "max_set": max_set, "confound_margin_bic": confound_margin,
            "gate_alpha": gate_alpha, "candidates": [c.label for c in candidates],
            "thermal_correction": rec.thermal_correction, "outside_library": _outside_settings(alpha), **more}


def _gate_and_unexplained(steps, ctx, lin, sel, f_all, chosen, usable, est, pure, gate_alpha, implausible_alone,
                          notes, findings, final, res_after, *, where_now, base_quality, where_base, whiten,
                          data_driven, alpha):
    """The global goodness-of-fit gate of the final model and, when it fails, what is left (:func:`_unexplained`):
    the findings demoted to partial (their quality and location then the baseline's: ``base_quality()``,
    ``where_base()``), and the data-driven description.  Returns (unexplained or None, findings, final,
    residuals after)."""
    steps.done()
    steps.begin("fit gate")
    gate = _gate(lin, f_all, sel.kcols(chosen), est, pure, usable, gate_alpha)
    steps.done()
    if gate["explained"]:
        return None, findings, final, res_after
    unexplained = _unexplained(gate, est, where_now(), sel, implausible_alone, chosen, notes)
    if findings:
        findings, final, res_after = _demote(unexplained, findings, base_quality)
        w0 = where_base()
        unexplained["where"] = {k: w0[k] for k in unexplained["where"]}
    if data_driven and gate["p_value"] is not None:
        X_final = np.concatenate([lin.Q0] + [usable[i][1] for i in chosen], axis=1)
        splits = 20
        steps.more(splits)
        steps.begin("data-driven search")
        unexplained["data_driven"] = _data_driven(ctx, lin, X_final, whiten, alpha, splits, on_split=steps.done)
    return unexplained, findings, final, res_after


def _demote(unexplained, findings, base_quality):
    """Effects that leave the recording unexplained are not findings: the structure they mimic may be physics
    outside the library (a tool-length error fitted as a drift); they are reported as partial."""
    unexplained["partial"] = [dict(f.to_dict(), why_not_a_finding=(
        "significant and plausible, but the recording stays unexplained with it: what it fits may be "
        "physics outside the library that it only resembles")) for f in findings]
    unexplained["notes"].append(f"{len(findings)} candidate(s) would explain part of the misfit "
                                "(unexplained.partial); none is reported as a finding")
    unexplained["where_after_partial"] = unexplained["where"]
    return [], base_quality(), None


# --------------------------------------------------------------------- several stations
@dataclass
class StationsDiagnosisContext(DiagnosisContext):
    """A :class:`~mtbudget.contracts.DiagnosisContext` for a recording of several stations.

    ``pose`` is the first xyz station's pose (zeros when there is none); ``P_LT`` holds each row's predicted point
    in its own station's frame (a range station: the vector from the station to the point, machine axes), so a
    candidate in the "tracker" frame acts in each row's station frame; a range row sees a displacement along its
    beam only.  ``stations`` ([:class:`mtbudget.recording.Station`]) and ``row_station`` (M,) say which station
    measured every row."""

    stations: list = field(default_factory=list)
    row_station: np.ndarray | None = None


@dataclass
class _Stations:
    """What :func:`locate` needs to summarise the residuals of several stations."""

    stations: list
    row_station: np.ndarray
    row: np.ndarray  # (n_res,) plan row of each whitened residual
    per_row: np.ndarray  # (M,) whitened residuals per row
    rotation: np.ndarray  # (M, 3, 3)
    beam: np.ndarray  # (M, 3) station frame
    size: np.ndarray  # (M,) mm


def _station_quality(res, L) -> dict:
    """chi2/dof, dof, RMS (um: the root mean square over the rows of each row's residual size: 3-D for an xyz row,
    the range residual for a range row) and convergence of an identification over several stations."""
    return {"chi2_per_dof": float(res.chi2_per_dof), "dof": int(res.dof),
            "rms": {"value": float(display(np.sqrt(np.mean(L.residual_size**2)), "mm", "um")), "unit": "um"},
            "converged": bool(res.converged)}


def _stations_whitener(L, scale=None):
    """Columns (M, 3, k) in ``frame`` -> whitened columns (n_res, k) of a recording of several stations; ``scale``
    (n_res,) multiplies each whitened residual (the estimated noise)."""
    def whiten(C, frame):
        op = L.machine if frame == "machine" else L.station
        out = np.einsum("nj,njk->nk", op, np.asarray(C, float)[L.row])
        return out if scale is None else out * scale[:, None]
    return whiten


def _expand(candidates, ctx, method: str):
    """A candidate with a ``method(ctx)`` (``per_station``: one candidate per station of the recording;
    ``per_rotary_axis``: one per rotary axis, none on a three-axis machine, where it is then not listed at all rather
    than skipped on every three-axis recording) stands for the candidates that method returns."""
    out = []
    for c in candidates:
        if not callable(getattr(c, method, None)):
            out.append(c)
            continue
        got = _call(c, method, ctx)
        if not isinstance(got, (list, tuple)) or not all(isinstance(x, Candidate) for x in got):
            _fail(c, f"must return a list of candidates, got {type(got).__name__}", method)
        out += list(got)
    return out


def _expand_per_station(candidates, ctx):
    return _expand(candidates, ctx, "per_station")


def _expand_per_rotary_axis(candidates, ctx):
    return _expand(candidates, ctx, "per_rotary_axis")


def _diagnose_stations(rec, candidates, alpha, max_set, confound_margin, max_degree, gate_alpha, data_driven, steps):
    """The diagnosis of a recording of several stations (docs/diagnose.md, "Several stations")."""
    from .multistation import identify_stations, linearise

    where_rec = rec.path or rec.name
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree)
    stations, row_station, fixed = rec.station_list(), rec.station_ids(), rec.fixed_inputs()
    lt_range = rec.lt_range if rec.lt_range is not None else np.full(len(rec), np.nan)

    def identify_all(lt_xyz, lt_rng):
        res = identify_stations(model, stations, row_station, lt_xyz, lt_rng, rec.repeatability, fixed=fixed)
        return res, linearise(res, lt_xyz, lt_rng, rec.repeatability, fixed=fixed)

    steps.begin("baseline fit (all stations)")
    try:
        base, L = identify_all(rec.lt, lt_range)
    except MtbudgetError as exc:
        raise DiagnosisError(f"{where_rec}: the baseline over its {len(stations)} stations cannot be identified: "
                             f"{exc}") from None
    if base.dof < 10:
        raise DiagnosisError(f"{where_rec}: only {base.dof} degrees of freedom are left after the baseline over "
                             f"{len(stations)} stations ({len(rec)} rows); measure more points")
    first_xyz = next((st for st in stations if st.kind == "xyz"), None)
    pose = base.station_values(first_xyz.id)[0] if first_xyz is not None else np.zeros(6)
    ctx = StationsDiagnosisContext(rec, model, pose, base.theta.copy(), L.P_W, L.P_station, stations=list(stations),
                                   row_station=np.asarray(row_station))
    info = _Stations(list(stations), np.asarray(row_station), L.row, L.residuals_per_row, L.rotation, L.beam,
                     L.residual_size)
    lin0 = _Linear(L.design, L.whitened, L.row)
    mismatch = locate(ctx, L.residual_machine, L.whitened, info)
    steps.done()
    expanded = _expand_per_rotary_axis(_expand_per_station(candidates, ctx), ctx)
    steps.more(len(expanded) - len(candidates))
    skipped, untestable, usable = _candidate_columns(expanded, ctx, lin0, _stations_whitener(L), steps)

    steps.begin("noise estimate (REML, per station)")
    groups = _point_groups(rec.plan)
    est, scale = _estimate_noise_stations(rec, L, lin0, [u[1] for u in usable], groups)
    if scale is not None:
        lin = _Linear(L.design * scale[:, None], L.whitened * scale, L.row)
        whiten = _stations_whitener(L, scale)
        usable = [(c, whiten(raw, c.frame), raw) for c, _, raw in usable]
    else:
        lin, whiten = lin0, _stations_whitener(L)
    steps.done()
    steps.begin(f"candidate scan ({len(usable)} candidates, sets up to {max_set})")
    # the stand-in rule as for one station; the scan of periodic and local terms is not run on several stations yet
    usable, sel, considered, chosen, implausible_alone, level, K, _, stand_ins = _select(
        ctx, lin, usable, alpha, max_set, whiten, scan_terms=False)
    steps.done()
    steps.begin(f"refit with the findings ({len(chosen)})")
    findings, f_all = _findings(chosen, sel, K, alpha, confound_margin, ctx, whiten)
    # refit with the effects at their estimates taken out of the measurements (each in its station's frame)
    offsets = np.cumsum([0] + [usable[i][1].shape[1] for i in chosen])
    lt_xyz, lt_rng = np.array(rec.lt, float), np.array(lt_range, float)
    xyz_rows = np.isin(row_station, [st.id for st in stations if st.kind == "xyz"])
    after, res, L_after = [], base, L
    for pos, i in enumerate(chosen):
        c, _, raw = usable[i]
        d = raw @ f_all.beta[offsets[pos]:offsets[pos + 1]]  # (M, 3) mm in the candidate's frame
        if c.frame == "machine":
            d = np.einsum("mji,mj->mi", L.rotation, d)  # R^T d: into each row's station frame
        lt_xyz[xyz_rows] -= d[xyz_rows]
        lt_rng[~xyz_rows] -= (d[~xyz_rows] * L.beam[~xyz_rows]).sum(axis=1)
        try:
            res, L_after = identify_all(lt_xyz, lt_rng)
        except MtbudgetError as exc:
            raise DiagnosisError(f"{where_rec}: the refit with {c.label} cannot be identified: {exc}") from None
        findings[pos].after = _station_quality(res, L_after)
        after.append(findings[pos].after)
    notes = []
    if findings and res.chi2 > base.chi2:
        notes.append("the effects the selection chose fit worse than the baseline once taken out of the measurements "
                     f"(chi-square per dof {res.chi2_per_dof:.3f} vs {base.chi2_per_dof:.3f}); none is reported")
        chosen, findings, after, res, L_after = [], [], [], base, L
        f_all = sel.fit([])
    final = after[-1] if after else _station_quality(base, L)
    res_after = L_after.residual_machine if after else None

    pure = None
    if est["replicates"]:
        pure = np.concatenate([_station_group_design(groups, L, scale), lin.Q0], axis=1)

    def where_now():
        info_after = _Stations(info.stations, info.row_station, L_after.row, L_after.residuals_per_row,
                               L_after.rotation, L_after.beam, L_after.residual_size)
        return locate(ctx, L_after.residual_machine, L_after.whitened, info_after)

    unexplained, findings, final, res_after = _gate_and_unexplained(
        steps, ctx, lin, sel, f_all, chosen, usable, est, pure, gate_alpha, implausible_alone, notes, findings, final,
        res_after, where_now=where_now, base_quality=lambda: _station_quality(base, L), where_base=lambda: mismatch,
        whiten=whiten, data_driven=data_driven, alpha=alpha)
    if stand_ins:
        unexplained, findings, final, res_after = _stand_in_verdict(
            unexplained, stand_ins, lin, sel, f_all, chosen, est, implausible_alone, notes, findings, final, res_after,
            where_base=lambda: mismatch, base_quality=lambda: _station_quality(base, L))
    return Diagnosis(rec.name, _station_quality(base, L), mismatch, findings, final, skipped, untestable, considered,
                     _settings(rec, candidates, alpha, level, max_set, confound_margin, gate_alpha,
                               stations=[{"id": int(st.id), "kind": st.kind,
                                          "rows": int(np.count_nonzero(row_station == st.id))} for st in stations],
                               baseline="all stations at once (mtbudget.multistation.identify_stations): geometric "
                                        "errors, each xyz station's pose, each range station's position and dead path",
                               refit="the findings at their estimates are taken out of the measurements, each in its "
                                     "station's frame, and all stations are identified again"),
                     residuals_before=L.residual_machine, residuals_after=res_after,
                     noise=est, unexplained=unexplained, stand_ins=stand_ins,
                     directions=_direction_accounts(ctx.plan, mismatch, sel, findings, skipped, untestable, unexplained, alpha,
                                                    level, after=lambda: where_now() if findings else None))


def _station_group_design(groups, L, scale=None) -> np.ndarray:
    """Whitened design of one free machine-frame position per group (the same nominal point and tool, whichever
    station measured it): (n_res, 3G)."""
    G = int(groups.max()) + 1
    g = groups[L.row]
    op = L.machine if scale is None else L.machine * scale[:, None]
    Z = np.zeros((len(L.row), 3 * G))
    for c in range(3):
        Z[np.arange(len(L.row)), 3 * g + c] = op[:, c]
    return Z


def _estimate_noise_stations(rec, L, lin0, cand_cols, groups):
    """The noise of several stations: one multiplier of the stated variance per station, by REML on the error
    contrasts of repeated points (the same nominal point and tool, measured by any station: a free machine-frame
    position per point, plus every station's unknowns and every testable candidate), or on the baseline residuals
    when there are too few.  Returns (the noise dict, the scale of every whitened residual or None)."""
    n = len(L.row)
    Clib = np.concatenate(cand_cols, axis=1) if cand_cols else np.zeros((n, 0))
    N = _complement(np.concatenate([_station_group_design(groups, L), L.design, Clib], axis=1))
    replicates = N.shape[1] >= MIN_PURE_ERROR_DOF
    if not replicates:
        N = _complement(np.concatenate([L.design, Clib], axis=1))
    y = N.T @ L.whitened
    sid = np.asarray(rec.station_ids())[L.row]
    stations = rec.station_list()
    Gs, keep = [], []
    for st in stations:
        m = sid == st.id
        G = N[m].T @ N[m]
        if np.trace(G) > 1e-6:  # the station carries part of the error contrasts
            Gs.append(G)
            keep.append(st)
    s, cov = _reml(y, Gs, np.ones(len(Gs))) if Gs else (np.zeros(0), np.zeros((0, 0)))
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    chi2_pe, df_pe = float(y @ y), int(N.shape[1])
    ratio_pe = math.sqrt(chi2_pe / df_pe) if df_pe else math.nan
    p_pe = float(min(1.0, 2 * min(stats.chi2.sf(chi2_pe, df_pe), stats.chi2.cdf(chi2_pe, df_pe)))) if df_pe else 1.0
    scatter = {"chi2_per_dof": chi2_pe / df_pe if df_pe else math.nan, "dof": df_pe, "p_value": p_pe,
               "ratio": ratio_pe, "misstated": bool(df_pe and p_pe < NOISE_ALPHA and
                                                    not (1 / MISSTATED_FACTOR <= ratio_pe <= MISSTATED_FACTOR))}

    def q(v, internal, unit):
        return None if v is None else {"value": float(display(v, internal, unit)), "unit": unit}

    per, bad, mult = [], [], {}
    for st in stations:
        entry = {"id": int(st.id), "kind": st.kind,
                 "stated": {"angular": q(st.angular, "rad", "urad"), "distance": q(st.distance, "mm", "um"),
                            "distance_per_length": q(st.distance_per_length, "", "um/m")},
                 "ratio": None, "ratio_uncertainty": None, "misstated": False}
        if st in keep:
            k = keep.index(st)
            f = math.sqrt(max(s[k], 0.0))
            if se[k] < 0.5 * max(s[k], 1.0):  # the plan separates this station's noise from the others'
                uf = se[k] / (2 * f) if f > 0 else None
                mis = bool(abs(s[k] - 1.0) > 3 * se[k] and not (1 / MISSTATED_FACTOR <= f <= MISSTATED_FACTOR))
                entry.update(ratio=f, ratio_uncertainty=uf, misstated=mis)
                mult[st.id] = f
                if mis:
                    bad.append(f"the noise of station {st.id} ({st.kind}) is {f:.2g} +- {uf:.1g} (k = 1) times the "
                               "stated value")
            else:
                entry["note"] = ("not separable from the other stations' noise with this plan (it is counted in the "
                                 "scatter of repeated points)")
        else:
            entry["note"] = "no error contrast of this station: its noise cannot be estimated"
        per.append(entry)
    if scatter["misstated"] and not bad:
        bad.append(f"the scatter of repeated points is {ratio_pe:.2g} times the stated noise (chi-square per dof "
                   f"{scatter['chi2_per_dof']:.2f} on {df_pe} dof, p = {p_pe:.1g})")
    used = "estimated" if bad else "stated"
    scale = None
    if used == "estimated":
        f_row = np.array([mult.get(int(i), ratio_pe if replicates else 1.0) for i in sid])
        scale = 1.0 / np.where(f_row > 0, f_row, 1.0)
    out = {
        "method": ("REML on the error contrasts of repeated points (one free machine-frame position per nominal point "
                   "and tool, whichever station measured it, plus every station's unknowns) after every testable "
                   "candidate; one multiplier of the stated variance per station" if replicates else
                   "REML on the baseline residuals after every testable candidate (too few repeated points: "
                   "unmodelled structure cannot be told from noise); one multiplier per station"),
        "dof": df_pe, "replicates": bool(replicates), "used": used, "stations": per,
        "repeated_points": scatter if replicates else None,
        "sentence": (("the stated uncertainties do not match the data: " + "; ".join(bad) +
                      ". Selection and the fit test use the estimated noise; no finding is claimed for the "
                      "mismatch itself") if bad else None),
    }
    return out, scale


#: members of a set whose individual sizes add up to more than this many times the size of their sum cancel
CANCEL = 2.5


def _findings(chosen, sel, K, alpha, confound_margin, ctx, whiten=None):
    """The chosen effects as findings, each with its evidence, estimate and confounding alternatives: the other
    candidates of the library (BIC margin) and the alternatives outside it (:func:`_outside_alternatives`)."""
    usable, lin, fit, ftest, bic, kcols = sel.usable, sel.lin, sel.fit, sel.ftest, sel.bic, sel.kcols
    f_all = fit(chosen)
    terms = _term_library(ctx, whiten) if (chosen and whiten is not None) else None
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
        given = _given_rest(lin, usable, rest, i)
        level = alpha / max(K, 1)  # the Bonferroni level every candidate was detected at
        for j, (a, _, _) in enumerate(usable):
            if j in chosen:
                continue
            alt = rest + [j]
            f_alt = fit(alt)
            d_alt = bic(alt, f_alt) - bic(chosen, f_all)
            # a pair the candidates name as easily confused (hints): also confounded when the finding is not significant
            # with the other in its place (BIC alone favours the one with fewer columns: a rotation of the tracker for
            # a translation)
            paired = a.effect in c.hints or c.effect in a.hints
            same = None if d_alt < confound_margin else _explains_alike(sel, i, j, rest, level, alpha)
            if d_alt < confound_margin or (paired and a.effect != c.effect and given(usable[j][1]) >= alpha) or same:
                conf.append({"effect": a.effect, "axis": a.axis, "delta_bic": d_alt, **(same or {})})
                hint = (c.hints.get(a.effect) or a.hints.get(c.effect)
                        or _separating_by_cause(c, a, ctx))
                if hint and hint not in hints:
                    hints.append(hint)
        est, unc, unit = _present(c, beta, cov * scale)
        stab = _stability(lin, usable, chosen, pos, ctx)
        # naming the finding alone rejects "it adds nothing beyond the alternative" for every alternative, each at
        # the level alpha: an intersection-union test, of level alpha without a correction for their number
        outside = _outside_alternatives(i, chosen, sel, ctx, whiten, terms, alpha) if terms is not None else []
        findings.append(Finding(c, est, unc, unit, {
            "F": F, "p_value": p, "p_value_bonferroni": min(1.0, p * K), "delta_chi2": f_rest.chi2 - f_all.chi2,
            "delta_bic": d_bic, "candidates_tested": len(usable), "alpha": alpha, "by_run": stab}, {}, conf, hints,
            outside))
    return findings, f_all


#: an approach-direction difference of the residuals beyond this many standard errors is reported by the mismatch
#: summary ("x residuals differ by -3.9 um between + and - approaches"), and accounted for (:func:`_direction_accounts`)
DIRECTION_Z = 3.0


def _label(c) -> str:
    return c.effect + (f"[{c.axis}]" if c.axis else "")


def _direction_accounts(plan, mismatch, sel, findings, skipped, untestable, unexplained, alpha, level, after) -> list:
    """What accounts for each approach-direction difference the mismatch summary reports: the finding
    ``reversal[axis]``; a finding declared confounded with it (both explain the same residuals: the plan cannot tell
    them apart); the findings, given which ``reversal[axis]`` adds nothing (its partial F-test not significant at
    ``alpha``); or nothing, said so.  ``after()``: the mismatch summary of the final residuals (None without
    findings)."""
    rows = [(a, v) for a, v in (mismatch.get("by_direction") or {}).items() if abs(v["z"]) > DIRECTION_Z]
    if not rows:
        return []
    usable = sel.usable
    chosen = [next(i for i, u in enumerate(usable) if u[0] is f.candidate) for f in findings]
    labels = [_label(f.candidate) for f in findings]
    after_dirs = (after() or {}).get("by_direction", {})
    out = []
    for a, v in rows:
        entry = {"axis": a, "difference": float(v["difference"]), "z": float(v["z"]),
                 "unit": mismatch.get("unit", "um")}
        head = f"the {a} residuals differ by {v['difference']:+.1f} um between + and - approaches ({v['z']:.1f} sigma)"
        if a in after_dirs:
            entry["after"] = {"difference": float(after_dirs[a]["difference"]), "z": float(after_dirs[a]["z"]),
                              "unit": entry["unit"]}
        rev = next((i for i, u in enumerate(usable) if u[0].effect == "reversal" and u[0].axis == a
                    and i not in sel.exclude), None)
        named = [f for f in findings if f.candidate.effect == "reversal" and f.candidate.axis == a]
        conf = [f for f in findings if any(c["effect"] == "reversal" and c["axis"] == a for c in f.confounded_with)]
        if rev is not None:
            f0, f1 = sel.fit([]), sel.fit([rev])
            k = usable[rev][1].shape[1]
            _, p_alone = sel.ftest(f0.chi2, f1.chi2, k, sel.lin.dof0 - k)
            fc, fr = sel.fit([i for i in chosen if i != rev]), sel.fit(sorted(set(chosen) | {rev}))
            _, p_given = sel.ftest(fc.chi2, fr.chi2, k, sel.lin.dof0 - sel.kcols(sorted(set(chosen) | {rev})))
            entry["reversal"] = {"candidate": _label(usable[rev][0]), "p_alone": float(p_alone),
                                 "p_given_findings": float(p_given), "level": float(level), "alpha": float(alpha)}
        if named:
            entry.update(accounted="named", by=[_label(f.candidate) for f in named],
                         sentence=f"{head}: the finding {_label(named[0].candidate)}")
        elif conf:
            entry.update(accounted="confounded", by=[f"reversal[{a}]"] + [_label(f.candidate) for f in conf],
                         sentence=f"{head}: reversal[{a}] and {', '.join(_label(f.candidate) for f in conf)} explain "
                                  "it alike (declared confounded: this plan cannot tell a reversal from them). "
                                  + SEPARATE["direction"])
        elif unexplained is not None:
            entry.update(accounted="not explained", by=[],
                         sentence=f"{head}: the recording is NOT EXPLAINED, and no finding is named for it"
                                  + (f" (reversal[{a}] alone: p = {entry['reversal']['p_alone']:.2g})"
                                     if "reversal" in entry else ""))
        elif rev is None:
            why = next((x["reason"] for x in list(skipped) + list(untestable)
                        if x["effect"] == "reversal" and x["axis"] == a), None)
            why = why or next((f"excluded from selection ({sel.exclude[m]})" for m, u in enumerate(usable)
                               if u[0].effect == "reversal" and u[0].axis == a and m in sel.exclude),
                              "no reversal candidate for this axis")
            entry.update(accounted="not explained", by=labels,
                         sentence=f"{head}: NOT ACCOUNTED FOR by a reversal (reversal[{a}]: {why})"
                                  + (f"; the findings {', '.join(labels)} were fitted" if labels else ""))
        elif findings and entry["reversal"]["p_given_findings"] >= alpha and not (
                entry.get("after") and abs(entry["after"]["z"]) > DIRECTION_Z):
            aft = entry.get("after")
            entry.update(accounted="explained by the findings", by=labels,
                         sentence=f"{head}: explained by {', '.join(labels)}: reversal[{a}] adds nothing given "
                                  f"{'it' if len(labels) == 1 else 'them'} (p = {entry['reversal']['p_given_findings']:.2g}"
                                  f" >= {alpha:g})" + (f"; after {'it' if len(labels) == 1 else 'them'} the difference is "
                                                       f"{aft['difference']:+.1f} um ({aft['z']:.1f} sigma)" if aft else ""))
        else:
            r = entry["reversal"]
            aft = entry.get("after")
            if aft and abs(aft["z"]) > DIRECTION_Z and r["p_given_findings"] >= alpha:
                why = (f"not significant given them, yet after them the difference is still {aft['difference']:+.1f} "
                       f"um ({aft['z']:.1f} sigma): what leaves it is not in the library or not separable here")
            elif r["p_given_findings"] >= level:
                why = f"not significant at the selection's Bonferroni level {level:.2g}"
            elif r["p_alone"] >= level:
                why = (f"significant at the selection's level {level:.2g} given them but not alone (p = "
                       f"{r['p_alone']:.2g}): selection combines only candidates significant alone")
            else:
                why = "significant, but not chosen by selection (BIC, significance given the others, plausibility)"
            entry.update(accounted="not explained", by=labels,
                         sentence=f"{head}: NOT ACCOUNTED FOR: reversal[{a}] "
                                  + (f"given the findings ({', '.join(labels)}) " if labels else "alone ")
                                  + f"has p = {r['p_given_findings']:.2g}, {why}, so no reversal is named. "
                                  + (SEPARATE["direction"] if not _both_sides_within_runs(plan, a)
                                     else "The plan approaches both sides within each run: more points, or "
                                          "repeated runs, would show a reversal of this size"))
        out.append(entry)
    return out


def _both_sides_within_runs(plan, axis) -> bool:
    """Whether every run of the plan approaches ``axis`` from both sides at a quarter of its points at least (then a
    reversal is not a change between runs, and approaching both sides is no advice)."""
    d = plan.direction[:, AXIS_INDEX[axis]]
    return all(min((d[plan.run == r] > 0).mean(), (d[plan.run == r] < 0).mean()) >= 0.25 for r in np.unique(plan.run))


def _explains_alike(sel, i, j, rest, level, alpha) -> dict | None:
    """Whether the candidate ``usable[j]`` explains the residual pattern the finding ``usable[i]`` explains (the
    chosen ``rest`` kept): ``j`` alone is detected at the selection's Bonferroni ``level`` with a plausible value, and
    the finding adds nothing beyond ``j`` that would itself be a detection (its partial F-test with ``j`` in its place
    not significant at ``level``).  The BIC margin misses such a pair when one of the two fits a little better: a
    reversal and a steady thermal effect in a plan whose runs alternate the approach direction with time (issue:
    reversal[x] alone at p = 4e-10, thermal_expansion[x] given it at p = 0.004, BIC 8 units apart).  Naming the
    finding alone would claim it over ``j`` on weaker evidence than either needed to be detected.  ``j`` is never
    one excluded from selection (a stand-in, a replaced uniform reversal).  Returns the evidence, or None."""
    lin, usable = sel.lin, sel.usable
    if j in sel.exclude:
        return None
    f0, fj = sel.fit(rest), sel.fit(rest + [j])
    kj = usable[j][1].shape[1]
    _, p_alone = sel.ftest(f0.chi2, fj.chi2, kj, lin.dof0 - sel.kcols(rest + [j]))
    if p_alone >= level:
        return None
    if sel.implausible(j, *sel.members(rest + [j], fj)[-1]):
        return None
    both = rest + [j, i]
    fb = sel.fit(both)
    dof_b = lin.dof0 - sel.kcols(both)
    _, p_finding = sel.ftest(fj.chi2, fb.chi2, usable[i][1].shape[1], dof_b)
    if p_finding < level:
        return None
    _, p_other = sel.ftest(sel.fit(rest + [i]).chi2, fb.chi2, kj, dof_b)
    return {"why": "explains the same residuals: alone it is significant at the selection level, and the finding "
                   "adds nothing beyond it that would be a detection",
            "test": {"p_alone": float(p_alone), "p_finding_given_it": float(p_finding),
                     "p_it_given_finding": float(p_other), "level": float(level), "alpha": float(alpha)}}


def _separating_by_cause(c, a, ctx) -> str | None:
    """The measurement that separates two candidates neither of which names the other in its hints: by the kinds of
    the recording columns each names as its cause (``variables``: an approach direction, a temperature, time)."""
    kinds = []
    for x in (c, a):
        for v in (_variables(x, ctx) if callable(getattr(x, "variables", None)) else []):
            kinds += [k for k in _feature_kinds(v, ctx) if k not in kinds and k != "position"]
    # the approach direction first: within one run it changes, a thermal or a time effect does not
    kinds = [k for k in ("direction", *SEPARATE) if k in kinds]
    return SEPARATE[kinds[0]] if kinds else None


def _given_rest(lin, usable, rest, i):
    """A function of columns A: the p-value of the finding ``usable[i]`` given A in its place (the chosen ``rest``
    kept), the partial F-test of :func:`_given`."""
    Qr = _orth(np.concatenate([lin.Q0] + [usable[j][1] for j in rest], axis=1))

    def clear(Y):
        return Y - Qr @ (Qr.T @ Y)

    w = clear(lin.w[:, None])[:, 0]
    Cc = clear(usable[i][1])
    dof_rest = lin.n - Qr.shape[1]
    return lambda A: _given(w, Cc, clear(A), dof_rest)[4]


# --------------------------------------------------------------------- alternatives outside the library
#: a data-driven term of which less than this fraction (whitened norm, after the rest of the model) lies outside the
#: span of a finding's own columns is the finding in other words ("dir_x along x" for reversal[x]), not an alternative
SAME_DESCRIPTION = 0.05
#: at most this many data-driven alternatives are listed per finding (the best first)
MAX_LISTED = 3
#: pairs of data-driven terms: each of this many best single terms completed by the best second one
PAIR_FIRST = 6
#: the measurement that separates a finding from a data-driven alternative, by the kind of column the term uses
SEPARATE = {
    "time": "Measure a fixed reflector on the table at the start and at the end of the test (what follows time "
            "moves it), and let the temperature go up and then down rather than steadily one way.",
    "temperature": "Let the temperature go up and then down (not steadily one way), or put a temperature sensor "
                   "where the alternative would act (on the spindle head, on the column).",
    "run": "Repeat a run in the same direction as the one before it (a change between passes then shows alone).",
    "tool": "Measure with the tools in the other order (a tool follows the holder, not the time).",
    "direction": "Approach the points from both sides within every run.",
    "position": "Measure a finer mesh, or another region, of that axis.",
}


def _outside_settings(alpha) -> dict:
    """How the findings were tested against explanations outside the library (the JSON's settings)."""
    return {"level": alpha,
            "test": "partial F-test of each finding given each alternative in its place (the rest of the chosen set "
                    "kept); named alone only when significant given every one (an intersection-union test)",
            "alternatives": "declared by the candidates (alternatives(ctx)); data-driven terms from the recording's "
                            f"own columns, alone and in pairs (each of the {PAIR_FIRST} best single terms completed by "
                            "the best second one), except the finding's own columns and causes (variables(ctx))"}


def _feature_kinds(fname, ctx) -> list:
    """The kinds of recording column a data-driven term is built from (time, temperature, run, tool, direction,
    position), in the order of :data:`SEPARATE`."""
    kinds = set()
    for part in fname.split("*"):
        if part == "t":
            kinds.add("time")
        elif part in ctx.plan.temperature:
            kinds.add("temperature")
        elif part.startswith("run"):
            kinds.add("run")
        elif part.startswith("tool"):
            kinds.add("tool")
        elif part.startswith("dir_"):
            kinds.add("direction")
        else:
            kinds.add("position")
    return [k for k in SEPARATE if k in kinds]


def _term_words(fname, d) -> str:
    """A data-driven term in words: "a displacement along z that follows T_z"."""
    def word(part):
        if part == "t":
            return "time"
        if part.startswith("dir_"):
            return f"the {part[4:]} approach direction"
        if part.startswith("run") and part[3:].isdigit():
            return f"run {part[3:]} (against the first run)"
        if part.startswith("tool") and part[4:].isdigit():
            return f"tool {part[4:]} (against the first tool)"
        if part in AXES:
            return f"the {part} position"
        return f"the reading of {part}"
    parts = fname.split("*")
    what = word(parts[0]) if len(parts) == 1 else ("the square of " + word(parts[0]) if parts[0] == parts[1] else
                                                   f"the product of {word(parts[0])} and {word(parts[1])}")
    where = "along the beam" if d == "range" else f"along {d}"
    return f"a displacement {where} that follows {what}"


def _orth(X: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the column space of X (rank-revealing)."""
    if X.shape[1] == 0:
        return X
    s_norm = np.linalg.norm(X, axis=0)
    Xs = X[:, s_norm > 0] / s_norm[s_norm > 0]
    if Xs.shape[1] == 0:
        return Xs
    U, sv, _ = np.linalg.svd(Xs, full_matrices=False)
    return U[:, sv > 1e-9 * sv[0]]


def _given(w, Cc, A, dof_rest):
    """The partial F-test of the finding's columns ``Cc`` given the alternative ``A`` (both already cleared of the
    rest of the model, as is ``w``): (chi2 with the alternative, chi2 with both, F, dof, p)."""
    QA = _orth(A)
    w2 = w - QA @ (QA.T @ w)
    C2 = Cc - QA @ (QA.T @ Cc)
    QC = _orth(C2)
    chi_alt = float(w2 @ w2)
    chi_both = float(chi_alt - np.sum((QC.T @ w2) ** 2))
    k = QC.shape[1]
    dof = dof_rest - QA.shape[1] - k
    if k == 0 or dof <= 0:
        return chi_alt, chi_alt, 0.0, (k, dof), 1.0
    F = max(chi_alt - chi_both, 0.0) / k / (chi_both / dof)
    return chi_alt, chi_both, F, (k, dof), float(stats.f.sf(F, k, dof))


def _scan_terms(w, Qc, q, ok, dof_alt):
    """Every single-term alternative at once: the finding's columns (orthonormal basis ``Qc``) tested given the unit
    column ``q[:, j]`` in its place (``w``, ``Qc`` and ``q`` already cleared of the rest of the model; ``dof_alt``
    the residual dof with the alternative).  Returns (chi2 with the alternative, F, p, dof with both), each (L,)."""
    k = Qc.shape[1]
    s = q.T @ w  # (L,)
    t = Qc.T @ q  # (k, L)
    b = Qc.T @ w  # (k,)
    chi_alt = float(w @ w) - s**2
    G = np.eye(k)[None] - np.einsum("al,bl->lab", t, t)  # (L, k, k): the finding's Gram matrix cleared of q
    bb = (b[:, None] - t * s[None, :]).T  # (L, k)
    red = np.einsum("la,lab,lb->l", bb, np.linalg.pinv(G, rcond=1e-10), bb)
    red = np.where(ok, np.maximum(red, 0.0), 0.0)
    dof = dof_alt - k
    F = red / k / np.maximum((chi_alt - red) / dof, 1e-300)
    return chi_alt, F, stats.f.sf(F, k, dof), int(dof)


def _variables(c, ctx) -> list:
    """The recording's columns (names of the data-driven features) the candidate names as the cause of its effect: the
    approach direction of a reversal, the sensor of a thermal expansion, the time of a drift.  A data-driven term that
    involves one of them is the same cause acting with another shape (a reversal "along the beam", a reversal that
    changes between runs), a variant of the finding, not an alternative to it.  From the candidate's
    ``variables(ctx)`` (none when it does not declare them)."""
    if not callable(getattr(c, "variables", None)):
        return []
    got = _call(c, "variables", ctx)
    if not isinstance(got, (list, tuple, set)) or not all(isinstance(x, str) for x in got):
        _fail(c, f"must return a list of column names, got {got!r}", "variables")
    return list(got)


def _held_out(lin, X_rest, Cc, A, seed=20261122) -> dict:
    """Chi-square per whitened residual on a random half of the points of the model fitted on the other half: with
    the finding and with the alternative in its place (a predictive comparison, free of the selection)."""
    rng = np.random.default_rng(seed)
    pts = np.unique(lin.rowpt)
    hold = np.isin(lin.rowpt, rng.permutation(pts)[: len(pts) // 2])
    out = {}
    for key, extra in (("with_finding", Cc), ("with_alternative", A)):
        X = np.concatenate([X_rest, extra], axis=1)
        beta, *_ = np.linalg.lstsq(X[~hold], lin.w[~hold], rcond=1e-10)
        r = lin.w[hold] - X[hold] @ beta
        out[f"chi2_per_residual_{key}"] = float(r @ r / max(hold.sum(), 1))
    out["residuals"] = int(hold.sum())
    return out


def _outside_alternatives(i, chosen, sel, ctx, whiten, terms, level) -> list:
    """Explanations outside the library that fit the recording about as well as the finding ``usable[i]``.

    For each alternative (the physical alternatives the candidate declares, ``alternatives(ctx)``, and every
    data-driven term built from the recording's own columns that is not the finding in other words), the finding is
    tested *given* the alternative in its place (the rest of the chosen set kept): the partial F-test of its columns.
    When it is not significant at ``alpha`` (the family-wise level, not divided: an intersection-union test), the
    alternative explains what the finding explains: the finding is confounded with it.  An alternative declared with
    no columns is the same displacement of every point (a tracker drift and a machine drifting as a whole): always
    confounded.  Returns the confounding alternatives, the declared ones first, then up to :data:`MAX_LISTED`
    data-driven terms (the best fitting first), each with its test, a held-out comparison and the measurement that
    would separate them."""
    lin, usable = sel.lin, sel.usable
    c = usable[i][0]
    rest = [j for j in chosen if j != i]
    X_rest = np.concatenate([lin.Q0] + [usable[j][1] for j in rest], axis=1)
    Qr = _orth(X_rest)

    def clear(Y):
        return Y - Qr @ (Qr.T @ Y)

    w = clear(lin.w[:, None])[:, 0]
    Cc = clear(usable[i][1])
    dof_rest = lin.n - Qr.shape[1]
    chi_with = float(w @ w - np.sum((_orth(Cc).T @ w) ** 2))
    out = []
    # the physical alternatives the candidate declares
    declared = _call(c, "alternatives", ctx) if callable(getattr(c, "alternatives", None)) else None
    for alt in declared or []:
        if not isinstance(alt, dict) or not {"name", "description", "separate"} <= set(alt):
            _fail(c, "must return a list of dicts with keys name, description, separate (and optionally columns, "
                     f"frame), got {alt!r}", "alternatives")
        entry = {"alternative": alt["name"], "kind": "declared by the candidate", "description": alt["description"],
                 "separating_measurement": alt["separate"]}
        cols = alt.get("columns")
        if cols is None:
            entry.update(identical=True, test={"F": 0.0, "dof": None, "p_value": 1.0, "level": level},
                         why="the same displacement of every measured point: no recording of the tool point alone can "
                             "tell them apart")
            out.append(entry)
            continue
        raw = np.asarray(cols, float)
        if raw.ndim != 3 or raw.shape[:2] != (len(ctx.plan), 3) or not np.all(np.isfinite(raw)):
            _fail(c, f"alternative {alt['name']!r}: columns must be a finite array of shape ({len(ctx.plan)}, 3, k)",
                  "alternatives")
        A = clear(whiten(raw, alt.get("frame", "machine")))
        if np.linalg.norm(A) <= 1e-9 * max(np.linalg.norm(whiten(raw, alt.get("frame", "machine"))), 1e-300):
            continue  # the baseline absorbs the alternative: it explains nothing the finding explains
        chi_alt, _, F, dof, p = _given(w, Cc, A, dof_rest)
        if p >= level:
            entry.update(identical=False, test={"F": F, "dof": list(dof), "p_value": p, "level": level},
                         chi2_with_finding=chi_with, chi2_with_alternative=chi_alt,
                         held_out=_held_out(lin, X_rest, usable[i][1], whiten(raw, alt.get("frame", "machine"))),
                         why="the finding is not significant once this alternative is in the model in its place")
            out.append(entry)
    # data-driven terms from the recording's own columns, alone and in pairs
    _, names, Craw = terms
    own = set(_variables(c, ctx))
    A = clear(Craw)
    na = np.linalg.norm(A, axis=0)
    Qc = _orth(Cc)
    ok = na > 1e-6 * max(na.max(), 1e-300)
    q = A / np.where(ok, na, 1.0)
    left = np.linalg.norm(q - Qc @ (Qc.T @ q), axis=0)
    ok &= left >= SAME_DESCRIPTION  # not a part of the finding's own columns
    # not the finding's own cause in another shape: a term that involves a reading the finding names as its cause (a
    # temperature, an approach direction, time); where the cause is an axis position (couplings, the next degree),
    # only a term built from those positions alone, since nearly every term involves a position
    positions = {"x", "y", "z"}
    cause, place = own - positions, own & positions

    def variant(parts):
        return bool(parts & cause) or bool(place and parts <= place)

    ok &= np.array([not variant(set(fname.split("*"))) for fname, _ in names], bool)
    if not ok.any() or not Qc.shape[1]:
        return out
    found = []  # (chi2 with the alternative, F, p, dof, [term indices])
    chi1, F1, p1, dof1 = _scan_terms(w, Qc, q, ok, dof_rest - 1)
    for j in np.flatnonzero(ok):
        found.append((chi1[j], F1[j], p1[j], dof1, [int(j)]))
    # pairs: each of the best single terms completed by the best second one (a composite structure, such as a
    # tilt following a temperature times the height, is a sum of terms)
    for j1 in np.flatnonzero(ok)[np.argsort(chi1[ok])][:PAIR_FIRST]:
        q1 = q[:, j1]
        w1 = w - q1 * (q1 @ w)
        Qc1 = _orth(Qc - np.outer(q1, q1 @ Qc))
        A1 = q - np.outer(q1, q1 @ q)
        n1 = np.linalg.norm(A1, axis=0)
        ok1 = ok & (n1 > 1e-3)
        ok1[j1] = False
        if not ok1.any() or not Qc1.shape[1]:
            continue
        chi2_, F2, p2, dof2 = _scan_terms(w1, Qc1, A1 / np.where(ok1, n1, 1.0), ok1, dof_rest - 2)
        j2 = int(np.flatnonzero(ok1)[np.argmin(chi2_[ok1])])
        found.append((chi2_[j2], F2[j2], p2[j2], dof2, [int(j1), j2]))
    # the simplest first: single terms (best fitting first), then pairs that do not merely add a term to one of them
    conf = sorted((x for x in found if x[2] >= level), key=lambda x: (len(x[4]), x[0]))
    listed = []
    for chi_a, F, p, dof, js in conf:
        if any(set(js) >= set(prev) for prev in listed) or any(x[2] >= level and x[4] == js[:1] for x in found):
            continue  # a pair that only adds a term to a single one that confounds the finding by itself
        listed.append(js)
        if len(listed) > MAX_LISTED:
            break
        fn = [names[j] for j in js]
        kinds = []
        for fname, _ in fn:
            kinds += [k for k in _feature_kinds(fname, ctx) if k not in kinds]
        kinds = [k for k in SEPARATE if k in kinds]
        out.append({"alternative": " + ".join(f"{f} along {d}" for f, d in fn), "kind": "data-driven",
                    "description": "; ".join(_term_words(f, d) for f, d in fn)
                                   + " (data-driven, not a named physical effect)",
                    "terms": [{"feature": f, "along": d} for f, d in fn],
                    "separating_measurement": " ".join(SEPARATE[x] for x in kinds[:2]),
                    "identical": False,
                    "test": {"F": float(F), "dof": [int(Qc.shape[1]), int(dof)], "p_value": float(p), "level": level},
                    "chi2_with_finding": chi_with, "chi2_with_alternative": float(chi_a),
                    "held_out": _held_out(lin, X_rest, usable[i][1], Craw[:, js]),
                    "why": "the finding is not significant once " + ("this term is" if len(js) == 1 else "these terms are")
                           + " in the model in its place"})
    return out


# --------------------------------------------------------------------- noise
#: a component is misstated when its estimate differs from the stated one by more than 3 standard errors
#: and by more than this factor (either way) in standard deviation (10 %)
MISSTATED_FACTOR = 1.1
#: fewer error contrasts than this from repeated points: the noise is estimated from the baseline instead
MIN_PURE_ERROR_DOF = 30
#: level of the chi-square test of the repeated points' scatter against the stated noise (two-sided)
NOISE_ALPHA = 0.01


def _point_groups(plan) -> np.ndarray:
    """Group index of each point: the same nominal position with the same tool (its repeats in other runs)."""
    key = np.column_stack([np.round(plan.nominal, 6), np.round(plan.tool, 6)])
    _, inv = np.unique(key, axis=0, return_inverse=True)
    return np.asarray(inv).reshape(-1)


def _group_design(groups: np.ndarray, Wn: np.ndarray) -> np.ndarray:
    """Whitened design of one free tracker-frame position per group: (3M, 3G)."""
    M, G = len(groups), int(groups.max()) + 1
    Z = np.zeros((M, 3, 3 * G))
    for c in range(3):
        Z[np.arange(M), :, 3 * groups + c] = Wn[:, :, c]
    return Z.reshape(3 * M, 3 * G)


def _complement(X: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the orthogonal complement of the columns of X."""
    if X.shape[1] == 0:
        return np.eye(X.shape[0])
    s_norm = np.linalg.norm(X, axis=0)
    Xs = X[:, s_norm > 0] / s_norm[s_norm > 0]
    U, s, _ = np.linalg.svd(Xs, full_matrices=True)
    rank = int((s > tol * s[0]).sum()) if s.size else 0
    return U[:, rank:]


def _saturated_complement(X: np.ndarray, A: np.ndarray, tol: float = 1e-8) -> np.ndarray:
    """Orthonormal basis of the error contrasts of the saturated model X (one free position per group of repeated
    points, plus the candidates), the model's own design A nested in it.

    A lack-of-fit test and the REML of the error contrasts need the model inside the saturated model: the residuals
    are orthogonal to A, and only then does the complement of X carry (M - rank X) dof of pure noise and the rest
    (rank X - rank A) of misfit.  A three-axis plan's groups (nominal point and tool) already span A (every column of
    the model is a function of the point); a five-axis plan's do not: a group is a linear position and tool at every
    commanded angle, and the rotary axes' location and zero errors and the tracker turning with the table move its
    points differently.  Left out, the lack of fit had rank X - rank A dof but more than that in expectation (on the
    example's 320-point plan 47 dof counted, 73 free): F about 1.4 in nulls.  A is added only when it is not
    already in the span of X, so a nested plan's basis is computed exactly as before."""
    N = _complement(X)
    if A.shape[1] and N.shape[1]:
        Q = np.linalg.qr(A)[0]
        if float(np.max(np.abs(N.T @ Q))) > tol:
            N = _complement(np.concatenate([X, A], axis=1))
    return N


def _components(rec, P):
    """Unwhitened covariance components (M, 3, 3) at the tracker points P: tracker range, tracker transverse,
    repeatability along the beam and across it, each at its stated value (or at a reference value when it is
    stated as zero), and the stated multipliers."""
    ref_d = rec.distance if (rec.distance > 0 or rec.distance_per_length > 0) else 1e-3
    ref_dpl = rec.distance_per_length if (rec.distance > 0 or rec.distance_per_length > 0) else 0.0
    ref_a = rec.angular if rec.angular > 0 else 1e-6
    ref_R = rec.repeatability if rec.repeatability > 0 else 1e-3
    u = P / np.linalg.norm(P, axis=1, keepdims=True)
    uu = u[:, :, None] * u[:, None, :]
    V = [lt.covariance(P, 0.0, ref_d, ref_dpl), lt.covariance(P, ref_a, 0.0, 0.0), ref_R**2 * uu,
         ref_R**2 * (np.eye(3)[None] - uu)]
    stated = np.array([float(rec.distance > 0 or rec.distance_per_length > 0), float(rec.angular > 0),
                       float(rec.repeatability > 0), float(rec.repeatability > 0)])
    return V, stated, (ref_d, ref_dpl, ref_a, ref_R)


def _reml(y, Gs, s0, iters: int = 15):
    """REML of the multipliers s of the covariance sum_k s_k G_k of the error contrasts y (Fisher scoring).

    Returns (s, covariance of s)."""
    s = np.where(s0 > 0, s0, 0.05).astype(float)
    for _ in range(iters):
        S = sum(sk * G for sk, G in zip(s, Gs))
        Si = np.linalg.inv(S)
        a = Si @ y
        B = [Si @ G for G in Gs]
        q = np.array([a @ G @ a for G in Gs])
        F = np.array([[np.sum(Bj * Bk.T) for Bk in B] for Bj in B])
        new = np.maximum(np.linalg.lstsq(F, q, rcond=1e-12)[0], 1e-4)
        done = np.max(np.abs(new - s) / np.maximum(s, 1e-4)) < 1e-4
        s = new
        if done:
            break
    S = sum(sk * G for sk, G in zip(s, Gs))
    Si = np.linalg.inv(S)
    B = [Si @ G for G in Gs]
    F = np.array([[np.sum(Bj * Bk.T) for Bk in B] for Bj in B])
    return s, 2.0 * np.linalg.pinv(F)


def _estimate_noise(rec, ctx, Wh, A0, w, cand_cols) -> dict:
    """The variance components estimated from the data beside the stated ones (see the module docstring).

    Two well-determined components carry the decision: the variance along the beam (tracker range plus the
    repeatability's share) and across it (tracker angles plus the rest of the repeatability), each as a multiple
    of the stated one.  The three physical components are also fitted; the repeatability is reported only when
    the plan separates it from the tracker noise.
    """
    P = rec.lt
    V, stated, (ref_d, ref_dpl, ref_a, ref_R) = _components(rec, P)
    M = len(P)
    G = [np.einsum("mij,mjk,mlk->mil", Wh, v, Wh) for v in V]  # whitened components (M, 3, 3)
    groups = _point_groups(rec.plan)
    Clib = np.concatenate(cand_cols, axis=1) if cand_cols else np.zeros((3 * M, 0))
    Z = _group_design(groups, Wh)
    N = _saturated_complement(np.concatenate([Z, Clib], axis=1), A0)
    replicates = N.shape[1] >= MIN_PURE_ERROR_DOF
    if not replicates:
        N = _complement(np.concatenate([A0, Clib], axis=1))
    y = N.T @ w
    Nr = N.reshape(M, 3, -1)
    Gs = [N.T @ np.einsum("mij,mjr->mir", g, Nr).reshape(3 * M, -1) for g in G]
    # along / across the beam (always determined), then the three physical components
    s2, cov2 = _reml(y, [Gs[0] + Gs[2], Gs[1] + Gs[3]], np.ones(2))
    se2 = np.sqrt(np.maximum(np.diag(cov2), 0.0))
    s3, cov3 = _reml(y, [Gs[0], Gs[1], Gs[2] + Gs[3]], stated[:3])
    se3 = np.sqrt(np.maximum(np.diag(cov3), 0.0))
    mis = [abs(s2[k] - 1.0) > 3 * se2[k] and not (1 / MISSTATED_FACTOR <= math.sqrt(s2[k]) <= MISSTATED_FACTOR)
           for k in range(2)]
    # the scatter of the repeated points as a whole against the stated noise: more powerful than either
    # component alone when the excess is shared (a misstated repeatability adds along and across the beam)
    scatter = None
    if replicates:
        chi2_pe, df_pe = float(y @ y), int(N.shape[1])
        ratio_pe = math.sqrt(chi2_pe / df_pe)
        p_pe = float(min(1.0, 2 * min(stats.chi2.sf(chi2_pe, df_pe), stats.chi2.cdf(chi2_pe, df_pe))))
        scatter = {"chi2_per_dof": chi2_pe / df_pe, "dof": df_pe, "p_value": p_pe, "ratio": ratio_pe,
                   "misstated": bool(p_pe < NOISE_ALPHA and not (1 / MISSTATED_FACTOR <= ratio_pe <= MISSTATED_FACTOR))}
    used = "estimated" if any(mis) or (scatter and scatter["misstated"]) else "stated"
    if used == "estimated":
        C = s2[0] * (V[0] + V[2]) + s2[1] * (V[1] + V[3])
        Wn = np.linalg.inv(np.linalg.cholesky(C))
    else:
        Wn = Wh
    r_mean = float(np.linalg.norm(P, axis=1).mean())

    def q(v, internal, unit):
        return {"value": float(display(v, internal, unit)), "unit": unit}

    ur = rec.distance + rec.distance_per_length * r_mean
    ut = rec.angular * r_mean
    R = rec.repeatability
    along = math.sqrt(ur**2 + R**2)
    across = math.sqrt(ut**2 + R**2)

    def ratio(k):
        f = math.sqrt(s2[k])
        return f, se2[k] / (2 * f)

    fa, ua = ratio(0)
    fc, uc = ratio(1)
    # the tracker's share when the repeatability is as stated
    ur_est = math.sqrt(max(s2[0] * along**2 - R**2, 0.0))
    ut_est = math.sqrt(max(s2[1] * across**2 - R**2, 0.0))
    sep = se3[2] < 0.5 * max(s3[2], 1.0)
    out = {
        "method": ("REML on the error contrasts of repeated points (one free position per point and tool) after "
                   "every testable candidate" if replicates else
                   "REML on the baseline residuals after every testable candidate (no repeated points: unmodelled "
                   "structure cannot be told from noise)"),
        "dof": int(N.shape[1]), "replicates": bool(replicates), "used": used,
        "mean_range": q(r_mean, "mm", "m"),
        "along_beam": {"stated": q(along, "mm", "um"), "estimated": q(fa * along, "mm", "um"), "ratio": fa,
                       "ratio_uncertainty": ua, "misstated": bool(mis[0])},
        "across_beam": {"stated": q(across, "mm", "um"), "estimated": q(fc * across, "mm", "um"), "ratio": fc,
                        "ratio_uncertainty": uc, "misstated": bool(mis[1])},
        "tracker_range": {"stated": {"distance": q(rec.distance, "mm", "um"),
                                     "distance_per_length": q(rec.distance_per_length, "", "um/m"),
                                     "at_mean_range": q(ur, "mm", "um")},
                          "estimated": {"at_mean_range": q(ur_est, "mm", "um")},
                          "ratio": ur_est / ur if ur > 0 else None, "misstated": bool(mis[0])},
        "tracker_transverse": {"stated": {"angular": q(rec.angular, "rad", "urad"), "at_mean_range": q(ut, "mm", "um")},
                               "estimated": {"angular": q(ut_est / r_mean, "rad", "urad"),
                                             "at_mean_range": q(ut_est, "mm", "um")},
                               "ratio": ut_est / ut if ut > 0 else None, "misstated": bool(mis[1])},
        "machine_repeatability": {"stated": q(R, "mm", "um"),
                                  "estimated": q(math.sqrt(s3[2]) * ref_R, "mm", "um") if sep else None,
                                  "separable": bool(sep),
                                  "note": None if sep else "not separable from the tracker noise with this plan "
                                                           "(it is counted in the along- and across-beam noise)"},
    }
    out["repeated_points"] = scatter
    bad = []
    if scatter and scatter["misstated"] and not any(mis):
        bad.append(f"the scatter of repeated points is {scatter['ratio']:.2g} times the stated noise (chi-square per "
                   f"dof {scatter['chi2_per_dof']:.2f} on {scatter['dof']} dof, p = {scatter['p_value']:.1g}), "
                   f"along the beam {fa:.2g} +- {ua:.1g} and across it {fc:.2g} +- {uc:.1g} times (k = 1)")
    if mis[0]:
        bad.append(f"the noise along the beam (tracker range) is {fa:.2g} +- {ua:.1g} (k = 1) times the stated value")
    if mis[1]:
        bad.append(f"the noise across the beam (tracker angles) is {fc:.2g} +- {uc:.1g} (k = 1) times the stated "
                   "value")
    out["sentence"] = (("the stated uncertainties do not match the data: " + "; ".join(bad) +
                        ". Selection and the fit test use the estimated noise; no finding is claimed for the "
                        "mismatch itself") if bad else None)
    out["whitener"] = Wn
    out["groups"] = groups if replicates else None
    return out


# --------------------------------------------------------------------- the gate
def _gate(lin, f_all, k_chosen, est, pure, usable, gate_alpha) -> dict:
    """Does the final model explain the recording within the noise?  Lack of fit against pure error when points
    are repeated (``pure``: the whitened design of the saturated static model, one free position per repeated
    point), else a chi-square test against the stated noise (impossible when that noise was rejected)."""
    dof = lin.dof0 - k_chosen
    chi2 = f_all.chi2
    out = {"chi2_per_dof": chi2 / dof if dof > 0 else math.nan, "dof": int(dof)}
    if pure is not None:
        Clib = [u[1] for u in usable]
        X = np.concatenate([pure] + Clib, axis=1)
        N = _saturated_complement(X, lin.Q0)
        chi2_pe, df_pe = float(np.sum((N.T @ lin.w) ** 2)), N.shape[1]
        df_lof = dof - df_pe
        if df_lof > 0 and df_pe > 0:
            F = max(chi2 - chi2_pe, 0.0) / df_lof / (chi2_pe / df_pe)
            p = float(stats.f.sf(F, df_lof, df_pe))
            out.update(test="lack of fit against the scatter of repeated points (F)", p_value=p,
                       lack_of_fit={"F": F, "dof": [int(df_lof), int(df_pe)],
                                    "chi2_per_dof": max(chi2 - chi2_pe, 0.0) / df_lof,
                                    "pure_error_chi2_per_dof": chi2_pe / df_pe})
            out["explained"] = p >= gate_alpha
            return out
    if est["used"] == "stated":
        p = float(stats.chi2.sf(chi2, dof))
        out.update(test="chi-square against the stated noise", p_value=p, explained=p >= gate_alpha)
    else:
        out.update(test="none possible: no repeated points and the stated noise does not match the data",
                   p_value=None, explained=False)
    return out


# --------------------------------------------------------------------- structure beyond the library
#: directions a data-driven term may act along
_DIRS = ("x", "y", "z", "range")


def _features(ctx) -> dict:
    """Scalar columns of the recording (name -> (M,)), centred and scaled to about [-1, 1], and their products."""
    plan = ctx.plan
    base = {}
    t = plan.time - plan.time.mean()
    if np.ptp(t) > 0:
        base["t"] = t / (np.ptp(t) / 2)
    for col, T in plan.temperature.items():
        if np.ptp(T) > 1e-3:
            base[col] = (T - T.mean()) / (np.ptp(T) / 2)
    for i, a in enumerate(AXES):
        p = plan.nominal[:, i]
        if np.ptp(p) > 0:
            base[a] = (p - p.min()) / (np.ptp(p) / 2) - 1.0
        d = plan.direction[:, i]
        if (d > 0).any() and (d < 0).any():
            base[f"dir_{a}"] = d.astype(float)
    trows = np.round(plan.tool, 6)
    uniq, first = np.unique(trows, axis=0, return_index=True)
    for k, j in enumerate(sorted(first)[1:], start=2):
        base[f"tool{k}"] = np.all(trows == trows[j], axis=1).astype(float)
    for k in np.unique(plan.run)[1:]:
        base[f"run{int(k)}"] = (plan.run == k).astype(float)
    feats = dict(base)
    names = list(base)
    for a, b in itertools.combinations_with_replacement(names, 2):
        v = base[a] * base[b]
        if np.ptp(v) > 0 and not (a == b and set(np.unique(base[a])) <= {-1.0, 0.0, 1.0}):
            feats[f"{a}*{b}"] = v
    return feats


def _term_library(ctx, whiten):
    """The data-driven terms: every feature of :func:`_features` acting along machine x, y, z and along the beam.

    Returns (features, [(feature, direction)], whitened columns (n_res, L))."""
    feats = _features(ctx)
    u = ctx.P_LT / np.linalg.norm(ctx.P_LT, axis=1, keepdims=True)
    names, cols = [], []
    for fname, f in feats.items():
        for d in _DIRS:
            raw = (f[:, None] * u) if d == "range" else f[:, None] * np.eye(3)[AXIS_INDEX[d]][None]
            cols.append(whiten(raw[:, :, None], "tracker" if d == "range" else "machine"))
            names.append((fname, d))
    return feats, names, np.concatenate(cols, axis=1)


def _data_driven(ctx, lin, X_final, whiten, alpha, splits: int = 20, on_split=None) -> dict | None:
    """The best sparse description of what the final model leaves, from the recording's own columns.

    Forward selection (up to three terms, each significant at a Bonferroni level over the library on the
    selection half) on one random half of the points; the selected terms are tested on the other half (F-test
    of the terms given the final model refitted there).  Stability: how often each term is selected first on
    ``splits`` random halves.  Data-driven, not a named physical effect.
    """
    feats, names, C = _term_library(ctx, whiten)
    M = len(ctx.plan)
    L = C.shape[1]
    rng = np.random.default_rng(20261122)

    def residualise(rows, X, Y):
        Q, _ = np.linalg.qr(X[rows])
        return Y[rows] - Q @ (Q.T @ Y[rows])

    def forward(rows, max_terms=3):
        w = residualise(rows, X_final, lin.w[:, None])[:, 0]
        Cp = residualise(rows, X_final, C)
        norms = np.linalg.norm(Cp, axis=0)
        ok = norms > 1e-6 * max(norms.max(), 1e-300)
        chosen = []
        r, B = w.copy(), Cp.copy()
        dof = len(r) - X_final.shape[1]
        for _ in range(max_terms):
            nb = np.linalg.norm(B, axis=0)
            score = np.where(ok & (nb > 1e-9), (B.T @ r) ** 2 / np.maximum(nb**2, 1e-300), -1.0)
            j = int(np.argmax(score))
            if score[j] <= 0:
                break
            dof -= 1
            chi_new = r @ r - score[j]
            F = score[j] / (chi_new / max(dof, 1))
            if stats.f.sf(F, 1, max(dof, 1)) * L >= alpha:
                break
            chosen.append(j)
            q = B[:, j] / nb[j]
            r = r - q * (q @ r)
            B = B - np.outer(q, q @ B)
            ok[j] = False
        return chosen

    point_rows = lambda pts: np.flatnonzero(np.isin(lin.rowpt, pts))  # noqa: E731  (pts sorted: rows in order)
    first = {}
    selected, p_held, held = None, None, None
    for k in range(splits):
        perm = rng.permutation(M)
        A, Bh = np.sort(perm[: M // 2]), np.sort(perm[M // 2:])
        sel = forward(point_rows(A))
        if on_split is not None:
            on_split()
        if sel:
            first[sel[0]] = first.get(sel[0], 0) + 1
        if k == 0:
            selected = sel
            if sel:  # confirm on the held-out half
                rows = point_rows(Bh)
                w = residualise(rows, X_final, lin.w[:, None])[:, 0]
                Cp = residualise(rows, X_final, C[:, sel])
                beta, *_ = np.linalg.lstsq(Cp, w, rcond=1e-10)
                chi_small, chi_big = float(w @ w), float(np.sum((w - Cp @ beta) ** 2))
                dof = len(rows) - X_final.shape[1] - len(sel)
                F = (chi_small - chi_big) / len(sel) / (chi_big / dof)
                p_held = float(stats.f.sf(F, len(sel), dof))
                held = {"chi2_per_dof_before": chi_small / (dof + len(sel)), "chi2_per_dof_after": chi_big / dof,
                        "delta_chi2": chi_small - chi_big, "F": F, "p_value": p_held, "points": int(len(Bh))}
    if not selected or p_held is None or p_held >= alpha:
        return None
    # the terms fitted on all points, in um
    Xp = lin.project(C[:, selected]) if X_final.shape[1] == lin.p0 else None
    Q, _ = np.linalg.qr(X_final)
    Cp = C[:, selected] - Q @ (Q.T @ C[:, selected])
    beta, *_ = np.linalg.lstsq(Cp, lin.w - Q @ (Q.T @ lin.w), rcond=1e-10)
    del Xp
    terms = []
    for j, b in zip(selected, beta):
        fname, d = names[j]
        disp = feats[fname] * b  # mm along d
        terms.append({"term": f"{fname} along {d}", "coefficient": {"value": float(display(b, "mm", "um")), "unit": "um"},
                      "rms": {"value": float(display(np.sqrt(np.mean(disp**2)), "mm", "um")), "unit": "um"},
                      "selected_first_in": f"{first.get(j, 0)} of {splits} random halves"})
    return {"kind": "data-driven, not a named physical effect", "terms": terms, "held_out": held,
            "library": {"features": len(feats), "terms_searched": L},
            "method": "forward selection on one half of the points (Bonferroni over the terms searched), "
                      "F-test of the selected terms on the other half"}


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
    return est, unc, json_unit(unit)


def _stability(lin, usable, chosen, pos, ctx):
    """The estimate from each run alone (the other runs' rows given no weight), in display units."""
    runs = np.unique(ctx.plan.run)
    if len(runs) < 2:
        return None
    out = {}
    c = usable[chosen[pos]][0]
    for k in runs:
        keep = (ctx.plan.run == k)[lin.rowpt]
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
        if np.linalg.norm(Cp[:, sl]) <= 1e-9 * max(np.linalg.norm(usable[chosen[pos]][1]), 1e-300):
            out[int(k)] = {"estimate": None, "uncertainty": None, "note": "this run's rows do not carry it"}
            continue
        est, unc, unit = _present(c, beta[sl], cov[sl, sl])
        out[int(k)] = {"estimate": est[0] if len(est) == 1 else est, "uncertainty": unc[0] if len(unc) == 1 else unc}
    return out
