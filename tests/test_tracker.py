"""Tracker pose (Eq. 21-22), spherical noise and its Cartesian covariance (Eq. 23-24)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mtbudget import tracker as lt


def Rx(a):
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def Ry(b):
    return np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])


def Rz(d):
    return np.array([[np.cos(d), -np.sin(d), 0], [np.sin(d), np.cos(d), 0], [0, 0, 1]])


def test_pose_hand_computed_case():
    # a = b = 0, d = 90 deg: the tracker x axis points along machine +y
    R = lt.rotation(0.0, 0.0, np.pi / 2)
    assert np.allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    # a point 1 m along machine +y from the tracker at (D, L, H) = (-500, 200, 700) is at tracker (1000, 0, 0)
    P = np.array([[[-500.0, 1200.0, 700.0]]])
    got = lt.to_tracker(P, np.array([[-500.0, 200.0, 700.0, 0.0, 0.0, np.pi / 2]]))
    assert np.allclose(got, [[[1000.0, 0.0, 0.0]]], atol=1e-12)


@given(st.floats(-3, 3), st.floats(-1.5, 1.5), st.floats(-3, 3))
def test_eq22_is_rx_ry_rz_and_a_rotation(a, b, d):
    R = lt.rotation(a, b, d)
    assert np.allclose(R, Rx(a) @ Ry(b) @ Rz(d), atol=1e-14)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0)
    ang = lt.euler_from_rotation(R)
    assert np.allclose(lt.rotation(*ang), R, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.floats(-3, 3), st.floats(-1.2, 1.2), st.floats(-3, 3), st.floats(-3000, 3000), st.floats(-3000, 3000))
def test_register_recovers_any_pose(a, b, d, D, H):
    rng = np.random.default_rng(0)
    P = rng.uniform([800, 100, 50], [1200, 500, 400], (40, 3))[None]
    pose = np.array([[D, 150.0, H, a, b, d]])
    got = lt.register(P, lt.to_tracker(P, pose))
    assert np.allclose(lt.rotation(*got[0, 3:]), lt.rotation(a, b, d), atol=1e-10)
    assert np.allclose(got[0, :3], pose[0, :3], atol=1e-7)


def test_pose_jacobian_matches_finite_differences(rng):
    P = rng.uniform([800, 100, 50], [1200, 500, 400], (2, 20, 3))
    pose = np.array([[-600.0, 200.0, 700.0, 0.01, -0.02, 1.0], [-900.0, 100.0, 650.0, -0.003, 0.004, -0.3]])
    J = lt.pose_jacobian(P, pose)
    for k in range(6):
        h = 1e-4 if k < 3 else 1e-7
        pp, pm = pose.copy(), pose.copy()
        pp[:, k] += h
        pm[:, k] -= h
        fd = (lt.to_tracker(P, pp) - lt.to_tracker(P, pm)) / (2 * h)
        assert np.allclose(J[..., k], fd, atol=1e-5)


def test_cartesian_covariance_matches_monte_carlo_of_spherical_noise(rng):
    pts = np.array([[1500.0, 300.0, -600.0], [200.0, 1800.0, 900.0], [-700.0, -400.0, 300.0]])
    angular, dist, ppm = 20e-6, 4e-3, 0.8e-6
    C = lt.covariance(pts, angular, dist, ppm)
    n = 400_000
    r = np.linalg.norm(pts, axis=1)
    noise = np.stack([rng.standard_normal((n, 3)) * (dist + ppm * r),
                      rng.standard_normal((n, 3)) * angular, rng.standard_normal((n, 3)) * angular], axis=-1)
    sample = lt.add_spherical_noise(np.broadcast_to(pts, (n, 3, 3)), noise) - pts
    for i in range(3):
        emp = np.cov(sample[:, i, :].T)
        scale = np.sqrt(np.outer(np.diag(C[i]), np.diag(C[i])))
        # each element within 5 standard errors of a covariance estimate (~ sqrt(2/n) of the scale)
        assert np.all(np.abs(emp - C[i]) < 5 * np.sqrt(2 / n) * scale + 1e-18)
    # the point uncertainty u_p^2 (Eq. 24) is the trace: u_r^2 + (r u_a cos el)^2 + (r u_a)^2
    up2 = np.trace(C, axis1=1, axis2=2)
    cos_el = np.hypot(pts[:, 0], pts[:, 1]) / r
    assert np.allclose(up2, (dist + ppm * r) ** 2 + (angular * r) ** 2 * (1 + cos_el**2), rtol=1e-12)


def test_eq23_is_the_diagonal_with_theta_the_polar_angle_and_misses_correlations(rng):
    pts = rng.uniform(-2000, 2000, (50, 3))
    C = lt.covariance(pts, 20e-6, 4e-3, 0.0)
    v23 = lt.eq23_variances(pts, 4e-3, 20e-6)
    assert np.allclose(np.diagonal(C, axis1=1, axis2=2), v23, rtol=1e-10)
    corr = C[:, 0, 1] / np.sqrt(C[:, 0, 0] * C[:, 1, 1])
    assert np.abs(corr).max() > 0.3  # the off-diagonal terms Eq. 23 leaves out are not small


def test_smr_offset_is_perpendicular_to_the_beam(rng):
    pts = rng.uniform(-2000, 2000, (20, 3))
    lat = rng.normal(0, 0.01, (20, 2))
    d = lt.smr_offset(pts, lat)
    assert np.allclose(np.einsum("ij,ij->i", d, pts), 0.0, atol=1e-9)
    assert np.allclose(np.linalg.norm(d, axis=1), np.linalg.norm(lat, axis=1))


def test_covariance_written_entry_by_entry_equals_the_jacobian_product():
    """tracker.covariance (six entries from the coordinates) against covariance_reference (J S J^T with the
    spherical Jacobian), anywhere around the tracker, including straight up and straight down."""
    from mtbudget.tracker import covariance, covariance_reference

    rng = np.random.default_rng(5)
    P = rng.uniform(-4000, 4000, (50, 40, 3))
    P[0, 0], P[0, 1] = [0.0, 0.0, 1500.0], [0.0, 0.0, -20.0]
    for ue in (None, 3e-5):
        a = covariance(P, 2e-5, 4e-3, 8e-7, ue)
        b = covariance_reference(P, 2e-5, 4e-3, 8e-7, ue)
        assert np.abs(a - b).max() <= 1e-14 * np.abs(b).max()
        assert np.array_equal(a, np.swapaxes(a, -1, -2))
    one = covariance(P[3, 7], 2e-5, 4e-3, 8e-7)
    assert one.shape == (3, 3) and np.allclose(one, covariance_reference(P[3, 7], 2e-5, 4e-3, 8e-7), rtol=1e-13)
