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

import difflib
import time
from dataclasses import dataclass

import numpy as np

from . import tracker as lt
from .config import Reader, to_unit
from .engine import Engine
from .errors import ConfigError
from .identify import identify
from .plan import mesh
from .progress import progress_bar
from .scenario import Scenario
from .units import display, factor


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


#: what the placement study takes from elsewhere in the configuration (one key per physical input)
_NOISE_KEYS = {"angular_mean": "tracker.angular", "distance": "tracker.distance",
               "distance_per_length": "tracker.distance_per_length", "angular_sd": "sources.tracker_noise.angular_sd"}
_PLACEMENT_KEYS = ("D", "L", "H", "range_min", "range_max", "elevation_max", "tests", "candidates", "envelope")


def placement_settings(scenario: Scenario, tests: int | None = None) -> PlacementSettings:
    """The placement study's settings: the [placement] table, and the tracker noise of the scenario."""
    cfg = scenario.config
    raw = cfg.source.get("placement", {}) if isinstance(cfg.source, dict) else {}
    r = Reader(raw, cfg.path, "placement.")
    for k in raw:
        if k in _NOISE_KEYS:
            raise ConfigError(f"{r.where(k)}: the tracker noise is stated once, as {_NOISE_KEYS[k]}; "
                              "remove it from [placement]")
        if k not in _PLACEMENT_KEYS:
            close = difflib.get_close_matches(k, _PLACEMENT_KEYS, n=1)
            raise ConfigError(f"{r.where(k)}: unknown key" + (f"; did you mean {close[0]!r}?" if close else
                                                              f"; [placement] takes {', '.join(_PLACEMENT_KEYS)}"))
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
    n_tests = tests if tests is not None else raw.get("tests", 100_000)
    n_cand = raw.get("candidates", 64)
    for key, v in (("tests", n_tests), ("candidates", n_cand)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            where = "--tests" if key == "tests" and tests is not None else r.where(key)
            raise ConfigError(f"{where}: must be a whole number >= 1, got {v!r}")
    noise = {s.name: s for s in scenario.sources}.get("tracker_noise")
    return PlacementSettings(
        tests=int(n_tests), candidates=int(n_cand),
        angular_mean=scenario.drawn["tracker.angular"],
        angular_sd=noise.value("angular_sd", "rad") if noise is not None else 0.0,
        distance=scenario.drawn["tracker.distance"], distance_per_length=scenario.drawn["tracker.distance_per_length"],
        range_min=r.quantity("range_min", "mm", "0.5 m"), range_max=r.quantity("range_max", "mm", "15 m"),
        elevation_max=r.quantity("elevation_max", "rad", "45 deg"),
        envelope_low=e_lo, envelope_high=e_hi, spaces=spaces)


def _visible(station: np.ndarray, pts: np.ndarray, s: PlacementSettings) -> np.ndarray:
    """(K,) stations that see every point within range and elevation limits and stand outside the envelope."""
    dx, dy, dz = _differences(station, pts)
    return _visible_from(_range(dx, dy, dz), dz, station, s)


def _differences(station: np.ndarray, pts: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The points seen from each station (tracker level, no tilt), component-major: (3, ..., M).

    station (..., 3), pts (M, 3).  The values are those of ``pts - station`` element for element; one
    contiguous array per component keeps every later operation on contiguous memory.
    """
    out = np.empty((3,) + station.shape[:-1] + (len(pts),)) if out is None else out
    for c in range(3):
        np.subtract(pts[:, c], station[..., c, None], out=out[c])
    return out


def _range(dx, dy, dz) -> np.ndarray:
    """``sqrt((dx^2 + dy^2) + dz^2)``: what ``np.linalg.norm`` computes over (x, y, z), bit for bit."""
    return np.sqrt((dx * dx + dy * dy) + dz * dz)


def _visible_from(r, dz, station, s: PlacementSettings) -> np.ndarray:
    """:func:`_visible` from the ranges and heights (..., M) of the points: the same decisions, bit for bit.

    arcsin is odd and increasing, so the largest |elevation| is the arcsin of the largest |dz| / r: one
    arcsin per station instead of one per point.
    """
    el = np.arcsin(np.clip(np.abs(dz / r).max(axis=-1), -1, 1))
    inside = np.all((station >= s.envelope_low) & (station <= s.envelope_high), axis=-1)
    return (r.min(-1) >= s.range_min) & (r.max(-1) <= s.range_max) & (el <= s.elevation_max) & ~inside


#: tests whose candidate stations are evaluated together: about 2 MB of differences (a mesh that is not a
#: grid: every point of every station), which stays in cache; on a grid, a few points per station
_PLACEMENT_SUBCHUNK = 32
_PLACEMENT_SUBCHUNK_GRID = 250
#: relative margin of the bounds that rule a station out before its u_p is computed at every point
#: (far above the round-off of the bounds, ~1e-15; far below any real difference between stations)
_BOUND_MARGIN = 1e-9


def placement(scenario: Scenario, tests: int | None = None, seed: int | None = None, progress: bool = False,
              chunk: int = 2000) -> dict:
    """The placement study: per direction, the best station and its maximum u_p for every test."""
    cfg = scenario.config
    s = placement_settings(scenario, tests)
    pts = mesh(cfg.mesh_ranges, cfg.mesh_step) + np.asarray(cfg.tools[0])[None, :]
    ss = np.random.SeedSequence(cfg.seed if seed is None else seed)
    out = {"settings": {"tests": s.tests, "candidates": s.candidates,
                        "angular_mean_urad": display(s.angular_mean, "rad", "urad"),
                        "angular_sd_urad": display(s.angular_sd, "rad", "urad"), "distance_um": display(s.distance, "mm", "um"),
                        "distance_per_length_um_per_m": display(s.distance_per_length, "", "um/m")},
           "directions": {}}
    bar = progress_bar(s.tests * len(s.spaces), "placement", "test", progress)
    um = factor("mm", "um")
    grid = _grid_axes(pts)  # the mesh is a grid: its extremes decide visibility and the ranking bounds
    sub = _PLACEMENT_SUBCHUNK_GRID if grid is not None else _PLACEMENT_SUBCHUNK
    buf = None if grid is not None else np.empty((3, sub, s.candidates, len(pts)))  # reused from call to call
    t0 = time.perf_counter()
    for sp, child in zip(s.spaces, ss.spawn(len(s.spaces))):
        best_loc = np.empty((s.tests, 3))
        best_err = np.empty(s.tests)
        rng = np.random.default_rng(child)
        for lo in range(0, s.tests, chunk):
            # the random draws: chunk by chunk, in this order (the numbers depend on it)
            n = min(chunk, s.tests - lo)
            ua = np.abs(rng.normal(s.angular_mean, s.angular_sd, (n, 2)))  # u_theta, u_phi per test
            st = rng.uniform(sp.low, sp.high, (n, s.candidates, 3))
            # the arithmetic: a few tests at a time, so that the differences stay in cache
            for a in range(0, n, sub):
                b = min(n, a + sub)
                best_err[lo + a:lo + b], best_loc[lo + a:lo + b] = _best_stations(st[a:b], ua[a:b], pts, s, um, buf, grid)
            bar.update(n)
        good = np.isfinite(best_err)
        out["directions"][sp.name] = {"space": {"low": sp.low.tolist(), "high": sp.high.tolist()},
                                      "best_location": best_loc[good], "max_error_um": best_err[good],
                                      "no_visible_station": int((~good).sum())}
    bar.close()
    out["seconds"] = time.perf_counter() - t0
    y, x = out["directions"]["Y"]["max_error_um"], out["directions"]["X"]["max_error_um"]
    better, worse = sorted([("X", x.mean()), ("Y", y.mean())], key=lambda t: t[1])
    out["reduction"] = {"better": better[0], "worse": worse[0], "mean_better_um": better[1], "mean_worse_um": worse[1],
                        "reduction": 1 - better[1] / worse[1]}
    out["fits"] = {k: fit_candidates(v["max_error_um"]) for k, v in out["directions"].items()}
    return out


def _grid_axes(pts: np.ndarray):
    """The axis values (x, y, z) when the points are exactly every combination of them, else None."""
    axes = [np.unique(pts[:, c]) for c in range(3)]
    if len(pts) != np.prod([len(v) for v in axes]):
        return None
    idx = [np.searchsorted(v, pts[:, c]) for c, v in enumerate(axes)]
    flat = (idx[0] * len(axes[1]) + idx[1]) * len(axes[2]) + idx[2]
    return axes if len(np.unique(flat)) == len(pts) else None


def _grid_extremes(st: np.ndarray, grid: list, s: PlacementSettings):
    """Visibility, farthest point and range to it for stations st (n, K, 3) and a grid of points, exactly.

    Every rounded operation is monotone, so the range computed as ``sqrt((dx^2 + dy^2) + dz^2)`` is
    largest at the grid point farthest on every axis (an end of each axis) and smallest at the nearest
    on every axis (one of the two values around the station), and among the points of one z level
    |dz| / r is largest at the nearest (x, y): the minimum and maximum range and the largest |elevation|
    over the grid, computed at those few points, are what the point-by-point computation finds, bit for
    bit.  Returns (visible (n, K), the farthest point seen from the station (n, K, 3), its range (n, K)).
    """
    far, near = [], []
    for c, v in enumerate(grid):  # v: the axis values, sorted
        x = st[..., c]
        lo, hi = v[0] - x, v[-1] - x
        far.append(np.where(np.abs(hi) >= np.abs(lo), hi, lo))
        i = np.clip(np.searchsorted(v, x), 1, len(v) - 1) if len(v) > 1 else np.zeros(x.shape, int)
        below, above = v[i - 1] - x, v[i] - x
        near.append(np.where(np.abs(above) < np.abs(below), above, below))
    r_max = _range(*far)
    r_min = _range(*near)
    dz = grid[2] - st[..., 2, None]  # every z level, at the nearest (x, y)
    el = np.arcsin(np.clip(np.abs(dz / _range(near[0][..., None], near[1][..., None], dz)).max(axis=-1), -1, 1))
    lo, hi = s.envelope_low, s.envelope_high
    inside = ((st[..., 0] >= lo[0]) & (st[..., 0] <= hi[0]) & (st[..., 1] >= lo[1]) & (st[..., 1] <= hi[1])
              & (st[..., 2] >= lo[2]) & (st[..., 2] <= hi[2]))
    ok = (r_min >= s.range_min) & (r_max <= s.range_max) & (el <= s.elevation_max) & ~inside
    return ok, np.stack(far, axis=-1), r_max


def _best_stations(st: np.ndarray, ua: np.ndarray, pts: np.ndarray, s: PlacementSettings, um: float,
                   buf: np.ndarray | None = None, grid: list | None = None):
    """For tests (n,) with candidate stations st (n, K, 3) and angular uncertainties ua (n, 2): the best
    station's maximum u_p (um; inf when no station sees the mesh) and the station (n, 3).

    The same numbers as ranking every visible station by its maximum u_p over the mesh, computed for
    fewer stations: u_p at a station's farthest point is a lower bound of its maximum, and
    sqrt((a + b r_max)^2 + (u_az^2 + u_el^2) r_max^2) an upper bound (the distance to every point is at
    most r_max, its horizontal part at most the distance).  A station whose lower bound exceeds the
    smallest upper bound of the test (by a relative margin far above round-off) cannot be the best and
    is not evaluated further; every u_p that decides comes from :func:`mtbudget.tracker.point_uncertainty`.
    buf: room for the differences (3, >= n, K, M), reused from one call to the next; grid: the points'
    axis values when they are every combination of them (:func:`_grid_axes`, :func:`_grid_extremes`).
    """
    n, K = st.shape[:2]
    a, b = s.distance, s.distance_per_length
    if grid is not None:  # the points are a grid: its extremes decide, a few points per station
        D = None
        ok, P_far, r_max = _grid_extremes(st, grid, s)
    else:
        D = _differences(st, pts, None if buf is None else buf[:, :n])  # (3, n, K, M): frame aligned
        r = _range(D[0], D[1], D[2])
        ok = _visible_from(r, D[2], st, s)
        i, j = np.indices((n, K))
        far = r.argmax(axis=-1)
        r_max = r[i, j, far]
        P_far = np.moveaxis(D[:, i, j, far], 0, -1)
    candidates = ok
    if a >= 0 and b >= 0:  # (a + b r)^2 grows with r: the bounds hold
        lower = lt.point_uncertainty(P_far, ua[:, None, 0], a, b, ua[:, None, 1])
        upper = np.sqrt((a + b * r_max) ** 2 + ((ua[:, 0] ** 2 + ua[:, 1] ** 2)[:, None]) * r_max**2)
        bound = np.where(ok, upper, np.inf).min(axis=1)
        candidates = ok & (lower <= bound[:, None] * (1 + _BOUND_MARGIN))
    t, k = np.nonzero(candidates)
    worst = np.full((n, K), np.inf)
    if t.size:
        # Eq. 24: u_p = sqrt(trace) of the tracker covariance of Eq. 23, at every point of the stations left;
        # the points (nv, M, 3) as a view whose component axis is outermost in memory (the same numbers as a
        # copy, faster to reduce)
        Dv = _differences(st[t, k], pts) if D is None else D[:, t, k]
        up = lt.point_uncertainty(np.moveaxis(Dv, 0, -1), ua[t, 0][:, None], a, b, ua[t, 1][:, None])
        worst[t, k] = up.max(axis=1)
    best = worst.argmin(axis=1)
    rows = np.arange(n)
    return worst[rows, best] * um, st[rows, best]


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


def placement_arrays(res: dict) -> dict:
    """Per direction, the per-test arrays of the study: best station (mm) and its maximum u_p (um)."""
    return {k: {"best_location": d["best_location"], "max_error_um": d["max_error_um"]} for k, d in res["directions"].items()}


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


# ----------------------------------------------------------------------------- verification study
def verification_clouds(res, scenario: Scenario, blocks: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Initial and final errors (um) at the mesh points of the run's first trials (paper Figs. 12-15).

    The run's own trials of its first ``blocks`` blocks are simulated again
    (same streams) and identified with the default strategy.
    """
    eng = Engine(scenario, seed=res.spec["seed"], block=res.spec["block"])
    n_blocks = max(1, min(blocks, res.trials // eng.block))
    init, final = [], []
    for b in range(n_blocks):
        meas, _, _ = eng.simulate(b)
        ident = identify(scenario.id_model, meas, scenario.noise, chunk=eng.block)
        init.append(ident.initial_error[:, scenario.mesh_rows])
        final.append(ident.residual_machine[:, scenario.mesh_rows])
    um = factor("mm", "um")
    return np.concatenate(init) * um, np.concatenate(final) * um


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
