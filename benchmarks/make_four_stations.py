"""Make the bundled example mtbudget/data/recordings/four_stations (recording format 2) and its truth.json.

    python benchmarks/make_four_stations.py [OUT_FOLDER]

One simulated XFYZ machine (rigid-body geometric errors, Legendre P1..P3, squareness) measured over the
paper's 5 x 5 x 3 mesh (75 points) from four stations, one pass each, with two tool lengths alternating
(150 mm and 300 mm, so that every station sees the tilt of the tool holder):

* stations 1 and 2: laser trackers (xyz) on either side of the machine, [tracker] uncertainties;
* stations 3 and 4: tracking interferometers (range) on the table, each with its own dead-path offset and
  the stated u_r = 0.2 um + 0.3 um/m.

Noise is drawn from the stated standard uncertainties (k = 1) with a fixed seed: tracker range and angles,
interferometer range, and the machine's repeatability (each row its own positioning).  The script uses
mtbudget's own chain and tracker model; the test of the identification (tests/test_multistation.py) has
its own, independent generator.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mtbudget import tracker as lt
from mtbudget.model import MeasurementModel
from mtbudget.plan import Plan
from mtbudget.recording import Recording, Station, write_recording

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "mtbudget" / "data" / "recordings" / "four_stations"
SEED = 2020
ANGULAR, DISTANCE, DPL = 5.0e-6, 4.0e-3, 0.8e-6  # tracker: rad, mm, mm/mm (k = 1)
IFM_DISTANCE, IFM_DPL = 0.2e-3, 0.3e-6  # interferometer: mm, mm/mm (k = 1)
REPEAT = 1.5e-3  # mm
#: (id, kind, truth): an xyz pose (D, L, H mm; a, b, d rad), a range station's position (mm) and dead path (mm)
STATIONS = [
    (1, "xyz", [-900.0, 250.0, 700.0, -0.002, 0.0004, -0.30]),
    (2, "xyz", [2900.0, 320.0, 650.0, 0.001, -0.0005, 2.80]),
    (3, "range", [600.0, -350.0, -250.0, -152.318]),
    (4, "range", [1450.0, 900.0, -200.0, 87.5]),
]


def main(out: Path = OUT) -> Path:
    rng = np.random.default_rng(SEED)
    mesh = np.array([(x, y, z) for z in (200.0, 300.0, 400.0) for y in (100.0, 200.0, 300.0, 400.0, 500.0)
                     for x in (800.0, 900.0, 1000.0, 1100.0, 1200.0)])
    n = len(mesh)
    blocks = []
    for k, _ in enumerate(STATIONS):
        tool = np.zeros((n, 3))
        tool[:, 2] = np.where((np.arange(n) + k) % 2 == 0, -150.0, -300.0)
        blocks.append(tool)
    M = n * len(STATIONS)
    plan = Plan(point=np.tile(np.arange(n), len(STATIONS)), run=np.repeat(np.arange(1, len(STATIONS) + 1), n),
                time=np.arange(M) * 20.0, nominal=np.tile(mesh, (len(STATIONS), 1)), direction=np.ones((M, 3)),
                tool=np.concatenate(blocks))
    model = MeasurementModel.for_plan("XFYZ", plan)
    theta = np.zeros(model.n_params)
    for j, par in enumerate(model.errors.params):
        if par.error in ("ez(y)", "ez(z)"):
            continue  # the roll of Y and Z: tool offsets along z cannot show it (left at zero, named by identify)
        if par.is_squareness:
            theta[j] = rng.normal(0, 30e-6)
        else:
            theta[j] = rng.normal(0, (6e-3 if par.unit == "mm" else 8e-6) / max(par.order, 1))
    P_W = model.machine_points(theta[None])[0] + rng.normal(0, REPEAT, (M, 3))
    station = np.repeat([s[0] for s in STATIONS], n)
    lt_xyz = np.full((M, 3), np.nan)
    lt_range = np.full(M, np.nan)
    for sid, kind, truth in STATIONS:
        rows = station == sid
        t = np.asarray(truth)
        if kind == "xyz":
            P = lt.to_tracker(P_W[rows][None], t[None])[0]
            r = np.linalg.norm(P, axis=1)
            noise = np.stack([rng.normal(0, DISTANCE + DPL * r), rng.normal(0, ANGULAR, len(r)),
                              rng.normal(0, ANGULAR, len(r))], axis=1)
            lt_xyz[rows] = lt.add_spherical_noise(P, noise)
        else:
            d = np.linalg.norm(P_W[rows] - t[:3], axis=1)
            lt_range[rows] = d + t[3] + rng.normal(0, IFM_DISTANCE + IFM_DPL * d)
    stations = [Station(sid, kind, ANGULAR if kind == "xyz" else None, DISTANCE if kind == "xyz" else IFM_DISTANCE,
                        DPL if kind == "xyz" else IFM_DPL,
                        "laser tracker" if kind == "xyz" else "tracking interferometer on the table")
                for sid, kind, _ in STATIONS]
    rec = Recording(name="four_stations", machine="XFYZ", plan=plan, lt=lt_xyz, angular=ANGULAR, distance=DISTANCE,
                    distance_per_length=DPL, repeatability=REPEAT,
                    description="one machine from two laser trackers and two tracking interferometers (simulated)",
                    station=station, stations=stations, lt_range=lt_range, format_version=2)
    coefs, rest = model.errors.coefficients(theta)
    truth = {
        "conventions": {
            "stations": "xyz: pose D, L, H in mm and Euler angles a, b, d in rad of the station frame in the machine "
                        "frame (the paper's Eq. 21-22); range: position in mm (machine frame) and dead path in mm: "
                        "lt_range = |P - S| + dead path",
            "geometric_errors": "Legendre P1..Pn of the axis position normalised to [-1, 1] over the measured "
                                "range; um for d*, urad for e*; [P0] terms: the tool holder's tilt",
        },
        "seed": SEED,
        "stations": [({"id": sid, "kind": kind, "pose": dict(zip(lt.POSE_NAMES, truth_))} if kind == "xyz" else
                      {"id": sid, "kind": kind, "position_mm": truth_[:3], "dead_path_mm": truth_[3]})
                     for sid, kind, truth_ in STATIONS],
        "noise": {"angular_urad": ANGULAR * 1e6, "dist_um": DISTANCE * 1e3, "dist_ppm": DPL * 1e6,
                  "interferometer_dist_um": IFM_DISTANCE * 1e3, "interferometer_dist_ppm": IFM_DPL * 1e6,
                  "repeat_um": REPEAT * 1e3},
        "geometric_errors": {
            "coefficients": {k: [v * (1e3 if k[0] == "d" else 1e6) for v in vals] for k, vals in coefs.items()},
            "other_urad": {k: v * 1e6 for k, v in rest.items()},
        },
        "parameters": {name: float(v) for name, v in zip(model.errors.names, theta)},
        "parameter_units": "mm for d* terms, rad for e* terms and squareness (mtbudget's internal units)",
    }
    return write_recording(rec, out, truth=truth)


if __name__ == "__main__":
    print(main(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT))
