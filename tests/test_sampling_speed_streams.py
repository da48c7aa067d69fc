"""Sampling without pint in the hot path (issue 12): the same numbers, bit for bit.

* ``simulate.stream`` is ``default_rng(SeedSequence(seed, spawn_key=(block, crc32(name))))``.
* The built-in sources draw in ``sample_internal`` (float arrays in the internal units, the three axes in one call,
  what depends on the parameters and the plan remembered): every array must equal, byte for byte, what the
  sources drew before that change.  The references below are those ``sample`` methods, copied as they were.
"""

import copy
import zlib
from pathlib import Path

import numpy as np
import pytest

from mtbudget import simulate
from mtbudget.config import load_config, parse_config
from mtbudget.contracts import Group, Source, check_internal, has_internal_sample
from mtbudget.errors import PluginError
from mtbudget.plugins import default_host
from mtbudget.scenario import build_scenario, target_shapes
from mtbudget.units import Q_
from mtbudget_plugins import machine_tool as mt
from mtbudget_plugins import measurement_system as ms
from mtbudget_plugins import measurement_strategy as mst
from mtbudget_plugins import optimisation_strategy as ost

DATA = Path(__file__).parent / "data"
PKG = Path(simulate.__file__).parent / "data"


def _reference_rng(seed, block, name):
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(block), zlib.crc32(name.encode()))))


class _Named:
    def __init__(self, name):
        self.name = name


# ----------------------------------------------------------------------------- streams
def test_stream_is_numpy_seedsequence_state():
    for seed, block, name in ((0, 0, ""), (1, 0, "repeatability"), (7, 3, "tracker_noise"), (2**64 + 5, 17, "x")):
        got, ref = simulate.stream(seed, block, _Named(name)), _reference_rng(seed, block, name)
        assert got.bit_generator.state == ref.bit_generator.state, (seed, block, name)


def test_streams_of_a_block_are_numpy_seedsequences():
    """simulate.streams hashes the block's sources together (its own code for numpy's SeedSequence): every generator
    must have numpy's state and draw numpy's numbers, for seeds and blocks of one word, several words, word limits."""
    rs = np.random.default_rng(12)
    cases = [(0, 0), (1, 0), (0, 1), (2**32 - 1, 2**32 - 1), (2**32, 2**32), (2**64 + 5, 17), (2**128 - 1, 3),
             (2**128, 3), (2**200 + 3, 2**40 + 1)] + [(int(rs.integers(0, 2**63)), int(rs.integers(0, 10**6)))
                                                       for _ in range(40)]
    sources = [_Named(n) for n in ("", "repeatability", "tracker_noise", "a" * 300, "unidentified_at_tool")]
    for seed, block in cases:
        for src, got in zip(sources, simulate.streams(seed, block, sources)):
            ref = _reference_rng(seed, block, src.name)
            assert got.bit_generator.state == ref.bit_generator.state, (seed, block, src.name)
    got, ref = simulate.stream(3, 5, sources[1]), _reference_rng(3, 5, "repeatability")
    assert np.array_equal(got.standard_normal(1000), ref.standard_normal(1000))
    with pytest.raises(ValueError):  # numpy's refusal of a negative seed, as before
        simulate.stream(-1, 0, sources[0])


def test_a_stream_seed_sequence_is_numpys_in_every_other_use():
    """What a plugin may ask of its generator beyond drawing: spawn, the seed sequence's entropy, spawn key and other
    states, a copy (pickle): the same as numpy's SeedSequence-seeded generator."""
    import pickle

    got, ref = simulate.stream(11, 2, _Named("smr_centring")), _reference_rng(11, 2, "smr_centring")
    ss, rs = got.bit_generator.seed_seq, ref.bit_generator.seed_seq
    assert (ss.entropy, ss.spawn_key, ss.pool_size) == (rs.entropy, rs.spawn_key, rs.pool_size)
    assert np.array_equal(ss.generate_state(4, np.uint64), rs.generate_state(4, np.uint64))
    assert np.array_equal(ss.generate_state(7), rs.generate_state(7))
    assert [c.random() for c in got.spawn(3)] == [c.random() for c in ref.spawn(3)]
    assert ss.n_children_spawned == rs.n_children_spawned == 3
    copy = pickle.loads(pickle.dumps(got))
    assert copy.random() == got.random() == ref.random()


# ----------------------------------------------------------------------------- the sources as they were
def _axis_ctes(src, ctx):
    scales = getattr(ctx.plan, "scales", None) or {}
    default = src.value("cte", "1/K")
    return {a: scales[a].cte if a in scales else default for a in "xyz"}


def _ref_temperature_sensor_calibration(self, n, rng, ctx):
    u = self.value("u_calibration", "K") / float(self.parameters["k"].magnitude)
    cte = _axis_ctes(self, ctx)
    out = {}
    for a in "xyz":
        dT = rng.normal(0.0, u, (n, 1))
        out[f"axis_scale.{a}"] = np.broadcast_to(cte[a] * dT, (n, ctx.n_points)).copy()
    return out


def _ref_cte_uncertainty(self, n, rng, ctx):
    cte = _axis_ctes(self, ctx)
    T = {a: ctx.plan.axis_temperature(a, ctx.reference_temperature) for a in "xyz"}
    out = {}
    for a in "xyz":
        w = self.width(cte[a])
        out[f"axis_scale.{a}"] = rng.uniform(-w / 2, w / 2, (n, 1)) * (T[a] - ctx.reference_temperature)[None, :]
    return out


def _ref_environmental_variation(self, n, rng, ctx):
    e = self.value("E_VE", "mm")
    t = ctx.plan.time
    frac = t / t[-1] if t[-1] > 0 else np.zeros_like(t)
    end = rng.uniform(-e / 2, e / 2, (n, 1, 3))
    return {"point_offset": end * frac[None, :, None]}


def _ref_temperature_drift(self, n, rng, ctx):
    rate, cte = self.value("rate", "K/s"), _axis_ctes(self, ctx)
    t = ctx.plan.time[None, :]
    return {f"axis_scale.{a}": cte[a] * rng.normal(0.0, rate, (n, 1)) * t for a in "xyz"}


def _ref_backlash(self, n, rng, ctx):
    bmax = self.value("B_max", "mm")
    return {f"axis_offset.{a}": -ctx.plan.direction[None, :, i] * rng.uniform(0, bmax, (n, 1)) / 2
            for i, a in enumerate("xyz")}


def _ref_per_point_normal(self, n, rng, ctx):
    u = self.value(self.key, "mm")
    return {f"axis_offset.{a}": rng.normal(0.0, u, (n, ctx.n_points)) for a in "xyz"}


def _ref_geometric_error_uncertainty(self, n, rng, ctx):
    base = np.array([p.order <= ctx.config.max_degree for p in ctx.model.errors.params]) if ctx.config is not None \
        else np.ones(len(ctx.theta), bool)
    z = np.zeros((n, len(ctx.theta)))
    z[:, base] = self._draw(rng, (n, int(base.sum())))
    mm, rad = ctx.parameter_mask("mm"), ctx.parameter_mask("rad")
    return {"geometry.translational": z * mm * self.value("translational", "mm"),
            "geometry.angular": z * rad * self.value("angular", "rad")}


def _ref_registration(self, n, rng, ctx):
    return {"pose.position": rng.normal(0.0, self.value("u_position", "mm"), (n, 3)),
            "pose.orientation": rng.normal(0.0, self.value("u_orientation", "rad"), (n, 3))}


def _ref_tracker_noise(self, n, rng, ctx):
    r = np.linalg.norm(ctx.nominal_tracker_points, axis=1)
    mean = self.value("angular_mean", "rad")
    ua = np.abs(rng.normal(mean, self.value("angular_sd", "rad"), (n, 1, 2)))
    if ctx.row_noise is None:
        ur = self.value("distance", "mm") + self.value("distance_per_length", "") * r
    else:
        ur = ctx.row_noise["distance"] + ctx.row_noise["distance_per_length"] * r
        ua = ua * (ctx.row_noise["angular"] / mean if mean > 0 else 0.0)[None, :, None]
    return {"spherical_noise.range": rng.standard_normal((n, ctx.n_points)) * ur[None, :],
            "spherical_noise.angles": rng.standard_normal((n, ctx.n_points, 2)) * ua}


def _ref_smr_centring(self, n, rng, ctx):
    from mtbudget import tracker as lt

    lateral = rng.normal(0.0, self.value("u_SMR", "mm"), (n, ctx.n_points, 2))
    pts = ctx.nominal_tracker_points
    e_az, e_el = lt.smr_offset(pts, np.array([1.0, 0.0])), lt.smr_offset(pts, np.array([0.0, 1.0]))
    return {"tracker_offset": lateral[..., :1] * e_az + lateral[..., 1:2] * e_el}


def _ref_software_point_uncertainty(self, n, rng, ctx):
    return {"tracker_offset": rng.normal(0.0, self.value("u_MS", "mm"), (n, ctx.n_points, 3))}


def _ref_choice(self, n, rng, ctx):
    return {"strategy": rng.integers(0, len(self.options(ctx)), n).astype(float)}


def _ref_model_form(self, n, rng, ctx):
    top = ctx.config.max_degree + 1
    extra = np.array([p.order == top and not p.is_squareness for p in ctx.model.errors.params])
    z = rng.standard_normal((n, len(extra))) * extra
    mm, rad = ctx.parameter_mask("mm"), ctx.parameter_mask("rad")
    return {"geometry.translational": z * mm * self.parameters["translational"].to("mm").magnitude,
            "geometry.angular": z * rad * self.parameters["angular"].to("rad").magnitude}


def _ref_in_use(self, n, rng, ctx):
    M = ctx.n_points
    R = self.parameters["R"].to("mm").magnitude
    B = rng.uniform(0.0, self.parameters["B_max"].to("mm").magnitude, (n, 1, 3))
    side = rng.choice((-1.0, 1.0), (n, M, 3))
    dcte = rng.standard_normal((n, 1, 3)) * self.parameters["u_cte"].to("1/K").magnitude
    dT = rng.uniform(-1.0, 1.0, (n, 1, 1)) * self.parameters["temperature_range"].to("K").magnitude
    pos = np.asarray(ctx.plan.nominal, float)[None]
    return {"measurand_offset": rng.standard_normal((n, M, 3)) * R - side * B / 2.0 + dcte * dT * pos}


REFERENCES = {
    mt.TemperatureSensorCalibration: _ref_temperature_sensor_calibration,
    mt.CTEUncertainty: _ref_cte_uncertainty,
    mt.EnvironmentalVariation: _ref_environmental_variation,
    mt.TemperatureDrift: _ref_temperature_drift,
    mt.Backlash: _ref_backlash,
    mt.Repeatability: _ref_per_point_normal,
    mt.ControlError: _ref_per_point_normal,
    mt.GeometricErrorUncertainty: _ref_geometric_error_uncertainty,
    mt.InUse: _ref_in_use,
    mst.Registration: _ref_registration,
    ms.TrackerNoise: _ref_tracker_noise,
    ms.SMRCentring: _ref_smr_centring,
    ms.SoftwarePointUncertainty: _ref_software_point_uncertainty,
    ost.ConvergenceCriteria: _ref_choice,
    ost.PhaseSequence: _ref_choice,
    ost.ApproximationDegree: _ref_choice,
    ost.ModelForm: _ref_model_form,
}


def _scenarios():
    small = copy.deepcopy(load_config(DATA / "small.toml").source)
    del small["sources"]
    small["sources"] = {"add": ["in_use", "model_form", "approximation_degree"], "geometric_error_uncertainty":
                        {"shape": "beta"}, "tracker_noise": {"angular_sd": "2 urad"}}
    yield "small, every reference source", build_scenario(parse_config(small, DATA / "small.toml"))
    yield "default", build_scenario(load_config())
    yield "four stations", build_scenario(load_config(PKG / "four_stations.toml"))


def _same(a, b):
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_builtin_sources_draw_what_they_drew_before():
    seen = set()
    for label, sc in _scenarios():
        shapes = target_shapes(sc)
        for src in sc.sources:
            ref = REFERENCES.get(type(src))
            if ref is None:
                continue
            seen.add(type(src))
            assert has_internal_sample(src)
            for seed, block, n in ((1, 0, 64), (7, 5, 64), (3, 2, 3), (3, 9, 1)):
                want = ref(src, n, _reference_rng(seed, block, src.name), sc.context)
                got = simulate.sample_source(sc, src, n, simulate.stream(seed, block, src), shapes, {})
                assert sorted(got) == sorted(want), (label, src.name)
                for k in want:
                    assert _same(got[k], np.asarray(want[k], float)), (label, src.name, k, seed, block, n)
                quantities = src.sample(n, simulate.stream(seed, block, src), sc.context)  # the contract: quantities
                assert all(_same(np.asarray(q.magnitude), np.asarray(want[k], float)) for k, q in quantities.items())
    assert seen == set(REFERENCES)


def test_remembered_values_follow_configure_and_context():
    sc = build_scenario(load_config())
    src = next(s for s in sc.sources if s.name == "cte_uncertainty")
    shapes = target_shapes(sc)
    first = simulate.sample_source(sc, src, 4, np.random.default_rng(0), shapes)
    src.configure({"fraction": "0.5"})  # a wider rectangle: width 0.5 * CTE instead of the floor
    again = simulate.sample_source(sc, src, 4, np.random.default_rng(0), shapes)
    want = _ref_cte_uncertainty(src, 4, np.random.default_rng(0), sc.context)
    assert not np.array_equal(first["axis_scale.x"], again["axis_scale.x"])
    assert all(_same(again[k], want[k]) for k in want)


def test_normal0_is_rng_normal():
    for scale in (2.5e-3, 1.0, 0.0, 1e-300):
        a = mt.normal0(np.random.default_rng(3), scale, (7, 11))
        b = np.random.default_rng(3).normal(0.0, scale, (7, 11))
        assert _same(a, b)
    with pytest.raises(ValueError):
        mt.normal0(np.random.default_rng(3), -1.0, 4)


# ----------------------------------------------------------------------------- the internal contract
class _Internal(Source):
    name = "internal_probe"
    group = Group.MACHINE_TOOL
    targets = ("point_offset", "strategy")
    result = None

    def sample_internal(self, n, rng, ctx):
        return self.result(n, ctx)


def _probe(result):
    src = _Internal()
    src.plugin = "probe_plugin"
    src.result = result
    return src


def test_check_internal_accepts_and_refuses():
    sc = build_scenario(load_config(DATA / "small.toml"))
    shapes = target_shapes(sc)
    M = sc.context.n_points
    ok = _probe(lambda n, ctx: {"point_offset": np.ones((n, M, 3))})
    out = simulate.sample_source(sc, ok, 2, np.random.default_rng(0), shapes)
    assert out["point_offset"].shape == (2, M, 3)
    # integers and lists are converted, as check_sample does for quantities
    conv = _probe(lambda n, ctx: {"point_offset": np.ones((n, M, 3), int)})
    assert simulate.sample_source(sc, conv, 2, np.random.default_rng(0), shapes)["point_offset"].dtype == float
    # the sample() contract still holds: quantities in the internal units
    q = ok.sample(2, np.random.default_rng(0), sc.context)["point_offset"]
    assert str(q.units) == "mm" and np.all(q.magnitude == 1.0)
    bad = {
        "contains NaN or infinity": lambda n, ctx: {"point_offset": np.full((n, M, 3), np.nan)},
        "has shape": lambda n, ctx: {"point_offset": np.ones((n, M))},
        "not among its declared targets": lambda n, ctx: {"tracker_offset": np.ones((n, M, 3))},
        "must return a dict": lambda n, ctx: [np.ones((n, M, 3))],
        "option indices": lambda n, ctx: {"strategy": np.full(n, 0.5)},
    }
    for words, result in bad.items():
        with pytest.raises(PluginError, match=words) as e:
            simulate.sample_source(sc, _probe(result), 2, np.random.default_rng(0), shapes, {"internal_probe": [{}]})
        assert e.value.plugin == "probe_plugin" and e.value.source == "internal_probe"
    # large but finite: absurd for a perturbation (issue 29: 1e300 mm made a run print inf/nan with exit 0)
    big = _probe(lambda n, ctx: {"point_offset": np.full((n, M, 3), 1e308)})
    with pytest.raises(PluginError, match="beyond the plausible 10000 mm") as e:
        simulate.sample_source(sc, big, 2, np.random.default_rng(0), shapes)
    assert e.value.plugin == "probe_plugin" and e.value.source == "internal_probe"
    fine = _probe(lambda n, ctx: {"point_offset": np.full((n, M, 3), 9999.0)})  # within: kept as it is
    assert np.all(simulate.sample_source(sc, fine, 2, np.random.default_rng(0), shapes)["point_offset"] == 9999.0)


def test_a_subclass_that_overrides_sample_is_sampled_through_it():
    class Mine(mt.Repeatability):
        def sample(self, n, rng, ctx):
            return {f"axis_offset.{a}": Q_(np.full((n, ctx.n_points), 2.0), "um") for a in "xyz"}

    sc = build_scenario(load_config(DATA / "small.toml"))
    src = Mine()
    assert not has_internal_sample(src) and has_internal_sample(mt.Repeatability())
    out = simulate.sample_source(sc, src, 3, np.random.default_rng(0), target_shapes(sc))
    assert np.allclose(out["axis_offset.y"], 2e-3, rtol=1e-15, atol=0)
    with pytest.raises(NotImplementedError):
        Source().sample(1, np.random.default_rng(0), sc.context)


def test_a_subclass_that_extends_a_builtin_through_super_sample():
    """A plugin that scales a built-in source's draws through super().sample(): the built-in's quantities."""
    class Doubled(mt.Repeatability):
        def sample(self, n, rng, ctx):
            return {k: 2 * v for k, v in super().sample(n, rng, ctx).items()}

    sc = build_scenario(load_config(DATA / "small.toml"))
    shapes = target_shapes(sc)
    base = simulate.sample_source(sc, mt.Repeatability(), 4, np.random.default_rng(3), shapes)
    twice = simulate.sample_source(sc, Doubled(), 4, np.random.default_rng(3), shapes)
    assert base.keys() == twice.keys()
    for k in base:
        assert np.array_equal(twice[k], 2 * base[k])


def test_every_builtin_source_samples_internally():
    for src in default_host().sources():
        if src.plugin in {"machine_tool", "measurement_system", "measurement_strategy", "optimisation_strategy"}:
            assert has_internal_sample(src), src.name


def test_check_internal_returns_the_arrays_themselves():
    src = mt.Repeatability()
    arrays = {"axis_offset.x": np.zeros((2, 5))}
    assert check_internal(src, arrays, 2, {"axis_offset.x": (5,)}) is arrays
