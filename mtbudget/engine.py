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
from .features import FeatureSet
from .identify import Strategy, identify, scale_vector
from .outputs import MACHINE_SCALARS, POINT_UNIT, SCALARS, BlockResult
from .plugins import call
from .scenario import Scenario, target_shapes
from .simulate import sample_source, simulate_block
from .tracker import norm3
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
        self._options: dict = {}  # strategy source name -> its options, asked once per engine
        self.features = FeatureSet.of(scenario)  # [[features]] (docs/features.md); None without

    # ------------------------------------------------------------------ one block
    def simulate(self, block: int, active: list | None = None):
        """The simulated measurements of one block (see :func:`mtbudget.simulate.simulate_block`)."""
        return simulate_block(self.scenario, block, self.block, self.seed, active, self.shapes, self._options)

    def run_block(self, block: int, active: list | None = None) -> BlockResult:
        """Trials ``block*B .. (block+1)*B - 1`` with the ``active`` sources (default: all selected)."""
        return self.run_blocks([block], active)[0]

    def run_blocks(self, blocks: list, active: list | None = None) -> list:
        """Several blocks at once: each block's results are bit-identical to :meth:`run_block` of that block alone.

        Each block draws its own streams; the blocks' trials are then identified together, one
        identification call per setting the optimisation-strategy sources chose, with one label per
        block (:func:`mtbudget.identify.identify` ``groups``): every product that mixes trials is
        done block by block, so only the fixed cost of each call is shared.
        """
        sc = self.scenario
        n = self.block
        blocks = [int(b) for b in blocks]
        nb = len(blocks)
        if not nb:
            return []
        sims = [self.simulate(b, active) for b in blocks]
        meas = np.concatenate([s[0] for s in sims]) if nb > 1 else sims[0][0]
        theta_true = [s[1] for s in sims]
        label = np.repeat(np.arange(nb), n)

        # group trials by the identification settings the optimisation-strategy sources chose
        choices = sims[0][2]
        options = [(src, self._options_of(src)) for src, _ in choices]
        keys = np.zeros(nb * n, int)
        for j, (src, opts) in enumerate(options):
            c = np.concatenate([s[2][j][1] for s in sims])
            keys = keys * len(opts) + c
        base = sc.id_model
        rows = sc.mesh_rows
        F_id = np.empty((nb * n, len(rows), 3))
        params = np.zeros((nb * n, base.n_params))
        out_scalars = {k: np.empty(nb * n) for k in SCALARS}
        not_converged = np.zeros(nb * n, bool)  # per trial: a block cut to a run's last trials counts its own
        fallbacks = np.zeros(nb * n, bool)
        fs = self.features
        Ff_id = None if fs is None else np.empty((nb * n, len(fs.points), 3))  # identified machine at the features
        um = self._um
        calls: dict = {}  # one identification call per setting: {key: (model, strategy, [key])}
        # the one-tracker identification's (noise, pose): [tracker], or a [[stations]] list of one laser tracker (its
        # own stated noise and pose; the same problem, so the same identification); None: several stations
        one = sc.one_tracker
        for key in np.unique(keys):
            settings: dict = {}
            rem = int(key)
            for _, opts in reversed(options):
                settings.update(opts[rem % len(opts)])
                rem //= len(opts)
            model, strategy = self._identification_setup(settings)
            # several stations too: one call per setting (the identification over all stations takes the strategy's
            # phases, xtol and max_iter with the one-tracker meaning: multistation.strategy_settings)
            calls.setdefault(key, (model, strategy, []))[2].append(key)
        for model, strategy, group in calls.values():
            idx = np.flatnonzero(np.isin(keys, group))
            if one is None:
                ranges = np.concatenate([s.ranges for s in sims]) if nb > 1 else sims[0].ranges
                res = _StationsResult(model, sc, meas[idx], ranges[idx], strategy)
            else:  # [scales]: the stated nominal expansion at the read temperatures is a known input, (1, M) arrays
                res = identify(model, meas[idx], one[0], strategy, chunk=n, groups=label[idx],
                               fixed=sc.correction or None, iteration_pose=one[1])
            not_converged[idx] = ~res.converged
            if res.fallback is not None:
                fallbacks[idx] = res.fallback
            F_id[idx] = sc.evaluate(model, res.theta, points=res.points)
            if fs is not None:
                Ff_id[idx] = fs.evaluate(model, res.theta)
            out_scalars["mean_error_after"][idx] = res.mean_error_after * um
            out_scalars["mean_error_before"][idx] = res.mean_error_before * um
            out_scalars["max_residual"][idx] = res.max_residual * um
            out_scalars["chi2_per_dof"][idx] = res.chi2_per_dof
            scale = scale_vector(model)  # um per mm, urad per rad: the units parameters are shown in
            if model is base:
                params[idx] = res.theta * scale
            else:
                names = base.errors.names
                for j, nm in enumerate(model.errors.names):
                    if nm in names:
                        params[idx, names.index(nm)] = res.theta[:, j] * scale[j]
        # the truth at the mesh for the whole chunk in one chain call (each trial's points depend on its own
        # parameters only: the same bits as one call per block); the compensated field's rigid motions removed
        # with one product per block (a BLAS product mixes trials: the same rows as a block alone), then the
        # per-point errors and the scalars of every trial of the chunk at once (elementwise, or reduced within
        # each trial's row: the same bits as per block), each block a view of them (issue 31)
        F_true = sc.evaluate(sc.truth, np.concatenate(theta_true) if nb > 1 else theta_true[0])
        if sc.null_bias is not None:  # the truth's own unidentifiable part at this tool: its prior is drawn instead
            F_true = F_true - sc.null_bias
        for i, s in enumerate(sims):  # the machine in use, the unidentified part at the tool (F_true is this call's)
            if s.measurand_offset is not None:
                F_true[i * n:(i + 1) * n] += s.measurand_offset[:, rows]
        diff = (F_true - F_id).reshape(nb * n, -1)  # the compensated field before the rigid motions are removed
        D = [(diff[i * n:(i + 1) * n] @ sc.rigid_free.T).reshape(n, -1, 3) for i in range(nb)]
        comp, e, whole = compensation_figures(D, um, out_scalars)
        nc_counts = not_converged.reshape(nb, n).sum(axis=1)
        fb_counts = fallbacks.reshape(nb, n).sum(axis=1)
        results = []
        for i, b in enumerate(blocks):
            sl = slice(i * n, (i + 1) * n)
            sc_b = {k: out_scalars[k][sl] for k in SCALARS}
            sc_b.update((k, v[sl]) for k, v in whole.items())
            results.append(BlockResult(b, n, sc_b, e[sl], params[sl], int(nc_counts[i]), components=comp[sl],
                                       fallbacks=int(fb_counts[i]), trial_not_converged=not_converged[sl],
                                       trial_fallbacks=fallbacks[sl]))
            if fs is not None:  # the same state of the compensated machine at every probed point, rigid part kept
                results[-1].features = fs.block_values(fs.evaluate(sc.truth, theta_true[i]) - Ff_id[sl], self.seed, b)
        return results

    def _options_of(self, src) -> list:
        if src.name not in self._options:
            self._options[src.name] = call(src, "options", self.scenario.context)
        return self._options[src.name]

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


def compensation_figures(D, um: float, scalars: dict) -> tuple:
    """The compensated field D (N, M, 3) mm (rigid motions removed), or its blocks (a list of (n_i, M, 3), one after
    the other along the trials), as reported: (components (N, M, 3) um, per-point errors (N, M) um, the whole machine's
    figures (``outputs.MACHINE_SCALARS``) {name: (N,)}), with SCALARS' ``compensation_rms``, ``_mean`` and ``_max``
    written into ``scalars``; one compiled pass per block (:func:`mtbudget.kernels_stats.compensation_figures`), the
    numbers of :func:`compensation_figures_reference` of the concatenation (each trial's figures are its own)."""
    from .kernels_stats import BUFFER, LIKE_NUMPY, compensation_figures as kernel

    parts = [D] if isinstance(D, np.ndarray) else list(D)
    M = parts[0].shape[1]
    if not M or (not LIKE_NUMPY and M > BUFFER):  # numpy < 2.3 sums more than BUFFER points by buffers: its bits
        return compensation_figures_reference(np.concatenate(parts), um, scalars)
    N = sum(p.shape[0] for p in parts)
    comp, e = np.empty((N, M, 3)), np.empty((N, M))
    rms, mean, emax, amax = np.empty(N), np.empty(N), np.empty(N), np.empty((4, N)).T
    at = 0
    for p in parts:
        sl = slice(at, at + p.shape[0])
        kernel(np.require(p, np.float64, ["C"]), float(um), comp[sl], e[sl], rms[sl], mean[sl], emax[sl], amax[sl])
        at = sl.stop
    scalars.update(compensation_rms=rms, compensation_mean=mean, compensation_max=emax)
    return comp, e, dict(zip(MACHINE_SCALARS, amax.T))


def compensation_figures_reference(D: np.ndarray, um: float, scalars: dict) -> tuple:
    """:func:`compensation_figures` in numpy: the formulation the engine used before the kernel (and BlockResult's
    own whole-machine figures), kept as its reference."""
    comp = D * um
    e = norm3(D) * um
    scalars.update(compensation_rms=np.sqrt((e**2).mean(axis=1)), compensation_mean=e.mean(axis=1),
                   compensation_max=e.max(axis=1))
    a = np.abs(comp).max(axis=1)
    return comp, e, {"largest_abs_component_x": a[:, 0].copy(), "largest_abs_component_y": a[:, 1].copy(),
                     "largest_abs_component_z": a[:, 2].copy(), "largest_abs_component": a.max(axis=1)}


class _StationsResult:
    """The trials of a verification from several stations ([[stations]]: two or more, or any interferometer; one laser
    tracker alone is identified as [tracker] is, ``Scenario.one_tracker``), identified over all their stations at
    once (:func:`mtbudget.multistation.identify_stations_batch`; a trial it cannot finish is solved again by
    :func:`mtbudget.multistation.identify_stations`, the reference, and counted in ``fallback``), with the
    optimisation strategy's phases, xtol and max_iter as the one-tracker identification takes them
    (:func:`mtbudget.multistation.strategy_settings`).  Holds what the engine reads of an identification: theta,
    convergence and the paper's Eq. 27 scalars.  Eq. 27 is a mean
    distance between measured and compensated points: it is taken over the laser trackers' rows (an interferometer
    measures a distance, not a point), or over the range residuals when every station is an interferometer."""

    points = None  # the machine points at the solution are not kept: the compensated field is evaluated anew

    def __init__(self, model, sc: Scenario, meas: np.ndarray, ranges: np.ndarray, strategy: Strategy | None = None):
        from .multistation import identify_stations, identify_stations_batch, multilaterate, strategy_settings

        fixed = sc.correction or None
        k, p = len(meas), model.n_params
        hold = sc.unidentifiable(model)
        how = strategy_settings(model, strategy or Strategy.one_phase())
        b = identify_stations_batch(model, sc.stations, sc.row_station, meas, ranges, sc.noise.repeatability,
                                    fixed=fixed, hold=hold, basis=_station_basis(sc, model, fixed, hold),
                                    **how["batch"])
        self.theta, self.converged = b["theta"].copy(), b["converged"].copy()
        self.chi2_per_dof = b["chi2"] / b["dof"]
        res_xyz, res_rng = b["residual_xyz"].copy(), b["residual_range"].copy()
        self.fallback = b["failed"].copy()
        for i in np.flatnonzero(self.fallback):
            r = identify_stations(model, sc.stations, sc.row_station, meas[i], ranges[i], sc.noise.repeatability,
                                  fixed=fixed, hold=hold, **how["reference"])
            self.theta[i], self.converged[i], self.chi2_per_dof[i] = r.x[:p], r.converged, r.chi2_per_dof
            res_xyz[i], res_rng[i] = r.residual_xyz, r.residual_range
        xyz_rows = np.isin(sc.row_station, [st.id for st in sc.stations if st.kind == "xyz"])
        # reduced within each trial's row, so that a trial's figures do not depend on the trials identified with it
        after = norm3(res_xyz[:, xyz_rows]) if xyz_rows.any() else np.abs(res_rng)  # (k, rows), each row its trial's
        self.mean_error_after = after.mean(axis=1)
        self.max_residual = after.max(axis=1)
        # before compensation: the nominal machine, each station placed by its closed-form start (unweighted Kabsch
        # for a tracker: the one-tracker path's weighted pose fit gives about 5 % less on the paper's configuration)
        # (a laser tracker's rows: the fit and the distances compiled, one trial at a time,
        # kernels_stations.registered_distances, the numbers of tracker.register and to_tracker to round-off)
        from .kernels_stations import registered_distances

        P0 = model.machine_points(np.zeros((1, p)), fixed)[0]
        before = []
        for st in sc.stations:
            idx = np.flatnonzero(sc.row_station == st.id)
            if st.kind == "xyz":
                d = np.empty((k, len(idx)))
                registered_distances(np.ascontiguousarray(P0[idx]), np.ascontiguousarray(meas[:, idx]), d)
                before.append(d)
            elif not xyz_rows.any():
                rows = []
                for i in range(k):
                    S, o = multilaterate(P0[idx], ranges[i, idx])
                    rows.append(np.abs(ranges[i, idx] - np.sqrt(((P0[idx] - S) ** 2).sum(-1)) - o))
                before.append(np.array(rows))
        before = np.concatenate(before, axis=1)
        self.mean_error_before = before.mean(axis=1)


def _station_basis(sc: Scenario, model, fixed, hold) -> tuple:
    """The directions the identification of several stations iterates along, from the noise-free verification of
    the scenario: one basis for every trial, so a trial's result does not depend on which trials are identified
    with it (chunking, executors, resume), bit for bit.  Cached per model in the scenario."""
    from .multistation import chord_basis, identify_stations_batch
    from .simulate import measure_stations

    def make():
        truth = sc.truth_inputs({})
        xyz, ranges = measure_stations(sc, sc.truth.machine_points(sc.theta[None, :], truth), truth)
        b = identify_stations_batch(model, sc.stations, sc.row_station, xyz, ranges, sc.noise.repeatability,
                                    fixed=fixed, hold=hold, max_iter=1)
        # with the chord's shared iteration matrix from the same Jacobian (used when nothing is fixed: [scales]);
        # the model is kept beside its basis (its id)
        return model, chord_basis(b, model, sc.stations, sc.row_station, hold=hold, fixed=fixed)

    return sc.cached(("station basis", id(model)), make)[1]
