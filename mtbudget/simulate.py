"""Simulate a verification: the same model the identification and diagnosis use, run forward.

:func:`simulate` turns a :class:`~mtbudget.config.SimulationConfig` into a
:class:`~mtbudget.recording.Recording` (and the ``truth.json`` of what it put
in, in the convention of the bundled examples).
"""

from __future__ import annotations

import numpy as np

from .config import SimulationConfig
from .machine import AXES, COMPONENT_ERRORS, ErrorModel
from .model import MeasurementModel, drift_offset, merge, reversal_offset, thermal_scale
from .recording import Recording


def truth_model(cfg: SimulationConfig, plan) -> MeasurementModel:
    """Error model used to *simulate*: free straightness convention (P1 terms allowed)."""
    return MeasurementModel.for_plan(cfg.machine, plan, max_degree=cfg.max_degree, straightness_convention="free")


def machine_parameters(cfg: SimulationConfig, model: MeasurementModel) -> np.ndarray:
    """The simulated machine's geometric parameters: explicit, or drawn from the generation functions."""
    g = cfg.geometric
    if "coefficients" in g:
        return model.errors.from_coefficients(g["coefficients"], g.get("squareness", {}))
    rng = np.random.default_rng(g.get("seed", 1))
    theta = np.zeros(model.n_params)
    for j, p in enumerate(model.errors.params):
        if p.is_squareness:
            theta[j] = rng.normal(0.0, g["squareness"])
        else:
            stds = g["translational"] if p.unit == "mm" else g["angular"]
            theta[j] = rng.normal(0.0, stds[min(p.order, len(stds)) - 1])
    return theta


def effect_perturbations(plan, effects: dict, reference: float) -> dict:
    """Perturbations of the physics effects of a config or truth (thermal, reversal, drift)."""
    parts = [thermal_scale(plan, effects.get("thermal", {}), reference),
             reversal_offset(plan, effects.get("reversal", {}))]
    if effects.get("drift") is not None:
        parts.append(drift_offset(plan, effects["drift"]))
    return merge(*parts)


def noise_perturbations(model: MeasurementModel, P_LT: np.ndarray, rng, angular, distance, dpl, repeatability) -> dict:
    """One draw of tracker (spherical) noise and machine repeatability for N trials."""
    N, M = P_LT.shape[:2]
    r = np.linalg.norm(P_LT, axis=-1)
    sph = np.empty((N, M, 3))
    sph[..., 0] = rng.standard_normal((N, M)) * (distance + dpl * r)
    sph[..., 1:] = rng.standard_normal((N, M, 2)) * angular
    out = {"spherical_noise": sph}
    for a in AXES:
        out[f"axis_offset.{a}"] = rng.standard_normal((N, M)) * repeatability
    return out


def simulate(cfg: SimulationConfig, seed: int | None = None) -> tuple[Recording, dict]:
    """Simulate one verification of ``cfg`` (noise seeded by ``seed`` or ``cfg.seed``)."""
    seed = cfg.seed if seed is None else seed
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    plan = cfg.plan(rng)
    model = truth_model(cfg, plan)
    theta = machine_parameters(cfg, model)
    physics = effect_perturbations(plan, cfg.effects, cfg.reference_temperature)
    clean = model.predict(theta, cfg.pose, physics)
    noise = noise_perturbations(model, clean, rng, cfg.angular, cfg.distance, cfg.distance_per_length, cfg.repeatability)
    measured = model.predict(theta, cfg.pose, merge(physics, noise))[0]
    rec = Recording(
        name=cfg.name, machine=cfg.machine, plan=plan, lt=measured, angular=cfg.angular, distance=cfg.distance,
        distance_per_length=cfg.distance_per_length, repeatability=cfg.repeatability,
        reference_temperature=cfg.reference_temperature, description=cfg.description or f"simulated by mtbudget (seed {seed})",
    )
    return rec, truth_dict(cfg, model, theta)


def truth_dict(cfg: SimulationConfig, model: MeasurementModel, theta: np.ndarray) -> dict:
    coefs, sq = model.errors.coefficients(theta)
    drift = cfg.effects.get("drift")
    return {
        "conventions": {
            "thermal": "axis -> CTE in um/(m K): the axis scale reads the nominal position p but moves to p * (1 + CTE * (T_axis - 20 degC)), about the axis zero",
            "reversal": "axis -> full reversal value B in um: approaching from either side the axis stops B/2 short of the target",
            "drift": "apparent velocity of the measured points in the machine frame, um/h, from the start of the test",
            "tracker_pose": "D, L, H in mm and Euler angles a, b, d in rad of the tracker frame in the machine frame (the paper's Eq. 21-22)",
        },
        "effects": {
            "thermal": {a: v * 1e6 for a, v in cfg.effects.get("thermal", {}).items()},
            "reversal": {a: v * 1e3 for a, v in cfg.effects.get("reversal", {}).items()},
            "drift": None if drift is None else [float(v) * 1e3 * 3600 for v in drift],
        },
        "tracker_pose": dict(zip("DLHabd", map(float, cfg.pose))),
        "noise": {"angular_urad": cfg.angular * 1e6, "dist_um": cfg.distance * 1e3,
                  "dist_ppm": cfg.distance_per_length * 1e6, "repeat_um": cfg.repeatability * 1e3},
        "squareness_urad": {k: v * 1e6 for k, v in sq.items()},
        "geometric_errors": {
            "basis": "Legendre P1..Pn of the axis position normalised to [-1, 1] over the measured range; um for d*, urad for e*",
            "coefficients": {k: [c * (1e3 if k[0] == "d" else 1e6) for c in v] for k, v in coefs.items() if k in COMPONENT_ERRORS},
        },
    }


def parameters_from_truth(truth: dict, model: MeasurementModel) -> tuple[np.ndarray, np.ndarray, dict]:
    """(theta, pose, effects) in internal units from a ``truth.json`` dictionary."""
    co = {k: [v * (1e-3 if k[0] == "d" else 1e-6) for v in vs] for k, vs in truth["geometric_errors"]["coefficients"].items()}
    theta = model.errors.from_coefficients(co, {k: v * 1e-6 for k, v in truth.get("squareness_urad", {}).items()})
    tp = truth["tracker_pose"]
    pose = np.array([tp[k] for k in "DLHabd"], float)
    e = truth.get("effects", {})
    effects = {
        "thermal": {a: v * 1e-6 for a, v in (e.get("thermal") or {}).items()},
        "reversal": {a: v * 1e-3 for a, v in (e.get("reversal") or {}).items()},
        "drift": None if not e.get("drift") else np.asarray(e["drift"], float) * 1e-3 / 3600.0,
    }
    return theta, pose, effects


def truth_error_model(plan, degrees_from: dict) -> ErrorModel:
    """An error model able to hold a truth.json (free convention, its degrees)."""
    base = ErrorModel.default(plan.nominal, straightness_convention="free")
    deg = {k: len(v) for k, v in degrees_from.items()}
    return ErrorModel(ranges=base.ranges, degrees={**{k: 0 for k in base.degrees}, **deg}, straightness_convention="free")
