"""The compiled kernels (mtbudget/kernels.py) against independent formulations.

The chain's points against ``machine.chain_reference`` (3 x 3 matrices per point, the paper's Eq. 6 as
matrices), for every configuration; the chord's weighted residual and gradient against the formulas
written out here with numpy; and the property the engine relies on: a trial's numbers do not depend on
the other trials computed with it, bit for bit.
"""

import numpy as np
import pytest

from mtbudget.kernels import chord_residual
from mtbudget.machine import ALL_CONFIGURATIONS, ChainInputs, Configuration, ErrorModel, chain, chain_reference


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(11)
    M = 33
    nom, tool = rng.uniform(-300, 300, (M, 3)), rng.uniform(-100, 100, (M, 3))
    return rng, M, nom, tool


@pytest.mark.parametrize("code", ALL_CONFIGURATIONS)
def test_compiled_chain_points_equal_the_matrix_formulation(code, setup):
    rng, M, nom, tool = setup
    cfg = Configuration.parse(code)
    for conv in ("iso230", "free"):
        em = ErrorModel.default(nom, 4, straightness_convention=conv, tool_axis=cfg.tool[-1] if cfg.tool else None)
        th = rng.standard_normal((4, len(em.params))) * 1e-4
        inp = ChainInputs(nom, tool, offset={"y": rng.standard_normal((4, M)) * 1e-3},
                          scale={"x": rng.standard_normal((1, M)) * 1e-5, "z": 2e-5})
        got = chain(cfg, em, th, inp)
        ref = chain_reference(cfg, em, th, inp)
        assert got.shape == (4, M, 3)
        assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max(), code


def test_compiled_chain_of_a_reduced_model_and_a_single_trial(setup):
    rng, M, nom, tool = setup
    cfg = Configuration.parse("XFYZ")
    em = ErrorModel(ranges={a: (-300, 300) for a in "xyz"}, degrees={"dx(x)": 2, "ey(z)": 1}, squareness=False)
    th = rng.standard_normal((1, len(em.params))) * 1e-4
    inp = ChainInputs(nom, tool)
    assert np.abs(chain(cfg, em, th, inp) - chain_reference(cfg, em, th, inp)).max() <= 1e-12 * 300
    # no error at all: the nominal chain, exactly
    zero = chain(cfg, em, np.zeros((2, len(em.params))), inp)
    assert np.array_equal(zero[0], zero[1])
    assert np.abs(zero[0] - (tool + nom)).max() <= 1e-12  # every axis moves the tool by +p relative to the part


def reference_residual(P, meas, WL, idx, R, T, c0):
    """The chord's quantities written out: r = x - R^T (P - T), u = C^-1 r, v = R u, the cost r.u, the sum of v
    and the torque sum (P - c0) x v."""
    x = meas[idx]
    W = np.moveaxis(WL[:, :, idx], (0, 1), (-2, -1))  # (n, M, 3, 3)
    r = x - np.einsum("nji,nmj->nmi", R, P - T[:, None])
    u = np.einsum("nmij,nmj->nmi", W, r)
    v = np.einsum("nij,nmj->nmi", R, u)
    cost = np.einsum("nmi,nmi->n", r, u)
    torque = np.cross(P - c0, v).sum(axis=1)
    return v, np.concatenate([v.sum(axis=1), torque], axis=1), cost


def test_chord_residual_against_the_formulas_and_trial_by_trial(setup):
    rng, M, _, _ = setup
    N = 7
    meas = rng.uniform(-1000, 1000, (N, M, 3))
    A = rng.standard_normal((N, M, 3, 3))
    WL = np.ascontiguousarray(np.moveaxis(A @ np.swapaxes(A, -1, -2) + 3 * np.eye(3), (2, 3), (0, 1)))  # SPD
    idx = np.array([4, 0, 6, 2], np.int64)
    n = len(idx)
    q, _ = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    R = q * np.sign(np.linalg.det(q))[:, None, None]
    T = rng.uniform(-500, 500, (n, 3))
    P = rng.uniform(-1000, 1000, (n, M, 3))
    c0 = rng.uniform(-100, 100, 3)
    v, G, cost = np.empty((n, M, 3)), np.empty((n, 6)), np.empty(n)
    chord_residual(P, meas, WL, idx, R, T, c0, v, G, cost)
    v_ref, G_ref, cost_ref = reference_residual(P, meas, WL, idx, R, T, c0)
    assert np.abs(v - v_ref).max() <= 1e-12 * np.abs(v_ref).max()
    assert np.abs(G - G_ref).max() <= 1e-12 * np.abs(G_ref).max()
    assert np.abs(cost - cost_ref).max() <= 1e-12 * np.abs(cost_ref).max()
    # each trial alone: the same bits
    for k in range(n):
        v1, G1, c1 = np.empty((1, M, 3)), np.empty((1, 6)), np.empty(1)
        chord_residual(P[k:k + 1], meas, WL, idx[k:k + 1], R[k:k + 1], T[k:k + 1], c0, v1, G1, c1)
        assert np.array_equal(v1[0], v[k]) and np.array_equal(G1[0], G[k]) and c1[0] == cost[k]


def test_one_compiled_signature_per_kernel_across_the_engine_identify_and_diagnosis():
    """Every path calls the kernels with the same array types (C-contiguous, writable float64): one compilation
    each, never a second one in the middle of a run (a read-only view would be another numba type).  In a
    fresh interpreter, so that other tests' calls do not count."""
    import subprocess
    import sys

    from mtbudget import kernels

    code = """
import numpy as np
from mtbudget import kernels
from mtbudget.config import example_recording, load_config
from mtbudget.diagnose import diagnose
from mtbudget.identify import Noise, identify
from mtbudget.model import MeasurementModel
from mtbudget.recording import read_recording
from mtbudget.runner import run
run(load_config(), trials=128, attribution_trials=16)
rec = read_recording(example_recording("thermal_x"))
meas = np.asarray(rec.lt, float)
meas.setflags(write=False)
identify(MeasurementModel.for_plan(rec.machine, rec.plan), meas, Noise.of(rec))
diagnose(rec)
print([len(k.signatures) for k in kernels.KERNELS], [len(k.signatures) for k in (kernels.chain_vjp, kernels.chord_residual)])
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    used, others = out.strip().splitlines()[-1].split("] [")
    assert used == "[" + ", ".join(["1"] * len(kernels.KERNELS)), out  # every kernel the engine uses: compiled once
    assert all(c in "01" for c in others.rstrip("]").split(", ")), out  # the references: at most once


def test_the_first_run_after_installing_says_it_compiles(monkeypatch, capsys, setup):
    """A computing command whose kernels are not yet compiled says so on stderr (once per machine), on a terminal
    and piped alike (issue 29: piped, `study all` was silent 17 s); never with --quiet or --help, never for other
    commands; never on stdout; after a call the cache holds them."""
    import sys

    from mtbudget import cli, kernels

    rng, M, nom, tool = setup
    em = ErrorModel.default(nom, 2)
    chain(Configuration.parse("XFYZ"), em, np.zeros((2, len(em.params))), ChainInputs(nom, tool))
    assert kernels.compiled_here() is True
    monkeypatch.setattr(kernels, "compiled_here", lambda: False)
    for tty in (True, False):
        monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)
        for args, said in ((["run", "--trials", "10"], True), (["study", "all"], True), (["run", "--quiet"], False),
                           (["diagnose", "--help"], False), (["plugins"], False), ([], False)):
            cli._first_run_note(args)
            out = capsys.readouterr()
            assert ("compiling the engine's kernels" in out.err) is said and out.out == "", (tty, args)


def test_the_adjoint_refuses_positions_outside_its_trials(setup):
    """The compiled J^T v does not check bounds itself: the operator refuses what the kernel would misread."""
    from mtbudget.machine import chain_adjoint

    rng, M, nom, tool = setup
    em = ErrorModel.default(nom, 2)
    _, adj = chain_adjoint(Configuration.parse("XFYZ"), em, np.zeros((4, len(em.params))), ChainInputs(nom, tool))
    v = rng.standard_normal((2, M, 3))
    assert adj(v, np.array([1, 3])).shape == (2, len(em.params))
    for bad in (np.array([1, 7]), np.array([-1, 0]), np.array([True, False, True, False]), np.array([0.0, 1.0])):
        with pytest.raises(IndexError):
            adj(v, bad)
    with pytest.raises(ValueError):
        adj(v[:1], np.array([1, 3]))


def test_without_a_writable_cache_the_kernels_compile_in_memory(tmp_path):
    """A read-only installation and a home where no cache can be made: the kernels still compute (numba compiles
    in memory, once per process) instead of failing at import.  kernels.py imports only numpy and numba: it is
    loaded here on its own from a folder whose __pycache__ is a file."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import mtbudget.kernels

    ro = tmp_path / "ro"
    ro.mkdir()
    shutil.copy(Path(mtbudget.kernels.__file__), ro / "kernels_copy.py")
    (ro / "__pycache__").write_text("")  # a file where numba would put its cache
    blocker = tmp_path / "afile"
    blocker.write_text("")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(PYTHONPATH=str(ro), XDG_CACHE_HOME=str(blocker / "cache"), HOME=str(blocker / "home"))
    code = ("import numpy as np, kernels_copy as k\n"
            "M = 4; v, G, c = np.empty((1, M, 3)), np.empty((1, 6)), np.empty(1)\n"
            "k.chord_residual(np.ones((1, M, 3)), np.zeros((1, M, 3)), np.ones((3, 3, 1, M)), np.zeros(1, np.int64),"
            " np.eye(3)[None].copy(), np.zeros((1, 3)), np.zeros(3), v, G, c)\n"
            "print(c[0], k.compiled_here())")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["36.0", "None"]  # r = -1 per coordinate, C^-1 all ones: r.u = 3 x 3 per point


def test_tracker_points_equal_to_tracker_then_spherical_noise():
    """The compiled measurement step (MeasurementModel.predict) against tracker.to_tracker followed by
    tracker.add_spherical_noise, the numpy formulation: points all round a tracker and at its centre, one pose per
    trial or one for all, with and without noise.  (Not on its vertical axis: there the azimuth is whatever the
    round-off of x and y makes it, in either formulation.)"""
    from mtbudget import tracker as lt
    from mtbudget.kernels import tracker_points

    rng = np.random.default_rng(3)
    P = rng.normal(0, 800, (6, 9, 3))
    pose = np.c_[rng.normal(0, 300, (6, 3)), rng.normal(0, 1, (6, 3))]
    P[:, 0] = pose[:, :3]  # the tracker's centre
    noise = rng.normal(0, 1e-3, P.shape)
    R = np.ascontiguousarray(lt.rotation(pose[:, 3], pose[:, 4], pose[:, 5]))
    T = np.ascontiguousarray(pose[:, :3])
    got = tracker_points(P, R, T, noise, np.empty(P.shape))
    assert np.abs(got - lt.add_spherical_noise(lt.to_tracker(P, pose), noise)).max() < 1e-10
    got = tracker_points(P, R[:1].copy(), T[:1].copy(), np.zeros((0, 9, 3)), np.empty(P.shape))
    assert np.abs(got - lt.to_tracker(P, np.broadcast_to(pose[:1], (6, 6)))).max() < 1e-10


def test_tracker_read_broadcasts_trials_as_to_tracker_does():
    """tracker.read: one set of points seen from several poses, several from one, per-trial noise on one set of
    points: the trials broadcast as to_tracker and add_spherical_noise broadcast them; shapes that do not broadcast
    are refused (never a read beyond an array)."""
    from mtbudget import tracker as lt

    rng = np.random.default_rng(4)
    P1, P3 = rng.normal(0, 800, (1, 5, 3)), rng.normal(0, 800, (3, 5, 3))
    poses = np.c_[rng.normal(0, 300, (3, 3)), rng.normal(0, 1, (3, 3))]
    noise = rng.normal(0, 1e-3, (3, 5, 3))
    for P, pose, nz in ((P1, poses, None), (P3, poses[:1], None), (P1, poses[:1], noise), (P3, poses, noise)):
        ref = lt.to_tracker(np.broadcast_to(P, (3, 5, 3)), np.broadcast_to(pose, (3, 6)))
        if nz is not None:
            ref = lt.add_spherical_noise(ref, nz)
        got = lt.read(P, pose, nz)
        assert got.shape == (3, 5, 3) and np.abs(got - ref).max() < 1e-10
    with pytest.raises(ValueError):
        lt.read(rng.normal(0, 800, (5, 4, 3)), poses[:2])
