"""The simulation made cheaper (issue 31), the same numbers bit for bit.

Each piece is compared with the plain formula it replaces, written here: ``model.from_targets`` joins the split
targets without padded arrays and their sum; ``ChainInputs.effective`` multiplies in place; ``predict`` adds the
offsets in place; ``kernel_chain`` remembers what does not change between blocks.  Every comparison is of the bytes
(``-0.0`` and ``0.0`` differ), with values chosen to hold signed zeros.
"""

import numpy as np
import pytest

from mtbudget import machine, plugins
from mtbudget import tracker as lt
from mtbudget.config import load_config
from mtbudget.machine import ChainInputs, kernel_chain
from mtbudget.model import from_targets
from mtbudget.scenario import build_scenario


def same_bits(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def reference_from_targets(arrays: dict) -> dict:
    """The split targets padded with zeros to the model input, each padded array added (as before issue 31)."""
    out = {}

    def add(k, v):
        out[k] = out[k] + v if k in out else v

    for key, v in arrays.items():
        if key in ("geometry.translational", "geometry.angular"):
            add("geometry", v)
        elif key == "pose.position":
            add("pose", np.concatenate([v, np.zeros_like(v)], axis=-1))
        elif key == "pose.orientation":
            add("pose", np.concatenate([np.zeros_like(v), v], axis=-1))
        elif key == "spherical_noise.range":
            add("spherical_noise", np.concatenate([v[..., None], np.zeros(v.shape + (2,))], axis=-1))
        elif key == "spherical_noise.angles":
            add("spherical_noise", np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], axis=-1))
        elif key != "strategy":
            add(key, v)
    return out


def signed(rng, shape):
    """Normal numbers with signed zeros among them (x + 0.0 turns -0.0 into 0.0: a sum of padded arrays does)."""
    x = rng.standard_normal(shape)
    flat = x.reshape(-1)
    flat[::7] = -0.0
    flat[3::11] = 0.0
    return x


@pytest.mark.parametrize("keys", [
    ("spherical_noise.range", "spherical_noise.angles", "pose.position", "pose.orientation"),
    ("spherical_noise.angles", "spherical_noise.range", "pose.orientation", "pose.position"),  # the other order
    ("spherical_noise.range",), ("spherical_noise.angles",), ("pose.position",), ("pose.orientation",),
    ("axis_offset.x", "pose.orientation", "geometry.translational", "geometry.angular", "strategy"),
])
def test_from_targets_joins_the_split_targets_as_padded_sums(keys):
    rng = np.random.default_rng(4)
    n, M, p = 5, 7, 4
    shapes = {"spherical_noise.range": (n, M), "spherical_noise.angles": (n, M, 2), "pose.position": (n, 3),
              "pose.orientation": (n, 3), "axis_offset.x": (n, M), "geometry.translational": (n, p),
              "geometry.angular": (n, p), "strategy": (n,)}
    arrays = {k: signed(rng, shapes[k]) for k in keys}
    kept = {k: v.copy() for k, v in arrays.items()}
    got, ref = from_targets(arrays), reference_from_targets(arrays)
    assert list(got) == list(ref)
    for k in ref:
        assert same_bits(got[k], ref[k]), k
    for k in kept:  # the sources' arrays are not written to
        assert same_bits(arrays[k], kept[k]), k


def test_effective_position_is_nominal_plus_offset_times_one_plus_scale():
    rng = np.random.default_rng(5)
    N, M = 6, 9
    nominal = rng.uniform(-500, 500, (M, 3))
    nominal[0] = 0.0
    cases = [(signed(rng, (N, M)), signed(rng, (N, M)) * 1e-5),  # both per trial
             (None, signed(rng, (N, M)) * 1e-5), (signed(rng, (N, M)), None), (None, None),
             (signed(rng, (1, M)), signed(rng, (1, M))), (signed(rng, (N, M)), signed(rng, (1, M))),
             (signed(rng, (1, M)), signed(rng, (N, M))), (signed(rng, (N, M)), np.float64(2e-5))]
    for off, sc in cases:
        inp = ChainInputs(nominal, np.zeros((M, 3)), offset={} if off is None else {"x": off},
                          scale={} if sc is None else {"x": sc})
        p = nominal[:, 0][None, :]
        if off is not None:
            p = p + off
        if sc is not None:
            p = p * (1.0 + sc)
        assert same_bits(inp.effective("x"), np.atleast_2d(p))
        if off is not None:
            assert not np.shares_memory(inp.effective("x"), off)


@pytest.fixture(scope="module")
def paper():
    return build_scenario(load_config(None))


def test_predict_adds_the_offsets_as_before_and_leaves_the_inputs(paper):
    """predict = tracker reading of (chain + point offset), plus the tracker offset: the plain sums, new arrays."""
    truth, rng, n = paper.truth, np.random.default_rng(6), 8
    M, p = truth.n_points, truth.n_params
    theta = paper.theta[None, :] + signed(rng, (n, p)) * 1e-4
    pert = {"point_offset": signed(rng, (n, M, 3)) * 1e-3, "tracker_offset": signed(rng, (n, M, 3)) * 1e-3,
            "axis_offset.y": signed(rng, (n, M)) * 1e-3, "axis_scale.z": signed(rng, (n, M)) * 1e-6,
            "spherical_noise": signed(rng, (n, M, 3)) * 1e-6, "pose": signed(rng, (n, 6)) * 1e-3}
    kept = {k: v.copy() for k, v in pert.items()}
    pose = np.atleast_2d(paper.pose) + pert["pose"]
    P_W = machine.chain(truth.config, truth.errors, theta, truth.chain_inputs(pert), B=truth.B) + pert["point_offset"]
    want = lt.read(P_W, pose, pert["spherical_noise"]) + pert["tracker_offset"]
    assert same_bits(truth.predict(theta, paper.pose, pert), want)
    assert same_bits(truth.machine_points(theta, pert), P_W)
    for k in kept:
        assert same_bits(pert[k], kept[k]), k
    # one trial's offsets against N trials' points: a new array of the broadcast shape
    one = {"point_offset": pert["point_offset"][:1]}
    got = truth.machine_points(theta, one)
    assert got.shape == (n, M, 3) and same_bits(got, truth.machine_points(theta) + one["point_offset"])


def test_kernel_chain_follows_a_changed_basis(paper):
    """What kernel_chain remembers between calls (axes, coefficient layout, squareness columns) follows the basis
    values by content: a basis changed in place, or another one, gets its own layout."""
    truth = paper.truth
    inp = truth.chain_inputs({})
    B = truth.B.copy()
    a = kernel_chain(truth.config, truth.errors, inp, B, 4)
    again = kernel_chain(truth.config, truth.errors, inp, B, 4)
    assert again is not a and all(same_bits(a[k], again[k]) for k in a)
    B[:, 0] *= 2.0  # in place
    b = kernel_chain(truth.config, truth.errors, inp, B, 4)
    assert not same_bits(a["L"], b["L"])
    fresh = machine._build_kernel_layout(truth.errors, B, truth.config.rotary_letters)
    assert same_bits(b["L"], fresh[0]) and same_bits(b["src"], fresh[1]) and same_bits(b["dst"], fresh[2])
    assert b["src"].dtype == b["dst"].dtype == b["sqi"].dtype == np.int64


def test_caller_reads_the_trace_setting_when_asked(monkeypatch, capsys):
    """plugins.caller(): the environment read once for a block's calls; a setting changed later applies to the
    next block."""
    class Thing:
        name = "thing"

        def hello(self, x):
            return x + 1

    monkeypatch.delenv("MTBUDGET_TRACE_PLUGINS", raising=False)
    quiet = plugins.caller()
    assert quiet(Thing(), "hello", 1) == 2
    assert "hello" not in capsys.readouterr().err
    monkeypatch.setenv("MTBUDGET_TRACE_PLUGINS", "1")
    traced = plugins.caller()
    assert traced(Thing(), "hello", 2) == 3
    assert "thing.hello" in capsys.readouterr().err


@pytest.mark.parametrize("direction, bmax", [((1.0, -1.0, 0.0, -0.0), "3 um"), ((1.0, -1.0, 0.0, -0.0), "1e-305 um"),
                                             ((0.1, -0.3, 1.0, 0.7), "1e-305 um")])
def test_backlash_halves_the_direction_only_when_that_gives_the_same_bits(paper, direction, bmax):
    """backlash draws B in [0, B_max] per axis and stops -d B / 2 short; with every d in {+-1, +-0} it multiplies by -d/2
    (the same bits), otherwise it divides as the formula says (-0.1 B / 2 and -0.05 B round differently where B is
    subnormal).  Compared with the formula, signed zeros included."""
    import copy
    from dataclasses import replace

    from mtbudget_plugins.machine_tool import Backlash

    plan = paper.plan
    d = np.resize(np.array(direction), plan.direction.shape)
    ctx = copy.copy(paper.context)
    ctx.plan = replace(plan, direction=d)
    src = Backlash(B_max=bmax)
    got = src.sample_internal(6, np.random.default_rng(8), ctx)
    rng = np.random.default_rng(8)
    B = rng.uniform(0, src.value("B_max", "mm"), (3, 6, 1))
    for i, a in enumerate("xyz"):
        want = (-d.T[i][None, :] * B[i]) / 2
        assert same_bits(got[f"axis_offset.{a}"], want), a
    if 0.0 in direction:  # both zeros are there to be told apart
        allv = np.concatenate([v.ravel() for v in got.values()])
        assert ((allv == 0) & np.signbit(allv)).any() and ((allv == 0) & ~np.signbit(allv)).any()


def test_rotation_is_eq22_element_by_element():
    """tracker.rotation writes each element's expression into its place: the same bits as the expressions of Eq. 22,
    for arrays (strided columns of a pose, as tracker.read passes them), scalars and the complex step of
    pose_jacobian."""
    rng = np.random.default_rng(9)
    pose = rng.normal(0, 0.3, (7, 6))
    cases = [(pose[:, 3], pose[:, 4], pose[:, 5]), (0.1, -0.2, 0.3), (pose[0, 3] + 1e-30j, pose[0, 4], pose[0, 5])]
    for a, b, d in cases:
        a, b, d = np.broadcast_arrays(np.asarray(a), np.asarray(b), np.asarray(d))
        ca, sa, cb, sb, cd, sd = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(d), np.sin(d)
        want = np.empty(a.shape + (3, 3), dtype=np.result_type(a, float))
        want[..., 0, :] = np.stack(np.broadcast_arrays(cb * cd, -cb * sd, sb), axis=-1)
        want[..., 1, :] = np.stack([ca * sd + sa * sb * cd, ca * cd - sa * sb * sd, -sa * cb], axis=-1)
        want[..., 2, :] = np.stack([sa * sd - ca * sb * cd, sa * cd + ca * sb * sd, ca * cb], axis=-1)
        assert same_bits(lt.rotation(a, b, d), want)


def test_kernel_array_is_np_require_c_w():
    """machine.kernel_array: what np.require(x, float64, ["C", "W"]) gives (the same values, C-contiguous, writable,
    float64; x itself exactly when np.require returns x itself)."""
    p = np.random.default_rng(10).random((8, 6))
    ro = p.copy()
    ro.flags.writeable = False
    for x in (p, p[:, :3], p.T, p[::2], np.broadcast_to(p[:1], (8, 6)), ro, p.astype(np.float32), [[1.0, 2.0]], 3.0):
        got, want = machine.kernel_array(x), np.require(x, np.float64, ["C", "W"])
        assert same_bits(got, want) and got.flags.c_contiguous and got.flags.writeable
        assert (got is x) == (want is x)
        if got is not x and isinstance(x, np.ndarray):
            assert not np.shares_memory(got, x)
