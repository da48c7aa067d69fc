"""Results as text, JSON, Markdown and self-contained HTML (with figures)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .distributions import t_factor
from .errors import make_folder
from .stats import HISTOGRAM_SHORTEST, decimals_for, percent
from .units import display, pretty, shown_unit

from .budget import conformance
from .outputs import (KEEP_SAMPLES_TRIALS, MAIN_OUTPUT, MAX_NOT_CONVERGED, SCALARS, RunResult,  # noqa: F401
                      frame_word, no_certificate_line, not_converged_line, table_frame, too_many_not_converged)


def result_json(res: RunResult) -> dict:
    out = {"statement_kind": statement_kind(res),
           "trials": res.trials, "coverage": res.coverage, "complete": res.complete, "seed": res.spec.get("seed"),
           "not_converged": res.not_converged, "fallbacks": res.fallbacks, "outputs": {}, "budget": res.budget, "convergence": res.convergence}
    if res.weights:
        out["weights"] = res.weights
    if getattr(res, "adaptive", None):
        out["adaptive"] = res.adaptive
    if getattr(res, "executor", None):
        out["executor"] = res.executor
    for k, v in res.outputs().items():
        out["outputs"][k] = {"unit": v["unit"], "description": v["description"], "mean": v["mean"], "std": v["std"],
                             "symmetric": list(v["symmetric"]), "shortest": None if v["shortest"] is None else list(v["shortest"]),
                             "interval_method": interval_method(v)}
    pm = res.acc.moments.get("point_error")
    if pm is not None:
        out["point_error"] = {"unit": "um", "mean": np.asarray(pm.mean).tolist(), "std": np.asarray(pm.std).tolist()}
    par = res.acc.moments.get("parameters")
    if par is not None:
        out["parameters"] = {"names": res.parameter_names, "units": res.parameter_units,
                             "mean": np.asarray(par.mean).tolist(), "std": np.asarray(par.std).tolist()}
    pts = res.points()
    out["validation"] = None
    if pts is not None:
        out["measurand"] = measurand_text(res)
        if (res.spec or {}).get("measurand"):
            out["measurand_tool"] = res.spec["measurand"]
        out["points"] = pts
        out["points_summary"] = points_summary(pts)
        out["validation"] = out["points_summary"].get("clause8")
    feats = features_of(res)
    if feats is not None:  # [[features]] (docs/features.md): only then, so other runs' JSON is unchanged
        out["features"] = feats
    if res.guf is not None:
        out["guf_points"] = {"estimate": np.asarray(res.guf["estimate"]).tolist(), "cov": np.asarray(res.guf["cov"]).tolist(),
                             "unit": "um", "cov_unit": "um**2"}
        if res.guf.get("basis"):
            out["guf_points"]["basis"] = res.guf["basis"]
    return out


def assumed_machine(cfg: dict) -> str:
    """The machine a run assumes, in one sentence, from its configuration (the truth every trial simulates)."""
    ge = cfg.get("geometric_errors") or {}
    if ge.get("coefficients"):
        errors = f"its geometric errors the {len(ge['coefficients'])} explicit coefficients of [geometric_errors.coefficients]"
    else:
        tr, an = ge.get("translational") or [], ge.get("angular") or []
        orders = ", ".join(str(k + 1) for k in range(max(len(tr), len(an)))) or "1, 2, 3"
        rotary = ""
        if cfg.get("rotary"):  # a five-axis machine: its rotary axes' location, orientation and zero errors
            rotary = (f"; rotary axes {', '.join(sorted(cfg['rotary']))}: location offsets "
                      f"{ge.get('rotary_location', '20 um')}, orientation errors {ge.get('rotary_orientation', '30 urad')}, "
                      f"zero errors {ge.get('rotary_zero', '30 urad')}" +
                      (f", stated values {', '.join(sorted(ge['rotary']))}" if ge.get("rotary") else ""))
        errors = ("its geometric errors drawn once from the generation functions ([geometric_errors] seed "
                  f"{ge.get('seed', cfg.get('seed', '-'))}: Legendre coefficients of orders {orders} with standard "
                  f"deviations {', '.join(map(str, tr)) or 'the defaults'} (translational) and "
                  f"{', '.join(map(str, an)) or 'the defaults'} (angular), squareness "
                  f"{ge.get('squareness', 'the default')}{rotary})")
    effects = cfg.get("effects") or {}
    physics = f"; physics added to it: {', '.join(sorted(effects))} ([effects])" if effects else ""
    return (f"a machine of kinematic chain {cfg.get('machine', 'XFYZ')} with {errors}, the same machine in every trial, at "
            f"{cfg.get('reference_temperature', '20 degC')} reference temperature{physics}")


def statement_kind(res) -> dict:
    """What kind of statement a run is: an a priori (virtual-experiment) evaluation of a planned verification on
    an assumed machine, with that machine stated and the GUF agreement as the evidence that the Monte Carlo here
    is a propagation of distributions of a near-linear model."""
    cfg = (res.spec or {}).get("config") or {}
    out = {"kind": "a priori",
           "name": "virtual-experiment evaluation of a planned verification",
           "what": ("every trial simulates the planned verification (plan, tracker station, sources) of an assumed "
                    "machine, identifies it as the real verification would and compensates it: the spread is what "
                    "this verification plan would achieve on that machine (a virtual experiment, VE-DA in Wübbeler "
                    "et al., Metrology 2021), not the uncertainty of a verification that was carried out (that is an "
                    "a posteriori evaluation of its recording, which `run` does not make)"),
           "assumed_machine": assumed_machine(cfg)}
    pts = res.points() if hasattr(res, "points") else None
    if pts and "guf_u" in pts[0]:
        r = np.array([m / g for p in pts for m, g in zip(p["u"]["value"], p["guf_u"]["value"]) if g > 0])
        c8 = [v["passed"] for p in pts for v in p.get("clause8", [])]
        if r.size:
            out["evidence"] = {"u_mcm_over_u_guf": {"median": float(np.median(r)), "min": float(r.min()),
                                                    "max": float(r.max())},
                               "clause8_validated": int(sum(c8)), "of": len(c8),
                               "what": "the law of propagation on the same inputs (guf_points.basis) against the "
                                       "Monte Carlo, per point-axis: where they agree the model is near-linear and "
                                       "the run is the propagation of the stated input distributions"}
    return out


def statement_kind_line(k: dict) -> str:
    ev = k.get("evidence")
    tail = ""
    if ev:
        r = ev["u_mcm_over_u_guf"]
        tail = (f" Evidence: u(MCM)/u(GUF on the same inputs) median {r['median']:.3f} ({r['min']:.3f}-{r['max']:.3f}) "
                f"over the point-axes; clause 8 validated at {ev['clause8_validated']} of {ev['of']}.")
    return (f"Kind of statement: A PRIORI, a {k['name']}: {k['what']}. Assumed machine: {k['assumed_machine']}.{tail}")


def features_of(res: RunResult) -> list | None:
    """The [[features]] statement of a run (mtbudget.features.features_json), None without features."""
    from .features import features_json

    spec = (res.spec or {}).get("features")
    if not spec:
        return None
    if not res.feature_blocks:
        return res.logged_features
    samples = None if any(b is None for b in res.feature_blocks) else np.concatenate(res.feature_blocks)
    return features_json(spec, samples, res.coverage, res.budget)


#: the per-point measurand in one sentence (docs/measurand.md has the definition)
MEASURAND = ("error of the compensated machine at each mesh point, per machine axis (x, y, z), at the verification's "
             "tool offset, given this verification: true minus identified error field, rigid-body part removed "
             "(docs/measurand.md)")


#: a five-axis machine with a rotary table: the frame of the per-point components (docs/measurand.md)
TABLE_FRAME = ("per axis of the workpiece (table) frame (x, y, z: the machine's X, Y, Z with every rotary axis at zero, "
               "turning with the table; at another pose they are not the machine's X, Y, Z, which are stated beside "
               "them: machine_frame)")



def measurand_text(res) -> str:
    """The measurand of this run in one sentence: which tool offset, and what the verification leaves unidentified
    there ([measurand] tool; docs/measurand.md), and from which stations ([[stations]])."""
    spec = res.spec or {}
    return in_frame(measurand_at_tool(spec.get("measurand")) + _stations_clause(spec) + _scales_clause(spec), res)


def in_frame(text: str, res) -> str:
    """A measurand sentence with the frame of this run's components: a turning table's (five-axis) where it is one."""
    return text.replace("per machine axis (x, y, z)", TABLE_FRAME) if table_frame(res) else text


def machine_frame_summary(pts: list) -> dict | None:
    """Five-axis with a rotary table: per machine axis X, Y, Z, the RMS over the mesh and the largest of u in the
    machine frame (the workpiece-frame components turned by the table's orientation at each pose); None otherwise."""
    if not pts or "machine_frame" not in pts[0]:
        return None
    u = np.array([q["machine_frame"]["u"] for q in pts])
    return {"unit": pts[0]["machine_frame"]["unit"], "u_rms_over_mesh": np.sqrt((u**2).mean(axis=0)).tolist(),
            "u_max": u.max(axis=0).tolist(), "u_min": u.min(axis=0).tolist()}


def _scales_clause(spec: dict) -> str:
    scales = (spec.get("config") or {}).get("scales") or {}
    if not scales:
        return ""
    axes = ", ".join(sorted(scales))
    return (f"; the nominal expansion of the {axes} scale(s) ([scales]: CTE about each fixed point) is simulated and "
            "corrected to the reference temperature with the read temperatures; what the correction cannot know "
            "(sensor calibration, CTE uncertainty, drift) is in the budget")


def _several_stations(spec: dict) -> bool:
    """[[stations]] identified over all stations at once: two or more, or an interferometer.  One laser tracker
    alone states the one-tracker problem and is identified as [tracker] is (``Scenario.one_tracker``)."""
    stations = (spec.get("config") or {}).get("stations") or []
    return len(stations) > 1 or any(st.get("kind") != "xyz" for st in stations)


def _idle_sources(spec: dict, rows: list | None = None) -> dict:
    """{source: why its row is zero by construction} for this run: a systematic source that leaves nothing at the mesh
    points (its sentence under the table says why).  (The optimisation-strategy sources act with several [[stations]]
    too: multistation.strategy_settings.)"""
    out = {}
    for r in rows or []:
        if r.get("systematic") and not max(r["u_rms_over_mesh"]) > 1e-6:  # um: nothing but round-off
            out[r["source"]] = "nothing at the mesh points: see how it was bounded, below"
        elif r.get("source") in STRATEGY_AT_MINIMUM and not max(r["u_rms_over_mesh"]) > 1e-3:
            out[r["source"]] = STRATEGY_AT_MINIMUM[r["source"]]
    return out


#: why the optimisation-strategy rows are about zero where they are (docs/model.md, "What the optimisation-strategy
#: sources contribute"): said beside the row, so a reader does not take it for a source that was not evaluated
STRATEGY_AT_MINIMUM = {
    "phase_sequence": "about zero: one and multi-phase end at the same least-squares minimum (docs/model.md)",
    "convergence_criteria": "about zero: the identification iterates every trial to the minimum; a loose Gauss-Newton "
                            "would leave about 1e-4 um (docs/model.md)"}


def _station_rows(cfg: dict, tr: dict) -> list:
    """The Conditions rows of the instruments: the tracker's pose, or one row per station of [[stations]]; the
    stated noise; the scales' nominal expansion ([scales]) where stated."""
    noise = ", ".join(f"{k} {tr[k]}" for k in ("angular", "distance", "distance_per_length") if k in tr) or "defaults"
    stations = cfg.get("stations") or []
    if not stations:
        rows = [f"| tracker pose | D {tr.get('D')}, L {tr.get('L')}, H {tr.get('H')}, a {tr.get('a')}, b {tr.get('b')}, "
                f"d {tr.get('d')} |", f"| tracker noise (k = 1) | {noise} |"]
    else:
        rows = [f"| stations | {len(stations)}, measuring the plan one after the other; the [tracker] noise (k = 1) "
                f"where a station states none: {noise} |"]
        for i, st in enumerate(stations, start=1):
            if st.get("kind") == "xyz":
                place = ", ".join(f"{k} {st.get(k)}" for k in "DLHabd")
            else:
                place = f"position {', '.join(str(v) for v in st.get('position') or [])}, dead path {st.get('dead_path', '0 mm')}"
            own = ", ".join(f"{k} {st[k]}" for k in ("angular", "distance", "distance_per_length") if k in st)
            rows.append(f"| station {i} ({st.get('kind')}) | {md_escape(str(st.get('description') or ''))} {place}"
                        + (f"; its own noise (k = 1): {own}" if own else "") + " |")
    for axis, sc in sorted((cfg.get("scales") or {}).items()):
        rows.append(f"| scale {axis} ([scales]) | CTE {sc.get('cte')} about {sc.get('fixed_point', '0 mm')}, simulated and "
                    "corrected to the reference temperature |")
    return rows


def _stations_clause(spec: dict) -> str:
    stations = (spec.get("config") or {}).get("stations") or []
    if not stations:
        return ""
    if not _several_stations(spec):
        return ("; verified from 1 station (xyz, [[stations]]): its pose identified with the errors by the one-tracker "
                "identification, as [tracker] (its own stated noise; the optimisation strategy's phases and tolerance "
                "apply)")
    kinds = ", ".join(str(st.get("kind")) for st in stations)
    return (f"; verified from {len(stations)} station(s) ({kinds}) measuring the plan one after the other, every "
            "station's pose (xyz) or position and dead path (range) identified with the errors over all stations (the "
            "optimisation strategy's phases and tolerance apply, as with one tracker); the paper's Eq. 27 figures are "
            "means over the laser trackers' points (an interferometer measures a distance, not a point)")


def measurand_at_tool(m: dict | None) -> str:
    if not m:
        return MEASURAND
    tool = ", ".join(f"{v:g}" for v in m["tool"])
    if m.get("verification_tool", True):
        where = f"at the verification's tool offset ({tool}) mm"
    else:
        where = f"at the tool offset ({tool}) mm, which the verification did not use"
    machine = ("error of the compensated machine in use (its repeatability, its reversal from either side and the "
               "residual of its thermal compensation added: source in_use)" if m.get("in_use") else
               "error of the compensated machine")
    text = (f"{machine} at each mesh point, per machine axis (x, y, z), {where}, given this "
            "verification: true minus identified error field, rigid-body part removed (docs/measurand.md)")
    un = m.get("unidentified") or []
    if un:
        by: dict = {}
        for u in un:
            by.setdefault(u.get("identified_by", "a second tool length or a lateral tool offset"), []).append(
                " + ".join(f"{c['weight']:+.2f} {c['iso']}" for c in u["combination"]))
        names = "; ".join(f"{', '.join(v)}, which {k} would identify" for k, v in by.items())
        text += (f". WARNING: {len(un)} combination(s) of geometric errors that this verification cannot identify act "
                 f"at this tool: {names}. Their part is covered only by the prior of the generation functions "
                 "(source unidentified_at_tool), not by the measurement")
    return text


def angles_label(point: dict) -> str:
    """A five-axis point's commanded angles (", a, c = (-90, 0) deg"), empty for three axes."""
    a = point.get("angles")
    if not a:
        return ""
    letters = sorted(a["value"])
    vals = ", ".join(f"{a['value'][r]:g}" for r in letters)
    return f", {', '.join(letters)} = ({vals}) {a['unit']}"


def points_summary(pts: list) -> dict:
    """Volume summaries of the per-point statement: per axis, the RMS over the mesh of u, the largest u and where."""
    u = np.array([p["u"]["value"] for p in pts])  # (M0, 3)
    mean = np.array([p["mean"]["value"] for p in pts])
    worst = int(np.argmax(np.linalg.norm(u, axis=1)))
    out = {"unit": pts[0]["u"]["unit"],
           "u_rms_over_mesh": np.sqrt((u**2).mean(axis=0)).tolist(),
           "u_max": u.max(axis=0).tolist(), "u_min": u.min(axis=0).tolist(),
           "worst_point": {"point": worst, "nominal": pts[worst]["nominal"], "u": pts[worst]["u"]["value"],
                           **({"angles": pts[worst]["angles"]} if "angles" in pts[worst] else {}),
                           "mean": pts[worst]["mean"]["value"]},
           "bias_rms_over_mesh": np.sqrt((mean**2).mean(axis=0)).tolist()}
    mf = machine_frame_summary(pts)
    if mf is not None:  # five-axis with a rotary table: the frame of the above, and the machine's X, Y, Z beside it
        out["frame"] = pts[0]["frame"]
        out["machine_frame"] = mf
    c8 = [v["passed"] for p in pts for v in p.get("clause8", [])]
    if c8:
        out["clause8"] = {"passed": int(sum(c8)), "of": len(c8),
                          "note": "GUF on the same inputs as the MCM: the identification and compensation "
                                  "linearised about the noise-free verification, every source with a first-order "
                                  "effect (guf_points.basis says how each entered)"}
    return out


def _fmt(x, nd=3):
    return "-" if x is None else f"{x:.{nd}g}"


def _vec(v, nd=1) -> str:
    return "(" + ", ".join(f"{x:.{nd}f}" for x in v) + ")"


def _columns(label: str) -> str:
    """The header line of the per-axis u: x, y, z six spaces after the label (as a three-axis run has always printed)."""
    return label + "      x        y        z"


def point_lines(res: RunResult) -> list:
    """The per-point statement as text: what it is, u per axis over the mesh, the worst point, the interval, GUF."""
    pts = res.points()
    if not pts:
        return []
    sm = points_summary(pts)
    u = pretty(sm["unit"])
    k = t_factor(res.coverage, float("inf"))
    half = np.array([[(h - lo) / 2 for lo, h in zip(p["interval"]["low"], p["interval"]["high"])] for p in pts]) \
        if "interval" in pts[0] else None
    nd = decimals_for(min(sm["u_min"]))
    fw = frame_word(res)
    lines = [f"Measurand: {measurand_text(res)}.",
             _columns(f"  {len(pts)} points; standard uncertainty u per axis{fw} (k = 1), {u}:")]
    lines.append("    RMS of u over the mesh                          " + "".join(f"{x:9.{nd}f}" for x in sm["u_rms_over_mesh"]))
    lines.append("    smallest u                                      " + "".join(f"{x:9.{nd}f}" for x in sm["u_min"]))
    lines.append("    largest u                                       " + "".join(f"{x:9.{nd}f}" for x in sm["u_max"]))
    if half is not None:
        label = f"largest half-width of the {percent(res.coverage)} interval"
        lines.append(f"    {label:<48}" + "".join(f"{x:9.{nd}f}" for x in half.max(axis=0))
                     + f"   (coverage {percent(res.coverage)}; {pts[0]['interval']['method']}; a normal would give "
                       f"k = {k:.2f})")
    mf = machine_frame_summary(pts)
    if mf is not None:  # five-axis, rotary table: the same u per machine axis X, Y, Z at each pose
        lines.append("  in the machine frame (X, Y, Z at each pose: the same errors turned by the table's orientation):")
        lines.append("    RMS of u over the mesh                          " + "".join(f"{x:9.{nd}f}" for x in mf["u_rms_over_mesh"]))
        lines.append("    largest u                                       " + "".join(f"{x:9.{nd}f}" for x in mf["u_max"]))
    w = sm["worst_point"]
    lines.append(f"  worst point (the largest u = sqrt(u_x^2 + u_y^2 + u_z^2), {float(np.linalg.norm(w['u'])):.{nd}f} {u}) "
                 f"#{w['point']} at x, y, z = {_vec(w['nominal']['value'], 0)} mm{angles_label(w)}: u = "
                 f"{_vec(w['u'], nd)} {u}{frame_word(res)}, mean (bias) {_vec(w['mean'], nd)} {u}"
                 + (f"; machine frame u = {_vec(pts[w['point']]['machine_frame']['u'], nd)} {u}" if mf is not None else ""))
    if "clause8" in sm:
        c = sm["clause8"]
        lines.append(f"  GUF vs MCM per point and axis (JCGM 101 clause 8, 2 significant digits): {c['passed']} of {c['of']} "
                     f"validated; {c['note']}; {clause8_why(res)}")
    lines.append("  every point and axis: mtbudget run --json (\"points\"), or the report's table")
    return lines


def clause8_why(res) -> str:
    """What the clause 8 comparison means for this run, and what to do before signing (the text and the report)."""
    a = getattr(res, "adaptive", None) or {}
    if a.get("point_axes") and a.get("stopped_at_limit") and a["point_axes_stable"] < a["point_axes"]:
        return (f"this adaptive run stopped at its limit of {a.get('max_trials') or a['trials']} trials with "
                f"{a['point_axes_stable']} of {a['point_axes']} point-axes stable: the MCM's interval ends of the "
                "others are not known to that tolerance (the adaptive run's lines say which, and how to finish)")
    if a.get("point_axes") and a["point_axes_stable"] == a["point_axes"]:
        return ("the MCM's u and interval ends are stable to that tolerance (adaptive run): where the GUF is not "
                "validated the output's distribution is not the normal the GUF assumes (non-linearity, a "
                "hierarchical or non-normal input); quote the MCM there")
    return ("the MCM's interval ends are not known to that tolerance unless the run is adaptive: for a statement "
            "to sign, run `mtbudget run --trials 0` (adaptive on every point-axis, JCGM 101 7.9)")


def adaptive_line(a: dict) -> str:
    """The adaptive run's final line: what stabilised, at how many trials (:func:`adaptive_lines`: and, at its limit,
    what did not and what to do)."""
    what = []
    if a.get("point_axes") is not None:
        what.append(f"{a['point_axes_stable']} of {a['point_axes']} point-axes of the measurand (u and the "
                    f"{100 * a['coverage']:g} % interval ends)")
    what += [f"{o} ({'stable' if ok else 'not stable'})" for o, ok in a.get("outputs_stable", {}).items()]
    if a.get("stopped_at_limit"):
        limit = f" of {a['max_trials']} trials (--max-trials)" if a.get("max_trials") else ""
        head = f"stopped at its limit{limit}, at the end of the batch that reached it, before every quantity was stable, after"
    else:
        head = "every quantity stable at"
    return (f"Adaptive Monte Carlo (JCGM 101 7.9): {head} {a['trials']} trials ({a['batches']} batches of "
            f"{a['batch_trials']}), to {a['ndig']} significant digits of each u: " + "; ".join(what)
            + (f". Note: {a['note']}" if a.get("note") else ""))


def _round_up(n: int, digits: int = 2) -> int:
    """n rounded up to ``digits`` significant digits (a limit to suggest)."""
    if n <= 0:
        return n
    step = 10 ** max(0, len(str(int(n))) - digits)
    return int(math.ceil(n / step) * step)


def adaptive_lines(a: dict) -> list:
    """:func:`adaptive_line` and, for a run stopped at its trial limit, the quantities that were not stable (how many,
    the worst with 2 s, their numerical tolerance and their last change) and how to finish."""
    lines = [adaptive_line(a)]
    if not a.get("stopped_at_limit") or "worst" not in a:
        return lines
    n = a["not_stable"]
    lines.append(f"Not stable: {n} quantit{'y' if n == 1 else 'ies'} (outputs and point-axes); "
                 f"{'the worst' if n > len(a['worst']) else 'each'}, by 2 s (twice the standard deviation of the average "
                 "of its batch values) against the numerical tolerance delta of its u (JCGM 101 7.9.2, 7.9.4), and how "
                 "far the last batch moved that average:")
    for r in a["worst"]:
        un = pretty(r["unit"])
        nd = decimals_for(r["delta"], 1) + 1  # every figure of the row to a decimal below delta's
        lines.append(f"  {r['quantity']}: {r['statistic']}: 2 s = {r['two_s']:.{nd}f} {un} against delta = "
                     f"{r['delta']:.{nd}f} {un} (u = {r['u']:.{nd}f} {un}, k = 1); last change "
                     f"{r['last_change']:+.{nd}f} {un}")
    need = a.get("trials_needed")
    more = (f"`mtbudget run --trials 0 --max-trials {_round_up(max(need, a['trials'] + a['batch_trials']))}` (at the "
            f"rate seen, 2 s falling as 1/sqrt(trials), the worst needs about {need} trials; an estimate); "
            if need else "`mtbudget run --trials 0 --max-trials N` with N above this run's trials; ")
    lines.append("To finish: raise the limit, " + more + f"or quote this run as a run of a fixed {a['trials']} trials "
                 f"(`mtbudget run --trials {a['trials']}` with the same seed draws the same trials; their intervals are "
                 "then quoted with no tolerance checked)")
    return lines


def interval_method(v: dict) -> str:
    """How a scalar output's intervals were computed (a summary of :meth:`stats.Accumulator.summary`)."""
    if v.get("exact_intervals", True):
        return "order statistics of every trial (JCGM 101 7.7.1 symmetric, 7.7.2 shortest)"
    h = v.get("histogram") or {}
    bins = h.get("bins", "a")
    return (f"the run does not keep every value: symmetric from the quantiles of a {bins}-bin histogram, shortest "
            + HISTOGRAM_SHORTEST.format(bins=bins))


def interval_note(outputs: dict, coverage: float) -> list:
    """The lines under the scalar outputs' table that say how its intervals were computed."""
    lines = [f"  {percent(coverage)} coverage intervals: {m}" for m in sorted({interval_method(v) for v in outputs.values()})]
    hist = [v for v in outputs.values() if not v.get("exact_intervals", True) and v.get("histogram")]
    if hist:
        worst = max(v["histogram"]["bin_width"] / v["std"] for v in hist if v["std"] > 0) if any(
            v["std"] > 0 for v in hist) else None
        if worst is not None:
            lines.append(f"  a bin is at most {worst:.2%} of its output's std dev (every trial's value is kept for exact "
                         f"order statistics in runs of up to {KEEP_SAMPLES_TRIALS:,} trials)".replace(",", " "))
    if any(v["shortest"] is None for v in outputs.values()):
        lines.append("  -: no shortest interval: it would reach into values beyond the histogram's range (fixed from "
                     "the first block); the symmetric interval stands")
    return lines


def executor_text(e: dict | None) -> str:
    """What ran a run's trials, with its workers, in words (``RunResult.executor``)."""
    if not e:
        return "not recorded (a log written before mtbudget recorded it, or a run stopped before its end)"
    n, kind = e.get("workers"), e.get("kind")
    what = {"inline": "inline (this process, one core)",
            "thread": f"threads of this process, {n} worker{'s' if n != 1 else ''}",
            "process": f"a local process pool, {n} worker process{'es' if n != 1 else ''}",
            "dask": f"a Dask cluster, {n} worker thread{'s' if n != 1 else ''}"}.get(kind, f"{kind}, {n} workers")
    chosen = " (chosen by --executor auto)" if e.get("requested") == "auto" else ""
    return f"{what}{chosen}; the numbers do not depend on it"


def _root_i(row: dict) -> float:
    """A budget row's square-rooted contribution, whatever its table's basis (rms_i, u_i; u_y in older logs)."""
    return next(row[k] for k in ("rms_i", "u_i", "u_y") if k in row)


def _root_total(table: dict) -> float:
    return next(table[k] for k in ("rms_total", "u_total") if k in table)


def budget_text(res: RunResult) -> str:
    lines = []
    status = "" if res.complete else "  (INCOMPLETE: partial results)"
    lines.append(statement_kind_line(statement_kind(res)))
    lines.append(f"Monte Carlo: {res.trials} trials, coverage probability {percent(res.coverage)}, seed {res.spec.get('seed')}{status}")
    lines.append(f"  trials run by: {executor_text(getattr(res, 'executor', None))}")
    if getattr(res, "adaptive", None):
        lines += ["  " + x for x in adaptive_lines(res.adaptive)]
    elif getattr(res, "stopped_at_limit", False):
        lines.append("  note: the adaptive run stopped at its trial limit before reaching its numerical tolerance")
    if res.fallbacks:
        lines.append(f"  note: {res.fallbacks} of {res.trials} trials left the linear range of the fast identification "
                     "and were solved by full Gauss-Newton (the reference solver)")
    if res.not_converged and too_many_not_converged(res.not_converged, res.trials):  # first: before any number
        lines.insert(0, not_converged_line(res.not_converged, res.trials) + "\n  NOT A STATEMENT TO SIGN: "
                     f"more than {100 * MAX_NOT_CONVERGED:g} % of the trials did not converge; `mtbudget report` "
                     "writes no certificate.xml for this run\n")
    elif res.not_converged:
        lines.append("  " + not_converged_line(res.not_converged, res.trials))
    if res.weights:
        lines.append("  identification weights stated apart from what the run draws ([weights]):")
        for name, w in res.weights.items():
            lines.append(f"    {name:<20} stated {display(w['stated'], w['unit'], shown_unit(w['unit'])):.4g} "
                         f"{pretty(shown_unit(w['unit']))}, drawn {display(w['drawn'], w['unit'], shown_unit(w['unit'])):.4g} "
                         f"{pretty(shown_unit(w['unit']))}")
    lines.append("")
    lines += point_lines(res)
    if (res.spec or {}).get("features"):
        from .features import features_text

        lines += features_text(features_of(res))
    pb = res.budget.get("points")
    if pb:
        lines.append("")
        lines.append(f"Budget of the per-point measurand, each source alone on the same trials ({pretty(pb['unit'])}, k = 1):")
        lines.append(f"  {'source':<32} {'group':<22} {'u_i, RMS over the mesh (x, y, z)':>34} {'share':>7}")
        if table_frame(res):
            lines.append("  (x, y, z: the workpiece (table) frame, as the statement above; no budget in the machine frame)")
        idle = _idle_sources(res.spec or {}, pb["rows"])
        for r in sorted(pb["rows"], key=lambda r: -r["share"]):
            lines.append(f"  {r['source']:<32} {r['group']:<22} {_vec(r['u_rms_over_mesh'], 2):>34} {r['share']:7.1%}"
                         + (f"  ({idle[r['source']]})" if r["source"] in idle else ""))
        lines.append(f"  {'interaction (not additive)':<32} {'':<22} {'':>34} {pb['interaction_share']:7.1%}")
        lines.append(f"  {'total':<32} {'':<22} {_vec(pb['total']['u_rms_over_mesh'], 2):>34} {1:7.1%}")
        lines.append("  by group: " + ", ".join(f"{g['group']} {g['share']:.1%}" for g in pb["groups"]))
        lines.append(f"  share: of the variance of the per-point errors summed over points and axes, on the budget's "
                     f"{pb.get('trials', 'first')} trials (the total's u can differ in its last digit from the "
                     "statement above, which uses every trial)")
        for k in pb.get("systematic", []):
            lines.append(f"  systematic, {k['systematic']} ({', '.join(k['sources'])}): u_i {_vec(k['u_rms_over_mesh'], 2)} "
                         f"{pretty(pb['unit'])} RMS over the mesh (k = 1), {k['share']:.1%}; how each was bounded:")
            lines += [f"    {name}: {sentence}" for name, sentence in k["bounded"].items()]
    lines.append("")
    lines.append("Volume summaries and the paper's figures, per verification (the spread is over simulated verifications;")
    lines.append("it is not the uncertainty of a point):")
    lines.append(f"{'output':<20} {'unit':<5} {'mean':>9} {'std dev':>9}   {'symmetric interval':>22}   {'shortest interval':>22}")
    for key, v in res.outputs().items():
        nd = decimals_for(v["std"])  # the spread to 2 significant digits, the rest to the same decimal (JCGM 101 7.9.2)
        sym = f"[{v['symmetric'][0]:.{nd}f}, {v['symmetric'][1]:.{nd}f}]"
        sh = "-" if v["shortest"] is None else f"[{v['shortest'][0]:.{nd}f}, {v['shortest'][1]:.{nd}f}]"
        lines.append(f"{key:<20} {pretty(v['unit']):<5} {v['mean']:9.{nd}f} {v['std']:9.{nd}f}   {sym:>22}   {sh:>22}")
    lines += interval_note(res.outputs(), res.coverage)
    b = res.budget.get(MAIN_OUTPUT)
    if b:
        lines.append("")
        lines.append(f"Budget of {MAIN_OUTPUT} ({pretty(b['unit'])}), one source at a time on {b['trials']} trials, "
                     f"by {b['basis'].replace('_', ' ')} (an RMS contribution per source, not a standard uncertainty):")
        lines.append(f"  {'source':<32} {'group':<22} {'u(x_i)':>14} {'RMS_i':>8} {'share':>7}")
        for r in sorted(b["rows"], key=lambda r: -r["contribution"]):
            ux = "-" if r["u_x"] is None else f"{r['u_x']['value']:.3g} {pretty(r['u_x']['unit'])}"
            lines.append(f"  {r['source']:<32} {r['group']:<22} {ux:>14} {_root_i(r):8.3f} {r['share']:7.1%}")
        lines.append(f"  {'interaction (not additive)':<32} {'':<22} {'':>14} "
                     f"{math.copysign(math.sqrt(abs(b['interaction'])), b['interaction']):8.3f} "
                     f"{(b['interaction'] / b['total'] if b['total'] else 0):7.1%}")
        lines.append(f"  {'total':<32} {'':<22} {'':>14} {_root_total(b):8.3f} {1:7.1%}")
        lines.append("  by group: " + ", ".join(f"{g['group']} {g['share']:.1%}" for g in b["groups"]))
    if getattr(res, "log_path", None):
        lines.append("")
        lines.append(f"run log: {res.log_path}  (mtbudget replay / mtbudget report)")
    return "\n".join(lines)


def _save(plt, fig, folder, name: str) -> Path:
    """Lay out, save (100 dpi) and close a report figure; its path."""
    fig.tight_layout()
    path = Path(folder) / name
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _pose_map(plt, pts: list, u: np.ndarray, folder: Path, um: str, mframe: bool = False) -> Path:
    """Five-axis: the largest u (k = 1) over the linear points at each rotary pose, per axis, as a grid of the first
    two rotary axes' angles (one row for a single rotary axis)."""
    letters = sorted(pts[0]["angles"]["value"])
    ang = np.array([[q["angles"]["value"][r] for r in letters] for q in pts])
    rows = np.unique(np.round(ang[:, 0], 9))
    cols = np.unique(np.round(ang[:, 1], 9)) if len(letters) > 1 else np.array([0.0])
    grid = np.zeros((3, len(rows), len(cols)))
    for q in range(len(pts)):
        i = int(np.searchsorted(rows, round(ang[q, 0], 9)))
        j = int(np.searchsorted(cols, round(ang[q, 1], 9))) if len(letters) > 1 else 0
        grid[:, i, j] = np.maximum(grid[:, i, j], u[q])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    vmax = float(grid.max())
    for k, a in enumerate("xyz"):
        im = axes[k].imshow(grid[k], cmap="viridis", vmin=0, vmax=vmax, origin="lower", aspect="auto")
        axes[k].set_yticks(range(len(rows)), [f"{v:g}" for v in rows])
        axes[k].set_ylabel(f"{letters[0]} commanded [deg]")
        if len(letters) > 1:
            axes[k].set_xticks(range(len(cols)), [f"{v:g}" for v in cols])
            axes[k].set_xlabel(f"{letters[1]} commanded [deg]")
        axes[k].set_title(f"largest u of the {a.upper() + ' (machine frame)' if mframe else a} error\nover the linear "
                          "points (k = 1)", fontsize=9)
        fig.colorbar(im, ax=axes[k], shrink=0.8, label=f"u [{um}]")
    fig.suptitle("standard uncertainty of the compensated machine at each rotary pose")
    return _save(plt, fig, folder, "uncertainty_poses.png")


def _figures(res: RunResult, folder):
    """PNG figures of a run; returns {name: path}. Every axis is labelled with its unit (one spelling: µm)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    figs = {}
    um = pretty("um")
    pts = res.points()
    # the per-point statement: u of each axis over the mesh (the map a metrologist looks at first)
    if pts and res.mesh is not None:
        # five-axis with a rotary table: the machine's X, Y, Z at each pose (the table frame's x at c = 90 deg is Y)
        mframe = "machine_frame" in pts[0]
        u = np.array([q["machine_frame"]["u"] if mframe else q["u"]["value"] for q in pts])
        cmd = np.array([q["nominal"]["value"] for q in pts])
        if "angles" in pts[0]:  # five-axis: the largest u over the rotary poses at each linear point
            uniq, inv = np.unique(np.round(cmd, 6), axis=0, return_inverse=True)
            inv = np.ravel(inv)
            u_pt = np.zeros((len(uniq), 3))
            np.maximum.at(u_pt, inv, u)
            cmd_plot, u_plot = uniq, u_pt
        else:
            cmd_plot, u_plot = cmd, u
        fig = plt.figure(figsize=(15, 4.8))
        vmax = float(u.max())
        for j, a in enumerate("xyz"):
            ax = fig.add_subplot(1, 3, j + 1, projection="3d")
            sc = ax.scatter(cmd_plot[:, 0], cmd_plot[:, 1], cmd_plot[:, 2], c=u_plot[:, j], cmap="viridis", vmin=0,
                            vmax=vmax, s=45)
            ax.set_title(f"u of the {a.upper() + ' (machine frame)' if mframe else a} error\nafter compensation (k = 1)",
                         fontsize=9)  # two lines: one line was clipped at the figure's left edge
            ax.set_xlabel("x [mm]", labelpad=6)
            ax.set_ylabel("y [mm]", labelpad=6)
            ax.set_zlabel("z [mm]", labelpad=6)
            fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.12, label=f"u [{um}]")
        fig.suptitle("standard uncertainty per point and axis of the compensated machine (commanded positions)"
                     + ("; largest u over the rotary poses at each point" if "angles" in pts[0] else ""))
        figs["uncertainty_map"] = _save(plt, fig, folder, "uncertainty_map.png")
        if "angles" in pts[0]:
            figs["uncertainty_poses"] = _pose_map(plt, pts, u, folder, um, mframe)
    # distributions of the volume summaries
    names = [k for k in SCALARS if res.acc.scalar_samples(k) is not None]
    if names:
        fig, axes = plt.subplots(2, 4, figsize=(14, 6.5))
        for ax, k in zip(axes.ravel(), names):
            y = res.acc.scalar_samples(k)
            ax.hist(y, bins=60, density=True, color="#7aa6c2", label="MCM")
            lo, hi = res.summary(k)["symmetric"]
            ax.axvline(lo, color="k", ls="--", lw=1)
            ax.axvline(hi, color="k", ls="--", lw=1, label=f"{percent(res.coverage)} interval")
            ax.set_title(k, fontsize=9)
            unit = pretty(SCALARS[k][0])
            ax.set_xlabel(f"{k} [{unit}]" if unit else k)
            ax.set_ylabel(f"probability density [1/{unit}]" if unit else "probability density")
            ax.legend(fontsize=6)
        for ax in axes.ravel()[len(names):]:
            ax.axis("off")
        figs["distributions"] = _save(plt, fig, folder, "distributions.png")
    # contributions to the per-point measurand, by source, coloured by group
    pb = res.budget.get("points")
    if pb:
        from matplotlib.patches import Patch

        rows = sorted(pb["rows"], key=lambda r: r["share"])
        fig, ax = plt.subplots(figsize=(8, 0.32 * len(rows) + 1.5))
        colours = {"machine tool": "#1f77b4", "measurement system": "#ff7f0e", "measurement strategy": "#2ca02c",
                   "optimisation strategy": "#9467bd"}
        ax.barh([r["source"] for r in rows], [r["share"] * 100 for r in rows],
                color=[colours.get(r["group"], "grey") for r in rows])
        ax.set_xlabel("share of the variance of the per-point errors, summed over points and axes [%]")
        ax.legend(handles=[Patch(color=c, label=g) for g, c in colours.items()], fontsize=7, loc="lower right")
        figs["contributions"] = _save(plt, fig, folder, "contributions.png")
    # convergence of the main volume summary
    if res.convergence:
        c = res.convergence
        n = [x["trials"] for x in c]
        fig, ax = plt.subplots(1, 2, figsize=(11, 3.5))
        ax[0].plot(n, [x["mean"] for x in c], "o-", ms=3, label="mean")
        ax[0].plot(n, [x["low"] for x in c], "v--", ms=3, label="interval low")
        ax[0].plot(n, [x["high"] for x in c], "^--", ms=3, label="interval high")
        ax[1].plot(n, [x["std"] for x in c], "o-", ms=3, color="k", label="standard deviation over trials")
        if len(n) < 2:  # one block: a point, not a curve; say so instead of drawing an empty axis
            for a in ax:
                a.text(0.5, 0.9, "one block only: run more trials to see convergence", transform=a.transAxes,
                       ha="center", fontsize=8, color="#555")
        for a in ax:
            a.set_xlabel("trials")
            a.legend(fontsize=7)
        ax[0].set_ylabel(f"{MAIN_OUTPUT} [{um}]")
        ax[1].set_ylabel(f"standard deviation of {MAIN_OUTPUT} [{um}]")
        fig.suptitle("convergence of the Monte Carlo estimate")
        fig.tight_layout(rect=(0, 0, 1, 0.94))
        figs["convergence"] = folder / "convergence.png"
        fig.savefig(figs["convergence"], dpi=100)
        plt.close(fig)
    return figs


def _span(v, sep=" to ") -> str:
    """A configuration value as a person writes it: ["800 mm", "1200 mm"] -> 800 mm to 1200 mm; a vector in brackets."""
    if isinstance(v, (list, tuple)):
        text = sep.join(_span(x) for x in v)
        return f"({text})" if sep != " to " else text
    return md_escape(str(v))


def _statement_tool(res, cfg) -> str:
    m = (res.spec or {}).get("measurand")
    if m:
        return "(" + ", ".join(f"{v:g} mm" for v in m["tool"]) + ")" + (
            "" if m.get("verification_tool", True) else " ([measurand] tool, not a tool of the verification)")
    return _span((cfg.get("plan", {}).get("tools") or [["0 mm"] * 3])[0], ", ")


def provenance_lines(res: RunResult) -> list:
    """Where the numbers come from: configuration, machine, mesh, tracker, sources, seed, versions, date."""
    import hashlib
    import json as _json
    import time

    from . import __version__

    cfg = res.spec.get("config") or {}
    digest = hashlib.sha256(_json.dumps(cfg, sort_keys=True, default=str).encode()).hexdigest()[:16]
    tr = cfg.get("tracker", {})
    mesh = cfg.get("mesh", {})
    lines = ["## Conditions", "", "| item | value |", "| --- | --- |",
             f"| configuration | {md_escape(res.spec.get('config_path') or '(built in code)')} "
             f"({md_escape(cfg.get('name', '-'))}; sha256 {digest}) |",
             f"| machine | {cfg.get('machine', 'XFYZ')} |",
             f"| mesh | x {_span(mesh.get('x'))}, y {_span(mesh.get('y'))}, z {_span(mesh.get('z'))}, "
             f"step {_mesh_step(mesh)} |",
             f"| tool offset of the statement | {_statement_tool(res, cfg)} |",
             *_station_rows(cfg, tr),
             f"| sources drawn | {', '.join(res.spec.get('sources') or []) or 'none'} |",
             f"| trials, seed, coverage | {res.trials}, {res.spec.get('seed')}, {percent(res.coverage)} |",
             f"| trials run by | {md_escape(executor_text(getattr(res, 'executor', None)))} |",
             f"| mtbudget | {__version__} |", f"| report written | {time.strftime('%Y-%m-%d %H:%M %Z')} |"]
    if res.weights:
        lines.append("| identification weights | stated apart from the drawn noise: " + "; ".join(
            f"{k} {display(w['stated'], w['unit'], shown_unit(w['unit'])):.3g} vs {display(w['drawn'], w['unit'], shown_unit(w['unit'])):.3g} "
            f"{pretty(shown_unit(w['unit']))}" for k, w in res.weights.items()) + " |")
    return lines


def _mesh_step(mesh: dict) -> str:
    """The mesh's step as the configuration states it: one step, or one per axis (step_x, step_y, step_z)."""
    if "step" in mesh:
        return _span(mesh["step"])
    per = [f"{a} {_span(mesh[f'step_{a}'])}" for a in "xyz" if f"step_{a}" in mesh]
    return ", ".join(per) if per else "-"


#: the kind of statement a report of a run log makes (a run simulates a planned verification)
A_PRIORI = ("a priori: the uncertainty of a planned verification, evaluated before it is measured by {n} Monte Carlo "
            "trials (JCGM 101) of the simulated verification; it states what the verification will achieve, not the "
            "result of a measurement")


def report_fields(res) -> dict:
    """The [report] table of the run's configuration (laboratory, instrument, customer, ...): {} when absent."""
    cfg = (res.spec or {}).get("config") or {}
    rep = cfg.get("report") if isinstance(cfg, dict) else None
    return rep if isinstance(rep, dict) else {}


def headline(res, tolerance_um: float | None = None, characteristic: str = "component") -> dict:
    """The statement in brief a laboratory issues: kind of statement, measurand in words, result, U with k and
    coverage (two significant digits), the decision and its rule, and the [report] fields (or "not stated")."""
    cfg = (res.spec or {}).get("config") or {}
    return statement_in_brief(
        kind="a priori", kind_text=A_PRIORI.format(n=res.trials), measurand=measurand_text(res), points=res.points(),
        coverage=res.coverage, frame=table_frame(res), statement=res, tolerance_um=tolerance_um,
        characteristic=characteristic, fields=report_fields(res),
        machine=f"machine tool of kinematic chain {cfg.get('machine', 'XFYZ')} (no name stated)", date=run_date(res),
        command="mtbudget report", trials=res.trials,
        warning=not_converged_line(res.not_converged, res.trials) if res.not_converged else None)


def longer_tails_than_normal(half: np.ndarray, U: np.ndarray, trials: int | None) -> bool:
    """Whether some point-axis' Monte Carlo half-width exceeds its U = k u by more than the trials' own scatter can
    explain: a distribution with longer tails than the normal that k assumes.  The ratio half / U of a normal
    component is 1.96 / 2 at 95 %; its relative standard deviation from n trials is about 1.2 / sqrt(n) (the interval
    ends' order statistics, 0.96 / sqrt(n) for the half-width, and u's 0.71 / sqrt(n)); a ratio above
    1 + 4 x 1.2 / sqrt(n) at some point-axis is said (about 1 in 150 runs of 225 normal point-axes would cross
    it by chance).  Unknown trials: nothing is said."""
    if not trials or trials < 2:
        return False
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(U > 0, half / U, 0.0)
    return bool(np.nanmax(r) > 1.0 + 4.0 * 1.2 / math.sqrt(trials))


def statement_in_brief(*, kind: str, kind_text: str, measurand: str, points: list | None, coverage: float,
                       frame: bool, statement, tolerance_um: float | None, characteristic: str, fields: dict,
                       machine: str, date: str, command: str, warning: str | None = None,
                       trials: int | None = None) -> dict:
    """The statement in brief of either kind of statement (:func:`headline` of a run, :func:`posterior_headline` of a
    recording): from what both have, its per-point statement (mean, u, coverage interval of each component at each
    mesh point), its coverage probability, its decision (:func:`mtbudget.budget.conformance` on ``statement``), its
    [report] ``fields``, the ``machine`` and ``date`` it says where [report] states none, the ``command`` whose
    --tolerance gives a decision, and a ``warning`` that must be read before signing."""
    pts = points
    out = {"kind": kind, "kind_text": kind_text, "measurand": measurand}
    if warning:
        out["warning"] = warning
    if pts and "interval" in pts[0]:
        u = np.array([q["u"]["value"] for q in pts])
        mean = np.array([q["mean"]["value"] for q in pts])
        half = np.array([[(h - lo) / 2 for lo, h in zip(q["interval"]["low"], q["interval"]["high"])] for q in pts])
        k, k_text = coverage_factor(coverage)
        U = k * float(u.max())
        nd = decimals_for(U)
        unit = pretty(pts[0]["u"]["unit"])
        out.update(unit=unit, points=len(pts), U_max=round(U, nd), U_rms=round(k * float(np.sqrt((u ** 2).mean())), nd),
                   half_width_max=round(float(half.max()), nd), bias_max=round(float(np.abs(mean).max()), nd),
                   k=k, k_text=k_text, coverage=coverage, decimals=nd)
        out["result_text"] = (f"the error of each component (x, y, z{', workpiece (table) frame' if frame else ''}) "
                              f"at each of the {len(pts)} mesh points after "
                              f"compensation is estimated by the mean of the trials: at most {out['bias_max']:.{nd}f} "
                              f"{unit} from zero")
        where = " of the workpiece (table) frame" if frame else ""
        out["U_text"] = (f"U = {out['U_max']:.{nd}f} {unit} ({k_text}), the largest over the mesh points and axes{where} "
                         f"(U = {k:g}u); RMS over the mesh {out['U_rms']:.{nd}f} {unit}; the largest half-width of the "
                         f"Monte Carlo {percent(coverage)} coverage intervals is {out['half_width_max']:.{nd}f} {unit}")
        if longer_tails_than_normal(half, k * u, trials):
            out["U_text"] += (f" (larger than U: somewhere the distribution is not normal and U = {k:g}u covers less "
                              f"than {percent(coverage)}; quote the Monte Carlo intervals, JCGM 101 7.7, not U)")
        if frame and "machine_frame" in pts[0]:  # the same errors in the machine's X, Y, Z at each pose: their U too
            um = max(max(q["machine_frame"]["u"]) for q in pts)
            out["U_machine_max"] = round(k * um, nd)
            out["U_text"] += (f"; in the machine's X, Y, Z at each pose the largest U (= {k:g}u) is "
                              f"{out['U_machine_max']:.{nd}f} {unit}")
    if tolerance_um is not None:
        from .budget import conformance

        conf = conformance(statement, tolerance_um, characteristic)
        out["decision"], out["rule"] = conf["statement"], conf["rule"]
    else:
        out["decision"] = f"none: no tolerance was given ({command} --tolerance \"20 um\")"
        out["rule"] = "ISO 14253-1, applied when a tolerance is given"
    f = fields
    ins = f.get("instrument") if isinstance(f.get("instrument"), dict) else {}
    out["fields"] = {
        "laboratory": f.get("laboratory"), "customer": f.get("customer"), "operator": f.get("operator"),
        "machine": f.get("machine") or machine,
        "instrument": ", ".join(x for x in (ins.get("model"), ins.get("serial") and f"serial {ins['serial']}",
                                            ins.get("calibration") and f"calibration: {ins['calibration']}") if x) or None,
        "date": f.get("date") or date, "traceability": f.get("traceability"),
        "certificate": f.get("certificate"), "country": f.get("country"), "location": f.get("location")}
    out["fields"]["date_stated"] = bool(f.get("date"))
    return out


#: the kind of statement of a recording's a posteriori statement (mtbudget.posterior)
A_POSTERIORI = ("a posteriori: the uncertainty of the compensated machine that the recorded verification {recording} "
                "(points.csv sha256 {sha}) identified, evaluated after it was measured (JCGM 101, {n} trials): {what}")


def posterior_headline(post, tolerance_um: float | None = None, characteristic: str = "component") -> dict:
    """The statement in brief of an a posteriori statement (:class:`mtbudget.posterior.Posterior`), by the code of a
    run's (:func:`statement_in_brief`): its recording and points.csv digest as the kind of statement, its measurand
    (the workpiece frame of a five-axis table with the machine frame beside it), U = k u from its own per-point u, the
    decision from its own intervals and trials, recording.toml's [report] fields, and the chi-square test's warning
    where the fit fails it."""
    import time

    p = post.data
    k = p["statement_kind"]
    pts = p["points"]
    return statement_in_brief(
        kind="a posteriori",
        kind_text=A_POSTERIORI.format(recording=k["recording"], sha=k.get("points_csv_sha256") or "-", n=p["trials"],
                                      what=k["what"]),
        measurand=f"{p['measurand']} ({p['not_identifiable']} combination(s) not identifiable)",
        points=pts, coverage=p["coverage"], frame=bool(pts) and "frame" in pts[0], statement=post,
        tolerance_um=tolerance_um, characteristic=characteristic, fields=p.get("report") or {},
        machine=f"machine tool of kinematic chain {p.get('machine', 'XFYZ')} (no name stated)",
        date=time.strftime("%Y-%m-%d"), command="mtbudget posterior", trials=p["trials"],
        warning="; ".join(w for w in (((p.get("identification") or {}).get("fit_test") or {}).get("warning"),
                                      not_converged_line(p["not_converged"], p["trials"])
                                      if p.get("not_converged") else None) if w) or None)


def _date_said(h: dict) -> str:
    """The statement's date as the statement in brief gives it: stated, or what the date is when [report] states none
    (a run: the date it was run, the only date an a priori evaluation has; a recording: not stated, since its date
    is the measurement's, which the evaluation's date is not)."""
    f = h["fields"]
    if f.get("date_stated", True):
        return md_escape(f["date"])
    if h.get("kind") == "a posteriori":
        return (f"not stated (the date of the measurement: [report] date in recording.toml); this evaluation ran on "
                f"{md_escape(f['date'])}")
    return md_escape(f["date"]) + " (the date this evaluation was run; [report] date not stated)"


def coverage_factor(p: float) -> tuple:
    """(k, what it says) of an expanded uncertainty U = k u at the run's coverage probability p: k = 2 for the
    customary 95 % (about 95.45 % for a normal distribution), else the normal quantile of (1 + p) / 2 to two decimals
    (2.58 for 99 %), so that U and the run's Monte Carlo coverage intervals state one coverage probability."""
    from statistics import NormalDist

    if abs(float(p) - 0.95) < 1e-12:
        return 2.0, "k = 2, coverage probability about 95 % for a normal distribution"
    k = round(NormalDist().inv_cdf((1.0 + float(p)) / 2.0), 2)
    return k, f"k = {k:g}, coverage probability about {percent(p)} for a normal distribution"


def run_date(res) -> str:
    """The date the evaluation was computed (YYYY-MM-DD): its run log's start, else today (a run reported as it
    ends).  What the statement gives when ``[report] date`` is not stated, said as such: an a priori evaluation
    measures nothing, so the only date it has is its own."""
    import time

    start = str(((getattr(res.log, "metadata", None) or {}).get("start_time")) or "")
    return start[:10] if len(start) >= 10 else time.strftime("%Y-%m-%d")


def headline_lines(h: dict) -> list:
    """The statement in brief as a Markdown table (first thing in the report)."""
    def said(key, hint):
        v = h["fields"].get(key)
        return md_escape(v) if v else f"not stated ([report] {hint})"

    rows = [("kind of statement", md_escape(h["kind_text"])), ("measurand", md_escape(h["measurand"]))]
    if h.get("warning"):
        rows.insert(0, ("WARNING", f"**{md_escape(h['warning'])}**"))
    if "U_text" in h:
        rows += [("result", md_escape(h["result_text"])), ("expanded uncertainty", f"**{md_escape(h['U_text'])}**")]
    rows += [("decision", md_escape(h["decision"])), ("decision rule", md_escape(h["rule"])),
             ("laboratory", said("laboratory", "laboratory")), ("instrument", said("instrument", "instrument.model, serial, calibration")),
             ("machine", md_escape(h["fields"]["machine"])), ("customer", said("customer", "customer")),
             ("operator", said("operator", "operator")), ("date", _date_said(h)),
             ("traceability", said("traceability", "traceability")), ("certificate", said("certificate", "certificate"))]
    return ["## Statement in brief", "", "| | |", "| --- | --- |"] + [f"| {k} | {v} |" for k, v in rows] + [""]


#: a caption for every figure mtbudget writes (the alt text and the caption in the HTML)
CAPTIONS = {
    "uncertainty_map": "Standard uncertainty (k = 1) of the compensated machine's error at each mesh point, per axis, "
                       "at the commanded positions (a five-axis plan: the largest over the rotary poses)",
    "uncertainty_poses": "Five-axis: the largest standard uncertainty (k = 1) over the linear points at each rotary pose, "
                         "per axis",
    "distributions": "Distributions over the simulated verifications of the volume summaries, with their coverage intervals",
    "contributions": "Share of each source in the variance of the per-point errors, coloured by the paper's four groups",
    "convergence": "Convergence of compensation_rms and of its standard deviation with the number of trials",
    "residual_vs_U": "Fit residual (measured - identified model) at the recording's points per axis, with its expanded "
                     "uncertainty U (k = 2)",
}


def md_escape(text: str) -> str:
    """A user string (a recording or configuration name) safe inside Markdown, mid-line: no markup, no HTML.

    Escaped: HTML's ``&`` and ``<``, and what makes markup mid-line (emphasis, code, links and images through
    ``[``, table cells, mathtext ``$``); parentheses, ``#``, ``+`` and quotes stay as they are, readable in
    the plain Markdown (they only act at a line start or after ``]``, which is escaped)."""
    import html

    out = html.escape(str(text), quote=False)
    for ch in "\\`*_[]|$":
        out = out.replace(ch, "\\" + ch)
    return out


def write_html(md: list, folder: Path, path: Path, title: str):
    """The Markdown lines as a self-contained HTML page: tables as tables, figures inlined with their captions."""
    import base64
    import html

    body = []
    for line in md:
        if line.startswith("# "):
            body.append(f"<h1>{html.escape(_unescape_md(line[2:]))}</h1>")
        elif line.startswith("### "):
            body.append(f"<h3>{html.escape(_unescape_md(line[4:]))}</h3>")
        elif line.startswith("## "):
            body.append(f"<h2>{html.escape(_unescape_md(line[3:]))}</h2>")
        elif line.startswith("| ---"):
            continue
        elif line.startswith("|"):
            # split on the table's pipes only: a user string keeps its own as "\|" (md_escape)
            cells = [c.strip() for c in _cells(line)]
            tag = "td"
            if not body or not (body[-1].startswith("<tr") or body[-1].startswith("<table")):
                body.append('<table class="budget">')
                tag = "th"
            body.append("<tr>" + "".join(f"<{tag}>{html.escape(_unescape_md(c.replace('**', '')))}</{tag}>" for c in cells) + "</tr>")
        elif line.startswith("!["):
            caption = _unescape_md(line[2:line.index("](")])
            name = line[line.index("](") + 2:-1]
            b64 = base64.b64encode((folder / name).read_bytes()).decode()
            body.append(f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{b64}">'
                        f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        else:
            if body and body[-1].startswith("<tr"):
                body.append("</table>")
            if line.strip():
                body.append(f"<p>{html.escape(_unescape_md(line.replace('**', '')))}</p>")
    if body and body[-1].startswith("<tr"):
        body.append("</table>")
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>" + html.escape(title) + "</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
            "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:3px 8px;font-size:13px}"
            "th{background:#eef}img{max-width:100%}figcaption{font-size:13px;color:#444}</style>"
            "<script>window.addEventListener('load',function(){var im=document.images,ok=0;"
            "for(var i=0;i<im.length;i++){if(im[i].complete&&im[i].naturalWidth>0)ok++;}"
            "document.body.setAttribute('data-images',ok+'/'+im.length);"
            "document.body.setAttribute('data-tables',document.querySelectorAll('table.budget').length);});</script>"
            "</head><body>" + "\n".join(body) + "</body></html>")
    path.write_text(page)


def _cells(line: str) -> list:
    """The cells of a Markdown table row: split on the pipes not escaped with a backslash."""
    import re

    body = line.strip()
    body = body[1:] if body.startswith("|") else body
    body = body[:-1] if body.endswith("|") and not body.endswith("\\|") else body
    return re.split(r"(?<!\\)\|", body)


def compensation_lines(table: dict) -> list:
    """Markdown: the compensated machine's residual against its U (k = 2) per axis, from
    ``CompensationTable.to_dict()`` (``residual_against_U``), and the --check (``check``) when there is one."""
    res = table.get("residual_against_U") or {}
    axes = res.get("axes") or {}
    if not axes:
        return []
    md = ["", "## Fit residual at the recording's points against its uncertainty", "",
          f"Recording {md_escape(table.get('recording', '-'))}: {md_escape(res['what'])}. Values in µm.", "",
          "| axis | points | RMS residual | max \\|residual\\| | median U (k = 2) | max \\|residual\\|/U | within U | expected |",
          "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for a, d in axes.items():
        md.append(f"| {a.upper()} | {d['points']} | {d['rms_residual']:.2f} | {d['max_abs_residual']:.2f} | "
                  f"{d['median_U']:.2f} | {d['max_abs_residual_over_U']:.2f} | {d['within_U']:.1%} | "
                  f"{d['expected_within_U']:.1%} |")
    chk = table.get("check")
    if chk:
        md += ["", f"Round trip (`--check`, format {md_escape(chk['format'])}): the written tables applied to the simulated "
                   "machine; error left on each table's line against the table's stated u (k = 1), µm.", "",
               "| line | before max \\|e\\| | after max \\|e\\| | max \\|e\\|/u | within 2u |", "| --- | --- | --- | --- | --- |"]
        for k, d in {**chk.get("axes", {}), **chk.get("cross", {})}.items():
            md.append(f"| {k.upper() if len(k) == 1 else k} | {d['max_abs_before_um']:.2f} | {d['max_abs_after_um']:.2f} | "
                      f"{d['max_abs_z']:.2f} | {d['within_2u']:.0%} |")
    return md


def compensation_figure(table, folder) -> Path | None:
    """residual_vs_U.png: per axis, the residual at the recording's points and +-U (k = 2) against position."""
    if not table.residual:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, len(table.residual), figsize=(4 * len(table.residual), 3.2), squeeze=False)
    for ax, (a, r) in zip(axs[0], table.residual.items()):
        order = np.argsort(r.positions, kind="stable")
        ax.plot(r.positions[order], r.residual[order], ".", ms=3, label="residual")
        ax.plot(r.positions[order], r.U[order], "k-", lw=0.6, label="±U (k = 2)")
        ax.plot(r.positions[order], -r.U[order], "k-", lw=0.6)
        ax.set_xlabel(f"{a} commanded [mm]")
        ax.set_ylabel(f"residual along {a} [µm]")
        ax.legend(fontsize=6)
    fig.suptitle("fit residual at the recording's points (measured - identified model) and its U (k = 2)")
    return _save(plt, fig, folder, "residual_vs_U.png")


def compensation_report(table, folder, check: dict | None = None) -> dict:
    """compensation.md and a self-contained compensation.html (with residual_vs_U.png) for a compensation table."""
    folder = make_folder(folder)
    data = table.to_dict()
    if check is not None:
        data["check"] = check
    md = [f"# Compensation of {md_escape(table.recording)}", ""] + compensation_lines(data)
    fig = compensation_figure(table, folder)
    if fig is not None:
        md += ["", "## Figures", "", f"![{md_escape(CAPTIONS['residual_vs_U'])}]({fig.name})"]
    (folder / "compensation.md").write_text("\n".join(md) + "\n")
    write_html(md, folder, folder / "compensation.html", f"mtbudget compensation of {table.recording}")
    return {"markdown": folder / "compensation.md", "html": folder / "compensation.html", "figure": fig}


def _unescape_md(text: str) -> str:
    import html
    import re

    return html.unescape(re.sub(r"\\(.)", r"\1", text))


def run_report(res: RunResult, folder, tolerance_um: float | None = None, characteristic: str = "component",
               extra_figures: dict | None = None, compensation: dict | None = None) -> dict:
    """Write report.md and a self-contained report.html (figures inlined) into ``folder``.

    extra_figures: name -> (PNG path in ``folder``, caption), e.g. the paper study's figures.
    """
    folder = make_folder(folder)
    figs = _figures(res, folder)
    data = result_json(res)
    kind = data["statement_kind"]
    md = ["# mtbudget a priori uncertainty evaluation of a planned verification (virtual experiment)", "",
          "## Kind of statement", "", md_escape(statement_kind_line(kind)), ""]
    if not res.complete:
        md += ["**INCOMPLETE run: partial results.**", ""]
    if res.not_converged:  # also the first row of the statement in brief (and the DCC's warning statement)
        md += ["**" + md_escape(not_converged_line(res.not_converged, res.trials)) + ".**", ""]
        if too_many_not_converged(res.not_converged, res.trials):
            md += ["**" + md_escape(no_certificate_line(res.not_converged, res.trials)) + ".**", ""]
    head = headline(res, tolerance_um, characteristic)
    data["statement"] = head
    md += headline_lines(head)
    if data.get("adaptive"):
        for x in adaptive_lines(data["adaptive"]):
            md += [f"* {md_escape(x.strip())}"] if x.startswith("  ") else \
                ["", md_escape(x) + ("" if x.endswith(":") else "."), ""]
    mt = measurand_text(res)
    md += ["## Measurand", "", md_escape(mt[0].upper() + mt[1:]) + ".", ""]
    md += provenance_lines(res)
    pts = data.get("points")
    if pts and "interval" not in pts[0]:
        md += ["", "## Result", "", "The per-point coverage intervals are not available for this log (an incomplete log of a "
               "run too long to log every trial); finish it with `mtbudget run --resume`."]
        pts = None
    if pts:
        sm = data["points_summary"]
        nd = decimals_for(min(sm["u_min"]))
        half = np.array([[(h - lo) / 2 for lo, h in zip(q["interval"]["low"], q["interval"]["high"])] for q in pts])
        md += ["", "## Result", "",
               f"Standard uncertainty u (k = 1) and the {percent(res.coverage)} coverage interval of each error component, "
               f"from {res.trials} Monte Carlo trials (JCGM 101); values in {pretty(sm['unit'])}, shown to the digits the "
               "run supports.", "",
               f"| summary over the mesh{' (workpiece (table) frame)' if table_frame(res) else ''} | x | y | z |",
               "| --- | --- | --- | --- |",
               "| RMS of u | " + " | ".join(f"{x:.{nd}f}" for x in sm["u_rms_over_mesh"]) + " |",
               "| smallest u | " + " | ".join(f"{x:.{nd}f}" for x in sm["u_min"]) + " |",
               "| largest u | " + " | ".join(f"{x:.{nd}f}" for x in sm["u_max"]) + " |",
               f"| largest half-width of the {percent(res.coverage)} interval | " + " | ".join(f"{x:.{nd}f}" for x in half.max(axis=0)) + " |",
               "| RMS of the mean (bias) | " + " | ".join(f"{x:.{nd}f}" for x in sm["bias_rms_over_mesh"]) + " |", ""]
        mf = machine_frame_summary(pts)
        if mf is not None:
            md += ["Five-axis: x, y, z above are the axes of the workpiece (table) frame, the machine's X, Y, Z with every "
                   "rotary axis at zero, turning with the table (docs/measurand.md). The same errors in the machine's "
                   "X, Y, Z at each pose (turned by the table's orientation there; mean and covariance exactly, no "
                   "coverage interval):", "",
                   "| summary over the mesh (machine frame) | X | Y | Z |", "| --- | --- | --- | --- |",
                   "| RMS of u | " + " | ".join(f"{x:.{nd}f}" for x in mf["u_rms_over_mesh"]) + " |",
                   "| smallest u | " + " | ".join(f"{x:.{nd}f}" for x in mf["u_min"]) + " |",
                   "| largest u | " + " | ".join(f"{x:.{nd}f}" for x in mf["u_max"]) + " |", ""]
        w = sm["worst_point"]
        md.append(f"Worst point: #{w['point']} at x, y, z = {_vec(w['nominal']['value'], 0)} mm{angles_label(w)}, u = "
                  f"{_vec(w['u'], nd)} {pretty(sm['unit'])}{frame_word(res)}" +
                  (f", machine frame u = {_vec(pts[w['point']]['machine_frame']['u'], nd)} {pretty(sm['unit'])}"
                   if mf is not None else "") + ".")
        fw = " (table frame)" if mf is not None or table_frame(res) else ""
        md += ["", "## Every point", "",
               f"| point | x, y, z commanded [mm] | mean x, y, z{fw} [{pretty(sm['unit'])}] | u x, y, z{fw} [{pretty(sm['unit'])}] | "
               + (f"u X, Y, Z (machine frame) [{pretty(sm['unit'])}] | " if mf is not None else "") +
               f"{percent(res.coverage)} interval x | y | z{fw} |",
               "| --- | --- | --- | --- | " + ("--- | " if mf is not None else "") + "--- | --- | --- |"]
        for q in pts:
            iv = q["interval"]
            md.append(f"| {q['point']} | {_vec(q['nominal']['value'], 0)}{angles_label(q)} | {_vec(q['mean']['value'], nd)} | "
                      f"{_vec(q['u']['value'], nd)} | " +
                      (f"{_vec(q['machine_frame']['u'], nd)} | " if mf is not None else "") + " | ".join(
                          f"[{lo:.{nd}f}, {hi:.{nd}f}]" for lo, hi in zip(iv["low"], iv["high"])) + " |")
        md += ["", f"Intervals: {pts[0]['interval']['kind']}, {pts[0]['interval']['method']}."]
    pb = res.budget.get("points")
    if pb:
        md += ["", "## Budget of the per-point measurand", "",
               f"Each source alone on the same {res.budget[MAIN_OUTPUT]['trials'] if MAIN_OUTPUT in res.budget else ''} "
               "trials: u_i is the standard deviation of each component with only that source active (k = 1); the share is "
               "of the variance summed over points and axes. No sensitivity coefficient is given: a source perturbs many "
               "inputs at once, so none is defined.", "",
               f"| source | group | u_i RMS over the mesh x, y, z{frame_word(res)} [{pretty(pb['unit'])}] | u_i at the worst point | share |",
               "| --- | --- | --- | --- | --- |"]
        idle = _idle_sources(res.spec or {}, pb["rows"])
        for r in sorted(pb["rows"], key=lambda r: -r["share"]):
            note = f" ({idle[r['source']]})" if r["source"] in idle else ""
            md.append(f"| {r['source']}{note} | {r['group']} | {_vec(r['u_rms_over_mesh'], 2)} | "
                      f"{_vec(r['u_at_worst_point'], 2)} | {r['share']:.1%} |")
        md.append(f"| interaction | | | | {pb['interaction_share']:.1%} |")
        md.append(f"| **total** | | {_vec(pb['total']['u_rms_over_mesh'], 2)} | {_vec(pb['total']['u_at_worst_point'], 2)} | 100 % |")
        md += ["", "| group | share |", "| --- | --- |"] + [f"| {g['group']} | {g['share']:.1%} |" for g in pb["groups"]]
        for k in pb.get("systematic", []):
            md += ["", f"Systematic, {k['systematic']} ({', '.join(k['sources'])}): u_i RMS over the mesh "
                       f"{_vec(k['u_rms_over_mesh'], 2)} {pretty(pb['unit'])}, {k['share']:.1%} of the variance. "
                       "How each was bounded:", ""] + [f"* `{n}`: {md_escape(t)}" for n, t in k["bounded"].items()]
    if data.get("features"):
        from .features import features_markdown

        md += features_markdown(data["features"])
    v = data.get("validation")
    if v:
        md += ["", "## GUF vs MCM (JCGM 101 clause 8), per point and axis", "",
               f"{v['passed']} of {v['of']} point-axes validated at two significant digits. {v['note']}; "
               f"{md_escape(clause8_why(res))}."]
    if tolerance_um is not None:
        conf = conformance(res, tolerance_um, characteristic)
        md += decision_lines(conf)
        data["conformance"] = conf
    if compensation:  # CompensationTable.to_dict() (with "check"), where a compensation is available
        md += compensation_lines(compensation)
    md += ["", "## Volume summaries and the paper's figures", "",
           "Per simulated verification; the spread is over verifications, not the uncertainty of a point.", "",
           "| output | unit | mean | std dev over trials | symmetric interval | shortest interval |",
           "| --- | --- | --- | --- | --- | --- |"]
    for k, val in data["outputs"].items():
        nd = decimals_for(val["std"])  # the spread to 2 significant digits, the rest to the same decimal
        sh = "-" if val["shortest"] is None else f"[{val['shortest'][0]:.{nd}f}, {val['shortest'][1]:.{nd}f}]"
        md.append(f"| {k} | {pretty(val['unit'])} | {val['mean']:.{nd}f} | {val['std']:.{nd}f} | "
                  f"[{val['symmetric'][0]:.{nd}f}, {val['symmetric'][1]:.{nd}f}] | {sh} |")
    for x in interval_note(res.outputs(), res.coverage):
        md += ["", md_escape(x.strip()[0].upper() + x.strip()[1:]) + "."]
    b = res.budget.get(MAIN_OUTPUT)
    if b:
        md += ["", f"### Budget of {MAIN_OUTPUT}", "",
               f"Each source alone on the same {b['trials']} trials; contributions by {b['basis'].replace('_', ' ')}, which add "
               "up for independent sources; RMS_i is a root-mean-square contribution, not a standard uncertainty.", "",
               f"| source | group | u(x_i) | RMS_i [{pretty(b['unit'])}] | share |", "| --- | --- | --- | --- | --- |"]
        for r in sorted(b["rows"], key=lambda r: -r["contribution"]):
            ux = "-" if r["u_x"] is None else f"{r['u_x']['value']:.3g} {pretty(r['u_x']['unit'])}"
            md.append(f"| {r['source']} | {r['group']} | {ux} | {_root_i(r):.3f} | {r['share']:.1%} |")
        md.append(f"| interaction | | | | {b['interaction'] / b['total'] if b['total'] else 0:.1%} |")
        md.append(f"| **total** | | | {_root_total(b):.3f} | 100 % |")
    figs.update({k: v[0] for k, v in (extra_figures or {}).items()})
    captions = {**CAPTIONS, **{k: v[1] for k, v in (extra_figures or {}).items()}}
    if res.angles is None:  # a three-axis plan: nothing to take the largest over
        captions["uncertainty_map"] = captions["uncertainty_map"].replace(
            " (a five-axis plan: the largest over the rotary poses)", "")
    md += ["", "## Figures", ""] + [f"![{md_escape(captions.get(k, k))}]({p.name})" for k, p in figs.items()]
    (folder / "report.md").write_text("\n".join(md) + "\n")
    write_html(md, folder, folder / "report.html", "mtbudget a priori uncertainty evaluation (virtual experiment)")
    (folder / "results.json").write_text(__import__("json").dumps(data, indent=1))
    return {"markdown": folder / "report.md", "html": folder / "report.html", "figures": figs}


def decision_lines(conf: dict) -> list:
    """The ISO 14253-1 decision (:func:`mtbudget.budget.conformance`) as a Markdown section, either kind of statement."""
    md = ["", "## Decision (ISO 14253-1)", "", f"Characteristic: {conf['characteristic']}.", "",
          f"Scope of the verdict: {'the whole machine' if conf['scope'] == 'machine' else 'each point-axis on its own'}.",
          "", f"Rule: {conf['rule']}.", "", f"**{conf['statement']}**"]
    if conf.get("per_point") and conf["scope"] == "machine":
        md += ["", f"Per point (scope: each point-axis on its own, not the machine): {conf['per_point']['rule']}."]
    return md


def posterior_json(post, tolerance_um: float | None = None, characteristic: str = "component") -> dict:
    """The a posteriori statement as JSON (:func:`mtbudget.posterior.posterior`'s dict) with its statement in brief
    (``statement``, :func:`posterior_headline`) and, with a tolerance, its ISO 14253-1 decision (``conformance``)."""
    from .budget import conformance

    data = dict(post.data)
    data["statement"] = posterior_headline(post, tolerance_um, characteristic)
    if tolerance_um is not None:
        data["conformance"] = conformance(post, tolerance_um, characteristic)
    return data


def posterior_report(post, folder, tolerance_um: float | None = None, characteristic: str = "component") -> dict:
    """posterior.md, posterior.html (self-contained) and posterior.json for an a posteriori statement
    (:class:`mtbudget.posterior.Posterior`), opening with the statement in brief a run's report opens with, and the
    ISO 14253-1 decision when a tolerance is given."""
    import json as _json

    from .posterior import fit_said

    folder = make_folder(folder)
    p = posterior_json(post, tolerance_um, characteristic)
    k, s, i = p["statement_kind"], p["summary"], p["identification"]
    r = s["u_over_u_linear"]
    half = np.array([[(h - lo) / 2 for lo, h in zip(q["interval"]["low"], q["interval"]["high"])] for q in p["points"]])
    md = ["# mtbudget a posteriori uncertainty statement", "", *headline_lines(p["statement"]), "## Kind of statement", "",
          md_escape(f"A POSTERIORI: the {k['name']} (recording {k['recording']}, points.csv sha256 "
                    f"{k.get('points_csv_sha256') or '-'}). {k['what'][0].upper() + k['what'][1:]}."), "",
          "## Measurand", "", md_escape(p["measurand"][0].upper() + p["measurand"][1:]) +
          f" ({p['not_identifiable']} combination(s) not identifiable).", "",
          "## Identification", "",
          md_escape(f"chi2/dof {i['chi2_per_dof']:.3f} on {i['dof']} degrees of freedom ({fit_said(i)}); noise: "
                    f"{i['noise']} (scale {i['noise_scale']:.3f}); {i['thermal_correction']}."), "",
          *([f"**Warning: {md_escape((i.get('fit_test') or {})['warning'])}.**", ""]
            if (i.get("fit_test") or {}).get("warning") else []),
          "## Result", "",
          f"Standard uncertainty u (k = 1) from {p['trials']} Monte Carlo trials (seed {p['seed']}); values in µm.", "",
          f"| summary over the mesh{' (workpiece (table) frame)' if 'frame' in s else ''} | x | y | z |",
          "| --- | --- | --- | --- |",
          "| RMS of u | " + " | ".join(f"{x:.2f}" for x in s["u_rms_over_mesh"]) + " |",
          "| largest u | " + " | ".join(f"{x:.2f}" for x in s["u_max"]) + " |",
          f"| largest half-width of the {percent(p['coverage'])} interval | " +
          " | ".join(f"{x:.2f}" for x in half.max(axis=0)) + " |", "",
          *(["| summary over the mesh (machine frame, X, Y, Z at each pose) | X | Y | Z |", "| --- | --- | --- | --- |",
             "| RMS of u | " + " | ".join(f"{x:.2f}" for x in s["machine_frame"]["u_rms_over_mesh"]) + " |",
             "| largest u | " + " | ".join(f"{x:.2f}" for x in s["machine_frame"]["u_max"]) + " |", ""]
            if "machine_frame" in s else []),
          f"Check: u(MCM) / u(identification covariance propagated linearly) median {r['median']:.3f} "
          f"({r['min']:.3f}-{r['max']:.3f}) over the point-axes.",
          *(decision_lines(p["conformance"]) if "conformance" in p else []), "",
          "## Every point", "",
          f"| point | x, y, z commanded [mm] | mean x, y, z [µm] | u x, y, z [µm] | u linear x, y, z [µm] | "
          f"{percent(p['coverage'])} interval x | y | z |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    mf = bool(p["points"]) and "machine_frame" in p["points"][0]
    if mf:  # five-axis with a rotary table: the components' frame, and the machine's X, Y, Z beside them
        fw = " (table frame)"
        md[-2] = (f"| point | x, y, z commanded [mm] | mean x, y, z{fw} [µm] | u x, y, z{fw} [µm] | u linear x, y, z{fw} "
                  f"[µm] | u X, Y, Z (machine frame) [µm] | {percent(p['coverage'])} interval x | y | z{fw} |")
        md[-1] = "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"
    for q in p["points"]:
        iv = q["interval"]
        md.append(f"| {q['point']} | {_vec(q['nominal']['value'], 0)}{angles_label(q)} | {_vec(q['mean']['value'], 2)} | "
                  f"{_vec(q['u']['value'], 2)} | {_vec(q['u_linear']['value'], 2)} | "
                  + (f"{_vec(q['machine_frame']['u'], 2)} | " if mf else "")
                  + " | ".join(f"[{lo:.2f}, {hi:.2f}]" for lo, hi in zip(iv["low"], iv["high"])) + " |")
    (folder / "posterior.md").write_text("\n".join(md) + "\n")
    write_html(md, folder, folder / "posterior.html", "mtbudget a posteriori uncertainty statement")
    (folder / "posterior.json").write_text(_json.dumps(p, indent=1))
    return {"markdown": folder / "posterior.md", "html": folder / "posterior.html", "json": folder / "posterior.json"}
