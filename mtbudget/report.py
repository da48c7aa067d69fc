"""Results as text, JSON, Markdown and self-contained HTML (with figures)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .units import display, pretty

from .budget import conformance, guf_validation
from .outputs import MAIN_OUTPUT, SCALARS, RunResult


def result_json(res: RunResult) -> dict:
    out = {"trials": res.trials, "coverage": res.coverage, "complete": res.complete, "seed": res.spec.get("seed"),
           "not_converged": res.not_converged, "outputs": {}, "budget": res.budget, "convergence": res.convergence}
    if res.weights:
        out["weights"] = res.weights
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


def _show_unit(internal_unit: str) -> str:
    return {"rad": "urad", "mm": "um", "mm/mm": "um/m"}.get(internal_unit, internal_unit)


def _fmt(x, nd=3):
    return "-" if x is None else f"{x:.{nd}g}"


def budget_text(res: RunResult) -> str:
    lines = []
    status = "" if res.complete else "  (INCOMPLETE: partial results)"
    lines.append(f"Monte Carlo: {res.trials} trials, coverage {res.coverage:.0%}, seed {res.spec.get('seed')}{status}")
    if getattr(res, "stopped_at_limit", False):
        lines.append("  note: the adaptive run stopped at its trial limit before reaching its numerical tolerance")
    if res.not_converged:
        lines.append(f"  note: the identification of {res.not_converged} of {res.trials} trials did not converge; "
                     "their results are included as they stood at the iteration limit")
    if res.weights:
        lines.append("  identification weights stated apart from what the run draws ([weights]):")
        for name, w in res.weights.items():
            lines.append(f"    {name:<20} stated {display(w['stated'], w['unit'], _show_unit(w['unit'])):.4g} "
                         f"{pretty(_show_unit(w['unit']))}, drawn {display(w['drawn'], w['unit'], _show_unit(w['unit'])):.4g} "
                         f"{pretty(_show_unit(w['unit']))}")
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


# ----------------------------------------------------------------------------- run reports
def _figures(res: RunResult, folder):
    """PNG figures of a run; returns {name: path}."""

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats as st

    folder = Path(folder)
    figs = {}
    # output distributions with the GUF normal overlaid
    names = [k for k in SCALARS if res.acc.scalar_samples(k) is not None]
    fig, axes = plt.subplots(2, 4, figsize=(14, 6.5))
    for ax, k in zip(axes.ravel(), names):
        y = res.acc.scalar_samples(k)
        ax.hist(y, bins=60, density=True, color="#7aa6c2", label="MCM")
        s = res.summary(k)
        lo, hi = s["symmetric"]
        ax.axvline(lo, color="k", ls="--", lw=1)
        ax.axvline(hi, color="k", ls="--", lw=1, label=f"{res.coverage:.0%} interval")
        b = res.budget.get(k)
        if b and b.get("u_combined"):
            xs = np.linspace(y.min(), y.max(), 200)
            ax.plot(xs, st.norm.pdf(xs, b["nominal_value"], b["u_combined"]), color="#c0392b", label="GUF normal")
        ax.set_title(k, fontsize=9)
        ax.set_xlabel(SCALARS[k][0] or "1")
        ax.legend(fontsize=6)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    figs["distributions"] = folder / "distributions.png"
    fig.savefig(figs["distributions"], dpi=100)
    plt.close(fig)
    # contributions
    b = res.budget.get(MAIN_OUTPUT)
    if b:
        rows = sorted(b["rows"], key=lambda r: r["contribution"])
        fig, ax = plt.subplots(figsize=(8, 0.32 * len(rows) + 1.5))
        colours = {"machine tool": "#1f77b4", "measurement system": "#ff7f0e", "measurement strategy": "#2ca02c",
                   "optimisation strategy": "#9467bd"}
        ax.barh([r["source"] for r in rows], [r["share"] * 100 for r in rows], color=[colours.get(r["group"], "grey") for r in rows])
        ax.set_xlabel(f"share of the {b['basis'].replace('_', ' ')} of {MAIN_OUTPUT} [%]")
        for g, c in colours.items():
            ax.barh([], [], color=c, label=g)
        ax.legend(fontsize=7, loc="lower right")
        fig.tight_layout()
        figs["contributions"] = folder / "contributions.png"
        fig.savefig(figs["contributions"], dpi=100)
        plt.close(fig)
    # convergence
    if res.convergence:
        c = res.convergence
        n = [x["trials"] for x in c]
        fig, ax = plt.subplots(1, 2, figsize=(11, 3.5))
        ax[0].plot(n, [x["mean"] for x in c], label="mean")
        ax[0].plot(n, [x["low"] for x in c], "--", label="interval low")
        ax[0].plot(n, [x["high"] for x in c], "--", label="interval high")
        ax[1].plot(n, [x["std"] for x in c], color="k", label="standard uncertainty")
        for a in ax:
            a.set_xlabel("trials")
            a.legend(fontsize=7)
        ax[0].set_ylabel(f"{MAIN_OUTPUT} [um]")
        fig.suptitle("convergence of the Monte Carlo estimate")
        fig.tight_layout()
        figs["convergence"] = folder / "convergence.png"
        fig.savefig(figs["convergence"], dpi=100)
        plt.close(fig)
    # per-point error map (paper Figs. 13 and 15): mean and spread of the error left after compensation
    pm = res.acc.moments.get("point_error")
    mesh = res.mesh
    if pm is not None and mesh is not None:
        fig = plt.figure(figsize=(12, 5))
        for j, (vals, title) in enumerate(((np.asarray(pm.mean), "mean error after compensation [um]"),
                                           (np.asarray(pm.std), "its standard deviation over trials [um]"))):
            ax = fig.add_subplot(1, 2, j + 1, projection="3d")
            sc = ax.scatter(mesh[:, 0], mesh[:, 1], mesh[:, 2], c=vals, cmap="viridis", s=40)
            fig.colorbar(sc, ax=ax, shrink=0.7)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("x [mm]")
            ax.set_ylabel("y [mm]")
            ax.set_zlabel("z [mm]")
        fig.tight_layout()
        figs["error_map"] = folder / "error_map.png"
        fig.savefig(figs["error_map"], dpi=100)
        plt.close(fig)
    return figs


def run_report(res: RunResult, folder, tolerance_um: float | None = None) -> dict:
    """Write report.md and a self-contained report.html (figures inlined) into ``folder``."""
    import base64
    import html

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    figs = _figures(res, folder)
    data = result_json(res)
    md = ["# mtbudget uncertainty budget", ""]
    md.append(f"{res.trials} Monte Carlo trials, coverage probability {res.coverage:.0%}, seed {res.spec.get('seed')}"
              + ("" if res.complete else " — **INCOMPLETE run: partial results**"))
    md += ["", "## Coverage intervals", "", "| output | unit | estimate | u | symmetric interval | shortest interval |",
           "| --- | --- | --- | --- | --- | --- |"]
    for k, v in data["outputs"].items():
        sh = "-" if v["shortest"] is None else f"[{v['shortest'][0]:.3f}, {v['shortest'][1]:.3f}]"
        md.append(f"| {k} | {v['unit']} | {v['mean']:.3f} | {v['std']:.3f} | [{v['symmetric'][0]:.3f}, {v['symmetric'][1]:.3f}] | {sh} |")
    b = res.budget.get(MAIN_OUTPUT)
    if b:
        md += ["", f"## Budget of {MAIN_OUTPUT} (by source)", "",
               f"Each source alone on the same {b['trials']} trials; contributions by {b['basis'].replace('_', ' ')}, which add "
               "up for independent sources; what they do not explain is the interaction.", "",
               "| source | group | u(x_i) | c_i | u_i(y) [um] | share |", "| --- | --- | --- | --- | --- | --- |"]
        for r in sorted(b["rows"], key=lambda r: -r["contribution"]):
            ux = "-" if r["u_x"] is None else f"{r['u_x']['value']:.3g} {r['u_x']['unit']}"
            ci = "-" if "sensitivity" not in r else f"{r['sensitivity']['value']:.3g} {r['sensitivity']['unit']}"
            md.append(f"| {r['source']} | {r['group']} | {ux} | {ci} | {r['u_y']:.3f} | {r['share']:.1%} |")
        md.append(f"| interaction | | | | | {b['interaction'] / b['total'] if b['total'] else 0:.1%} |")
        md.append(f"| **total** | | | | {b['u_total']:.3f} | 100 % |")
        md += ["", "## Budget by group", "", "| group | share |", "| --- | --- |"]
        md += [f"| {g['group']} | {g['share']:.1%} |" for g in b["groups"]]
    v = data.get("validation")
    if v:
        md += ["", "## GUF vs MCM (JCGM 101 clause 8)", "",
               f"GUF: {v['guf_estimate']:.3f} um with u_c = {v['guf_u']:.3f} um (law of propagation over the source "
               f"contributions), interval [{v['guf_interval'][0]:.3f}, {v['guf_interval'][1]:.3f}] um; MCM interval "
               f"[{v['mcm_interval'][0]:.3f}, {v['mcm_interval'][1]:.3f}] um. d_low = {v['d_low']:.3g}, d_high = "
               f"{v['d_high']:.3g}, delta = {v['delta']:.3g}: **{'validated' if v['passed'] else 'not validated'}**."]
    if tolerance_um is not None:
        conf = conformance(res, tolerance_um)
        md += ["", "## Conformance (ISO 14253-1)", "", conf["statement"]]
        data["conformance"] = conf
    md += ["", "## Figures", ""] + [f"![{k}]({p.name})" for k, p in figs.items()]
    (folder / "report.md").write_text("\n".join(md) + "\n")
    # HTML: the same content, tables as tables, figures inlined (opens with no network)
    body = []
    for line in md:
        if line.startswith("# "):
            body.append(f"<h1>{html.escape(line[2:])}</h1>")
        elif line.startswith("## "):
            body.append(f"<h2>{html.escape(line[3:])}</h2>")
        elif line.startswith("| ---"):
            continue
        elif line.startswith("|"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            tag = "th" if body and not body[-1].startswith("<tr") and not body[-1].startswith("<table") else "td"
            if not body or not (body[-1].startswith("<tr") or body[-1].startswith("<table")):
                body.append('<table class="budget">')
                tag = "th"
            body.append("<tr>" + "".join(f"<{tag}>{html.escape(c.replace('**', ''))}</{tag}>" for c in cells) + "</tr>")
        elif line.startswith("!["):
            name = line[line.index("(") + 1:-1]
            b64 = base64.b64encode((folder / name).read_bytes()).decode()
            body.append(f'<figure><img alt="{html.escape(name)}" src="data:image/png;base64,{b64}"></figure>')
        else:
            if body and body[-1].startswith("<tr"):
                body.append("</table>")
            if line.strip():
                body.append(f"<p>{html.escape(line.replace('**', ''))}</p>")
    if body and body[-1].startswith("<tr"):
        body.append("</table>")
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>mtbudget report</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
            "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:3px 8px;font-size:13px}"
            "th{background:#eef}img{max-width:100%}</style>"
            "<script>window.addEventListener('load',function(){var im=document.images,ok=0;"
            "for(var i=0;i<im.length;i++){if(im[i].complete&&im[i].naturalWidth>0)ok++;}"
            "document.body.setAttribute('data-images',ok+'/'+im.length);"
            "document.body.setAttribute('data-tables',document.querySelectorAll('table.budget').length);});</script>"
            "</head><body>" + "\n".join(body) + "</body></html>")
    (folder / "report.html").write_text(page)
    (folder / "results.json").write_text(__import__("json").dumps(data, indent=1))
    return {"markdown": folder / "report.md", "html": folder / "report.html", "figures": figs}
