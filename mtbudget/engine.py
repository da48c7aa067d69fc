"""The Monte Carlo kernel of a verification: one block of trials, from sources to outputs.

For a block, :class:`Engine` draws the sources (through the one simulator,
:func:`mtbudget.simulate.simulate_block`), identifies every simulated
verification as the real one would (grouped by the identification settings
the optimisation-strategy sources chose), and evaluates the error left after
compensation at the mesh points.  Running many blocks, merging their
statistics, logging and the budget live in :mod:`mtbudget.runner`,
:mod:`mtbudget.executors` and :mod:`mtbudget.budget`.
"""

from __future__ import annotations

import numpy as np

from .errors import ConfigError
from .identify import Strategy, identify
from .outputs import POINT_UNIT, SCALARS, BlockResult
from .plugins import call
from .scenario import Scenario, target_shapes
from .simulate import sample_source, simulate_block
from .units import factor, shown_unit


class Engine:
    """Monte Carlo of a verification: build once from a scenario, run blocks."""

    def __init__(self, scenario: Scenario, *, block: int = 64, seed: int | None = None):
        self.scenario = scenario
        self.block = int(block)
        if self.block < 1:
            raise ConfigError("block size must be >= 1", key="block")
        self.seed = scenario.config.seed if seed is None else int(seed)
        self.sources = scenario.sources
        self.shapes = target_shapes(scenario)
        for s in self.sources:  # probe: keys, shapes, dimensions and NaN checked once, before any trial
            sample_source(scenario, s, 2, np.random.default_rng(0), self.shapes)
        self._um = factor("mm", POINT_UNIT)

    # ------------------------------------------------------------------ one block
    def simulate(self, block: int, active: list | None = None):
        """The simulated measurements of one block (see :func:`mtbudget.simulate.simulate_block`)."""
        return simulate_block(self.scenario, block, self.block, self.seed, active, self.shapes)

    def run_block(self, block: int, active: list | None = None) -> BlockResult:
        """Trials ``block*B .. (block+1)*B - 1`` with the ``active`` sources (default: all selected)."""
        sc = self.scenario
        n = self.block
        meas, theta_true, choices = self.simulate(block, active)
        F_true = sc.truth.machine_points(theta_true)[:, sc.mesh_rows]

        # group trials by the identification settings the optimisation-strategy sources chose
        options = [(src, call(src, "options", sc.context)) for src, _ in choices]
        keys = np.zeros(n, int)
        for (src, c), (_, opts) in zip(choices, options):
            keys = keys * len(opts) + c
        base = sc.id_model
        out_scalars = {k: np.empty(n) for k in SCALARS}
        point_err = np.empty((n, len(sc.mesh_rows)))
        components = np.empty((n, len(sc.mesh_rows), 3))
        params = np.zeros((n, base.n_params))
        not_converged = fallbacks = 0
        um = self._um
        for key in np.unique(keys):
            idx = np.flatnonzero(keys == key)
            settings: dict = {}
            rem = int(key)
            for _, opts in reversed(options):
                settings.update(opts[rem % len(opts)])
                rem //= len(opts)
            model, strategy = self._identification_setup(settings)
            res = identify(model, meas[idx], sc.noise, strategy, chunk=self.block)
            not_converged += int((~res.converged).sum())
            fallbacks += int(res.n_fallback)
            F_id = model.machine_points(res.theta)[:, sc.mesh_rows]
            D = (F_true[idx] - F_id).reshape(len(idx), -1) @ sc.rigid_free.T
            comp = D.reshape(len(idx), -1, 3) * um
            components[idx] = comp
            e = np.linalg.norm(D.reshape(len(idx), -1, 3), axis=2) * um
            point_err[idx] = e
            out_scalars["compensation_rms"][idx] = np.sqrt((e**2).mean(axis=1))
            out_scalars["compensation_mean"][idx] = e.mean(axis=1)
            out_scalars["compensation_max"][idx] = e.max(axis=1)
            out_scalars["mean_error_after"][idx] = res.mean_error_after * um
            out_scalars["mean_error_before"][idx] = res.mean_error_before * um
            out_scalars["max_residual"][idx] = res.max_residual * um
            out_scalars["chi2_per_dof"][idx] = res.chi2_per_dof
            scale = np.array([factor(u, shown_unit(u)) for u in model.errors.units])
            if model is base:
                params[idx] = res.theta * scale
            else:
                names = base.errors.names
                for j, nm in enumerate(model.errors.names):
                    if nm in names:
                        params[idx, names.index(nm)] = res.theta[:, j] * scale[j]
        return BlockResult(block, n, out_scalars, point_err, params, not_converged, components=components,
                           fallbacks=fallbacks)

    def _identification_setup(self, settings: dict):
        model = self.scenario.identification_model(int(settings.get("max_degree", self.scenario.max_degree)))
        phases = settings.get("phases", "one-phase")
        base = Strategy.multi_phase() if phases == "multi-phase" else Strategy.one_phase()
        if "xtol" in settings:
            base.xtol = float(settings["xtol"])
        if "max_iter" in settings:
            base.max_iter = int(settings["max_iter"])
        return model, base

    # ------------------------------------------------------------------ description
    @property
    def parameter_names(self) -> list:
        return self.scenario.id_model.errors.names

    @property
    def parameter_units(self) -> list:
        return [shown_unit(u) for u in self.scenario.id_model.errors.units]
