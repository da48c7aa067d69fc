"""The a posteriori statement of a recording: the uncertainty of the compensated machine that verification identified.

A run on a configuration (:mod:`mtbudget.runner`) is an a priori evaluation: a virtual experiment of a planned
verification on an assumed machine.  Here the verification was carried out: its recording is identified (the
recording's stated noise as weights), and a Monte Carlo around the identified errors says how well that
identification knows the compensated machine.  Each trial re-measures the identified machine at the recording's own
points and station with noise drawn from the recording's stated noise (paper Eq. 23 plus the repeatability; with
``noise="estimated"`` scaled by sqrt(chi2/dof) of the fit, said in the output), identifies it as the recording was
identified, and keeps the compensated error at the mesh points (the first tool's points of the first run, the
rigid-body part removed, as docs/measurand.md): e = Pi (F(theta_hat) - F(theta_r)).  The spread of e is the
a posteriori uncertainty; the identification covariance propagated linearly (Pi J cov_theta J^T Pi^T) is given
beside it as the check.  What the plan cannot identify is not in this statement (the unidentifiable combinations
keep their initial value in every identification): it is named.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ConfigError, IdentificationError
from .identify import FIT_ALPHA, Noise, fit_test, identify, implausible  # noqa: F401 (FIT_ALPHA: re-exported)
from .model import MeasurementModel
from .outputs import WORKPIECE_FRAME
from .recording import read_recording
from .scenario import rigid_projector
from .stats import percent, symmetric_interval

UM = 1000.0  # um per mm
@dataclass
class Posterior:
    """An a posteriori statement with its trials: ``data`` the JSON-able statement (:func:`posterior`), ``components``
    (trials, 3 M0) every trial's compensated error at the mesh points, x, y, z per point in the statement's frame (um),
    from which the per-point figures and the decision's per-trial figures come."""

    data: dict
    components: np.ndarray

    @property
    def coverage(self) -> float:
        return float(self.data["coverage"])

    @property
    def trials(self) -> int:
        return int(self.data["trials"])

    def points(self) -> list:
        return self.data["points"]

    def figure(self, name: str) -> np.ndarray | None:
        """A per-trial figure of the compensated machine over the mesh (um), as a run keeps them (mtbudget.outputs):
        ``largest_abs_component`` (and ``_x``, ``_y``, ``_z``: the largest |error component| over the mesh) and
        ``compensation_max`` (the largest 3-D error over the mesh); None for another name."""
        E = self.components.reshape(len(self.components), -1, 3)
        if name == "largest_abs_component":
            return np.abs(E).max(axis=(1, 2))
        if name.startswith("largest_abs_component_") and name[-1] in "xyz":
            return np.abs(E[:, :, "xyz".index(name[-1])]).max(axis=1)
        if name == "compensation_max":
            return np.linalg.norm(E, axis=2).max(axis=1)
        return None


def posterior(folder, trials: int = 2000, seed: int = 1, coverage: float = 0.95, noise: str = "stated",
              max_degree: int = 3, block: int = 256) -> dict:
    """The a posteriori statement of the recording in ``folder`` (see the module docstring), as a JSON-able dict."""
    return posterior_result(folder, trials, seed, coverage, noise, max_degree, block).data


def posterior_result(folder, trials: int = 2000, seed: int = 1, coverage: float = 0.95, noise: str = "stated",
                     max_degree: int = 3, block: int = 256) -> Posterior:
    """The a posteriori statement of the recording in ``folder`` with its trials (:class:`Posterior`)."""
    if noise not in ("stated", "estimated"):
        raise ConfigError(f"noise must be 'stated' or 'estimated', got {noise!r}", key="--noise")
    if trials < 2:
        raise ConfigError(f"must be >= 2, got {trials}", key="--trials")
    folder = Path(folder)
    rec = read_recording(folder, several_stations=True)
    if rec.several_stations:
        raise ConfigError(f"{folder}: a recording of several stations has no a posteriori statement yet "
                          "(one xyz station only)")
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=max_degree)
    stated = Noise.of(rec)
    fixed = rec.fixed_inputs()
    res = identify(model, rec.lt, stated, fixed=fixed)
    problems = implausible(res)
    if problems:  # a statement around a fit that is not one of the machine would be a number about a mistake
        raise IdentificationError(f"{folder}: not an identification of the machine, no a posteriori statement is made: "
                                  f"{problems[0]}; check the recording's units (the column headers of points.csv), its "
                                  "stated noise ([tracker], [machine_tool]) and the machine code")
    theta, pose = res.theta[0], res.pose[0]
    chi2 = float(res.chi2_per_dof[0])
    scale = math.sqrt(chi2) if noise == "estimated" else 1.0
    y_hat = model.predict(theta[None], pose, fixed)[0]  # (M, 3) the identified machine, measured without noise
    C = model.covariance(y_hat, stated.angular * scale, stated.distance * scale, stated.distance_per_length * scale,
                         stated.repeatability * scale)
    L = np.linalg.cholesky(C)  # (M, 3, 3)
    plan = rec.plan
    rows = np.flatnonzero((plan.run == plan.run.min()) & np.all(plan.tool == plan.tool[0], axis=1))
    F_hat = model.machine_points(theta[None], fixed)[0][rows]
    Pi = rigid_projector(F_hat)  # the rigid motions the tracker pose absorbs, removed (scenario: rank 6)
    M0 = len(rows)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    E = np.empty((trials, 3 * M0))
    not_converged = 0
    for s in range(0, trials, block):
        n = min(block, trials - s)
        z = rng.standard_normal((n, len(y_hat), 3))
        y = y_hat[None] + np.einsum("mij,nmj->nmi", L, z)
        r = identify(model, y, stated, fixed=fixed)
        not_converged += int((~r.converged).sum())
        F_r = model.machine_points(r.theta, fixed)[:, rows]
        E[s:s + n] = (F_hat[None] - F_r).reshape(n, -1) @ Pi.T * UM
    mean, u = E.mean(axis=0), E.std(axis=0, ddof=1)
    Es = np.sort(E, axis=0)
    ends = np.array([symmetric_interval(Es[:, j], coverage) for j in range(Es.shape[1])])
    # the check: the identification covariance propagated linearly to the same measurand
    _, J = model.machine_points(theta[None], fixed, jacobian=True)
    Jf = Pi @ J[0][rows].reshape(3 * M0, -1)
    cov = Jf @ (res.cov_theta[0] * scale**2) @ Jf.T * UM**2
    u_lin = np.sqrt(np.maximum(np.diagonal(cov), 0.0))
    ok = u_lin > 1e-9 * max(u_lin.max(), 1e-30)
    ratio = u[ok] / u_lin[ok]
    # five-axis: each point's commanded angles, and with a rotary table the frame of its components and the same errors
    # in the machine's X, Y, Z at its pose (every trial's components turned: mean, u and interval alike)
    angles = {r: np.degrees(v[rows]) for r, v in sorted(plan.angles.items())}
    from .machine import workpiece_rotation

    R = workpiece_rotation(model.config, {r: v[rows] for r, v in plan.angles.items()}) if plan.angles else None
    if R is not None:
        Em = np.einsum("mij,nmj->nmi", R, E.reshape(trials, M0, 3)).reshape(trials, -1)
        mean_m, u_m = Em.mean(axis=0), Em.std(axis=0, ddof=1)
        Ems = np.sort(Em, axis=0)
        ends_m = np.array([symmetric_interval(Ems[:, j], coverage) for j in range(Ems.shape[1])])
    digest = hashlib.sha256((folder / "points.csv").read_bytes()).hexdigest()[:16] if (folder / "points.csv").exists() else None
    combos = res.identifiability.combinations()
    points = [{"point": i, "nominal": {"value": plan.nominal[rows[i]].tolist(), "unit": "mm"},
               **({"angles": {"value": {r: float(v[i]) for r, v in angles.items()}, "unit": "deg"}} if angles else {}),
               **({"frame": WORKPIECE_FRAME,
                   "machine_frame": {"what": "the same errors in the machine's X, Y, Z at this pose (every trial's "
                                             "components turned by the table's nominal orientation there)",
                                     "mean": mean_m[3 * i:3 * i + 3].tolist(), "u": u_m[3 * i:3 * i + 3].tolist(),
                                     "interval": {"low": ends_m[3 * i:3 * i + 3, 0].tolist(),
                                                  "high": ends_m[3 * i:3 * i + 3, 1].tolist(), "coverage": coverage,
                                                  "kind": "probabilistically symmetric"},
                                     "unit": "um", "rotation": R[i].tolist()}} if R is not None else {}),
               "mean": {"value": mean[3 * i:3 * i + 3].tolist(), "unit": "um"},
               "u": {"value": u[3 * i:3 * i + 3].tolist(), "unit": "um"},
               "u_linear": {"value": u_lin[3 * i:3 * i + 3].tolist(), "unit": "um"},
               "interval": {"low": ends[3 * i:3 * i + 3, 0].tolist(), "high": ends[3 * i:3 * i + 3, 1].tolist(),
                            "unit": "um", "coverage": coverage, "kind": "probabilistically symmetric"}}
              for i in range(M0)]
    data = {
        "statement_kind": {
            "kind": "a posteriori", "name": "uncertainty of the compensated machine this recorded verification identified",
            "what": ("Monte Carlo around the identified errors: each trial re-measures the identified machine at the "
                     "recording's points and station with the recording's " +
                     ("stated noise" if noise == "stated" else f"stated noise scaled by sqrt(chi2/dof) = {scale:.3f} "
                                                               "(the noise the fit estimated)") +
                     ", identifies it as the recording was identified and compensates it"),
            "recording": rec.name, "points_csv_sha256": digest},
        "machine": rec.machine,
        "report": rec.report,
        "measurand": ("error of the compensated machine at each mesh point (the recording's first tool, first run), " +
                      ("per axis of the workpiece (table) frame (x, y, z: the machine's X, Y, Z with every rotary axis at "
                       "zero, turning with the table; the machine's X, Y, Z at each pose: machine_frame)" if R is not None
                       else "per machine axis") +
                      ", after compensating with the identified errors: true minus identified error field, "
                      "rigid-body part removed (docs/measurand.md); the combinations the plan cannot identify are not in "
                      "it"),
        "not_identifiable": len(combos),
        "identification": {"chi2_per_dof": chi2, "dof": int(res.dof), "converged": bool(res.converged[0]),
                           "noise": noise, "noise_scale": scale, "thermal_correction": rec.thermal_correction,
                           "fit_test": fit_test(chi2, int(res.dof), noise, rec.name)},
        "trials": trials, "seed": seed, "coverage": coverage, "not_converged": not_converged,
        "points": points,
        "summary": {"unit": "um", "u_rms_over_mesh": np.sqrt((u.reshape(-1, 3) ** 2).mean(axis=0)).tolist(),
                    "u_max": u.reshape(-1, 3).max(axis=0).tolist(),
                    **({"frame": WORKPIECE_FRAME,
                        "machine_frame": {"u_rms_over_mesh": np.sqrt((u_m.reshape(-1, 3) ** 2).mean(axis=0)).tolist(),
                                          "u_max": u_m.reshape(-1, 3).max(axis=0).tolist()}} if R is not None else {}),
                    "u_over_u_linear": {"median": float(np.median(ratio)), "min": float(ratio.min()),
                                        "max": float(ratio.max()),
                                        "what": "Monte Carlo u over the identification covariance propagated linearly, "
                                                "per point-axis"}},
    }
    return Posterior(data, E)


def posterior_text(p: dict) -> str:
    """The a posteriori statement in a few lines."""
    k, s, i = p["statement_kind"], p["summary"], p["identification"]
    r = s["u_over_u_linear"]
    warn = (i.get("fit_test") or {}).get("warning")
    from .outputs import not_converged_line

    nc = [not_converged_line(p["not_converged"], p["trials"]) + "."] if p.get("not_converged") else []
    return "\n".join(nc + ([f"WARNING: {warn}."] if warn else []) + [
        f"Kind of statement: A POSTERIORI, the {k['name']} (recording {k['recording']}): {k['what']}.",
        f"Measurand: {p['measurand']} ({p['not_identifiable']} combination(s) not identifiable).",
        f"Identification: chi2/dof {i['chi2_per_dof']:.3f} on {i['dof']} degrees of freedom ({fit_said(i)}); "
        f"{i['thermal_correction']}.",
        f"Monte Carlo: {p['trials']} trials, seed {p['seed']}, {percent(p['coverage'])} intervals, "
        f"{p['not_converged']} not converged.",
        "  standard uncertainty u (k = 1), µm:      x        y        z" + (" (table frame)" if "frame" in s else ""),
        "    RMS of u over the mesh          " + "".join(f"{x:9.2f}" for x in s["u_rms_over_mesh"]),
        "    largest u                       " + "".join(f"{x:9.2f}" for x in s["u_max"]),
        *(["  in the machine frame (X, Y, Z at each pose):",
           "    RMS of u over the mesh          " + "".join(f"{x:9.2f}" for x in s["machine_frame"]["u_rms_over_mesh"]),
           "    largest u                       " + "".join(f"{x:9.2f}" for x in s["machine_frame"]["u_max"])]
          if "machine_frame" in s else []),
        f"  check: u(MCM) / u(identification covariance propagated linearly) median {r['median']:.3f} "
        f"({r['min']:.3f}-{r['max']:.3f}) over the point-axes",
        *([f"Expanded uncertainty: {p['statement']['U_text']}.",
           f"Decision (ISO 14253-1): {p['statement']['decision']}"] if "U_text" in p.get("statement", {}) else []),
    ])


def fit_said(i: dict) -> str:
    """The chi-square test in a few words (the statement's identification line)."""
    t = i.get("fit_test")
    if not t:
        return "no test of the fit"
    return (f"chi-square test against the stated noise: P(above) {t['p_above']:.2g}, P(below) {t['p_below']:.2g}, "
            + ("fails" if t["warning"] else "passes") + f" at {t['alpha']:g}")
