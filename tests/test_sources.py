"""Every built-in source draws the distribution it states, in the units it declares."""

import copy
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from mtbudget.config import load_config, parse_config
from mtbudget.plugins import default_host
from mtbudget.scenario import ROTARY_INPUTS, build_scenario
from mtbudget.simulate import sample_source
from mtbudget.contracts import TARGETS, Group
from mtbudget.units import ureg

N = 20000
SMALL = Path(__file__).parent / "data" / "small.toml"


class AllSources:
    """Every registered source, each configured alone on the small study with the paper's tracker noise."""

    def __init__(self):
        raw = copy.deepcopy(load_config(SMALL).source)
        del raw["sources"]
        raw["tracker"]["angular"] = "20 urad"
        self.cfg = parse_config(raw, SMALL)
        self.scenario = build_scenario(self.cfg)
        self.plan, self.context = self.scenario.plan, self.scenario.context
        # the rotary axes' sources act on five-axis machines only (tests/test_fiveaxis_mc.py)
        names = [s.name for s in default_host().sources() if not set(s.targets) <= ROTARY_INPUTS]
        self.sources = [build_scenario(self.cfg, sources=[n]).sources[0] for n in names]

    def _sample(self, s, n, rng):
        return sample_source(self.scenario, s, n, rng)


@pytest.fixture(scope="module")
def eng():
    return AllSources()


def src(eng, name):
    return [s for s in eng.sources if s.name == name][0]


def draw(eng, name, n=N):
    s = src(eng, name)
    raw = s.sample(n, np.random.default_rng(42), eng.context)
    for k, q in raw.items():  # declared units and dimensions
        unit = TARGETS[k][0]
        assert q.dimensionality == (ureg(unit) if unit else ureg.dimensionless).dimensionality, (name, k)
    return s, eng._sample(s, n, np.random.default_rng(42))


def sd_ok(x, sigma, n=N):
    return abs(np.std(x) - sigma) < 5 * sigma / math.sqrt(2 * n)


def test_every_group_has_sources(eng):
    groups = {Group(s.group) for s in eng.sources}
    assert groups == set(Group)


def test_temperature_sensor_calibration_eq3(eng):
    s, a = draw(eng, "temperature_sensor_calibration")
    x = a["axis_scale.x"]
    assert np.all(x == x[:, :1])  # one offset for the whole test
    cte = s.value("cte", "1/K")
    assert sd_ok(x[:, 0] / cte, 0.1 / 2)  # u_device = u_calibration / k
    assert stats.normaltest(x[:, 0]).pvalue > 1e-3


def test_cte_uncertainty_eq10(eng):
    s, a = draw(eng, "cte_uncertainty")
    T = eng.plan.axis_temperature("x", eng.context.reference_temperature) - eng.context.reference_temperature
    dalpha = a["axis_scale.x"][:, 0] / T[0]
    w = max(0.1 * 11.5e-6, 0.002e-3)  # 10 % of 11.5 um/(m K) is below the floor of 0.002 um/(mm K)
    assert w == pytest.approx(2e-6)
    assert np.abs(dalpha).max() <= w / 2 + 1e-18
    assert sd_ok(dalpha, w / (2 * math.sqrt(3)))  # Eq. 10: u = 0.002 / (2 sqrt 3) = 0.0006 um/(mm K)
    assert s.standard_uncertainty().to("um/(mm*K)").magnitude == pytest.approx(0.000577, abs=1e-6)


def test_environmental_variation_eq14(eng):
    s, a = draw(eng, "environmental_variation")
    end = a["point_offset"][:, -1, :]
    assert sd_ok(end[:, 0], 2e-3 / (2 * math.sqrt(3)))
    assert np.abs(end).max() <= 1e-3 + 1e-15
    assert np.allclose(a["point_offset"][:, 0, :], 0.0)


def test_temperature_drift_follows_time(eng):
    s, a = draw(eng, "temperature_drift")
    t = eng.plan.time
    rate = a["axis_scale.y"][:, -1] / (s.value("cte", "1/K") * t[-1])
    assert sd_ok(rate, 0.2 / 3600)
    assert np.allclose(a["axis_scale.y"] / t[None, :].clip(1e-9)[:, :] * (t > 0), rate[:, None] * s.value("cte", "1/K") * (t > 0))


def test_backlash_is_rectangular_and_follows_direction(eng):
    s, a = draw(eng, "backlash")
    B = -2 * a["axis_offset.x"] * eng.plan.direction[None, :, 0]
    assert np.all(B == B[:, :1]) and B.min() >= 0 and B.max() <= 3e-3
    assert sd_ok(B[:, 0], 3e-3 / math.sqrt(12))
    assert stats.kstest(B[:, 0] / 3e-3, "uniform").pvalue > 1e-3


@pytest.mark.parametrize("name,sigma", [("repeatability", 1.5e-3), ("control_error", 0.5e-3)])
def test_per_point_normal(eng, name, sigma):
    s, a = draw(eng, name, 2000)
    x = a["axis_offset.z"].ravel()
    assert sd_ok(x, sigma, x.size)
    assert stats.normaltest(x[:5000]).pvalue > 1e-3


@pytest.mark.parametrize("shape", ["normal", "beta"])
def test_geometric_error_uncertainty_eq18_20(eng, shape):
    s = src(eng, "geometric_error_uncertainty")
    s.configure({"shape": shape})
    try:
        a = eng._sample(s, N, np.random.default_rng(1))
    finally:
        s.configure({"shape": "normal"})
    mm = eng.context.parameter_mask("mm")
    t = a["geometry.translational"][:, mm][:, 0]
    assert sd_ok(t, 0.5e-3)
    assert np.all(a["geometry.translational"][:, ~mm] == 0) and np.all(a["geometry.angular"][:, mm] == 0)
    if shape == "beta":
        assert np.abs(t).max() <= math.sqrt(5) * 0.5e-3


def test_tracker_noise_paper_values(eng):
    s, a = draw(eng, "tracker_noise", 4000)
    r = np.linalg.norm(eng.context.nominal_tracker_points, axis=1)
    rng_noise = a["spherical_noise.range"]
    assert sd_ok(rng_noise[:, 0], 4e-3 + 0.8e-6 * r[0], 4000)
    ang = a["spherical_noise.angles"]
    # u_angle ~ N(20, 3) urad per trial: the pooled standard deviation is sqrt(20^2 + 3^2) urad
    assert np.std(ang) == pytest.approx(math.hypot(20e-6, 3e-6), rel=0.02)
    per_trial = ang.std(axis=1)[:, 0]
    m = ang.shape[1]  # the spread of per-trial standard deviations: 3 urad plus their sampling error
    assert np.std(per_trial) == pytest.approx(math.sqrt(3e-6**2 + 20e-6**2 / (2 * (m - 1))), rel=0.1)


def test_smr_and_software(eng):
    s, a = draw(eng, "smr_centring", 2000)
    off = a["tracker_offset"]
    beam = eng.context.nominal_tracker_points
    assert np.allclose(np.einsum("nmi,mi->nm", off, beam), 0.0, atol=1e-12)
    assert np.sqrt((off**2).sum(-1).mean()) == pytest.approx(math.sqrt(2) * 2e-3, rel=0.02)
    s, a = draw(eng, "software_point_uncertainty", 2000)
    assert sd_ok(a["tracker_offset"].ravel(), 1e-3, a["tracker_offset"].size)


def test_registration_eq25_26(eng):
    s, a = draw(eng, "registration")
    assert sd_ok(a["pose.position"][:, 0], 0.5)
    assert sd_ok(a["pose.orientation"][:, 2], 100e-6)


@pytest.mark.parametrize("name", ["approximation_degree", "convergence_criteria", "phase_sequence"])
def test_strategy_sources_choose_uniformly(eng, name):
    s, a = draw(eng, name)
    k = len(s.options(eng.context))
    counts = np.bincount(a["strategy"].astype(int), minlength=k)
    assert stats.chisquare(counts).pvalue > 1e-3


