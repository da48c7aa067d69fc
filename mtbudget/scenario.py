"""One scenario, built once from a configuration: what is verified, how, and what may vary.

A :class:`Scenario` holds everything a simulated verification needs and that
does not change from trial to trial: the plan (mesh, passes, timing, sensor
readings), the truth model and the simulated machine's geometric parameters,
the tracker pose, the mesh rows where the compensated machine is evaluated,
the identification weights the verification states, and the configured
uncertainty sources.  The engine, both studies, ``mtbudget simulate``,
``replay --verify`` and the diagnosis calibration all take a scenario.

**One key per physical input.**  A physical input (the tracker's angular and
range noise, the machine's repeatability, the scales' expansion coefficient)
is stated once in the configuration (:data:`mtbudget.config.PHYSICAL_INPUTS`).
Sources draw it through their ``links``; the identification weights follow
it.  A source table may state a linked parameter instead of the
configuration key; stating both with different values is an error.  To see
what misstated weights cost, a ``[weights]`` table states the weights
explicitly, and every output shows both.  The scales' expansion coefficient is per axis:
``[scales.<axis>] cte`` for an axis whose nominal expansion is simulated and corrected, ``[machine_tool] cte`` for
the axes without such a table (stating it beside all three is an error).

**Thermal correction** ([scales]): the simulated machine's stated scales expand about their fixed points at the
true axis temperatures (:meth:`Scenario.truth_inputs`), the verification corrects them with the stated scales at
the read temperatures (:attr:`Scenario.correction`, a fixed input of the identification).
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field

import numpy as np

from .config import PHYSICAL_INPUTS, WEIGHT_KEYS, SimulationConfig, given_with_set
from .contracts import Context, TARGETS
from .errors import ConfigError, PluginError
from .identify import Noise, null_coordinates
from .machine import AXIS_INDEX, ROTARY_INDEX, is_rotary, kernel_chain, kernel_points, kernel_rows
from . import tracker as lt
from .model import MeasurementModel
from .plan import Plan
from .plugins import PluginHost, call, default_host
from .recording import UNCERTAINTIES, cte_problem, uncertainty_problem
from .units import Q_, to_internal

#: keys of the [sources] table that are not source names
SOURCE_TABLE_KEYS = ("enable", "disable", "add")

#: the shortest distance a station may stand from a measured point (mm): closer, no tracker or interferometer measures
MIN_STATION_DISTANCE = 100.0

#: sources that were retired, with where their physics lives now: a [sources] disable list may still name them (it
#: asks for nothing); enable, add or a [sources.NAME] table is an error that says where to go
RETIRED_SOURCES = {"multilateration": "multilateration is simulated from the stations themselves since issue 20 (the "
                                      "linearised surrogate source is retired): state [[stations]] with kind = \"range\" "
                                      "(docs/configuration.md, docs/user-guide.md \"Several stations\")"}

#: the [effects] shorthand: effect table -> (source, parameter of each axis)
EFFECT_SOURCES = {"thermal": ("thermal_expansion", "cte_{}", "1/K"), "reversal": ("reversal", "B_{}", "mm"),
                  "drift": ("tracker_drift", "v_{}", "mm/s")}


@dataclass
class Scenario:
    config: SimulationConfig
    plan: Plan
    truth: MeasurementModel  # the model that simulates (free straightness convention)
    theta: np.ndarray  # (p,) the simulated machine's geometric parameters
    pose: np.ndarray  # (6,) tracker pose D, L, H (mm), a, b, d (rad)
    noise: Noise  # the identification weights the verification states
    drawn: dict  # physical input key -> internal value the run draws
    sources: list  # the configured, enabled sources
    context: Context
    mesh_rows: np.ndarray  # plan rows of the mesh (first run, first tool)
    mesh_points: np.ndarray  # (M0, 3) nominal tool points of those rows, machine frame (mm)
    rigid_free: "RigidFree"  # (3 M0, 3 M0) projector that removes what the tracker pose absorbs (rank-6 form)
    measurand_tool: np.ndarray | None = None  # (3,) mm: [measurand] tool, when not the verification's first tool
    #: [[stations]]: the stations as the identification knows them (:class:`mtbudget.recording.Station`, ids 1..K,
    #: the stated uncertainties), their true places (config.StationSpec) and the station of every plan row; None for
    #: the single tracker of [tracker]
    stations: list | None = None
    station_specs: list | None = None
    row_station: np.ndarray | None = None
    null_bias: np.ndarray | None = None  # (M0, 3) mm: the truth's own unidentifiable part there (replaced by its prior)
    #: [scales]: what the verification takes as known, the nominal expansion of the stated scales at the READ axis
    #: temperatures (``identify(..., fixed=...)``, (1, M) arrays, as ``Recording.fixed_inputs()``); empty without
    correction: dict = field(default_factory=dict)
    _id_models: dict = field(default_factory=dict, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)  # models at the measurand's tool, identifiability, prior

    @property
    def max_degree(self) -> int:
        return self.config.max_degree

    def truth_inputs(self, pert: dict) -> dict:
        """The simulated machine's model inputs: ``pert`` (the sources' perturbations, summed per input) with the
        stated scales' expansion ([scales]).  For an axis with a stated scale the true relative expansion is the
        nominal one at the read temperatures plus what the sources draw on ``axis_scale`` (the deviations: sensor
        calibration and drift times the CTE, the CTE's own uncertainty times the temperature difference), and all of
        it acts about the scale's fixed point: ``axis_offset`` gets ``-fixed_point s / (1 + s)`` of the total s, so
        the effective position is ``fixed_point + (p - fixed_point)(1 + s)`` exactly.  Without [scales]: ``pert``."""
        scales = self.plan.scales
        if not scales:
            return pert
        nominal = self._cache.get("nominal_scale")
        if nominal is None:
            nominal = self._cache["nominal_scale"] = {
                a: self.plan.expansion({a: sc}, self.config.reference_temperature)[f"axis_scale.{a}"]
                for a, sc in scales.items()}
        out = dict(pert)
        for a, sc in scales.items():
            s = np.atleast_2d(nominal[a] + out.get(f"axis_scale.{a}", 0.0))
            out[f"axis_scale.{a}"] = s
            if sc.fixed_point:
                out[f"axis_offset.{a}"] = out.get(f"axis_offset.{a}", 0.0) - sc.fixed_point * s / (1.0 + s)
        return out

    def identification_model(self, max_degree: int | None = None) -> MeasurementModel:
        """The model the verification identifies with (ISO 230-1 convention), cached per degree."""
        d = self.config.max_degree if max_degree is None else int(max_degree)
        if d not in self._id_models:
            self._id_models[d] = MeasurementModel.for_plan(self.config.machine, self.plan, max_degree=d,
                                                           **_rotary_kw(self.config))
        return self._id_models[d]

    @property
    def commanded(self) -> np.ndarray:
        """(M0, 3) commanded axis positions x, y, z of the mesh points (mm)."""
        return self.plan.nominal[self.mesh_rows]

    @property
    def commanded_angles(self) -> dict:
        """Five-axis: {letter: (M0,) commanded angle of each rotary axis at the mesh points (deg)}; empty otherwise."""
        return {r: np.degrees(v[self.mesh_rows]) for r, v in sorted(self.plan.angles.items())}

    @property
    def tool(self) -> np.ndarray:
        """(3,) the tool offset at which the compensated machine is evaluated, mm: [measurand] tool, else the
        verification's first tool."""
        return self.plan.tool[self.mesh_rows[0]] if self.measurand_tool is None else self.measurand_tool

    def evaluate(self, model: MeasurementModel, theta, jacobian: bool = False, points=None):
        """Tool points of ``model`` with parameters ``theta`` at the mesh points and the measurand's tool: (N, M0, 3)
        (and the Jacobian (N, M0, 3, p)).  At the verification's own tool these are the plan's mesh rows; at
        another tool the same error functions evaluated there (the verification's ranges and basis).  points:
        ``model.machine_points(theta)`` when already computed (an identification's ``points``), used at the
        verification's own tool."""
        if self.measurand_tool is None:
            # np.take: the same copy as indexing with mesh_rows, 4x faster on (trials, points, 3) arrays (issue 31)
            if points is not None and not jacobian:
                return np.take(points, self.mesh_rows, axis=1)
            if not jacobian:  # the chain at the mesh rows alone (issue 31): the same bits as its points there
                return kernel_points(self._mesh_chain(model), np.atleast_2d(np.asarray(theta, float)))
            out = model.machine_points(theta, jacobian=jacobian)
            if jacobian:
                return np.take(out[0], self.mesh_rows, axis=1), np.take(out[1], self.mesh_rows, axis=1)
            return np.take(out, self.mesh_rows, axis=1)
        key = ("at tool", id(model))
        if key not in self._cache:  # the model is kept beside its copy so that its id is not reused
            self._cache[key] = (model, MeasurementModel(model.config, model.errors,
                                                        _tool_plan(self.commanded, self.measurand_tool, self.plan,
                                                                   self.mesh_rows)))
        return self._cache[key][1].machine_points(theta, jacobian=jacobian)

    def _mesh_chain(self, model: MeasurementModel) -> dict:
        """The compiled chain's inputs of ``model`` (no perturbations) at the mesh rows only
        (:func:`mtbudget.machine.kernel_rows`), built once per model, basis and plan (kept beside them, so that
        their ids are not reused)."""
        key = ("mesh chain", id(model), id(model.B), id(model.errors.params), id(model.plan))
        if key not in self._cache:
            k = kernel_chain(model.config, model.errors, model.inputs, model.B, 1)
            self._cache[key] = ((model, model.B, model.errors.params, model.plan), kernel_rows(k, self.mesh_rows))
        return self._cache[key][1]

    def identifiability(self):
        """What the verification can identify (:func:`mtbudget.identify.analyse` of ``id_model``), computed once."""
        if "identifiability" not in self._cache:
            from .identify import analyse, datum_parameters

            ident = analyse(self.id_model)
            if self.id_model.rotary:  # the datum the identification applies (identify._phase)
                ident.held = datum_parameters(self.id_model, ident.null_space)
            self._cache["identifiability"] = ident
        return self._cache["identifiability"]

    def cached(self, key, make):
        """``make()`` computed once per scenario and ``key`` (a key that holds an object's id must keep the object
        alive in the value, so that the id is not reused)."""
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def unidentifiable(self, model: MeasurementModel) -> np.ndarray:
        """(p, k) orthonormal directions (scaled parameters: um, urad) of ``model`` that this plan cannot identify from
        one tracker (:func:`mtbudget.identify.analyse`: what the tracker pose absorbs, what no tool offset shows).
        Several stations cannot identify them either (they move the points rigidly, or not at all); the
        identification over several stations holds them at zero (``identify_stations(..., hold=)``), as the one-
        tracker identification does, so that at another tool they are covered by the prior
        (``unidentified_at_tool``) rather than by a datum convention."""
        from .identify import analyse

        key = ("null", id(model))
        if key not in self._cache:  # the model is kept beside its null space so that its id is not reused
            Nz = analyse(model).null_space if model is not self.id_model else self.identifiability().null_space
            self._cache[key] = (model, Nz)
        return self._cache[key][1]

    def unidentified_prior(self):
        """At a tool the verification did not use: (N, L), the directions of the identification model's parameters
        (unscaled, (p_id, k)) that the verification cannot identify and the Cholesky factor of their prior covariance
        from the generation functions; ``id_model`` evaluated at ``N @ L @ z`` (z standard normal) is their part of the
        true field, drawn afresh in every trial.  None at the verification's tool or without a prior."""
        if self.measurand_tool is None or "coefficients" in self.config.geometric:
            return None
        if "prior" not in self._cache:
            from .identify import scale_vector

            model = self.id_model
            Nz = self.identifiability().null_space  # (p_id, k), scaled parameters (um, urad)
            if Nz.size == 0:
                self._cache["prior"] = None
                return None
            scale = scale_vector(model)
            sd = np.array([prior_std(self.config, p) for p in model.errors.params]) * scale
            held = self.identifiability().held
            if held is None:  # minimum norm: the coordinates are the orthogonal projection N^T theta
                C = Nz.T @ (sd[:, None] ** 2 * Nz)
            else:  # a datum: the coordinates are the held parameters' values mapped by N[held]^-1
                K = np.linalg.inv(Nz[held, :])
                C = K @ (sd[held, None] ** 2 * K.T)
            L = np.linalg.cholesky(C + 1e-12 * np.trace(C) * np.eye(len(C)))
            self._cache["prior"] = (Nz / scale[:, None], L)
        return self._cache["prior"]

    def unidentified_at_tool(self, threshold_um: float = 0.01) -> list:
        """The combinations of geometric errors this verification cannot identify that still move the compensated
        machine at the measurand's tool (rigid part removed): each with its ISO 230-1 names and its largest effect
        over the mesh per unit of the combination (1 um or 1 urad of each unit-weight direction).  The Monte Carlo
        covers them through the truth's prior (the generation functions); nothing in the verification corrects
        them.  Empty at the verification's own tool, where they do not show by definition."""
        from .identify import scale_vector
        from .model import iso_parameter
        from .units import factor

        model = self.id_model
        ident = self.identifiability()
        if ident.null_space.size == 0:
            return []
        _, J = self.evaluate(model, np.zeros((1, model.n_params)), jacobian=True)
        J = J[0].reshape(-1, model.n_params)
        scale = scale_vector(model)
        out = []
        for combo in ident.combinations():
            v = np.zeros(model.n_params)
            for n, w in combo:
                v[model.errors.names.index(n)] = w
            d = (self.rigid_free @ (J @ (v / scale))).reshape(-1, 3) * factor("mm", "um")
            big = float(np.abs(d).max())
            if big > threshold_um:
                iso = [iso_parameter(n) for n, _ in combo]
                about = {x[1] for x in iso if x[0] == "E" and x[1] in "ABC" and not x[2:3].isdigit()}
                axis = "xyz"["ABC".index(next(iter(about)))] if len(about) == 1 else None
                out.append({"combination": [{"parameter": n, "iso": i, "weight": w} for (n, w), i in zip(combo, iso)],
                            "largest_effect": {"value": big, "unit": "um per um or urad of the combination"},
                            "identified_by": (f"a tool offset across the {axis} direction (rotations about {axis} do "
                                              f"not move a tool on the {axis} axis)" if axis else
                                              "a second tool length or a lateral tool offset")})
        return out

    @property
    def one_tracker(self) -> tuple | None:
        """(noise, pose) of the one-tracker identification this verification states, or None when it is measured
        from several stations.  ``[tracker]``: its stated noise and pose.  A ``[[stations]]`` list of exactly one
        laser tracker (kind "xyz") states the same problem (the same unknowns, weights, datum and degrees of freedom;
        tests/test_stations_mc.py): the station's own stated noise (else ``[tracker]``'s or ``[weights]``'), the
        machine's repeatability and the station's pose.  Two or more stations, or any interferometer, are identified
        over all stations at once (:mod:`mtbudget.multistation`): None."""
        if not self.stations:
            return self.noise, self.pose
        if len(self.stations) > 1 or self.stations[0].kind != "xyz":
            return None
        st, spec = self.stations[0], self.station_specs[0]
        return (Noise(st.angular, st.distance, st.distance_per_length, self.noise.repeatability),
                np.asarray(spec.tracker_pose, float))

    @property
    def id_model(self) -> MeasurementModel:
        return self.identification_model()

    @property
    def weights_differ(self) -> bool:
        return self.config.weights is not None

    def weights_report(self) -> dict | None:
        """Stated weights beside what the run draws, when the configuration sets them apart ([weights])."""
        if not self.weights_differ:
            return None
        out = {}
        for name, key in WEIGHT_KEYS.items():
            unit = PHYSICAL_INPUTS[key][0]
            out[name] = {"stated": getattr(self.noise, name), "drawn": self.drawn[key], "unit": unit}
        return out


#: sources that need the truth one Legendre degree richer than the identification model (model-form error)
RICHER_TRUTH = ("model_form",)


def truth_model(config: SimulationConfig, plan: Plan, richer: bool = False) -> MeasurementModel:
    """Error model used to *simulate*: free straightness convention (P1 terms allowed); one degree above the
    identification's when a model-form source draws the terms the identification cannot represent."""
    return MeasurementModel.for_plan(config.machine, plan, max_degree=config.max_degree + int(richer),
                                     straightness_convention="free", **_rotary_kw(config))


def _rotary_kw(config: SimulationConfig) -> dict:
    """The error model's rotary options of a five-axis configuration (none for three axes: the same model as ever)."""
    return {"harmonics": config.rotary_harmonics} if config.rotary else {}


def machine_parameters(config: SimulationConfig, model: MeasurementModel) -> np.ndarray:
    """The simulated machine's geometric parameters: explicit, or drawn from the generation functions."""
    g = config.geometric
    if "coefficients" in g:
        return model.errors.from_coefficients(g["coefficients"], g.get("squareness", {}), g.get("rotary"))
    rng = np.random.default_rng(g.get("seed", 1))
    theta = np.zeros(model.n_params)
    for j, p in enumerate(model.errors.params):
        if p.order > config.max_degree and not is_rotary(p.error[3]):  # the model-form terms: drawn by their source
            continue
        theta[j] = rng.normal(0.0, prior_std(config, p))
    for name, value in (g.get("rotary") or {}).items():  # stated location and zero errors replace the draws
        theta[model.errors.index(name)] = value
    return theta


def prior_std(config: SimulationConfig, param) -> float | None:
    """The generation functions' standard deviation of one geometric parameter (mm or rad); None when the
    configuration states explicit coefficients (no prior)."""
    g = config.geometric
    if "coefficients" in g:
        return None
    if param.is_squareness:
        return g["squareness"]
    if is_rotary(param.error[3]):  # location, orientation and zero errors; a quarter of them per Fourier term
        if param.error[0] == "d":
            sd = g["rotary_location"]
        else:
            sd = g["rotary_zero"] if AXIS_INDEX[param.error[1]] == ROTARY_INDEX[param.error[3]] else g["rotary_orientation"]
        return sd if param.order == 0 else sd / 4.0
    stds = g["translational"] if param.unit == "mm" else g["angular"]
    return stds[min(param.order, len(stds)) - 1]


class RigidFree:
    """``I - Q Q^T``: removes from fields on M points (vectors of 3 M, x y z per point) what the tracker pose absorbs,
    their least-squares rigid motion.  Q (3 M, r <= 6) is an orthonormal basis of the rigid motions of the points, so
    the removal is a rank-6 correction, O(M) in time and memory (the dense 3M x 3M projector it replaces grew as M^2).
    Symmetric; used as a matrix: ``P @ X`` on (3 M,) or (3 M, k), ``X @ P`` and ``X @ P.T`` on (..., 3 M).
    ``np.asarray(P)`` is the dense matrix (tests and small meshes only)."""

    __array_ufunc__ = None  # numpy hands ``array @ P`` to __rmatmul__

    def __init__(self, Q: np.ndarray):
        self.Q = Q
        self.shape = (len(Q), len(Q))

    @property
    def T(self) -> "RigidFree":
        return self

    def __matmul__(self, X):
        X = np.asarray(X)
        return X - self.Q @ (self.Q.T @ X)

    def __rmatmul__(self, X):
        X = np.asarray(X)
        return X - (X @ self.Q) @ self.Q.T

    def __array__(self, dtype=None, copy=None):
        return np.asarray(np.eye(len(self.Q)) - self.Q @ self.Q.T, dtype=dtype)


def rigid_projector(P: np.ndarray) -> RigidFree:
    """I - projector onto rigid motions of points P (M, 3): removes what the tracker pose absorbs."""
    M = len(P)
    A = np.zeros((M, 3, 6))
    A[:, :, :3] = np.eye(3)
    c = P - P.mean(0)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1
        A[:, :, 3 + k] = np.cross(e, c)
    A = A.reshape(3 * M, 6)
    # the range of A, as pinv(A) sees it (singular values above its default cut-off: points on a line lose a rotation)
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return RigidFree(U[:, s > max(A.shape) * np.finfo(float).eps * s[0]])


def _effects_as_sources(config: SimulationConfig) -> dict:
    """The [effects] shorthand as source settings: {source name: {parameter: Quantity}}."""
    out: dict = {}
    for kind, (source, pattern, unit) in EFFECT_SOURCES.items():
        value = config.effects.get(kind)
        if value is None or (isinstance(value, dict) and not value):
            continue
        if isinstance(value, dict):
            out[source] = {pattern.format(a): Q_(v, unit) for a, v in value.items()}
        else:
            out[source] = {pattern.format(a): Q_(float(v), unit) for a, v in zip("xyz", value)}
    return out


def select_sources(config: SimulationConfig, host: PluginHost, names: list | None = None) -> list:
    """The enabled sources, configured from the [sources] table, [effects] and the physical inputs."""
    settings = config.source.get("sources", {}) if isinstance(config.source, dict) else {}
    if not isinstance(settings, dict):
        raise ConfigError(f"{config.where('sources')}: must be a table")
    available = {s.name: s for s in host.sources()}

    def check_name(n, where):
        if n in RETIRED_SOURCES and where != "sources.disable":
            raise ConfigError(f"{config.where(where)}: {RETIRED_SOURCES[n]}")
        if n not in available and not (n in RETIRED_SOURCES and where == "sources.disable"):
            close = difflib.get_close_matches(n, list(available) + list(RETIRED_SOURCES), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f"; available: {', '.join(sorted(available))}"
            raise ConfigError(f"{config.where(where)}: unknown source {n!r}{hint}")

    for key, value in settings.items():
        if key in SOURCE_TABLE_KEYS:
            if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
                raise ConfigError(f"{config.where('sources.' + key)}: expected a list of source names")
            for n in value:
                check_name(n, f"sources.{key}")
        elif isinstance(value, dict):
            check_name(key, f"sources.{key}")
        else:
            raise ConfigError(f"{config.where('sources.' + key)}: unknown key; [sources] takes enable, disable, add "
                              "and one table per source")
    effects = _effects_as_sources(config)
    for n, params in effects.items():
        if n in settings:
            raise ConfigError(f"{config.where('effects')}: the effect of source {n!r} is stated twice, in [effects] and "
                              f"in [sources.{n}]; keep one")
        check_name(n, "effects")
    enable = names if names is not None else settings.get("enable")
    disable = set(settings.get("disable", []))
    if names is not None:
        for n in names:
            check_name(n, "sources")
    five_axis = bool(getattr(config, "rotary", None))
    if not five_axis:  # a source of rotary axes only has nothing to act on in a three-axis machine
        for n in list(enable or []) + list(settings.get("add", [])):
            if n in available and _rotary_only(available[n]):
                raise ConfigError(f"{config.where('sources')}: source {n!r} acts on rotary axes (A, B, C), which "
                                  f"machine {config.machine!r} does not have")
    if enable is None:
        chosen = [n for n, s in available.items() if not s.opt_in and (five_axis or not _rotary_only(s))]
        chosen += [n for n in list(settings.get("add", [])) + list(effects) if n not in chosen]
    else:
        chosen = list(enable) + [n for n in effects if n not in enable]
    chosen = [n for n in chosen if n not in disable]
    for n, value in settings.items():
        if isinstance(value, dict) and n not in chosen and available[n].opt_in and n not in disable:
            raise ConfigError(f"{config.where('sources.' + n)}: source {n!r} is configured but not enabled (it is "
                              f"opt-in): add it to [sources] add = [\"{n}\"]")
    for n in chosen:
        for other in available[n].excludes:
            if other in chosen:
                raise ConfigError(f"{config.where('sources')}: sources {n!r} and {other!r} model the same thing in two "
                                  f"ways and cannot both be enabled; disable one")
    srcs = [available[n] for n in chosen]
    tables = {s.name: dict(effects.get(s.name) or settings.get(s.name, {})) for s in srcs}
    drawn = _resolve_links(config, srcs, tables)
    for s in srcs:
        try:
            s.configure(tables[s.name])
        except PluginError as exc:
            if getattr(exc, "parameter", None):  # an implausible value: the key that states it
                raise ConfigError(f"{config.where(f'sources.{s.name}.{exc.parameter}')}: {exc.problem}") from None
            raise ConfigError(f"{config.where('sources.' + s.name)}: {exc.reason}") from None
        problem = call(s, "check")
        if problem:
            raise ConfigError(f"{config.where('sources.' + s.name)}: {problem}")
    return srcs, drawn


#: the model inputs of rotary axes only (a source that targets nothing else applies to five-axis machines only)
ROTARY_INPUTS = frozenset({"axis_offset.a", "axis_offset.b", "axis_offset.c"})


def _rotary_only(src) -> bool:
    return bool(src.targets) and set(src.targets) <= ROTARY_INPUTS


def _resolve_links(config: SimulationConfig, sources: list, tables: dict) -> dict:
    """One value per physical input: from the configuration key or from one source table, never two that differ.

    Fills the linked parameters of every source table and returns the value drawn for each physical input.
    """
    drawn = {key: getattr(config, attr) for key, (_, attr, _) in PHYSICAL_INPUTS.items()}
    stated_by: dict = {key: key for key in PHYSICAL_INPUTS if config.stated(key)}  # input -> the key that states it
    for s in sources:
        for param, key in s.links.items():
            if key not in PHYSICAL_INPUTS:
                raise PluginError(f"links parameter {param!r} to {key!r}, which is not a physical input "
                                  f"({', '.join(PHYSICAL_INPUTS)})", s.plugin or None, s.name)
            if param not in tables[s.name]:
                continue
            unit = PHYSICAL_INPUTS[key][0]
            here = f"sources.{s.name}.{param}"
            where = config.where(here)
            value = to_internal(tables[s.name][param], unit, where=where, error=ConfigError)
            problem = uncertainty_problem(key, value) if key in UNCERTAINTIES else cte_problem(value)  # machine_tool.cte
            if problem:  # the rule of the key it states ([tracker], [machine_tool]), whichever key states it
                raise ConfigError(f"{where}: {problem}")
            if key in stated_by and not np.isclose(value, drawn[key], rtol=1e-12, atol=0.0):
                raise ConfigError(_stated_twice(config, key, (here, value, _unit_of(s, param) or unit),
                                                (stated_by[key], drawn[key], _unit_of(s, param) or unit)))
            drawn[key], stated_by[key] = value, here
    scales = getattr(config, "scales", None) or {}
    if "machine_tool.cte" in stated_by and len(scales) == 3:
        raise ConfigError(f"{config.where(stated_by['machine_tool.cte'])}: the scales' expansion coefficient is stated "
                          "twice, here and "
                          "in [scales.x], [scales.y] and [scales.z]; [machine_tool] cte (and a thermal source's cte) is "
                          "the CTE of the axes without a [scales.<axis>] table: remove it")
    for s in sources:
        for param, key in s.links.items():
            q = Q_(drawn[key], PHYSICAL_INPUTS[key][0])
            unit = _unit_of(s, param)
            tables[s.name].setdefault(param, q.to(unit) if unit else q)
    return drawn


def _stated_twice(config: SimulationConfig, key: str, second: tuple, first: tuple) -> str:
    """The one line for a physical input stated twice with different values: it names the statement nearest the
    user (--set, then the configuration's own file, then the files it extends; the later one where both are as
    near), and says where the other is.  ``second``, ``first``: (dotted key, value in internal units, unit shown)."""
    if config.origin_rank(first[0]) < config.origin_rank(second[0]):
        second, first = first, second
    unit = PHYSICAL_INPUTS[key][0]
    base = config.origin_rank(first[0]) >= 2  # the other statement is in a file this one extends
    shown = [f"{Q_(v, unit).to(u) if u else Q_(v, unit):~P}" for _, v, u in (second, first)]
    fix = (f"change it there too (or state it only there: {first[0]})" if base else "state it once")
    return (f"{config.where(second[0])}: states the physical input {key} a second time with another value ({shown[0]}; "
            f"already {shown[1]} at {config.where(first[0])}{', a file this configuration extends' if base else ''}); "
            f"{fix}, or put the identification weights apart in a [weights] table")


def _unit_of(src, param):
    v = type(src).parameters.get(param)
    return v.units if hasattr(v, "units") else ""


def build_scenario(config: SimulationConfig, host: PluginHost | None = None, sources: list | None = None) -> Scenario:
    """Build the scenario of ``config`` (plan, truth, pose, weights, configured sources)."""
    host = host or default_host()
    try:
        srcs, drawn = select_sources(config, host, sources)
    except ConfigError as exc:  # a key given with --set says so, as parse errors do
        raise given_with_set(exc, getattr(config, "provenance", None)) from None
    rng = np.random.default_rng(np.random.SeedSequence(config.seed))  # the plan and sensor readings of the study
    plan = config.plan(rng)
    truth = truth_model(config, plan, richer=any(s.name in RICHER_TRUTH for s in srcs))
    theta = machine_parameters(config, truth)
    pose = np.asarray(config.pose, float)
    stated = {name: drawn[key] for name, key in WEIGHT_KEYS.items()}
    if config.weights is not None:
        stated.update(config.weights)
    noise = Noise(**stated)
    stations = specs = row_station = None
    if config.stations:
        stations, specs, row_station = _stations(config, plan, noise)
        P0 = truth.machine_points(np.zeros(truth.n_params))[0]
        nominal = np.empty_like(P0)
        row_noise = {name: np.empty(len(plan)) for name in ("angular", "distance", "distance_per_length")}
        for st, spec in zip(stations, specs):
            rows = row_station == st.id
            nominal[rows] = lt.to_tracker(P0[rows][None], spec.tracker_pose)[0]
            for name, arr in row_noise.items():  # what the run draws: the station's own, else the tracker's
                v = getattr(spec, name)
                arr[rows] = drawn[f"tracker.{name}"] if v is None else v
        row_noise = {k: _read_only(v) for k, v in row_noise.items()}
    else:
        nominal = truth.predict(np.zeros(truth.n_params), pose)[0]
        row_noise = None
    context = Context(plan, truth, _read_only(nominal), _read_only(theta), config.reference_temperature, config,
                      row_noise=row_noise)
    first = (plan.run == plan.run.min()) & np.all(plan.tool == plan.tool[0], axis=1)
    mesh_rows = np.flatnonzero(first)
    mesh_points = truth.machine_points(np.zeros(truth.n_params))[0][mesh_rows]
    tool = None
    if config.measurand_tool is not None and not np.allclose(config.measurand_tool, plan.tool[mesh_rows[0]]):
        tool = np.asarray(config.measurand_tool, float)
        at_tool = MeasurementModel(truth.config, truth.errors, _tool_plan(plan.nominal[mesh_rows], tool, plan, mesh_rows))
        mesh_points = at_tool.machine_points(np.zeros(truth.n_params))[0]
    correction = {k: _read_only(v[None, :]) for k, v in plan.nominal_expansion(config.reference_temperature).items()}
    sc = Scenario(config, plan, truth, theta, pose, noise, drawn, srcs, context, mesh_rows, mesh_points,
                  rigid_projector(mesh_points), tool, stations, specs, row_station, correction=correction)
    if tool is not None:
        _unidentified_source(sc, host)
    return sc


def _stations(config: SimulationConfig, plan: Plan, noise: Noise):
    """[[stations]] as the identification states them (ids 1..K, the stated uncertainties of the weights), their
    true places, and the station of every plan row (station k measures runs (k-1)*runs+1 .. k*runs)."""
    from .recording import Station

    def own(spec, name):  # a station's own stated uncertainty, else the verification's ([tracker] or [weights])
        v = getattr(spec, name)
        return getattr(noise, name) if v is None else v

    stations = [Station(k + 1, spec.kind, own(spec, "angular") if spec.kind == "xyz" else None, own(spec, "distance"),
                        own(spec, "distance_per_length"), spec.description) for k, spec in enumerate(config.stations)]
    P = plan.nominal + plan.tool  # the nominal tool points (an error-free XFYZ machine) the stations measure
    if plan.angles:  # a five-axis plan: the nominal tool points in the table frame, turned by the rotary axes
        m = MeasurementModel.for_plan(config.machine, plan, max_degree=1)
        P = m.machine_points(np.zeros(m.n_params))[0]
    for k, spec in enumerate(config.stations):
        where = config.where(f"stations[{k}]." + ("D, L, H" if spec.kind == "xyz" else "position"))
        d = float(np.sqrt(((P - spec.tracker_pose[:3]) ** 2).sum(axis=1)).min())
        if not d >= MIN_STATION_DISTANCE:
            raise ConfigError(f"{where}: the station stands {d:.0f} mm from a measured point; no instrument measures "
                              f"closer than {MIN_STATION_DISTANCE:.0f} mm: put it outside the measured volume")
    row_station = (plan.run - 1) // config.runs + 1
    row_station = row_station.astype(np.int64)
    row_station.setflags(write=False)
    return stations, list(config.stations), row_station


def _unidentified_source(sc: Scenario, host: PluginHost):
    """At a tool the verification did not use: the field of each unit draw of what it cannot identify (prior of the
    generation functions) goes to the sources' context, the source ``unidentified_at_tool`` draws it (its own
    budget row), and the truth's own unidentifiable part at that tool is taken out (``null_bias``) so it is not
    counted twice, once as a bias and once as an uncertainty."""
    from .identify import scale_vector

    prior = sc.unidentified_prior()
    if prior is None:
        return
    N, L = prior  # (p_id, k) unscaled, (k, k)
    model = sc.id_model
    zero = sc.evaluate(model, np.zeros((1, model.n_params)))[0]
    per_unit = sc.evaluate(model, (N @ L).T) - zero[None]  # (k, M0, 3): first order in the parameters
    field = np.zeros((L.shape[0], len(sc.plan), 3))
    field[:, sc.mesh_rows] = per_unit
    sc.context.measurand = {"unidentified_field": _read_only(field)}
    scale = scale_vector(model)
    names = sc.truth.errors.names
    theta_id = np.array([sc.theta[names.index(n)] if n in names else 0.0 for n in model.errors.names])
    c = null_coordinates(sc.identifiability(), theta_id * scale)
    sc.null_bias = sc.evaluate(model, (N @ c)[None])[0] - zero
    settings = sc.config.source.get("sources", {}) if isinstance(sc.config.source, dict) else {}
    if "unidentified_at_tool" not in settings.get("disable", []) and all(s.name != "unidentified_at_tool"
                                                                          for s in sc.sources):
        available = {s.name: s for s in host.sources()}
        if "unidentified_at_tool" in available:
            sc.sources = list(sc.sources) + [available["unidentified_at_tool"]]


def _tool_plan(commanded: np.ndarray, tool: np.ndarray, like: Plan | None = None, rows=None) -> Plan:
    """A plan of the mesh points at one tool offset: where the compensated machine is evaluated (a five-axis plan
    keeps the mesh rows' angles and rotary geometry, from ``like`` at ``rows``)."""
    M0 = len(commanded)
    extra = {}
    if like is not None and like.angles:
        extra = {"angles": {k: v[rows] for k, v in like.angles.items()}, "rotary": dict(like.rotary)}
    return Plan(np.arange(M0), np.ones(M0, int), np.zeros(M0), np.asarray(commanded, float), np.ones((M0, 3)),
                np.tile(np.asarray(tool, float), (M0, 1)), **extra)


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def target_shapes(scenario: Scenario) -> dict:
    """Shape after the trial axis of every source target in this scenario."""
    M, p = len(scenario.plan), scenario.truth.n_params
    return {k: tuple(M if s == "M" else p if s == "p" else s for s in shape) for k, (_, shape) in TARGETS.items()}

