"""The one laser-tracker model: pose (paper Eq. 21-22), spherical measurement, noise.

Pose: the tracker frame in the machine (workpiece) frame is given by the
translation ``T_LT = (D, L, H)`` (Eq. 21) and the rotation ``R_LT(a, b, d)``
of Eq. 22.  A point ``P_W`` in the workpiece frame is seen by the tracker at
``P_LT = R_LT^T (P_W - T_LT)`` (the outer part of Eq. 2).

Measurement: the tracker measures range ``r``, azimuth ``az`` (about its own z
axis, from x) and elevation ``el`` (from its xy plane).  Noise is normal with
``u_r = a + b r`` and the same angular standard uncertainty for both angles.
The Cartesian covariance is ``J diag(u_r^2, u_az^2, u_el^2) J^T`` with the
exact Jacobian of the spherical-to-Cartesian map.

About the paper's Eq. 23: its rows are the diagonal of that same product
when its ``theta`` is read as the polar angle from the z axis and ``phi`` as
the azimuth (the text names them the other way round), and it drops the
off-diagonal covariances.  Eq. 24 (the trace) is unaffected; a weighted fit
that used only the diagonal would mis-weight points whose beam is not along
a machine axis.  ``tests/test_tracker.py`` shows both facts numerically.
"""

from __future__ import annotations

import numpy as np

from .machine import broadcast_shape, kernel_array

POSE_NAMES = ("D", "L", "H", "a", "b", "d")
POSE_UNITS = ("mm", "mm", "mm", "rad", "rad", "rad")


def rotation(a, b, d) -> np.ndarray:
    """Eq. 22 rotation matrix, vectorised over the shapes of a, b, d: (..., 3, 3)."""
    a, b, d = np.asarray(a), np.asarray(b), np.asarray(d)
    if not a.shape == b.shape == d.shape:
        a, b, d = np.broadcast_arrays(a, b, d)
    ca, sa, cb, sb, cd, sd = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(d), np.sin(d)
    R = np.empty(a.shape + (3, 3), dtype=np.result_type(a, float))
    # each element's expression written into its place (no temporary and copy): cb cd, -cb sd, sb, ...
    sasb, casb = sa * sb, ca * sb
    np.multiply(cb, cd, out=R[..., 0, 0])
    np.multiply(-cb, sd, out=R[..., 0, 1])
    R[..., 0, 2] = sb
    np.add(ca * sd, sasb * cd, out=R[..., 1, 0])
    np.subtract(ca * cd, sasb * sd, out=R[..., 1, 1])
    np.multiply(-sa, cb, out=R[..., 1, 2])
    np.subtract(sa * sd, casb * cd, out=R[..., 2, 0])
    np.add(sa * cd, casb * sd, out=R[..., 2, 1])
    np.multiply(ca, cb, out=R[..., 2, 2])
    return R


def euler_from_rotation(R: np.ndarray) -> np.ndarray:
    """Angles (a, b, d) of Eq. 22 from a rotation matrix (..., 3, 3); |b| < pi/2."""
    b = np.arcsin(np.clip(R[..., 0, 2], -1.0, 1.0))
    d = np.arctan2(-R[..., 0, 1], R[..., 0, 0])
    a = np.arctan2(-R[..., 1, 2], R[..., 2, 2])
    return np.stack([a, b, d], axis=-1)


def to_tracker(P_W: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points (N, M, 3) in the workpiece frame to the tracker frame, pose (N, 6)."""
    pose = np.atleast_2d(pose)
    R = rotation(pose[:, 3], pose[:, 4], pose[:, 5])
    return (P_W - pose[:, None, :3]) @ R  # R^T (P - T) for every point: one small product per trial


def to_machine(P_LT: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_tracker`."""
    pose = np.atleast_2d(pose)
    R = rotation(pose[:, 3], pose[:, 4], pose[:, 5])
    return P_LT @ np.swapaxes(R, 1, 2) + pose[:, None, :3]


def pose_jacobian(P_W: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """d P_LT / d pose (N, M, 3, 6), exact (angle derivatives by complex step)."""
    pose = np.atleast_2d(pose)
    N, M = P_W.shape[:2]
    R = rotation(pose[:, 3], pose[:, 4], pose[:, 5])
    J = np.empty((N, M, 3, 6))
    J[..., :3] = -np.swapaxes(R, 1, 2)[:, None, :, :]
    h = 1e-30
    diff = P_W - pose[:, None, :3]
    for k in range(3):
        ang = pose[:, 3:].astype(complex)
        ang[:, k] += 1j * h
        dR = rotation(ang[:, 0], ang[:, 1], ang[:, 2]).imag / h  # (N,3,3), exact by complex step
        J[..., 3 + k] = diff @ dR  # (dR^T (P - T)) for every point
    return J


def spherical(P_LT: np.ndarray):
    """(r, azimuth, elevation) of Cartesian tracker points (..., 3)."""
    x, y, z = P_LT[..., 0], P_LT[..., 1], P_LT[..., 2]
    rho = np.hypot(x, y)
    return np.hypot(rho, z), np.arctan2(y, x), np.arctan2(z, rho)


def cartesian(r, az, el) -> np.ndarray:
    ce = np.cos(el)
    return np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el)], axis=-1)


def spherical_jacobian(P_LT: np.ndarray) -> np.ndarray:
    """d(x, y, z)/d(r, az, el) at the points: (..., 3, 3)."""
    r, az, el = spherical(P_LT)
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    J = np.empty(P_LT.shape[:-1] + (3, 3))
    J[..., 0, 0], J[..., 0, 1], J[..., 0, 2] = ce * ca, -r * ce * sa, -r * se * ca
    J[..., 1, 0], J[..., 1, 1], J[..., 1, 2] = ce * sa, r * ce * ca, -r * se * sa
    J[..., 2, 0], J[..., 2, 1], J[..., 2, 2] = se, 0.0, r * ce
    return J


def norm3(P: np.ndarray) -> np.ndarray:
    """|P| over the last axis of length 3: the sum of squares in order, as ``np.linalg.norm`` (the same bits), without
    its general-purpose overhead."""
    x, y, z = P[..., 0], P[..., 1], P[..., 2]
    return np.sqrt(x * x + y * y + z * z)


def covariance(P_LT: np.ndarray, angular, distance, distance_per_length, angular_elevation=None) -> np.ndarray:
    """Cartesian covariance (..., 3, 3) of a tracker point (the paper's Eq. 23, exact), internal units.

    angular: rad, the standard uncertainty of the azimuth (and of the
    elevation unless ``angular_elevation`` is given); distance: mm;
    distance_per_length: mm/mm (u_r = distance + distance_per_length * r).

    ``J diag(u_r^2, u_az^2, u_el^2) J^T`` with the columns of the spherical Jacobian written as
    u_r along the beam e_r, r cos(el) u_az along e_az = (-sin az, cos az, 0) and r u_el along
    e_el = (-sin el cos az, -sin el sin az, cos el): the six distinct entries, elementwise (the
    directions from the coordinates, no trigonometry).  :func:`covariance_reference` is the
    matrix product itself.
    """
    P = np.asarray(P_LT, float)
    x, y, z = P[..., 0], P[..., 1], P[..., 2]
    rho = np.hypot(x, y)  # r cos(el)
    r = np.hypot(rho, z)
    with np.errstate(invalid="ignore", divide="ignore"):  # on the axes the angles of spherical() are 0
        ca = np.where(rho > 0, x / rho, 1.0)
        sa = np.where(rho > 0, y / rho, 0.0)
        ce = np.where(r > 0, rho / r, 1.0)
        se = np.where(r > 0, z / r, 0.0)
    ur = np.asarray(distance) + np.asarray(distance_per_length) * r
    ue = angular if angular_elevation is None else angular_elevation
    A = ur * ur  # along the beam
    Bv = (np.asarray(angular) * rho) ** 2  # along e_az
    Cv = (np.asarray(ue) * r) ** 2  # along e_el
    rx, ry = ce * ca, ce * sa  # e_r = (rx, ry, se)
    ex, ey = se * ca, se * sa  # e_el = (-ex, -ey, ce)
    C = np.empty(np.broadcast_shapes(r.shape, np.shape(A), np.shape(Bv), np.shape(Cv)) + (3, 3))
    C[..., 0, 0] = A * rx * rx + Bv * sa * sa + Cv * ex * ex
    C[..., 1, 1] = A * ry * ry + Bv * ca * ca + Cv * ey * ey
    C[..., 2, 2] = A * se * se + Cv * ce * ce
    C[..., 0, 1] = C[..., 1, 0] = A * rx * ry - Bv * sa * ca + Cv * ex * ey
    C[..., 0, 2] = C[..., 2, 0] = A * rx * se - Cv * ex * ce
    C[..., 1, 2] = C[..., 2, 1] = A * ry * se - Cv * ey * ce
    return C


def covariance_reference(P_LT: np.ndarray, angular, distance, distance_per_length, angular_elevation=None) -> np.ndarray:
    """:func:`covariance` as the matrix product ``J S J^T`` with :func:`spherical_jacobian` (the reference)."""
    r = np.linalg.norm(P_LT, axis=-1)
    ur = np.asarray(distance) + np.asarray(distance_per_length) * r
    ua = np.broadcast_to(np.asarray(angular, float), r.shape)
    ue = ua if angular_elevation is None else np.broadcast_to(np.asarray(angular_elevation, float), r.shape)
    J = spherical_jacobian(P_LT)
    S = np.stack([ur**2, ua**2, ue**2], axis=-1)
    return np.einsum("...ij,...j,...kj->...ik", J, S, J)


def point_uncertainty(P_LT: np.ndarray, angular, distance, distance_per_length, angular_elevation=None) -> np.ndarray:
    """u_p of the paper's Eq. 24: the square root of the trace of :func:`covariance`, without forming it.

    The trace of J S J^T is u_r^2 + (r cos(el) u_az)^2 + (r u_el)^2, since the
    columns of the spherical Jacobian have lengths 1, r cos(el) and r.
    """
    r = norm3(P_LT)
    rho = np.hypot(P_LT[..., 0], P_LT[..., 1])  # r cos(el)
    ur = np.asarray(distance) + np.asarray(distance_per_length) * r
    ue = angular if angular_elevation is None else angular_elevation
    return np.sqrt(ur**2 + (rho * angular) ** 2 + (r * ue) ** 2)


def eq23_variances(P_LT: np.ndarray, u_r, u_angle) -> np.ndarray:
    """The paper's Eq. 23 as printed, theta = polar angle from z, phi = azimuth: (..., 3)."""
    x, y, z = P_LT[..., 0], P_LT[..., 1], P_LT[..., 2]
    r = np.linalg.norm(P_LT, axis=-1)
    th = np.arccos(z / r)
    ph = np.arctan2(y, x)
    s2t, c2t, s2p, c2p = np.sin(th) ** 2, np.cos(th) ** 2, np.sin(ph) ** 2, np.cos(ph) ** 2
    ur2, ut2, up2 = np.asarray(u_r) ** 2, np.asarray(u_angle) ** 2, np.asarray(u_angle) ** 2
    ux2 = s2t * c2p * ur2 + r**2 * c2t * c2p * ut2 + r**2 * s2t * s2p * up2
    uy2 = s2t * s2p * ur2 + r**2 * c2t * s2p * ut2 + r**2 * s2t * c2p * up2
    uz2 = c2t * ur2 + r**2 * s2t * ut2
    return np.stack([ux2, uy2, uz2], axis=-1)


def read(P_W: np.ndarray, pose: np.ndarray, noise: np.ndarray | None = None) -> np.ndarray:
    """What the tracker reads of the machine points P_W (N, M, 3) from pose (1 or N, 6): :func:`to_tracker`, then
    :func:`add_spherical_noise` with ``noise`` (broadcastable to P_W's shape; None: none), in one compiled pass
    (:func:`mtbudget.kernels.tracker_points`: their numbers, round-off apart)."""
    from .kernels import tracker_points

    pose = np.atleast_2d(np.asarray(pose, float))
    P_W = np.asarray(P_W, float)
    # the trials of the points, the pose and the noise broadcast together (to_tracker and add_spherical_noise's rule;
    # shapes that do not broadcast raise ValueError, as there)
    n = broadcast_shape(P_W.shape[:1], pose.shape[:1], P_W.shape[:1] if noise is None else np.shape(noise)[:1])
    shape = n + P_W.shape[1:]
    P_W = _broadcast(P_W, shape)
    if noise is not None:
        noise = _broadcast(noise, shape)
    pose = _broadcast(pose, n + (6,))
    return tracker_points(kernel_array(P_W), kernel_array(rotation(pose[:, 3], pose[:, 4], pose[:, 5])),
                          kernel_array(pose[:, :3]),
                          kernel_array(noise) if noise is not None else np.zeros((0,) + P_W.shape[1:]), np.empty(P_W.shape))


def _broadcast(x, shape: tuple):
    """``np.broadcast_to(x, shape)``, or ``x`` itself when it has that shape already (a read-only view of it would be
    copied for the kernel)."""
    return x if np.shape(x) == shape else np.broadcast_to(x, shape)


def add_spherical_noise(P_LT: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Apply (dr, daz, del) offsets (..., 3) in spherical coordinates exactly."""
    r, az, el = spherical(P_LT)
    return cartesian(r + noise[..., 0], az + noise[..., 1], el + noise[..., 2])


def smr_offset(P_LT: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """Shift of the measured centre when the beam strikes the reflector off centre.

    ``lateral`` (..., 2) are offsets (mm) in the plane perpendicular to the
    beam (along the azimuth and elevation directions).
    """
    J = spherical_jacobian(P_LT)
    e_az = J[..., :, 1] / np.linalg.norm(J[..., :, 1], axis=-1, keepdims=True)
    e_el = J[..., :, 2] / np.linalg.norm(J[..., :, 2], axis=-1, keepdims=True)
    return lateral[..., :1] * e_az + lateral[..., 1:2] * e_el


def register(P_W: np.ndarray, P_LT: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Closed-form rigid registration (Kabsch) of tracker points onto machine points.

    Returns the pose (N, 6) such that ``to_tracker(P_W, pose) ~ P_LT``; used as
    the starting point of every identification, so a tracker far from any
    guess is still found.
    """
    P_W = np.asarray(P_W, float)
    P_LT = np.asarray(P_LT, float)
    if P_W.ndim == 2:
        P_W = P_W[None]
    P_W = np.broadcast_to(P_W, P_LT.shape)
    w = np.ones(P_LT.shape[:2]) if weights is None else np.broadcast_to(weights, P_LT.shape[:2])
    w = w / w.sum(axis=1, keepdims=True)
    wc = w[:, None, :]  # (N, 1, M): the weighted sums over the points as one small product per trial
    cw = (wc @ P_W)[:, 0]
    cl = (wc @ P_LT)[:, 0]
    H = np.swapaxes((P_LT - cl[:, None]) * w[..., None], 1, 2) @ (P_W - cw[:, None])  # sum_m w_m a_m b_m^T
    U, _, Vt = np.linalg.svd(H)
    det = np.sign(np.linalg.det(U @ Vt))
    # R = V diag(1, 1, det) U^T maps tracker-frame vectors to machine-frame vectors: P_W = R P_LT + T
    VD = np.swapaxes(Vt, 1, 2).copy()
    VD[:, :, 2] *= det[:, None]
    R = VD @ np.swapaxes(U, 1, 2)
    T = cw - (R @ cl[:, :, None])[:, :, 0]
    return np.concatenate([T, euler_from_rotation(R)], axis=1)
