"""Results as text, JSON, Markdown and self-contained HTML (with figures)."""

from __future__ import annotations

import math

import numpy as np

from .distributions import t_factor
from .engine import MAIN_OUTPUT, SCALARS, RunResult
from .stats import numerical_tolerance


def guf_validation(res: RunResult, output: str = MAIN_OUTPUT) -> dict | None:
    """JCGM 101 clause 8 for a run output: the GUF interval (nominal value +- k u_c) vs the MCM interval."""
    b = res.budget.get(output)
    if not b:
        return None
    s = res.summary(output)
    k = t_factor(res.coverage, math.inf)
    u_c = b["u_combined"]
    y = b["nominal_value"]
    lo, hi = y - k * u_c, y + k * u_c
    delta = numerical_tolerance(s["std"], 2)
    d_low, d_high = abs(lo - s["symmetric"][0]), abs(hi - s["symmetric"][1])
    return {"guf_estimate": y, "guf_u": u_c, "k": k, "guf_interval": [lo, hi], "mcm_interval": list(s["symmetric"]),
            "d_low": d_low, "d_high": d_high, "delta": delta, "passed": bool(d_low <= delta and d_high <= delta)}


def result_json(res: RunResult) -> dict:
    out = {"trials": res.trials, "coverage": res.coverage, "complete": res.complete, "seed": res.spec.get("seed"),
           "outputs": {}, "budget": res.budget, "convergence": res.convergence}
    for k, v in res.outputs().items():
        out["outputs"][k] = {"unit": v["unit"], "description": v["description"], "mean": v["mean"], "std": v["std"],
                             "symmetric": list(v["symmetric"]), "shortest": None if v["shortest"] is None else list(v["shortest"])}
    pm = res.acc.moments.get("point_error")
    if pm is not None:
        out["point_error"] = {"unit": "um", "mean": np.asarray(pm.mean).tolist(), "std": np.asarray(pm.std).tolist()}
    par = res.acc.moments.get("parameters")
    if par is not None:
        out["parameters"] = {"names": res.parameter_names, "units": res.parameter_units,
                             "mean": np.asarray(par.mean).tolist(), "std": np.asarray(par.std).tolist()}
    out["validation"] = guf_validation(res)
    return out


def _fmt(x, nd=3):
    return "-" if x is None else f"{x:.{nd}g}"


def budget_text(res: RunResult) -> str:
    lines = []
    status = "" if res.complete else "  (INCOMPLETE: partial results)"
    lines.append(f"Monte Carlo: {res.trials} trials, coverage {res.coverage:.0%}, seed {res.spec.get('seed')}{status}")
    lines.append("")
    lines.append(f"{'output':<20} {'unit':<5} {'mean':>9} {'u (std)':>9}   {'symmetric interval':>22}   {'shortest interval':>22}")
    for k, v in res.outputs().items():
        sym = f"[{v['symmetric'][0]:.3f}, {v['symmetric'][1]:.3f}]"
        sh = "-" if v["shortest"] is None else f"[{v['shortest'][0]:.3f}, {v['shortest'][1]:.3f}]"
        lines.append(f"{k:<20} {v['unit']:<5} {v['mean']:9.3f} {v['std']:9.3f}   {sym:>22}   {sh:>22}")
    b = res.budget.get(MAIN_OUTPUT)
    if b:
        lines.append("")
        lines.append(f"Budget of {MAIN_OUTPUT} ({b['unit']}), one source at a time on {b['trials']} trials, "
                     f"by {b['basis'].replace('_', ' ')}:")
        lines.append(f"  {'source':<32} {'group':<22} {'u(x_i)':>14} {'c_i':>22} {'u_i(y)':>8} {'share':>7}")
        for r in sorted(b["rows"], key=lambda r: -r["contribution"]):
            ux = "-" if r["u_x"] is None else f"{r['u_x']['value']:.3g} {r['u_x']['unit']}"
            ci = "-" if "sensitivity" not in r else f"{r['sensitivity']['value']:.3g} {r['sensitivity']['unit']}"
            lines.append(f"  {r['source']:<32} {r['group']:<22} {ux:>14} {ci:>22} {r['u_y']:8.3f} {r['share']:7.1%}")
        lines.append(f"  {'interaction (not additive)':<32} {'':<22} {'':>14} {'':>22} "
                     f"{math.copysign(math.sqrt(abs(b['interaction'])), b['interaction']):8.3f} "
                     f"{(b['interaction'] / b['total'] if b['total'] else 0):7.1%}")
        lines.append(f"  {'total':<32} {'':<22} {'':>14} {'':>22} {b['u_total']:8.3f} {1:7.1%}")
        lines.append("  by group: " + ", ".join(f"{g['group']} {g['share']:.1%}" for g in b["groups"]))
        v = guf_validation(res)
        if v:
            verdict = "validated" if v["passed"] else "NOT validated (the model is non-linear: use the MCM interval)"
            lines.append(f"  GUF vs MCM (JCGM 101 clause 8): GUF {v['guf_estimate']:.3f} +- {v['k']:.2f} x {v['guf_u']:.3f}; "
                         f"d_low {v['d_low']:.3g}, d_high {v['d_high']:.3g}, delta {v['delta']:.3g}: {verdict}")
    if getattr(res, "log_path", None):
        lines.append("")
        lines.append(f"run log: {res.log_path}  (mtbudget replay / mtbudget report)")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- diagnosis
def _fmt_value(v, nd=3):
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.{nd}g}" for x in v) + ")"
    return f"{v:.{nd}g}"


def diagnosis_text(d) -> str:
    out = [f"recording {d.recording!r}"]
    b = d.baseline
    out.append(f"  baseline (rigid-body model): chi-square per dof {b['chi2_per_dof']:.3f} ({b['dof']} dof), "
               f"RMS residual {b['rms']['value']:.2f} um")
    m = d.mismatch
    hints = []
    for a, v in m.get("by_direction", {}).items():
        if abs(v["z"]) > 3:
            hints.append(f"{a} residuals differ by {v['difference']:+.1f} um between + and - approaches ({v['z']:.1f} sigma)")
    for a, v in m.get("by_time", {}).items():
        if abs(v["z"]) > 3:
            hints.append(f"{a} residuals drift {v['slope_um_per_h']:+.1f} um/h over the test ({v['z']:.1f} sigma)")
    for a, v in m.get("by_temperature", {}).items():
        if abs(v["correlation"]) > 0.3:
            hints.append(f"{a} residuals follow the {a}-axis temperature (correlation {v['correlation']:+.2f})")
    if hints:
        out.append("  where the mismatch is:")
        out += [f"    - {h}" for h in hints]
    if not d.findings:
        out.append("  no finding: the recording is explained by the baseline model within its stated uncertainty")
        out.append(f"  ({len(d.considered)} candidates tested at a family-wise level of {d.settings['alpha']:g})")
    for f in d.findings:
        x = f.to_dict()
        ax = f" of the {f.candidate.axis} axis" if f.candidate.axis and len(f.candidate.axis) == 1 else (
            f" ({f.candidate.axis})" if f.candidate.axis else "")
        out.append(f"  FOUND {f.candidate.effect}{ax}: {f.candidate.description}")
        out.append(f"    estimate {_fmt_value(x['estimate']['value'])} {f.unit} +- {_fmt_value(x['uncertainty']['value'], 2)} "
                   f"{f.unit} (k = 1)")
        ev = f.evidence
        out.append(f"    evidence: F = {ev['F']:.1f}, p = {ev['p_value']:.2g} (Bonferroni over {ev['candidates_tested']}: "
                   f"{ev['p_value_bonferroni']:.2g}), BIC better by {ev['delta_bic']:.1f}")
        out.append(f"    fit after: chi-square per dof {f.after['chi2_per_dof']:.3f}, RMS {f.after['rms']['value']:.2f} um")
        if f.confounded_with:
            alts = ", ".join(f"{c['effect']}" + (f"[{c['axis']}]" if c["axis"] else "") for c in f.confounded_with)
            out.append(f"    CONFOUNDED: the data fit {alts} about as well; they cannot be told apart from this recording. "
                       f"{disambiguation(f.candidate.effect, f.confounded_with)}")
    if d.findings:
        out.append(f"  final: chi-square per dof {d.final['chi2_per_dof']:.3f}, RMS {d.final['rms']['value']:.2f} um")
    for s in d.skipped:
        out.append(f"  skipped {s['effect']}{'[' + s['axis'] + ']' if s['axis'] else ''}: {s['reason']}")
    for s in d.untestable:
        out.append(f"  not testable {s['effect']}{'[' + s['axis'] + ']' if s['axis'] else ''}: {s['reason']}")
    return "\n".join(out)


DISAMBIGUATE = {
    frozenset({"tracker_drift", "air_temperature_drift"}): "Repeat the test with the air temperature held, or measure a fixed reference point every few minutes.",
    frozenset({"tracker_range_offset", "tracker_range_scale"}): "Measure a calibrated length, or the same points from a second tracker station.",
    frozenset({"thermal_expansion", "tracker_drift"}): "Measure while the temperature goes up and then down (not steadily one way).",
    frozenset({"thermal_expansion", "air_temperature_drift"}): "Add a sensor on the structure away from the air stream, or repeat at another temperature.",
}


def disambiguation(effect, confounded):
    tips = []
    for c in confounded:
        tip = DISAMBIGUATE.get(frozenset({effect, c["effect"]}))
        if tip and tip not in tips:
            tips.append(tip)
    return " ".join(tips) or "A second pass with other approach directions, temperatures or tool offsets would separate them."


def diagnosis_report(d, rec, folder) -> "Path":
    """Markdown report with residual plots before and after (PNG beside it)."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    plan = rec.plan
    t = plan.time / 3600
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex="col")
    for i, a in enumerate("xyz"):
        for j, (res, label) in enumerate(((d.residuals_before, "before"), (d.residuals_after, "after"))):
            ax = axes[i, j]
            if res is None:
                res = d.residuals_before
                label = "after (no finding: unchanged)"
            for dirn, mk in ((1, "^"), (-1, "v")):
                m = plan.direction[:, i] == dirn
                ax.scatter(t[m], res[m, i] * 1e3, s=9, marker=mk, label=f"{a} approached {'+' if dirn > 0 else '-'}")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_ylabel(f"{a} residual [um]")
            if i == 0:
                ax.set_title(f"residuals {label}")
            if i == 2:
                ax.set_xlabel("time [h]")
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{d.recording}: machine-frame residuals before and after the findings")
    fig.tight_layout()
    fig.savefig(folder / "residuals.png", dpi=110)
    plt.close(fig)
    lines = [f"# Diagnosis of {d.recording}", "", "```", diagnosis_text(d), "```", "",
             "![residuals before and after](residuals.png)", ""]
    if d.findings:
        lines += ["| effect | axis | estimate | uncertainty (k=1) | p (Bonferroni) | chi2/dof after | confounded with |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for f in d.findings:
            x = f.to_dict()
            lines.append(f"| {f.candidate.effect} | {f.candidate.axis or '-'} | {_fmt_value(x['estimate']['value'])} {f.unit} | "
                         f"{_fmt_value(x['uncertainty']['value'], 2)} {f.unit} | {f.evidence['p_value_bonferroni']:.2g} | "
                         f"{f.after['chi2_per_dof']:.3f} | {', '.join(c['effect'] for c in f.confounded_with) or '-'} |")
    (folder / "diagnosis.md").write_text("\n".join(lines) + "\n")
    return folder / "diagnosis.md"
