"""The GUM-style budget of a verification run, its GUF comparison and the ISO 14253-1 decision.

Budget attribution: the model is non-linear, so contributions are measured,
not linearised.  For each source the same trials are run with that source
alone ("one at a time", OAT): its variance V_i.  The budget lists
u_i(y) = sqrt(V_i) (``u_i``; ``rms_i`` for a budget by mean square), the source's own standard
uncertainty u(x_i) where it has one, and the share V_i / V.  No sensitivity coefficient: a source moves many inputs
at once (every point, both angles), so none is defined.  What the contributions do not explain, V - sum V_i, is reported as
the interaction term, so the table adds up exactly.  Optionally the
leave-one-out variant (V - V_without_i) is computed too.  The same trials
(common random numbers: each source's stream depends on seed, block and
source only) are used for every row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .contracts import Group
from .executors import Executor
from .outputs import MEAN_SQUARE_OUTPUTS, SCALARS, RunResult, table_frame
from .plugins import call
from .progress import progress_bar
from .stats import bound, percent, symmetric_interval


class RunReduction:
    """What the budget keeps of one Monte Carlo run of the first ``n`` trials: every trial's scalar outputs and the
    co-moments of the per-point components, merged block by block in block order.

    ``add`` takes the run's blocks in order (a block past ``n`` trials is cut to the trials left; blocks after
    that are ignored); ``moments()`` gives, per scalar output, the variance (ddof 1), the mean square and the
    mean of the ``n`` values, and the variance of each point's components.  It is exactly what merging the
    blocks into a :class:`mtbudget.stats.Accumulator` gave (same concatenation, same merges in the same order),
    without the statistics the budget never reads (histograms, moments of the other vector outputs).
    """

    def __init__(self, n: int, components: bool = True):
        self.limit = int(n)
        self.n = 0
        self.components = components
        self.scalars: dict = {o: [] for o in SCALARS}
        self.cm = None  # CoMoments of the components so far
        self.blocks: list = []
        self.features: list = []  # [[features]]: (n, K, C) per block

    @property
    def full(self) -> bool:
        return self.n >= self.limit

    def add(self, b) -> None:
        """Merge block ``b`` (a BlockResult), or its first trials when it crosses ``n``."""
        if self.full:
            return
        left = self.limit - self.n
        t = b if left >= b.n else b.truncated(left)
        for o in SCALARS:
            self.scalars[o].append(t.scalars[o])
        if self.components:
            m = t.component_comoments()
            if m is not None:
                self.cm = m if self.cm is None else self.cm.merge(m)
        self.blocks.append(int(b.block))
        self.n += t.n
        if getattr(t, "features", None) is not None:
            self.features.append(t.features)

    def moments(self) -> dict:
        out = {}
        for o in SCALARS:
            y = np.concatenate(self.scalars[o])
            out[o] = {"variance": float(np.var(y, ddof=1)), "mean_square": float(np.mean(y**2)), "mean": float(y.mean())}
        if self.cm is not None:
            out["components"] = np.diagonal(self.cm.cov, axis1=1, axis2=2)  # (M0, 3) variance of each point's components
        if self.features and len(self.features) == len(self.blocks):  # [[features]]: (K, C) variances
            out["features"] = np.concatenate(self.features).var(axis=0, ddof=1)
        return out


class RunPrefix(RunReduction):
    """The budget's "all sources" row, collected while the run merges its blocks (:func:`mtbudget.runner.run`).

    The budget's first row is the first ``n`` trials with every source active: the same blocks, drawn from the same
    per-source streams, as the run's own first ``n`` trials (a block's results depend on seed, block and active
    sources only, not on the chunking or the executor: bit-identical).  The run hands its merged blocks here in
    block order, each marked computed now by ``engine`` or resumed from a log (a resumed block may come from another
    mtbudget or other plugins: it makes the prefix unusable and the budget computes the row itself, as it does
    when this run does not cover ``n`` trials).  It holds references to the run's arrays, copies nothing.
    """

    def __init__(self, engine, n: int):
        super().__init__(n)
        self.engine = engine
        self.usable = True

    def add(self, b, computed: bool = True) -> None:
        if self.full or not self.usable:
            return
        if (not computed or int(b.block) != len(self.blocks) or b.component_comoments() is None
                or (b.components is None and b.n > self.limit - self.n)):
            # a resumed block, a block out of order, or one without the per-point statistics the row needs
            self.usable = False
            return
        super().add(b)

    def covers(self, engine, n: int) -> bool:
        """Whether this is the budget's "all sources" row of ``engine`` on its first ``n`` trials, exactly: the prefix
        holds the run's first ``self.n`` trials (all of them when the run had fewer than its limit)."""
        return self.usable and engine is self.engine and self.n == n


def _same_block(a, b) -> bool:
    """Whether two blocks' results are the same bits (every scalar, every per-point component, the counts)."""
    def same(x, y):
        if x is None or y is None:
            return x is None and y is None
        x, y = np.asarray(x), np.asarray(y)
        return x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes()

    return (a.n == b.n and a.not_converged == b.not_converged and a.fallbacks == b.fallbacks
            and set(a.scalars) == set(b.scalars) and all(same(a.scalars[k], b.scalars[k]) for k in a.scalars)
            and same(a.components, b.components))


def attribution(engine, result: RunResult, n: int, *, ex_kind="inline", workers=None, address=None,
                chunk_blocks=4, leave_one_out: bool = False, progress: bool = False,
                executor: Executor | None = None) -> dict:
    """One-source-at-a-time budget of every scalar output on the first ``n`` trials (see the module docstring).

    Two rows are not computed as Monte Carlo runs of their own when they need not be:

    * "all sources" is the run's own first ``n`` trials: taken from ``result.prefix`` (a :class:`RunPrefix` the
      run filled while merging) when it covers them with this engine, every block computed in this run;
    * "no source": no source draws anything, so nothing in a trial depends on the block (the random streams are
      the only thing that does): every block is the same nominal block.  Blocks 0 and 1 are computed and compared
      bit for bit; when they are equal, the others are that block (the statistics are merged from it block by
      block, as they were from each block: the same numbers); when not, every block is computed.

    ``executor``: an open :class:`mtbudget.executors.Executor` of ``engine`` to run the rows on (the run's: its
    workers have the engine built), left open; by default one of ``ex_kind`` is started and closed here.
    """
    import uncertainties

    nblocks = math.ceil(n / engine.block)
    blocks = list(range(nblocks))
    spec = result.spec
    ex = executor if executor is not None else Executor(engine, spec, ex_kind, workers, address)
    runs = 2 + len(engine.sources) * (2 if leave_one_out else 1)
    bar = progress_bar(runs * nblocks, "budget", "block", progress)

    def chunked(ids):
        return [ids[i:i + chunk_blocks] for i in range(0, len(ids), chunk_blocks)]

    def moments(active_names, components=True):
        red = RunReduction(n, components)
        for res in ex.map(chunked(blocks), active_names):
            for b in res:
                red.add(b)
            bar.update(len(res))
        return red.moments()

    def nominal_moments():
        red = RunReduction(n, components=False)
        res = [b for chunk in ex.map([blocks[:2]], []) for b in chunk]
        bar.update(len(res))
        if len(res) == 1 or _same_block(res[0], res[1]):
            for _ in blocks:  # every block is block 0: its statistics merged once per block, as before
                red.add(res[0])
            bar.update(nblocks - len(res))
        else:  # a block differs from another without any source: compute every block, as any other row
            for b in res:
                red.add(b)
            for more in ex.map(chunked(blocks[2:]), []):
                for b in more:
                    red.add(b)
                bar.update(len(more))
        return red.moments()

    try:
        prefix = getattr(result, "prefix", None)
        if isinstance(prefix, RunPrefix) and prefix.covers(engine, n):
            total = prefix.moments()
            bar.update(nblocks)
        else:
            total = moments([s.name for s in engine.sources])
        nominal = nominal_moments()
        per_source = {s.name: moments([s.name]) for s in engine.sources}
        loo = {}
        if leave_one_out:
            for s in engine.sources:
                loo[s.name] = moments([t.name for t in engine.sources if t.name != s.name], components=False)
    finally:
        if executor is None:
            ex.close()
        bar.close()
    systematic = systematic_sources(engine)
    tables = {}
    for o, (unit, _) in SCALARS.items():
        basis = "mean_square" if o in MEAN_SQUARE_OUTPUTS else "variance"
        # what the square root of a contribution is: a root-mean-square contribution for a mean-square budget (of a
        # figure such as compensation_rms, whose "std" under outputs is another quantity), a standard deviation for a
        # variance budget; no sensitivity coefficient: every source moves many inputs (all points, both angles ...),
        # so no single input exists to be sensitive to
        yk, tk, ck = (("rms_i", "rms_total", "rms_combined") if basis == "mean_square" else
                      ("u_i", "u_total", "u_combined"))
        rows = []
        V = total[o][basis]
        for s in engine.sources:
            v = per_source[s.name][o][basis]
            ux = call(s, "standard_uncertainty")
            y_i = math.sqrt(max(v, 0.0))
            row = {"source": s.name, "group": Group(s.group).value, "plugin": s.plugin, "distribution": s.distribution,
                   "u_x": None if ux is None else {"value": float(ux.magnitude), "unit": f"{ux.units:~}"},
                   "contribution": v, yk: y_i, "share": v / V if V > 0 else 0.0}
            if leave_one_out:
                row["loo"] = V - loo[s.name][o][basis]
            row.update(systematic.get(s.name, {}))
            rows.append(row)
        groups: dict = {}
        for r in rows:
            groups[r["group"]] = groups.get(r["group"], 0.0) + r["contribution"]
        # law of propagation over the (independent) source contributions, through `uncertainties`
        comb = 0.0
        for r in rows:
            if r[yk] > 0:
                comb = comb + uncertainties.ufloat(0.0, r[yk], tag=r["source"])
        tables[o] = {
            "unit": unit, "trials": n, "basis": basis,
            "keys": (f"contribution: the {basis.replace('_', ' ')} of {o} with that source alone ({unit}^2); {yk}: its "
                     f"square root ({unit}{', a root-mean-square contribution, not a standard uncertainty' if basis == 'mean_square' else ', a standard deviation'}); "
                     f"{tk}: the square root of the total; {ck}: the root sum of squares of the {yk}"),
            "total": V, tk: math.sqrt(max(V, 0.0)),
            "sum_of_contributions": sum(r["contribution"] for r in rows),
            "interaction": V - sum(r["contribution"] for r in rows),
            "nominal": nominal[o][basis],
            "nominal_value": nominal[o]["mean"],
            ck: float(getattr(comb, "std_dev", 0.0)),
            "rows": rows,
            "groups": [{"group": g.value, "contribution": groups.get(g.value, 0.0),
                        "share": groups.get(g.value, 0.0) / V if V > 0 else 0.0} for g in Group],
        }
    if "components" in total:
        tables["points"] = {**point_budget(engine, total, per_source, systematic), "trials": n}
    if "features" in total and all("features" in v for v in per_source.values()):
        from .features import feature_budget

        tables["features"] = feature_budget(engine, total, per_source, n)
    return tables


def systematic_sources(engine) -> dict:
    """{source name: {"systematic": "model form", "bounded": one sentence}} for the sources that declare a kind of
    systematic effect (``Source.systematic``, for example the model-form sources: the machine richer than the
    identification's model) and say how its size was bounded (``Source.bounded(context)``)."""
    out = {}
    ctx = engine.scenario.context
    for s in engine.sources:
        kind = getattr(s, "systematic", None)
        if kind:
            out[s.name] = {"systematic": str(kind),
                           "bounded": str(call(s, "bounded", ctx)) if hasattr(s, "bounded") else ""}
    return out


def point_budget(engine, total: dict, per_source: dict, systematic: dict | None = None) -> dict:
    """Per source, its variance contribution to each component at each point, summarised over the volume.

    Each source alone on the same trials (common random numbers): u_i at a
    point and axis is the standard deviation of that component with only
    source i active.  Summaries: the RMS over the mesh of u_i per axis, u_i
    at the worst point (the largest total u), and the share of the total
    variance summed over points and axes.  No sensitivity coefficient: a
    source perturbs many inputs at once, so none is defined.  A systematic
    source (:func:`systematic_sources`) carries its kind and the sentence on
    how it was bounded, and "systematic" sums each kind: its share, its u
    (root sum of squares of its sources' u) and its sources.
    """
    systematic = systematic_sources(engine) if systematic is None else systematic
    V = total["components"]  # (M0, 3)
    worst = int(np.argmax(V.sum(axis=1)))
    Vsum = float(V.sum())
    rows, groups = [], {}
    for s in engine.sources:
        v = per_source[s.name]["components"]
        row = {"source": s.name, "group": Group(s.group).value, "plugin": s.plugin,
               "u_rms_over_mesh": np.sqrt(v.mean(axis=0)).tolist(), "u_at_worst_point": np.sqrt(v[worst]).tolist(),
               "share": float(v.sum()) / Vsum if Vsum > 0 else 0.0}
        groups[row["group"]] = groups.get(row["group"], 0.0) + float(v.sum())
        row.update(systematic.get(s.name, {}))
        rows.append(row)
    inter = Vsum - sum(float(per_source[s.name]["components"].sum()) for s in engine.sources)
    kinds: dict = {}
    for s in engine.sources:
        if s.name in systematic:
            kinds.setdefault(systematic[s.name]["systematic"], []).append(s.name)
    summary = []
    for kind, names in kinds.items():
        v = sum(per_source[n]["components"] for n in names)
        summary.append({"systematic": kind, "sources": names, "share": float(v.sum()) / Vsum if Vsum > 0 else 0.0,
                        "u_rms_over_mesh": np.sqrt(v.mean(axis=0)).tolist(), "u_at_worst_point": np.sqrt(v[worst]).tolist(),
                        "bounded": {n: systematic[n]["bounded"] for n in names}})
    return {"unit": "um", "axes": ["x", "y", "z"], "worst_point": worst,
            "total": {"u_rms_over_mesh": np.sqrt(V.mean(axis=0)).tolist(), "u_at_worst_point": np.sqrt(V[worst]).tolist()},
            "rows": rows, "interaction_share": inter / Vsum if Vsum > 0 else 0.0,
            "groups": [{"group": g.value, "share": groups.get(g.value, 0.0) / Vsum if Vsum > 0 else 0.0} for g in Group],
            "systematic": summary}


def point_lpu(scenario) -> dict:
    """The law of propagation (GUF) for the per-point measurand, at every mesh point and axis.

    The noise-free verification is identified with the stated weights; its
    compensated error is the GUF estimate y0, and the identification
    covariance of the geometric parameters, propagated through the Jacobian
    of the compensated field at the mesh points (rigid part removed, as for
    the MCM), gives the covariance of each point's three components:
    ``cov_e = P J cov_theta J^T P^T``.  It covers the measurement noise the
    verification states (tracker and repeatability), which is what the
    identification covariance describes; sources without a stated weight are
    in the MCM only.  With [scales] the noise-free machine expands about the stated fixed points at the read
    temperatures and the identification corrects it as a fixed input, as in every Monte Carlo trial.
    Returns {"estimate": (M0, 3) um, "cov": (M0, 3, 3) um^2}.
    """
    from .identify import identify
    from .units import factor

    sc = scenario
    # [scales]: the machine expands about each stated fixed point at the read temperatures, and the verification
    # corrects that as a known input (the stated scales, the read temperatures); without [scales] both are empty
    truth_inputs, fixed = sc.truth_inputs({}), sc.correction or None
    if sc.stations:  # [[stations]]: the noise-free measurements of every station, identified over all of them
        from .multistation import identify_stations
        from .simulate import measure_stations

        xyz, ranges = measure_stations(sc, sc.truth.machine_points(sc.theta[None, :], truth_inputs), truth_inputs)
        ms = identify_stations(sc.id_model, sc.stations, sc.row_station, xyz[0], ranges[0], sc.noise.repeatability,
                               fixed=fixed, hold=sc.unidentifiable(sc.id_model))
        p = sc.id_model.n_params
        theta, cov_theta = ms.x[None, :p], ms.cov[:p, :p]
    else:
        res = identify(sc.id_model, sc.truth.predict(sc.theta[None, :], sc.pose, truth_inputs), sc.noise, fixed=fixed)
        theta, cov_theta = res.theta, res.cov_theta[0]
    F_true = sc.evaluate(sc.truth, sc.theta[None, :])[0]
    if sc.null_bias is not None:
        F_true = F_true - sc.null_bias
    F_id, J = sc.evaluate(sc.id_model, theta, jacobian=True)
    F_id, J = F_id[0], J[0]  # (M0, 3), (M0, 3, p): at the mesh points and the measurand's tool
    M0 = len(sc.mesh_rows)
    P = sc.rigid_free
    um = factor("mm", "um")
    y0 = (P @ (F_true - F_id).reshape(-1)).reshape(M0, 3) * um
    Jf = (P @ J.reshape(3 * M0, -1)).reshape(M0, 3, -1)
    # only each point's 3 x 3 block of P J cov_theta J^T P^T: O(M0), not the (3 M0)^2 matrix
    blocks = np.einsum("mip,mjp->mij", Jf @ cov_theta, Jf) * um**2
    m = sc.context.measurand
    if m is not None:  # at a tool the verification did not use: the unidentifiable errors' prior, as the MCM draws it
        G = (P @ m["unidentified_field"][:, sc.mesh_rows].reshape(m["unidentified_field"].shape[0], -1).T
             ).reshape(M0, 3, -1)
        blocks = blocks + np.einsum("mik,mjk->mij", G, G) * um**2
    return {"estimate": y0, "cov": blocks}


#: sources whose input covariance the GUF states in closed form: the identification's own noise model (paper Eq. 23
#: plus a per-point, per-axis normal in the machine frame), with the second moments the Monte Carlo draws
CLOSED_FORM_SOURCES = ("tracker_noise", "repeatability", "control_error")


def _closed_form_noise(sources) -> tuple:
    """(Noise with the second moments the active sources draw, the names covered): the tracker's angular u is drawn
    per trial from |N(mean, sd)| (a hierarchical noise), so its effective variance is E[u^2] = mean^2 + sd^2; the
    repeatability and the control error are both per-point normals of each axis, so their variances add."""
    from .identify import Noise

    on = {s.name: s for s in sources}
    ang = dist = dpl = r2 = 0.0
    covered = []
    t = on.get("tracker_noise")
    if t is not None:
        ang = math.hypot(t.value("angular_mean", "rad"), t.value("angular_sd", "rad"))
        dist, dpl = t.value("distance", "mm"), t.value("distance_per_length", "")
        covered.append("tracker_noise")
    for name, key in (("repeatability", "R"), ("control_error", "C")):
        if name in on:
            r2 += on[name].value(key, "mm") ** 2
            covered.append(name)
    return Noise(ang, dist, dpl, math.sqrt(r2)), covered


#: measured coordinates whose identifications point_guf runs in one call (a larger plan goes in chunks of this many)
GUF_DIRECTIONS = 2048
#: beyond this many measured coordinates (2000 points) point_guf is point_lpu, said in its basis
GUF_MAX_DIRECTIONS = 6000


#: trials of the central differences identified per call (rounded down to a multiple of identify's chunk, at least
#: one chunk): a call's result holds every trial's whiteners, residuals and points (about 0.2 MB a trial on a
#: 1080-point plan), of which point_guf keeps theta; in one call of 2048 trials the five-axis example's run peaked at
#: 1.5 GB, in calls of 256 at 0.39 GB, the same numbers (issue 31)
GUF_TRIALS_PER_CALL = 256


def _identified(sc, meas, fixed) -> np.ndarray:
    """theta_hat (N, p) of every verification in ``meas`` (N, M, 3): identify's numbers for all of them in one call,
    from calls on pieces that are whole multiples of its chunk (:func:`mtbudget.identify.default_chunk`: the trials
    that share an iteration matrix are the same), each result dropped once its theta is taken."""
    from .identify import default_chunk, identify

    model = sc.id_model
    chunk = default_chunk(meas.shape[1], model.n_params)
    step = chunk * max(1, GUF_TRIALS_PER_CALL // chunk)
    if len(meas) <= step:
        return identify(model, meas, sc.noise, fixed=fixed).theta
    return np.concatenate([identify(model, meas[lo:lo + step], sc.noise, fixed=fixed).theta
                           for lo in range(0, len(meas), step)])


def _identification_map(sc, meas0, fixed, h):
    """(d theta_hat / d y (p, 3 M), theta_hat at the noise-free measurements (1, p)) by central differences of the
    identification in each measured coordinate: up to GUF_DIRECTIONS coordinates at once, in chunks beyond (a
    plan of thousands of points would otherwise hold 2 x (3 M)^2 numbers at once); each identified in calls of
    GUF_TRIALS_PER_CALL trials (:func:`_identified`)."""
    M = meas0.shape[1]
    n = 3 * M
    if n <= GUF_DIRECTIONS:
        E = np.eye(n).reshape(n, M, 3) * h
        theta = _identified(sc, np.concatenate([meas0, meas0 + E, meas0 - E]), fixed)
        return ((theta[1:1 + n] - theta[1 + n:]) / (2 * h)).T, theta[:1]
    theta0 = _identified(sc, meas0, fixed)
    G = np.empty((theta0.shape[1], n))
    for start in range(0, n, GUF_DIRECTIONS // 2):
        k = min(GUF_DIRECTIONS // 2, n - start)
        E = np.zeros((k, n))
        E[np.arange(k), start + np.arange(k)] = h
        E = E.reshape(k, M, 3)
        theta = _identified(sc, np.concatenate([meas0 + E, meas0 - E]), fixed)
        G[:, start:start + k] = ((theta[:k] - theta[k:]) / (2 * h)).T
    return G, theta0


def point_guf(scenario, draws: int = 1024, seed: int = 0, h: float = 2e-4) -> dict:
    """The law of propagation for the per-point measurand on the same inputs as the Monte Carlo (JCGM 101 clause 8
    can then validate where the model is near-linear).

    One first-order model of every trial: e = Pi (F_true + offset - F_id(theta_hat(y))) at the mesh points, linearised
    about the noise-free verification: the identification (with the stated weights, as every trial) by central
    differences in the measured coordinates (step ``h`` mm), the identified field by its Jacobian.  Its inputs are
    those the Monte Carlo draws, source by source (independent, so their covariances add):

    * the tracker noise, the repeatability and the control error in closed form (:func:`_closed_form_noise`: the
      tracker's hierarchical angular noise by E[u^2] = mean^2 + sd^2, not the stated mean);
    * every other active source with a first-order effect (reflector centring, thermal, backlash ...): its own
      draws (``draws`` of them, its own stream) pushed through the same linear model, which is the law of
      propagation with the source's input covariance evaluated from its distribution by sampling; their mean
      moves the estimate (f at the inputs' expectations, to first order);
    * the optimisation-strategy sources (a discrete choice of the identification) have no first-order effect;
    * at a [measurand] tool the unidentifiable part's prior, as :func:`point_lpu`.

    With [[stations]] it is :func:`point_lpu` (the stated noise only), said in ``basis``.
    Returns {"estimate": (M0, 3) um, "cov": (M0, 3, 3) um^2, "basis": {...}}.
    """
    from .simulate import simulate_block
    from .units import factor

    sc = scenario
    if 3 * len(sc.plan) > GUF_MAX_DIRECTIONS:  # the central differences cost (3 M)^2 point evaluations: too many
        out = point_lpu(sc)
        out["basis"] = {"closed_form": ["the stated tracker noise and repeatability (identification covariance)"],
                        "sampled": [], "no_first_order_effect": [],
                        "note": f"a plan of {len(sc.plan)} measured points is beyond the {GUF_MAX_DIRECTIONS // 3} "
                                "for which the GUF on the MCM's inputs is computed (its central differences cost the "
                                "square of the plan's size): the GUF is the identification covariance of the stated "
                                "noise; sources without a stated weight are in the MCM only"}
        return out
    if sc.stations:
        out = point_lpu(sc)
        out["basis"] = {"closed_form": ["the stated noise of every station (identification covariance)"],
                        "sampled": [], "no_first_order_effect": [],
                        "note": "with [[stations]] the GUF is the identification covariance of the stated noise; "
                                "sources without a stated weight are in the MCM only"}
        return out
    um = factor("mm", "um")
    fixed = sc.correction or None
    nominal = simulate_block(sc, 0, 1, seed, active=[])
    meas0, th0 = np.asarray(nominal[0]), np.asarray(nominal[1])  # (1, M, 3) mm, (1, p)
    M = meas0.shape[1]
    G, theta0 = _identification_map(sc, meas0, fixed, h)  # (p, 3 M): d theta_hat / d y; theta_hat(y0)
    F_id, J = sc.evaluate(sc.id_model, theta0, jacobian=True)
    M0 = F_id.shape[1]
    P = sc.rigid_free
    PJ = -(P @ J[0].reshape(3 * M0, -1))  # (3 M0, p): d e / d theta_hat; d e / d y = PJ G, never formed (3 M0 x 3 M)
    F_true0 = sc.evaluate(sc.truth, th0)[0]
    if sc.null_bias is not None:
        F_true0 = F_true0 - sc.null_bias
    y0 = P @ (F_true0 - F_id[0]).reshape(-1)
    # closed form: S blockdiag(C_i) S^T per point, S = PJ G: the parameters' covariance K = G blockdiag(C_i) G^T once
    noise, covered = _closed_form_noise(sc.sources)
    C = sc.id_model.covariance(meas0[0], noise.angular, noise.distance, noise.distance_per_length,
                               noise.repeatability)  # (M, 3, 3) tracker frame, mm^2
    Gb = G.reshape(G.shape[0], M, 3)
    K = np.einsum("pmk,mkl,qml->pq", Gb, C, Gb)
    PJb = PJ.reshape(M0, 3, -1)
    cov = np.einsum("aip,pq,ajq->aij", PJb, K, PJb)
    m = sc.context.measurand
    if m is not None:  # at a tool the verification did not use: the unidentifiable errors' prior
        Gu = P @ m["unidentified_field"][:, sc.mesh_rows].reshape(m["unidentified_field"].shape[0], -1).T
        cov = cov + np.einsum("aik,ajk->aij", Gu.reshape(M0, 3, -1), Gu.reshape(M0, 3, -1))
    sampled, skipped = [], []
    shift = np.zeros(3 * M0)
    for src in sc.sources:
        if src.name in covered or src.name == "unidentified_at_tool":
            continue
        sim = simulate_block(sc, 0, draws, seed, active=[src])
        if sim[2]:  # a discrete choice of the identification's settings
            skipped.append(src.name)
            continue
        dF = sc.evaluate(sc.truth, np.asarray(sim[1])) - sc.evaluate(sc.truth, th0)
        if sim.measurand_offset is not None:
            dF = dF + sim.measurand_offset[:, sc.mesh_rows]
        de = dF.reshape(draws, -1) @ P.T + ((np.asarray(sim[0]) - meas0).reshape(draws, -1) @ G.T) @ PJ.T  # (draws, 3 M0)
        if not np.any(de):
            skipped.append(src.name)
            continue
        mean = de.mean(axis=0)
        d = (de - mean).reshape(draws, M0, 3)
        cov = cov + np.einsum("nai,naj->aij", d, d) / (draws - 1)
        shift += mean
        sampled.append(src.name)
    basis = {"closed_form": covered + (["unidentified_at_tool (prior)"] if m is not None else []),
             "sampled": sampled, "draws": draws, "no_first_order_effect": skipped,
             "note": "GUF on the same inputs as the MCM: the identification and compensation linearised about the "
                     "noise-free verification; the tracker noise (angular u by E[u^2] of its hierarchical draw), "
                     "repeatability and control error in closed form" +
                     (f"; {', '.join(sampled)}: their own draws ({draws} each) through the same linear model"
                      if sampled else "")}
    return {"estimate": ((y0 + shift) * um).reshape(M0, 3), "cov": cov * um**2, "basis": basis}


CHARACTERISTICS = ("component", "max")

#: the per-trial figures over the mesh a decision reads (mtbudget.outputs.SCALARS names)
DECISION_FIGURES = ("largest_abs_component", "largest_abs_component_x", "largest_abs_component_y",
                    "largest_abs_component_z", "compensation_max")


@dataclass
class Evidence:
    """What an ISO 14253-1 decision needs of a statement, whichever its kind: a run's a priori statement
    (:class:`mtbudget.outputs.RunResult`) or a recording's a posteriori one (:class:`mtbudget.posterior.Posterior`).

    ``coverage`` p; ``points()`` the per-point statement (its coverage intervals); ``figures`` the names of the
    per-trial figures over the mesh it holds (:data:`DECISION_FIGURES`), ``samples(name)`` every trial's value (None
    when only a histogram is kept) and ``quantiles(name, probs)`` their order statistics (JCGM 101 7.7.1) or the
    histogram's; ``trials`` how many; ``components()`` every trial's components (trials, 3 M0) or None;
    ``max_interval()`` the symmetric coverage interval of compensation_max; ``refers_to`` what the decision is
    about, in words."""

    coverage: float
    points: Callable
    figures: tuple
    samples: Callable
    quantiles: Callable
    trials: int
    components: Callable
    max_interval: Callable
    refers_to: str
    caveat: str | None = None  # why no verdict is supported whatever the figures say (an a posteriori fit that fails)
    frame: bool = False  # the components are in a turning table's frame (five-axis), not the machine's X, Y, Z

    @classmethod
    def of(cls, statement) -> "Evidence":
        """The evidence of a run, of an a posteriori statement, or itself."""
        if isinstance(statement, cls):
            return statement
        from .posterior import Posterior

        return cls.of_posterior(statement) if isinstance(statement, Posterior) else cls.of_run(statement)

    @classmethod
    def of_run(cls, res: RunResult) -> "Evidence":
        def components():
            parts = res.acc.vector_samples.get("components")
            return np.concatenate(parts) if parts else None

        in_use = bool(((res.spec or {}).get("measurand") or {}).get("in_use"))
        return cls(coverage=res.coverage, points=res.points, figures=tuple(res.acc.scalar_names),
                   samples=res.acc.scalar_samples, quantiles=lambda name, probs: _quantiles(res, name, probs),
                   trials=res.acc.n, components=components,
                   max_interval=lambda: res.summary("compensation_max")["symmetric"],
                   refers_to=("the compensated machine in use (repeatability, reversal and thermal residual included)"
                              if in_use else "the compensated machine as the verification sees it (not its use: add "
                                             "the source in_use for a tolerance on positioning in use)"),
                   frame=table_frame(res))

    @classmethod
    def of_posterior(cls, post) -> "Evidence":
        p = post.coverage
        return cls(coverage=p, points=post.points, figures=DECISION_FIGURES, samples=post.figure,
                   quantiles=lambda name, probs: [_order_quantile(post.figure(name), q) for q in probs],
                   trials=post.trials, components=lambda: post.components,
                   max_interval=lambda: symmetric_interval(np.sort(post.figure("compensation_max")), p),
                   refers_to="the compensated machine as this recorded verification identified it, given the "
                             "recording's stated noise (only the physics the identified model holds; not the machine "
                             "in use)",
                   caveat=_fit_caveat(post), frame=bool(post.points()) and "frame" in post.points()[0])


def _fit_caveat(post) -> str | None:
    """The fit test's warning when the residuals exceed the stated noise (the model leaves out physics the recording
    shows: the statement does not contain it, so no verdict is supported); None otherwise (residuals below the noise
    make u conservative, which a verdict can stand on)."""
    t = (post.data.get("identification") or {}).get("fit_test") or {}
    return t.get("warning") if t.get("warning") and t.get("p_above", 1.0) < t.get("alpha", 0.0) else None


def _xyz(res: Evidence) -> str:
    """"x, y, z" of the statement's components, with their frame where it is a turning table's (five-axis): a
    tolerance box +-T is not the same box in another frame, so the decision says which one it is decided in."""
    return "x, y, z of the workpiece (table) frame" if res.frame else "x, y, z"


def conformance(res, tolerance_um: float, characteristic: str = "component") -> dict:
    """ISO 14253-1 decision for a tolerance T on the compensated machine's error, with the rule and its scope stated.

    characteristic "component": every error component (x, y, z) at every mesh point must lie within [-T, T].  The
    verdict is for the whole machine (``scope`` "machine", :func:`machine_conformance`): a statement at the run's
    coverage probability p about all point-axes at once, from the distribution of the largest |component| over the
    mesh.  The per-point decisions stay beside it under ``per_point`` (``scope`` "per point"): conformance proven at
    a point and axis when its own coverage interval lies inside the zone; they are not a statement about the
    machine (225 intervals of 95 % each do not make a 95 % statement about all 225).
    characteristic "max": the largest 3-D error over the mesh (compensation_max) must not exceed T; decided on the
    upper end of its coverage interval (scope "machine").

    ``res``: a run, an a posteriori statement (:class:`mtbudget.posterior.Posterior`) or their :class:`Evidence`: the
    same rule on either kind of statement.
    """
    if characteristic not in CHARACTERISTICS:
        raise ValueError(f"characteristic must be one of {CHARACTERISTICS}")
    res = Evidence.of(res)
    if characteristic == "max":
        out = _conformance(res, tolerance_um, characteristic)
    else:
        pp = _conformance(res, tolerance_um, characteristic)
        out = machine_conformance(res, tolerance_um)
        if out is None:  # a log without the per-trial figures of the machine: the per-point decisions alone, said so
            out = {**pp, "scope": "per point", "per_point": pp,
                   "statement": pp["statement"] + " No decision for the whole machine: this run log does not hold the "
                                                  "largest error component of each trial (run it again)."}
        else:
            out["per_point"] = pp
            out["statement"] += " Per point (each point-axis on its own interval, not a statement about the machine): " + \
                pp["statement"]
    out["refers_to"] = res.refers_to
    out["statement"] += f" The decision refers to {out['refers_to']}."
    if res.caveat:  # the figures' verdict kept beside it; the statement's is undecided: nothing is proven
        out["verdict_of_the_figures"], out["verdict"], out["supported"] = out["verdict"], "undecided", False
        out["statement"] = (f"Undecided: no verdict is supported, because {res.caveat}. What the figures alone would "
                            f"give: {out['statement']}")
    return out


def _said(verdict: str) -> str:
    """A verdict after "the compensated machine": conforms, does not conform, or is undecided (neither proven)."""
    return "is undecided (neither conformance nor non-conformance is proven)" if verdict == "undecided" else verdict


def _order_quantile(y: np.ndarray, prob: float) -> float:
    """The prob-quantile of values y as JCGM 101 7.7.1 reads one: the q-th smallest, q = the integer part of prob M + 1/2."""
    M = y.shape[0]
    q = min(max(int(prob * M + 0.5), 1), M)
    return float(np.partition(y, q - 1)[q - 1])


def _quantiles(res: RunResult, name: str, probs) -> list:
    """Quantiles of a per-trial figure of the run: order statistics of every trial, or its histogram's."""
    y = res.acc.scalar_samples(name)
    if y is not None:
        return [_order_quantile(y, p) for p in probs]
    h = res.acc.scalar_hist
    return h.quantiles(np.asarray(probs, float), rows=[res.acc.scalar_names.index(name)])[0].tolist()


def machine_conformance(res, tolerance_um: float) -> dict | None:
    """The whole machine against a tolerance T on every error component at every mesh point (scope "machine").

    The figure decided on is m = max over points and axes of |e|, per trial (``largest_abs_component``): every
    component lies within +-T exactly when m <= T.  Conformance is proven when P(m <= T) >= p, i.e. the p-quantile
    of m (the upper end of the one-sided coverage interval [0, m_p]) is within T; non-conformance when
    P(m > T) >= p, i.e. its (1 - p)-quantile exceeds T; undecided otherwise.  Beside it: the probability that every
    component is within +-T (the fraction of trials), the same quantile per axis, and, when the run kept every
    trial's components, the simultaneous band over all point-axes (the hyperrectangular coverage region of JCGM 102
    7.7.3: y_j +- k u_j with k the p-quantile of max_j |e_j - y_j| / u_j).  None when the run's blocks do not hold
    the figure (a log written before it existed).
    """
    res = Evidence.of(res)
    if "largest_abs_component" not in res.figures:
        return None
    p, T = res.coverage, float(tolerance_um)
    lo, hi = res.quantiles("largest_abs_component", [1 - p, p])
    axes = [res.quantiles(f"largest_abs_component_{a}", [p])[0] for a in "xyz"]
    y = res.samples("largest_abs_component")
    prob = None if y is None else float(np.mean(y <= T))
    verdict = "conforms" if hi <= T else "does not conform" if lo > T else "undecided"
    band = simultaneous_band(res, T)
    P = "" if prob is None else f"; the probability that every component lies within ±{T:g} µm is {prob:.3f}"
    return {"characteristic": f"every error component ({_xyz(res)}) at every mesh point after compensation, all at once",
            "scope": "machine",
            "rule": f"ISO 14253-1 guarded acceptance for the whole machine: conformance proven when, with probability "
                    f"at least {percent(p)}, every component at every point lies within [-T, T] (the {percent(p)} "
                    f"quantile of the largest |component| over the mesh is within T); non-conformance when, with "
                    f"probability at least {percent(p)}, some component lies outside (its {percent(1 - p)} quantile "
                    f"exceeds T); undecided otherwise",
            "tolerance": T, "unit": "um", "coverage": p, "verdict": verdict,
            "largest_abs_component": {"quantile": hi, "lower_quantile": lo, "per_axis_quantile": axes,
                                      "probability_within": prob, "unit": "um", "trials": res.trials,
                                      "what": f"the {percent(p)} quantile (and the {percent(1 - p)} quantile) of the "
                                              "largest |error component| over the mesh, per trial; per axis: of the "
                                              "largest |x|, |y|, |z| error"},
            "simultaneous_band": band,
            "statement": (f"Whole machine, tolerance ±{T:g} µm on every component at every point: the largest "
                          f"|component| over the mesh is at most {bound(hi, 'up', 1)} µm with probability {percent(p)} (per axis "
                          f"{_xyz(res)}: {', '.join(bound(a, 'up', 1) for a in axes)} µm; rounded up){P}: the compensated machine "
                          f"{_said(verdict)}.")}


def simultaneous_band(res, tolerance_um: float | None = None) -> dict | None:
    """The simultaneous coverage band over every point-axis (JCGM 102 7.7.3's hyperrectangular region) when the
    run kept every trial's components: {"k", "coverage", "half_width" (per point-axis, um), "largest_extent"
    (max_j |y_j| + k u_j), "verdict" against the tolerance}; None otherwise."""
    res = Evidence.of(res)
    Y = res.components()  # (M, 3 M0) um
    if Y is None:
        return None
    ym, u = Y.mean(axis=0), Y.std(axis=0, ddof=1)
    ok = u > 0
    t = (np.abs(Y[:, ok] - ym[ok]) / u[ok]).max(axis=1)
    k = _order_quantile(t, res.coverage)
    half = k * u
    extent = float((np.abs(ym) + half).max())
    out = {"k": k, "coverage": res.coverage, "unit": "um", "half_width": half.tolist(), "largest_extent": extent,
           "what": f"y_j ± k u_j at every point-axis j, k the {percent(res.coverage)} quantile of the largest "
                   "standardised deviation over the mesh per trial (JCGM 102 7.7.3, hyperrectangular region)"}
    if tolerance_um is not None:
        T = float(tolerance_um)
        lo, hi = ym - half, ym + half
        out["verdict"] = ("conforms" if extent <= T else
                          "does not conform" if bool(np.any((hi < -T) | (lo > T))) else "undecided")
    return out


def _conformance(res: Evidence, tolerance_um: float, characteristic: str) -> dict:
    p = res.coverage
    T = tolerance_um
    if characteristic == "max":
        lo, hi = res.max_interval()
        verdict = "conforms" if hi <= T else "does not conform" if lo > T else "undecided"
        return {"characteristic": "largest 3-D error over the mesh after compensation (compensation_max)",
                "scope": "machine",
                "rule": f"ISO 14253-1 guarded acceptance: conformance proven when the upper end of the {percent(p)} coverage "
                        f"interval is within the tolerance; non-conformance when its lower end exceeds it",
                "tolerance": T, "unit": "um", "coverage": p, "interval": [lo, hi], "verdict": verdict,
                "statement": f"The largest error over the mesh after compensation lies in [{bound(lo, 'down', 1)}, {bound(hi, 'up', 1)}] µm "
                             f"({percent(p)} coverage): against a tolerance of {T:g} µm the compensated machine {_said(verdict)}."}
    pts = res.points()
    if not pts or "interval" not in pts[0]:
        raise ValueError("the per-point intervals are not available for this run")
    lo = np.array([q["interval"]["low"] for q in pts])
    hi = np.array([q["interval"]["high"] for q in pts])
    U = (hi - lo) / 2
    inside = (lo >= -T) & (hi <= T)
    outside = (hi < -T) | (lo > T)
    n = lo.size
    return {"characteristic": f"each error component ({_xyz(res)}) at each mesh point after compensation, each on its own",
            "scope": "per point",
            "rule": f"ISO 14253-1 guarded acceptance per point and axis: conformance proven where the {percent(p)} coverage "
                    f"interval lies within [-T, T] (for a symmetric interval: |mean| <= T - h, h its half-width), "
                    f"non-conformance where it lies outside",
            "tolerance": T, "unit": "um", "coverage": p, "U_max": float(U.max()), "U_unit": "um",
            "conforming": int(inside.sum()), "nonconforming": int(outside.sum()),
            "undecided": int(n - inside.sum() - outside.sum()), "of": n,
            "verdict": "conforms" if inside.all() else "does not conform" if outside.any() else "undecided",
            "statement": (f"Tolerance ±{T:g} µm on each axis at each point, per point: conformance proven at {int(inside.sum())} of "
                          f"{n} point-axes, non-conformance at {int(outside.sum())}, undecided at "
                          f"{int(n - inside.sum() - outside.sum())} (largest guard band, the half-width of the coverage interval, {bound(float(U.max()), 'up', 1)} µm, "
                          f"{percent(p)} coverage).")}
