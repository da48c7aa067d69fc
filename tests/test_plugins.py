"""The plugin contract: discovery, errors that name the culprit, switches, tracing, docs, an external package."""

import ast
import dataclasses
import inspect
import json
import logging
import os
import re
import shutil
import site
import subprocess
import sys
import types
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import mtbudget
from mtbudget import hookspecs
from mtbudget.cli import main
from mtbudget.config import load_config
from mtbudget.contracts import Candidate, Context, Source
from mtbudget.engine import Engine
from mtbudget.errors import PluginError
from mtbudget.hookspecs import hookimpl
from mtbudget.plugins import PluginHost, call, checkout_builtins
from mtbudget.scenario import build_scenario
from mtbudget.units import Q_

from conftest import OffsetSource, plugin_module

ROOT = Path(__file__).resolve().parents[1]
SMALL = ROOT / "tests" / "data" / "small.toml"
BUILTIN = {"machine_tool", "measurement_system", "measurement_strategy", "optimisation_strategy", "physics", "exporters"}


plugin = plugin_module
Good = OffsetSource


class Wobble(Candidate):
    effect = "wobble"
    description = "a test candidate"
    parameters = {"a": "um"}


def builtin_entry_points():
    eps = [ep for ep in metadata.entry_points(group="mtbudget") if ep.dist is not None
           and ep.dist.metadata["Name"] == "mtbudget"]
    assert {ep.name for ep in eps} == BUILTIN, "mtbudget is not installed (pip install -e .)"
    return eps


def module_entry_point(monkeypatch, name, module_name, **hooks):
    """An entry point (of no distribution, so third-party) to an in-memory module with these hooks."""
    mod = types.ModuleType(module_name)
    for hook, fn in hooks.items():
        setattr(mod, hook, hookimpl(fn))
    monkeypatch.setitem(sys.modules, module_name, mod)
    return metadata.EntryPoint(name=name, value=module_name, group="mtbudget")


# ----------------------------------------------------------------- discovery
def test_builtins_arrive_through_entry_points():
    host = PluginHost()
    assert BUILTIN <= set(host.info) and BUILTIN <= host.builtin
    assert all(host.info[n].distribution == "mtbudget" for n in BUILTIN)
    names = {s.name for s in host.sources()}
    assert {"tracker_noise", "repeatability", "registration", "phase_sequence"} <= names
    assert all(s.dist_name == "mtbudget" and s.dist_version for s in host.sources())


def test_environment_switches(monkeypatch, caplog):
    monkeypatch.setenv("MTBUDGET_DISABLE_PLUGINS", "measurement_system")
    assert "tracker_noise" not in {s.name for s in PluginHost().sources()}
    monkeypatch.delenv("MTBUDGET_DISABLE_PLUGINS")
    monkeypatch.setenv("MTBUDGET_PLUGINS", "measurement_strategy")
    assert {s.name for s in PluginHost().sources()} == {"registration"}
    assert not caplog.records
    # a misspelled name is not silently ignored
    monkeypatch.setenv("MTBUDGET_PLUGINS", "measurment_strategy")
    with caplog.at_level(logging.WARNING, logger="mtbudget.plugins"):
        assert PluginHost().sources() == []
    assert any("MTBUDGET_PLUGINS names 'measurment_strategy'" in r.getMessage()
               and "did you mean 'measurement_strategy'" in r.getMessage() for r in caplog.records)


def test_builtins_fall_back_to_the_checkout_when_no_entry_point_is_present():
    """The fallback itself, in process: an empty entry-point list still gives the five built-ins."""
    assert set(checkout_builtins()) == BUILTIN
    assert checkout_builtins(ROOT / "tests") == {}  # not a checkout: nothing
    host = PluginHost(entry_points=[])
    assert set(host.info) == BUILTIN == host.builtin
    assert all(host.info[n].distribution == "mtbudget" and host.info[n].version == mtbudget.__version__ for n in BUILTIN)
    assert {"tracker_noise", "repeatability"} <= {s.name for s in host.sources()}
    assert PluginHost(entry_points=False).info == {}  # discovery off: not even the built-ins


def _filtered_site_packages(dest: Path) -> Path:
    """A view of site-packages without mtbudget's installation (its dist-info, editable finder and .pth files)."""
    dest.mkdir()
    dirs = [Path(p) for p in site.getsitepackages() + [site.getusersitepackages()] if Path(p).is_dir()]
    for d in dirs:
        for entry in d.iterdir():
            low = entry.name.lower()
            if low.startswith(("mtbudget", "__editable__", "__editable___")) or low.endswith(".pth"):
                continue
            if not (dest / entry.name).exists():
                (dest / entry.name).symlink_to(entry)
    return dest


def test_builtins_registered_from_a_source_checkout_that_is_not_installed(tmp_path):
    """A copy of the checkout on PYTHONPATH, in an interpreter where mtbudget is not installed.

    ``python -S`` skips site-packages (and so the editable install's finder); PYTHONPATH gives the
    checkout and a view of site-packages without mtbudget's dist-info, so no ``mtbudget`` entry
    point of mtbudget exists and ``mtbudget_plugins`` is not importable until the host loads it.
    """
    checkout = tmp_path / "checkout"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "recordings")
    for part in ("mtbudget", "plugins"):
        shutil.copytree(ROOT / part, checkout / part, ignore=ignore)
    shutil.copy(ROOT / "pyproject.toml", checkout)
    view = _filtered_site_packages(tmp_path / "site")
    code = """
import importlib.util, json, sys
from importlib import metadata
before = importlib.util.find_spec("mtbudget_plugins")
eps = [(e.name, e.dist.metadata["Name"] if e.dist else None) for e in metadata.entry_points(group="mtbudget")]
import mtbudget
from mtbudget.plugins import PluginHost
host = PluginHost()
print(json.dumps({"installed": before is not None, "eps": eps, "mtbudget": mtbudget.__file__,
                  "info": {n: [i.module, i.distribution, i.version] for n, i in host.info.items()},
                  "files": {n: sys.modules[i.module].__file__ for n, i in host.info.items()},
                  "sources": sorted(s.name for s in host.sources()), "candidates": len(host.candidates())}))
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "MTBUDGET_"))}
    env["PYTHONPATH"] = os.pathsep.join([str(checkout), str(view)])
    out = subprocess.run([sys.executable, "-S", "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    import json

    res = json.loads(out.stdout)
    # the isolation is real: nothing of mtbudget is installed in that interpreter
    assert not res["installed"] and all(dist != "mtbudget" for _, dist in res["eps"]), res["eps"]
    assert Path(res["mtbudget"]).is_relative_to(checkout)
    assert BUILTIN <= set(res["info"])
    for name in BUILTIN:
        module, dist, version = res["info"][name]
        assert module == f"mtbudget_plugins.{name}" and dist == "mtbudget" and version == mtbudget.__version__
        assert Path(res["files"][name]) == checkout / "plugins" / f"{name}.py"
    assert {"tracker_noise", "repeatability", "registration", "phase_sequence"} <= set(res["sources"])
    assert res["candidates"] > 0


# ----------------------------------------------------------------- the hooks
def engine_with(*mods):
    cfg = load_config(SMALL)
    cfg.source = {k: v for k, v in cfg.source.items() if k != "sources"}
    return Engine(build_scenario(cfg, PluginHost(entry_points=False, plugins=mods)), block=8)


def test_hook_mtbudget_register_sources():
    # built-ins and a third-party plugin, each source stamped with the plugin that registered it
    host = PluginHost()
    by_name = {s.name: s for s in host.sources()}
    assert by_name["repeatability"].plugin == "machine_tool" and by_name["tracker_noise"].plugin == "measurement_system"
    eng = engine_with(plugin("mine", lambda register: register(Good())))
    assert [s.name for s in eng.sources] == ["good"] and eng.sources[0].plugin == "mine"
    assert eng.sources[0].dist_name == "(registered in code)"
    b = eng.run_block(0)
    assert np.all(np.isfinite(b.scalars["compensation_rms"]))
    # register() checks what it is given, naming the plugin and the hook
    with pytest.raises(PluginError, match="plugin 'wrong'.*hook mtbudget_register_sources.*needs a mtbudget.contracts.Source"):
        PluginHost(entry_points=False, plugins=(plugin("wrong", lambda register: register(object())),)).sources()
    # an exception inside the hook names plugin, hook and exception
    def explode(register):
        raise ValueError("cannot start")

    with pytest.raises(PluginError, match="plugin 'exploder'.*mtbudget_register_sources.*ValueError: cannot start"):
        PluginHost(entry_points=False, plugins=(plugin("exploder", explode),)).sources()


def test_hook_mtbudget_register_candidates():
    cands = PluginHost().candidates()
    assert cands and all(c.plugin == "physics" and c.dist_name == "mtbudget" for c in cands)
    assert "thermal_expansion[x]" in {c.label for c in cands}
    host = PluginHost(entry_points=False,
                      plugins=(plugin("wobbly", lambda register: register(Wobble("x")), "mtbudget_register_candidates"),))
    (c,) = host.candidates()
    assert c.label == "wobble[x]" and c.plugin == "wobbly"
    with pytest.raises(PluginError, match="plugin 'src'.*hook mtbudget_register_candidates.*needs a mtbudget.contracts.Candidate"):
        PluginHost(entry_points=False, plugins=(plugin("src", lambda register: register(Good()),
                                                       "mtbudget_register_candidates"),)).candidates()

    def explode(register):
        raise KeyError("column")

    with pytest.raises(PluginError, match="plugin 'exploder'; hook mtbudget_register_candidates: raised KeyError"):
        PluginHost(entry_points=False, plugins=(plugin("exploder", explode, "mtbudget_register_candidates"),)).candidates()


class Bad(Good):
    def __init__(self, result=None, raises=False, name="bad"):
        super().__init__()
        self.result, self.raises, self.name = result, raises, name

    def sample(self, n, rng, ctx):
        if self.raises:
            raise RuntimeError("boom")
        return self.result(n, ctx)


CASES = {
    "raises": (dict(raises=True), "method sample\\(\\): raised RuntimeError: boom"),
    "wrong shape": (dict(result=lambda n, c: {"tracker_offset": Q_(np.zeros((n, 3)), "mm")}), "has shape"),
    "wrong dimension": (dict(result=lambda n, c: {"tracker_offset": Q_(np.zeros((n, c.n_points, 3)), "s")}), "dimension"),
    "NaN": (dict(result=lambda n, c: {"tracker_offset": Q_(np.full((n, c.n_points, 3), np.nan), "mm")}), "NaN"),
    "undeclared key": (dict(result=lambda n, c: {"point_offset": Q_(np.zeros((n, c.n_points, 3)), "mm")}), "not among its declared"),
    "not a dict": (dict(result=lambda n, c: 3), "must return a dict"),
    # issue 29: finite but absurd (1e300 mm) made run print inf/nan with exit 0
    "absurd, in mm": (dict(result=lambda n, c: {"tracker_offset": Q_(np.full((n, c.n_points, 3), 1e300), "mm")}),
                      r"'tracker_offset' of magnitude up to 1e\+300 mm, beyond the plausible 10000 mm"),
    "absurd, in km": (dict(result=lambda n, c: {"tracker_offset": Q_(np.full((n, c.n_points, 3), -20.0), "km")}),
                      r"magnitude up to 2e\+07 mm"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_misbehaving_source_is_named(case):
    kw, pattern = CASES[case]
    with pytest.raises(PluginError) as info:
        engine_with(plugin("culprit", lambda register: register(Bad(**kw))))
    msg = str(info.value)
    assert "plugin 'culprit'" in msg and "source 'bad'" in msg and re.search(pattern, msg), msg


def test_call_names_plugin_source_hook_and_method():
    src = Bad(raises=True)
    src.plugin = "culprit"
    with pytest.raises(PluginError) as info:
        call(src, "sample", 2, np.random.default_rng(0), None)
    e = info.value
    assert (e.plugin, e.source, e.hook, e.method) == ("culprit", "bad", "mtbudget_register_sources", "sample")
    assert call(Good(), "value", "u", "um") == pytest.approx(1.0)


def test_invalid_registrations_are_named():
    with pytest.raises(PluginError, match="group"):
        bad = Good()
        bad.group = "kitchen"
        PluginHost(entry_points=False, plugins=(plugin("g", lambda register: register(bad)),)).sources()
    # a hook implementation with the wrong arguments is refused at registration, naming the plugin
    with pytest.raises(PluginError, match="plugin 'typo'.*register"):
        PluginHost(entry_points=False, plugins=(plugin("typo", lambda reg: None),))


def test_misspelled_hook_is_refused_with_the_closest_hook():
    hookimpl_typo = plugin("typo", lambda register: None, hook="mtbudget_register_source")
    with pytest.raises(PluginError) as info:
        PluginHost(entry_points=False, plugins=(hookimpl_typo,))
    e = info.value
    assert e.plugin == "typo" and e.hook == "mtbudget_register_source"
    assert "did you mean 'mtbudget_register_sources'?" in str(e)
    # without the marker pluggy ignores a function; a near-miss is still caught
    unmarked = types.ModuleType("unmarked")
    unmarked.mtbudget_register_candidate = lambda register: None
    with pytest.raises(PluginError, match="plugin 'unmarked'.*did you mean 'mtbudget_register_candidates'"):
        PluginHost(entry_points=False, plugins=(unmarked,))
    # the exact name without @hookimpl would never be called either
    forgot = types.ModuleType("forgot")
    forgot.mtbudget_register_sources = lambda register: None
    with pytest.raises(PluginError, match="plugin 'forgot'; hook mtbudget_register_sources: .*not marked with @hookimpl"):
        PluginHost(entry_points=False, plugins=(forgot,))
    # optional hooks and unrelated helpers are fine
    ok = types.ModuleType("ok")
    ok.mtbudget_future_hook = hookimpl(optionalhook=True)(lambda x: None)
    ok.mtbudget_cache_folder = lambda: "/tmp"
    ok.mtbudget_register_sources = hookimpl(lambda register: register(Good()))
    assert [s.name for s in PluginHost(entry_points=False, plugins=(ok,)).sources()] == ["good"]


def test_duplicate_source_names_blame_the_later_or_third_party_plugin(monkeypatch):
    # two third-party plugins: both named, the later blamed
    host = PluginHost(entry_points=False, plugins=(plugin("first", lambda register: register(Good())),
                                                   plugin("second", lambda register: register(Good()))))
    with pytest.raises(PluginError) as info:
        host.sources()
    assert info.value.plugin == "second" and info.value.source == "good"
    assert "already registered by plugin 'first'" in str(info.value) and "registered again by plugin 'second'" in str(info.value)

    # a third-party plugin that sorts (and registers) before the built-ins and takes a built-in's name
    class Clash(Good):
        name = "repeatability"

    early = module_entry_point(monkeypatch, "aaa", "mtbudget_test_aaa", mtbudget_register_sources=lambda register: register(Clash()))
    monkeypatch.setenv("MTBUDGET_STRICT_PLUGINS", "1")  # strict: an error, for the plugin's own tests
    host = PluginHost(entry_points=[early, *builtin_entry_points()])
    assert [i.plugin_name for i in host.pm.hook.mtbudget_register_sources.get_hookimpls()][0] == "aaa"
    with pytest.raises(PluginError) as info:
        host.sources()
    msg = str(info.value)
    assert info.value.plugin == "aaa" and "'aaa'" in msg and "'machine_tool' (mtbudget " in msg, msg
    assert "MTBUDGET_DISABLE_PLUGINS=aaa" in msg
    # by default the third-party plugin is skipped with that warning and the built-in's source is the one used
    monkeypatch.delenv("MTBUDGET_STRICT_PLUGINS")
    host = PluginHost(entry_points=[early, *builtin_entry_points()])
    mine = {s.name: s for s in host.sources()}
    assert mine["repeatability"].plugin == "machine_tool" and "aaa" not in host.info
    assert len(host.skipped) == 1 and "'aaa'" in host.skipped[0] and "duplicate source name 'repeatability'" in host.skipped[0]

    # a plugin registered after the built-ins is blamed too (candidates: effect and axis)
    class Thermal(Wobble):
        effect = "thermal_expansion"

    late = plugin("late", lambda register: register(Thermal("x")), "mtbudget_register_candidates")
    host = PluginHost(entry_points=builtin_entry_points(), plugins=(late,))
    with pytest.raises(PluginError, match="duplicate candidate name 'thermal_expansion\\[x\\]'.*plugin 'physics'") as info:
        host.candidates()
    assert info.value.plugin == "late"


def test_duplicate_plugin_name_blames_the_third_party_package(monkeypatch):
    impostor = module_entry_point(monkeypatch, "physics", "mtbudget_test_impostor")
    eps = [impostor, *builtin_entry_points()]  # listed first: the built-in still wins its name
    monkeypatch.setenv("MTBUDGET_STRICT_PLUGINS", "1")
    with pytest.raises(PluginError, match="two plugins are named 'physics'.*the one from mtbudget_test_impostor") as info:
        PluginHost(entry_points=eps)
    assert info.value.plugin == "physics"
    monkeypatch.delenv("MTBUDGET_STRICT_PLUGINS")  # by default: skipped with a warning, the built-in kept
    host = PluginHost(entry_points=eps)
    assert host.info["physics"].distribution == "mtbudget" and host.candidates()
    assert len(host.skipped) == 1 and "two plugins are named 'physics'" in host.skipped[0]


def write_broken_distribution(folder: Path) -> Path:
    """An installed (dist-info on sys.path) third-party plugin whose import fails."""
    folder.mkdir(exist_ok=True)
    (folder / "mtbudget_test_broken.py").write_text("import mtbudget_test_missing_dependency\n")
    info = folder / "mtbudget_broken-0.3.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mtbudget-broken\nVersion: 0.3.1\n")
    (info / "entry_points.txt").write_text("[mtbudget]\nbroken = mtbudget_test_broken\n")
    return folder


def test_plugin_that_fails_to_import_is_skipped_with_a_warning(tmp_path, monkeypatch, caplog):
    monkeypatch.syspath_prepend(str(write_broken_distribution(tmp_path / "site")))
    with caplog.at_level(logging.WARNING, logger="mtbudget.plugins"):
        host = PluginHost()
    assert "broken" not in host.info and BUILTIN <= set(host.info)
    assert {"tracker_noise", "repeatability"} <= {s.name for s in host.sources()}
    (record,) = [r for r in caplog.records if r.name == "mtbudget.plugins"]
    msg = record.getMessage()
    assert record.levelno == logging.WARNING and "\n" not in msg and host.skipped == [msg]
    for part in ("'broken'", "mtbudget-broken 0.3.1", "ModuleNotFoundError", "mtbudget_test_missing_dependency",
                 "MTBUDGET_DISABLE_PLUGINS=broken"):
        assert part in msg, (part, msg)
    caplog.clear()
    monkeypatch.setenv("MTBUDGET_DISABLE_PLUGINS", "broken")
    assert PluginHost().skipped == [] and not caplog.records


def test_a_broken_builtin_is_an_error(monkeypatch):
    """mtbudget's own plugins are not skipped: a run without one of them would be wrong, not smaller."""
    import mtbudget.plugins as host_module

    declared = dict(checkout_builtins(), physics="mtbudget_plugins.no_such_module")
    monkeypatch.setattr(host_module, "checkout_builtins", lambda root=None: declared)
    with pytest.raises(PluginError, match="plugin 'physics'; hook load: built-in plugin .*no_such_module.*"
                                          "MTBUDGET_DISABLE_PLUGINS=physics"):
        PluginHost(entry_points=[])


def test_trace_switch_prints_every_hook_call_and_method_call(monkeypatch, capsys):
    mine = plugin("mine", lambda register: register(Good()))
    PluginHost(entry_points=False, plugins=(mine,)).sources()
    assert capsys.readouterr().err == ""  # off by default
    monkeypatch.setenv("MTBUDGET_TRACE_PLUGINS", "1")
    host = PluginHost(entry_points=False, plugins=(mine,))
    (src,) = host.sources()
    call(src, "value", "u", unit="um")
    with pytest.raises(PluginError):
        PluginHost(entry_points=False, plugins=(plugin("exploder", lambda register: 1 / 0),)).sources()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3, lines
    hook, method, failed = lines
    assert re.fullmatch(r"mtbudget trace: hook mtbudget_register_sources\(register=<register\(\)>\), plugin mine "
                        r"\(registered in code\): ok, registered 1: good, \d+\.\d+ ms", hook), hook
    assert re.fullmatch(r"mtbudget trace: method good\.value\('u', unit='um'\), plugin mine \(registered in code\), "
                        r"hook mtbudget_register_sources: ok, \d+\.\d+ ms", method), method
    assert "plugin exploder" in failed and "raised ZeroDivisionError" in failed


def test_cli_shows_the_import_warning_and_the_trace_on_stderr(tmp_path):
    site_dir = write_broken_distribution(tmp_path / "site")
    env = dict(os.environ, MTBUDGET_TRACE_PLUGINS="1",
               PYTHONPATH=os.pathsep.join([str(site_dir)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    env.pop("MTBUDGET_DISABLE_PLUGINS", None)
    env.pop("MTBUDGET_PLUGINS", None)
    out = subprocess.run([sys.executable, "-m", "mtbudget", "plugins"], capture_output=True, text=True, env=env,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "machine_tool" in out.stdout and "tracker_noise" in out.stdout
    err = out.stderr.splitlines()
    warnings = [line for line in err if "skipping plugin 'broken'" in line]
    assert len(warnings) == 1 and "MTBUDGET_DISABLE_PLUGINS=broken" in warnings[0], out.stderr
    traced = {re.search(r"plugin (\w+)", line).group(1) for line in err if line.startswith("mtbudget trace: hook ")}
    assert BUILTIN <= traced, out.stderr


FAILING_PLUGINS = {  # entry-point name -> module text: four ways a third-party plugin fails, one good plugin
    "raiser": "from mtbudget import hookimpl\n@hookimpl\ndef mtbudget_register_sources(register):\n"
              "    raise RuntimeError('no licence file')\n",
    "physics": "",  # the name of a built-in plugin
    "typo": "from mtbudget import hookimpl\n@hookimpl\ndef mtbudget_register_sourcez(register):\n    pass\n",
    "clash": "from mtbudget import hookimpl\nfrom mtbudget.contracts import Group, Source\n"
             "class R(Source):\n    name = 'repeatability'\n    targets = ('tracker_offset',)\n"
             "@hookimpl\ndef mtbudget_register_sources(register):\n    register(R())\n",
    "nice": "from mtbudget import hookimpl\nfrom mtbudget.contracts import Group, Source\nfrom mtbudget.units import Q_\n"
            "class Nice(Source):\n    name = 'nice_offset'\n    opt_in = True\n    group = Group.MEASUREMENT_SYSTEM\n"
            "    targets = ('tracker_offset',)\n    parameters = {'u': Q_(1.0, 'um')}\n"
            "    def sample(self, n, rng, ctx):\n"
            "        return {'tracker_offset': Q_(rng.normal(0, self.value('u', 'mm'), (n, ctx.n_points, 3)), 'mm')}\n"
            "@hookimpl\ndef mtbudget_register_sources(register):\n    register(Nice())\n",
}


def test_a_failing_third_party_plugin_is_skipped_and_the_others_run(tmp_path, monkeypatch, caplog):
    """Issue 29: a plugin whose hook raises, that reuses a built-in's name or misspells a hook made `mtbudget plugins`
    and every run exit 2; each is now named, skipped with a warning, and the built-ins and the good plugin run."""
    import mtbudget.plugins as host_module

    site_dir = tmp_path / "site"
    site_dir.mkdir()
    for name, text in FAILING_PLUGINS.items():
        (site_dir / f"mtbudget_test_{name}.py").write_text(text)
    info = site_dir / "mtbudget_zoo-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: mtbudget-zoo\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[mtbudget]\n" + "".join(f"{n} = mtbudget_test_{n}\n" for n in FAILING_PLUGINS))
    monkeypatch.syspath_prepend(str(site_dir))
    for var in ("MTBUDGET_DISABLE_PLUGINS", "MTBUDGET_PLUGINS", "MTBUDGET_STRICT_PLUGINS"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(host_module, "_default", None)
    res = CliRunner().invoke(main, ["plugins", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    skipped = {re.search(r"skipping plugin '(\w+)'", m).group(1): m for m in data["skipped"]}
    assert set(skipped) == {"raiser", "physics", "typo", "clash"}, data["skipped"]
    for name, part in [("raiser", "RuntimeError: no licence file"), ("physics", "two plugins are named 'physics'"),
                       ("typo", "did you mean 'mtbudget_register_sources'"),
                       ("clash", "duplicate source name 'repeatability'")]:
        m = skipped[name]
        assert part in m and "mtbudget-zoo 1.0" in m and f"MTBUDGET_DISABLE_PLUGINS={name}" in m and "\n" not in m, m
    by_name = {s["name"]: s for s in data["sources"]}
    assert by_name["repeatability"]["plugin"] == "machine_tool" and by_name["nice_offset"]["plugin"] == "nice"
    assert next(p for p in data["plugins"] if p["name"] == "physics")["distribution"] == "mtbudget"
    # a run with the good plugin's source enabled: exit 0, every warning on stderr, the source in the budget
    cfg = tmp_path / "c.toml"
    cfg.write_text(SMALL.read_text().replace('enable = ["tracker_noise", ', 'enable = ["nice_offset", "tracker_noise", ', 1))
    monkeypatch.setattr(host_module, "_default", None)
    caplog.clear()
    res = CliRunner().invoke(main, ["run", str(cfg), "--trials", "16", "--block", "8", "--attribution-trials", "16",
                                    "--quiet", "--json", "--log", str(tmp_path / "r.mcap")])
    assert res.exit_code == 0, res.output
    assert "nice_offset" in {r["source"] for r in json.loads(res.stdout)["budget"]["compensation_rms"]["rows"]}
    said = " ".join(r.getMessage() for r in caplog.records if r.name == "mtbudget.plugins")
    assert all(f"skipping plugin '{n}'" in said for n in skipped), said  # (on stderr: the subprocess test above)


def test_parameter_override_checks_dimension():
    with pytest.raises(PluginError, match="source 'good'.*parameter 'u'"):
        Good().configure({"u": "3 s"})
    assert Good().configure({"u": "3 um"}).value("u", "um") == pytest.approx(3)


# ----------------------------------------------------------------- meta-tests
def hook_names():
    names = [n for n, f in inspect.getmembers(hookspecs, inspect.isfunction) if n.startswith("mtbudget_")]
    assert names, "no hookspecs found"
    return names


def test_hookspecs_are_typed_and_documented():
    for name in hook_names():
        fn = getattr(hookspecs, name)
        sig = inspect.signature(fn)
        assert all(p.annotation is not inspect.Parameter.empty for p in sig.parameters.values()), name
        assert sig.return_annotation is not inspect.Signature.empty, name
        doc = inspect.getdoc(fn) or ""
        for p in sig.parameters:
            assert f":param {p}:" in doc, f"{name}: document what {p} is"
        assert ":return:" in doc, f"{name}: document what is expected back"


def test_every_hook_has_a_docs_heading_with_its_exact_signature():
    doc = (ROOT / "docs" / "plugins.md").read_text()
    for name in hook_names():
        params = ", ".join(inspect.signature(getattr(hookspecs, name)).parameters)
        assert f"### {name}({params})\n" in doc, f"docs/plugins.md needs a heading '### {name}({params})'"


def test_every_hook_has_a_test_named_after_it():
    """For each hook a test function named exactly test_hook_<hook> somewhere in tests/ (found by AST)."""
    defined = set()
    for path in Path(__file__).parent.glob("test_*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                defined.add(node.name)
    missing = [f"test_hook_{name}" for name in hook_names() if f"test_hook_{name}" not in defined]
    assert not missing, f"no test named {', '.join(missing)} in tests/"


def test_docs_describe_the_context_the_switches_and_the_source_attributes():
    doc = (ROOT / "docs" / "plugins.md").read_text()
    rows = set(re.findall(r"^\| `([\w.]+)", doc, re.MULTILINE))
    fields = {f.name for f in dataclasses.fields(Context)}
    fields |= {n for n, v in vars(Context).items() if isinstance(v, property) or
               (inspect.isfunction(v) and not n.startswith("_"))}
    missing = {f for f in fields if not any(r == f or r.startswith((f + ".", f + "(")) for r in rows)}
    assert not missing, f"docs/plugins.md: the Context table lacks {sorted(missing)}"
    for word in ("MTBUDGET_DISABLE_PLUGINS", "MTBUDGET_PLUGINS", "MTBUDGET_TRACE_PLUGINS", "from mtbudget import hookimpl",
                 "`opt_in`", "`links`", '{"R": "machine_tool.repeatability"}'):
        assert word in doc, word
    assert mtbudget.hookimpl is hookimpl


def test_docs_show_the_example_package_verbatim():
    doc = (ROOT / "docs" / "plugins.md").read_text()
    for f in ("pyproject.toml", "mtbudget_spindle/__init__.py"):
        assert (ROOT / "docs" / "example-plugin" / f).read_text() in doc, f


def test_example_package_installs_and_appears_in_the_budget(tmp_path):
    target, source = tmp_path / "site", tmp_path / "example-plugin"
    # built from a copy, so the build leaves nothing behind in docs/example-plugin
    shutil.copytree(ROOT / "docs" / "example-plugin", source, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    res = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--quiet",
                          "--target", str(target), str(source)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    code = f"""
import sys; sys.path.insert(0, {str(target)!r})
from mtbudget.config import load_config
from mtbudget.runner import run
cfg = load_config({str(SMALL)!r})
cfg.source["sources"]["enable"] = ["tracker_noise", "spindle_growth"]
res = run(cfg, trials=32, block=16, attribution_trials=32)
rows = {{r["source"]: r for r in res.budget["compensation_rms"]["rows"]}}
print(rows["spindle_growth"]["plugin"], rows["spindle_growth"]["group"], rows["spindle_growth"]["rms_i"] > 0)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["spindle", "machine", "tool", "True"]


# ------------------------------------------------------------------ temperatures in source options (issue 19)
class _Thermo(Source):
    """A test source with a temperature difference (K) and an absolute temperature (degC) among its parameters."""

    name = "thermo_test"
    distribution = "normal"
    targets = ("sensor",)
    parameters = {"u_t": Q_(0.1, "K"), "ambient": Q_(20.0, "degC"), "slope": Q_(1.0, "um/K")}


@pytest.mark.parametrize("text, kelvin", [("0.1 delta_degC", 0.1), ("0.25 K", 0.25), ("0.9 delta_degF", 0.5),
                                          ("250 mK", 0.25)])
def test_a_temperature_difference_option_reads_difference_units(text, kelvin):
    src = _Thermo(u_t=text)
    assert src.value("u_t", "K") == pytest.approx(kelvin, rel=1e-12)  # 1 degF step = 5/9 K, by definition


@pytest.mark.parametrize("text, hint", [("0.1 degC", '"0.1 delta_degC"'), ("0.2 degF", '"0.2 delta_degF"')])
def test_a_temperature_difference_option_refuses_an_offset_scale(text, hint):
    with pytest.raises(PluginError) as exc:
        _Thermo(u_t=text)
    msg = str(exc.value)
    assert "\n" not in msg and "'u_t'" in msg and hint in msg and "thermo_test" in msg


def test_a_product_with_degC_is_a_difference():
    # um/degC is um per kelvin of difference: 2 um/degC = 2 um/K (pint's as_delta inside a product)
    assert _Thermo(slope="2 um/degC").value("slope", "um/K") == pytest.approx(2.0, rel=1e-12)


def test_an_absolute_temperature_option_refuses_delta_units_and_implausible_values():
    assert _Thermo(ambient="25 degC").value("ambient", "K") == pytest.approx(298.15, rel=1e-12)
    assert _Thermo(ambient="77 degF").value("ambient", "K") == pytest.approx(298.15, rel=1e-12)  # (77-32)*5/9 + 273.15
    with pytest.raises(PluginError, match="is a temperature difference; it is an absolute temperature"):
        _Thermo(ambient="20 delta_degC")
    with pytest.raises(PluginError, match="not a plausible absolute temperature"):
        _Thermo(ambient="20 K")


def test_a_config_with_an_offset_temperature_difference_is_one_line(tmp_path):
    from click.testing import CliRunner

    from mtbudget.cli import main

    small = (Path(__file__).parent / "data" / "small.toml").read_text().replace(
        'enable = ["tracker_noise",', 'enable = ["temperature_sensor_calibration", "tracker_noise",')
    assert "temperature_sensor_calibration" in small
    cfg = tmp_path / "t.toml"
    cfg.write_text(small + '\n[sources.temperature_sensor_calibration]\nu_calibration = "0.1 degC"\n')
    res = CliRunner().invoke(main, ["plugins", str(cfg)])
    assert res.exit_code == 2 and "delta_degC" in res.output and "273.25 K" in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1 and "Traceback" not in res.output
    cfg.write_text(small + '\n[sources.temperature_sensor_calibration]\nu_calibration = "0.1 delta_degC"\n')
    res = CliRunner().invoke(main, ["plugins", str(cfg), "--json"])
    assert res.exit_code == 0, res.output


def test_sources_that_model_one_thing_twice_cannot_both_be_enabled():
    """Source.excludes: a plugin's alternative model of what a built-in draws refuses to run beside it, in one line
    naming both (the built-in `tracker_noise` here)."""
    from mtbudget.errors import ConfigError
    from mtbudget.scenario import select_sources

    class OtherNoise(Good):
        name = "other_noise"
        excludes = ("tracker_noise",)

    host = PluginHost(plugins=(plugin("alt", lambda register: register(OtherNoise())),))
    cfg = load_config(SMALL)
    with pytest.raises(ConfigError, match="'other_noise' and 'tracker_noise' model the same thing"):
        select_sources(cfg, host, ["tracker_noise", "other_noise"])
    assert [s.name for s in select_sources(cfg, host, ["other_noise"])[0]] == ["other_noise"]


def test_the_plugin_guide_names_every_public_member_of_source():
    """Issue 29: value(), nonnegative, excludes, configure, check, description were used but undocumented."""
    doc = (ROOT / "docs" / "plugins.md").read_text()
    table = doc[doc.index("### Every member of `Source`"):doc.index("An example that uses them")]
    rows = " ".join(line.split("|")[1] for line in table.splitlines() if line.startswith("| `"))
    members = {n for n in dir(Source) if not n.startswith("_")} | {"bounded"}
    missing = sorted(m for m in members if f"`{m}" not in rows and f"`{m}(" not in rows and f", `{m}`" not in rows)
    assert not missing, f"docs/plugins.md: the Source table lacks {missing}"


def test_the_plugin_guides_source_example_runs_and_its_checks_bite():
    doc = (ROOT / "docs" / "plugins.md").read_text()
    start = doc.index("An example that uses them")
    code = doc[doc.index("```python", start) + len("```python"):doc.index("```", doc.index("```python", start) + 9)]
    mod = types.ModuleType("mtbudget_doc_example")
    exec(compile(code, "docs/plugins.md", "exec"), mod.__dict__)
    eng = engine_with(mod)
    assert "squareness_tolerance" in [s.name for s in eng.scenario.sources]
    src = mod.SquarenessTolerance(half_width="2 mrad")
    assert "above 1000 urad" in src.check()
    assert "must not be negative" in mod.SquarenessTolerance(half_width="-1 urad").check()
    with pytest.raises(PluginError, match="is a ratio, not an angle"):
        mod.SquarenessTolerance(half_width="10 um/m")
    draws = call(src.configure({"half_width": "8 urad"}), "sample", 4000, np.random.default_rng(1), eng.scenario.context)
    a = draws["geometry.angular"].to("urad").magnitude
    col = [p.name for p in eng.scenario.context.model.errors.params].index("sxy")
    assert np.abs(a[:, col]).max() <= 8 and a[:, col].std() == pytest.approx(8 / np.sqrt(3), rel=0.05)
    assert np.count_nonzero(np.delete(a, col, axis=1)) == 0
