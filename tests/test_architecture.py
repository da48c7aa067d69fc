"""The architecture of docs/architecture.md, checked on the source: layers, no cycles, no private imports.

Every import between mtbudget's modules (including those inside functions)
is read from the syntax tree.  A module may import modules of its own layer
or of lower layers only; the import graph has no cycle; no module imports
another module's underscore names.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "mtbudget"

#: top to bottom, as in docs/architecture.md
LAYERS = [
    ["cli", "__main__"],
    ["runner", "study", "testing"],
    ["report", "report_study", "report_diagnosis", "report_dcc", "budget"],
    ["executors", "diagnose", "runlog", "compensate", "posterior"],
    ["engine"],
    ["simulate"],
    ["scenario", "features"],
    ["outputs", "identify", "multistation", "plugins", "config", "recording", "mcm", "diagnose_scan"],
    ["contracts", "model", "distributions"],
    ["machine", "tracker", "plan", "stats", "hookspecs", "progress"],
    ["units", "errors", "kernels", "kernels_stations", "kernels_stats"],
]
#: the package facade (``__version__``, lazy ``ureg``/``Q_``/``hookimpl``) stands outside the layers
FACADE = "__init__"
LAYER_OF = {m: i for i, names in enumerate(LAYERS) for m in names}


def modules() -> list[str]:
    return sorted(p.stem for p in PKG.glob("*.py") if p.stem != FACADE)


def _type_checking_only(tree) -> set:
    """Line numbers of imports inside ``if TYPE_CHECKING:`` (annotations only, no runtime dependency)."""
    lines = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", None)) == "TYPE_CHECKING":
            for sub in node.body:
                for inner in ast.walk(sub):
                    if isinstance(inner, (ast.Import, ast.ImportFrom)):
                        lines.add(inner.lineno)
    return lines


def imports_of(name: str) -> list[tuple[str, list[str], int]]:
    """(imported mtbudget module, names imported from it, line) for every import in module ``name``."""
    tree = ast.parse((PKG / f"{name}.py").read_text())
    annotations_only = _type_checking_only(tree)
    out = []
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in annotations_only:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level == 1 and node.module:  # from .x import a, b
                out.append((node.module.split(".")[0], [a.name for a in node.names], node.lineno))
            elif node.level == 1:  # from . import x
                out += [(a.name, [], node.lineno) for a in node.names if (PKG / f"{a.name}.py").exists()]
            elif node.module and node.module.startswith("mtbudget."):
                out.append((node.module.split(".")[1], [a.name for a in node.names], node.lineno))
        elif isinstance(node, ast.Import):
            out += [(a.name.split(".")[1], [], node.lineno) for a in node.names if a.name.startswith("mtbudget.")]
    return [(m, names, line) for m, names, line in out if (PKG / f"{m}.py").exists() and m != FACADE]


def test_every_module_has_a_layer():
    missing = [m for m in modules() if m not in LAYER_OF]
    assert not missing, f"modules without a layer in docs/architecture.md and LAYERS: {missing}"


def test_layers_read_top_down():
    bad = []
    for m in modules():
        for dep, _, line in imports_of(m):
            if LAYER_OF[dep] < LAYER_OF[m]:
                bad.append(f"mtbudget/{m}.py:{line} imports {dep}, a higher layer")
    assert not bad, "\n".join(bad)


def test_no_import_cycle():
    graph = {m: {dep for dep, _, _ in imports_of(m) if dep != m} for m in modules()}
    state: dict = {}

    def visit(m, path):
        if state.get(m) == "done":
            return
        if state.get(m) == "active":
            cycle = path[path.index(m):] + [m]
            pytest.fail("import cycle: " + " -> ".join(cycle))
        state[m] = "active"
        for d in sorted(graph[m]):
            visit(d, path + [m])
        state[m] = "done"

    for m in modules():
        visit(m, [])


def test_no_module_imports_another_modules_private_names():
    bad = []
    for m in modules():
        for dep, names, line in imports_of(m):
            bad += [f"mtbudget/{m}.py:{line} imports {dep}.{n}" for n in names
                    if n.startswith("_") and not n.startswith("__")]
        # attribute access on an imported module: `from . import tracker as lt; lt._private`
        tree = ast.parse((PKG / f"{m}.py").read_text())
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 1 and not node.module:
                aliases.update({(a.asname or a.name): a.name for a in node.names})
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                bad.append(f"mtbudget/{m}.py:{node.lineno} uses {aliases[node.value.id]}.{node.attr}")
    assert not bad, "\n".join(bad)


def test_plugins_use_only_public_names():
    bad = []
    for p in sorted((ROOT / "plugins").glob("*.py")):
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mtbudget"):
                bad += [f"plugins/{p.name}:{node.lineno} imports {node.module}.{a.name}" for a in node.names
                        if a.name.startswith("_")]
    assert not bad, "\n".join(bad)


def test_help_and_run_start_without_plotting_or_statistics_libraries():
    """`mtbudget --help` and the run and report modules import neither matplotlib nor scipy.stats (both lazily)."""
    code = ("import sys; from click.testing import CliRunner; from mtbudget.cli import main; "
            "r = CliRunner().invoke(main, ['--help']); assert r.exit_code == 0, r.output; "
            "import mtbudget.runner, mtbudget.report; "
            "print(','.join(m for m in ('matplotlib', 'scipy.stats') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "", f"imported at start-up: {out.stdout.strip()}"
