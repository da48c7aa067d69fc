"""Calibration of `mtbudget diagnose` on concealed, simulated recordings: the detection table of docs/diagnose.md.

Run:  python benchmarks/calibrate_diagnose.py [--cases 100]

Each case: a machine with random geometric errors larger than the effect, a
tracker at a random pose, drifting and cycling temperatures, the example
recordings' noise, and zero, one or two hidden effects at a multiple of the
point noise. Written and read back as a recording (some in inch, minutes and
degF).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

from mtbudget.testing import named, named_or_confounded, run_case
from mtbudget.plugins import default_host

SINGLE = [("thermal_expansion", "x"), ("thermal_expansion", "y"), ("thermal_expansion", "z"), ("reversal", "x"),
          ("reversal", "y"), ("reversal", "z"), ("tracker_drift", None), ("axis_coupling", "xy"),
          ("air_temperature_drift", None), ("tracker_range_offset", None)]
PAIRS = [(("thermal_expansion", "x"), ("reversal", "y")), (("tracker_drift", None), ("reversal", "x")),
         (("thermal_expansion", "y"), ("axis_coupling", "xy"))]


def label(e):
    return e[0] + (f"[{e[1]}]" if e[1] else "")


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--multiple", type=float, default=2.5)
    args = ap.parse_args()
    cands = default_host().candidates()
    n = args.cases
    t0 = time.time()
    claims, what = 0, Counter()
    for seed in range(n):
        d, _ = run_case(20_000 + seed, (), candidates=cands)
        if d.findings:
            claims += 1
            what.update(label(e) for e in named(d))
    print(f"| no effect | {n} | claimed an effect in {claims} ({claims / n:.0%}) {dict(what) or ''} |")
    print()
    print(f"| hidden effect ({args.multiple} x noise) | cases | named alone | named or declared confounded | other claims |")
    print("| --- | --- | --- | --- | --- |")
    for eff in SINGLE:
        alone = conf = 0
        other = Counter()
        for seed in range(n):
            d, _ = run_case(30_000 + seed, (eff,), args.multiple, imperial=seed % 4 == 0, candidates=cands)
            nm = named(d)
            alone += nm == {eff}
            conf += eff in named_or_confounded(d)
            other.update(label(e) for e in nm - {eff})
        print(f"| {label(eff)} | {n} | {alone / n:.0%} | {conf / n:.0%} | {', '.join(f'{k} {v}' for k, v in other.most_common(3)) or '-'} |")
    print()
    print("| hidden pair (3 x noise) | cases | both named (or confounded) |")
    print("| --- | --- | --- |")
    for pair in PAIRS:
        hits = sum(set(pair) <= named_or_confounded(run_case(40_000 + s, pair, 3.0, imperial=s % 2 == 0, candidates=cands)[0])
                   for s in range(n // 2))
        print(f"| {' + '.join(label(e) for e in pair)} | {n // 2} | {hits / (n // 2):.0%} |")
    print(f"\n({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
