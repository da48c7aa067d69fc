"""Several stations in the Monte Carlo (issue 20): [[stations]] in the configuration, their simulation, the engine
identifying every trial over all stations at once, and one station against several side by side.

Independent references: the one-station path of the engine (the chord identification of :mod:`mtbudget.identify`)
for a single xyz station stated in [[stations]] (a second implementation: :mod:`mtbudget.multistation`'s
Gauss-Newton); closed-form ranges of an error-free machine written here from the configuration's numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mtbudget.config import bundled_config, load_config, parse_config
from mtbudget.engine import Engine
from mtbudget.errors import ConfigError
from mtbudget.scenario import build_scenario

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

FOUR = bundled_config("four_stations")
PAPER = bundled_config("paper_xfyz")


def four(**change) -> dict:
    d = tomllib.loads(FOUR.read_text())
    for k, v in change.items():
        d[k] = v
    return d


def noise_free(d: dict) -> dict:
    """No source at all and an error-free machine: what the stations measure is the nominal geometry."""
    d["sources"] = {"enable": []}
    d["geometric_errors"] = {"coefficients": {}, "squareness": {}}
    d.pop("sensors", None)
    return d


def one_station(name: str) -> tuple:
    """(the configuration ``name`` with its tracker stated as the only [[stations]] entry, the configuration itself):
    the four_stations configuration's first station against the paper's [tracker] (everything else is the paper's
    configuration), or the five-axis configuration's tracker moved into [[stations]]."""
    if name == "paper":
        d = four()
        d["stations"] = d["stations"][:1]
        return parse_config(d), load_config(PAPER)
    d = tomllib.loads(bundled_config("five_axis_cafxyz").read_text())
    d["stations"] = [{"kind": "xyz", **{k: d["tracker"].pop(k) for k in "DLHabd"}}]
    return parse_config(d), load_config(bundled_config("five_axis_cafxyz"))


@pytest.mark.parametrize("name, block", [("paper", 16), ("five_axis", 3)])
def test_one_station_in_stations_is_the_one_tracker_path(name, block):
    """The configuration's tracker stated as the only [[stations]] entry: measured by the stations' simulator
    (simulate.measure_stations, numpy) instead of the tracker's (the compiled MeasurementModel.predict), then
    identified as [tracker] is (Scenario.one_tracker: identify.identify, the optimisation-strategy sources' settings
    and the station's pose as iteration_pose).  The same trials to the two simulators' round-off (measured 7e-13 mm),
    so every output agrees to round-off: the compensated field (measured 6e-10 um), the identified parameters in the
    same datum (5e-9 um or urad; minimum norm on three axes, the datum rule on five, measured 3e-10), Eq. 27 before
    and after, chi2 (1e-11 relative).  When the several-station identification took this run (before issue 31),
    these tolerances failed: the field was 2.2e-6 um apart on three axes (the two chords' tolerances), 1e-7 um on
    five, Eq. 27's "before" 5-10 % (an unweighted Kabsch against the weighted pose fit) and a five-axis run's
    parameters 58 urad along what one tracker cannot identify (minimum norm against the datum rule)."""
    one_cfg, ref_cfg = one_station(name)
    one, ref = build_scenario(one_cfg), build_scenario(ref_cfg)
    assert len(one.plan) == len(ref.plan) and one.stations and not ref.stations
    a = Engine(one, block=block).run_block(0)
    b = Engine(ref, block=block).run_block(0)
    assert np.abs(a.components - b.components).max() < 1e-8  # um
    assert np.abs(a.components).max() > 1.0  # and the comparison is not between zeros
    assert np.abs(a.parameters - b.parameters).max() < 1e-7  # um, urad
    assert np.abs(a.parameters).max() > 10.0
    for k in a.scalars:
        np.testing.assert_allclose(a.scalars[k], b.scalars[k], rtol=1e-9, err_msg=k)
    assert a.not_converged == b.not_converged == 0


def test_one_laser_tracker_station_agrees_with_identify_stations(monkeypatch):
    """The engine's one-station trials, identified by the one-tracker route (never multistation's batch: it is made to
    fail here), against multistation.identify_stations (Gauss-Newton with each trial's exact Jacobian, the several-
    station reference, a second implementation), trial by trial, to the one-tracker chord's accuracy against
    Gauss-Newton (tests/test_identify_fast.py: 1e-6 mm): the compensated field (rebuilt here from the reference's
    parameters and the simulated truth), Eq. 27's mean and largest residual, chi2 per degree of freedom (measured:
    5.7e-6 um, 5.9e-6 um in the residuals, 9e-12 in chi2; the several-station chord stopped within 3e-9 um of the
    reference, the one-tracker chord accepts a bias of 1e-3 um by design, Strategy.chord_bias).  [scales]: the stated
    expansion is a fixed input of both, as of [tracker]'s identification; the station states its own angular
    uncertainty, which both weigh."""
    import mtbudget.engine as engine_module
    from mtbudget.multistation import identify_stations

    def refuse(*a, **k):
        raise AssertionError("one laser tracker station identified over several stations")

    monkeypatch.setattr(engine_module, "_StationsResult", refuse)
    d = four()
    d["stations"] = [{**d["stations"][0], "angular": "10 urad"}]  # its own stated noise: drawn and weighed
    d["scales"] = {"x": {"cte": "11.5 um/(m*K)", "fixed_point": "800 mm"}}
    d["machine_tool"].pop("cte", None)
    d["sources"]["disable"] = d["sources"].get("disable", []) + ["temperature_drift"]
    sc = build_scenario(parse_config(d))
    assert sc.correction and sc.one_tracker is not None
    n = 12
    eng = Engine(sc, block=n, seed=11)
    blk, sim = eng.run_block(0), eng.simulate(0)
    model, p = sc.id_model, sc.id_model.n_params
    F_true = sc.evaluate(sc.truth, sim[1])
    tol_um = 1e-6 * 1e3
    for i in range(n):
        r = identify_stations(model, sc.stations, sc.row_station, sim[0][i], sim.ranges[i], sc.noise.repeatability,
                              fixed=sc.correction, hold=sc.unidentifiable(model))
        assert r.converged
        comp = (sc.rigid_free @ (F_true[i] - sc.evaluate(model, r.x[None, :p])[0]).ravel()).reshape(-1, 3) * 1e3
        assert np.abs(blk.components[i] - comp).max() < tol_um, i
        d_um = np.linalg.norm(r.residual_xyz, axis=1) * 1e3
        assert abs(blk.scalars["mean_error_after"][i] - d_um.mean()) < tol_um
        assert abs(blk.scalars["max_residual"][i] - d_um.max()) < tol_um
        assert abs(blk.scalars["chi2_per_dof"][i] / r.chi2_per_dof - 1) < 1e-6
    assert np.abs(blk.components).max() > 1.0 and blk.not_converged == 0


def test_several_stations_are_not_the_one_tracker_path():
    """Two stations, or one interferometer with a tracker, keep the identification over all stations at once."""
    for keep in ([0, 1], [0, 2]):  # two trackers; a tracker and an interferometer
        d = four()
        d["stations"] = [d["stations"][i] for i in keep]
        assert build_scenario(parse_config(d)).one_tracker is None
    d = four()
    d["stations"] = d["stations"][:1]
    noise, pose = build_scenario(parse_config(d)).one_tracker
    st = d["stations"][0]
    assert np.allclose(pose[:3], [-563.52, 194.37, 677.78]) and pose[5] == pytest.approx(np.radians(59.4652))
    assert (noise.angular, noise.distance, noise.repeatability) == pytest.approx((20e-6, 4e-3, 1.5e-3))
    d["stations"][0] = {**st, "angular": "5 urad", "distance": "2 um"}  # the station's own stated noise weighs
    noise, _ = build_scenario(parse_config(d)).one_tracker
    assert (noise.angular, noise.distance, noise.distance_per_length) == pytest.approx((5e-6, 2e-3, 0.8e-6))


def test_stations_measure_the_plan_one_after_the_other_from_their_places():
    """Error-free machine, no noise: a range station reads |P - S| + dead path, an xyz station's point has the
    length |P - T| in its frame, with P = nominal + tool (XFYZ, zero errors); computed here from the TOML numbers."""
    d = noise_free(four())
    sc = build_scenario(parse_config(d))
    sim = Engine(sc, block=2).simulate(0)
    xyz, ranges = sim[0][0], sim.ranges[0]
    M0 = 75
    assert len(sc.plan) == 4 * M0
    mm = {"mm": 1.0, "m": 1000.0}
    for k, st in enumerate(d["stations"]):
        rows = np.arange(k * M0, (k + 1) * M0)
        assert np.all(sc.row_station[rows] == k + 1)
        P = sc.plan.nominal[rows] + sc.plan.tool[rows]
        if st["kind"] == "range":
            S = np.array([float(v.split()[0]) * mm[v.split()[1]] for v in st["position"]])
            o = float(st["dead_path"].split()[0])
            np.testing.assert_allclose(ranges[rows], np.linalg.norm(P - S, axis=1) + o, rtol=0, atol=1e-9)
            assert np.isnan(xyz[rows]).all()
        else:  # the point in the tracker's frame, R^T (P - T), R = Rx(a) Ry(b) Rz(d) (Eq. 22) built by scipy
            from scipy.spatial.transform import Rotation

            T = np.array([float(st[k].split()[0]) for k in "DLH"])
            R = Rotation.from_euler("XYZ", [float(st[k].split()[0]) for k in "abd"], degrees=True).as_matrix()
            np.testing.assert_allclose(xyz[rows], (P - T) @ R, atol=1e-9)
            assert np.isnan(ranges[rows]).all()
    # station k's rows come after station k-1's, with the time to move the station between them ([plan], 10 min)
    t = sc.plan.time
    assert all(t[(k + 1) * M0] - t[(k + 1) * M0 - 1] >= 600.0 for k in range(3))


def test_noise_free_stations_identify_the_machine_exactly():
    """Four stations, every pose, position and dead path unknown, a machine with errors but no noise: what is left
    after compensation is the small-angle chain's second-order leftover of this machine (below 0.01 um, as in
    tests/test_measurand.py), the same as the paper's one tracker leaves through the one-station path."""
    def run(d):
        d["sources"] = {"enable": []}
        d.pop("sensors", None)
        return Engine(build_scenario(parse_config(d)), block=2).run_block(0)

    res = run(four())
    ref = run(tomllib.loads(PAPER.read_text()))
    assert np.abs(res.components).max() < 0.01  # um
    # the leftover is outside the model space, so each set of weights projects it a little differently
    assert np.abs(res.components - ref.components).max() < 1e-3  # um
    assert res.scalars["mean_error_before"].min() > 10.0  # um: the machine has errors to identify


@pytest.mark.parametrize("change, where", [
    (lambda d: d["stations"][1].update(kind="laser"), "stations[1].kind"),
    (lambda d: d["stations"][2].pop("position"), "stations[2].position"),
    (lambda d: d["stations"][2].update(D="1 m"), "stations[2].D"),
    (lambda d: d["stations"][0].update(dead_path="1 mm"), "stations[0].dead_path"),
    (lambda d: d["stations"][0].update(dead_pth="1 mm"), "stations[0].dead_pth"),
    (lambda d: d["stations"][3].update(dead_path="12 s"), "stations[3].dead_path"),
    (lambda d: d["tracker"].update(D="1 m"), "tracker.D"),
    (lambda d: d.update(stations=d["stations"][2:]), "stations"),
    (lambda d: d.update(stations={"kind": "xyz"}), "stations"),
    (lambda d: d.update(stations=d["stations"] * 4), "stations"),  # 16 stations: more than 12
    (lambda d: d["stations"][2].update(position=["1e6 m", "0 m", "0 m"]), "stations[2].position"),
    (lambda d: d["stations"][0].update(description=3), "stations[0].description"),
    (lambda d: d["stations"][1].update(H="300 mm", D="1000 mm", L="300 mm"), "stations[1].D, L, H"),
    (lambda d: d["stations"][2].update(position=["1000 mm", "300 mm", "100 mm"]), "stations[2].position"),
    (lambda d: d["stations"][2].update(angular="5 urad"), "stations[2].angular"),
    (lambda d: d["stations"][0].update(distance="-1 um"), "stations[0].distance"),
    (lambda d: d["stations"][3].update(distance_per_length="3 kg"), "stations[3].distance_per_length"),
])
def test_bad_stations_are_one_line_naming_the_key(change, where):
    d = four()
    change(d)
    with pytest.raises(ConfigError) as exc:
        build_scenario(parse_config(d, Path("four.toml")))  # a station on the measured points: found with the plan
    msg = str(exc.value)
    assert "\n" not in msg and f"four.toml: {where}" in msg, msg


def test_simulate_writes_a_format_2_recording_that_identifies_to_its_truth(tmp_path):
    """`mtbudget simulate` of a [[stations]] configuration: a format-2 recording (station column, ranges, each
    station's stated uncertainties); identified over its stations, every dead path, tracker orientation and the
    stations' places relative to each other are found within 4 u of what truth.json says was simulated (the
    registration source's draw included)."""
    from click.testing import CliRunner

    from mtbudget.cli import main
    from mtbudget.multistation import identify_recording_any

    out = tmp_path / "sim"
    res = CliRunner().invoke(main, ["simulate", str(FOUR), "--out", str(out), "--no-identify"])
    assert res.exit_code == 0, res.output
    truth = json.loads((out / "truth.json").read_text())
    rec, ms = identify_recording_any(out)
    assert rec.format_version == 2 and len(rec.station_list()) == 4
    assert ms.converged and 0.5 < ms.chi2_per_dof < 1.5
    # what the data fix: the dead paths and where the stations stand relative to each other (the network as a whole
    # may translate along a datum freedom the error model holds by minimum norm: identify prints the datum)
    def where(st):
        return np.array(st["position_mm"] if st["kind"] == "range" else [st["pose"][k] for k in "DLH"])

    def index(st):
        first = ms.names.index(f"station {st['id']}: " + ("S_x" if st["kind"] == "range" else "D"))
        return np.arange(first, first + 3)

    first = truth["stations"][0]
    assert first["pose"] != {k: v for k, v in zip("DLHabd", load_config(FOUR).stations[0].pose)}  # as drawn
    for st in truth["stations"]:
        if st["kind"] == "xyz":  # the orientation of each tracker, as the registration source drew it
            vals, us = ms.station_values(st["id"])
            expect = np.array([st["pose"][k] for k in "abd"])
            diff = (vals[3:] - expect + np.pi) % (2 * np.pi) - np.pi  # d = pi and -pi are one orientation
            assert np.all(np.abs(diff) < 4 * us[3:]), (st["id"], diff, us[3:])
        if st["kind"] == "range":
            j = ms.names.index(f"station {st['id']}: dead path")
            assert abs(ms.x[j] - st["dead_path_mm"]) < 4 * np.sqrt(ms.cov[j, j]), st
        if st is first:
            continue
        D = np.zeros((3, len(ms.x)))
        D[:, index(st)] += np.eye(3)
        D[:, index(first)] -= np.eye(3)
        got, expect = D @ ms.x, where(st) - where(first)
        u = np.sqrt(np.diag(D @ ms.cov @ D.T))
        assert np.all(np.abs(got - expect) < 4 * u), (st["id"], got - expect, u)


def test_one_station_and_four_side_by_side(tmp_path):
    """The comparison runs the first station alone and all four on the same machine; both are complete per-point
    statements and the four-station verification is the better one where the one tracker's angles dominate."""
    from mtbudget.report_study import stations_lines, stations_report
    from mtbudget.study import stations_comparison

    r = stations_comparison(load_config(FOUR), trials=32, attribution_trials=0)
    one, many = r["variants"]
    assert one["label"].startswith("1 station") and many["label"].startswith("4 stations")
    assert one["u"].shape == many["u"].shape == (75, 3)
    assert max(r["ratio_median"]) < 1.0
    text = "\n".join(stations_lines(r))
    assert "k = 1" in text and "µm" in text
    md = stations_report(r, tmp_path)
    assert (tmp_path / "stations_u.png").stat().st_size > 1000 and md.read_text().count("\n| ") >= 77
    json.loads((tmp_path / "stations.json").read_text())


def test_the_comparison_needs_two_stations():
    from mtbudget.study import stations_comparison

    with pytest.raises(ConfigError, match="at least two"):
        stations_comparison(load_config(PAPER), trials=2)


@pytest.mark.parametrize("tool", [None, ["0 mm", "0 mm", "-300 mm"]])
def test_four_stations_monte_carlo_matches_the_propagated_identification_covariance(tool):
    """With only the noise the identification states (tracker noise with a fixed angular u, repeatability), the
    Monte Carlo's u per point and axis agrees with the GUF: the covariance of the multi-station identification
    propagated to the compensated field (budget.point_lpu), also at a [measurand] tool the verification did not use
    (what it cannot identify there drawn from its prior in both).  384 trials: each MC u is known to about 4 %."""
    from mtbudget.runner import run

    d = four()
    d["sources"] = {"enable": ["tracker_noise", "repeatability"], "tracker_noise": {"angular_sd": "0 urad"}}
    d.pop("sensors", None)
    if tool:
        d["measurand"] = {"tool": tool}
    res = run(parse_config(d), trials=384, attribution_trials=0, block=64)
    pts = res.points()
    u = np.array([p["u"]["value"] for p in pts])
    g = np.array([p["guf_u"]["value"] for p in pts])
    ratio = u / g
    assert abs(np.median(ratio) - 1) < 0.05, np.median(ratio)
    assert np.all(np.abs(ratio - 1) < 0.2), (ratio.min(), ratio.max())
    if tool:
        return
    # and the GUF is the four-station one: well below what the one tracker alone gives (y: about a fifth)
    one = four()
    one["stations"] = one["stations"][:1]
    from mtbudget.budget import point_lpu

    g1 = np.sqrt(np.diagonal(point_lpu(build_scenario(parse_config(one)))["cov"], axis1=1, axis2=2))
    assert np.median(g[:, 1] / g1[:, 1]) < 0.5


# ----------------------------------------------------------------------------- where to put several stations
def test_station_information_summed_is_the_joint_identification():
    """The placement study's u of a set (each station's reduced information, summed: Schur complements) equals the
    GUF of the identification over all the set's stations at once (budget.point_lpu through identify_stations, the
    full joint covariance), for the bundled four stations and for the first alone."""
    from mtbudget.budget import point_lpu
    from mtbudget.study import configured_candidates, set_uncertainty, station_information, unidentified_variance

    for tool in (None, ["0 mm", "0 mm", "-300 mm"]):  # at the verification's tool, and at a longer one
        d = four()
        if tool:
            d["measurand"] = {"tool": tool}
        cfg = parse_config(d)
        sc = build_scenario(cfg)
        info, Jf = station_information(sc, configured_candidates(cfg))
        for k in (1, 4):
            dk = dict(d, stations=d["stations"][:k])
            g = np.sqrt(np.diagonal(point_lpu(build_scenario(parse_config(dk)))["cov"], axis1=1, axis2=2))
            u = set_uncertainty(info[:k].sum(axis=0), Jf, prior=unidentified_variance(sc)) * 1e3  # um
            np.testing.assert_allclose(u, g, rtol=5e-3)  # linearised at the nominal vs at the noise-free solution


def test_station_placement_ranks_sets_and_more_stations_never_hurt():
    from mtbudget.study import ring_candidates, set_uncertainty, station_information, station_placement

    sc = build_scenario(load_config(PAPER))
    cands = ring_candidates(sc, 6, "xyz", 2500.0, 500.0)
    r = station_placement(sc, cands, k_max=3)
    best = [k["best_max_u"] for k in r["per_k"]]
    assert best[0] > best[1] > best[2]
    # the best set is the best: every set of two, recomputed here, is no better
    from itertools import combinations

    info, Jf = station_information(sc, cands)
    two = min(set_uncertainty(info[list(c)].sum(axis=0), Jf).max() for c in combinations(range(6), 2)) * 1e3
    assert abs(two - best[1]) < 1e-9 * two
    assert [k["sets"] for k in r["per_k"]] == [6, 15, 20]
    # information only adds: a station added to any set lowers u at every point and axis
    rng = np.random.default_rng(5)
    for _ in range(5):
        a = list(rng.choice(6, 2, replace=False))
        extra = [i for i in range(6) if i not in a][0]
        u2 = set_uncertainty(info[a].sum(axis=0), Jf)
        u3 = set_uncertainty(info[a + [extra]].sum(axis=0), Jf)
        assert np.all(u3 <= u2 * (1 + 1e-9))


def test_range_stations_too_few_to_identify_are_said_so():
    from mtbudget.study import ring_candidates, station_placement

    sc = build_scenario(load_config(PAPER))
    r = station_placement(sc, ring_candidates(sc, 6, "range", 2500.0, 500.0), k_max=4)
    assert r["per_k"][0]["identifying"] == 0 and "best_max_u" not in r["per_k"][0]
    assert r["per_k"][3]["identifying"] > 0 and np.isfinite(r["per_k"][3]["best_max_u"])


@pytest.mark.parametrize("args, text", [
    (["--radius", "2 kg"], "--radius"),
    (["--stations", "5", "--candidates", "4"], "--candidates"),
])
def test_station_placement_options_are_checked(args, text, tmp_path):
    from click.testing import CliRunner

    from mtbudget.cli import main

    res = CliRunner().invoke(main, ["study", "station-placement", "--quiet", "--out", str(tmp_path)] + args)
    assert res.exit_code != 0 and text in res.output and "Traceback" not in res.output


def test_station_placement_command_writes_its_report(tmp_path):
    from click.testing import CliRunner

    from mtbudget.cli import main

    res = CliRunner().invoke(main, ["study", "station-placement", "--stations", "2", "--candidates", "5", "--quiet",
                                    "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "k = 1" in res.output and "µm" in res.output
    data = json.loads((tmp_path / "station_placement.json").read_text())
    assert [k["sets"] for k in data["per_k"]] == [5, 10]
    assert (tmp_path / "station_placement.png").stat().st_size > 1000
    assert "<table" in (tmp_path / "station_placement.html").read_text()


def test_a_study_never_replaces_a_previous_one_silently(tmp_path):
    """As `run` refuses to overwrite a log: a second study into the same --out is one line unless --force."""
    from click.testing import CliRunner

    from mtbudget.cli import main

    args = ["study", "station-placement", "--stations", "1", "--candidates", "2", "--quiet", "--out", str(tmp_path)]
    assert CliRunner().invoke(main, args).exit_code == 0
    before = (tmp_path / "station_placement.json").read_bytes()
    res = CliRunner().invoke(main, args + ["--candidates", "3"])
    assert res.exit_code == 2 and "already there" in res.output and "--force" in res.output
    assert (tmp_path / "station_placement.json").read_bytes() == before
    res = CliRunner().invoke(main, args + ["--candidates", "3", "--force"])
    assert res.exit_code == 0 and (tmp_path / "station_placement.json").read_bytes() != before


@pytest.mark.parametrize("stations", [slice(None), slice(1, None)])
def test_batched_identification_is_identify_stations_trial_by_trial(stations):
    """identify_stations_batch (the engine's: vectorised over trials, Jacobian refreshed only after chord steps)
    gives every trial's result as identify_stations does, one trial at a time: the compensated field to 1e-6 um,
    every unknown to 1e-4 of a scaled unknown (um, urad; both stop when a step is below 1e-7, and the weakest
    directions stop further apart), with and without the held directions; four stations, and one tracker with two
    interferometers."""
    from mtbudget.multistation import _scales, identify_stations, identify_stations_batch

    d = four()
    d["stations"] = d["stations"][stations]
    sc = build_scenario(parse_config(d))
    sim = Engine(sc, block=12).simulate(0)
    model = sc.id_model
    for hold in (None, sc.unidentifiable(model)):
        b = identify_stations_batch(model, sc.stations, sc.row_station, sim[0], sim.ranges, sc.noise.repeatability,
                                    hold=hold)
        assert b["converged"].all() and not b["failed"].any()
        for i in range(12):
            r = identify_stations(model, sc.stations, sc.row_station, sim[0][i], sim.ranges[i],
                                  sc.noise.repeatability, hold=hold)
            scale = _scales(model, sc.stations)
            assert np.abs((b["x"][i] - r.x) * scale).max() < 1e-4, i
            p = model.n_params
            F = sc.evaluate(model, np.stack([b["theta"][i], r.x[:p]]))
            assert np.abs(sc.rigid_free @ (F[0] - F[1]).ravel()).max() * 1e3 < 1e-6  # um
            assert abs(b["chi2"][i] / r.chi2 - 1) < 1e-9
            np.testing.assert_allclose(b["residual_range"][i], r.residual_range, atol=1e-9)  # mm


def test_a_trial_the_batch_cannot_finish_is_solved_by_the_reference(monkeypatch):
    """A trial the batched solver gives up on (its cost rose on a Gauss-Newton step) is solved again by
    identify_stations and counted as a fallback: the block's results equal those of the batch itself."""
    import mtbudget.multistation as ms

    sc = build_scenario(load_config(FOUR))
    ref = Engine(sc, block=4).run_block(0)
    real = ms.identify_stations_batch

    given_up, depth = [], []

    def gives_up(*args, **kw):
        depth.append(1)  # a lone trial is identified as two by a call of the function itself: count the outer call
        try:
            out = real(*args, **kw)
        finally:
            depth.pop()
        if kw.get("basis") is None or depth:  # the engine's basis from the noise-free verification, or inner
            return out
        out["failed"] = np.arange(len(out["theta"])) % 2 == 1
        given_up.append(int(out["failed"].sum()))
        out["theta"] = out["theta"] + out["failed"][:, None] * 1e-3  # wrong where failed: the reference must replace it
        return out

    monkeypatch.setattr(ms, "identify_stations_batch", gives_up)
    res = Engine(sc, block=4).run_block(0)
    assert res.fallbacks == sum(given_up) >= 1
    assert np.abs(res.components - ref.components).max() < 1e-6  # um


def test_the_paper_studies_refuse_several_stations_and_study_stations_needs_a_tracker(tmp_path):
    from click.testing import CliRunner

    from mtbudget.cli import main
    from mtbudget.study import stations_comparison

    for cmd in (["study", "verification"], ["study", "all"]):
        res = CliRunner().invoke(main, cmd + [str(FOUR), "--out", str(tmp_path / "x"), "--quiet"])
        assert res.exit_code == 2 and "study stations" in res.output and "Traceback" not in res.output
        assert not (tmp_path / "x").exists()
    d = four()
    d["stations"] = d["stations"][2:] + [dict(d["stations"][3], position=["2500 mm", "300 mm", "1200 mm"])]
    with pytest.raises(ConfigError, match="all interferometers"):
        stations_comparison(parse_config(d), trials=2)
    # a range station first: the one-station baseline is the first laser tracker
    d = four()
    d["stations"] = d["stations"][2:] + d["stations"][:2]
    r = stations_comparison(parse_config(d), trials=16, attribution_trials=0)
    assert r["variants"][0]["kinds"] == "xyz" and r["variants"][1]["kinds"] == "range, range, xyz, xyz"


def test_a_station_draws_and_weighs_its_own_stated_noise():
    """An interferometer stating 0.2 um + 0.3 um/m: tracker_noise draws its ranges with that standard deviation
    (closed form at each row's distance, 4000 trials), the trackers keep the [tracker] 4 um + 0.8 um/m, and the
    identification weighs each station with its own."""
    from mtbudget.simulate import sample_source

    sc = build_scenario(load_config(FOUR))
    src = next(s for s in sc.sources if s.name == "tracker_noise")
    draw = sample_source(sc, src, 4000, np.random.default_rng(1))["spherical_noise.range"]  # (n, M) mm
    r = np.linalg.norm(sc.context.nominal_tracker_points, axis=1)
    for st in sc.stations:
        rows = sc.row_station == st.id
        expect = (0.2e-3 + 0.3e-6 * r[rows]) if st.kind == "range" else (4e-3 + 0.8e-6 * r[rows])
        np.testing.assert_allclose(draw[:, rows].std(axis=0), expect, rtol=0.1)
        assert st.distance == (0.2e-3 if st.kind == "range" else 4e-3)


def test_the_best_set_pasted_into_a_configuration_gives_the_same_uncertainty(tmp_path):
    """The [[stations]] tables the placement study prints for its best set read back as a configuration whose own
    stations, ranked the same way, give the same largest u (the printed places are rounded to 0.1 mm and 1e-4 deg)."""
    from mtbudget.report_study import stations_toml
    from mtbudget.study import (configured_candidates, ring_candidates, set_uncertainty, station_information,
                                station_placement)

    sc = build_scenario(load_config(PAPER))
    r = station_placement(sc, ring_candidates(sc, 6, "xyz", 2500.0, 500.0, {"angular": 10e-6}), k_max=3)
    best = r["per_k"][-1]
    text = PAPER.read_text()
    start = text.index("[tracker]")
    end = text.index('angular = "20 urad"', start)
    text = text[:start] + "[tracker]\n" + text[end:] + "\n" + "\n".join(
        stations_toml([r["candidates"][i] for i in best["best"]])) + "\n"
    (tmp_path / "best.toml").write_text(text)
    cfg = load_config(tmp_path / "best.toml")
    assert [st.angular for st in cfg.stations] == [pytest.approx(10e-6)] * 3
    sc3 = build_scenario(cfg)
    info, Jf = station_information(sc3, configured_candidates(cfg))
    assert set_uncertainty(info.sum(axis=0), Jf).max() * 1e3 == pytest.approx(best["best_max_u"], rel=1e-3)


def test_several_stations_are_bit_identical_for_any_grouping_of_the_trials():
    """Blocks identified together equal each block alone, bit for bit, and a run does not depend on its chunking
    (the batch iterates along one basis from the noise-free verification, not the first trial of its group)."""
    from mtbudget.runner import run

    sc = build_scenario(load_config(FOUR))
    eng = Engine(sc, block=8)
    together = eng.run_blocks([0, 1, 2])
    for b, res in zip([0, 1, 2], together):
        alone = Engine(sc, block=8).run_block(b)
        assert np.array_equal(res.components, alone.components) and np.array_equal(res.parameters, alone.parameters)
    a = run(load_config(FOUR), trials=48, block=8, chunk_blocks=1, attribution_trials=0)
    b = run(load_config(FOUR), trials=48, block=8, chunk_blocks=3, attribution_trials=0)
    assert a.outputs() == b.outputs() and a.points() == b.points()


def test_one_station_run_is_bit_for_bit_under_any_grouping_replays_and_says_stations(tmp_path):
    """A one-station run, now identified as [tracker] (labels per block, shared iteration matrices from the station's
    pose): blocks identified together equal each block alone bit for bit; its log recomputes bit for bit (replay
    --verify); and what it prints says it was measured from one [[stations]] station, with the strategy acting."""
    from mtbudget.report import _idle_sources, measurand_text
    from mtbudget.runner import execute, verify

    cfg, _ = one_station("paper")
    sc = build_scenario(cfg)
    together = Engine(sc, block=8).run_blocks([0, 1, 2])
    for b, res in zip([0, 1, 2], together):
        alone = Engine(sc, block=8).run_block(b)
        assert np.array_equal(res.components, alone.components) and np.array_equal(res.parameters, alone.parameters)
        assert all(np.array_equal(res.scalars[k], alone.scalars[k]) for k in res.scalars)
    path = tmp_path / "one.mcap"
    text = FOUR.read_text()
    (tmp_path / "one.toml").write_text(text[:text.index("[[stations]]                 # a second tracker")])
    res = execute(load_config(tmp_path / "one.toml"), trials=48, log_path=path, progress=False, attribution_trials=0,
                  block=16)
    v = verify(path)
    assert v["identical"] and v["trials"] == 48
    said = measurand_text(res)
    assert "1 station (xyz, [[stations]])" in said and "strategy's phases and tolerance apply" in said
    assert _idle_sources(res.spec) == {}
    d = four()
    d["stations"] = d["stations"][:2]
    assert _idle_sources({"config": {"stations": d["stations"]}}) == {}  # the strategy acts on several stations too


def test_budgets_of_several_stations_count_the_strategy_sources_as_with_one_tracker(tmp_path):
    """Both budgets (per point and compensation_rms), in the text and in the report, show the optimisation-strategy
    sources of a four-station run as rows like any other (they act: multistation.strategy_settings), as with
    [tracker]; what the run says of its stations says the strategy applies.  (They were marked 'does not act with
    several [[stations]]' while the identification over several stations ignored them.)"""
    from mtbudget.report import budget_text, measurand_text, run_report
    from mtbudget.runner import run

    def rows(text, head):
        part = text[text.index(head):].split("\n\n")[0]  # the table, to its blank line
        return {ln.split()[0]: ln for ln in part.splitlines()[2:]}

    res = run(load_config(FOUR), trials=16, block=8, attribution_trials=8)
    text = budget_text(res)
    for head in ("Budget of the per-point measurand", "Budget of compensation_rms"):
        got = rows(text, head)
        for src in ("convergence_criteria", "phase_sequence"):
            assert src in got and "act" not in got[src], (head, got[src])
    assert "does not act" not in text
    assert "strategy's phases and tolerance apply, as with one tracker" in measurand_text(res)
    md = run_report(res, tmp_path / "r")["markdown"].read_text()
    part = md[md.index("### Budget of compensation_rms"):]
    assert "| convergence_criteria | optimisation strategy |" in part
    assert "| phase_sequence | optimisation strategy |" in part
