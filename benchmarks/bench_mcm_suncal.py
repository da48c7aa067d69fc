"""mtbudget.mcm.propagate vs Sandia's suncal on JCGM 101 9.4 and 9.5, 10^6 trials each, same run.

Run:  python -m pip install suncal && python benchmarks/bench_mcm_suncal.py

Each arm is timed from the inputs to the estimate, the standard uncertainty and the probabilistically
symmetric 95 % (9.5: 99 %) coverage interval (mtbudget: ``propagate``, then ``estimate``,
``std_uncertainty`` and ``interval()``; suncal: ``monte_carlo``, which computes its mean and standard
deviation, then ``expand(conf=p)``); both must agree on all three within Monte Carlo noise before a time is
reported.  Best of 3 (``--repeat``), the two arms alternating, same run.  Under load, ``--rounds K`` repeats
the whole comparison K times and prints every round with the load average (the ratio moves with what else runs
on the machine).  ``--threads 1`` draws mtbudget's inputs one after the other (``mcm.DRAW_THREADS``: what is
left when the other core is busy); ``--burner`` keeps one other core busy (a ``while True: pass`` process,
ended by its id at the end) to measure a busy machine.
"""

import argparse
import math
import os
import subprocess
import sys
import time


from mtbudget import ureg
from mtbudget.distributions import Arcsine, CurvilinearTrapezoid, Normal, Rectangular, StudentT
from mtbudget import mcm
from mtbudget.mcm import propagate

M = 1_000_000
nm, degC, perK = ureg.nm, ureg.delta_degC, ureg("1/K").units


def best_times(fns, repeat):
    """Best time and last result of each function, the functions run in turn (ours, theirs, ours, ...)."""
    outs, best = [None] * len(fns), [math.inf] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            t = time.perf_counter()
            outs[i] = fn()
            best[i] = min(best[i], time.perf_counter() - t)
    return list(zip(best, outs))


def case_94():
    from suncal import Model

    u, x1 = 0.005, 0.010

    def ours():
        r = propagate(lambda X1, X2: X1**2 + X2**2, {"X1": Normal(x1, u), "X2": Normal(0.0, u)}, trials=M, seed=1)
        return r.estimate.magnitude, r.std_uncertainty.magnitude, tuple(float(q.magnitude) for q in r.interval())

    def theirs():
        m = Model("f = x1**2 + x2**2")
        m.var("x1").measure(x1).typeb(dist="normal", std=u)
        m.var("x2").measure(0.0).typeb(dist="normal", std=u)
        r = m.monte_carlo(samples=M)
        e = r.expand("f", conf=0.95)
        return r.expected["f"], r.uncertainty["f"], (float(e.low), float(e.high))

    return "9.4 comparison loss (x1 = 0.010)", ours, theirs, 1.0, 0.95


def case_95():
    from suncal import Model

    def ours():
        def L(Ls, D1, D2, D3, a_s, th, De, da, dth):
            theta = th + De
            return ((Ls * (1 + a_s * (theta - dth)) + D1 + D2 + D3) / (1 + (a_s + da) * theta) - 50_000_000 * nm).to(nm)

        r = propagate(L, {
            "Ls": StudentT(50_000_623.6 * nm, 25 * nm, 18), "D1": StudentT(215 * nm, 5.8 * nm, 24),
            "D2": StudentT(0 * nm, 3.9 * nm, 5), "D3": StudentT(0 * nm, 6.7 * nm, 8),
            "a_s": Rectangular(9.5e-6 * perK, 13.5e-6 * perK), "th": Normal(-0.1 * degC, 0.2 * degC),
            "De": Arcsine(-0.5 * degC, 0.5 * degC), "da": CurvilinearTrapezoid(-1e-6 * perK, 1e-6 * perK, 0.1e-6 * perK),
            "dth": CurvilinearTrapezoid(-0.05 * degC, 0.05 * degC, 0.025 * degC)}, coverage=0.99, trials=M, seed=2)
        return r.estimate.to(nm).magnitude, r.std_uncertainty.to(nm).magnitude, tuple(float(q.to(nm).magnitude) for q in r.interval())

    def theirs():
        m = Model("f = (Ls*(1 + a_s*(th + De - dth)) + D1 + D2 + D3)/(1 + (a_s + da)*(th + De)) - 50000000")
        # suncal's 't' takes the standard deviation of the t-distributed input: scale * sqrt(df/(df-2))
        for name, val, scale, df in (("Ls", 50_000_623.6, 25, 18), ("D1", 215, 5.8, 24), ("D2", 0, 3.9, 5), ("D3", 0, 6.7, 8)):
            m.var(name).measure(val).typeb(dist="t", std=scale * math.sqrt(df / (df - 2)), df=df)
        m.var("a_s").measure(11.5e-6).typeb(dist="uniform", a=2e-6)
        m.var("th").measure(-0.1).typeb(dist="normal", std=0.2)
        m.var("De").measure(0.0).typeb(dist="arcsine", a=0.5)
        m.var("da").measure(0.0).typeb(dist="curvtrap", a=1e-6, d=0.1e-6)
        m.var("dth").measure(0.0).typeb(dist="curvtrap", a=0.05, d=0.025)
        r = m.monte_carlo(samples=M)
        e = r.expand("f", conf=0.99)
        return r.expected["f"], r.uncertainty["f"], (float(e.low), float(e.high))

    return "9.5 gauge block", ours, theirs, 1.0, 0.99


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3, help="best of this many runs per arm")
    ap.add_argument("--rounds", type=int, default=1, help="repeat the whole comparison (under load)")
    ap.add_argument("--threads", type=int, default=mcm.DRAW_THREADS, help="mtbudget's drawing threads (mcm.DRAW_THREADS)")
    ap.add_argument("--burner", action="store_true", help="keep one other core busy during the measurement")
    args = ap.parse_args()
    mcm.DRAW_THREADS = args.threads
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.burner else None
    try:
        print(f"threads {args.threads}, burner {'on' if burner else 'off'}, best of {args.repeat}")
        print("| round | load 1 min | case | mtbudget s | suncal s | ratio | mean (ours, suncal) | u (ours, suncal) "
              "| interval (ours; suncal) |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for k in range(args.rounds):
            for make in (case_94, case_95):
                name, ours, theirs, _, p = make()
                (t_ours, (y_o, u_o, (lo, hi))), (t_theirs, (y_s, u_s, (lo_s, hi_s))) = best_times([ours, theirs], args.repeat)
                assert abs(y_o - y_s) < 5 * u_o / math.sqrt(M) * 1.5 + 1e-12, (y_o, y_s)
                assert abs(u_o - u_s) / u_o < 0.01, (u_o, u_s)
                assert abs(lo - lo_s) < 0.02 * (hi - lo) and abs(hi - hi_s) < 0.02 * (hi - lo), (lo, hi, lo_s, hi_s)
                print(f"| {k + 1} | {os.getloadavg()[0]:.2f} | {name} | {t_ours:.4f} | {t_theirs:.4f} | {t_theirs / t_ours:.2f}x | "
                      f"{y_o:.6g}, {float(y_s):.6g} | {u_o:.4g}, {float(u_s):.4g} | {lo:.5g}, {hi:.5g}; {lo_s:.5g}, "
                      f"{hi_s:.5g} |", flush=True)
    finally:
        if burner is not None:
            burner.kill()
            burner.wait()


if __name__ == "__main__":
    main()
