"""Diagnosis of recordings of several stations (issue 20): a range offset of one laser-tracker station is named.

The four-station recordings are made here by an independent generator written from the paper's equations
with plain numpy (the Eq. 6 small-angle chain of an XFYZ machine with Legendre error functions, the Eq. 22
rotation as Rx(a) Ry(b) Rz(d), spherical tracker noise, ranges plus a dead path: tests/stations_generator.py,
shared with tests/test_multistation.py): it calls neither
mtbudget's chain, nor its tracker model, nor any candidate's columns.  The range offset is added to the
measured distance r before the point is put back into Cartesian coordinates, as the tracker's ADM would.
mtbudget is used only to hold the numbers (Plan, Recording) and to diagnose them.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mtbudget.config import example_recording
from mtbudget.diagnose import diagnose
from mtbudget.errors import DiagnosisError, RecordingError
from mtbudget.plan import Plan
from mtbudget.recording import Recording, read_recording, write_recording
from mtbudget.report_diagnosis import diagnosis_report, diagnosis_text

# ----------------------------------------------------------------------------- the independent generator
from stations_generator import (INTERFEROMETER, REPEAT, TRACKER, X_POS, Y_POS, Z_POS, machine_point, rot,  # noqa: E402
                                station_recording, true_errors)

from conftest import unit_fields

#: (id, kind, truth): an xyz pose (D, L, H mm; a, b, d rad) or a range station's (S_x, S_y, S_z, dead path) mm.
#: The trackers stand 0.9-1.8 m from the points (the mesh spans 400 x 400 x 200 mm): a station's pose absorbs
#: the part of its range offset along the mean beam, and what is left grows with the spread of the beam
#: directions; at 2 m (the bundled example's trackers) 27 um is about 2 standard deviations
#: (test_from_two_metres_the_offset_is_absorbed_and_nothing_wrong_is_named).
STATIONS = [
    (1, "xyz", np.array([-300.0, 250.0, 700.0, -0.002, 0.0004, -0.30])),
    (2, "xyz", np.array([2000.0, 320.0, 650.0, 0.001, -0.0005, 2.80])),
    (3, "range", np.array([600.0, -350.0, -250.0, -152.318])),
    (4, "range", np.array([1450.0, 900.0, -200.0, 87.5])),
]


def four_stations(seed: int, offsets: dict | None = None, *, machine_seed: int | None = None, jitter: float = 0.0,
                  stations=STATIONS, name="four", tracker_noise: float = 1.0, range_error: dict | None = None
                  ) -> Recording:
    """Four stations (two trackers, two interferometers) measure the 75 mesh points, one pass each, two tool lengths
    alternating; noise from the stated uncertainties (k = 1).  offsets: {station id: range offset in mm} added to
    that tracker's measured distances.  jitter: multiple of (100 mm, 50 mm, 1 mrad, 0.05 rad) of random change of
    the stations' truth (other setups).  tracker_noise: the trackers' noise drawn as that multiple of the stated.
    range_error: {station id: function of the distance r (mm) -> its error (mm)}, for physics outside the library."""
    rng = np.random.default_rng(seed)
    errors = true_errors(np.random.default_rng(seed if machine_seed is None else machine_seed))
    offsets = offsets or {}
    mesh = np.array([(x, y, z) for z in Z_POS for y in Y_POS for x in X_POS])
    n = len(mesh)
    cols = {k: [] for k in ("point", "run", "nominal", "tool", "station", "lt", "range")}
    for k, (sid, kind, truth) in enumerate(stations):
        spread = np.array([100.0, 100.0, 50.0, 1e-3, 1e-3, 0.05]) if kind == "xyz" else np.full(4, 50.0)  # mm, rad
        truth = truth + jitter * spread * rng.normal(0, 1, truth.shape)
        tool = np.zeros((n, 3))
        tool[:, 2] = np.where((np.arange(n) + k) % 2 == 0, -150.0, -300.0)
        P = machine_point(errors, mesh, tool) + rng.normal(0, REPEAT, (n, 3))
        if kind == "xyz":
            q = (P - truth[:3]) @ rot(*truth[3:])
            r = np.linalg.norm(q, axis=1)
            az, el = np.arctan2(q[:, 1], q[:, 0]), np.arcsin(q[:, 2] / r)
            if sid in (range_error or {}):
                r = r + range_error[sid](r)
            f = tracker_noise
            r = r + offsets.get(sid, 0.0) + rng.normal(0, f * (TRACKER["distance"] + TRACKER["distance_per_length"] * r))
            az = az + rng.normal(0, f * TRACKER["angular"], n)
            el = el + rng.normal(0, f * TRACKER["angular"], n)
            lt = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
            rng_col = np.full(n, np.nan)
        else:
            dist = np.linalg.norm(P - truth[:3], axis=1)
            rng_col = dist + truth[3] + rng.normal(0, INTERFEROMETER["distance"] + INTERFEROMETER["distance_per_length"] * dist)
            lt = np.full((n, 3), np.nan)
        for key, v in (("point", np.arange(n)), ("run", np.full(n, k + 1)), ("nominal", mesh), ("tool", tool),
                       ("station", np.full(n, sid)), ("lt", lt), ("range", rng_col)):
            cols[key].append(v)
    return station_recording(cols, stations, name)


OFFSET_UM = 27.0  # the hidden range offset of station 2 (a reflector of another type)


@pytest.fixture(scope="module")
def with_offset():
    return diagnose(four_stations(7, {2: OFFSET_UM * 1e-3}))


@pytest.fixture(scope="module")
def without_offset():
    return diagnose(four_stations(7))


# ----------------------------------------------------------------------------- the offset is named
def test_a_range_offset_of_one_tracker_station_is_named_with_its_value(with_offset):
    d = with_offset
    assert [(f.candidate.effect, f.candidate.axis) for f in d.findings] == [("station_range_offset", "2")]
    f = d.findings[0]
    assert f.unit == "um"
    est, u = f.estimate[0], f.uncertainty[0]
    assert 0 < u < 10  # um, k = 1
    assert abs(est - OFFSET_UM) < 2.5 * u, (est, u)
    assert d.unexplained is None
    assert d.final["chi2_per_dof"] < d.baseline["chi2_per_dof"]


def test_the_mismatch_is_located_by_station(with_offset):
    by = with_offset.mismatch["by_station"]
    assert set(by) == {1, 2, 3, 4} and by[2]["kind"] == "xyz" and by[3]["kind"] == "range"
    # station 2's rows carry the misfit: chi-square per residual above the others'
    assert by[2]["chi2_per_residual"] > max(by[k]["chi2_per_residual"] for k in (1, 3, 4))
    text = diagnosis_text(with_offset)
    assert "FOUND station_range_offset (station 2)" in text
    assert "by station" in text and "station 2 (xyz)" in text


def test_range_stations_say_their_dead_path_is_their_offset(with_offset):
    reasons = {(s["effect"], s["axis"]): s["reason"] for s in with_offset.skipped}
    for sid in ("3", "4"):
        assert "dead path" in reasons[("station_range_offset", sid)]
    tested = {(c["effect"], c["axis"]) for c in with_offset.considered}
    assert {("station_range_offset", "1"), ("station_range_offset", "2")} <= tested


def test_without_the_offset_nothing_is_found(without_offset):
    d = without_offset
    assert d.findings == [] and d.unexplained is None
    assert d.noise["used"] == "stated"
    assert "no finding" in diagnosis_text(d)


def test_an_offset_on_every_tracker_is_not_called_one_station(tmp_path):
    """The same offset on both trackers (one tracker moved between stations) is named as the common
    tracker_range_offset, not as one station's."""
    d = diagnose(four_stations(11, {1: 27e-3, 2: 27e-3}))
    named = {(f.candidate.effect, f.candidate.axis) for f in d.findings}
    assert ("tracker_range_offset", None) in named, diagnosis_text(d)


def test_json_and_report_carry_the_station_summaries(with_offset, tmp_path):
    rec = four_stations(7, {2: OFFSET_UM * 1e-3})
    doc = json.loads(json.dumps(with_offset.to_dict()))
    assert doc["findings"][0]["effect"] == "station_range_offset" and doc["findings"][0]["axis"] == "2"
    assert doc["findings"][0]["estimate"]["unit"] == "um"
    assert {s["id"] for s in doc["settings"]["stations"]} == {1, 2, 3, 4}
    assert doc["mismatch"]["by_station"]["2"]["kind"] == "xyz"
    md = diagnosis_report(with_offset, rec, tmp_path).read_text()
    assert "By station" in md and r"station\_range\_offset[2]" in md
    assert "Noise: stated and estimated" in md


def test_one_station_recordings_keep_tracker_range_offset(null_recording):
    """On one station the new candidate is skipped with its reason; the single-station diagnosis is unchanged."""
    d = diagnose(null_recording)
    reasons = {(s["effect"], s["axis"]): s["reason"] for s in d.skipped}
    assert "tracker_range_offset" in reasons[("station_range_offset", None)]
    assert ("tracker_range_offset", None) in {(c["effect"], c["axis"]) for c in d.considered}


def test_from_two_metres_the_offset_is_absorbed_and_nothing_wrong_is_named():
    """The bundled example's trackers stand about 2 m from the points: station 2's pose absorbs 95 % of a 27 um
    offset, too little is left to name it, and nothing else is named in its place."""
    far = [(1, "xyz", np.array([-900.0, 250.0, 700.0, -0.002, 0.0004, -0.30])),
           (2, "xyz", np.array([2900.0, 320.0, 650.0, 0.001, -0.0005, 2.80]))] + STATIONS[2:]
    d = diagnose(four_stations(7, {2: OFFSET_UM * 1e-3}, stations=far))
    assert {f.candidate.label for f in d.findings} <= {"station_range_offset[2]"}
    assert d.unexplained is None


def test_physics_outside_the_library_stays_unexplained_and_is_located_at_its_station(tmp_path):
    """A cyclic error of station 1's distance meter (15 um, period 100 mm of range): no candidate describes it; the
    recording is not explained, and the misfit is located on station 1."""
    rec = four_stations(5, range_error={1: lambda r: 15e-3 * np.sin(2 * np.pi * r / 100.0)})
    d = diagnose(rec)
    assert d.findings == [] and d.unexplained is not None
    by = d.unexplained["where"]["by_station"]
    assert by[1]["chi2_per_residual"] > 1.5 * max(by[k]["chi2_per_residual"] for k in (2, 3, 4))
    text = diagnosis_text(d)
    assert "NOT EXPLAINED" in text and "      station 1 (xyz)" in text
    md = diagnosis_report(d, rec, tmp_path).read_text()
    assert "By station (an xyz row's residual in its station's frame" in md




def test_every_json_unit_of_a_station_diagnosis_parses_and_is_spelled_one_way(with_offset):
    from mtbudget.diagnose import json_unit
    from mtbudget.units import parse_unit

    doc = json.loads(json.dumps(with_offset.to_dict()))
    seen = dict(unit_fields(doc))
    assert any(".noise.stations[].stated.distance.unit" in p for p in seen)
    for path, unit in seen.items():
        parse_unit(unit, where=path)
        assert unit.isascii() and json_unit(unit) == unit, (path, unit)


# ----------------------------------------------------------------------------- bad input: one line
def test_a_station_with_too_few_rows_is_one_line_naming_the_recording():
    rec = four_stations(3)
    keep = (rec.station != 4) | (rec.plan.point < 4)  # station 4 keeps 4 rows: too few for its position
    plan = rec.plan
    small = Plan(point=plan.point[keep], run=plan.run[keep], time=plan.time[keep], nominal=plan.nominal[keep],
                 direction=plan.direction[keep], tool=plan.tool[keep])
    bad = Recording(name="too_few", machine="XFYZ", plan=small, lt=rec.lt[keep], angular=rec.angular,
                    distance=rec.distance, distance_per_length=rec.distance_per_length, repeatability=rec.repeatability,
                    station=rec.station[keep], stations=rec.stations, lt_range=rec.lt_range[keep], format_version=2)
    with pytest.raises(DiagnosisError) as exc:
        diagnose(bad)
    msg = str(exc.value)
    assert "\n" not in msg and "too_few" in msg and "station 4" in msg


def test_a_written_recording_with_too_few_rows_is_refused_in_one_line(tmp_path):
    folder = write_recording(four_stations(3), tmp_path / "rec")
    lines = (folder / "points.csv").read_text().splitlines()
    head, rows = lines[0], lines[1:]
    col = head.split(",").index("station")
    kept = [r for r in rows if r.split(",")[col].strip() != "4"] + [r for r in rows if r.split(",")[col].strip() == "4"][:3]
    (folder / "points.csv").write_text("\n".join([head] + kept) + "\n")
    with pytest.raises(RecordingError) as exc:
        read_recording(folder, several_stations=True)
    msg = str(exc.value)
    assert "\n" not in msg and "points.csv" in msg and "station 4" in msg


# ----------------------------------------------------------------------------- the bundled example
def test_the_bundled_four_station_example_has_no_finding():
    rec = read_recording(example_recording("four_stations"), several_stations=True)
    d = diagnose(rec)
    assert d.findings == [] and d.unexplained is None
    assert {s["id"] for s in d.settings["stations"]} == {1, 2, 3, 4}
