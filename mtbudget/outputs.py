"""What a verification Monte Carlo run produces: its outputs, one block's results, the run's result.

Plain data: the engine fills :class:`BlockResult` s, the runner merges them
into a :class:`RunResult`, the run log writes and reads them, reports
present them.  Nothing here computes a trial.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .stats import Accumulator, Moments

#: scalar outputs per trial: name -> (unit, description)
SCALARS = {
    "compensation_rms": ("um", "root mean square over the mesh of the error left after compensation (true minus identified field, rigid-body part removed)"),
    "compensation_mean": ("um", "mean over the mesh of the error left after compensation (true minus identified field, rigid-body part removed)"),
    "compensation_max": ("um", "largest error left after compensation over the mesh"),
    "mean_error_after": ("um", "paper Eq. 27 after compensation: mean distance between measured and compensated points"),
    "mean_error_before": ("um", "paper Eq. 27 before compensation: mean distance between measured and nominal points"),
    "max_residual": ("um", "largest residual distance after compensation"),
    "chi2_per_dof": ("", "weighted residuals against the stated uncertainties"),
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
    compensation at each mesh point (um); parameters: (n, p) identified
    geometric parameters (um / urad); not_converged: trials of the block whose
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

    def truncated(self, n: int) -> "BlockResult":
        """The first ``n`` trials of the block."""
        if self.point_error is None:
            from .errors import ConfigError

            raise ConfigError("a resumed block cannot be shortened; resume with the logged trial count")
        return BlockResult(self.block, n, {k: v[:n] for k, v in self.scalars.items()}, self.point_error[:n],
                           self.parameters[:n], self.not_converged)

    def vector_moments(self) -> dict:
        return {"point_error": self.point_moments if self.point_moments is not None else Moments.of(self.point_error),
                "parameters": self.parameter_moments if self.parameter_moments is not None else Moments.of(self.parameters)}


def accumulate_block(acc: Accumulator, b: BlockResult):
    """Merge one block into the run's statistics (scalars exactly, vector outputs by their moments)."""
    acc.add(b.block, b.n, b.scalars, b.vector_moments(), b.not_converged)


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
    weights: dict | None = None  # stated identification weights when they differ from what the run draws
    log_path: object = None
    log: object = None
    mesh: np.ndarray | None = None

    @property
    def not_converged(self) -> int:
        return self.acc.not_converged

    def summary(self, name: str = MAIN_OUTPUT) -> dict:
        return self.acc.summary(name, self.coverage)

    def outputs(self) -> dict:
        """Every scalar output: mean, std, intervals, with units."""
        return {k: {**self.summary(k), "unit": SCALARS[k][0], "description": SCALARS[k][1]} for k in SCALARS}

    def convergence_row(self) -> dict:
        s = self.summary(MAIN_OUTPUT)
        return {"trials": self.acc.n, "mean": s["mean"], "std": s["std"], "low": s["symmetric"][0],
                "high": s["symmetric"][1], "output": MAIN_OUTPUT, "unit": SCALARS[MAIN_OUTPUT][0]}
