"""The adaptive procedure (JCGM 101 7.9) applied to the per-point measurand, and the GUF on the MCM's inputs."""

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from mtbudget.budget import point_guf, point_lpu
from mtbudget.config import load_config, parse_config
from mtbudget.report import budget_text, result_json
from mtbudget.runner import run
from mtbudget.scenario import build_scenario

SMALL = Path(__file__).parent / "data" / "small.toml"


def tolerance(u, ndig):  # JCGM 101 7.9.2, written here: u = c 10^l with c of ndig digits, delta = 10^l / 2
    return 0.5 * 10.0 ** (math.floor(math.log10(u)) - (ndig - 1))


def batch_stats(Y, p):
    """(batches, K, 4): mean, std, and the 7.7.1 interval ends of each batch of Y (batches, h, K), written here."""
    h = Y.shape[1]
    q = int(p * h + 0.5)
    r = (h - q) // 2 if (h - q) % 2 == 0 else int((h - q + 1) / 2)  # 1-based
    s = np.sort(Y, axis=1)
    return np.stack([Y.mean(axis=1), Y.std(axis=1, ddof=1), s[:, r - 1], s[:, r - 1 + q]], axis=2)


def all_stable(Y, ndig, p):
    st = batch_stats(Y, p)
    spread = 2 * st.std(axis=0, ddof=1) / math.sqrt(len(st))  # (K, 4)
    u = Y.reshape(-1, Y.shape[2]).std(axis=0, ddof=1)
    return spread <= np.array([tolerance(x, ndig) for x in u])[:, None]


def test_the_adaptive_run_stops_on_every_point_axis(monkeypatch):
    # every trial's per-point values kept (a run beyond runner.VECTOR_SAMPLE_LIMIT streams them into histograms),
    # so that this test can recompute the batches' statistics from them
    import mtbudget.runner

    monkeypatch.setattr(mtbudget.runner, "VECTOR_SAMPLE_LIMIT", 10**8)
    res = run(load_config(SMALL), trials=None, block=32, adaptive_batch=256, attribution_trials=0,
              max_trials=60_000, ndig=1)
    a = res.adaptive
    assert not res.stopped_at_limit and a["point_axes"] == a["point_axes_stable"] == 81
    assert a["trials"] == res.trials and res.trials % 256 == 0
    Y = np.concatenate(res.acc.vector_samples["components"]).reshape(-1, 256, 81)
    assert all_stable(Y, 1, 0.95).all()  # every point-axis' mean, u and interval ends, checked here
    assert not all_stable(Y[:-1], 1, 0.95).all()  # and not one batch earlier: it stopped when they were
    line = budget_text(res)
    assert "81 of 81 point-axes" in line and f"at {res.trials} trials" in line
    assert result_json(res)["adaptive"]["point_axes_stable"] == 81


def test_guf_uses_the_second_moment_of_the_hierarchical_angular_noise():
    """u_angle ~ |N(20, 3)| urad has E[u^2] = 20^2 + 3^2 = 409 urad^2: the GUF of that draw is the GUF of a constant
    u_angle = sqrt(409) urad, with the identification's weights the same (stated apart in [weights])."""
    def sc(mean, sd):
        raw = copy.deepcopy(load_config().source)
        raw["sources"] = {"enable": ["tracker_noise"], "tracker_noise": {"angular_sd": sd}}
        raw.setdefault("tracker", {})["angular"] = mean  # what the run draws (the source's angular_mean)
        raw["weights"] = {"angular": "20 urad"}  # what the identification weights with
        return build_scenario(parse_config(raw))

    hier, const, stated = point_guf(sc("20 urad", "3 urad")), point_guf(sc(f"{math.sqrt(409)} urad", "0 urad")), \
        point_guf(sc("20 urad", "0 urad"))
    assert np.allclose(hier["cov"], const["cov"], rtol=1e-9, atol=1e-12)
    u_h = np.sqrt(np.diagonal(hier["cov"], axis1=1, axis2=2))
    u_s = np.sqrt(np.diagonal(stated["cov"], axis1=1, axis2=2))
    assert 1.001 < np.median(u_h / u_s) < math.sqrt(409 / 400)  # the angles' share only: the range noise is the same
    assert hier["basis"]["closed_form"] == ["tracker_noise"] and not hier["basis"]["sampled"]


@pytest.mark.slow
def test_guf_on_the_same_inputs_agrees_with_the_mcm_where_the_stated_noise_guf_did_not():
    cfg = load_config()  # the paper's: hierarchical tracker noise and every source
    sc = build_scenario(cfg)
    res = run(cfg, trials=20_000, seed=4, attribution_trials=0)
    u = np.array([p["u"]["value"] for p in res.points()])
    g = np.sqrt(np.diagonal(point_guf(sc)["cov"], axis1=1, axis2=2))
    old = np.sqrt(np.diagonal(point_lpu(sc)["cov"], axis1=1, axis2=2))
    # u of 20 000 trials scatters by 1/sqrt(2 * 20 000) = 0.5 % (the points together less: their median, but the
    # shared angular u of each trial correlates them); the stated-noise GUF is 1.4 % low everywhere
    assert np.median(u / g) == pytest.approx(1.0, abs=0.004)
    assert np.median(u / old) > 1.008
    assert "smr_centring" in point_guf(sc)["basis"]["sampled"]
