"""The compensated machine at a tool the verification did not use ([measurand] tool, issue 14).

The verification's tools lie on the spindle axis, so the yaw of Z (ECZ) cannot be identified; at a lateral
tool it moves the tool point by its angle times the lateral offset (an Abbe error), which nothing corrects.
Checked against that closed form, with the rigid part removed by a least-squares fit written in the test.
"""

from pathlib import Path

import numpy as np
import pytest

from mtbudget.budget import point_lpu
from mtbudget.config import load_config
from mtbudget.errors import ConfigError
from mtbudget.scenario import build_scenario

SMALL = Path(__file__).parent / "data" / "small.toml"
EPS_URAD = 20.0  # ez(z)[P1] of the truth: the yaw of Z, linear in z over the mesh
LATERAL = 100.0  # mm: the lateral tool offset along x


def config(tmp_path, tool=None, coefficients=True, name="c.toml"):
    text = SMALL.read_text()
    if coefficients:
        text += f'\n[geometric_errors.coefficients]\n"ez(z)" = ["{EPS_URAD} urad"]\n'
    if tool is not None:
        text += "\n[measurand]\ntool = [" + ", ".join(f'"{v} mm"' for v in tool) + "]\n"
    p = tmp_path / name
    p.write_text(text)
    return load_config(p)


def rigid_residual(points: np.ndarray, field: np.ndarray) -> np.ndarray:
    """``field`` (M, 3) minus its least-squares rigid motion (translation + small rotation) over ``points``."""
    c = points - points.mean(axis=0)
    M = len(points)
    A = np.zeros((M, 3, 6))
    A[:, :, :3] = np.eye(3)
    for k in range(3):  # omega_k e_k x c
        e = np.zeros(3)
        e[k] = 1.0
        A[:, :, 3 + k] = np.cross(e, c)
    A = A.reshape(3 * M, 6)
    b = field.reshape(-1)
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    return (b - A @ x).reshape(M, 3)


def test_the_verifications_own_tool_leaves_nothing_of_an_unidentifiable_yaw(tmp_path):
    sc = build_scenario(config(tmp_path))
    assert sc.measurand_tool is None and np.allclose(sc.tool, [0, 0, -150])
    assert np.abs(point_lpu(sc)["estimate"]).max() < 1e-6  # um
    assert sc.unidentified_at_tool() == []


def test_stating_the_verifications_tool_changes_nothing(tmp_path):
    a = build_scenario(config(tmp_path, name="a.toml"))
    b = build_scenario(config(tmp_path, tool=(0, 0, -150), name="b.toml"))
    assert b.measurand_tool is None
    np.testing.assert_array_equal(a.mesh_points, b.mesh_points)


def test_a_lateral_tool_shows_the_abbe_error_of_the_yaw_of_z(tmp_path):
    sc = build_scenario(config(tmp_path, tool=(LATERAL, 0, -150)))
    np.testing.assert_allclose(sc.tool, [LATERAL, 0, -150])
    y0 = point_lpu(sc)["estimate"]  # the noise-free verification's compensated error, um
    z = sc.commanded[:, 2]
    zn = (z - 300.0) / 100.0  # Legendre argument over the verification's z range 200..400 mm
    phi = EPS_URAD * 1e-6 * zn  # rad, P1 = zn
    abbe = np.zeros((len(z), 3))
    abbe[:, 1] = phi * LATERAL  # (phi e_z) x (LATERAL, 0, -150) = (0, phi LATERAL, 0), mm
    points = sc.commanded + np.array([LATERAL, 0.0, -150.0])
    expected = rigid_residual(points, abbe) * 1e3  # um
    assert np.abs(expected).max() > 0.3  # the check has something to see: 20 urad x 100 mm = 2 um before the rigid fit
    np.testing.assert_allclose(y0, expected, atol=2e-3)
    names = {c["iso"] for u in sc.unidentified_at_tool() for c in u["combination"]}
    assert "ECZ[P1]" in names


def test_the_monte_carlo_covers_the_unidentifiable_part_through_the_prior(tmp_path):
    """With generation functions (no explicit coefficients) the truth draws ECZ; at a lateral tool the compensated
    machine's error grows with the lateral offset, at the verification's tool it does not."""
    from mtbudget.engine import Engine

    def rms(tool):
        sc = build_scenario(config(tmp_path, tool=tool, coefficients=False, name=f"{tool[0]:g}.toml"), sources=[])
        comp = Engine(sc, block=4, seed=3).run_block(0).components
        return float(np.sqrt(np.mean(comp**2)))

    assert rms((300.0, 0.0, -150.0)) > 1.5 * rms((0.0, 0.0, -150.0))


@pytest.mark.parametrize("value, words", [('["1 mm", "2 mm"]', "expected [tx, ty, tz]"),
                                          ('["1 mm", "2 mm", "3 s"]', "[length]"),
                                          ('["1 km", "0 mm", "0 mm"]', "beyond")])
def test_bad_measurand_tool_names_the_key(tmp_path, value, words):
    p = tmp_path / "c.toml"
    p.write_text(SMALL.read_text() + f"\n[measurand]\ntool = {value}\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert "measurand.tool" in str(e.value) and words in str(e.value)


def test_the_unidentified_part_is_drawn_from_the_prior_and_the_guf_agrees(tmp_path):
    """No noise source: at a lateral tool the only spread left is the prior of what the verification cannot
    identify; the Monte Carlo (sampling the prior in the truth) and the GUF (its covariance propagated) agree."""
    from mtbudget.engine import Engine

    sc = build_scenario(config(tmp_path, tool=(300.0, 0.0, -150.0), coefficients=False), sources=[])
    assert sc.unidentified_prior() is not None and sc.null_bias is not None
    eng = Engine(sc, block=256, seed=11)
    comp = np.concatenate([eng.run_block(b).components for b in range(4)])  # (1024, M0, 3) um
    u_mc = comp.std(axis=0)
    # the GUF's prior part: its covariance with the prior less the one without (the stated noise, which this MCM
    # does not draw: no source)
    assert [s.name for s in sc.sources] == ["unidentified_at_tool"]  # switched on by [measurand] tool, its own row
    with_prior = point_lpu(sc)["cov"]
    measurand, sc.context.measurand = sc.context.measurand, None
    u_guf = np.sqrt(np.einsum("mii->mi", with_prior - point_lpu(sc)["cov"]))
    sc.context.measurand = measurand
    big = u_guf > 0.2 * u_guf.max()
    assert big.sum() >= 10
    ratio = u_mc[big] / u_guf[big]
    assert abs(np.median(ratio) - 1) < 0.05 and np.all(np.abs(ratio - 1) < 0.15)  # 1024 draws: sd of u ~2.2 %
    # at the verification's own tool the prior is not drawn: nothing there depends on it
    assert build_scenario(config(tmp_path, coefficients=False, name="v.toml"), sources=[]).unidentified_prior() is None


def test_the_budget_at_another_tool_gives_the_unidentified_part_its_own_row(tmp_path):
    """The prior is a source of its own: the other sources' one-at-a-time contributions stay what they are at
    the verification's tool (their rows do not carry it), and the truth's own unidentifiable part is not also
    left as a bias."""
    from mtbudget.runner import run

    def rows(tool, name):
        res = run(config(tmp_path, tool=tool, coefficients=False, name=name), trials=64, attribution_trials=64)
        return {r["source"]: np.asarray(r["u_rms_over_mesh"]) for r in res.budget["points"]["rows"]}, res

    at_tool, res = rows((300.0, 0.0, -150.0), "lateral.toml")
    own, _ = rows(None, "own.toml")
    assert "unidentified_at_tool" in at_tool and "unidentified_at_tool" not in own
    assert at_tool["unidentified_at_tool"].max() > 1.0  # um
    assert at_tool["cte_uncertainty"].max() < 0.2 and own["cte_uncertainty"].max() < 0.2
    mean = np.array([p["mean"]["value"] for p in res.points()])
    u = np.array([p["u"]["value"] for p in res.points()])
    assert np.abs(mean).max() < 2.0 * u.max()


def test_a_misspelt_measurand_key_is_an_error(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text(SMALL.read_text() + '\n[measurand]\ntol = ["0 mm", "0 mm", "-300 mm"]\n')
    with pytest.raises(ConfigError, match="unknown key; did you mean 'tool'"):
        load_config(p)
