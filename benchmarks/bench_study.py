"""Speed of the Monte Carlo engine on the paper configuration: batched blocks vs one trial at a time.

Run:  python benchmarks/bench_study.py

Both arms run the same engine code on the same configuration in this run;
"one trial at a time" uses blocks of one trial (what a per-trial loop would do),
the batched arm the default 64-trial blocks. Results per trial are identical
in distribution (different blocks draw different streams).
"""

import time

from mtbudget.config import load_config
from mtbudget.runner import run


def per_trial(trials, block):
    cfg = load_config()
    t = time.perf_counter()
    run(cfg, trials=trials, block=block, attribution_trials=0)
    return (time.perf_counter() - t) / trials


def main():
    batched = min(per_trial(512, 64) for _ in range(2))
    single = min(per_trial(48, 1) for _ in range(2))
    print(f"batched (64 per block): {batched * 1e3:.2f} ms/trial ({1 / batched:.0f} trials/s)")
    print(f"one trial at a time:    {single * 1e3:.2f} ms/trial ({1 / single:.0f} trials/s)")
    print(f"ratio: {single / batched:.1f}x")


if __name__ == "__main__":
    main()
