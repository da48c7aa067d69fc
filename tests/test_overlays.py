"""Configuration overlays (issue 29): `extends = FILE | "default"` and `--set key=value`, so that one source can be
changed in a three-line file; the result equals the same change made by hand in a full copy."""

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from mtbudget.cli import main
from mtbudget.config import default_config_path, load_config
from mtbudget.errors import ConfigError
from mtbudget.runlog import read_runlog
from mtbudget.runner import execute, replay, run

SMALL = Path(__file__).parent / "data" / "small.toml"


def hand_edited(tmp_path, old: str, new: str, base=SMALL) -> Path:
    text = base.read_text()
    assert old in text
    p = tmp_path / "full.toml"
    p.write_text(text.replace(old, new, 1))
    return p


def test_a_three_line_overlay_equals_the_same_change_in_a_full_copy(tmp_path):
    over = tmp_path / "over.toml"
    over.write_text(f'extends = "{SMALL}"\n[sources.tracker_noise]\nangular_sd = "3 urad"\n')
    full = hand_edited(tmp_path, 'angular_sd = "0 urad"', 'angular_sd = "3 urad"')
    a, b = load_config(over), load_config(full)
    assert a.source == b.source  # the same table, key by key
    ra, rb = run(a, trials=32, block=16, attribution_trials=0), run(b, trials=32, block=16, attribution_trials=0)
    assert ra.summary("compensation_rms") == rb.summary("compensation_rms")


def test_extends_default_and_set_reach_any_key(tmp_path):
    over = tmp_path / "over.toml"
    over.write_text('extends = "default"\n[machine_tool]\nrepeatability = "2.5 um"\n')
    cfg = load_config(over, ["tracker.angular=30 urad", "plan.runs=3", 'sources.tracker_noise.angular_sd="1 urad"'])
    base = load_config(default_config_path())
    assert cfg.repeatability == pytest.approx(2.5e-3) and base.repeatability != cfg.repeatability
    assert cfg.angular == pytest.approx(30e-6) and cfg.runs == 3
    assert cfg.source["sources"]["tracker_noise"]["angular_sd"] == "1 urad"
    assert {k: v for k, v in cfg.source.items() if k not in ("machine_tool", "tracker", "plan", "sources")} == \
        {k: v for k, v in base.source.items() if k not in ("machine_tool", "tracker", "plan", "sources")}


@pytest.mark.parametrize("text, sets, message", [
    ('extends = "nothere.toml"\n', [], "extends: no such configuration file"),
    ('extends = 5\n', [], "extends: expected a file name"),
    ('extends = "self.toml"\n', [], "extends itself"),
    ('extends = "default"\n', ["tracker.angulr=5 urad"], "tracker.angulr: unknown key; did you mean 'angular'.*given with --set"),
    ('extends = "default"\n', ["tracker.angular"], "expected KEY=VALUE"),
    ('extends = "default"\n', ["tracker.angular=5 ppm"], "tracker.angular: '5 ppm' is a ratio, not an angle"),
    ('extends = "default"\n', ["sensors.9.noise=0.1 K"], "sensors has 4 entries; '9' is not one"),
])
def test_overlay_mistakes_are_one_line(tmp_path, text, sets, message):
    p = tmp_path / "self.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(p, sets)
    assert "\n" not in str(info.value)


def test_run_set_is_logged_resolved_and_replays(tmp_path):
    log = tmp_path / "r.mcap"
    res = CliRunner().invoke(main, ["run", str(SMALL), "--trials", "16", "--block", "8", "--attribution-trials", "0",
                                    "--quiet", "--log", str(log), "--set", "sources.tracker_noise.angular_sd=3 urad"])
    assert res.exit_code == 0, res.output
    got = read_runlog(log)
    assert got.header["spec"]["config"]["sources"]["tracker_noise"]["angular_sd"] == "3 urad"
    assert "--set sources.tracker_noise.angular_sd=3 urad" in got.config_text and '"angular_sd": "3 urad"' in got.config_text
    full = hand_edited(tmp_path, 'angular_sd = "0 urad"', 'angular_sd = "3 urad"')
    assert replay(log).summary("compensation_rms") == run(load_config(full), trials=16, block=8,
                                                            attribution_trials=0).summary("compensation_rms")
