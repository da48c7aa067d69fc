"""The GUM-style budget of a verification run, its GUF comparison and the ISO 14253-1 decision.

Budget attribution: the model is non-linear, so contributions are measured,
not linearised.  For each source the same trials are run with that source
alone ("one at a time", OAT): its variance V_i.  The budget lists
u_i(y) = sqrt(V_i), the source's own standard uncertainty u(x_i) where it has
one, the effective sensitivity c_i = u_i(y) / u(x_i), and the share
V_i / V.  What the contributions do not explain, V - sum V_i, is reported as
the interaction term, so the table adds up exactly.  Optionally the
leave-one-out variant (V - V_without_i) is computed too.  The same trials
(common random numbers: each source's stream depends on seed, block and
source only) are used for every row.
"""

from __future__ import annotations

import math

import numpy as np

from .contracts import Group
from .distributions import t_factor
from .executors import Executor
from .outputs import MAIN_OUTPUT, MEAN_SQUARE_OUTPUTS, SCALARS, RunResult, accumulate_block
from .plugins import call
from .progress import progress_bar
from .stats import Accumulator, clause8


def attribution(engine, result: RunResult, n: int, *, ex_kind="inline", workers=None, address=None,
                chunk_blocks=4, leave_one_out: bool = False, progress: bool = False) -> dict:
    """One-source-at-a-time budget of every scalar output on the first ``n`` trials (see the module docstring)."""
    import uncertainties

    nblocks = math.ceil(n / engine.block)
    blocks = list(range(nblocks))
    spec = result.spec
    ex = Executor(engine, spec, ex_kind, workers, address)
    runs = 2 + len(engine.sources) * (2 if leave_one_out else 1)
    bar = progress_bar(runs * nblocks, "budget", "block", progress)

    def moments(active_names):
        acc = Accumulator(keep_samples=True)
        chunks = [blocks[i:i + chunk_blocks] for i in range(0, len(blocks), chunk_blocks)]
        for res in ex.map(chunks, active_names):
            for b in res:
                accumulate_block(acc, b if acc.n + b.n <= n else b.truncated(n - acc.n))
            bar.update(len(res))
        out = {}
        for o in SCALARS:
            y = acc.scalar_samples(o)
            out[o] = {"variance": float(np.var(y, ddof=1)), "mean_square": float(np.mean(y**2)), "mean": float(y.mean())}
        return out

    try:
        total = moments([s.name for s in engine.sources])
        nominal = moments([])
        per_source = {s.name: moments([s.name]) for s in engine.sources}
        loo = {}
        if leave_one_out:
            for s in engine.sources:
                loo[s.name] = moments([t.name for t in engine.sources if t.name != s.name])
    finally:
        ex.close()
        bar.close()
    tables = {}
    for o, (unit, _) in SCALARS.items():
        basis = "mean_square" if o in MEAN_SQUARE_OUTPUTS else "variance"
        rows = []
        V = total[o][basis]
        for s in engine.sources:
            v = per_source[s.name][o][basis]
            ux = call(s, "standard_uncertainty")
            u_y = math.sqrt(max(v, 0.0))
            row = {"source": s.name, "group": Group(s.group).value, "plugin": s.plugin, "distribution": s.distribution,
                   "u_x": None if ux is None else {"value": float(ux.magnitude), "unit": f"{ux.units:~}"},
                   "contribution": v, "u_y": u_y, "share": v / V if V > 0 else 0.0}
            if ux is not None and ux.magnitude:
                row["sensitivity"] = {"value": u_y / float(ux.magnitude),
                                      "unit": f"{unit}/({ux.units:~})" if unit else f"1/({ux.units:~})"}
            if leave_one_out:
                row["loo"] = V - loo[s.name][o][basis]
            rows.append(row)
        groups: dict = {}
        for r in rows:
            groups[r["group"]] = groups.get(r["group"], 0.0) + r["contribution"]
        # law of propagation over the (independent) source contributions, through `uncertainties`
        comb = 0.0
        for r in rows:
            if r["u_y"] > 0:
                comb = comb + uncertainties.ufloat(0.0, r["u_y"], tag=r["source"])
        tables[o] = {
            "unit": unit, "trials": n, "basis": basis, "total": V, "u_total": math.sqrt(max(V, 0.0)),
            "sum_of_contributions": sum(r["contribution"] for r in rows),
            "interaction": V - sum(r["contribution"] for r in rows),
            "nominal": nominal[o][basis],
            "nominal_value": nominal[o]["mean"],
            "u_combined": float(getattr(comb, "std_dev", 0.0)),
            "rows": rows,
            "groups": [{"group": g.value, "contribution": groups.get(g.value, 0.0),
                        "share": groups.get(g.value, 0.0) / V if V > 0 else 0.0} for g in Group],
        }
    return tables


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
    d_low, d_high, delta, ok = clause8((lo, hi), s["symmetric"], u_c, 2)
    return {"guf_estimate": y, "guf_u": u_c, "k": k, "guf_interval": [lo, hi], "mcm_interval": list(s["symmetric"]),
            "d_low": d_low, "d_high": d_high, "delta": delta, "passed": ok}


def conformance(res: RunResult, tolerance_um: float) -> dict:
    """ISO 14253-1 decision zones for an upper tolerance on the error left after compensation."""
    s = res.summary(MAIN_OUTPUT)
    U = s["symmetric"][1] - 0.0  # the verification contributes at most this (upper end of the interval)
    return {"tolerance": tolerance_um, "U": U, "conformance_limit": tolerance_um - U, "nonconformance_limit": tolerance_um + U,
            "statement": (f"A machine verified this way can be declared to conform to {tolerance_um:g} um only when its "
                          f"measured error is at most {tolerance_um - U:.2f} um (guard band U = {U:.2f} um); it is proven "
                          f"not to conform above {tolerance_um + U:.2f} um; in between, neither can be proven (ISO 14253-1).")
            if tolerance_um > U else
            (f"The verification's own uncertainty (U = {U:.2f} um) exceeds the tolerance of {tolerance_um:g} um: "
             "conformance cannot be proven for any result (ISO 14253-1).")}
