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


# --------------------------------------------------------------------------- screenshots (issue 18)
def _browser(exe, tmp_path, *args):
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars",
           "--force-device-scale-factor=1", f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=5000",
           *args]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def _screenshot(page: Path, png: Path, tmp_path, width=1280, height=9000):
    """Render ``page`` in headless Chromium to ``png``; the pixels as an (H, W, 3) array of 0-255 values, and the
    positions of the page's figures (x, y, w, h) when the page records them (the diagnosis report does)."""
    from matplotlib.image import imread

    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium on this machine: install Debian's 'chromium' (.ci/run does) to take the screenshots")
    size = f"--window-size={width},{height}"
    _browser(exe, tmp_path, size, f"--screenshot={png}", page.as_uri())
    dom = _browser(exe, tmp_path, size, "--dump-dom", page.as_uri()).stdout
    m = re.search(r'data-figures="([^"]*)"', dom)
    rects = [tuple(int(v) for v in r.split(",")) for r in m.group(1).split(";") if r] if m else []
    img = imread(png)[:, :, :3]
    return (img * 255).round(), rects


def _not_blank(px):
    non_white = (px < 245).any(axis=2)
    assert non_white.mean() > 0.02, f"only {non_white.mean():.1%} of the screenshot is not white"
    # the figures' colours (matplotlib's blue and orange markers, the colour maps): saturated pixels
    sat = px.max(axis=2) - px.min(axis=2)
    assert (sat > 100).sum() > 2000, "no coloured pixels: the figures did not render"
    return non_white


def test_run_report_screenshot(report_dir, tmp_path):
    px, _ = _screenshot(report_dir / "report.html", tmp_path / "report.png", tmp_path)
    non_white = _not_blank(px)
    # the four figures are at the end of the page: the last third is mostly plots, not white
    rows = non_white.mean(axis=1)
    assert (rows > 0.05).sum() > 1000, "fewer than 1000 rows of the page carry content: figures missing"


def test_diagnosis_report_screenshot(tmp_path):
    from mtbudget.config import example_recording
    from mtbudget.diagnose import diagnose
    from mtbudget.recording import read_recording
    from mtbudget.report_diagnosis import diagnosis_report

    rec = read_recording(example_recording("thermal_x"))
    diagnosis_report(diagnose(rec), rec, tmp_path / "rep")
    px, rects = _screenshot(tmp_path / "rep" / "diagnosis.html", tmp_path / "diagnosis.png", tmp_path, height=4000)
    _not_blank(px)
    assert len(rects) == 1, rects
    for x, y, w, h in rects:
        assert w > 500 and h > 300, (x, y, w, h)  # the figure is shown at a readable size
        assert y + h <= px.shape[0], "the figure lies below the screenshot: raise its height"
        region = px[y:y + h, x:x + w]
        assert region.std() > 20, "the figure's region is uniform: the image did not render"
        sat = region.max(axis=2) - region.min(axis=2)
        assert (sat > 100).mean() > 0.002, "no markers in the figure's region"
