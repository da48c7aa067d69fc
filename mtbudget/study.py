"""The paper's two studies: tracker placement (Figs. 9-11) and 1000 verifications (Figs. 12-15).

Placement (paper Section 3, first part).  In each Monte Carlo test the
tracker's angular uncertainties are drawn from N(20, 3) urad (one value per
angle), its distance uncertainty is 4 um + 0.8 um/m, and a set of candidate
stations is drawn in the available space.  For every station the point
uncertainty u_p of Eq. 24 is computed at every mesh point (the trace of the
Cartesian covariance, Eq. 23); the "maximum error the tracker introduces"
is its largest value over the mesh, and the test keeps the station where it
is smallest.  The two directions of the paper are two placements of the
available space: along the Y axis (the tracker beside the machine on its
-X side, L spanning the Y direction) and along the X axis (the tracker in
front, on the -Y side, spanning X).  Stations must see every mesh point
within the tracker's range (0.5-15 m) and elevation (+-45 deg) limits and may
not stand inside the machine's envelope.

Verification (second part): ``mtbudget run`` of the paper configuration, with
the figures of the paper's Figs. 12-15 and the final mean volumetric error
distribution.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import SimulationConfig, _Reader, to_unit
from .plan import mesh


@dataclass
class PlacementSpace:
    name: str
    low: np.ndarray  # (3,) mm: x, y, z of the station
    high: np.ndarray


@dataclass
class PlacementSettings:
    tests: int
    candidates: int
    angular_mean: float
    angular_sd: float
    distance: float
    distance_per_length: float
    range_min: float
    range_max: float
    elevation_max: float
    envelope_low: np.ndarray
    envelope_high: np.ndarray
    spaces: list


def placement_settings(cfg: SimulationConfig, tests: int | None = None) -> PlacementSettings:
    raw = cfg.source.get("placement", {}) if isinstance(cfg.source, dict) else {}
    r = _Reader(raw, cfg.path, "placement.")
    D = [to_unit(v, "mm", r.where("D")) for v in raw.get("D", ["-2000 mm", "-500 mm"])]
    H = [to_unit(v, "mm", r.where("H")) for v in raw.get("H", ["350 mm", "2000 mm"])]
    L = [to_unit(v, "mm", r.where("L")) for v in raw.get("L", ["-2000 mm", "2000 mm"])]
    env = raw.get("envelope", {"x": ["0 mm", "2000 mm"], "y": ["-300 mm", "900 mm"], "z": ["0 mm", "2500 mm"]})
    e_lo = np.array([to_unit(env[a][0], "mm", r.where("envelope")) for a in "xyz"])
    e_hi = np.array([to_unit(env[a][1], "mm", r.where("envelope")) for a in "xyz"])
    # along Y: beside the machine (x = D, y = L); along X: in front of it (y = D mirrored below the envelope, x spans L)
    centre_x = 0.5 * (cfg.mesh_ranges["x"][0] + cfg.mesh_ranges["x"][1])
    spaces = [
        PlacementSpace("Y", np.array([D[0], L[0], H[0]]), np.array([D[1], L[1], H[1]])),
        # in front: the same distances D from the machine's front face (the envelope's low y), L along X
        PlacementSpace("X", np.array([centre_x + L[0], e_lo[1] + D[0], H[0]]),
                       np.array([centre_x + L[1], e_lo[1] + D[1], H[1]])),
    ]
    return PlacementSettings(
        tests=int(tests if tests is not None else raw.get("tests", 100_000)),
        candidates=int(raw.get("candidates", 64)),
        angular_mean=r.quantity("angular_mean", "rad", "20 urad"), angular_sd=r.quantity("angular_sd", "rad", "3 urad"),
        distance=r.quantity("distance", "mm", "4 um"), distance_per_length=r.quantity("distance_per_length", "mm/mm", "0.8 um/m"),
        range_min=r.quantity("range_min", "mm", "0.5 m"), range_max=r.quantity("range_max", "mm", "15 m"),
        elevation_max=r.quantity("elevation_max", "rad", "45 deg"),
        envelope_low=e_lo, envelope_high=e_hi, spaces=spaces)


def _visible(station: np.ndarray, pts: np.ndarray, s: PlacementSettings) -> np.ndarray:
    """(K,) stations that see every point within range and elevation limits and stand outside the envelope."""
    d = pts[None, :, :] - station[:, None, :]  # (K, M, 3), tracker level (no tilt)
    r = np.linalg.norm(d, axis=2)
    el = np.arcsin(np.clip(d[..., 2] / r, -1, 1))
    inside = np.all((station >= s.envelope_low) & (station <= s.envelope_high), axis=1)
    return (r.min(1) >= s.range_min) & (r.max(1) <= s.range_max) & (np.abs(el).max(1) <= s.elevation_max) & ~inside


def placement(cfg: SimulationConfig, tests: int | None = None, seed: int | None = None, progress: bool = False,
              chunk: int = 2000) -> dict:
    """The placement study: per direction, the best station and its maximum u_p for every test."""
    s = placement_settings(cfg, tests)
    pts = mesh(cfg.mesh_ranges, cfg.mesh_step) + np.asarray(cfg.tools[0])[None, :]
    ss = np.random.SeedSequence(cfg.seed if seed is None else seed)
    out = {"settings": {"tests": s.tests, "candidates": s.candidates, "angular_mean_urad": s.angular_mean * 1e6,
                        "angular_sd_urad": s.angular_sd * 1e6, "distance_um": s.distance * 1e3,
                        "distance_per_length_um_per_m": s.distance_per_length * 1e6},
           "directions": {}}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=s.tests * len(s.spaces), unit="test", desc="placement")
    t0 = time.perf_counter()
    for sp, child in zip(s.spaces, ss.spawn(len(s.spaces))):
        best_loc = np.empty((s.tests, 3))
        best_err = np.empty(s.tests)
        rng = np.random.default_rng(child)
        for lo in range(0, s.tests, chunk):
            n = min(chunk, s.tests - lo)
            ua = np.abs(rng.normal(s.angular_mean, s.angular_sd, (n, 2)))  # u_theta, u_phi per test
            st = rng.uniform(sp.low, sp.high, (n, s.candidates, 3))
            ok = _visible(st.reshape(-1, 3), pts, s).reshape(n, s.candidates)
            d = pts[None, None] - st[:, :, None, :]  # (n, K, M, 3): the point seen from the station (frame aligned)
            r = np.linalg.norm(d, axis=3)
            rho = np.hypot(d[..., 0], d[..., 1])
            ur = s.distance + s.distance_per_length * r
            # Eq. 24: u_p^2 = u_r^2 + (r cos(el) u_az)^2 + (r u_el)^2 (trace of the exact covariance)
            up = np.sqrt(ur**2 + (rho * ua[:, None, None, 0]) ** 2 + (r * ua[:, None, None, 1]) ** 2)
            worst = up.max(axis=2)
            worst[~ok] = np.inf
            k = worst.argmin(axis=1)
            rows = np.arange(n)
            best_err[lo:lo + n] = worst[rows, k] * 1e3
            best_loc[lo:lo + n] = st[rows, k]
            if bar:
                bar.update(n)
        good = np.isfinite(best_err)
        out["directions"][sp.name] = {"space": {"low": sp.low.tolist(), "high": sp.high.tolist()},
                                      "best_location": best_loc[good], "max_error_um": best_err[good],
                                      "no_visible_station": int((~good).sum())}
    if bar:
        bar.close()
    out["seconds"] = time.perf_counter() - t0
    y, x = out["directions"]["Y"]["max_error_um"], out["directions"]["X"]["max_error_um"]
    better, worse = sorted([("X", x.mean()), ("Y", y.mean())], key=lambda t: t[1])
    out["reduction"] = {"better": better[0], "worse": worse[0], "mean_better_um": better[1], "mean_worse_um": worse[1],
                        "reduction": 1 - better[1] / worse[1]}
    out["fits"] = {k: fit_candidates(v["max_error_um"]) for k, v in out["directions"].items()}
    return out


def fit_candidates(x: np.ndarray) -> list:
    """Candidate distributions fitted to the maximum errors, best first (Kolmogorov-Smirnov distance)."""
    from scipy import stats

    sample = x if len(x) <= 20000 else np.random.default_rng(0).choice(x, 20000, replace=False)
    out = []
    for name in ("norm", "lognorm", "gamma", "weibull_min", "gumbel_r"):
        dist = getattr(stats, name)
        try:
            params = dist.fit(sample)
            ks = stats.kstest(sample, dist(*params).cdf).statistic
            out.append({"distribution": name, "parameters": [float(p) for p in params], "ks_distance": float(ks)})
        except Exception:  # a fit that fails is simply not a candidate
            continue
    return sorted(out, key=lambda d: d["ks_distance"])


def placement_figures(res: dict, folder: Path) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    folder.mkdir(parents=True, exist_ok=True)
    figs = {}
    for name, d in res["directions"].items():
        loc, err = d["best_location"], d["max_error_um"]
        show = np.random.default_rng(0).choice(len(err), min(len(err), 20000), replace=False)
        fig = plt.figure(figsize=(7, 5.5))
        ax = fig.add_subplot(projection="3d")
        sc = ax.scatter(loc[show, 0], loc[show, 1], loc[show, 2], c=err[show], s=2, cmap="viridis")
        fig.colorbar(sc, ax=ax, shrink=0.7, label="maximum u_p over the mesh [um]")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        ax.set_zlabel("z [mm]")
        ax.set_title(f"best tracker station of each test: {name}-axis direction (paper Fig. {9 if name == 'Y' else 10})")
        p = folder / f"placement_{name}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        figs[f"placement_{name}"] = p
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, d in res["directions"].items():
        err = d["max_error_um"]
        ax.hist(err, bins=80, density=True, alpha=0.5, label=f"{name} direction (mean {err.mean():.1f} um)")
        best = res["fits"][name][0]
        xs = np.linspace(err.min(), err.max(), 300)
        ax.plot(xs, getattr(stats, best["distribution"])(*best["parameters"]).pdf(xs), lw=1.5,
                label=f"{name}: best fit {best['distribution']} (KS {best['ks_distance']:.3f})")
    ax.set_xlabel("maximum error introduced by the tracker [um]")
    ax.set_title("paper Fig. 11: maximum error at the best station of each test")
    ax.legend(fontsize=7)
    fig.tight_layout()
    p = folder / "placement_histogram.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    figs["placement_histogram"] = p
    return figs


def placement_json(res: dict) -> dict:
    out = {"settings": res["settings"], "reduction": res["reduction"], "seconds": res["seconds"], "fits": res["fits"],
           "directions": {}}
    for k, d in res["directions"].items():
        e = d["max_error_um"]
        out["directions"][k] = {"space": d["space"], "tests": int(len(e)), "no_visible_station": d["no_visible_station"],
                                "max_error_um": {"mean": float(e.mean()), "std": float(e.std()), "min": float(e.min()),
                                                 "p05": float(np.percentile(e, 5)), "p95": float(np.percentile(e, 95)),
                                                 "max": float(e.max())},
                                "best_location_mean_mm": d["best_location"].mean(0).tolist()}
    return out


def write_placement_log(res: dict, path: Path, cfg: SimulationConfig):
    """Log the placement study to MCAP (JSON messages, arrays base64 float64)."""
    from mcap.writer import Writer

    from . import __version__
    from .runlog import _enc

    with open(path, "wb") as fh:
        w = Writer(fh, use_chunking=False)
        w.start(profile="", library=f"mtbudget {__version__}")
        sid = w.register_schema(name="mtbudget.PlacementStudy", encoding="jsonschema",
                                data=json.dumps({"type": "object", "title": "mtbudget.PlacementStudy"}).encode())
        ch = w.register_channel(topic="/mtbudget/placement", message_encoding="json", schema_id=sid)
        t = time.time_ns()
        if cfg.path:
            w.add_attachment(create_time=t, log_time=t, name="config.toml", media_type="application/toml",
                             data=Path(cfg.path).read_bytes())
        w.add_metadata("mtbudget.placement", {"format": "mtbudget-placement/1", "seed": str(cfg.seed)})
        body = placement_json(res)
        body["arrays"] = {k: {"best_location": _enc(d["best_location"]), "max_error_um": _enc(d["max_error_um"])}
                          for k, d in res["directions"].items()}
        w.add_message(channel_id=ch, log_time=t, publish_time=t, data=json.dumps(body).encode())
        w.finish()


def placement_report(res: dict, folder: Path) -> Path:
    figs = placement_figures(res, folder)
    j = placement_json(res)
    red = j["reduction"]
    lines = ["# Tracker placement study (paper Figs. 9-11)", "",
             f"{j['settings']['tests']} Monte Carlo tests per direction, {j['settings']['candidates']} candidate stations per "
             f"test; u_theta, u_phi ~ N({j['settings']['angular_mean_urad']:g}, {j['settings']['angular_sd_urad']:g}) urad, "
             f"u_d = {j['settings']['distance_um']:g} um + {j['settings']['distance_per_length_um_per_m']:g} um/m.", "",
             "| direction | tests | mean max error [um] | std | 5 % | 95 % | best fit |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for k, d in j["directions"].items():
        e = d["max_error_um"]
        lines.append(f"| {k} | {d['tests']} | {e['mean']:.1f} | {e['std']:.1f} | {e['p05']:.1f} | {e['p95']:.1f} | "
                     f"{j['fits'][k][0]['distribution']} (KS {j['fits'][k][0]['ks_distance']:.3f}) |")
    lines += ["", f"The {red['better']} direction reduces the mean maximum error by {red['reduction']:.0%} against the "
              f"{red['worse']} direction ({red['mean_better_um']:.1f} vs {red['mean_worse_um']:.1f} um); the paper reports "
              "about 30 %.", ""]
    lines += [f"![{k}]({p.name})" for k, p in figs.items()]
    (folder / "placement.md").write_text("\n".join(lines) + "\n")
    (folder / "placement.json").write_text(json.dumps(j, indent=1))
    return folder / "placement.md"


# ----------------------------------------------------------------------------- verification study
def verification_figures(res, folder: Path, cfg: SimulationConfig) -> dict:
    """Figs. 12-15: initial and final error clouds per point, and the final mean volumetric error distribution."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    from .engine import Engine
    from .identify import identify

    folder.mkdir(parents=True, exist_ok=True)
    figs = {}
    # a sample of verifications redrawn with the run's own streams (first blocks) for the point clouds
    eng = Engine(cfg, seed=res.spec["seed"], sources=res.spec["sources"], block=res.spec["block"])
    blocks = max(1, min(4, res.trials // eng.block))
    init, final = [], []
    for b in range(blocks):
        meas, _, _ = eng.simulate(b)  # the run's own trials of block b (identified with the default strategy)
        ident = identify(eng.id_model, meas, eng.noise, chunk=eng.block)
        init.append(ident.initial_error[:, eng.mesh_rows])
        final.append(ident.residual_machine[:, eng.mesh_rows])
    init, final = np.concatenate(init) * 1e3, np.concatenate(final) * 1e3
    for name, data, fig_no in (("initial", init, 12), ("final", final, 14)):
        fig, axes = plt.subplots(1, 4, figsize=(15, 3.6))
        for i, a in enumerate("xyz"):
            axes[i].hist(data[..., i].ravel(), bins=80, density=True, color="#7aa6c2")
            axes[i].set_xlabel(f"{a} error [um]")
        axes[3].hist(np.linalg.norm(data, axis=2).ravel(), bins=80, density=True, color="#c2a67a")
        axes[3].set_xlabel("distance error [um]")
        fig.suptitle(f"{name} error of the verification points, {len(data)} simulated verifications (paper Fig. {fig_no})")
        fig.tight_layout()
        p = folder / f"{name}_errors.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        figs[f"{name}_errors"] = p
    mesh_pts = eng.truth.machine_points(np.zeros(eng.truth.n_params))[0][eng.mesh_rows]
    fig = plt.figure(figsize=(13, 5.5))
    for j, (data, title) in enumerate(((init, "initial (paper Fig. 13)"), (final, "final (paper Fig. 15)"))):
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        scale = 40.0 / max(np.abs(data).max(), 1e-9)  # mm of plot per um of error: clouds 40 mm across at most
        cloud = mesh_pts[None] + data * scale
        norm = np.linalg.norm(data, axis=2)
        sc = ax.scatter(cloud[..., 0].ravel(), cloud[..., 1].ravel(), cloud[..., 2].ravel(), c=norm.ravel(), s=1, cmap="viridis")
        fig.colorbar(sc, ax=ax, shrink=0.6, label="error [um]")
        ax.set_title(f"{title}: error clouds, exaggerated x{scale * 1e3:.0f}", fontsize=9)
    fig.tight_layout()
    p = folder / "error_clouds.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    figs["error_clouds"] = p
    # final mean volumetric error (Eq. 27) distribution with a fitted normal
    y = res.acc.scalar_samples("mean_error_after")
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.hist(y, bins=50, density=True, color="#7aa6c2", label="MCM")
    mu, sd = y.mean(), y.std(ddof=1)
    xs = np.linspace(y.min(), y.max(), 200)
    ax.plot(xs, stats.norm.pdf(xs, mu, sd), "r", label=f"normal fit: mean {mu:.2f} um, sigma {sd:.2f} um")
    ax.set_xlabel("final mean volumetric error, Eq. 27 [um]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = folder / "final_mean_error.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    figs["final_mean_error"] = p
    return figs


def verification_summary(res) -> dict:
    from scipy import stats

    y = res.acc.scalar_samples("mean_error_after")
    mu, sd = float(y.mean()), float(y.std(ddof=1))
    return {"trials": res.trials, "final_mean_error_um": {"mean": mu, "sigma": sd, "p95": float(np.percentile(y, 95)),
                                                          "normal_mean_plus_2sigma": mu + 1.96 * sd,
                                                          "shapiro_p": float(stats.shapiro(y[:5000]).pvalue)},
            "max_residual_um": {"mean": float(res.acc.scalar_samples("max_residual").mean()),
                                "max": float(res.acc.scalar_samples("max_residual").max())},
            "compensation_rms_um": res.summary("compensation_rms")}
