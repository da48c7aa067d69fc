"""The compensated machine in use (issue 14): repeatability, reversal from an unknown side and the thermal residual
at a workshop temperature, added to the measurand only.  Checked against their covariance written in closed form."""

from pathlib import Path

import numpy as np

from mtbudget.config import load_config
from mtbudget.engine import Engine
from mtbudget.scenario import build_scenario

SMALL = Path(__file__).parent / "data" / "small.toml"
R, B_MAX, U_CTE, DT = 1.5e-3, 3.0e-3, 0.577e-6, 2.0  # mm, mm, 1/K, K: the source's defaults


def scenario(tmp_path, sources):
    p = tmp_path / "c.toml"
    p.write_text(SMALL.read_text() + '\n[geometric_errors.coefficients]\n"dx(x)" = ["0 um"]\n')  # an error-free machine
    return build_scenario(load_config(p), sources=sources)


def test_the_in_use_terms_have_their_closed_form_covariance(tmp_path):
    sc = scenario(tmp_path, ["in_use"])
    comp = np.concatenate([Engine(sc, block=256, seed=2).run_block(b).components for b in range(8)])  # um
    pos = sc.commanded  # (M0, 3) mm: the thermal residual is (CTE error) x (T - 20 degC) x position, about zero
    M0 = len(pos)
    S = np.zeros((M0, 3, M0, 3))
    for a in range(3):
        S[:, a, :, a] = np.outer(pos[:, a], pos[:, a]) * U_CTE**2 * DT**2 / 3.0  # one CTE error per axis and trial
        S[np.arange(M0), a, np.arange(M0), a] += R**2 + B_MAX**2 / 12.0  # repeatability; +-B/2, B ~ U[0, B_max]
    S = S.reshape(3 * M0, 3 * M0)
    u_closed = np.sqrt(np.diag(sc.rigid_free @ S @ sc.rigid_free.T)).reshape(M0, 3) * 1e3  # um
    ratio = comp.std(axis=0) / u_closed
    assert abs(np.median(ratio) - 1.0) < 0.04 and np.all(np.abs(ratio - 1.0) < 0.15)  # 2048 trials: sd ~1.6 %


def test_the_verifications_measurements_do_not_see_the_machine_in_use(tmp_path):
    with_it = Engine(scenario(tmp_path, ["tracker_noise", "in_use"]), block=16, seed=4).simulate(0)
    without = Engine(scenario(tmp_path, ["tracker_noise"]), block=16, seed=4).simulate(0)
    np.testing.assert_array_equal(with_it[0], without[0])
    assert with_it.measurand_offset is not None and without.measurand_offset is None
