"""What `mtbudget run` tells the user about its own conditions: an adaptive run stopped at its limit (what did not
stabilise, by how much, and what to do), which executor ran the trials, options that cannot apply together, and the
shortest interval of a run that histograms its values (how it was found)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import optimize, stats

from mtbudget.cli import main
from mtbudget.config import load_config
from mtbudget.report import budget_text, result_json, run_report
from mtbudget.runner import execute, replay, run
from mtbudget.stats import VectorHistogram

SMALL = Path(__file__).parent / "data" / "small.toml"


@pytest.fixture(scope="module")
def small():
    return load_config(SMALL)


# ------------------------------------------------------------------ the shortest interval from a histogram
def _filled(dist, n=10**6, seed=1):
    """A histogram (ranged from 64 of the values, as a run ranges it from its first block) of the n quantiles of
    ``dist`` at (i + 1/2)/n: its empirical distribution is the distribution itself, to 1/n."""
    v = dist.ppf((np.arange(n) + 0.5) / n)
    h = VectorHistogram(v[np.random.default_rng(seed).choice(n, 64)][:, None])
    h.add(v[:, None])
    return h


def test_the_histograms_shortest_interval_of_a_gamma_is_its_closed_form():
    """Gamma(3): the shortest 95 % interval [a, b] has f(a) = f(b) and F(b) - F(a) = 0.95, solved here by scipy."""
    g, p = stats.gamma(3), 0.95
    mode = 2.0  # (shape - 1) for the gamma of scale 1

    def upper(a):  # the b > mode with f(b) = f(a)
        return optimize.brentq(lambda b: g.pdf(b) - g.pdf(a), mode, 60.0)

    a = optimize.brentq(lambda a: g.cdf(upper(a)) - g.cdf(a) - p, 1e-9, mode - 1e-9)
    b = upper(a)
    h = _filled(g)
    lo, hi = h.shortest(p)[0]
    w = h.bin_width()[0]
    assert abs(lo - a) <= w and abs(hi - b) <= w, (lo, hi, a, b, w)
    assert (hi - lo) < (g.ppf(0.975) - g.ppf(0.025)) - 0.1  # and it is not the symmetric one


def test_the_histograms_shortest_interval_of_an_exponential_starts_at_zero():
    """Exponential(1): the density falls everywhere, so the shortest 95 % interval is [0, -ln 0.05]."""
    h = _filled(stats.expon())
    lo, hi = h.shortest(0.95)[0]
    w = h.bin_width()[0]
    assert abs(lo - 0.0) <= w and abs(hi + math.log(0.05)) <= w


def test_the_histograms_shortest_interval_is_nan_when_it_would_reach_beyond_the_range():
    h = VectorHistogram(np.zeros((4, 1)))  # a tiny range: almost every value of the normal falls outside
    h.add(np.random.default_rng(2).normal(0.0, 1.0, (5000, 1)))
    assert np.isnan(h.shortest(0.95)).all()


def test_a_run_that_histograms_its_values_states_its_shortest_intervals_and_how(small):
    exact = run(small, trials=256, block=32, attribution_trials=0)
    streamed = run(small, trials=256, block=32, attribution_trials=0, keep_samples=False)
    a, b = exact.summary("compensation_rms"), streamed.summary("compensation_rms")
    assert b["shortest"] is not None
    width = a["shortest"][1] - a["shortest"][0]
    assert abs(a["shortest"][0] - b["shortest"][0]) < 0.05 * width  # the order statistics of the same trials
    assert abs(a["shortest"][1] - b["shortest"][1]) < 0.05 * width
    text = budget_text(streamed)
    table = text[text.index("shortest interval"):]
    assert "[" in table.splitlines()[1].split("]", 1)[1]  # a shortest interval in the row, not "-"
    assert "95 % coverage intervals: the run does not keep every value" in text and "-bin histogram" in text
    assert "95 % coverage intervals: order statistics of every trial" in budget_text(exact)
    js = result_json(streamed)
    assert "histogram" in js["outputs"]["compensation_rms"]["interval_method"]
    # the per-point statement too: each point-axis' shortest interval, with its method, near the exact one
    pe, ps = exact.points(), streamed.points()
    assert "shortest_interval" in ps[0] and "histogram" in ps[0]["shortest_interval"]["method"]
    for q_e, q_s in zip(pe, ps):
        for end in ("low", "high"):
            w = np.subtract(q_e["shortest_interval"]["high"], q_e["shortest_interval"]["low"])
            assert np.all(np.abs(np.subtract(q_e["shortest_interval"][end], q_s["shortest_interval"][end])) < 0.1 * w)


# ------------------------------------------------------------------ which executor ran
def test_the_executor_is_said_with_the_runs_conditions_and_in_its_replay_and_report(small, tmp_path):
    log = tmp_path / "t.mcap"
    res = execute(small, trials=48, block=16, attribution_trials=0, executor="thread", workers=2, log_path=log)
    line = "trials run by: threads of this process, 2 workers"
    assert line in budget_text(res)
    assert result_json(res)["executor"] == {"kind": "thread", "workers": 2, "requested": "thread"}
    again = replay(log)
    assert line in budget_text(again)
    md = run_report(again, tmp_path / "rep")["markdown"].read_text()
    assert "| trials run by | threads of this process, 2 workers" in md
    inline = run(small, trials=32, block=16, attribution_trials=0)
    assert "trials run by: inline (this process, one core)" in budget_text(inline)


# ------------------------------------------------------------------ options that cannot apply together
@pytest.mark.parametrize("args, named", [
    (["--executor", "inline", "--workers", "2"], "--workers"),
    (["--address", "tcp://127.0.0.1:1"], "--address"),
    (["--executor", "thread", "--address", "tcp://127.0.0.1:1"], "--address"),
    (["--executor", "dask", "--address", "tcp://127.0.0.1:1", "--workers", "2"], "--workers"),
    (["--adaptive-batch", "500"], "--adaptive-batch"),
    (["--trials", "5000", "--max-trials", "20000"], "--max-trials"),
])
def test_options_that_cannot_apply_together_are_refused_in_one_line(args, named, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, ["run", str(SMALL), "--quiet", *args])
    said = [ln for ln in res.output.strip().splitlines() if not ln.startswith("compiling the engine's kernels")]
    assert res.exit_code == 2 and len(said) == 1, res.output
    assert said[0].startswith("error: ") and named in said[0] and said[0].endswith("run --help')"), said[0]
    assert not list(tmp_path.iterdir())  # refused before anything ran or was logged


def test_replay_refuses_verify_with_json_in_one_line(tmp_path):
    log = tmp_path / "r.mcap"
    execute(SMALL, trials=16, block=8, attribution_trials=0, log_path=log)
    res = CliRunner().invoke(main, ["replay", str(log), "--verify", "--json"])
    said = [ln for ln in res.output.strip().splitlines() if not ln.startswith("compiling the engine's kernels")]
    assert res.exit_code == 2 and len(said) == 1 and "--verify" in said[0] and said[0].endswith("replay --help')"), said


# ------------------------------------------------------------------ an adaptive run at its limit
def _batch_spread(Y, p):
    """Per point-axis and quantity (mean, std, interval low, interval high): 2 s of the batch values (JCGM 101 7.9.4)
    and the change of their average with the last batch, from Y (batches, h, K), written here."""
    h = Y.shape[1]
    q = int(p * h + 0.5)
    r = (h - q + 1) // 2  # 1-based
    s = np.sort(Y, axis=1)
    st = np.stack([Y.mean(axis=1), Y.std(axis=1, ddof=1), s[:, r - 1], s[:, r - 1 + q]], axis=2)  # (batches, K, 4)
    return 2 * st.std(axis=0, ddof=1) / math.sqrt(len(st)), st.mean(axis=0) - st[:-1].mean(axis=0)


def tolerance(u, ndig=2):  # JCGM 101 7.9.2: u = c 10^l with c of ndig digits, delta = 10^l / 2
    return 0.5 * 10.0 ** (math.floor(math.log10(u)) - (ndig - 1))


def test_an_adaptive_run_at_its_limit_names_what_did_not_stabilise_and_how_to_finish(small, monkeypatch):
    import mtbudget.runner

    monkeypatch.setattr(mtbudget.runner, "VECTOR_SAMPLE_LIMIT", 10**8)  # keep the per-point values to check them
    res = run(small, trials=None, block=32, adaptive_batch=256, attribution_trials=0, max_trials=768,
              adaptive_outputs=("points",))
    a = res.adaptive
    assert res.stopped_at_limit and a["trials"] == 768 and a["max_trials"] == 768
    Y = np.concatenate(res.acc.vector_samples["components"]).reshape(3, 256, -1)
    two_s, change = _batch_spread(Y, 0.95)
    u = Y.reshape(-1, Y.shape[2]).std(axis=0, ddof=1)
    delta = np.array([tolerance(x) for x in u])
    ratio = two_s / delta[:, None]
    assert a["not_stable"] == int((ratio > 1).any(axis=1).sum()) == a["point_axes"] - a["point_axes_stable"]
    worst = np.argsort(-ratio.max(axis=1))[:5]
    for r, j in zip(a["worst"], worst):
        q = int(np.argmax(ratio[j]))
        assert r["quantity"].startswith(f"point #{j // 3} ") and r["quantity"].endswith(f"axis {'xyz'[j % 3]}")
        assert r["statistic"] == ("estimate", "standard uncertainty", "interval low end", "interval high end")[q]
        assert r["two_s"] == pytest.approx(two_s[j, q], rel=1e-9) and r["delta"] == pytest.approx(delta[j])
        assert r["last_change"] == pytest.approx(change[j, q], rel=1e-9, abs=1e-12) and r["unit"] == "um"
    # 2 s falls as 1/sqrt(trials): the trials the worst needs, in whole batches
    assert a["trials_needed"] == 256 * math.ceil(768 * ratio.max() ** 2 / 256)
    text = budget_text(res)
    assert "stopped at its limit of 768 trials (--max-trials), at the end of the batch that reached it" in text
    assert f"Not stable: {a['not_stable']} quantities" in text and "against delta = " in text
    assert "--max-trials " in text.split("To finish:")[1]
    assert "run `mtbudget run --trials 0`" not in text  # never the advice to run what was just run


def test_the_cli_adaptive_limit_and_its_advice(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "0", "--adaptive-batch", "256", "--block", "32",
                                    "--max-trials", "512", "--attribution-trials", "0", "--quiet", "--json"])
    assert res.exit_code == 0, res.output
    a = json.loads(res.output)["adaptive"]
    assert a["stopped_at_limit"] and a["trials"] == 512 and a["max_trials"] == 512 and a["trials_needed"] > 512


def test_an_adaptive_run_histograms_its_values_beyond_the_fixed_runs_limit_and_decides_the_same(small, monkeypatch):
    """Beyond KEEP_SAMPLES_TRIALS the adaptive run keeps no trial's scalar values (bounded memory); it stops where a
    run that keeps them all stops, and states the intervals a fixed run of as many trials states."""
    import mtbudget.runner

    monkeypatch.setattr(mtbudget.runner, "KEEP_SAMPLES_TRIALS", 300)
    kw = dict(block=32, adaptive_batch=256, attribution_trials=0, ndig=1, adaptive_outputs=("compensation_rms",))
    streamed = run(small, trials=None, max_trials=20_000, **kw)
    assert streamed.trials > 300 and not streamed.acc.keep and not streamed.acc.samples
    kept = run(small, trials=None, max_trials=20_000, keep_samples=True, **kw)
    assert kept.acc.keep and streamed.adaptive == kept.adaptive  # the same stop, at the same trials
    fixed = run(small, trials=streamed.trials, block=32, attribution_trials=0)  # > 300: histogrammed from its start
    assert not fixed.acc.keep
    for o in ("compensation_rms", "max_residual"):
        assert streamed.summary(o) == fixed.summary(o)


@pytest.mark.parametrize("trials", [448, None], ids=["fixed", "adaptive"])
def test_a_replay_states_the_intervals_its_run_stated_beyond_the_kept_values(small, tmp_path, monkeypatch, trials):
    """Past KEEP_SAMPLES_TRIALS a run states histogram intervals (bounded memory); its log holds every trial's values,
    but the replay (and the report built on it) must state what the run stated, by the same method, not exact order
    statistics the run never printed. The run's JSON is compared with the replay's, output by output; and the exact
    order statistics of the logged values, computed here with numpy, are not what either states (the check can
    fail)."""
    import mtbudget.runner

    monkeypatch.setattr(mtbudget.runner, "KEEP_SAMPLES_TRIALS", 300)
    log = tmp_path / "long.mcap"
    kw = dict(adaptive_batch=256, max_trials=2048, ndig=1, adaptive_outputs=("compensation_rms",)) if trials is None \
        else {}
    res = execute(small, trials=trials, block=32, attribution_trials=0, log_path=log, **kw)
    assert res.trials > 300 and not res.acc.keep
    again = replay(log)
    assert again.trials == res.trials and not again.acc.keep
    ran, replayed = result_json(res), result_json(again)
    for o in ("compensation_rms", "max_residual", "mean_error_after"):
        assert replayed["outputs"][o] == ran["outputs"][o], o
        assert ran["outputs"][o]["interval_method"].startswith("the run does not keep every value"), o
    # JCGM 101 7.7.1 written out here: q = pM if an integer, else floor(pM + 1/2); r = (M - q)/2 if M - q is even,
    # else (M - q + 1)/2; the interval [y_r, y_(r+q)], 1-based
    y = np.sort(np.concatenate([b.scalars["compensation_rms"] for b in again.log.block_results()]))
    M = len(y)
    q = int(0.95 * M) if float(0.95 * M).is_integer() else math.floor(0.95 * M + 0.5)
    r = (M - q) // 2 if (M - q) % 2 == 0 else (M - q + 1) // 2
    exact = (y[r - 1], y[r + q - 1])
    assert again.exact_from_log["n"] == M == res.trials
    assert again.exact_from_log["symmetric"] == exact
    widths = y[q:] - y[:M - q]  # the shortest: the narrowest [y_j, y_(j+q)]
    assert again.exact_from_log["shortest"][1] - again.exact_from_log["shortest"][0] == pytest.approx(widths.min())
    assert tuple(ran["outputs"]["compensation_rms"]["symmetric"]) != exact  # the run's are the histogram's
    out = CliRunner().invoke(main, ["replay", str(log)])
    assert out.exit_code == 0, out.output
    assert f"compensation_rms from the order statistics of the {M} logged trials (JCGM 101 7.7), 95 % coverage" in out.output


def test_the_adaptive_limit_stops_at_the_end_of_the_batch_that_reaches_it_and_needs_two_batches(small, tmp_path,
                                                                                                 monkeypatch):
    """--max-trials is met at the end of a batch (a limit between batches runs the batch that crosses it: 600 ->
    768 with batches of 256, and says so); a limit below two batches, which the rule always runs, is refused in one
    line before any log is opened."""
    res = run(small, trials=None, block=32, adaptive_batch=256, attribution_trials=0, max_trials=600,
              adaptive_outputs=("points",))
    assert res.stopped_at_limit and res.adaptive["trials"] == 768 and 768 - 256 < 600 <= 768
    assert "limit of 600 trials (--max-trials), at the end of the batch that reached it" in budget_text(res)
    monkeypatch.chdir(tmp_path)
    out = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "0", "--adaptive-batch", "256", "--block", "32",
                                    "--max-trials", "500", "--log", "a.mcap", "--quiet"])
    assert out.exit_code == 2 and out.output.count("\n") == 1, out.output
    assert "--max-trials: must be at least two adaptive batches (512 trials: two of 256" in out.output
    assert not list(tmp_path.glob("a.mcap*"))


def test_the_worst_point_says_its_criterion_and_the_strategy_rows_say_why_they_are_about_zero(tmp_path):
    """The worst point is the one of largest sqrt(u_x^2 + u_y^2 + u_z^2), found here from the per-point JSON; the
    optimisation-strategy rows of the per-point budget, about zero, say why beside them (docs/model.md)."""
    from mtbudget.config import default_config_path

    res = run(load_config(default_config_path()), trials=64, block=32, attribution_trials=32)
    text = budget_text(res)
    pts = result_json(res)["points"]
    u = np.array([p["u"]["value"] for p in pts])
    j = int(np.argmax(np.sqrt((u ** 2).sum(axis=1))))
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("worst point"))
    assert "(the largest u = sqrt(u_x^2 + u_y^2 + u_z^2), " in line
    assert f"#{j} " in line and f"{np.sqrt((u[j] ** 2).sum()):.1f}" in line, line
    rows = [ln for ln in text.splitlines() if ln.strip().startswith(("phase_sequence", "convergence_criteria"))]
    per_point = [ln for ln in rows if "(0.00, 0.00, 0.00)" in ln]
    assert len(per_point) == 2 and all("about zero" in ln and "docs/model.md" in ln for ln in per_point), rows
