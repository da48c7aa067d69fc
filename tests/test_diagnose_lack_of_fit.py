"""The lack-of-fit F test of the diagnosis' fit gate when the model is not nested in the groups of repeated points.

A five-axis plan groups its points by linear position and tool (``_point_groups``): a group holds the points at
every commanded angle, which the rotary axes' location and zero errors, and a tracker turning with the table, move
differently, so the identification's columns are not in the span of one free position per group.  The gate took
the complement of (groups + candidates) alone: its "pure error" then held part of the model's space and its lack of
fit more chi-square than its dof (rank X - rank A counted, rank [X A] - rank A free; on the example's 320-point plan
47 counted, 73 free), and nulls were NOT EXPLAINED in 40 % of cases.  Checked here against numbers the diagnosis
does not make: the F distribution's own level on synthetic Gaussian residuals with numpy's ranks, and five-axis null
recordings drawn by the simulator that the old gate rejected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from mtbudget.config import load_config
from mtbudget.diagnose import _Fit, _gate, _Linear, diagnose
from mtbudget.recording import read_recording, write_recording
from mtbudget.report_diagnosis import diagnosis_text
from mtbudget.scenario import build_scenario
from mtbudget.simulate import simulate_recording

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "five_axis_cafxyz.toml"
SMALL = ("mesh.step_x=400 mm", "mesh.step_y=400 mm", "mesh.step_z=300 mm")
NULL = ("sources.rotary_reversal.B_max=0 urad", "sources.rotary_encoder.E_max=0 urad")


def _synthetic(rng, M=120, G=20):
    """M points in G groups (3 rows each), a model A of 8 columns of which 4 vary within a group (not nested) and
    a group design Z of one free 3-vector per group."""
    groups = np.arange(M) % G
    Z = np.zeros((3 * M, 3 * G))
    for c in range(3):
        Z[3 * np.arange(M) + c, 3 * groups + c] = 1.0
    nested = Z @ rng.standard_normal((3 * G, 4))
    A = np.concatenate([nested, rng.standard_normal((3 * M, 4))], axis=1)
    return A, Z


def test_lack_of_fit_dof_are_the_ranks_numpy_gives():
    rng = np.random.default_rng(3)
    A, Z = _synthetic(rng)
    lin = _Linear(A, rng.standard_normal(len(A)))
    lin.w = lin.project(lin.w[:, None])[:, 0]
    g = _gate(lin, _Fit(float(lin.w @ lin.w), np.zeros(0), np.zeros((0, 0))), 0, {"used": "stated"}, Z, [], 0.01)
    rAZ, rA = np.linalg.matrix_rank(np.concatenate([Z, A], axis=1)), np.linalg.matrix_rank(A)
    assert g["lack_of_fit"]["dof"] == [rAZ - rA, len(A) - rAZ]
    # the old count (rank Z - rank A) is short by the model's columns outside the groups
    assert rAZ - rA > np.linalg.matrix_rank(Z) - rA


def test_a_null_is_rejected_at_the_tests_level_when_the_model_is_not_nested():
    """Residuals of the model A from standard normal errors: the gate's p-values are uniform (Kolmogorov-Smirnov)
    and its rejections at 0.05 within the binomial's 99.9 % bound; the old gate gave F about 1 + (4 model columns
    outside the groups) / lof dof and rejected far more often."""
    rng = np.random.default_rng(11)
    A, Z = _synthetic(rng)
    lin = _Linear(A, np.zeros(len(A)))
    n = 300
    E = rng.standard_normal((len(A), n))
    W = E - lin.Q0 @ (lin.Q0.T @ E)
    ps = []
    for j in range(n):
        lin.w = W[:, j]
        g = _gate(lin, _Fit(float(lin.w @ lin.w), np.zeros(0), np.zeros((0, 0))), 0, {"used": "stated"}, Z, [], 0.01)
        ps.append(g["p_value"])
    ps = np.array(ps)
    assert stats.kstest(ps, "uniform").pvalue > 1e-3
    assert (ps < 0.05).sum() <= stats.binom.ppf(0.999, n, 0.05)


def _null(tmp_path, seed):
    sc = build_scenario(load_config(EXAMPLE, list(SMALL + NULL)))
    rec, truth = simulate_recording(sc, seed, 0)
    write_recording(rec, tmp_path / "r", truth=truth)
    return read_recording(tmp_path / "r")


# seeds 80012 and 80013 of benchmarks/calibrate_diagnose.py --only five_axis: NOT EXPLAINED before (lack of fit
# F = 1.62 and 1.67 on (47, 884) dof, p = 0.004 and 0.002)
@pytest.mark.parametrize("seed", [80012, 80013])
def test_a_five_axis_null_is_explained(tmp_path, seed):
    d = diagnose(_null(tmp_path, seed), data_driven=False)
    assert d.unexplained is None, diagnosis_text(d)
    assert not d.findings, diagnosis_text(d)


@pytest.mark.slow
def test_five_axis_nulls_are_rejected_about_at_the_level(tmp_path):
    """20 nulls (seeds 80000..80019; before: 6 NOT EXPLAINED): at most 2 (binomial 20, 0.01: P(>= 3) = 0.001)."""
    bad = 0
    for seed in range(80000, 80020):
        bad += diagnose(_null(tmp_path / str(seed), seed), data_driven=False).unexplained is not None
    assert bad <= 2
