"""The a posteriori statement a laboratory signs (mtbudget posterior): the statement in brief, U = k u, the ISO 14253-1
decision and the DCC, by the code of the a priori statement of a run (report.statement_in_brief, budget.conformance,
report_dcc.statement_tree), and recording.toml's [report] table.

Independent numbers: k from scipy's normal quantile, U and the half-widths recomputed here from the per-point u and
intervals, the decision against an interval/tolerance case and trials made by hand with their order statistics counted
here (JCGM 101 7.7.1), the DCC's numbers against posterior.json read back with ElementTree.
"""

import json
import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from click.testing import CliRunner
from test_report_dcc import NS, follows_the_schema_structure

from mtbudget.budget import conformance
from mtbudget.cli import main
from mtbudget.config import example_recording
from mtbudget.errors import RecordingError
from mtbudget.posterior import Posterior, posterior_result
from mtbudget.recording import read_recording, write_recording
from mtbudget.report import posterior_headline

REPORT = '''
[report]
laboratory = "Metrology Lab North"
machine = "Hermle C42, serial 4711"
customer = "ACME Parts"
operator = "J. Doe"
date = "2026-11-20"
traceability = "The tracker is calibrated by an accredited laboratory (DAkkS D-K-12345), traceable to the SI metre."
certificate = "LAB-2026-041"
country = "DE"
location = "customer"

[report.instrument]
model = "Leica AT960"
serial = "750123"
calibration = "DAkkS 2026-03, certificate 17"
'''


def with_report(tmp_path, text=REPORT, name="null"):
    folder = tmp_path / name
    shutil.copytree(example_recording(name), folder)
    with open(folder / "recording.toml", "a", encoding="utf-8") as fh:
        fh.write(text)
    return folder


@pytest.fixture(scope="module")
def stated(tmp_path_factory):
    """The null recording with a [report] table, its statement and DCC written by the command (20 um tolerance)."""
    tmp = tmp_path_factory.mktemp("post")
    folder = with_report(tmp)
    out = tmp / "out"
    r = CliRunner().invoke(main, ["posterior", str(folder), "--trials", "256", "--tolerance", "20 um", "--out", str(out),
                                  "--quiet"])
    assert r.exit_code == 0, r.output
    return folder, out, json.loads((out / "posterior.json").read_text())


def test_U_is_k_u_with_k_from_the_normal_quantile_of_the_coverage(stated):
    from scipy.stats import norm

    folder, out, p = stated
    h = p["statement"]
    u = np.array([q["u"]["value"] for q in p["points"]])
    half = np.array([[(hi - lo) / 2 for lo, hi in zip(q["interval"]["low"], q["interval"]["high"])] for q in p["points"]])
    assert 2 * norm.cdf(2.0) - 1 == pytest.approx(0.9545, abs=1e-4)  # k = 2: "about 95 %" for a normal
    assert h["k"] == 2.0 and h["kind"] == "a posteriori"
    tol = 0.5 * 10 ** -h["decimals"]
    assert h["U_max"] == pytest.approx(2.0 * u.max(), abs=tol)
    assert h["U_rms"] == pytest.approx(2.0 * np.sqrt((u**2).mean()), abs=tol)
    assert h["half_width_max"] == pytest.approx(half.max(), abs=tol)
    md = (out / "posterior.md").read_text()
    brief = md[md.index("## Statement in brief"):md.index("## Kind of statement")]
    for v in ("a posteriori", p["statement_kind"]["points_csv_sha256"], f"U = {h['U_max']:.{h['decimals']}f} µm",
              "k = 2", "Metrology Lab North", "Leica AT960", "750123", "ACME Parts", "J. Doe", "2026-11-20",
              "DAkkS D-K-12345", "LAB-2026-041", "Hermle C42", "ISO 14253-1", "conforms"):
        assert v in brief, v
    assert md.index("## Statement in brief") < md.index("## Kind of statement")  # the statement opens with it
    # at 99 %: k is the normal quantile of 0.995 to two decimals, and U states that coverage, not 95 %
    post = posterior_result(folder, trials=64, seed=2, coverage=0.99)
    h99 = posterior_headline(post)
    k = round(float(norm.ppf(0.995)), 2)
    u99 = np.array([q["u"]["value"] for q in post.points()])
    assert h99["k"] == k and h99["U_max"] == pytest.approx(k * u99.max(), abs=0.5 * 10 ** -h99["decimals"])
    assert "99 %" in h99["U_text"] and "95" not in h99["U_text"]
    assert "none: no tolerance" in h99["decision"] and "mtbudget posterior --tolerance" in h99["decision"]


def _hand_made():
    """Two points; per-point intervals made by hand; 100 trials whose largest |component| is 0.25, 0.5, ..., 25 um."""
    iv = [([-5.0, 15.0, -30.0], [5.0, 25.0, -22.0]), ([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])]
    points = [{"point": i, "nominal": {"value": [0.0, 0.0, 0.0], "unit": "mm"},
               "mean": {"value": [(a + b) / 2 for a, b in zip(lo, hi)], "unit": "um"},
               "u": {"value": [1.0, 1.0, 1.0], "unit": "um"},
               "interval": {"low": lo, "high": hi, "unit": "um", "coverage": 0.95}} for i, (lo, hi) in enumerate(iv)]
    E = np.zeros((100, 6))
    E[:, 0] = 0.25 * np.arange(1, 101)
    return Posterior({"coverage": 0.95, "trials": 100, "points": points}, E)


def test_the_decision_applies_the_runs_rule_to_the_posteriors_own_intervals_and_trials():
    post = _hand_made()
    pp = conformance(post, 20.0)["per_point"]
    # counted by hand: [-5, 5] inside +-20; [15, 25] across +20; [-30, -22] outside; the three [-1, 1] inside
    assert (pp["conforming"], pp["nonconforming"], pp["undecided"], pp["of"]) == (4, 1, 1, 6)
    assert pp["verdict"] == "does not conform" and pp["U_max"] == pytest.approx(5.0)
    # the whole machine: 95 % quantile of the largest |component| = the 95th smallest of 100 (JCGM 101 7.7.1) = 23.75,
    # the 5 % quantile the 5th = 1.25; 80 of the 100 trials within 20 um
    m = conformance(post, 20.0)
    assert m["scope"] == "machine" and m["largest_abs_component"]["quantile"] == 23.75
    assert m["largest_abs_component"]["lower_quantile"] == 1.25 and m["verdict"] == "undecided"
    assert m["largest_abs_component"]["probability_within"] == pytest.approx(0.80)
    assert conformance(post, 24.0)["verdict"] == "conforms" and conformance(post, 1.0)["verdict"] == "does not conform"
    assert "ISO 14253-1" in m["rule"] and "recorded verification" in m["refers_to"]
    # characteristic max: the symmetric 95 % interval of 100 values is [y(3), y(98)] (1-based) = [0.75, 24.5]
    mx = conformance(post, 24.0, "max")
    assert mx["interval"] == [0.75, 24.5] and mx["verdict"] == "undecided"
    assert conformance(post, 25.0, "max")["verdict"] == "conforms"
    assert conformance(post, 0.5, "max")["verdict"] == "does not conform"


def test_the_dcc_holds_the_posteriors_numbers_in_the_schemas_order(stated):
    _, out, p = stated
    root = ET.parse(out / "certificate.xml").getroot()
    follows_the_schema_structure(root)
    h = p["statement"]
    nd = h["decimals"]
    assert root.find(".//dcc:uniqueIdentifier", NS).text == "LAB-2026-041"
    assert root.find(".//dcc:performanceLocation", NS).text == "customer"
    assert root.find(".//dcc:beginPerformanceDate", NS).text == "2026-11-20"
    said = {s.find("dcc:name/dcc:content", NS).text: s.find("dcc:declaration/dcc:content", NS).text
            for s in root.iterfind(".//dcc:statement", NS)}
    assert said["kind of statement"].startswith("a posteriori") and p["statement_kind"]["points_csv_sha256"] in \
        said["kind of statement"]
    assert said["decision"] == p["conformance"]["statement"] and said["decision rule"] == p["conformance"]["rule"]
    assert "warning" not in said  # null fits its stated noise
    reals = list(root.iterfind(".//si:real", NS))
    per = [r for r in reals if r.find("si:label", NS).text.startswith("e_")]
    assert len(per) == 3 * len(p["points"])
    for n, r in enumerate(per):
        q, j = p["points"][n // 3], n % 3
        ci = r.find("si:coverageInterval", NS)
        assert float(r.find("si:value", NS).text) == pytest.approx(q["mean"]["value"][j], abs=0.51 * 10 ** -nd)
        assert float(ci.find("si:standardUnc", NS).text) == pytest.approx(q["u"]["value"][j], abs=0.51 * 10 ** -nd)
        assert float(ci.find("si:intervalMin", NS).text) == pytest.approx(q["interval"]["low"][j], abs=0.51 * 10 ** -nd)
        assert float(ci.find("si:intervalMax", NS).text) == pytest.approx(q["interval"]["high"][j], abs=0.51 * 10 ** -nd)
        assert float(ci.find("si:coverageProbability", NS).text) == p["coverage"]
    U = [float(r.find("si:value", NS).text) for r in reals if r.find("si:label", NS).text.startswith("U_max")]
    u = np.array([q["u"]["value"] for q in p["points"]])
    assert U == pytest.approx(list(2.0 * u.max(axis=0)), abs=0.51 * 10 ** -nd) and max(U) == h["U_max"]


def test_a_failed_fit_is_in_the_statement_in_brief_and_the_dcc_and_no_verdict_is_supported(tmp_path):
    """thermal_x's fit fails the chi-square test: the warning heads the brief and the DCC, and with a tolerance the
    decision is undecided (the figures' verdict kept beside it), since the statement leaves out the physics the
    recording shows.  Without [report] date no certificate is written (its performance date is the measurement's);
    with one, it is."""
    rec = tmp_path / "thermal_x"
    shutil.copytree(example_recording("thermal_x"), rec)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["posterior", str(rec), "--trials", "8", "--out", str(out), "--tolerance", "200 um"])
    assert r.exit_code == 0, r.output
    assert not (out / "certificate.xml").exists() and "certificate.xml is not written" in r.stderr
    md = (out / "posterior.md").read_text()
    brief = md[md.index("## Statement in brief"):md.index("## Kind of statement")]
    assert "| WARNING | **the identified model does not fit thermal\\_x" in brief and "diagnose" in brief
    assert "not stated ([report] laboratory)" in brief  # thermal_x's recording.toml has no [report]
    assert "not stated (the date of the measurement" in brief
    decision = next(ln for ln in brief.splitlines() if ln.startswith("| decision |"))
    assert "Undecided: no verdict is supported, because the identified model does not fit" in decision
    r = CliRunner().invoke(main, ["posterior", str(rec), "--trials", "8", "--tolerance", "200 um", "--json"])
    conf = json.loads(r.stdout)["conformance"]
    assert conf["verdict"] == "undecided" and conf["supported"] is False and conf["verdict_of_the_figures"] == "conforms"
    with open(rec / "recording.toml", "a") as fh:
        fh.write('\n[report]\ndate = "2026-11-20"\n')
    r = CliRunner().invoke(main, ["posterior", str(rec), "--trials", "8", "--out", str(out)])
    assert r.exit_code == 0, r.output
    root = ET.parse(out / "certificate.xml").getroot()
    assert root.find(".//dcc:beginPerformanceDate", NS).text == "2026-11-20"
    follows_the_schema_structure(root)
    said = {s.find("dcc:name/dcc:content", NS).text: s.find("dcc:declaration/dcc:content", NS).text
            for s in root.iterfind(".//dcc:statement", NS)}
    assert said["warning"].startswith("the identified model does not fit thermal_x")
    assert root.find(".//dcc:calibrationLaboratory/dcc:contact/dcc:name/dcc:content", NS).text == "not stated"


@pytest.mark.parametrize("text, key, msg", [
    ('\n[report]\nlaboratry = "x"\n', "report.laboratry", "did you mean 'laboratory'"),
    ('\n[report]\ndate = "20.11.2026"\n', "report.date", "expected a date YYYY-MM-DD"),
    ('\n[report]\ndate = "20261120"\n', "report.date", "expected a date YYYY-MM-DD"),
    ('\n[report]\ndate = "2026-W48-3"\n', "report.date", "expected a date YYYY-MM-DD"),
    ('\n[report]\ncountry = "Germany"\n', "report.country", "ISO 3166-1"),
    ('\n[report]\nlocation = "shop"\n', "report.location", "performanceLocation"),
    ('\n[report]\ncustomer = 5\n', "report.customer", "expected a non-empty string"),
    ('\n[report.instrument]\nmodle = "AT960"\n', "report.instrument.modle", "did you mean 'model'"),
    ('\n[report.instrument]\nserial = ""\n', "report.instrument.serial", "expected a non-empty string"),
    ('\nreport = "Lab"\n', "report", "expected a table [report]"),
])
def test_a_bad_report_table_in_recording_toml_is_one_line_naming_file_and_key(tmp_path, text, key, msg):
    if text.startswith("\nreport ="):  # a top-level key: before any table
        folder = tmp_path / "null"
        shutil.copytree(example_recording("null"), folder)
        toml = folder / "recording.toml"
        toml.write_text(text.strip() + "\n" + toml.read_text())
    else:
        folder = with_report(tmp_path, text)
    with pytest.raises(RecordingError) as exc:
        read_recording(folder)
    assert exc.value.key == key and msg in str(exc.value) and "recording.toml" in str(exc.value)
    r = CliRunner().invoke(main, ["posterior", str(folder), "--trials", "4"])
    assert r.exit_code == 2 and len(r.stderr.strip().splitlines()) == 1 and key in r.stderr, r.output


def test_the_report_table_is_read_and_written_back(tmp_path):
    rec = read_recording(with_report(tmp_path))
    assert rec.report["laboratory"] == "Metrology Lab North" and rec.report["instrument"]["serial"] == "750123"
    again = read_recording(write_recording(rec, tmp_path / "again"))
    assert again.report == rec.report
    assert read_recording(example_recording("null")).report == {}


def test_a_statement_without_a_certificate_leaves_no_earlier_certificate_in_its_folder(tmp_path, stated):
    """The folder of a dated statement holds its certificate.xml; an undated recording's statement into the same
    folder writes none and must not leave the earlier one standing for it."""
    _, out, _ = stated
    folder = tmp_path / "again"
    shutil.copytree(out, folder)
    assert (folder / "certificate.xml").exists()
    r = CliRunner().invoke(main, ["posterior", str(example_recording("null")), "--trials", "16", "--out", str(folder),
                                  "--quiet"])
    assert r.exit_code == 0, r.output
    assert "certificate.xml is not written" in r.output and not (folder / "certificate.xml").exists()
