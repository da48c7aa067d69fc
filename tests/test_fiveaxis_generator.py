"""Self-checks of the independent five-axis generator (tests/fiveaxis_generator.py, issue 26).

The generator is the truth of the five-axis acceptance tests, so it is checked here against a second route
written differently (4 x 4 homogeneous transforms composed first and inverted with numpy, Rodrigues' formula
instead of scipy, the Legendre polynomials written out), against hand calculations of one error at a time,
against the statistics of the noise it states, and for the file format (columns, units, TOML keys).
"""

from __future__ import annotations

import csv
import json
import tomllib

import numpy as np
import pint
import pytest

import fiveaxis_generator as g

UREG = pint.UnitRegistry()


# ------------------------------------------------------------------------------------------- a second route
def rodrigues(rotvec) -> np.ndarray:
    rotvec = np.asarray(rotvec, float)
    th = np.linalg.norm(rotvec)
    if th == 0:
        return np.eye(3)
    k = rotvec / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def homogeneous(R, t) -> np.ndarray:
    H = np.eye(4)
    H[:3, :3], H[:3, 3] = R, t
    return H


def P(n, u):
    return {0: 1.0, 1: u, 2: (3 * u * u - 1) / 2, 3: (5 * u ** 3 - 3 * u) / 2}[n]


def brute_force_lt(truth: dict, rows: list) -> np.ndarray:
    """lt of every CSV row from truth.json alone, by 4 x 4 transforms: H_tool = H_1 ... H_n applied to the tool
    offset, H_work = H_1 ... H_m inverted by numpy."""
    kind = truth["kind"]
    f = kind.index("F")
    work, tool = kind[:f][::-1], kind[f + 1:]
    par = truth["parameters"]
    geo = truth["geometric_errors"]
    sq = {s: par.get(s, 0.0) * 1e-6 for s in ("sxy", "sxz", "syz")}
    pose = truth["tracker_pose"]
    R_LT = rodrigues([pose["a"], 0, 0]) @ rodrigues([0, pose["b"], 0]) @ rodrigues([0, 0, pose["d"]])
    T_LT = np.array([pose["D"], pose["L"], pose["H"]])
    out = []
    for row in rows:
        pos = {a: float(row[f"{a} [mm]"]) for a in "xyz"}

        def H(letter, side):
            if letter in "ABC":
                rot = truth["rotary"][letter]
                p = np.array(rot["pivot_mm"])
                i = "ABC".index(letter)
                u = np.zeros(3)
                u[i] = 1.0 if rot["direction"][0] == "+" else -1.0
                delta = np.array([par.get(f"E{c}O{letter}", 0.0) * 1e-3 if j != i else 0.0
                                  for j, c in enumerate("XYZ")])
                w = np.array([par.get(f"E{c}O{letter}", 0.0) * 1e-6 for c in "ABC"])
                R = rodrigues(w) @ rodrigues(u * np.radians(float(row[f"{letter.lower()} [deg]"])))
                return homogeneous(np.eye(3), p + delta) @ homogeneous(R, np.zeros(3)) @ homogeneous(np.eye(3), -p)
            a = letter.lower()
            lo, hi = geo["ranges_mm"][a]
            un = (pos[a] - (lo + hi) / 2) / ((hi - lo) / 2)
            err = {}
            for k in "de":
                for c in "xyz":
                    coefs = geo["coefficients"][f"{k}{c}({a})"]
                    err[k + c] = sum(v * P(n + 1, un) for n, v in enumerate(coefs)) * (1e-3 if k == "d" else 1e-6)
            q = pos[a]
            d = {"x": [q, 0, 0], "y": [-q * sq["sxy"], q, 0], "z": [-q * sq["sxz"], -q * sq["syz"], q]}[a]
            s = 1.0 if side == "tool" else -1.0
            t = s * np.array(d) + np.array([err["dx"], err["dy"], err["dz"]])
            return homogeneous(rodrigues([err["ex"], err["ey"], err["ez"]]), t)

        H_tool, H_work = np.eye(4), np.eye(4)
        for L in tool:
            H_tool = H_tool @ H(L, "tool")
        for L in work:
            H_work = H_work @ H(L, "work")
        T = np.array([float(row[f"tool_{c} [mm]"]) for c in "xyz"] + [1.0])
        P_W = (np.linalg.inv(H_work) @ H_tool @ T)[:3]
        out.append(R_LT.T @ (P_W - T_LT))
    return np.array(out)


def read_csv(folder):
    with open(folder / "points.csv", newline="") as fh:
        reader = csv.DictReader(fh)
        return reader.fieldnames, list(reader)


def lt_of(rows):
    return np.array([[float(r[f"lt_{c} [mm]"]) for c in "xyz"] for r in rows])


@pytest.mark.parametrize("kind", list(g.PRESETS))
def test_zero_errors_give_the_nominal_pose_by_a_second_route(tmp_path, kind):
    truth = g.make_recording(tmp_path, kind, null=True, noise_free=True, seed=3)
    assert all(v == 0 for v in truth["parameters"].values())
    _, rows = read_csv(tmp_path)
    assert np.abs(brute_force_lt(truth, rows) - lt_of(rows)).max() < 2e-6  # the CSV's 1e-6 mm rounding


def test_cafxyz_nominal_by_hand(tmp_path):
    """P_W = p_C + Rz(c)^T (p_A + Rx(a)^T ((x, y, z) + T - p_A) - p_C), the trunnion written out."""
    truth = g.make_recording(tmp_path, "CAFXYZ", null=True, noise_free=True, seed=3)
    _, rows = read_csv(tmp_path)
    pA, pC = np.array(truth["rotary"]["A"]["pivot_mm"]), np.array(truth["rotary"]["C"]["pivot_mm"])
    pose = truth["tracker_pose"]
    R_LT = g.tracker_rotation(pose["a"], pose["b"], pose["d"])
    for r in rows[::37]:
        a, c = np.radians(float(r["a [deg]"])), np.radians(float(r["c [deg]"]))
        Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        Rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
        PM = np.array([float(r[f"{k} [mm]"]) + float(r[f"tool_{k} [mm]"]) for k in "xyz"])
        PW = pC + Rz.T @ (pA + Rx.T @ (PM - pA) - pC)
        lt = R_LT.T @ (PW - np.array([pose["D"], pose["L"], pose["H"]]))
        assert np.allclose(lt, [float(r[f"lt_{k} [mm]"]) for k in "xyz"], atol=2e-6)


@pytest.mark.parametrize("kind", list(g.PRESETS))
def test_every_error_at_once_agrees_with_the_second_route(tmp_path, kind):
    truth = g.make_recording(tmp_path, kind, linear_errors=True, noise_free=True, seed=11,
                             linear_scale={"d": 0.05, "e": 200e-6, "squareness": 300e-6})  # large: visible terms
    _, rows = read_csv(tmp_path)
    assert np.abs(brute_force_lt(truth, rows) - lt_of(rows)).max() < 2e-6
    nominal = g.make_recording(tmp_path / "nom", kind, null=True, noise_free=True, seed=11)
    assert np.abs(lt_of(read_csv(tmp_path / "nom")[1]) - lt_of(rows)).max() > 0.05  # the errors do show


# ------------------------------------------------------------------------------------------- by hand
def _table_points(kind, params, seed=0):
    pre = g.PRESETS[kind]
    m = g.Machine(kind, pre["pivots"], pre["directions"])
    plan = g.make_plan(pre["plan"], kind)
    return m, plan, m.table_points(plan, params, g.plan_ranges(plan))


def _Rx(t):
    return np.stack([np.stack([np.ones_like(t), 0 * t, 0 * t], -1), np.stack([0 * t, np.cos(t), -np.sin(t)], -1),
                     np.stack([0 * t, np.sin(t), np.cos(t)], -1)], -2)


def _Rz(t):
    return np.stack([np.stack([np.cos(t), -np.sin(t), 0 * t], -1), np.stack([np.sin(t), np.cos(t), 0 * t], -1),
                     np.stack([0 * t, 0 * t, np.ones_like(t)], -1)], -2)


def test_exoc_shifts_table_points_by_minus_rc_transpose_delta():
    _, plan, P0 = _table_points("CAFXYZ", {})
    _, _, P1 = _table_points("CAFXYZ", {"EXOC": 40.0})
    RcT = np.transpose(_Rz(np.radians(plan["angles"]["C"])), (0, 2, 1))
    assert np.allclose(P1 - P0, -RcT @ np.array([40e-3, 0, 0]), atol=1e-12)


def test_ezoa_shifts_table_points_by_minus_rc_t_ra_t_delta():
    _, plan, P0 = _table_points("CAFXYZ", {})
    _, _, P1 = _table_points("CAFXYZ", {"EZOA": -25.0})
    Rc, Ra = _Rz(np.radians(plan["angles"]["C"])), _Rx(np.radians(plan["angles"]["A"]))
    expect = -np.einsum("mji,mkj,k->mi", Rc, Ra, np.array([0, 0, -25e-3]))
    assert np.allclose(P1 - P0, expect, atol=1e-12)


def test_ecoc_turns_the_table_about_the_c_axis():
    m, plan, P0 = _table_points("CAFXYZ", {})
    _, _, P1 = _table_points("CAFXYZ", {"ECOC": 70.0})
    pC = m.pivots["C"]
    assert np.allclose(P1, pC + (P0 - pC) @ _Rz(np.array(-70e-6)).T, atol=1e-12)


def test_a_zero_error_is_the_same_as_commanding_the_angle_plus_it():
    """EAOA rotates A's element about its own (nominal) axis: w = eps u commutes with R_u(theta)."""
    m, plan, _ = _table_points("CAFXYZ", {})
    ranges = g.plan_ranges(plan)
    P1 = m.table_points(plan, {"EAOA": 80.0}, ranges)
    shifted = {**plan, "angles": {**plan["angles"], "A": plan["angles"]["A"] + np.degrees(80e-6)}}
    assert np.allclose(P1, m.table_points(shifted, {}, ranges), atol=1e-12)


def test_exob_moves_the_head_tool_point_by_rc_delta():
    """Head-head, tracker on the bed: a B offset moves the tool point by Rz(c) (EXOB, 0, 0) in the machine frame."""
    _, plan, P0 = _table_points("FXYZCB", {})
    _, _, P1 = _table_points("FXYZCB", {"EXOB": 30.0})
    assert np.allclose(P1 - P0, _Rz(np.radians(plan["angles"]["C"])) @ np.array([30e-3, 0, 0]), atol=1e-12)


def test_a_reversed_direction_turns_the_other_way_and_keeps_the_iso_zero_error_machine_frame():
    pre = g.PRESETS["CAFXYZ"]
    plan = g.make_plan(pre["plan"], "CAFXYZ")
    ranges = g.plan_ranges(plan)
    plus = g.Machine("CAFXYZ", pre["pivots"], pre["directions"])
    minus = g.Machine("CAFXYZ", pre["pivots"], {**pre["directions"], "A": "-x"})
    flipped = {**plan, "angles": {**plan["angles"], "A": -plan["angles"]["A"]}}
    assert np.allclose(minus.table_points(plan, {"EAOA": 50.0}, ranges),
                       plus.table_points(flipped, {"EAOA": 50.0}, ranges), atol=1e-12)


# ------------------------------------------------------------------------------------------- noise and truth
def test_the_drawn_noise_is_recorded_and_has_the_stated_size(tmp_path):
    truth = g.make_recording(tmp_path / "n", "CAFXYZ", linear_errors=True, seed=5)
    _, rows = read_csv(tmp_path / "n")
    pre = g.PRESETS["CAFXYZ"]
    m = g.Machine("CAFXYZ", pre["pivots"], pre["directions"])
    plan = g.make_plan(pre["plan"], "CAFXYZ")
    dn = truth["drawn_noise"]
    rep = np.array(dn["repeat_um"]) * 1e-3
    P_W = m.table_points(plan, truth["parameters"], g.plan_ranges(plan), repeat_noise=rep)
    lt0 = g.to_tracker(P_W, tuple(truth["tracker_pose"].values()))
    sph = np.stack([np.array(dn["range_um"]) * 1e-3, np.array(dn["azimuth_urad"]) * 1e-6,
                    np.array(dn["elevation_urad"]) * 1e-6], axis=1)
    assert np.abs(g.spherical_noise(lt0, sph) - lt_of(rows)).max() < 2e-6  # the record reproduces the data
    r = np.linalg.norm(lt0, axis=1)
    n = len(r)
    for z in (sph[:, 0] / (4e-3 + 0.8e-6 * r), sph[:, 1] / 5e-6, sph[:, 2] / 5e-6, rep.ravel() / 1.5e-3):
        assert abs(z.mean()) < 4 / np.sqrt(len(z)) and abs(z.std() - 1) < 4 / np.sqrt(2 * n)


def test_the_truth_names_every_parameter_and_a_null_is_null(tmp_path):
    truth = g.make_recording(tmp_path / "a", "CAFXYZ", linear_errors=True, seed=7)
    names = ["EYOA", "EZOA", "EBOA", "ECOA", "EAOA", "EXOC", "EYOC", "EAOC", "EBOC", "ECOC"]
    assert sorted(truth["rotary_parameters"]) == sorted(names)
    rot = np.abs(np.array([truth["rotary_parameters"][k] for k in names]))
    assert rot[[0, 1, 5, 6]].min() >= 10 and rot[[0, 1, 5, 6]].max() <= 60  # um
    assert rot[[2, 3, 4, 7, 8, 9]].min() >= 20 and rot[[2, 3, 4, 7, 8, 9]].max() <= 100  # urad
    assert "dy(x)[P1]" not in truth["parameters"] and "dy(x)[P2]" in truth["parameters"]  # no straightness P1
    assert truth["geometric_errors"]["ranges_mm"]["x"] == [-150.0, 150.0]
    null = g.make_recording(tmp_path / "b", "FXYZCB", null=True, seed=7)
    assert set(null["rotary_parameters"]) == {"EXOB", "EZOB", "EAOB", "ECOB", "EBOB", "EXOC", "EYOC", "EAOC",
                                              "EBOC", "ECOC"}
    assert not any(null["parameters"].values())
    assert json.loads((tmp_path / "b" / "truth.json").read_text())["null"] is True


# ------------------------------------------------------------------------------------------- the files
@pytest.mark.parametrize("kind,letters", [("CAFXYZ", "ac"), ("FXYZCB", "bc")])
def test_the_csv_reads_back_with_units_pint_parses(tmp_path, kind, letters):
    g.make_recording(tmp_path, kind, seed=1, rotary_dir_columns=True)
    header, rows = read_csv(tmp_path)
    fmt1 = ["point", "run", "time [s]", "x [mm]", "y [mm]", "z [mm]", "dir_x", "dir_y", "dir_z", "tool_x [mm]",
            "tool_y [mm]", "tool_z [mm]", "lt_x [mm]", "lt_y [mm]", "lt_z [mm]"]
    assert set(fmt1) <= set(header)
    assert [h for h in header if h.endswith("[deg]")] == [f"{L} [deg]" for L in letters]
    assert [h for h in header if h.startswith("dir_") and h[-1] in "abc"] == [f"dir_{L}" for L in letters]
    assert not any(h.startswith("T_") for h in header)
    for h in header:
        if "[" in h:
            unit = UREG.Unit(h.split("[")[1].rstrip("]"))
            assert unit.dimensionality == UREG.Unit({"s": "s", "deg": "rad"}.get(h.split("[")[1][:-1], "mm")) \
                .dimensionality
    assert len(rows) == 1080 and len({r["point"] for r in rows}) == 540 and {r["run"] for r in rows} == {"1", "2"}
    for r in rows[:5]:
        assert all(np.isfinite(float(r[h])) for h in header)


def test_the_toml_says_format_3_and_the_rotary_tables(tmp_path):
    g.make_recording(tmp_path, "CAFXYZ", seed=1, sensors=True)
    meta = tomllib.loads((tmp_path / "recording.toml").read_text())
    assert meta["format"] == "mtbudget-recording/3" and meta["machine"] == "CAFXYZ"
    assert meta["rotary"]["A"] == {"pivot": ["0 mm", "-20 mm", "-80 mm"], "direction": "+x"}
    assert meta["rotary"]["C"] == {"pivot": ["50 mm", "-20 mm", "0 mm"], "direction": "+z"}
    assert meta["tracker"]["mount"] == "table"
    for key, dim in (("angular", "urad"), ("distance", "um"), ("distance_per_length", "um/m")):
        assert UREG.Quantity(meta["tracker"][key]).dimensionality == UREG.Unit(dim).dimensionality
    assert UREG.Quantity(meta["machine_tool"]["repeatability"]).to("um").magnitude == pytest.approx(1.5)
    assert [s["column"] for s in meta["sensors"]] == ["T_x", "T_y", "T_z", "T_air"]
    header, rows = read_csv(tmp_path)
    assert {r["T_air [degC]"] for r in rows} == {"20.000"}


# ------------------------------------------------------------------------------------------- identifiability
def _jacobian(kind, names, plan_spec=None):
    """d lt / d (named parameters in um / urad, then the tracker pose in um / urad) by central differences."""
    pre = g.PRESETS[kind]
    m = g.Machine(kind, pre["pivots"], pre["directions"])
    plan = g.make_plan(plan_spec or pre["plan"], kind)
    ranges = g.plan_ranges(plan)
    pose0 = np.array(pre["tracker_pose"])

    def lt(params, pose):
        return g.to_tracker(m.table_points(plan, params, ranges), pose).ravel()

    cols, h = [], 1.0
    for n in names:
        cols.append((lt({n: h}, pose0) - lt({n: -h}, pose0)) / (2 * h))
    for j in range(6):
        dp = np.zeros(6)
        dp[j] = 1e-3 if j < 3 else 1e-6
        cols.append((lt({}, pose0 + dp) - lt({}, pose0 - dp)) / 2)
    return np.stack(cols, axis=1) * 1e3  # um per um / urad


def test_the_trunnion_plan_has_the_two_null_directions_of_format_3():
    """An independent least-squares view of FORMAT-3 section 6: with the 3 squareness terms, rank 17 of 19."""
    names = g.all_rotary_names("CAFXYZ") + ["sxy", "sxz", "syz"]
    J = _jacobian("CAFXYZ", names)
    s = np.linalg.svd(J, compute_uv=False)
    assert s[16] / s[17] > 1e5 and s[17] / s[0] < 1e-7
    _, _, Vt = np.linalg.svd(J)
    null = Vt[17:].T
    ecoc = np.zeros(len(names) + 6)
    ecoc[names.index("ECOC")] = 1.0
    combo = np.zeros(len(names) + 6)
    combo[[names.index("EAOA"), names.index("EAOC"), names.index("EYOC")]] = (1.0, -1.0, 0.080)
    for v in (ecoc, combo):  # the machine part of each null direction lies in the computed null space
        part = null[:len(names)] @ np.linalg.lstsq(null[:len(names)], v[:len(names)], rcond=None)[0]
        assert np.allclose(part, v[:len(names)], atol=1e-5)


def test_the_head_head_plan_has_the_four_null_directions_of_format_3():
    names = g.all_rotary_names("FXYZCB") + ["sxy", "sxz", "syz"]
    J = _jacobian("FXYZCB", names)
    s = np.linalg.svd(J, compute_uv=False)
    assert s[14] / s[15] > 1e5 and s[15] / s[0] < 1e-7
    null = np.linalg.svd(J)[2][15:].T[:len(names)]
    for combo in ({"ECOC": 1.0, "ECOB": -1.0}, {"EXOC": 1.0}, {"EYOC": 1.0}, {"EZOB": 1.0}):
        v = np.array([combo.get(n, 0.0) for n in names])
        assert np.allclose(null @ np.linalg.lstsq(null, v, rcond=None)[0], v, atol=1e-5)
