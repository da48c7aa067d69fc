"""Diagnosis results for people: the text summary and the Markdown report with residual plots."""

from __future__ import annotations

from pathlib import Path

from .units import display, pretty

#: when the confounded candidates give no hint of their own
GENERIC_HINT = "A second pass with other approach directions, temperatures or tool offsets would separate them."


def _fmt_value(v, nd=3):
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.{nd}g}" for x in v) + ")"
    return f"{v:.{nd}g}"


def diagnosis_text(d) -> str:
    out = [f"recording {d.recording!r}"]
    b = d.baseline
    out.append(f"  baseline (rigid-body model): chi-square per dof {b['chi2_per_dof']:.3f} ({b['dof']} dof), "
               f"RMS residual {_rms(b)}{_not_converged(b)}")
    m = d.mismatch
    um = pretty(m.get("unit", "um"))
    hints = []
    for a, v in m.get("by_direction", {}).items():
        if abs(v["z"]) > 3:
            hints.append(f"{a} residuals differ by {v['difference']:+.1f} {um} between + and - approaches ({v['z']:.1f} sigma)")
    for a, v in m.get("by_time", {}).items():
        if abs(v["z"]) > 3:
            hints.append(f"{a} residuals drift {v['slope_um_per_h']:+.1f} {pretty('um/h')} over the test ({v['z']:.1f} sigma)")
    for a, v in m.get("by_temperature", {}).items():
        if abs(v["correlation"]) > 0.3:
            hints.append(f"{a} residuals follow the {a}-axis temperature (correlation {v['correlation']:+.2f})")
    if hints:
        out.append("  where the mismatch is:")
        out += [f"    - {h}" for h in hints]
    noise = getattr(d, "noise", None) or {}
    if noise.get("sentence"):
        out.append(f"  NOISE: {noise['sentence']}.")
    which = "estimated" if noise.get("used") == "estimated" else "stated"
    unexplained = getattr(d, "unexplained", None)
    if not d.findings:
        if unexplained is None:
            out.append(f"  no finding: the recording is explained by the baseline model within its {which} uncertainty"
                       + (" (not the stated one, see NOISE)" if which == "estimated" else ""))
        else:
            out.append("  no finding: no candidate of the library explains the misfit with plausible values")
        out.append(f"  ({len(d.considered)} candidates tested at a family-wise level of {d.settings['alpha']:g})")
    for f in d.findings:
        x = f.to_dict()
        ax = f" of the {f.candidate.axis} axis" if f.candidate.axis and len(f.candidate.axis) == 1 else (
            f" ({f.candidate.axis})" if f.candidate.axis else "")
        out.append(f"  FOUND {f.candidate.effect}{ax}: {f.candidate.description}")
        unit = pretty(f.unit)
        out.append(f"    estimate {_fmt_value(x['estimate']['value'])} {unit} +- {_fmt_value(x['uncertainty']['value'], 2)} "
                   f"{unit} (k = 1)")
        ev = f.evidence
        out.append(f"    evidence: F = {ev['F']:.1f}, p = {ev['p_value']:.2g} (Bonferroni over {ev['candidates_tested']}: "
                   f"{ev['p_value_bonferroni']:.2g}), BIC better by {ev['delta_bic']:.1f}")
        out.append(f"    fit after: chi-square per dof {f.after['chi2_per_dof']:.3f}, RMS {_rms(f.after)}{_not_converged(f.after)}")
        if f.confounded_with:
            alts = ", ".join(f"{c['effect']}" + (f"[{c['axis']}]" if c["axis"] else "") for c in f.confounded_with)
            out.append(f"    CONFOUNDED: the data fit {alts} about as well; they cannot be told apart from this recording. "
                       f"{' '.join(f.hints) or GENERIC_HINT}")
    if d.findings:
        out.append(f"  final: chi-square per dof {d.final['chi2_per_dof']:.3f}, RMS {_rms(d.final)}")
        if unexplained is None:
            out.append(f"  the final model explains the recording within its {which} uncertainty")
    if unexplained is not None:
        out += _unexplained_text(unexplained)
    for s in d.skipped:
        out.append(f"  skipped {s['effect']}{'[' + s['axis'] + ']' if s['axis'] else ''}: {s['reason']}")
    for s in d.untestable:
        out.append(f"  not testable {s['effect']}{'[' + s['axis'] + ']' if s['axis'] else ''}: {s['reason']}")
    return "\n".join(out)


def _unexplained_text(u) -> list:
    out = []
    p = u.get("p_value")
    ptxt = f"p = {p:.2g}" if p is not None else "no test possible"
    out.append(f"  NOT EXPLAINED: the final model leaves a misfit beyond the noise (chi-square per dof "
               f"{u['chi2_per_dof']:.3f} on {u['dof']} dof; {u['test']}: {ptxt})")
    lof = u.get("lack_of_fit")
    if lof:
        out.append(f"    misfit beyond the scatter of repeated points: {lof['chi2_per_dof']:.2f} per dof vs "
                   f"{lof['pure_error_chi2_per_dof']:.2f} (F = {lof['F']:.2f} on {lof['dof'][0]}, {lof['dof'][1]} dof)")
    where = u.get("where", {})
    lines = []
    for a, v in where.get("by_direction", {}).items():
        if abs(v["z"]) > 3:
            lines.append(f"{a} residuals differ by {v['difference']:+.1f} {pretty('um')} between + and - approaches")
    for a, v in where.get("by_time", {}).items():
        if abs(v["z"]) > 3:
            lines.append(f"{a} residuals drift {v['slope_um_per_h']:+.1f} {pretty('um/h')} ({v['z']:.1f} sigma)")
    tools = where.get("by_tool", {})
    if len(tools) > 1:
        lines.append("by tool: " + ", ".join(f"tool {k} mean ({', '.join(f'{x:+.1f}' for x in v['mean'])}) {pretty('um')}"
                                             for k, v in tools.items()))
    for x in lines:
        out.append(f"    - {x}")
    for imp in u.get("implausible", []):
        ax = f"[{imp['axis']}]" if imp["axis"] else ""
        out.append(f"    IMPLAUSIBLE {imp['effect']}{ax} would fit, but {imp['reason']}: not a finding")
    for n in u.get("notes", []):
        out.append(f"    note: {n}")
    dd = u.get("data_driven")
    if dd:
        h = dd["held_out"]
        terms = "; ".join(f"{t['term']} ({t['rms']['value']:.2f} {pretty('um')} RMS, first in {t['selected_first_in']})"
                          for t in dd["terms"])
        out.append(f"    best description ({dd['kind']}): {terms}")
        out.append(f"      on held-out points chi-square per dof {h['chi2_per_dof_before']:.3f} -> {h['chi2_per_dof_after']:.3f} "
                   f"(F = {h['F']:.1f}, p = {h['p_value']:.2g}, {h['points']} points)")
    else:
        out.append("    no data-driven term built from the recording's columns describes it (confirmed on held-out points)")
    return out


def _rms(q) -> str:
    return f"{q['rms']['value']:.2f} {pretty(q['rms']['unit'])}"


def _not_converged(q) -> str:
    return "" if q.get("converged", True) else " (the identification did NOT converge: these numbers are not at its minimum)"


def diagnosis_report(d, rec, folder) -> Path:
    """Markdown report with residual plots before and after (PNG beside it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    plan = rec.plan
    t = display(plan.time, "s", "h")
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex="col")
    for i, a in enumerate("xyz"):
        for j, (res, label) in enumerate(((d.residuals_before, "before"), (d.residuals_after, "after"))):
            ax = axes[i, j]
            if res is None:
                res = d.residuals_before
                label = "after (no finding: unchanged)"
            for dirn, mk in ((1, "^"), (-1, "v")):
                m = plan.direction[:, i] == dirn
                ax.scatter(t[m], display(res[m, i], "mm", "um"), s=9, marker=mk,
                           label=f"{a} approached {'+' if dirn > 0 else '-'}")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_ylabel(f"{a} residual [{pretty('um')}]")
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
            unit = pretty(f.unit)
            lines.append(f"| {f.candidate.effect} | {f.candidate.axis or '-'} | {_fmt_value(x['estimate']['value'])} {unit} | "
                         f"{_fmt_value(x['uncertainty']['value'], 2)} {unit} | {f.evidence['p_value_bonferroni']:.2g} | "
                         f"{f.after['chi2_per_dof']:.3f} | {', '.join(c['effect'] for c in f.confounded_with) or '-'} |")
    (folder / "diagnosis.md").write_text("\n".join(lines) + "\n")
    return folder / "diagnosis.md"
