"""Diagnosis results for people: the text summary, and the Markdown and self-contained HTML report with
residual plots.  Every user string (recording name and description, column, plugin and effect names, notes
from plugins) is escaped for Markdown (:func:`mtbudget.report.md_escape`), HTML and matplotlib's mathtext."""

from __future__ import annotations

import html
import math
from pathlib import Path

from .errors import make_folder
from .report import md_escape
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
    if d.settings.get("thermal_correction"):
        out.append(f"  {d.settings['thermal_correction']}")
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
    if m.get("by_station"):
        out.append("  by station (baseline residuals: an xyz row's in its station's frame, a range row's along its beam; "
                   "an xyz station's pose absorbs the mean of a range offset, station_range_offset tests what is left):")
        out += _by_station_text(m["by_station"], um)
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
        ax = _axis_words(f.candidate.axis)
        out.append(f"  FOUND {f.candidate.effect}{ax}: {f.candidate.description}")
        unit = pretty(f.unit)
        out.append(f"    estimate {_fmt_value(x['estimate']['value'])} {unit} +- {_fmt_value(x['uncertainty']['value'], 2)} "
                   f"{unit} (k = 1)")
        ev = f.evidence
        out.append(f"    evidence: F = {ev['F']:.1f}, p = {ev['p_value']:.2g} (Bonferroni over {ev['candidates_tested']}: "
                   f"{ev['p_value_bonferroni']:.2g}), BIC better by {ev['delta_bic']:.1f}")
        out.append(f"    fit after: chi-square per dof {f.after['chi2_per_dof']:.3f}, RMS {_rms(f.after)}{_not_converged(f.after)}")
        out += _details_text(getattr(f, "details", None) or {})
        if f.confounded_with:
            alts = ", ".join(f"{c['effect']}" + (f"[{c['axis']}]" if c["axis"] else "") for c in f.confounded_with)
            out.append(f"    CONFOUNDED: the data fit {alts} about as well; they cannot be told apart from this recording. "
                       f"{' '.join(f.hints) or GENERIC_HINT}")
        out += _outside_text(f)
    if d.findings:
        out.append(f"  final: chi-square per dof {d.final['chi2_per_dof']:.3f}, RMS {_rms(d.final)}")
        if unexplained is None:
            out.append(f"  the final model explains the recording within its {which} uncertainty")
    for e in getattr(d, "directions", None) or []:
        out.append(f"  APPROACH DIRECTION ({e['accounted']}): {e['sentence'].replace(' um ', ' ' + pretty('um') + ' ')}")
    if unexplained is not None:
        out += _unexplained_text(unexplained)
    out += _scan_text(getattr(d, "scan", None) or [])
    for s in d.skipped:
        out.append(f"  skipped {s['effect']}{'[' + s['axis'] + ']' if s['axis'] else ''}: {s['reason']}")
    for s in d.untestable:
        out.append(f"  not testable {s['effect']}{'[' + s['axis'] + ']' if s['axis'] else ''}: {s['reason']}")
    return "\n".join(out)


def _details_text(x) -> list:
    """What the scan of periodic and local terms adds to a finding (docs/diagnose.md, "Periodic and local terms")."""
    if x.get("kind") == "periodic":
        per, up = x["period"], x["period_uncertainty"]
        amp, ua = x["amplitude"], x["amplitude_uncertainty"]
        return [f"    PERIODIC along {x['along']}: period {per['value']:.4g} {pretty(per['unit'])} +- {up['value']:.2g} "
                f"{pretty(up['unit'])}, amplitude {amp['value']:.3g} {pretty(amp['unit'])} +- {ua['value']:.2g} "
                f"{pretty(ua['unit'])} (standard uncertainties, k = 1); a controller's pitch table can hold it"]
    if x.get("sentence"):
        return [f"    {'LOCAL' if x.get('kind') == 'local' else 'UNIFORM'}: {x['sentence']}"]
    return []


def _scan_text(scan) -> list:
    """One line per pass of the scan of periodic and local terms."""
    out = []
    for s in scan:
        b = s.get("best") or {}
        what = (f"period {b['period']['value']:.4g} mm" if "period" in b else
                f"boundary {b['boundary']['value']:.6g} mm" if "boundary" in b else "")
        bound = {"upper": " (a Bonferroni bound)", "lower": " (at least: the smallest nominal p)"}.get(
            s.get("p_value_bound"), "")
        out.append(f"  scan of periodic and local terms, pass {s['pass']} ({s.get('terms', 0)} terms, level "
                   f"{s['level']:.2g}): best {b.get('term', '-')}[{b.get('axis', '-')}] {what}, family-wise "
                   f"p = {s['p_value']:.2g}{bound}" + (f": added {s['added']}" if s.get("added") else ": nothing added"))
    return out


def outside_sentence(f) -> str:
    """One plain sentence: the finding is not named alone, an explanation outside the library fits about as well."""
    label = f.candidate.effect + (f"[{f.candidate.axis}]" if f.candidate.axis else "")
    return (f"{label} is not named alone: an explanation outside the library fits this recording about as well, so "
            f"the recording shows {label} or that explanation, and cannot tell which")


def _alternative_evidence(a) -> str:
    """How the alternative fits: identical, or the finding's partial F-test given it."""
    if a.get("identical"):
        return a.get("why", "the same displacement of every measured point")
    t = a["test"]
    return (f"with it in the finding's place the finding is not significant (F = {t['F']:.2f} on {t['dof'][0]} and "
            f"{t['dof'][1]} dof, p = {t['p_value']:.2g} >= {t['level']:g}); chi-square {a['chi2_with_alternative']:.1f} "
            f"with it against {a['chi2_with_finding']:.1f} with the finding")


def _outside_text(f) -> list:
    if not getattr(f, "outside", None):
        return []
    out = [f"    CONFOUNDED WITH AN ALTERNATIVE OUTSIDE THE LIBRARY: {outside_sentence(f)}."]
    for a in f.outside:
        out.append(f"      - {a['alternative']} ({a['kind']}): {a['description']}; {_alternative_evidence(a)}.")
        ho = a.get("held_out")
        if ho:
            out.append(f"        on held-out points (fitted on the other half): chi-square per residual "
                       f"{ho['chi2_per_residual_with_finding']:.3f} with the finding, "
                       f"{ho['chi2_per_residual_with_alternative']:.3f} with the alternative ({ho['residuals']} residuals)")
        out.append(f"        to separate them: {a['separating_measurement']}")
    return out


def _axis_words(axis) -> str:
    """" of the x axis", " (station 2)", " (xy)" or ""."""
    if not axis:
        return ""
    if axis in ("x", "y", "z"):
        return f" of the {axis} axis"
    return f" (station {axis})" if str(axis).isdigit() else f" ({axis})"


def _by_station_text(by, um) -> list:
    out = []
    for sid, v in by.items():
        se = v.get("mean_along_beam_stderr")
        se_txt = f" (standard error {se:.2f} {um}, k = 1)" if se is not None else ""
        out.append(f"    station {sid} ({v['kind']}): {v['rows']} rows, RMS residual {v['rms']:.2f} {um}, mean along the "
                   f"beam {v['mean_along_beam']:+.2f} {um}{se_txt}, chi-square per residual {v['chi2_per_residual']:.2f}")
    return out


def _unexplained_text(u) -> list:
    out = []
    p = u.get("p_value")
    ptxt = f"p = {p:.2g}" if p is not None else "no test possible"
    if u.get("stand_ins") and u.get("p_value") is None and u["test"].startswith("an effect"):
        out.append(f"  NOT EXPLAINED: {u['test']}")
    else:
        out.append(f"  NOT EXPLAINED: the final model leaves a misfit beyond the noise (chi-square per dof "
                   f"{u['chi2_per_dof']:.3f} on {u['dof']} dof; {u['test']}: {ptxt})")
    for x in u.get("stand_ins", []):
        ax = f"[{x['axis']}]" if x["axis"] else ""
        est, unc = x["estimate"], x["uncertainty"]
        out.append(f"    STAND-IN {x['effect']}{ax} ({_fmt_value(est['value'])} +- {_fmt_value(unc['value'], 2)} "
                   f"{pretty(est['unit'])}, k = 1) {x['sentence']}"
                   + (f"; to separate them: {x['separating_measurement']}" if x.get("separating_measurement") else ""))
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
    if where.get("by_station"):
        out.append("    by station:")
        out += ["  " + x for x in _by_station_text(where["by_station"], pretty("um"))]
    for imp in u.get("implausible", []):
        ax = f"[{imp['axis']}]" if imp["axis"] else ""
        out.append(f"    IMPLAUSIBLE {imp['effect']}{ax} would fit, but {imp['reason']}: not a finding")
    for f in u.get("partial", []):
        ax = f"[{f['axis']}]" if f["axis"] else ""
        est, unc = f["estimate"], f["uncertainty"]
        out.append(f"    PARTIAL {f['effect']}{ax}: explains part of the misfit ({_fmt_value(est['value'])} "
                   f"+- {_fmt_value(unc['value'], 2)} {pretty(est['unit'])}, k = 1), but the recording stays "
                   f"unexplained with it: not a finding")
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


class U(str):
    """A user string inside report text: escaped for Markdown and HTML (the rest of the text is mtbudget's own)."""


def _md(parts) -> str:
    parts = (parts,) if isinstance(parts, str) else parts
    return "".join(md_escape(p) if isinstance(p, U) else p for p in parts)


def _html(parts) -> str:
    parts = (parts,) if isinstance(parts, str) else parts
    return html.escape("".join(parts))


def mpl_escape(text) -> str:
    """A user string inside a matplotlib title or label: ``$`` would start mathtext."""
    return str(text).replace("$", r"\$")


def _label(effect, axis) -> tuple:
    return (U(effect), "[", U(axis), "]") if axis else (U(effect),)


def _num(x, nd=3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return _fmt_value(x, nd)


def _q(q, nd=3) -> str:
    """A {"value", "unit"} quantity as text: value and pretty unit."""
    return "-" if q is None else f"{_num(q['value'], nd)} {pretty(q['unit'])}".rstrip()


class _Doc:
    """Blocks rendered once as Markdown and once as HTML: the same content, escaped for each."""

    def __init__(self):
        self.blocks = []

    def h(self, level, *parts):
        self.blocks.append(("h", level, parts))

    def p(self, *parts, strong=False):
        self.blocks.append(("p", strong, parts))

    def ul(self, items):
        if items:
            self.blocks.append(("ul", [tuple(i) if isinstance(i, (tuple, list)) else (i,) for i in items]))

    def table(self, header, rows):
        self.blocks.append(("table", header, [[c if isinstance(c, (tuple, list)) else (c,) for c in r] for r in rows]))

    def fig(self, name, caption):
        self.blocks.append(("fig", name, caption))

    def markdown(self) -> str:
        out = []
        for b in self.blocks:
            if b[0] == "h":
                out += ["#" * b[1] + " " + _md(b[2]), ""]
            elif b[0] == "p":
                t = _md(b[2])
                out += [f"**{t}**" if b[1] else t, ""]
            elif b[0] == "ul":
                out += [f"- {_md(i)}" for i in b[1]] + [""]
            elif b[0] == "table":
                out.append("| " + " | ".join(_md(h) for h in b[1]) + " |")
                out.append("|" + " --- |" * len(b[1]))
                out += ["| " + " | ".join(_md(c) for c in r) + " |" for r in b[2]]
                out.append("")
            else:
                out += [f"![{_md(b[2])}]({b[1]})", "", f"*{_md(b[2])}*", ""]
        return "\n".join(out)

    def html(self, folder: Path, title) -> str:
        import base64

        body = []
        for b in self.blocks:
            if b[0] == "h":
                body.append(f"<h{b[1]}>{_html(b[2])}</h{b[1]}>")
            elif b[0] == "p":
                t = _html(b[2])
                body.append(f"<p><strong>{t}</strong></p>" if b[1] else f"<p>{t}</p>")
            elif b[0] == "ul":
                body.append("<ul>" + "".join(f"<li>{_html(i)}</li>" for i in b[1]) + "</ul>")
            elif b[0] == "table":
                body.append('<table class="diagnosis"><tr>' + "".join(f"<th>{_html(h)}</th>" for h in b[1]) + "</tr>"
                            + "".join("<tr>" + "".join(f"<td>{_html(c)}</td>" for c in r) + "</tr>" for r in b[2])
                            + "</table>")
            else:
                b64 = base64.b64encode((folder / b[1]).read_bytes()).decode()
                cap = _html(b[2])
                body.append(f'<figure><img alt="{cap}" src="data:image/png;base64,{b64}"><figcaption>{cap}</figcaption>'
                            "</figure>")
        return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>" + _html(title) + "</title><style>"
                "body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}"
                "table{border-collapse:collapse;margin:0.5em 0 1em}td,th{border:1px solid #bbb;padding:3px 8px;"
                "font-size:13px;text-align:left}th{background:#eef}img{max-width:100%}"
                "figcaption{font-size:13px;color:#444}li{margin:0.2em 0}</style>"
                "<script>window.addEventListener('load',function(){var im=document.images,ok=0;"
                "for(var i=0;i<im.length;i++){if(im[i].complete&&im[i].naturalWidth>0)ok++;}"
                "document.body.setAttribute('data-images',ok+'/'+im.length);"
                "document.body.setAttribute('data-tables',document.querySelectorAll('table.diagnosis').length);"
                "var r=[];for(var i=0;i<im.length;i++){var b=im[i].getBoundingClientRect();"
                "r.push([Math.round(b.left+window.scrollX),Math.round(b.top+window.scrollY),Math.round(b.width),"
                "Math.round(b.height)].join(','));}document.body.setAttribute('data-figures',r.join(';'));});"
                "</script></head><body>\n" + "\n".join(body) + "\n</body></html>\n")


def _verdict(d) -> tuple:
    noise = getattr(d, "noise", None) or {}
    which = "estimated" if noise.get("used") == "estimated" else "stated"
    names = []
    for f in d.findings:
        names += list(_label(f.candidate.effect, f.candidate.axis)) + [", "]
    if getattr(d, "unexplained", None) is not None:
        found = ("Found: ", *names[:-1], ". ") if names else ("No named effect accounts for it. ",)
        return ("NOT EXPLAINED: the final model leaves a misfit beyond the noise (see Not explained). ", *found)
    if d.findings:
        caveat = "" if not any(getattr(f, "outside", None) for f in d.findings) else (" Not every finding is named alone: an explanation outside the library fits about "
                                   "as well (see Findings).")
        return ("Found: ", *names[:-1], f". The final model explains the recording within its {which} uncertainty."
                + caveat)
    return (f"No finding: the recording is explained by the baseline model within its {which} uncertainty"
            + (" (not the stated one: see Noise)." if which == "estimated" else "."),)


def _noise_section(doc: _Doc, n: dict):
    doc.h(2, "Noise: stated and estimated")
    if not n:
        doc.p("No noise estimate in this diagnosis.")
        return
    if "stations" in n:
        _noise_stations(doc, n)
        return
    doc.p(f"Standard deviations (k = 1) of one measured point; the estimate is {n['method']} "
          f"({n['dof']} degrees of freedom). Along and across the beam at the mean range "
          f"{_q(n['mean_range'])}. The ratio is estimated / stated, with its standard uncertainty (k = 1). "
          f"Selection and the fit gate used the {n['used']} noise.")

    def row(name, comp, stated, estimated, ratio, ratio_u, mis):
        r = "-" if ratio is None else f"{ratio:.2f}" + ("" if ratio_u is None else f" ± {ratio_u:.2f}")
        return [name, comp, stated, estimated, r, "MISSTATED" if mis else "as stated"]

    rows = [row("along the beam", "tracker range and repeatability", _q(n["along_beam"]["stated"]),
                _q(n["along_beam"]["estimated"]), n["along_beam"]["ratio"], n["along_beam"]["ratio_uncertainty"],
                n["along_beam"]["misstated"]),
            row("across the beam", "tracker angles and repeatability", _q(n["across_beam"]["stated"]),
                _q(n["across_beam"]["estimated"]), n["across_beam"]["ratio"], n["across_beam"]["ratio_uncertainty"],
                n["across_beam"]["misstated"])]
    tr, tt, mr = n["tracker_range"], n["tracker_transverse"], n["machine_repeatability"]
    rows.append(row("tracker range", f"{_q(tr['stated']['distance'])} + {_q(tr['stated']['distance_per_length'])}, "
                    "at the mean range", _q(tr["stated"]["at_mean_range"]), _q(tr["estimated"]["at_mean_range"]),
                    tr["ratio"], None, tr["misstated"]))
    rows.append(row("tracker transverse", "angle", _q(tt["stated"]["angular"]), _q(tt["estimated"]["angular"]),
                    tt["ratio"], None, tt["misstated"]))
    est_r = mr["estimated"]
    rows.append(row("machine repeatability", "per point", _q(mr["stated"]),
                    _q(est_r) if est_r else "not separable", est_r["value"] / mr["stated"]["value"]
                    if est_r and mr["stated"]["value"] > 0 else None, None, False))
    doc.table(["component", "what", "stated (k = 1)", "estimated (k = 1)", "ratio estimated / stated", "verdict"], rows)
    if n.get("sentence"):
        doc.p(n["sentence"][0].upper() + n["sentence"][1:] + ".", strong=True)
    if mr.get("note"):
        doc.p(f"Machine repeatability: {mr['note']}.")


def _noise_stations(doc: _Doc, n: dict):
    """The noise of a recording of several stations: one multiplier of the stated variance per station."""
    doc.p(f"Stated standard uncertainties (k = 1) of each station and the estimated ratio of its noise to them, with "
          f"the ratio's standard uncertainty (k = 1); the estimate is {n['method']} ({n['dof']} degrees of freedom). "
          f"Selection and the fit gate used the {n['used']} noise.")
    rows = []
    for st in n["stations"]:
        stated = st["stated"]
        what = ", ".join(x for x in (f"angle {_q(stated['angular'])}" if stated.get("angular") else "",
                                     f"distance {_q(stated['distance'])} + {_q(stated['distance_per_length'])}") if x)
        r = "-" if st["ratio"] is None else f"{st['ratio']:.2f}" + (
            "" if st["ratio_uncertainty"] is None else f" ± {st['ratio_uncertainty']:.2f}")
        verdict = "MISSTATED" if st["misstated"] else ("as stated" if st["ratio"] is not None else
                                                        U(st.get("note", "not estimated")))
        rows.append([f"station {st['id']}", st["kind"], what, r, verdict])
    doc.table(["station", "kind", "stated (k = 1)", "ratio estimated / stated", "verdict"], rows)
    rp = n.get("repeated_points")
    if rp:
        doc.p(f"Scatter of repeated points (every station together): {rp['ratio']:.2f} times the stated noise "
              f"(χ²/dof {rp['chi2_per_dof']:.3f} on {rp['dof']} degrees of freedom, p-value {rp['p_value']:.2g}).")
    if n.get("sentence"):
        doc.p(n["sentence"][0].upper() + n["sentence"][1:] + ".", strong=True)


def _by_station_table(doc: _Doc, by: dict):
    um = pretty("um")
    doc.table(["station", "kind", "rows", f"RMS residual [{um}]", f"mean along the beam [{um}]",
               "standard error (k = 1)", "χ² per residual"],
              [[str(k), v["kind"], str(v["rows"]), f"{v['rms']:.2f}", f"{v['mean_along_beam']:+.2f}",
                "-" if v.get("mean_along_beam_stderr") is None else f"{v['mean_along_beam_stderr']:.2f}",
                f"{v['chi2_per_residual']:.2f}"] for k, v in by.items()])


def _unexplained_section(doc: _Doc, u: dict):
    doc.h(2, "Not explained")
    p = u.get("p_value")
    if u.get("stand_ins") and p is None and u["test"].startswith("an effect"):
        doc.p(f"Not explained: {u['test']} (χ²/dof = {u['chi2_per_dof']:.3f} on {u['dof']} degrees of freedom; noise "
              f"used: {u.get('noise_used', 'stated')}).", strong=True)
    else:
        doc.p(f"The final model does not explain the recording: χ²/dof = {u['chi2_per_dof']:.3f} on {u['dof']} degrees "
              "of freedom, " + (f"p-value {p:.2g}" if p is not None else "no test possible") +
              f". Test: {u['test']}; noise used: {u.get('noise_used', 'stated')}.", strong=True)
    lof = u.get("lack_of_fit")
    if lof:
        doc.p(f"Misfit beyond the scatter of repeated points: {lof['chi2_per_dof']:.3f} per degree of freedom against a "
              f"pure error of {lof['pure_error_chi2_per_dof']:.3f} (F = {lof['F']:.2f} on {lof['dof'][0]} and "
              f"{lof['dof'][1]} degrees of freedom).")
    w = u.get("where", {})
    um = pretty("um")
    doc.h(3, "Where the misfit lives")
    doc.p(f"Residuals after the final model, in the machine frame, in {um}.")
    if w.get("by_run"):
        doc.p("By run:")
        doc.table(["run", "points", f"mean x, y, z [{um}]", f"RMS [{um}]", "χ² per coordinate"],
                  [[str(k), str(v["points"]), _vec(v["mean"]), f"{v['rms']:.2f}", f"{v['chi2_per_point']:.2f}"]
                   for k, v in w["by_run"].items()])
    if w.get("by_station"):
        doc.p("By station (an xyz row's residual in its station's frame, a range row's along its beam):")
        _by_station_table(doc, w["by_station"])
    if w.get("by_tool"):
        doc.p("By tool (reflector holder offset):")
        doc.table(["tool", f"offset [{pretty(next(iter(w['by_tool'].values())).get('tool_unit', 'mm'))}]", "points",
                   f"mean x, y, z [{um}]", f"RMS [{um}]", "χ² per coordinate"],
                  [[str(k), _vec(v["tool"]), str(v["points"]), _vec(v["mean"]), f"{v['rms']:.2f}",
                    f"{v['chi2_per_point']:.2f}"] for k, v in w["by_tool"].items()])
    if w.get("by_time"):
        doc.p("Drift over the test (slope of the residual against time):")
        doc.table(["axis", f"drift [{pretty('um/h')}]", "standard error (k = 1)", "z"],
                  [[a, f"{v['slope_um_per_h']:+.2f}", f"{v['stderr']:.2f}", f"{v['z']:+.1f}"]
                   for a, v in w["by_time"].items()])
    if w.get("by_direction"):
        doc.p("By approach direction:")
        doc.table(["axis", f"+ approach mean [{um}]", f"- approach mean [{um}]", f"difference [{um}]", "z"],
                  [[a, f"{v['plus_mean']:+.2f}", f"{v['minus_mean']:+.2f}", f"{v['difference']:+.2f}", f"{v['z']:+.1f}"]
                   for a, v in w["by_direction"].items()])
    if w.get("worst_points"):
        doc.p("The five points with the largest misfit:")
        doc.table(["row", "point", "run", f"residual x, y, z [{um}]", "χ²"],
                  [[str(v["row"]), str(v["point"]), str(v["run"]), _vec(v["residual"]), f"{v['chi2']:.1f}"]
                   for v in w["worst_points"]])
    if u.get("stand_ins"):
        doc.h(3, "Stand-ins: fit only like a candidate rejected as implausible")
        doc.p("Each of these effects is significant, but its fitted displacement is what a candidate rejected as "
              "implausible would give: it stands in for it and is not a finding.")
        doc.table(["effect", "estimate (k = 1)", "fits like", "why not a finding"],
                  [[_label(x["effect"], x["axis"]),
                    f"{_fmt_value(x['estimate']['value'])} ± {_fmt_value(x['uncertainty']['value'], 2)} "
                    f"{pretty(x['estimate']['unit'])}", _label(x["fits_like"]["effect"], x["fits_like"]["axis"]),
                    (U(x["fits_like"]["reason"]),)] for x in u["stand_ins"]])
    if u.get("implausible"):
        doc.h(3, "Implausible: would fit, but not a finding")
        doc.p("Each of these candidates alone would reduce the misfit significantly, but only with a value outside "
              "its physically plausible range; the structure it tried to explain stays here.")
        rows = []
        for imp in u["implausible"]:
            est, unc = imp.get("estimate"), imp.get("uncertainty")
            pl = imp.get("plausible", [])
            what = pl[0]["quantity"] if len(pl) == 1 else "a value"
            rng = "; ".join((f"{md_escape(r['parameter'])}: " if len(pl) > 1 else "") +
                            f"{_num(r['low'], 3)} to {_num(r['high'], 3)} {pretty(r['unit'])}" for r in pl) or "-"
            need = (U(what), f" of {_q(est)} ± {_q(unc, 2)} (k = 1)") if est else (U(imp["reason"]),)
            rows.append([_label(imp["effect"], imp["axis"]), need, rng, "implausible: not a finding"])
        doc.table(["candidate", "would need", "plausible range", "verdict"], rows)
    if u.get("partial"):
        doc.h(3, "Partial: explains part of the misfit, but not a finding")
        doc.p("Each of these candidates is significant and plausible, but the recording stays unexplained with it: "
              "what it fits may be physics outside the library that it only resembles.")
        doc.table(["candidate", "estimate (k = 1)", "χ²/dof with it"],
                  [[_label(f["effect"], f["axis"]),
                    f"{_q(f['estimate'])} ± {_q(f['uncertainty'], 2)}", f"{f['after']['chi2_per_dof']:.3f}"]
                   for f in u["partial"]])
    notes = u.get("notes") or []
    doc.ul([("note: ", U(x)) for x in notes])
    dd = u.get("data_driven")
    doc.h(3, "Best data-driven description")
    if dd:
        h = dd["held_out"]
        doc.p(f"{dd['kind'][0].upper() + dd['kind'][1:]}: terms built from the recording's own columns "
              f"({dd['library']['features']} features, {dd['library']['terms_searched']} terms searched), "
              f"selected on one half of the points and confirmed on the other: χ²/dof on the {h['points']} held-out "
              f"points {h['chi2_per_dof_before']:.3f} → {h['chi2_per_dof_after']:.3f} "
              f"(F = {h['F']:.1f}, p-value {h['p_value']:.2g}).")
        doc.table(["term (data-driven, not a named physical effect)", "coefficient", "RMS over the points",
                   "selected first in"],
                  [[(U(t["term"]),), _q(t["coefficient"]), _q(t["rms"]), t["selected_first_in"]] for t in dd["terms"]])
    else:
        doc.p("No data-driven term built from the recording's columns describes the misfit (none confirmed on "
              "held-out points).")


def _vec(v, nd=2) -> str:
    return "(" + ", ".join(f"{x:.{nd}f}" for x in v) + ")"


def _residual_figure(d, rec, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plan = rec.plan
    t = display(plan.time, "s", "h")
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex="col", sharey="row")
    after_label = "after the findings" if d.residuals_after is not None else "after (no finding: unchanged)"
    for i, a in enumerate("xyz"):
        for j, (res, label) in enumerate(((d.residuals_before, "before (baseline)"),
                                          (d.residuals_after, after_label))):
            ax = axes[i, j]
            res = d.residuals_before if res is None else res
            for dirn, mk, col in ((1, "^", "tab:blue"), (-1, "v", "tab:orange")):
                m = plan.direction[:, i] == dirn
                if m.any():
                    ax.scatter(t[m], display(res[m, i], "mm", "um"), s=9, marker=mk, color=col,
                               label=f"approached from {'+' if dirn > 0 else '-'}{a}")
            ax.axhline(0, color="k", lw=0.5)
            if j == 0:
                ax.set_ylabel(f"{a} residual [{pretty('um')}]")
            if i == 0:
                ax.set_title(f"residuals {label}")
            if i == 2:
                ax.set_xlabel("time since the start [h]")
            ax.legend(fontsize=7, loc="best", framealpha=0.85)
    fig.suptitle(f"{mpl_escape(d.recording)}: machine-frame residuals before and after")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def diagnosis_report(d, rec, folder) -> Path:
    """diagnosis.md and a self-contained diagnosis.html (figures inlined) with residual plots before and after
    (PNG beside them).  Returns the Markdown path."""
    import time

    from . import __version__

    folder = make_folder(folder)
    _residual_figure(d, rec, folder / "residuals.png")
    doc = _Doc()
    doc.h(1, "Diagnosis of ", U(d.recording))
    doc.p(*_verdict(d), strong=True)
    doc.h(2, "Recording")
    plan = rec.plan
    sensors = "; ".join(f"{s.column} on {s.attached_to}" for s in getattr(plan, "sensors", []) or []) or "none"
    doc.table(["item", "value"], [
        ["recording", (U(d.recording),)],
        ["folder", (U(str(getattr(rec, "path", None) or "-")),)],
        ["description", (U(getattr(rec, "description", "") or "-"),)],
        ["machine", (U(rec.machine),)],
        ["points, runs", f"{len(plan)}, {len(set(plan.run.tolist()))}"],
        *([["stations", "; ".join(f"{st['id']} {st['kind']} ({st['rows']} rows)" for st in d.settings["stations"])]]
          if d.settings.get("stations") else []),
        ["temperature sensors", (U(sensors),)],
        ["candidates tested", (U(", ".join(d.settings.get("candidates", []))),)],
        ["family-wise level (Bonferroni), fit gate level", f"{d.settings['alpha']:g}, {d.settings.get('gate_alpha', 0.01):g}"],
        ["mtbudget, report written", f"{__version__}, {time.strftime('%Y-%m-%d %H:%M %Z')}"],
    ])
    doc.h(2, "Fit before and after")
    doc.p("χ²/dof is the chi-square of the whitened residuals per degree of freedom (1 when the model explains "
          "the recording within its stated noise); RMS of the residuals in the machine frame.")
    b, fin = d.baseline, d.final
    doc.table(["model", "χ²/dof", "degrees of freedom", "RMS residual", "converged"],
              [["baseline (rigid-body model)", f"{b['chi2_per_dof']:.3f}", str(b["dof"]), _q(b["rms"], 3),
                "yes" if b.get("converged", True) else "NO"],
               ["final (with the findings)", f"{fin['chi2_per_dof']:.3f}", str(fin["dof"]), _q(fin["rms"], 3),
                "yes" if fin.get("converged", True) else "NO"]])
    if d.mismatch.get("by_station"):
        doc.h(3, "By station")
        doc.p("Baseline: ", U(d.settings.get("baseline", "")), ". Residuals of the baseline by station: an xyz row's "
              "residual in its station's frame, a range row's along its beam. A station's pose absorbs the mean of a "
              "range offset along its beam; the candidate station_range_offset tests what is left.")
        _by_station_table(doc, d.mismatch["by_station"])
    doc.h(2, "Findings")
    if d.findings:
        rows = []
        for f in d.findings:
            x = f.to_dict()
            unit = pretty(f.unit)
            conf = [c for c in f.confounded_with]
            cw = []
            for c in conf:
                cw += list(_label(c["effect"], c["axis"])) + [", "]
            rows.append([_label(f.candidate.effect, f.candidate.axis), (U(f.candidate.plugin or "-"),),
                         f"{_fmt_value(x['estimate']['value'])} {unit}", f"{_fmt_value(x['uncertainty']['value'], 2)} {unit}",
                         f"{f.evidence['p_value_bonferroni']:.2g}", f"{f.after['chi2_per_dof']:.3f}",
                         tuple(cw[:-1]) if cw else "-",
                         (U("; ".join(a["alternative"] for a in f.outside)),) if getattr(f, "outside", None)
                         else "none fits as well: named alone" if not f.confounded_with else "none fits as well"])
        doc.table(["effect", "plugin", "estimate", "standard uncertainty (k = 1)", "p-value (Bonferroni)",
                   "χ²/dof after", "confounded with", "outside the library"], rows)
        for f in d.findings:
            doc.p(*_label(f.candidate.effect, f.candidate.axis), ": ", U(f.candidate.description))
            for line in _details_text(getattr(f, "details", None) or {}):
                doc.p(U(line.strip()), strong=True)
            if f.confounded_with:
                doc.p("Confounded: the data fit the alternatives about as well. ", U(" ".join(f.hints) or GENERIC_HINT))
            if getattr(f, "outside", None):
                doc.p("Not named alone: ", *_label(f.candidate.effect, f.candidate.axis),
                      " or an explanation outside the library; this recording fits both about as well and cannot "
                      "tell which.", strong=True)
                rows = []
                for a in f.outside:
                    ho = a.get("held_out")
                    rows.append([(U(a["alternative"]),), a["kind"], (U(a["description"]),),
                                 (U(_alternative_evidence(a)),),
                                 "-" if not ho else f"{ho['chi2_per_residual_with_finding']:.3f} / "
                                                    f"{ho['chi2_per_residual_with_alternative']:.3f}",
                                 (U(a["separating_measurement"]),)])
                doc.table(["alternative outside the library", "kind", "what it is", "how it fits",
                           "held-out χ² per residual: finding / alternative", "measurement that separates them"], rows)
    else:
        doc.p(f"No effect of the library is significant and plausible ({len(d.considered)} candidates tested at a "
              f"family-wise level of {d.settings['alpha']:g}).")
    if getattr(d, "directions", None):
        doc.h(3, "Approach directions")
        doc.p("Every difference between the + and - approaches the mismatch summary reports (beyond 3 standard "
              "errors) and what accounts for it.")
        doc.table(["axis", "difference (baseline)", "accounted", "what accounts for it"],
                  [[e["axis"], f"{e['difference']:+.2f} {pretty(e.get('unit', 'um'))} ({e['z']:.1f} σ)", e["accounted"],
                    (U(e["sentence"].split(": ", 1)[-1]),)] for e in d.directions])
    _noise_section(doc, getattr(d, "noise", None) or {})
    if getattr(d, "unexplained", None) is not None:
        _unexplained_section(doc, d.unexplained)
    if d.skipped or d.untestable:
        doc.h(2, "Candidates not tested")
        doc.ul([("skipped ", *_label(s["effect"], s["axis"]), ": ", U(s["reason"])) for s in d.skipped]
               + [("not testable ", *_label(s["effect"], s["axis"]), ": ", U(s["reason"])) for s in d.untestable])
    doc.h(2, "Figures")
    doc.fig("residuals.png", "Machine-frame residuals (µm) against time (h), before and after the findings, per axis; "
                             "triangles up and down: approached from the + and - side.")
    (folder / "diagnosis.md").write_text(doc.markdown() + "\n")
    (folder / "diagnosis.html").write_text(doc.html(folder, ("Diagnosis of ", U(d.recording))))
    return folder / "diagnosis.md"
