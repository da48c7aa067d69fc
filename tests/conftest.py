import numpy as np
import pytest

from mtbudget.config import example_recording, load_config
from mtbudget.contracts import Group, Source
from mtbudget.recording import read_recording
from mtbudget.units import Q_

EXAMPLES = ("null", "thermal_x", "reversal_y", "tracker_drift")


@pytest.fixture(scope="session")
def null_recording():
    return read_recording(example_recording("null"))


@pytest.fixture(scope="session")
def default_config():
    return load_config()


#: the eight candidate families before issue 16: spindle growth, column tilt, tool length and the two-axis terms are
#: outside it (the calibration's "against the original library" rows)
ORIGINAL_LIBRARY = {"thermal_expansion", "reversal", "tracker_drift", "tracker_range_offset", "tracker_range_scale",
                    "air_temperature_drift", "approximation_degree", "axis_coupling"}


@pytest.fixture(scope="session")
def candidates():
    """Every registered diagnosis candidate."""
    from mtbudget.plugins import default_host

    return default_host().candidates()


@pytest.fixture(scope="session")
def original_library(candidates):
    """The library before issue 16: what an effect outside it meets."""
    return [c for c in candidates if c.effect in ORIGINAL_LIBRARY]


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session", autouse=True)
def one_blas_thread():
    """The suite's matrices are small: one BLAS thread is faster, and much faster on a shared 2-core machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


@pytest.fixture(scope="session")
def null():
    """The null example and its compensation table (50 mm grid): (recording, table)."""
    from mtbudget.compensate import build_table

    rec = read_recording(example_recording("null"))
    return rec, build_table(rec, 50.0)


@pytest.fixture(scope="session")
def reversal():
    """The reversal_y example and its compensation table (50 mm grid): (recording, table)."""
    from mtbudget.compensate import build_table

    rec = read_recording(example_recording("reversal_y"))
    return rec, build_table(rec, 50.0)


def rigid_free(P):
    """I - the projector onto translations and small rotations (about the centroid) of the points P (M, 3)."""
    c = P - P.mean(axis=0)
    cols = []
    for k in range(3):
        t = np.zeros_like(P)
        t[:, k] = 1.0
        cols.append(t.ravel())
    for k in range(3):
        w = np.zeros(3)
        w[k] = 1.0
        cols.append(np.cross(w, c).ravel())
    A = np.array(cols).T
    return np.eye(len(A)) - A @ np.linalg.pinv(A)


def independent_fit(sc, h=1e-4):
    """The identification's weighted least squares, written here without the engine, to first order: central finite
    differences of the model in the pose and the geometric errors, the tracker covariance of Eq. 23 written here,
    the errors the plan cannot tell apart kept at their initial value, the rigid part removed by a projector written
    here.  Returns (P (3 M0, 3 M0) the rigid-part remover at the mesh points, Jm (3 M0, p) the compensated field's
    Jacobian, KB (p, 3 M) the identified errors per machine-frame displacement of the measured points, sel (3 M0, 3 M)
    the mesh rows of the plan).  A displacement d (3 M,) of the measured points leaves P (sel d - Jm KB d) when the
    machine moves with it (model form), -P Jm KB d when only the measurements see it (a scale's expansion beyond the
    correction).  Used by tests/test_model_form.py and tests/test_thermal_correction.py."""
    model, pose, rows = sc.id_model, np.asarray(sc.pose, float), sc.mesh_rows
    p = model.n_params
    th0 = np.zeros(p)
    steps = np.array([h if q.unit == "mm" else h / 1000.0 for q in model.errors.params] + [h] * 3 + [h / 1000.0] * 3)
    E = np.eye(p + 6) * steps
    th = np.concatenate([th0 + E[:, :p], th0 - E[:, :p]])
    po = np.concatenate([pose + E[:, p:], pose - E[:, p:]])
    m = model.predict(th, po)  # (2 (p + 6), M, 3) tracker coordinates
    A = ((m[:p + 6] - m[p + 6:]) / (2 * steps[:, None, None])).reshape(p + 6, -1).T  # (3 M, p + 6)
    m0 = model.predict(th0[None], pose)[0]
    M = len(m0)
    # the measured points move with the machine-frame displacement, rotated into the tracker frame
    R = np.stack([(model.predict(th0[None], pose, {"point_offset": np.broadcast_to(np.eye(3)[k], (1, M, 3))})[0]
                   - m0)[0] for k in range(3)], axis=1)  # (3, 3): tracker <- machine
    B = np.kron(np.eye(M), R)
    # Eq. 23: range u_d + u_dl r, both angles u_angular, plus the machine repeatability, at each point
    n = sc.noise
    r, az, el = np.linalg.norm(m0, axis=1), np.arctan2(m0[:, 1], m0[:, 0]), np.arcsin(m0[:, 2] / np.linalg.norm(m0, axis=1))
    W = np.zeros((3 * M, 3 * M))
    for i in range(M):
        ca, sa, ce, se = np.cos(az[i]), np.sin(az[i]), np.cos(el[i]), np.sin(el[i])
        J = np.array([[ce * ca, -r[i] * ce * sa, -r[i] * se * ca], [ce * sa, r[i] * ce * ca, -r[i] * se * sa],
                      [se, 0.0, r[i] * ce]])
        C = J @ np.diag([(n.distance + n.distance_per_length * r[i]) ** 2, n.angular**2, n.angular**2]) @ J.T
        W[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.linalg.inv(C + n.repeatability**2 * np.eye(3))
    # weighted least squares in um and urad; the geometric errors the plan cannot tell apart keep their initial value
    # (the identification's convention, docs: identifiability; it shows only at a tool the verification did not use)
    sv = np.array([1e3 if q.unit == "mm" else 1e6 for q in model.errors.params] + [1e3] * 3 + [1e6] * 3)
    As = A / sv
    norms = np.linalg.norm(As, axis=0)
    norms[norms == 0] = 1.0
    _, sing, Vt = np.linalg.svd(As / norms, full_matrices=False)
    null = (Vt.T / norms[:, None])[:, sing < 1e-7 * sing[0]]
    geo = np.linalg.svd(null[:p], full_matrices=True)[0]
    k = int(np.sum(np.linalg.svd(null[:p], compute_uv=False) > 1e-9))
    T = np.zeros((p + 6, p + 6 - k))  # free directions: the identifiable geometric ones and the pose
    T[:p, :p - k] = geo[:, k:]
    T[p:, p - k:] = np.eye(6)
    Ar = As @ T
    K = (T @ np.linalg.solve(Ar.T @ W @ Ar, Ar.T @ W)) / sv[:, None]
    # the compensated machine: the identified errors at the mesh points, at the verification's tool or at [measurand]
    # tool (there through the scenario's evaluation, differentiated here); the positioning error itself is the same
    points = (lambda t: sc.evaluate(model, t)) if sc.measurand_tool is not None else \
        (lambda t: model.machine_points(t)[:, rows])
    F = points(np.concatenate([th0 + E[:p, :p], th0 - E[:p, :p]]))
    Jm = ((F[:p] - F[p:]) / (2 * steps[:p, None, None])).reshape(p, -1).T  # (3 M0, p) compensated field
    sel = np.zeros((3 * len(rows), 3 * M))
    for j, i in enumerate(rows):
        sel[3 * j:3 * j + 3, 3 * i:3 * i + 3] = np.eye(3)
    P = rigid_free(points(th0[None])[0])
    return P, Jm, K[:p] @ B, sel


def unit_fields(obj, path=""):
    """(path, value) of every unit field: keys "unit" and "*_unit"."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if (k == "unit" or k.endswith("_unit")) and isinstance(v, str):
                yield f"{path}.{k}", v
            else:
                yield from unit_fields(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for v in obj:
            yield from unit_fields(v, path + "[]")


def plugin_module(name, register_fn, hook="mtbudget_register_sources"):
    """A plugin registered in code: a module whose ``hook`` is ``register_fn`` (tests of the plugin host)."""
    import types

    from mtbudget.hookspecs import hookimpl

    mod = types.ModuleType(name)
    setattr(mod, hook, hookimpl(register_fn))
    return mod


class OffsetSource(Source):
    """A minimal source registered in code: a normal offset of every measured point in the tracker frame, u = 1 um."""

    name = "good"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal"
    targets = ("tracker_offset",)
    parameters = {"u": Q_(1.0, "um")}

    def sample(self, n, rng, ctx):
        return {"tracker_offset": Q_(rng.normal(0, self.value("u", "mm"), (n, ctx.n_points, 3)), "mm")}


def stated_noise_propagation(field, m0, noise, h=2e-4):
    """Standard deviations of ``field(meas)`` ((K, M, 3) tracker coordinates -> (K, L) values) by central differences
    in the measured coordinates about the noise-free ``m0`` (M, 3), with the stated covariance of each point written
    here: spherical tracker noise (u_r = distance + distance_per_length r, one angular u for both angles) plus the
    machine repeatability, isotropic.  The independent linear propagation the per-point tests compare against."""
    from mtbudget import tracker as lt

    M = len(m0)
    E = np.eye(3 * M).reshape(3 * M, M, 3) * h
    S = ((field(m0[None] + E) - field(m0[None] - E)) / (2 * h)).T  # (L, 3 M)
    r = np.linalg.norm(m0, axis=1)
    sph = lt.spherical_jacobian(m0)  # columns: d/dr, d/daz, d/del
    C = np.zeros((3 * M, 3 * M))
    for i in range(M):
        s = np.diag([(noise.distance + noise.distance_per_length * r[i]) ** 2, noise.angular**2, noise.angular**2])
        C[3 * i:3 * i + 3, 3 * i:3 * i + 3] = sph[i] @ s @ sph[i].T + noise.repeatability**2 * np.eye(3)
    return np.sqrt(np.diag(S @ C @ S.T))


def compensated_field_propagation(sc, h=2e-4):
    """u (um) of each mesh point's compensated error of scenario ``sc``, by :func:`stated_noise_propagation` of
    simulate -> identify -> compensate about the noise-free verification: the independent linear propagation the
    per-point maps (tests/test_measurand.py, tests/test_fiveaxis_mc.py) are compared against (mm written here)."""
    from mtbudget.identify import identify

    m0 = sc.truth.predict(sc.theta[None, :], sc.pose)[0]  # (M, 3) noise-free tracker points
    F_true = sc.truth.machine_points(sc.theta[None, :])[0][sc.mesh_rows]

    def field(meas):  # (K, M, 3) -> (K, 3 M0): error after compensation, rigid part removed
        res = identify(sc.id_model, meas, sc.noise)
        F_id = sc.id_model.machine_points(res.theta)[:, sc.mesh_rows]
        return (F_true[None] - F_id).reshape(len(meas), -1) @ sc.rigid_free.T

    return stated_noise_propagation(field, m0, sc.noise, h).reshape(-1, 3) * 1000.0  # um per mm
