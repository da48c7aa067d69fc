"""The decision for the whole machine: a statement at the stated coverage about every point-axis at once."""

import numpy as np
import pytest

from mtbudget.budget import conformance
from mtbudget.outputs import BlockResult
from mtbudget.runner import run


@pytest.fixture(scope="module")
def paper():
    # the paper's default configuration (tracker noise dominant), enough trials for the 95 % quantile of the largest
    # component to be known to about a micrometre
    return run(None, trials=1024, seed=11, attribution_trials=0)


def test_paper_default_35_um_is_not_a_machine_conformance_but_60_um_is(paper):
    Y = np.concatenate(paper.acc.vector_samples["components"])  # (M, 225): every trial's components, um
    m = np.sort(np.abs(Y).max(axis=1))  # the largest |component| over the mesh, per trial, computed here
    q95 = m[int(0.95 * m.size + 0.5) - 1]
    c35 = conformance(paper, 35.0)
    assert c35["scope"] == "machine" and c35["verdict"] != "conforms"
    assert c35["per_point"]["scope"] == "per point" and c35["per_point"]["verdict"] == "conforms"  # what it said before
    assert c35["largest_abs_component"]["quantile"] == pytest.approx(q95, abs=1e-9)
    assert c35["largest_abs_component"]["probability_within"] == pytest.approx(np.mean(m <= 35.0))
    assert 0.6 < c35["largest_abs_component"]["probability_within"] < 0.85
    assert "Whole machine" in c35["statement"] and "Per point" in c35["statement"]
    c60 = conformance(paper, 60.0)
    assert c60["verdict"] == "conforms" and c60["simultaneous_band"]["verdict"] == "conforms"
    assert conformance(paper, 5.0)["verdict"] == "does not conform"


def test_simultaneous_band_covers_every_point_axis_at_once(paper):
    Y = np.concatenate(paper.acc.vector_samples["components"])
    band = conformance(paper, 60.0)["simultaneous_band"]
    y, u = Y.mean(axis=0), Y.std(axis=0, ddof=1)
    inside = np.all(np.abs(Y - y) <= np.asarray(band["half_width"]) * (1 + 1e-12), axis=1)
    assert inside.mean() == pytest.approx(0.95, abs=1.5 / Y.shape[0])
    # wider than any per-point 95 % interval: k well above 1.96 for 225 correlated components
    assert 2.5 < band["k"] < 4.0 and np.allclose(np.asarray(band["half_width"]) / u, band["k"])


def test_the_machine_figures_come_from_the_components():
    comp = np.array([[[1.0, -2.0, 0.5], [-3.0, 1.0, 0.0]], [[0.0, 0.1, -0.2], [0.3, 0.0, 4.0]]])  # (n, M0, 3)
    b = BlockResult(0, 2, {"compensation_rms": np.zeros(2)}, np.linalg.norm(comp, axis=2), np.zeros((2, 1)),
                    components=comp)
    assert b.scalars["largest_abs_component_x"].tolist() == [3.0, 0.3]
    assert b.scalars["largest_abs_component_y"].tolist() == [2.0, 0.1]
    assert b.scalars["largest_abs_component"].tolist() == [3.0, 4.0]
    assert b.truncated(1).scalars["largest_abs_component"].tolist() == [3.0]


def test_a_run_says_it_is_an_a_priori_evaluation_of_an_assumed_machine(paper, tmp_path):
    from mtbudget.report import budget_text, result_json, run_report

    k = result_json(paper)["statement_kind"]
    assert k["kind"] == "a priori" and "virtual" in k["name"]
    assert "seed 7" in k["assumed_machine"] and "15 um, 8 um, 4 um" in k["assumed_machine"]  # the paper's truth
    assert 0.97 < k["evidence"]["u_mcm_over_u_guf"]["median"] < 1.03
    assert budget_text(paper).startswith("Kind of statement: A PRIORI")
    run_report(paper, tmp_path, 60.0)
    md = (tmp_path / "report.md").read_text()
    assert md.startswith("# mtbudget a priori uncertainty evaluation") and "Assumed machine" in md
    assert "Scope of the verdict: the whole machine" in md


def test_blocks_of_an_older_log_and_new_blocks_merge_on_the_older_outputs():
    from mtbudget.outputs import accumulate_block
    from mtbudget.stats import Accumulator

    comp = np.ones((2, 2, 3))
    old = BlockResult(0, 2, {"compensation_rms": np.zeros(2)}, np.zeros((2, 2)), np.zeros((2, 1)))  # no components
    new = BlockResult(1, 2, {"compensation_rms": np.ones(2)}, np.zeros((2, 2)), np.zeros((2, 1)), components=comp)
    acc = Accumulator()
    accumulate_block(acc, old)
    accumulate_block(acc, new)
    assert acc.scalar_names == ("compensation_rms",) and acc.n == 4
