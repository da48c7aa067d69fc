"""The plugin contract: discovery, errors that name the culprit, switches, docs, an external package."""

import inspect
import re
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from mtbudget import hookspecs
from mtbudget.config import load_config
from mtbudget.engine import Engine
from mtbudget.errors import PluginError
from mtbudget.hookspecs import hookimpl
from mtbudget.plugins import PluginHost
from mtbudget.contracts import Group, Source
from mtbudget.units import Q_

ROOT = Path(__file__).resolve().parents[1]
SMALL = ROOT / "tests" / "data" / "small.toml"
BUILTIN = {"machine_tool", "measurement_system", "measurement_strategy", "optimisation_strategy", "physics"}


def plugin(name, register_fn):
    mod = types.ModuleType(name)
    mod.mtbudget_register_sources = hookimpl(register_fn)
    return mod


class Good(Source):
    name = "good"
    group = Group.MEASUREMENT_SYSTEM
    distribution = "normal"
    targets = ("tracker_offset",)
    parameters = {"u": Q_(1.0, "um")}

    def sample(self, n, rng, ctx):
        return {"tracker_offset": Q_(rng.normal(0, self.value("u", "mm"), (n, ctx.n_points, 3)), "mm")}


def test_builtins_arrive_through_entry_points():
    host = PluginHost()
    assert BUILTIN <= set(host.info)
    assert all(host.info[n].distribution == "mtbudget" for n in BUILTIN)
    names = {s.name for s in host.sources()}
    assert {"tracker_noise", "repeatability", "registration", "phase_sequence"} <= names
    assert all(s.dist_name == "mtbudget" and s.dist_version for s in host.sources())


def test_environment_switches(monkeypatch):
    monkeypatch.setenv("MTBUDGET_DISABLE_PLUGINS", "measurement_system")
    assert "tracker_noise" not in {s.name for s in PluginHost().sources()}
    monkeypatch.delenv("MTBUDGET_DISABLE_PLUGINS")
    monkeypatch.setenv("MTBUDGET_PLUGINS", "measurement_strategy")
    assert {s.name for s in PluginHost().sources()} == {"registration", "multilateration"}


def engine_with(*mods):
    cfg = load_config(SMALL)
    cfg.source = {k: v for k, v in cfg.source.items() if k != "sources"}
    return Engine(cfg, PluginHost(entry_points=False, plugins=mods), block=8)


def test_a_third_party_source_runs_and_is_stamped():
    eng = engine_with(plugin("mine", lambda register: register(Good())))
    assert [s.name for s in eng.sources] == ["good"] and eng.sources[0].plugin == "mine"
    b = eng.run_block(0)
    assert np.all(np.isfinite(b.scalars["compensation_rms"]))


class Bad(Good):
    def __init__(self, result=None, raises=False, name="bad"):
        super().__init__()
        self.result, self.raises, self.name = result, raises, name

    def sample(self, n, rng, ctx):
        if self.raises:
            raise RuntimeError("boom")
        return self.result(n, ctx)


CASES = {
    "raises": (dict(raises=True), "sample\\(\\) raised RuntimeError: boom"),
    "wrong shape": (dict(result=lambda n, c: {"tracker_offset": Q_(np.zeros((n, 3)), "mm")}), "has shape"),
    "wrong dimension": (dict(result=lambda n, c: {"tracker_offset": Q_(np.zeros((n, c.n_points, 3)), "s")}), "dimension"),
    "NaN": (dict(result=lambda n, c: {"tracker_offset": Q_(np.full((n, c.n_points, 3), np.nan), "mm")}), "NaN"),
    "undeclared key": (dict(result=lambda n, c: {"point_offset": Q_(np.zeros((n, c.n_points, 3)), "mm")}), "not among its declared"),
    "not a dict": (dict(result=lambda n, c: 3), "must return a dict"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_misbehaving_source_is_named(case):
    kw, pattern = CASES[case]
    with pytest.raises(PluginError) as info:
        engine_with(plugin("culprit", lambda register: register(Bad(**kw))))
    msg = str(info.value)
    assert "plugin 'culprit'" in msg and "source 'bad'" in msg and re.search(pattern, msg), msg


def test_hook_that_raises_and_duplicates_are_named():
    def explode(register):
        raise ValueError("cannot start")

    with pytest.raises(PluginError, match="plugin 'exploder'.*mtbudget_register_sources.*ValueError: cannot start"):
        PluginHost(entry_points=False, plugins=(plugin("exploder", explode),)).sources()
    host = PluginHost(entry_points=False, plugins=(plugin("first", lambda register: register(Good())),
                                                   plugin("second", lambda register: register(Good()))))
    with pytest.raises(PluginError, match="duplicate name 'good': already registered by plugin 'first'"):
        host.sources()
    with pytest.raises(PluginError, match="group"):
        bad = Good()
        bad.group = "kitchen"
        PluginHost(entry_points=False, plugins=(plugin("g", lambda register: register(bad)),)).sources()
    # a hook implementation with the wrong arguments is refused at registration, naming the plugin
    with pytest.raises(PluginError, match="plugin 'typo'.*register"):
        PluginHost(entry_points=False, plugins=(plugin("typo", lambda reg: None),))


def test_parameter_override_checks_dimension():
    with pytest.raises(PluginError, match="source 'good'.*parameter 'u'"):
        Good().configure({"u": "3 s"})
    assert Good().configure({"u": "3 um"}).value("u", "um") == pytest.approx(3)


# ----------------------------------------------------------------- meta-tests
def hook_names():
    return [n for n, f in inspect.getmembers(hookspecs, inspect.isfunction) if n.startswith("mtbudget_")]


def test_every_hook_has_a_docs_heading_with_its_exact_signature():
    doc = (ROOT / "docs" / "plugins.md").read_text()
    for name in hook_names():
        sig = f"{name}{inspect.signature(getattr(hookspecs, name))}"
        assert f"### {sig}" in doc, f"docs/plugins.md needs a heading '### {sig}'"


def test_every_hook_has_a_test():
    """Each hook is exercised by name in some test outside this meta-test section."""
    here = Path(__file__).parent
    text = "".join(p.read_text() for p in here.glob("test_*.py") if p.name != "test_plugins.py")
    text += Path(__file__).read_text().split("# ----------------------------------------------------------------- meta-tests")[0]
    for name in hook_names():
        assert name in text, f"no test exercises {name}"


def test_docs_show_the_example_package_verbatim():
    doc = (ROOT / "docs" / "plugins.md").read_text()
    for f in ("pyproject.toml", "mtbudget_spindle/__init__.py"):
        assert (ROOT / "docs" / "example-plugin" / f).read_text() in doc, f


def test_example_package_installs_and_appears_in_the_budget(tmp_path):
    target = tmp_path / "site"
    res = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--quiet",
                          "--target", str(target), str(ROOT / "docs" / "example-plugin")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    code = f"""
import sys; sys.path.insert(0, {str(target)!r})
from mtbudget.config import load_config
from mtbudget.engine import run
cfg = load_config({str(SMALL)!r})
cfg.source["sources"]["enable"] = ["tracker_noise", "spindle_growth"]
res = run(cfg, trials=32, block=16, attribution_trials=32)
rows = {{r["source"]: r for r in res.budget["compensation_rms"]["rows"]}}
print(rows["spindle_growth"]["plugin"], rows["spindle_growth"]["group"], rows["spindle_growth"]["u_y"] > 0)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["spindle", "machine", "tool", "True"]
