"""Budget reports: Markdown and self-contained HTML, rendered in a real browser."""

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.runner import execute

SMALL = Path(__file__).parent / "data" / "small.toml"


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    execute(SMALL, trials=64, log_path=tmp / "run.mcap", progress=False, attribution_trials=32, block=16)
    res = CliRunner().invoke(main, ["report", str(tmp / "run.mcap"), "--out", str(tmp / "rep"), "--tolerance", "25 um"])
    assert res.exit_code == 0, res.output
    return tmp / "rep"


def test_markdown_has_every_section(report_dir):
    md = (report_dir / "report.md").read_text()
    for part in ("## Measurand", "## Conditions", "## Result", "## Every point", "## Budget of the per-point measurand",
                 "GUF vs MCM (JCGM 101 clause 8), per point and axis", "## Decision (ISO 14253-1)", "Rule: ISO 14253-1",
                 "## Volume summaries and the paper's figures", "### Budget of compensation_rms", "tracker_noise",
                 "measurement system", "sha256", "k = 1", "95 % coverage interval"):
        assert part in md, part
    assert md.count("\n| ") > 27 + 10  # one table row per mesh point (27 in the small study) and the summaries
    for fig in ("uncertainty_map.png", "distributions.png", "contributions.png", "convergence.png"):
        assert (report_dir / fig).stat().st_size > 5000, fig


def test_html_is_self_contained(report_dir):
    page = (report_dir / "report.html").read_text()
    assert "http://" not in page and "https://" not in page
    assert page.count("data:image/png;base64,") == 4
    assert page.count('<table class="budget">') >= 3


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def test_html_renders_in_headless_chromium(report_dir, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium on this machine: install Debian's 'chromium' (.ci/run does) to run the browser check")
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
           "--virtual-time-budget=5000", "--dump-dom", (report_dir / "report.html").as_uri()]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    dom = out.stdout
    images = re.search(r'data-images="(\d+)/(\d+)"', dom)
    assert images, "the page's load handler did not run"
    assert images.group(1) == images.group(2) == "4"  # every figure decoded and shown
    assert int(re.search(r'data-tables="(\d+)"', dom).group(1)) >= 3
    assert "tracker_noise" in dom
    assert "Uncaught" not in out.stderr
