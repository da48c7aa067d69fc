"""What a verification Monte Carlo run produces: its outputs, one block's results, the run's result.

Plain data: the engine fills :class:`BlockResult` s, the runner merges them
into a :class:`RunResult`, the run log writes and reads them, reports
present them.  Nothing here computes a trial.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .stats import Accumulator, CoMoments, Moments, clause8

#: scalar outputs per trial: name -> (unit, description)
SCALARS = {
    "compensation_rms": ("um", "root mean square over the mesh of the error left after compensation (true minus identified field, rigid-body part removed)"),
    "compensation_mean": ("um", "mean over the mesh of the error left after compensation (true minus identified field, rigid-body part removed; paper Eq. 27 read as the compensated machine)"),
    "compensation_max": ("um", "largest error left after compensation over the mesh"),
    "mean_error_after": ("um", "paper Eq. 27 read as the fit residual after compensation: mean distance between measured and compensated points"),
    "mean_error_before": ("um", "paper Eq. 27 before compensation: mean distance between measured and nominal points"),
    "max_residual": ("um", "largest residual distance after compensation"),
    "chi2_per_dof": ("", "weighted residuals against the stated uncertainties"),
}
#: per-trial figures of the whole machine, derived from the per-point components (docs/measurand.md, "The decision"):
#: the largest |error component| over the mesh, per axis and over every point-axis; not volume summaries of the
#: paper, so not in SCALARS (no budget table of their own), but merged, logged and replayed as the scalars are
MACHINE_SCALARS = {
    "largest_abs_component_x": ("um", "largest |x error| over the mesh after compensation"),
    "largest_abs_component_y": ("um", "largest |y error| over the mesh after compensation"),
    "largest_abs_component_z": ("um", "largest |z error| over the mesh after compensation"),
    "largest_abs_component": ("um", "largest |error component| over every point and axis of the mesh after compensation"),
}
MAIN_OUTPUT = "compensation_rms"
#: outputs whose budget is attributed by mean square (additive over independent sources), the others by variance
MEAN_SQUARE_OUTPUTS = ("compensation_rms",)
#: unit of the per-point error and of the parameters in results (display units)
POINT_UNIT = "um"


@dataclass
class BlockResult:
    """The results of one block of trials.

    scalars: output name -> (n,) values; point_error: (n, M0) error left after
    compensation at each mesh point (um); components: (n, M0, 3) the same
    error per machine axis (um), the per-point measurand of docs/measurand.md;
    parameters: (n, p) identified geometric parameters (um / urad); not_converged: trials of the block whose
    identification did not converge (counted, never hidden).  A block read
    back from a run log knows its vector outputs only by their moments
    (``point_moments``, ``parameter_moments``).
    """

    block: int
    n: int
    scalars: dict
    point_error: np.ndarray | None
    parameters: np.ndarray | None
    not_converged: int = 0
    point_moments: Moments | None = None
    parameter_moments: Moments | None = None
    components: np.ndarray | None = None  # (n, M0, 3) um: the compensated machine's error per point and axis
    component_moments: CoMoments | None = None
    fallbacks: int = 0  # trials whose fast identification handed over to full Gauss-Newton
    # which trials did not converge / fell back, (n,) bools, when the block was computed here (so that a block cut
    # to a run's last trials counts its own trials only); a block read back from a log has its counts only
    trial_not_converged: np.ndarray | None = field(default=None, repr=False, compare=False)
    trial_fallbacks: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: [[features]]: (n, K, C) each feature's error per trial (mtbudget.features: total, the verification's state
    #: alone, each in-use source alone); None without features or for a block read back from a log
    features: np.ndarray | None = field(default=None, repr=False, compare=False)
    # the moments of the vector outputs, computed once (a worker computes them before sending the block; the run
    # merges them and the run log writes them); never part of a comparison
    _moments: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        # the whole machine's figures (MACHINE_SCALARS) from the components, once, where the block has them and a log
        # did not bring them already: a block logged with them brings them back, one logged without stays without
        if self.components is not None and self.n and "largest_abs_component" not in self.scalars:
            a = np.abs(self.components).max(axis=1)  # (n, 3)
            self.scalars = {**self.scalars, "largest_abs_component_x": a[:, 0].copy(),
                            "largest_abs_component_y": a[:, 1].copy(), "largest_abs_component_z": a[:, 2].copy(),
                            "largest_abs_component": a.max(axis=1)}

    def truncated(self, n: int) -> "BlockResult":
        """The first ``n`` trials of the block (a run logs the block it merged, already cut to its trials)."""
        if n >= self.n:
            return self
        if self.point_error is None:
            from .errors import ConfigError

            raise ConfigError("a block read back from a log cannot be shortened; resume with the logged trial count")
        nc, fb = self.trial_not_converged, self.trial_fallbacks
        out = BlockResult(self.block, n, {k: v[:n] for k, v in self.scalars.items()}, self.point_error[:n],
                           self.parameters[:n], self.not_converged if nc is None else int(nc[:n].sum()),
                           components=None if self.components is None else self.components[:n],
                           fallbacks=self.fallbacks if fb is None else int(fb[:n].sum()),
                           trial_not_converged=None if nc is None else nc[:n],
                           trial_fallbacks=None if fb is None else fb[:n])
        out.features = None if self.features is None else self.features[:n]
        return out

    def vector_moments(self) -> dict:
        """{"point_error": Moments, "parameters": Moments, "components": CoMoments}, those the block knows (a block
        read back from a log of format 2 knows none: the log's histogram checkpoints hold the run's), computed once."""
        c = self._moments
        if "point_error" not in c:
            c["point_error"] = (self.point_moments if self.point_moments is not None
                                else None if self.point_error is None else Moments.of(self.point_error))
        if "parameters" not in c:
            c["parameters"] = (self.parameter_moments if self.parameter_moments is not None
                               else None if self.parameters is None else Moments.of(self.parameters))
        out = {k: c[k] for k in ("point_error", "parameters") if c[k] is not None}
        cm = self.component_comoments()
        if cm is not None:
            out["components"] = cm
        return out

    def component_comoments(self) -> CoMoments | None:
        """The co-moments of the per-point components (None when the block knows neither them nor the samples),
        computed once."""
        c = self._moments
        if "components" not in c:
            cm = self.component_moments
            if cm is None and self.components is not None:
                cm = CoMoments.of(self.components)
            c["components"] = cm
        return c["components"]


def accumulate_block(acc: Accumulator, b: BlockResult):
    """Merge one block into the run's statistics (scalars exactly, vector outputs by their moments,
    the per-point components also by their samples or a histogram for their intervals)."""
    vectors = None if b.components is None else {"components": b.components.reshape(b.n, -1)}
    scalars = b.scalars
    if acc.scalar_names and tuple(scalars) != acc.scalar_names and set(acc.scalar_names) <= set(scalars):
        # a run resumed from a log written before MACHINE_SCALARS existed: its outputs, those of its first blocks
        scalars = {k: scalars[k] for k in acc.scalar_names}
    acc.add(b.block, b.n, scalars, b.vector_moments(), b.not_converged, vectors, b.fallbacks)


#: a run keeps every trial's scalar outputs (exact order-statistic intervals) up to this many trials, and histograms
#: them beyond (memory bounded; the intervals say their method): a fixed run from its start, an adaptive run from the
#: block that takes it past this many (runner.run)
KEEP_SAMPLES_TRIALS = 200_000


#: the frame of a five-axis machine's per-point components (docs/measurand.md, "Five-axis machines: the frame")
WORKPIECE_FRAME = ("workpiece (table) frame: x, y, z are the machine's X, Y, Z with every rotary axis at zero, "
                   "turning with the table (the tracker's frame; ISO 230-1's tool relative to the workpiece)")


def table_frame(res) -> bool:
    """Whether a run's per-point components are in a turning table's frame (a rotary axis carries the workpiece):
    then x, y, z are not the machine's X, Y, Z at every pose."""
    if getattr(res, "to_machine", None) is not None:
        return True
    code = str(((res.spec or {}).get("config") or {}).get("machine") or "").upper()
    return bool(getattr(res, "angles", None)) and any(ch in "ABC" for ch in code.partition("F")[0])


def frame_word(res) -> str:
    """" (table frame)" after x, y, z where the components are in a turning table's frame; empty otherwise."""
    return " (table frame)" if table_frame(res) else ""


def machine_frame(mean, cov, R) -> dict:
    """A five-axis point's entries beside its workpiece-frame statement: ``frame`` and ``machine_frame`` (mean R m,
    u from R C R^T, covariance; R the nominal orientation of the table at the point's pose)."""
    R = np.asarray(R, float)
    C = R @ np.asarray(cov, float) @ R.T
    return {"frame": WORKPIECE_FRAME,
            "machine_frame": {"what": "the same error in the machine's X, Y, Z at this pose (the workpiece-frame "
                                      "components turned by the table's nominal orientation): what a compensation in "
                                      "the linear axes acts on; mean and covariance exact, no coverage interval",
                              "mean": (R @ np.asarray(mean, float)).tolist(),
                              "u": np.sqrt(np.maximum(np.diagonal(C), 0.0)).tolist(),
                              "covariance": C.tolist(), "unit": POINT_UNIT, "rotation": R.tolist()}}


@dataclass
class RunResult:
    spec: dict
    trials: int
    coverage: float
    acc: Accumulator
    parameter_names: list
    parameter_units: list
    convergence: list = field(default_factory=list)  # per chunk: {"trials", "mean", "std", "low", "high"} of MAIN_OUTPUT
    budget: dict = field(default_factory=dict)  # output -> budget table
    complete: bool = True
    stopped_at_limit: bool = False  # adaptive run that hit max_trials before reaching its tolerance
    adaptive: dict | None = None  # adaptive run: what stabilised at how many trials (report.adaptive_line)
    #: what ran the trials: {"kind": inline|thread|process|dask, "workers": n, "requested": the --executor given}
    executor: dict | None = None
    weights: dict | None = None  # stated identification weights when they differ from what the run draws
    log_path: object = None
    log: object = None
    mesh: np.ndarray | None = None  # (M0, 3) nominal tool points of the mesh, machine frame (mm)
    commanded: np.ndarray | None = None  # (M0, 3) commanded axis positions of the mesh points (mm)
    angles: dict | None = None  # five-axis: {letter: (M0,) commanded angle of each rotary axis (deg)} at the mesh points
    #: five-axis with a rotary table: (M0, 3, 3) the nominal orientation of the workpiece (table) frame, in which the
    #: per-point components are stated, in the machine frame at each point's pose (machine.workpiece_rotation)
    to_machine: np.ndarray | None = None
    guf: dict | None = None  # law of propagation per point: {"estimate": (M0, 3) um, "cov": (M0, 3, 3) um^2}
    logged_points: list | None = None  # per-point results of a complete log (replay of a run too long to log trials)
    log_problem: str | None = None  # the run log could not be written (a full disk): what happened, how to resume
    resume_notes: list = field(default_factory=list)  # what a resume recomputed and why (damaged blocks ...)
    prefix: object = field(default=None, repr=False, compare=False)  # during a run: its first trials for the budget
    #: [[features]]: every merged block's (n, K, C) feature errors, in block order (a resumed block has none: None)
    feature_blocks: list = field(default_factory=list, repr=False, compare=False)
    logged_features: list | None = None  # the features of a complete log (replay)
    #: replay of a run that histogrammed its scalars: the main output's exact order-statistic intervals from the
    #: logged values, stated beside the run's ({"output", "unit", "n", "coverage", "symmetric", "shortest"})
    exact_from_log: dict | None = None

    @property
    def not_converged(self) -> int:
        return self.acc.not_converged

    @property
    def fallbacks(self) -> int:
        return self.acc.fallbacks

    def summary(self, name: str = MAIN_OUTPUT) -> dict:
        return self.acc.summary(name, self.coverage)

    def outputs(self) -> dict:
        """Every scalar output: mean, std, intervals, with units."""
        return {k: {**self.summary(k), "unit": SCALARS[k][0], "description": SCALARS[k][1]} for k in SCALARS}

    def points(self) -> list | None:
        """The per-point, per-axis statement (docs/measurand.md): one entry per mesh point, in plan order."""
        cm = self.acc.moments.get("components")
        if cm is None or self.commanded is None:
            return self.logged_points
        M0 = cm.mean.shape[0]
        iv = self.acc.vector_intervals("components", self.coverage)
        if iv is None and self.logged_points is not None:
            return self.logged_points
        u = cm.std
        out = []
        from .distributions import t_factor

        k = t_factor(self.coverage, float("inf"))
        for i in range(M0):
            e = {"point": i, "nominal": {"value": self.commanded[i].tolist(), "unit": "mm"},
                 **({"angles": {"value": {r: float(v[i]) for r, v in self.angles.items()}, "unit": "deg"}}
                    if self.angles else {}),
                 "mean": {"value": cm.mean[i].tolist(), "unit": POINT_UNIT},
                 "u": {"value": u[i].tolist(), "unit": POINT_UNIT},
                 "covariance": {"value": cm.cov[i].tolist(), "unit": f"{POINT_UNIT}^2"}}
            if self.to_machine is not None:  # five-axis: the same components, turned into the machine axes
                e.update(machine_frame(cm.mean[i], cm.cov[i], self.to_machine[i]))
            if iv is not None:
                sl = slice(3 * i, 3 * i + 3)
                e["interval"] = {"low": iv["low"][sl].tolist(), "high": iv["high"][sl].tolist(), "unit": POINT_UNIT,
                                 "coverage": self.coverage, "kind": "probabilistically symmetric", "method": iv["method"]}
                if iv["shortest_low"] is not None:
                    e["shortest_interval"] = {"low": iv["shortest_low"][sl].tolist(),
                                              "high": iv["shortest_high"][sl].tolist(), "unit": POINT_UNIT,
                                              "coverage": self.coverage, "kind": "shortest",
                                              "method": iv["shortest_method"]}
            if self.guf is not None:
                g_u = np.sqrt(np.maximum(np.diagonal(self.guf["cov"][i]), 0.0))
                g_y = self.guf["estimate"][i]
                e["guf_u"] = {"value": g_u.tolist(), "unit": POINT_UNIT}
                e["guf_estimate"] = {"value": g_y.tolist(), "unit": POINT_UNIT}
                if iv is not None:
                    verdicts = []
                    for a in range(3):
                        d_lo, d_hi, delta, ok = clause8((g_y[a] - k * g_u[a], g_y[a] + k * g_u[a]),
                                                        (iv["low"][3 * i + a], iv["high"][3 * i + a]), g_u[a], 2)
                        verdicts.append({"d_low": d_lo, "d_high": d_hi, "delta": delta, "passed": ok})
                    e["clause8"] = verdicts
            out.append(e)
        return out

    def convergence_row(self) -> dict:
        s = self.summary(MAIN_OUTPUT)
        return {"trials": self.acc.n, "mean": s["mean"], "std": s["std"], "low": s["symmetric"][0],
                "high": s["symmetric"][1], "output": MAIN_OUTPUT, "unit": SCALARS[MAIN_OUTPUT][0]}


#: a run whose identification did not converge on more than this share of its trials is no statement to sign: its
#: text and report open with the warning, and no certificate (certificate.xml, the DCC) is written for it
MAX_NOT_CONVERGED = 0.01


def too_many_not_converged(n: int, trials: int) -> bool:
    """Whether ``n`` trials of ``trials`` whose identification did not converge are more than
    :data:`MAX_NOT_CONVERGED` of them."""
    return n > MAX_NOT_CONVERGED * max(trials, 1)


def no_certificate_line(n: int, trials: int) -> str:
    """Why a run with too many trials that did not converge gets no certificate.xml (the report says the same)."""
    return (f"certificate.xml is not written: the identification of {n} of {trials} trials "
            f"({100.0 * n / max(trials, 1):.3g} %) did not converge, more than {100 * MAX_NOT_CONVERGED:g} %: the "
            "numbers describe a verification whose identification fails, not a statement to certify; check the "
            "configuration's inputs (units, noise, the machine's errors)")


def not_converged_line(n: int, trials: int) -> str:
    """What trials whose identification did not converge mean for the run's numbers (text and report alike)."""
    return (f"WARNING: the identification of {n} of {trials} trials ({100.0 * n / max(trials, 1):.3g} %) did not "
            "converge: they stopped at the iteration limit, away from the solution a verification would report, and "
            "every number below includes them as they stood, so it describes a verification whose identification "
            "may fail, not one that succeeds; before signing, check the stated inputs (units, noise, the machine's "
            "errors) against the machine (`mtbudget run --json`: not_converged)")
