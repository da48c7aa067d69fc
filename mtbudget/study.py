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
-X side, L spanning the Y direction) and along the X axis (by default the
same space turned a quarter about z, L spanning X; ``PLACEMENT_READINGS``).
Stations must see every mesh point within the tracker's range (0.5-15 m) and
elevation (+-45 deg) limits and may not stand inside the machine's envelope.

Verification (second part): ``mtbudget run`` of the paper configuration, with
the figures of the paper's Figs. 12-15 and the final mean volumetric error
distribution.

Readings (:func:`paper_readings`): where the paper's text allows several
readings of a figure, every one computed side by side with the paper's
numbers, and a sensitivity table (docs/paper-reproduction.md).
"""

from __future__ import annotations

import difflib
import time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from . import tracker as lt
from .config import PLACEMENT_NOISE_KEYS, SCHEMA, Reader, to_unit
from .config import PLACEMENT_READINGS as _READINGS
from .engine import Engine
from .errors import ConfigError
from .identify import Strategy, identify
from .plan import mesh
from .progress import progress_bar, working
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
    directions: str = "machine"  # which reading of D, L, H (PLACEMENT_READINGS)
    eq23: str = "polar"  # which reading of theta in Eq. 23 (EQ23_READINGS)


#: what the placement study takes from elsewhere in the configuration (one key per physical input)
_NOISE_KEYS = PLACEMENT_NOISE_KEYS
_PLACEMENT_KEYS = SCHEMA["placement"]

#: The readings of the paper that its text leaves open, default first: the default of each is the one that
#: reproduces the paper on the most counts (docs/paper-reproduction.md; ``mtbudget study all`` prints every
#: reading side by side).  Each is one key of [placement] away.
#:
#: directions: what "Y direction" and "X direction" (Figs. 9-10) are.  "machine": D, L, H are the station's
#: machine coordinates x, y, z (Eq. 21 as printed, the paper's own station d = -563.52 mm is such an x), and the
#: X direction is the same space turned a quarter about z (x = L, y = D).  "envelope": the X direction stands
#: in front of the machine at distance D from the envelope's front face, L along x from the mesh centre.
PLACEMENT_READINGS = _READINGS["directions"]
#: eq23: what theta of Eq. 23 is.  "polar": the angle from the tracker's z axis (the rows of Eq. 23 are then
#: the exact diagonal of the tracker covariance).  "elevation": the angle from the tracker's horizontal plane
#: (the paper's range "-45 deg <= theta <= 45 deg" reads so), Eq. 23 then used as printed.
EQ23_READINGS = _READINGS["eq23"]
#: eq27: what the paper's final mean volumetric error (Eq. 27, Figs. 14-15) averages.  "compensated": the
#: distance error of the compensated machine at each mesh point (docs/measurand.md), rigid part removed;
#: "compensated_rigid": the same with the rigid part kept; "residual": the fit residual of the verification.
EQ27_READINGS = _READINGS["eq27"]


def _reading(raw: dict, r: Reader, key: str, choices: tuple, given: str | None) -> str:
    v = raw.get(key, choices[0]) if given is None else given
    if v not in choices:
        where = r.where(key) if given is None else key
        raise ConfigError(f"{where}: expected one of {', '.join(map(repr, choices))}, got {v!r}")
    return v


def study_readings(scenario: Scenario) -> dict:
    """The readings the configuration chooses: {"directions", "eq23", "eq27"} (defaults: the first of each)."""
    cfg = scenario.config
    raw = cfg.source.get("placement", {}) if isinstance(cfg.source, dict) else {}
    r = Reader(raw, cfg.path, "placement.")
    return {k: _reading(raw, r, k, c, None) for k, c in (("directions", PLACEMENT_READINGS), ("eq23", EQ23_READINGS),
                                                         ("eq27", EQ27_READINGS))}


def placement_settings(scenario: Scenario, tests: int | None = None, directions: str | None = None,
                       eq23: str | None = None) -> PlacementSettings:
    """The placement study's settings: the [placement] table, and the tracker noise of the scenario.

    directions, eq23: a reading other than the configuration's (PLACEMENT_READINGS, EQ23_READINGS)."""
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
    directions = _reading(raw, r, "directions", PLACEMENT_READINGS, directions)
    eq23 = _reading(raw, r, "eq23", EQ23_READINGS, eq23)
    # along Y: beside the machine (x = D, y = L), in both readings
    spaces = [PlacementSpace("Y", np.array([D[0], L[0], H[0]]), np.array([D[1], L[1], H[1]]))]
    if directions == "machine":  # along X: the same space turned a quarter about z (x = L, y = D)
        spaces.append(PlacementSpace("X", np.array([L[0], D[0], H[0]]), np.array([L[1], D[1], H[1]])))
    else:  # in front: the same distances D from the machine's front face (the envelope's low y), L along X
        centre_x = 0.5 * (cfg.mesh_ranges["x"][0] + cfg.mesh_ranges["x"][1])
        spaces.append(PlacementSpace("X", np.array([centre_x + L[0], e_lo[1] + D[0], H[0]]),
                                     np.array([centre_x + L[1], e_lo[1] + D[1], H[1]])))
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
        envelope_low=e_lo, envelope_high=e_hi, spaces=spaces, directions=directions, eq23=eq23)


def eq24_point_uncertainty(P_LT: np.ndarray, u_az, distance, distance_per_length, u_el, eq23: str = "polar") -> np.ndarray:
    """u_p of Eq. 24 (internal units) as the trace of Eq. 23 under a reading of its theta (EQ23_READINGS).

    Eq. 23's trace is u_r^2 + r^2 u_theta^2 + r^2 sin^2(theta) u_phi^2 whatever theta is, with phi the
    azimuth.  "polar": theta from the z axis, sin^2(theta) = cos^2(el): the exact trace
    (:func:`mtbudget.tracker.point_uncertainty`).  "elevation": theta = el, so the azimuth's noise counts
    with sin^2(el) instead of cos^2(el).
    """
    if eq23 == "polar":
        return lt.point_uncertainty(P_LT, u_az, distance, distance_per_length, u_el)
    r = np.linalg.norm(P_LT, axis=-1)
    ur = np.asarray(distance) + np.asarray(distance_per_length) * r
    sin_el = P_LT[..., 2] / r
    return np.sqrt(ur**2 + (r * u_el) ** 2 + (r * sin_el * u_az) ** 2)


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
              chunk: int = 2000, directions: str | None = None, eq23: str | None = None, fits: bool = True) -> dict:
    """The placement study: per direction, the best station and its maximum u_p for every test.

    directions, eq23: readings other than the configuration's (PLACEMENT_READINGS, EQ23_READINGS); fits: fit
    the candidate distributions to the maximum errors (Fig. 11; most of the time of a short study)."""
    cfg = scenario.config
    s = placement_settings(scenario, tests, directions, eq23)
    pts = mesh(cfg.mesh_ranges, cfg.mesh_step) + np.asarray(cfg.tools[0])[None, :]
    if cfg.rotary:  # a five-axis machine, tracker on the table: the tool points in the table frame at every pose
        pts = np.asarray(scenario.mesh_points, float)
    ss = np.random.SeedSequence(cfg.seed if seed is None else seed)
    out = {"settings": {"tests": s.tests, "candidates": s.candidates,
                        "angular_mean_urad": display(s.angular_mean, "rad", "urad"),
                        "angular_sd_urad": display(s.angular_sd, "rad", "urad"), "distance_um": display(s.distance, "mm", "um"),
                        "distance_per_length_um_per_m": display(s.distance_per_length, "", "um/m"),
                        "directions": s.directions, "eq23": s.eq23},
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
    with working("fitting the distributions of Fig. 11", progress):
        out["fits"] = {k: fit_candidates(v["max_error_um"]) for k, v in out["directions"].items()} if fits else {}
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
    is not evaluated further; every u_p that decides comes from :func:`eq24_point_uncertainty`.
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
        lower = eq24_point_uncertainty(P_far, ua[:, None, 0], a, b, ua[:, None, 1], s.eq23)
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
        up = eq24_point_uncertainty(np.moveaxis(Dv, 0, -1), ua[t, 0][:, None], a, b, ua[t, 1][:, None], s.eq23)
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
    one_tracker(scenario, "the error clouds of paper Figs. 12-15")
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
    # one name per quantity, the run's own output names: mean_error_after is Eq. 27 read as the fit residual,
    # compensation_mean Eq. 27 read as the compensated machine's error (the study's default reading)
    return {"trials": res.trials, "mean_error_after_um": {"mean": mu, "sigma": sd, "p95": float(np.percentile(y, 95)),
                                                          "normal_mean_plus_2sigma": mu + 1.96 * sd,
                                                          "shapiro_p": float(stats.shapiro(y[:5000]).pvalue)},
            "max_residual_um": {"mean": float(res.acc.scalar_samples("max_residual").mean()),
                                "max": float(res.acc.scalar_samples("max_residual").max())},
            "compensation_rms_um": res.summary("compensation_rms"),
            "compensation_mean_um": _compensated_summary(res)}


def _compensated_summary(res) -> dict:
    """Eq. 27 read as the compensated machine's error, per test (the default reading, EQ27_READINGS), from the
    run's own ``compensation_mean`` and ``compensation_max`` (um): mean, sigma, mean + 2 sigma, and the largest
    point error that 95 % of the tests stay below."""
    y = res.acc.scalar_samples("compensation_mean")
    worst = res.acc.scalar_samples("compensation_max")
    mu, sd = float(y.mean()), float(y.std(ddof=1))
    return {"mean": mu, "sigma": sd, "mean_plus_2sigma": mu + 2 * sd, "max_p95": float(np.percentile(worst, 95)),
            "max": float(worst.max())}


# ----------------------------------------------------------------------------- every reading side by side
#: The paper's numbers (Section 3 and Conclusions) that the readings are compared with.  A range is (low, high);
#: "about" numbers and exact ones alike match within ``MATCH_TOLERANCE`` of the number (of the range's ends).
PAPER = {
    "fig11_Y_um": ((60.0, 80.0), "Fig. 9: lower maximum errors, Y direction, 60-80 um"),
    "fig11_X_um": ((40.0, 60.0), "Fig. 10: lowest maximum errors, X direction, 40-60 um"),
    "reduction": (0.30, "the better direction lowers the maximum error by about 30 %"),
    "max_difference_um": (30.0, "the maximum values of Fig. 9 are about 30 um above those of Fig. 10"),
    "station_up_max_um": (50.0, "the tracker's error at its chosen station (Fig. 10) is about 50 um, like the final maximum"),
    "eq27_mean_um": (13.77, "final mean volumetric error (Eq. 27): mean 13.77 um"),
    "eq27_sigma_um": (5.02, "its sigma 5.02 um"),
    "eq27_bound_um": (23.81, "95 % below 23.81 um (= mean + 2 sigma)"),
    "eq27_max_um": (50.0, "maximum error about 50 um, reached in a few tests only (most stay below)"),
    "eq27_reduction": ((0.0, 0.5), "the errors have been greatly minimized (Fig. 13 vs 15): final below half the initial"),
    "geometry_dominated": ((0.9, 1.0), "Fig. 13: geometric errors greater than the noise (share of the points)"),
}
MATCH_TOLERANCE = 0.15


def matches(value: float, key: str) -> bool:
    """True when ``value`` reproduces the paper's number ``PAPER[key]`` (within MATCH_TOLERANCE)."""
    ref = PAPER[key][0]
    if isinstance(ref, tuple):
        return ref[0] * (1 - MATCH_TOLERANCE) <= value <= ref[1] * (1 + MATCH_TOLERANCE)
    return abs(value - ref) <= MATCH_TOLERANCE * abs(ref)


def readings_verdict(r: dict) -> str:
    """One line: how many of the paper's numbers the default readings reproduce (within MATCH_TOLERANCE), naming
    each that is not reproduced with its value beside the paper's (``r`` from :func:`paper_readings`)."""
    ch = r["chosen"]
    pl = r["placement"]["rows"][f"{ch['directions']}, {ch['eq23']}"]
    e27 = r["eq27"]["rows"][f"{ch['eq27']}, per test"]
    checks = [("Fig. 9 Y mean max error", pl["Y_mean"], "fig11_Y_um", "um"),
              ("Fig. 10 X mean max error", pl["X_mean"], "fig11_X_um", "um"),
              ("Fig. 11 reduction", pl["reduction"], "reduction", "%"),
              ("Figs. 9-10 difference of the maxima", pl["max_difference"], "max_difference_um", "um"),
              ("Eq. 24 largest u_p at the station", r["eq23"]["readings"][ch["eq23"]]["max"], "station_up_max_um", "um"),
              ("Fig. 13 share of geometry-dominated points", r["initial"]["share_geometry_dominated"],
               "geometry_dominated", "%"),
              ("Eq. 27 mean", e27["mean"], "eq27_mean_um", "um"), ("Eq. 27 sigma", e27["sigma"], "eq27_sigma_um", "um"),
              ("Eq. 27 mean + 2 sigma", e27["bound"], "eq27_bound_um", "um"),
              ("Eq. 27 largest error in 95 % of tests", e27["max_p95"], "eq27_max_um", "um"),
              ("Eq. 27 final / initial", e27["reduction"], "eq27_reduction", "%")]

    def show(v, unit):
        return f"{100 * v:.0f} %" if unit == "%" else f"{v:.3g} µm"

    def paper(key, unit):
        ref = PAPER[key][0]
        if isinstance(ref, tuple):
            return " to ".join(show(x, unit) for x in ref).replace(" µm to", " to").replace(" % to", " to")
        return show(ref, unit)

    # the numbers of one reading stand or fall together: a reading is reproduced only when every number of it matches
    readings = {"placement (Figs. 9-11)": checks[:4], "Eq. 24 at the station": checks[4:5], "Fig. 13": checks[5:6],
                "Eq. 27": checks[6:]}
    ok = {name: matches(v, key) for name, v, key, unit in checks}
    full = [r for r, cs in readings.items() if all(ok[c[0]] for c in cs)]
    strict = sum(len(readings[r]) for r in full)
    missed = [f"{name} {show(v, unit)} (paper {paper(key, unit)})" for name, v, key, unit in checks if not ok[name]]
    text = (f"Verdict: the default readings reproduce {strict} of {len(checks)} of the paper's numbers within "
            f"{100 * MATCH_TOLERANCE:g} %, counting a number only when every number of its reading matches "
            f"({len(full)} of {len(readings)} readings in full: {', '.join(full) or 'none'}); one by one "
            f"{sum(ok.values())} of {len(checks)} match")
    return text + ("; not reproduced: " + "; ".join(missed) + "." if missed else ".")


def station_points(scenario: Scenario) -> np.ndarray:
    """(M, 3) the mesh points at the verification's tool, in the frame of the configured tracker (mm)."""
    return lt.to_tracker(scenario.mesh_points[None], scenario.pose)[0]


def eq23_readings(scenario: Scenario) -> dict:
    """Eq. 24 at the configured station for each reading of Eq. 23, and the correlations Eq. 23 drops.

    u_p (um) at every mesh point with u_theta = u_phi = the configured angular noise; the correlations are those
    of the exact Cartesian covariance (tracker frame), the largest |rho| of each point's three pairs.
    """
    P = station_points(scenario)
    d = scenario.drawn
    um = factor("mm", "um")
    rows = {}
    for reading in EQ23_READINGS:
        up = eq24_point_uncertainty(P, d["tracker.angular"], d["tracker.distance"], d["tracker.distance_per_length"],
                                    d["tracker.angular"], reading) * um
        rows[reading] = {"min": float(up.min()), "mean": float(up.mean()), "sigma": float(up.std(ddof=1)),
                         "max": float(up.max()), "matches": int(matches(float(up.max()), "station_up_max_um"))}
    C = lt.covariance(P, d["tracker.angular"], d["tracker.distance"], d["tracker.distance_per_length"])
    s = np.sqrt(np.einsum("mii->mi", C))
    rho = np.abs(C / (s[:, :, None] * s[:, None, :]))
    worst = np.maximum.reduce([rho[:, 0, 1], rho[:, 0, 2], rho[:, 1, 2]])
    return {"points": len(P), "readings": rows,
            "largest_correlation": {"min": float(worst.min()), "max": float(worst.max())}}


def verification_arrays(scenario: Scenario, trials: int, seed: int | None = None, block: int = 64,
                        weighted: bool = True) -> dict:
    """The run's first ``trials`` verifications simulated again (same streams) and identified with the
    one-phase strategy: per trial and mesh point (um)

    initial (N, M, 3): machine-frame deviation after the pose-only registration (Eq. 1, Figs. 12-13);
    residual (N, M): the fit's residual distance; compensated (N, M): the distance error of the compensated
    machine, rigid part removed (docs/measurand.md); compensated_rigid (N, M): the same, rigid part kept;
    compensated_vectors (N, M, 3): the compensated error's components (machine frame), residual_vectors
    (N, M, 3): the residual's (tracker frame).
    """
    one_tracker(scenario, "the paper's verification figures")
    eng = Engine(scenario, seed=seed, block=block)
    strategy = Strategy.one_phase(weighted=weighted)
    rows = scenario.mesh_rows
    um = factor("mm", "um")
    parts: dict = {k: [] for k in ("initial", "residual", "compensated", "compensated_rigid", "compensated_vectors",
                                   "residual_vectors")}
    for b in range(-(-trials // eng.block)):
        meas, theta_true, _ = eng.simulate(b)
        ident = identify(scenario.id_model, meas, scenario.noise, strategy, chunk=eng.block)
        n = len(meas)
        D = (scenario.truth.machine_points(theta_true)[:, rows]
             - scenario.id_model.machine_points(ident.theta)[:, rows]).reshape(n, -1)
        parts["initial"].append(ident.initial_error[:, rows] * um)
        parts["residual_vectors"].append(ident.residual[:, rows] * um)
        parts["residual"].append(np.linalg.norm(parts["residual_vectors"][-1], axis=-1))
        parts["compensated_vectors"].append((D @ scenario.rigid_free.T).reshape(n, -1, 3) * um)
        parts["compensated"].append(np.linalg.norm(parts["compensated_vectors"][-1], axis=2))
        parts["compensated_rigid"].append(np.linalg.norm(D.reshape(n, -1, 3), axis=2) * um)
    return {k: np.concatenate(v)[:trials] for k, v in parts.items()}


def initial_table(arrays: dict) -> dict:
    """Fig. 13: per mesh point, the geometric (systematic) part of the initial error against the noise.

    geometry: |mean over the trials| of the initial error vector; noise: the RMS 3-D scatter about it."""
    init = arrays["initial"]
    geo = np.linalg.norm(init.mean(axis=0), axis=1)
    noise = np.sqrt(init.var(axis=0, ddof=1).sum(axis=1))
    share = float((geo > noise).mean())
    return {"trials": len(init), "geometry_mean_um": float(geo.mean()), "geometry_max_um": float(geo.max()),
            "noise_mean_um": float(noise.mean()), "ratio_median": float(np.median(geo / noise)),
            "share_geometry_dominated": share, "matches": int(matches(share, "geometry_dominated")),
            "initial_mean_um": float(np.linalg.norm(init, axis=2).mean())}


def normality_table(arrays: dict) -> dict:
    """Figs. 12 and 14: how normal the errors of every point of every verification look, pooled, per component
    (x, y, z) and for the distance: the Kolmogorov-Smirnov distance to the normal of the same mean and sigma.

    The paper: the initial errors do not fit a normal (Fig. 12), the final ones do, "particularly the final
    error in the distance and the error in the Y coordinate" (Fig. 14).  A final row matches once for each of
    the four whose KS distance is below the initial one, and once if the distance and y are its two smallest."""
    from scipy.special import ndtr

    def ks(x):  # the one-sample KS statistic, sup |F_n - F|, against N(mean, sigma) of the sample
        x = np.sort(np.ravel(x))
        n = len(x)
        F = ndtr((x - x.mean()) / x.std(ddof=1))
        return float(max((np.arange(1, n + 1) / n - F).max(), (F - np.arange(n) / n).max()))

    def row(v):
        return {"x": ks(v[..., 0]), "y": ks(v[..., 1]), "z": ks(v[..., 2]), "distance": ks(np.linalg.norm(v, axis=-1))}

    init = row(arrays["initial"])
    rows = {"initial (Fig. 12)": {**init, "matches": None}}
    for name, key in (("compensated (Fig. 14)", "compensated_vectors"), ("residual", "residual_vectors")):
        r = row(arrays[key])
        two = sorted(("x", "y", "z", "distance"), key=r.get)[:2]
        r["matches"] = sum(r[k] < init[k] for k in ("x", "y", "z", "distance")) + int(set(two) == {"y", "distance"})
        rows[name] = r
    n = arrays["initial"].shape[0] * arrays["initial"].shape[1]
    return {"samples": n, "rows": rows, "out_of": 5}


def eq27_table(arrays: dict) -> dict:
    """Eq. 27 (Figs. 14-15) under every reading: per test (the mean over the points of each verification, its
    spread over the verifications) and pooled (every point of every verification as one sample).

    mean, sigma (ddof 1) and mean + 2 sigma (the paper's 23.81 um is 13.77 + 2 x 5.02); max_p95: the 95th
    percentile of each verification's largest point error (the paper: about 50 um in a few tests, below in
    most); max: the largest of all; reduction: the reading's mean over the initial Eq. 27 (pose-only fit)."""
    initial = float(np.linalg.norm(arrays["initial"], axis=2).mean())
    rows = {}
    for reading in EQ27_READINGS:
        e = arrays[reading]
        worst = e.max(axis=1)
        for pooling, sample in (("per test", e.mean(axis=1)), ("pooled", e.ravel())):
            mu, sd = float(sample.mean()), float(sample.std(ddof=1))
            row = {"mean": mu, "sigma": sd, "bound": mu + 2 * sd, "max_p95": float(np.percentile(worst, 95)),
                   "max": float(worst.max()), "reduction": mu / initial}
            row["matches"] = sum(matches(row[k], p) for k, p in (
                ("mean", "eq27_mean_um"), ("sigma", "eq27_sigma_um"), ("bound", "eq27_bound_um"),
                ("max_p95", "eq27_max_um"), ("reduction", "eq27_reduction")))
            rows[f"{reading}, {pooling}"] = row
    return {"trials": len(arrays["initial"]), "initial_mean_um": initial, "rows": rows, "out_of": 5}


def placement_row(res: dict) -> dict:
    """The paper's Fig. 9-11 numbers of one placement study (um, the reduction as a fraction)."""
    y, x = res["directions"]["Y"]["max_error_um"], res["directions"]["X"]["max_error_um"]
    row = {"tests": len(y), "Y_mean": float(y.mean()), "Y_sigma": float(y.std(ddof=1)), "Y_max": float(y.max()),
           "X_mean": float(x.mean()), "X_sigma": float(x.std(ddof=1)), "X_max": float(x.max()),
           "reduction": float(1 - x.mean() / y.mean()), "max_difference": float(y.max() - x.max())}
    row["matches"] = sum(matches(row[k], p) for k, p in (("Y_mean", "fig11_Y_um"), ("X_mean", "fig11_X_um"),
                                                         ("reduction", "reduction"), ("max_difference", "max_difference_um")))
    return row


def _variant(scenario: Scenario, angular_factor: float) -> Scenario:
    """The scenario with the tracker's angular noise (mean and spread, drawn and stated) scaled."""
    import copy

    from .config import parse_config
    from .scenario import build_scenario
    from .units import Q_

    raw = copy.deepcopy(scenario.config.source)
    tn = raw.setdefault("sources", {}).setdefault("tracker_noise", {})
    a = Q_(raw["tracker"]["angular"]) * angular_factor
    raw["tracker"]["angular"] = f"{a.to('urad').magnitude:.6g} urad"
    tn["angular_mean"] = raw["tracker"]["angular"]
    if "angular_sd" in tn:
        tn["angular_sd"] = f"{(Q_(tn['angular_sd']) * angular_factor).to('urad').magnitude:.6g} urad"
    return build_scenario(parse_config(raw, scenario.config.path), sources=[s.name for s in scenario.sources])


def paper_readings(scenario: Scenario, trials: int = 1000, tests: int = 5_000, sensitivity_trials: int = 256,
                   seed: int | None = None, sensitivity: bool = True, block: int = 64) -> dict:
    """Every reading of the paper's figures side by side, with the configured defaults, and a sensitivity table.

    trials: verifications simulated again for Eq. 27 and Fig. 13 (the run's first, same streams); tests:
    placement tests per direction for each reading of Figs. 9-11 and each row of the sensitivity table, whose
    verifications are the smaller count ``sensitivity_trials`` (both stated in the result).  seed, block: those
    of the run whose verifications are simulated again (a block draws from its own random stream)."""
    one_tracker(scenario, "the readings of the paper's figures")
    seed = scenario.config.seed if seed is None else seed
    chosen = study_readings(scenario)
    out: dict = {"chosen": chosen, "match_tolerance": MATCH_TOLERANCE,
                 "paper": {k: v[1] for k, v in PAPER.items()}}
    out["placement"] = {"tests": tests, "rows": {}}
    for d in PLACEMENT_READINGS:
        for e in EQ23_READINGS:
            out["placement"]["rows"][f"{d}, {e}"] = placement_row(placement(scenario, tests, seed, directions=d, eq23=e,
                                                                                      fits=False))
    out["eq23"] = eq23_readings(scenario)
    arrays = verification_arrays(scenario, trials, seed, block)
    out["initial"] = initial_table(arrays)
    out["normality"] = normality_table(arrays)
    out["eq27"] = eq27_table(arrays)
    if sensitivity:
        out["sensitivity"] = sensitivity_table(scenario, sensitivity_trials, tests, seed, chosen,
                                               out["placement"]["rows"], arrays, block)
    return out


def sensitivity_table(scenario: Scenario, trials: int, tests: int, seed: int, chosen: dict, placement_rows: dict,
                      arrays: dict, block: int = 64) -> dict:
    """How each paper number moves with the placement geometry, the Eq. 23 reading, the weighting and the
    tracker's angular noise: one change at a time from the chosen readings, on the same random streams.

    placement_rows, arrays: the readings already computed (:func:`paper_readings`); the rows of the geometry and
    the Eq. 23 reading are theirs, the verification columns of the chosen readings their first ``trials``."""
    def verification(arr):
        t = eq27_table(arr)["rows"][f"{chosen['eq27']}, per test"]
        return {"eq27_mean": t["mean"], "eq27_sigma": t["sigma"], "eq27_max_p95": t["max_p95"]}

    def place(r):
        return {"Y_mean": r["Y_mean"], "X_mean": r["X_mean"], "reduction": r["reduction"]}

    none_v = {"eq27_mean": None, "eq27_sigma": None, "eq27_max_p95": None}
    rows = {"chosen readings": {**place(placement_rows[f"{chosen['directions']}, {chosen['eq23']}"]),
                                **verification({k: v[:trials] for k, v in arrays.items()})}}
    for d in PLACEMENT_READINGS:
        if d != chosen["directions"]:
            rows[f"directions = {d}"] = {**place(placement_rows[f"{d}, {chosen['eq23']}"]), **none_v}
    for e in EQ23_READINGS:
        if e != chosen["eq23"]:
            rows[f"eq23 = {e}"] = {**place(placement_rows[f"{chosen['directions']}, {e}"]), **none_v}
    rows["plain least squares"] = {"Y_mean": None, "X_mean": None, "reduction": None,
                                   **verification(verification_arrays(scenario, trials, seed, block, weighted=False))}
    for f in (0.5, 1.5):
        sc = _variant(scenario, f)
        rows[f"angular noise x {f:g}"] = {
            **place(placement_row(placement(sc, tests, seed, directions=chosen["directions"], eq23=chosen["eq23"], fits=False))),
            **verification(verification_arrays(sc, trials, seed, block))}
    return {"trials": trials, "tests": tests, "rows": rows,
            "note": "the change does not reach this number (the verification uses the configured station; "
                    "the weighting acts on the verification only)"}


def one_tracker(scenario: Scenario, what: str):
    """The paper's studies are of one tracker: a configuration with [[stations]] is refused in one line."""
    if scenario.stations:
        raise ConfigError(f"{scenario.config.where('stations')}: {what}: the paper's one tracker only; for "
                          "[[stations]] use `mtbudget study stations` (one station against all) or `mtbudget run`")


def station_variants(config) -> list:
    """The verification of ``config`` ([[stations]]) from its first laser tracker alone and from all its stations: the same
    machine (the same generation functions and seed), the same plan per station, the same sources.  Returns
    [(label, SimulationConfig)]."""
    from dataclasses import replace

    if len(config.stations) < 2:
        raise ConfigError(f"{config.where('stations')}: the comparison needs at least two [[stations]] (it runs the "
                          f"first laser tracker alone and all of them); this configuration has {len(config.stations)}")
    first = next((i for i, st in enumerate(config.stations) if st.kind == "xyz"), None)
    if first is None:
        raise ConfigError(f"{config.where('stations')}: the comparison runs one laser tracker (kind = \"xyz\") against "
                          "all the stations; these are all interferometers, and one cannot locate a point alone")
    out = []
    for keep in ([first], list(range(len(config.stations)))):
        src = dict(config.source)
        src["stations"] = [list(config.source.get("stations", []))[i] for i in keep]
        k = len(keep)
        out.append((f"{k} station{'s' if k > 1 else ''}",
                    replace(config, stations=[config.stations[i] for i in keep], source=src)))
    return out


def stations_comparison(config, trials: int = 256, attribution_trials: int = 64, seed: int | None = None,
                        progress: bool = False) -> dict:
    """The per-point uncertainty of the compensated machine verified from one station and from several, side by
    side (issue 20; the paper's Section 2.2.3 leaves it open): each variant of :func:`station_variants` is one
    Monte Carlo run of the engine (same seed), with its budget when ``attribution_trials`` > 0.  Per point and axis:
    u (k = 1) of each variant and their ratio; per variant the volume summaries and the budget by group."""
    from .report import in_frame, measurand_at_tool, points_summary
    from .runner import run

    variants = []
    for label, cfg in station_variants(config):
        if progress:
            from .progress import note

            note(f"verification from {label}: {trials} trials ...", True)
        res = run(cfg, trials=trials, attribution_trials=attribution_trials, seed=seed, progress=progress)
        pts = res.points()
        u = np.array([p["u"]["value"] for p in pts])
        pb = (res.budget or {}).get("points") or {}
        out = res.outputs()["compensation_rms"]
        variants.append({"label": label, "kinds": ", ".join(st.kind for st in cfg.stations),
                         "stations": [{"kind": st.kind, "description": st.description}
                                                      for st in cfg.stations],
                         "trials": res.acc.n, "u": u, "summary": points_summary(pts),
                         "compensation_rms": {"mean": out["mean"], "std": out["std"], "unit": out["unit"]},
                         "not_converged": res.not_converged,
                         "budget_groups": pb.get("groups"), "budget_rows": pb.get("rows"),
                         "interaction_share": pb.get("interaction_share")})
    one, many = variants[0]["u"], variants[-1]["u"]
    text = in_frame(measurand_at_tool(res.spec.get("measurand")), res)  # five-axis: the table's frame (measurand.md)
    return {"measurand": text + "; u is the standard uncertainty (k = 1) from the Monte Carlo",
            "unit": "um", "commanded": [p["nominal"]["value"] for p in pts], "variants": variants,
            **({"angles": [p["angles"] for p in pts]} if pts and "angles" in pts[0] else {}),
            "ratio": many / one, "ratio_median": np.median(many / one, axis=0).tolist(),
            "ratio_max": (many / one).max(axis=0).tolist()}


def station_information(scenario: Scenario, stations: list) -> tuple[np.ndarray, np.ndarray]:
    """What each candidate station tells the identification about the machine: the reduced information matrix of the
    identification model's parameters (scaled: um, urad) from that station measuring the whole plan, its own unknowns
    (an xyz station's pose, a range station's position and dead path) eliminated (Schur complement).  Stations'
    own unknowns are separate, so the information of a set of stations is the sum of its members' (the
    identification over all of them at once, :func:`mtbudget.multistation.identify_stations`, linearised at the
    noise-free verification).

    stations: [(kind, place)] with place a pose (6,) for "xyz" or a position (3,) for "range", mm and rad, or
    [(kind, place, noise)] with noise a dict of the station's own "angular", "distance", "distance_per_length" (any
    missing or None: the verification's); :func:`configured_candidates` gives a configuration's [[stations]].
    Returns (R (K, p, p), the field Jacobian with the rigid part removed (3 M0, p), scaled)."""
    from .identify import scale_vector, whitener

    sc = scenario
    model = sc.id_model
    rows = np.flatnonzero(sc.row_station == sc.stations[0].id) if sc.stations else np.arange(len(sc.plan))
    P, J = model.machine_points(np.zeros((1, model.n_params)), jacobian=True)
    sv = scale_vector(model)
    P, J = P[0][rows], J[0][rows] / sv  # (M, 3), (M, 3, p) per um / urad
    out = []
    for cand in stations:
        kind, place = cand[0], np.asarray(cand[1], float)
        own = cand[2] if len(cand) > 2 else {}
        noise = SimpleNamespace(**{k: own.get(k) if own.get(k) is not None else getattr(sc.noise, k)
                                   for k in ("angular", "distance", "distance_per_length", "repeatability")})
        if kind == "xyz":
            R = lt.rotation(*place[3:])
            P_LT = (P - place[:3]) @ R
            C = lt.covariance(P_LT, noise.angular, noise.distance, noise.distance_per_length)
            W = whitener(C + noise.repeatability**2 * np.eye(3))  # (M, 3, 3)
            A_t = np.einsum("mij,jk,mkp->mip", W, R.T, J).reshape(-1, J.shape[-1])
            A_s = np.einsum("mij,mjk->mik", W, lt.pose_jacobian(P[None], place[None])[0]).reshape(-1, 6)
        elif kind == "range":
            d = P - place[:3]
            r = np.sqrt((d * d).sum(axis=1))
            u = d / r[:, None]
            w = 1.0 / np.sqrt((noise.distance + noise.distance_per_length * r) ** 2 + noise.repeatability**2)
            A_t = w[:, None] * np.einsum("mi,mip->mp", u, J)
            A_s = w[:, None] * np.column_stack([-u, np.ones(len(r))])
        else:
            raise ConfigError(f"unknown station kind {kind!r}; expected 'xyz' or 'range'")
        Ntt, Nts, Nss = A_t.T @ A_t, A_t.T @ A_s, A_s.T @ A_s
        out.append(Ntt - Nts @ np.linalg.solve(Nss, Nts.T))
    _, Jf = sc.evaluate(model, np.zeros((1, model.n_params)), jacobian=True)
    Jf = sc.rigid_free @ (Jf[0].reshape(-1, model.n_params) / sv)
    return np.array(out), Jf


#: an eigenvalue of the information below this fraction of the largest one of all candidates together is a
#: direction the identification does not see (relative to the parameters in um and urad)
RANK_TOL = 1e-9


def set_uncertainty(info: np.ndarray, Jf: np.ndarray, rank_tol: float = RANK_TOL,
                    prior: np.ndarray | None = None) -> np.ndarray:
    """u (M0, 3) of the compensated machine's error per point and axis (mm: the field Jacobian's unit, parameters
    scaled) from the summed information ``info`` (p, p) of a set of stations: the parameters' covariance is its
    pseudo-inverse on the directions the set identifies (what it cannot see is held, as the identification holds
    it, and does not show at the verification's tool).  prior: (3 M0,) mm^2 added to every variance, what the
    verification cannot identify at a [measurand] tool it did not use (:func:`unidentified_variance`)."""
    lam, V = np.linalg.eigh(info)
    keep = lam > rank_tol * lam.max()
    G = Jf @ V[:, keep]
    var = (G * G / lam[keep]).sum(axis=1)
    if prior is not None:
        var = var + prior
    return np.sqrt(var).reshape(-1, 3)


def unidentified_variance(scenario: Scenario) -> np.ndarray | None:
    """At a [measurand] tool the verification did not use: the variance (3 M0,) mm^2 of what it cannot identify
    there, from the prior of the generation functions (as :func:`mtbudget.budget.point_lpu` and the Monte Carlo's
    source unidentified_at_tool); None at the verification's tool."""
    m = scenario.context.measurand
    if m is None:
        return None
    field = m["unidentified_field"][:, scenario.mesh_rows]
    G = scenario.rigid_free @ field.reshape(field.shape[0], -1).T
    return (G * G).sum(axis=1)


def configured_candidates(config) -> list:
    """A configuration's [[stations]] as candidates of :func:`station_information`, with their own noise."""
    return [(st.kind, st.pose if st.kind == "xyz" else st.position,
             {"angular": st.angular, "distance": st.distance, "distance_per_length": st.distance_per_length})
            for st in config.stations]


def ring_candidates(scenario: Scenario, n: int, kind: str, radius: float, height: float,
                    noise: dict | None = None) -> list:
    """``n`` candidate stations evenly around the mesh centre at ``radius`` (mm) from it: xyz stations on a horizontal
    circle ``height`` (mm) above the centre, upright (a = b = 0) and facing it; range stations alternately ``height``
    above and below it (ranges from one plane cannot resolve the direction across it)."""
    c = scenario.mesh_points.mean(axis=0)
    out = []
    for k in range(n):
        phi = 2 * np.pi * k / n
        h = height if kind == "xyz" or k % 2 == 0 else -height
        pos = c + np.array([radius * np.cos(phi), radius * np.sin(phi), h])
        out.append((kind, np.concatenate([pos, [0.0, 0.0, phi + np.pi]]) if kind == "xyz" else pos, dict(noise or {})))
    return out


def _candidate_noise(scenario: Scenario, cand) -> dict:
    """The standard uncertainties (k = 1) a candidate is ranked with, in display units."""
    own = cand[2] if len(cand) > 2 else {}
    get = {k: own.get(k) if own.get(k) is not None else getattr(scenario.noise, k)
           for k in ("angular", "distance", "distance_per_length")}
    out = {"distance_um": get["distance"] * 1e3, "distance_per_length_um_per_m": get["distance_per_length"] * 1e6}
    if cand[0] == "xyz":
        out["angular_urad"] = get["angular"] * 1e6
    return out


def _check_candidates(scenario: Scenario, candidates: list):
    """Every candidate at least the tracker's shortest range ([placement] range_min) from every measured point."""
    s = placement_settings(scenario, tests=1)
    pts = scenario.mesh_points
    for i, cand in enumerate(candidates):
        d = float(np.sqrt(((pts - np.asarray(cand[1], float)[:3]) ** 2).sum(axis=1)).min())
        if not d >= s.range_min:
            raise ConfigError(f"candidate station {i} stands {d:.0f} mm from a measured point, closer than the "
                              f"shortest range {s.range_min:.0f} mm ([placement] range_min): a larger circle, or "
                              "another height", key="--radius")


def station_placement(scenario: Scenario, candidates: list, k_max: int = 4, progress: bool = False) -> dict:
    """Which set of stations minimises the per-point uncertainty of the compensated machine (issue 20): every subset
    of 1 .. ``k_max`` of the ``candidates`` ([(kind, place)], see :func:`station_information`), ranked by the largest u
    over the mesh points and axes (k = 1), from the identification's covariance linearised at the noise-free
    verification (the GUF of docs/measurand.md: the stated tracker noise and repeatability; what else the Monte
    Carlo draws is not in it).  Returns per k the best and worst set and the spread over all sets."""
    from itertools import combinations

    if not 1 <= k_max <= len(candidates):
        raise ConfigError(f"the number of stations must be between 1 and the {len(candidates)} candidates, got {k_max}",
                          key="--stations")
    t0 = time.perf_counter()
    _check_candidates(scenario, candidates)
    info, Jf = station_information(scenario, candidates)
    prior = unidentified_variance(scenario)
    um = factor("mm", "um")
    # what every candidate together identifies: a set that sees less (a lone range station) identifies too little
    lam_all = np.linalg.eigvalsh(info.sum(axis=0))
    tol = RANK_TOL * lam_all.max()
    full = int(np.count_nonzero(lam_all > tol))
    per_k = []
    for k in range(1, k_max + 1):
        sets = list(combinations(range(len(candidates)), k))
        worst_u = np.full(len(sets), np.inf)
        rms_u = np.full((len(sets), 3), np.inf)
        bar = progress_bar(len(sets), f"sets of {k} station(s)", "set", progress)
        for i, idx in enumerate(sets):
            N = info[list(idx)].sum(axis=0)
            if np.count_nonzero(np.linalg.eigvalsh(N) > tol) == full:
                u = set_uncertainty(N, Jf, tol / np.linalg.eigvalsh(N).max(), prior) * um
                worst_u[i] = u.max()
                rms_u[i] = np.sqrt((u**2).mean(axis=0))
            bar.update(1)
        bar.close()
        ok = np.isfinite(worst_u)
        row = {"stations": k, "sets": len(sets), "identifying": int(ok.sum())}
        if ok.any():
            best = int(np.argmin(worst_u))
            worst = int(np.argmax(np.where(ok, worst_u, -np.inf)))
            row.update({"best": list(sets[best]), "best_max_u": float(worst_u[best]), "best_rms_u": rms_u[best].tolist(),
                        "worst": list(sets[worst]), "worst_max_u": float(worst_u[worst]),
                        "median_max_u": float(np.median(worst_u[ok])),
                        "best_u": set_uncertainty(info[list(sets[best])].sum(axis=0), Jf,
                                                  tol / np.linalg.eigvalsh(info[list(sets[best])].sum(axis=0)).max(),
                                                  prior) * um})
        per_k.append(row)
    return {"measurand": "largest standard uncertainty (k = 1) over the mesh points and axes of the compensated "
                         "machine's error (docs/measurand.md), GUF: the identification covariance from the stated "
                         "tracker noise and repeatability, linearised at the noise-free verification",
            "unit": "um", "candidates": [{"kind": c[0], "place": np.asarray(c[1], float).tolist(),
                                          "noise": _candidate_noise(scenario, c)} for c in candidates],
            "per_k": per_k, "seconds": time.perf_counter() - t0, "mesh_points": scenario.mesh_points}


def main(argv: list | None = None) -> int:
    """``python -m mtbudget.study [CONFIG]``: the side-by-side tables alone (what ``study all`` ends with)."""
    import sys

    from .config import load_config
    from .report_study import readings_text
    from .scenario import build_scenario

    args = sys.argv[1:] if argv is None else argv
    try:
        r = paper_readings(build_scenario(load_config(args[0] if args else None)))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(readings_text(r))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
