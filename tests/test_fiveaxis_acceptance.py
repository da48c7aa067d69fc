"""Issue 26, "Done when" for five-axis identification: recordings written by the independent generator
(tests/fiveaxis_generator.py, no mtbudget code) identified through the public CLI (`identify DIR --json`).

* chi-square per degree of freedom in [0.8, 1.25];
* every rotary location, orientation and zero parameter within 3 of its stated standard uncertainties (k = 1) of
  the truth, or named in `not_identifiable`; the null (perfect rotary axes) shows nothing beyond 3 u;
* `not_identifiable` is the null space of the plan at hand: every combination it names is a null direction of
  the generator's own Jacobian, and it names as many independent ones as there are.

The comparison (tests/fiveaxis_check.py) is invariant under any datum or minimum-norm choice: a parameter in a
null direction is compared through its identifiable combination; tests/test_fiveaxis_check.py checks it against
a second, independent fit under several datum choices.

Until mtbudget reads format 3 the module is skipped (reading a generated recording says "unsupported format").
"""

from __future__ import annotations

import json
import os
import tempfile

import numpy as np
import pytest
from click.testing import CliRunner

import fiveaxis_generator as g
from fiveaxis_check import compare, estimates, null_problems, problems, unknown_parameters
from mtbudget.cli import main
from mtbudget.errors import MtbudgetError
from mtbudget.recording import read_recording

SMALL_PLAN = {"x": (0.0, 100.0), "y": (0.0, 100.0), "z": (0.0, 100.0), "angles": {"A": (0.0, 90.0), "C": (0.0, 90.0)},
              "tools": ((0.0, 0.0, -100.0),)}


def _format3_unsupported() -> str | None:
    """The reader's message when it refuses format 3 as such, else None (then the tests run, and fail loudly if
    the reader refuses a generated recording for any other reason)."""
    with tempfile.TemporaryDirectory() as d:
        g.make_recording(d, "CAFXYZ", seed=0, plan=SMALL_PLAN)
        try:
            read_recording(d)
        except MtbudgetError as exc:
            if "unsupported format" in str(exc):
                return str(exc)
    return None


_WHY = _format3_unsupported()
pytestmark = pytest.mark.skipif(_WHY is not None, reason=f"mtbudget does not read format 3 yet: {_WHY}")

#: the four recordings of the issue's "Done when" (seeds chosen once, before any run against mtbudget)
CASES = {
    "CAFXYZ": {"kind": "CAFXYZ", "linear_errors": False, "null": False, "seed": 2601},
    "CAFXYZ+linear": {"kind": "CAFXYZ", "linear_errors": True, "null": False, "seed": 2602},
    "CAFXYZ-null": {"kind": "CAFXYZ", "linear_errors": True, "null": True, "seed": 2603},
    "FXYZCB": {"kind": "FXYZCB", "linear_errors": False, "null": False, "seed": 2604},
}
CHI2_PER_DOF = (0.8, 1.25)


# ------------------------------------------------------------------------------------------- the comparison
def identify(folder) -> dict:
    res = CliRunner().invoke(main, ["identify", str(folder), "--json"])
    assert res.exit_code == 0, f"identify {folder} exited {res.exit_code}: {res.output[-2000:]}"
    return json.loads(res.stdout)


# ------------------------------------------------------------------------------------------- the cases
_RESULTS: dict = {}


@pytest.fixture(scope="module", params=list(CASES))
def case(request, tmp_path_factory):
    name = request.param
    if name not in _RESULTS:
        folder = tmp_path_factory.mktemp(name.replace("+", "_"))
        spec = CASES[name]
        truth = g.make_recording(folder, spec["kind"], linear_errors=spec["linear_errors"], null=spec["null"],
                                 seed=spec["seed"])
        _RESULTS[name] = (truth, identify(folder))
    return name, *_RESULTS[name]


def test_chi2_per_dof_is_near_one(case):
    name, truth, result = case
    assert result["converged"], name
    assert CHI2_PER_DOF[0] <= result["chi2_per_dof"] <= CHI2_PER_DOF[1], (name, result["chi2_per_dof"])


def test_every_rotary_parameter_is_within_3u_of_the_truth_or_named(case):
    name, truth, result = case
    checked = g.all_rotary_names(truth["kind"])
    bad = problems(result, truth, checked)
    assert not bad, f"{name}:\n" + "\n".join(bad)


def test_not_identifiable_is_the_null_space_of_the_plan(case):
    name, truth, result = case
    unknown = unknown_parameters(result, truth["kind"])
    if unknown:
        pytest.skip(f"parameters the generator's model does not have: {unknown[:5]}")
    bad = null_problems(result, truth)
    assert not bad, f"{name}:\n" + "\n".join(bad)


def test_the_comparison_can_fail(case):
    """The check above is not vacuous: a truth off by 10 u on one identifiable combination fails it."""
    name, truth, result = case
    for pname, z, _ in compare(result, truth, g.all_rotary_names(truth["kind"])):
        if z is not None:
            break
    est, _ = estimates(result)
    shifted = {**truth, "parameters": {**truth["parameters"],
                                       pname: truth["parameters"].get(pname, 0.0) + 10 * est[pname][1] + 1e-3}}
    assert problems(result, shifted, [pname])


# ------------------------------------------------------------------------------------------- recordings not seen
#: MTBUDGET_FIVEAXIS_SEED=<int> draws another campaign (the seed is printed on failure)
CAMPAIGN_SEED = int(os.environ.get("MTBUDGET_FIVEAXIS_SEED", "926"))


@pytest.mark.slow
def test_recordings_not_seen(tmp_path):
    """Eight recordings (both kinds, with and without linear-axis errors, one null of each kind), random machines
    and plans: chi2/dof in range for each; over all rotary checks none beyond 4 u and at most 2 beyond 3 u
    (expected 0.3 of about 80 for a correct identification); the null spaces as reported."""
    rng = np.random.default_rng(CAMPAIGN_SEED)
    zs, bad = [], []
    for i in range(8):
        kind = g.KINDS[i % 2]
        seed = int(rng.integers(1 << 31))
        over = g.random_overrides(np.random.default_rng(seed), kind)
        null, linear = i in (6, 7), i % 4 >= 2
        truth = g.make_recording(tmp_path / f"r{i}", kind, linear_errors=linear, null=null, seed=seed, **over)
        result = identify(tmp_path / f"r{i}")
        where = f"campaign {CAMPAIGN_SEED}, recording {i} ({kind}, seed {seed}, linear {linear}, null {null})"
        if not CHI2_PER_DOF[0] <= result["chi2_per_dof"] <= CHI2_PER_DOF[1]:
            bad.append(f"{where}: chi2/dof {result['chi2_per_dof']:.3f}")
        for name, z, text in compare(result, truth, g.all_rotary_names(kind)):
            if z is None and text != "named in not_identifiable":
                bad.append(f"{where}: {name} {text}")
            elif z is not None:
                zs.append(z)
                if abs(z) > 3:
                    bad.append(f"{where}: {name} z = {z:+.2f}; {text}")
        bad += [f"{where}: {b}" for b in null_problems(result, truth)]
    zs = np.abs(np.array(zs))
    hard = [b for b in bad if "z = " not in b or abs(float(b.split("z = ")[1].split(";")[0])) > 4]
    assert not hard and (zs > 3).sum() <= 2, "\n".join(bad)


@pytest.mark.slow
@pytest.mark.parametrize("kind", g.KINDS)
def test_with_linear_errors_every_identifiable_combination_is_within_4u(tmp_path, kind):
    """Beyond the issue: the linear-axis terms and squareness too (through their identifiable combinations)."""
    truth = g.make_recording(tmp_path, kind, linear_errors=True, seed=2611)
    result = identify(tmp_path)
    est, _ = estimates(result)
    checked = sorted(n for n in est if g.known_parameter(n, kind))
    bad = problems(result, truth, checked, k=4.0)
    assert not bad, "\n".join(bad)


@pytest.mark.slow
def test_a_reversed_direction_keeps_the_iso_parameters_machine_frame(tmp_path):
    """direction = "-x" for A and "-z" for C: the ISO parameters stay the machine-frame components of the axis's
    error rotation and offset (generator docstring); the identification must agree."""
    truth = g.make_recording(tmp_path, "CAFXYZ", seed=2612, directions={"A": "-x", "C": "-z"})
    result = identify(tmp_path)
    assert CHI2_PER_DOF[0] <= result["chi2_per_dof"] <= CHI2_PER_DOF[1]
    bad = problems(result, truth, g.all_rotary_names("CAFXYZ"))
    assert not bad, "\n".join(bad)


@pytest.mark.slow
def test_a_weakly_identifiable_combination_keeps_an_honest_uncertainty(tmp_path):
    """A head-head machine whose B pivot is 3 mm off the C axis (make_five_axis.py --random --seed 7, recording
    13): ECOC - ECOB is then identifiable only through that offset (0.3 nm per urad), its standard uncertainty is
    about 1.3 mrad (the generator's exact-rotation Jacobian, and mtbudget's own with exact=True, at the estimate).
    The small-angle matrices I + [e]x stretch lengths by |e|^2 / 2, which at estimates of some hundred urad adds
    curvature of the same order as the true signal: on 2026-11-25 identify stated 240 urad and landed 4.7 of
    those from the truth, although the truth's chi-square is within the expected 61 of the minimum."""
    seed = 1753345572
    truth = g.make_recording(tmp_path, "FXYZCB", seed=seed,
                             **g.random_overrides(np.random.default_rng(seed + 1), "FXYZCB"))
    result = identify(tmp_path)
    bad = problems(result, truth, g.all_rotary_names("FXYZCB"))
    assert not bad, "\n".join(bad)


@pytest.mark.slow
@pytest.mark.parametrize("random_machine", [False, True])
def test_a_table_head_machine(tmp_path, random_machine):
    """CFXYZB (C table on the bed with the tracker, B head on Z), beyond the issue's two set-ups: the same
    criteria, the null space computed for the plan."""
    seed = 2621 + random_machine
    over = g.random_overrides(np.random.default_rng(seed + 1), "CFXYZB") if random_machine else {}
    truth = g.make_recording(tmp_path, "CFXYZB", linear_errors=True, seed=seed, **over)
    result = identify(tmp_path)
    assert CHI2_PER_DOF[0] <= result["chi2_per_dof"] <= CHI2_PER_DOF[1]
    bad = problems(result, truth, g.all_rotary_names("CFXYZB")) + null_problems(result, truth)
    assert not bad, "\n".join(bad)
