"""Several stations (issue 20): recording format 2 and the identification over all stations at once.

The four-station data are made here by an independent generator written from the paper's
equations with plain numpy (the Eq. 6 small-angle chain of an XFYZ machine with Legendre error
functions, the Eq. 22 rotation as Rx(a) Ry(b) Rz(d), spherical tracker noise, ranges plus a dead
path): it calls neither mtbudget's chain nor its tracker model.  mtbudget is used only to hold the
numbers (Plan, Recording) and to map parameter names to the unknown vector.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats

from mtbudget.config import example_recording
from mtbudget.errors import RecordingError
from mtbudget.identify import Noise, Strategy, identify
from mtbudget.model import MeasurementModel
from mtbudget.multistation import identify_recording_any, identify_stations, summary, summary_text
from mtbudget.recording import Recording, read_recording, write_recording

EXAMPLE = Path(__file__).resolve().parents[1] / "mtbudget" / "data" / "recordings" / "four_stations"

# ----------------------------------------------------------------------------- the independent generator
from stations_generator import (INTERFEROMETER, REPEAT, TRACKER, X_POS, Y_POS, Z_POS, machine_point, rot,  # noqa: E402
                                station_recording, true_errors)

#: (id, kind, truth): an xyz pose (D, L, H mm; a, b, d rad) or a range station's (S_x, S_y, S_z, dead path) mm
STATIONS = [
    (1, "xyz", np.array([-900.0, 250.0, 700.0, -0.002, 0.0004, -0.30])),
    (2, "xyz", np.array([2900.0, 320.0, 650.0, 0.001, -0.0005, 2.80])),
    (3, "range", np.array([600.0, -350.0, -250.0, -152.318])),
    (4, "range", np.array([1450.0, 900.0, -200.0, 87.5])),
]
def four_stations(errors, stations=STATIONS, seed=None, repeat=REPEAT) -> Recording:
    """Every station measures the 75 mesh points in one pass; noise from the stated uncertainties (seed None: none)."""
    rng = np.random.default_rng(seed)
    mesh = np.array([(x, y, z) for z in Z_POS for y in Y_POS for x in X_POS])
    rows = {k: [] for k in ("point", "run", "nominal", "tool", "station", "lt", "range")}
    for k, (sid, kind, truth) in enumerate(stations):
        tool = np.zeros((len(mesh), 3))  # two tool lengths, alternating, so that every station sees the tool's tilt
        tool[:, 2] = np.where((np.arange(len(mesh)) + k) % 2 == 0, -150.0, -300.0)
        P = machine_point(errors, mesh, tool)
        if seed is not None:
            P = P + rng.normal(0, repeat, P.shape)
        if kind == "xyz":
            q = (P - truth[:3]) @ rot(*truth[3:])  # R^T (P - T), row by row
            r, az, el = np.linalg.norm(q, axis=1), np.arctan2(q[:, 1], q[:, 0]), np.arcsin(q[:, 2] / np.linalg.norm(q, axis=1))
            if seed is not None:
                r = r + rng.normal(0, TRACKER["distance"] + TRACKER["distance_per_length"] * r)
                az = az + rng.normal(0, TRACKER["angular"], r.shape)
                el = el + rng.normal(0, TRACKER["angular"], r.shape)
            lt = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
            rng_col = np.full(len(mesh), np.nan)
        else:
            dist = np.linalg.norm(P - truth[:3], axis=1)
            rng_col = dist + truth[3]
            if seed is not None:
                rng_col = rng_col + rng.normal(0, INTERFEROMETER["distance"] + INTERFEROMETER["distance_per_length"] * dist)
            lt = np.full((len(mesh), 3), np.nan)
        rows["point"].append(np.arange(len(mesh)))
        rows["run"].append(np.full(len(mesh), k + 1))
        rows["nominal"].append(mesh)
        rows["tool"].append(tool)
        rows["station"].append(np.full(len(mesh), sid))
        rows["lt"].append(lt)
        rows["range"].append(rng_col)
    return station_recording(rows, stations, "four", repeat)


def truth_vector(model, errors, stations=STATIONS) -> np.ndarray:
    theta = np.zeros(model.n_params)
    for name, v in errors.items():
        theta[model.errors.names.index(name)] = v
    return np.concatenate([theta] + [t for _, _, t in stations])


@pytest.fixture(scope="module")
def machine():
    return true_errors(np.random.default_rng(20))


# ----------------------------------------------------------------------------- identification
def test_noise_free_four_stations_recover_the_truth_exactly(machine):
    rec = four_stations(machine)
    rec2, res = identify_recording_any(rec)
    truth = truth_vector(res.model, machine)
    assert res.converged
    err = np.abs(res.x - truth)
    lengths = np.array([u == "mm" for u in res.units])
    assert err[lengths].max() < 1e-6, res.names[int(np.argmax(np.where(lengths, err, 0)))]  # mm
    assert err[~lengths].max() < 1e-9  # rad (1e-6 mm on a 1 m lever)
    assert res.chi2 < 1e-6
    # the roll of Y and Z is what no station sees: named (ISO 230-1), nothing else
    named = sorted(n for combo in res.combinations() for n, _ in combo)
    assert named == sorted(["ECY[P1]", "ECY[P2]", "ECY[P3]", "ECZ[P0]", "ECZ[P1]", "ECZ[P2]"])
    assert res.rank == res.n_unknowns - 6
    assert res.dof == 2 * 75 * 3 + 2 * 75 - res.rank
    assert all(not g["null_direction"] for g in res.gauge)  # the error model's convention fixes the datum


def test_noisy_four_stations_agree_with_the_truth_within_the_stated_uncertainty(machine):
    rec = four_stations(machine, seed=7)
    _, res = identify_recording_any(rec)
    truth = truth_vector(res.model, machine)
    sv = np.array([1e3 if u == "mm" else 1e6 for u in res.units])  # um, urad
    d = (res.x - truth) * sv
    C = res.cov * np.outer(sv, sv)
    chi2 = float(d @ np.linalg.pinv(C, rcond=1e-10, hermitian=True) @ d)
    k = res.rank
    assert stats.chi2.ppf(0.001, k) < chi2 < stats.chi2.ppf(0.999, k), (chi2, k)
    assert 0.75 < res.chi2_per_dof < 1.25  # the weights are the stated uncertainties (sd of chi2/dof ~ 0.06)
    for sid in (3, 4):  # each range station's dead path within 3 standard uncertainties
        vals, us = res.station_values(sid)
        assert abs(vals[3] - STATIONS[sid - 1][2][3]) < 3 * us[3]
        assert us[3] < 0.05  # mm: the dead path is determined to a few um


def test_dead_path_uncertainty_is_its_spread_over_noise_draws(machine):
    """Over 30 noise draws the dead path's error divided by its stated u has a standard deviation near 1."""
    z = []
    for seed in range(100, 130):
        _, res = identify_recording_any(four_stations(machine, seed=seed))
        vals, us = res.station_values(3)
        z.append((vals[3] - STATIONS[2][2][3]) / us[3])
    z = np.array(z)
    assert abs(z.mean()) < 4 / np.sqrt(len(z)), z.mean()
    assert 0.55 < z.std(ddof=1) < 1.5, z.std(ddof=1)


def test_range_only_multilateration(machine):
    """Four range stations: the machine and the dead paths from ranges alone, exact on exact data."""
    st4 = [(1, "range", np.array([600.0, -350.0, -250.0, -152.318])),
           (2, "range", np.array([1450.0, 900.0, -200.0, 87.5])),
           (3, "range", np.array([300.0, 800.0, 450.0, 12.0])),
           (4, "range", np.array([1700.0, -200.0, 500.0, -40.0]))]
    rec = four_stations(machine, stations=st4)
    _, res = identify_recording_any(rec)
    truth = truth_vector(res.model, machine, st4)
    lengths = np.array([u == "mm" for u in res.units])
    err = np.abs(res.x - truth)
    assert err[lengths].max() < 1e-6 and err[~lengths].max() < 1e-9
    assert res.condition > 1.0 and np.isfinite(res.condition)


def test_one_station_matches_the_one_station_identification(null_recording):
    """A second implementation: mtbudget.identify's Gauss-Newton on the same recording."""
    rec, res = identify_recording_any(null_recording)
    model = MeasurementModel.for_plan(rec.machine, rec.plan)
    ref = identify(model, rec.lt, Noise.of(rec), Strategy(solver="gauss-newton"))
    p = model.n_params
    assert np.abs(res.theta - ref.theta[0]).max() < 1e-9
    assert np.abs(res.x[p:] - ref.pose[0]).max() < 1e-8
    assert res.chi2 == pytest.approx(float(ref.chi2[0]), rel=1e-9)
    assert res.dof == ref.dof
    assert np.allclose(res.u_theta(), ref.u_theta()[0], rtol=1e-6, atol=1e-12)  # 0 on the null directions


def test_a_free_straightness_convention_leaves_part_of_the_datum_to_minimum_norm(machine):
    """With the P1 terms of straightness (convention "free", and then no P0 tilt of the tool axis), worked out by hand:

    * rotation about Z of the whole: dx(y)[P1] with dy(x)[P1] (the tool offsets, all along Z, do not turn);
    * translation along X: a squareness scales about the axis zero, a Legendre P1 about the middle of the range, so
      sxz with dx(z)[P1] is a constant x offset; along Y: syz with dy(z)[P1];
    * not along Z (no squareness acts on z), not about X or Y (the two tool lengths would turn differently);
    * and sxy with dx(y)[P1] is a second constant x offset: their difference moves nothing (one null direction of
      the geometry alone).
    With the three rolls of Y and ECZ[P1], ECZ[P2] (what tool offsets along Z cannot show) the rank is
    (51 + 20 unknowns) - 9."""
    rec = four_stations(machine)
    iso = MeasurementModel.for_plan("XFYZ", rec.plan)
    free = MeasurementModel.for_plan("XFYZ", rec.plan, straightness_convention="free")
    args = (rec.station_list(), rec.station_ids(), rec.lt, rec.lt_range, rec.repeatability)
    a, b = identify_stations(iso, *args), identify_stations(free, *args)
    assert free.n_params == iso.n_params + 6 - 3 == 51
    assert [g["null_direction"] for g in b.gauge] == [True, True, False, False, False, True]
    assert b.rank == 51 + 20 - 9
    assert b.chi2 < 1e-6 and a.chi2 < 1e-6  # the same exact data, fitted exactly by both


def test_summary_states_units_and_coverage(machine):
    rec = four_stations(machine, seed=3)
    _, res = identify_recording_any(rec)
    s = summary(rec, res)
    assert s["rank"] == res.rank and "k = 1" in s["coverage"]
    assert {p["unit"] for p in s["parameters"]} == {"um", "urad"}
    text = "\n".join(summary_text(rec, res))
    assert "dead path" in text and "k = 1" in text and "condition number" in text


def test_the_bundled_example_is_identified_within_its_truth():
    import json

    rec, res = identify_recording_any(EXAMPLE)
    truth = json.loads((EXAMPLE / "truth.json").read_text())
    for st_ in truth["stations"]:
        if st_["kind"] == "range":
            vals, us = res.station_values(st_["id"])
            assert abs(vals[3] - st_["dead_path_mm"]) < 3 * us[3]
    assert 0.75 < res.chi2_per_dof < 1.25


# ----------------------------------------------------------------------------- recording format 2
@pytest.fixture
def written(machine, tmp_path):
    rec = four_stations(machine, seed=1)
    write_recording(rec, tmp_path / "four")
    return rec, tmp_path / "four"


def test_format2_round_trip(written):
    rec, folder = written
    back = read_recording(folder, several_stations=True)
    assert back.format_version == 2 and len(back.stations) == 4
    for a, b in zip(back.stations, rec.stations):
        assert (a.id, a.kind) == (b.id, b.kind) and (a.angular is None) == (b.angular is None)
        for key in ("angular", "distance", "distance_per_length"):
            if getattr(b, key) is None:  # not stated for this station (pytest >= 9.2 refuses approx(None))
                assert getattr(a, key) is None, key
            else:
                assert getattr(a, key) == pytest.approx(getattr(b, key), rel=1e-9)
    assert np.array_equal(back.station, rec.station)
    assert np.array_equal(np.isnan(back.lt), np.isnan(rec.lt)) and np.array_equal(np.isnan(back.lt_range), np.isnan(rec.lt_range))
    assert np.nanmax(np.abs(back.lt - rec.lt)) <= 0.5e-6 + 1e-9
    assert np.nanmax(np.abs(back.lt_range - rec.lt_range)) <= 0.5e-6 + 1e-9
    assert np.array_equal(back.plan.nominal, rec.plan.nominal)


def test_one_station_consumers_refuse_several_stations(written):
    _, folder = written
    with pytest.raises(RecordingError) as info:
        read_recording(folder)
    msg = str(info.value)
    assert "recording.toml" in msg and "stations" in msg and "4 stations (2 xyz, 2 range)" in msg and "\n" not in msg


def test_format1_is_format2_with_one_xyz_station(tmp_path):
    """The null example as format 2 with one declared station: the same recording, the same identification."""
    a = read_recording(example_recording("null"))
    assert a.format_version == 1 and not a.several_stations and a.station_list()[0].kind == "xyz"
    dst = tmp_path / "null2"
    shutil.copytree(example_recording("null"), dst)
    toml = (dst / "recording.toml").read_text().replace('"mtbudget-recording/1"', '"mtbudget-recording/2"')
    (dst / "recording.toml").write_text(toml + '\n[[stations]]\nid = 7\nkind = "xyz"\n')
    b = read_recording(dst)
    assert b.format_version == 2 and b.stations[0].id == 7 and np.array_equal(a.lt, b.lt)
    assert (b.angular, b.distance, b.distance_per_length) == (a.angular, a.distance, a.distance_per_length)
    _, ra = identify_recording_any(a)
    _, rb = identify_recording_any(b)
    assert np.array_equal(ra.x, rb.x)


def _edit(folder, fn, name="points.csv"):
    p = folder / name
    p.write_text(fn(p.read_text()))


def _cells(text, line, column, value):
    """Set the cell of (1-based) ``line`` in the column whose header starts with ``column``."""
    lines = text.splitlines()
    head = lines[0].split(",")
    j = next(i for i, h in enumerate(head) if h.split(" [")[0] == column)
    cells = lines[line - 1].split(",")
    cells[j] = value
    lines[line - 1] = ",".join(cells)
    return "\n".join(lines) + "\n"


def _keep_three_of_station_4(text):
    lines = text.splitlines()
    j = lines[0].split(",").index("station")
    keep = [ln for ln in lines[1:] if ln.split(",")[j] != "4" or int(ln.split(",")[0]) < 3]
    return "\n".join([lines[0]] + keep) + "\n"


BAD = {
    "unknown station": (lambda f: _edit(f, lambda t: _cells(t, 5, "station", "9")),
                        ["points.csv", "line 5", "'station'", "station 9 is not declared", "1, 2, 3, 4"]),
    "xyz row with a range": (lambda f: _edit(f, lambda t: _cells(t, 3, "lt_range", "1500.0")),
                             ["points.csv", "line 3", "'lt_range [mm]'", "station 1 is an xyz station", "leave the cell empty"]),
    "range row with lt_x": (lambda f: _edit(f, lambda t: _cells(t, 160, "lt_x", "12.0")),
                            ["points.csv", "line 160", "'lt_x [mm]'", "station 3 is a range station"]),
    "range row without its range": (lambda f: _edit(f, lambda t: _cells(t, 161, "lt_range", "")),
                                    ["points.csv", "line 161", "lt_range", "empty cell", "station 3"]),
    "xyz row without lt_y": (lambda f: _edit(f, lambda t: _cells(t, 90, "lt_y", "")),
                             ["points.csv", "line 90", "lt_y", "empty cell", "station 2"]),
    "a station with 3 ranges": (lambda f: _edit(f, _keep_three_of_station_4),
                                ["points.csv", "'station'", "station 4 (range) measures 3 distinct points", "needs at least 4"]),
    "station column in format 1": (lambda f: _edit(f, lambda t: t.replace('"mtbudget-recording/2"', '"mtbudget-recording/1"'),
                                                   "recording.toml"),
                                   ["recording.toml", "stations", "format"]),
    "no [[stations]]": (lambda f: _edit(f, lambda t: t.split("[[stations]]")[0], "recording.toml"),
                        ["recording.toml", "stations", "at least one [[stations]]"]),
    "unknown kind": (lambda f: _edit(f, lambda t: t.replace('kind = "range"', 'kind = "laser"', 1), "recording.toml"),
                     ["recording.toml", "stations[2].kind", "'laser'"]),
    "angle for a range station": (lambda f: _edit(f, lambda t: t.replace('kind = "range"', 'kind = "range"\nangular = "5 urad"', 1),
                                                  "recording.toml"),
                                  ["recording.toml", "stations[2].angular", "measures no angle"]),
    "misspelt key": (lambda f: _edit(f, lambda t: t + 'distance_per_lenght = "0.3 um/m"\n', "recording.toml"),
                     ["recording.toml", "stations[3].distance_per_lenght", "unknown key"]),
    "duplicate id": (lambda f: _edit(f, lambda t: t.replace("id = 2", "id = 1"), "recording.toml"),
                     ["recording.toml", "stations[1].id", "declared twice"]),
    "id not a number": (lambda f: _edit(f, lambda t: t.replace("id = 2", 'id = "B"'), "recording.toml"),
                        ["recording.toml", "stations[1].id", "whole number"]),
    "a station without rows": (lambda f: _edit(f, lambda t: t + '\n[[stations]]\nid = 5\nkind = "xyz"\n', "recording.toml"),
                               ["recording.toml", "stations[4].id", "station 5 measures no row"]),
    "implausible station uncertainty": (lambda f: _edit(f, lambda t: t.replace('distance = "0.5 um"', 'distance = "0.5 m"', 1),
                                                        "recording.toml"),
                                        ["recording.toml", "stations[2].distance", "not a plausible standard uncertainty"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_station_data_name_file_and_place(case, written):
    _, folder = written
    damage, must = BAD[case]
    damage(folder)
    with pytest.raises(RecordingError) as info:
        read_recording(folder, several_stations=True)
    msg = str(info.value)
    for part in must:
        assert part in msg, (case, msg)
    assert "\n" not in msg


def test_station_column_needs_format2(tmp_path):
    dst = tmp_path / "rec"
    shutil.copytree(example_recording("null"), dst)
    _edit(dst, lambda t: "\n".join([ln + (",lt_range [mm]" if i == 0 else ",") for i, ln in enumerate(t.splitlines())]) + "\n")
    with pytest.raises(RecordingError, match=r"points.csv, line 1, column 'lt_range \[mm\]'.*format 2"):
        read_recording(dst)


def test_simultaneous_stations_are_not_duplicates(written, tmp_path):
    """Two stations may measure one point at one time (several interferometers at once); one station cannot."""
    _, folder = written
    lines = (folder / "points.csv").read_text().splitlines()
    head = lines[0].split(",")
    t = head.index("time [s]")
    same = lines[1].split(",")
    row3 = lines[151].split(",")  # the first row of station 3: give it the time, point and tool of line 2
    for j, h in enumerate(head):
        if h.split(" [")[0] in ("point", "run", "x", "y", "z", "tool_x", "tool_y", "tool_z"):
            row3[j] = same[j]
    row3[t] = same[t]
    rows = [lines[1], ",".join(row3)] + [ln for i, ln in enumerate(lines[2:], start=2) if i != 151]
    (folder / "points.csv").write_text("\n".join([lines[0]] + rows) + "\n")
    read_recording(folder, several_stations=True)  # reads
    (folder / "points.csv").write_text("\n".join([lines[0], lines[1]] + [lines[1]] + lines[2:]) + "\n")
    with pytest.raises(RecordingError, match="duplicate row .*station"):
        read_recording(folder, several_stations=True)


# ----------------------------------------------------------------------------- fuzz (bounded)
@pytest.fixture(scope="module")
def small_v2(tmp_path_factory, machine):
    rec = four_stations(machine, seed=2)
    folder = tmp_path_factory.mktemp("v2") / "rec"
    write_recording(rec, folder)
    return (folder / "recording.toml").read_text(), (folder / "points.csv").read_text()


CELL_VALUES = ["", " ", "1", "0", "-1", "5", "4", "3.5", "nan", "1e400", "x", "2e6", "1,5", "-0", "  2  ", "99"]
TOML_EDITS = [("id = 1", "id = 3"), ("id = 4", "id = -4"), ('kind = "xyz"', 'kind = "range"'),
              ('kind = "range"', 'kind = "xyz"'), ('kind = "range"', "kind = 3"), ("id = 2", "id = 2.0"),
              ('distance = "0.5 um"', 'distance = "0 um"'), ("[[stations]]", "[stations]"),
              ('"mtbudget-recording/2"', '"mtbudget-recording/3"'), ("id = 3", "id = true"), ("", "")]


@settings(max_examples=60, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_format2_reads_or_names_the_problem(data, small_v2, tmp_path):
    """Damaged format 2 recordings: read, or one RecordingError line naming the file; never another exception."""
    toml, csv = small_v2
    lines = csv.splitlines()
    head = lines[0].split(",")
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(1, len(lines) - 1))
        j = data.draw(st.sampled_from([k for k, h in enumerate(head) if h.split(" [")[0] in
                                       ("station", "lt_x", "lt_y", "lt_z", "lt_range", "point")]))
        cells = lines[i].split(",")
        cells[j] = data.draw(st.sampled_from(CELL_VALUES))
        lines[i] = ",".join(cells)
    old, new = data.draw(st.sampled_from(TOML_EDITS))
    folder = Path(tempfile.mkdtemp(dir=tmp_path))
    (folder / "recording.toml").write_text(toml.replace(old, new, 1) if old else toml)
    (folder / "points.csv").write_text("\n".join(lines) + "\n")
    try:
        rec = read_recording(folder, several_stations=True)
    except RecordingError as exc:
        msg = str(exc)
        assert "\n" not in msg and ("points.csv" in msg or "recording.toml" in msg), msg
        return
    # what reads is consistent: every row's cells are those of its station's kind
    kind = {s.id: s.kind for s in rec.stations}
    is_range = np.array([kind[int(s)] == "range" for s in rec.station])
    assert np.isfinite(rec.lt_range[is_range]).all() and np.isnan(rec.lt_range[~is_range]).all()
    assert np.isfinite(rec.lt[~is_range]).all() and np.isnan(rec.lt[is_range]).all()


def test_multilateration_of_many_trials_is_each_trial_alone():
    """multilaterate_trials (the several-station start of every trial at once) against multilaterate (numpy's lstsq,
    one trial): the same position and dead path to round-off, a trial's numbers the same alone or among others, and
    the same refusal when the points lie on one plane."""
    from mtbudget.errors import IdentificationError
    from mtbudget.multistation import multilaterate, multilaterate_trials

    rng = np.random.default_rng(8)
    P = rng.uniform(-500, 500, (30, 3))
    S, o = np.array([1500.0, -300.0, 200.0]), 12.0
    R = np.sqrt(((P - S) ** 2).sum(axis=1)) + o + rng.normal(0, 1e-3, (6, 30))
    many = multilaterate_trials(P, R)
    for i in range(6):
        Si, oi = multilaterate(P, R[i])
        assert np.abs(many[i, :3] - Si).max() < 1e-9 and abs(many[i, 3] - oi) < 1e-9
        np.testing.assert_array_equal(multilaterate_trials(P, R[i:i + 1])[0], many[i])
    assert np.abs(many[:, :3] - S).max() < 0.05 and np.abs(many[:, 3] - o).max() < 0.05
    flat = P.copy()
    flat[:, 2] = 0.0
    Rf = np.sqrt(((flat - S) ** 2).sum(axis=1))[None] + o
    with pytest.raises(IdentificationError):
        multilaterate(flat, Rf[0])
    with pytest.raises(IdentificationError):
        multilaterate_trials(flat, Rf)
