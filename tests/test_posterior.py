"""The a posteriori statement of a recording against an independent linear propagation of its stated noise."""

import json

import numpy as np
import pytest
from conftest import stated_noise_propagation
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.config import example_recording
from mtbudget.identify import Noise, identify
from mtbudget.model import MeasurementModel
from mtbudget.posterior import posterior
from mtbudget.recording import read_recording

UM_PER_MM = 1000.0


def linear_u(folder, h=2e-4):
    """u of each compensated point-axis by central differences of identify -> compensate in the recording's measured
    coordinates, with the stated Eq. 23 covariance plus repeatability written here (um)."""
    rec = read_recording(folder)
    model = MeasurementModel.for_plan(rec.machine, rec.plan, max_degree=3)
    noise, fixed = Noise.of(rec), rec.fixed_inputs()
    fit = identify(model, rec.lt, noise, fixed=fixed)
    y0 = model.predict(fit.theta, fit.pose[0], fixed)[0]
    plan = rec.plan
    rows = np.flatnonzero((plan.run == plan.run.min()) & np.all(plan.tool == plan.tool[0], axis=1))
    P = model.machine_points(fit.theta, fixed)[0][rows]
    c = P - P.mean(0)  # the rigid motions of the mesh points, removed by least squares (written here)
    R = np.concatenate([np.tile(np.eye(3), (len(P), 1)),
                        np.stack([np.cross(np.eye(3)[k], c).reshape(-1) for k in range(3)], axis=1)], axis=1)
    Pi = np.eye(3 * len(P)) - R @ np.linalg.solve(R.T @ R, R.T)

    def field(meas):
        th = identify(model, meas, noise, fixed=fixed).theta
        return (model.machine_points(th, fixed)[:, rows]).reshape(len(meas), -1) @ Pi.T

    return stated_noise_propagation(field, y0, noise, h) * UM_PER_MM


def test_a_posteriori_u_agrees_with_the_identification_covariance_within_5_percent():
    folder = example_recording("thermal_x")
    p = posterior(folder, trials=4096, seed=3)
    u = np.array([q["u"]["value"] for q in p["points"]]).reshape(-1)
    u_ind = linear_u(folder)
    ok = u_ind > 1e-3
    ratio = u[ok] / u_ind[ok]
    # u of 4096 trials scatters by 1/sqrt(2 * 4096) = 1.1 % per point-axis
    assert np.median(ratio) == pytest.approx(1.0, abs=0.015)
    assert np.abs(ratio - 1).max() < 0.05
    assert np.allclose(np.array([q["u_linear"]["value"] for q in p["points"]]).reshape(-1), u_ind, rtol=5e-3, atol=1e-4)
    assert p["statement_kind"]["kind"] == "a posteriori" and p["statement_kind"]["recording"]
    assert p["not_converged"] == 0


def test_posterior_command(tmp_path):
    r = CliRunner().invoke(main, ["posterior", "--example", "null", "--trials", "256", "--json", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["statement_kind"]["kind"] == "a posteriori"
    md = (tmp_path / "posterior.md").read_text()
    assert md.startswith("# mtbudget a posteriori") and md.count("\n| ") >= 75 + 2  # a row per point
    assert (tmp_path / "posterior.html").exists() and json.loads((tmp_path / "posterior.json").read_text())["points"]
    r = CliRunner().invoke(main, ["posterior", "--example", "null", "--trials", "256", "--noise", "estimated"])
    assert r.exit_code == 0 and "A POSTERIORI" in r.output and "sqrt(chi2/dof)" in r.output


def test_a_posteriori_statement_tests_the_fit_and_warns_where_the_model_leaves_physics_out(tmp_path):
    """thermal_x holds a thermal expansion the rigid-body model leaves out (chi2/dof 1.42 on 852 dof): the statement
    warns, on stderr, in its text and in posterior.md, naming diagnose; the null recording (the model's own physics)
    passes.  The tail probabilities against scipy.stats' chi2, computed here from the reported chi2/dof and dof."""
    from scipy.stats import chi2 as chi2_dist

    from mtbudget.posterior import FIT_ALPHA

    for example, warns in (("thermal_x", True), ("null", False)):
        p = posterior(example_recording(example), trials=8, seed=1)
        i = p["identification"]
        t, x = i["fit_test"], i["chi2_per_dof"] * i["dof"]
        assert t["p_above"] == pytest.approx(chi2_dist.sf(x, i["dof"]), rel=1e-9, abs=1e-300)
        assert t["p_below"] == pytest.approx(chi2_dist.cdf(x, i["dof"]), rel=1e-9, abs=1e-300)
        assert (t["warning"] is not None) == warns == (min(t["p_above"], t["p_below"]) < FIT_ALPHA)
    assert "diagnose thermal_x" in posterior(example_recording("thermal_x"), trials=8)["identification"]["fit_test"]["warning"]
    r = CliRunner().invoke(main, ["posterior", "--example", "thermal_x", "--trials", "8", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert "warning: the identified model does not fit thermal_x" in r.stderr
    assert "WARNING: the identified model does not fit" in r.stdout
    assert "**Warning: the identified model does not fit" in (tmp_path / "posterior.md").read_text()
    r = CliRunner().invoke(main, ["posterior", "--example", "null", "--trials", "8"])
    assert "warning" not in r.output.lower() and "passes at 0.001" in r.output
