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
