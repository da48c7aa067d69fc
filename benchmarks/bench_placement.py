"""The placement study (paper Figs. 9-11): vectorised implementation vs the test-by-chunk original.

Run:  python benchmarks/bench_placement.py [--tests 10000] [--full 100000]

Both arms draw the same numbers (same seed, same draws in the same order) on the built-in default
configuration; the benchmark refuses to report a time unless every test's best station and maximum
error are identical, bit for bit.  The original is the placement loop as it was before the
vectorisation (commit 70b5602), copied here as the reference.  ``--full`` then times the study at
the paper's size (10^5 tests per direction, 32 candidate stations) with the current implementation
alone (the original takes about 10x longer).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mtbudget import tracker as lt
from mtbudget.config import load_config
from mtbudget.plan import mesh
from mtbudget.scenario import build_scenario
from mtbudget.study import placement, placement_settings


def reference(scenario, tests, seed=None, chunk=2000):
    """The original placement loop (commit 70b5602): per direction, best station and its maximum u_p (um)."""
    cfg = scenario.config
    s = placement_settings(scenario, tests)
    pts = mesh(cfg.mesh_ranges, cfg.mesh_step) + np.asarray(cfg.tools[0])[None, :]
    ss = np.random.SeedSequence(cfg.seed if seed is None else seed)

    def visible(station):
        d = pts[None, :, :] - station[:, None, :]
        r = np.linalg.norm(d, axis=2)
        el = np.arcsin(np.clip(d[..., 2] / r, -1, 1))
        inside = np.all((station >= s.envelope_low) & (station <= s.envelope_high), axis=1)
        return (r.min(1) >= s.range_min) & (r.max(1) <= s.range_max) & (np.abs(el).max(1) <= s.elevation_max) & ~inside

    out = {}
    for sp, child in zip(s.spaces, ss.spawn(len(s.spaces))):
        best_loc, best_err = np.empty((s.tests, 3)), np.empty(s.tests)
        rng = np.random.default_rng(child)
        for lo in range(0, s.tests, chunk):
            n = min(chunk, s.tests - lo)
            ua = np.abs(rng.normal(s.angular_mean, s.angular_sd, (n, 2)))
            st = rng.uniform(sp.low, sp.high, (n, s.candidates, 3))
            ok = visible(st.reshape(-1, 3)).reshape(n, s.candidates)
            d = pts[None, None] - st[:, :, None, :]
            up = lt.point_uncertainty(d, ua[:, None, None, 0], s.distance, s.distance_per_length, ua[:, None, None, 1])
            worst = up.max(axis=2)
            worst[~ok] = np.inf
            k = worst.argmin(axis=1)
            rows = np.arange(n)
            best_err[lo:lo + n] = worst[rows, k] * 1e3
            best_loc[lo:lo + n] = st[rows, k]
        good = np.isfinite(best_err)
        out[sp.name] = (best_loc[good], best_err[good])
    return out


def timed(f, *a, **k):
    t = time.perf_counter()
    r = f(*a, **k)
    return time.perf_counter() - t, r


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tests", type=int, default=10000, help="tests per direction for the comparison")
    ap.add_argument("--full", type=int, default=100000, help="tests per direction for the full-size run (0: skip)")
    args = ap.parse_args()
    scenario = build_scenario(load_config())
    s = placement_settings(scenario, args.tests)

    t_new, new = timed(placement, scenario, tests=args.tests)
    t_ref, ref = timed(reference, scenario, args.tests)
    for name, (loc, err) in ref.items():
        d = new["directions"][name]
        same = np.array_equal(d["best_location"], loc) and np.array_equal(d["max_error_um"], err)
        assert same, f"direction {name}: the vectorised study does not reproduce the original"
    print(f"identical, bit for bit: best station and maximum error of every test, both directions "
          f"({args.tests} tests each, {s.candidates} candidate stations)")
    print(f"original:   {t_ref:7.2f} s  ({t_ref / (2 * args.tests) * 1e6:.0f} us per test)")
    print(f"vectorised: {new['seconds']:7.2f} s  ({new['seconds'] / (2 * args.tests) * 1e6:.0f} us per test); "
          f"{t_new - new['seconds']:.2f} s more for the distribution fits")
    print(f"ratio:      {t_ref / new['seconds']:.1f}x")
    if args.full:
        t_full, full = timed(placement, scenario, tests=args.full)
        per_dir = full["seconds"] / len(full["directions"])
        print(f"\nfull size, {args.full} tests x {s.candidates} candidates per direction: {full['seconds']:.2f} s for "
              f"{len(full['directions'])} directions ({per_dir:.2f} s per direction), "
              f"{t_full - full['seconds']:.2f} s more for the distribution fits")


if __name__ == "__main__":
    main()
