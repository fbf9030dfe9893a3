"""Package layering: dependencies point one way (docs/architecture.md, "Layout").

The whole rule set, per package: which hilstack packages it may depend on. A dependency is an
import statement anywhere in a file (inside functions too) or a module name ``hilstack.<pkg>``
in a string that is not a docstring (an import string, ``python -m`` line or registry entry is a
dependency as real as an import). A static check names the file and line of a violation; a
runtime check imports every module of the low packages in a fresh interpreter and checks what
they pulled in, transitively.
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: package -> the hilstack packages it may depend on (lowest floor first). tools, at the top,
#: is the CLI and the experiments' wiring; nothing below it depends on it. drivers never name
#: a simulator (backends and emulators are found through entry points, pyproject.toml).
#: calibration sits above learning: a learned checkpoint is one of the models it calibrates.
ALLOWED: dict[str, set[str]] = {
    "configs": set(),
    "bus": {"configs"},
    "perception": {"configs"},
    "drivers": {"bus", "configs", "perception"},
    "sim_backends": {"drivers", "bus", "configs", "perception"},
    "control": {"sim_backends", "drivers", "bus", "configs", "perception"},
    "learning": {"control", "sim_backends", "drivers", "bus", "configs", "perception"},
    "calibration": {"learning", "control", "sim_backends", "drivers", "bus", "configs", "perception"},
    "tools": {"calibration", "learning", "control", "sim_backends", "drivers", "bus", "configs", "perception"},
}
PACKAGES = tuple(ALLOWED)
_IN_STRING = re.compile(r"\bhilstack\.(\w+)")


def _package(dotted: str) -> str | None:
    """The hilstack sub-package a module name is in (``hilstack.bus.node`` -> ``bus``)."""
    parts = dotted.split(".")
    return parts[1] if parts[0] == "hilstack" and len(parts) > 1 and parts[1] in ALLOWED else None


def _docstrings(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def dependencies(path: Path) -> list[tuple[int, str, str]]:
    """(line, package, how) of every hilstack package a file depends on, at any depth."""
    tree = ast.parse(path.read_text(), filename=str(path))
    docs = _docstrings(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, p, "import") for a in node.names if (p := _package(a.name))]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "hilstack":
                out += [(node.lineno, a.name, "import") for a in node.names if a.name in ALLOWED]
            elif p := _package(node.module):
                out.append((node.lineno, p, "import"))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            out += [(node.lineno, p, "string") for p in _IN_STRING.findall(node.value) if p in ALLOWED]
    return out


def violations(package: str, root: Path = ROOT) -> list[str]:
    bad = []
    for f in sorted((root / package).rglob("*.py")):
        for line, dep, how in dependencies(f):
            if dep != package and dep not in ALLOWED[package]:
                bad.append(f"{f.relative_to(root)}:{line} depends on {dep} ({how})")
    return bad


def test_the_rules_have_no_cycle():
    order: list[str] = []
    seen: set[str] = set()

    def visit(p: str, path: tuple[str, ...]) -> None:
        assert p not in path, f"cycle: {' -> '.join((*path, p))}"
        if p not in seen:
            for q in ALLOWED[p]:
                visit(q, (*path, p))
            seen.add(p)
            order.append(p)

    for p in ALLOWED:
        visit(p, ())
    assert set(order) == set(ALLOWED)


def test_every_top_level_package_has_rules():
    folders = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests", "hilstack", "scripts"}
    assert folders <= set(ALLOWED), folders - set(ALLOWED)


def test_the_check_sees_imports_in_functions_and_module_names_in_strings(tmp_path):
    f = tmp_path / "m.py"
    f.write_text('"""Docs may name hilstack.tools.cli."""\nimport os\n\n'
                 "def g():\n    from hilstack.sim_backends.base import LockstepSim\n\n"
                 'CMD = ["python", "-m", "hilstack.tools.cli"]\nfrom hilstack import control\n')
    assert sorted(dependencies(f)) == [(5, "sim_backends", "import"), (7, "tools", "string"), (8, "control", "import")]


def test_a_deliberately_added_upward_import_fails_the_check(tmp_path):
    (tmp_path / "bus").mkdir()
    (tmp_path / "bus" / "ok.py").write_text("from hilstack.configs.schema import BusConfig\n")
    assert violations("bus", tmp_path) == []
    (tmp_path / "bus" / "up.py").write_text("def f():\n    import hilstack.control.planners\n")
    assert violations("bus", tmp_path) == ["bus/up.py:2 depends on control (import)"]


@pytest.mark.parametrize("package", PACKAGES)
def test_no_dependency_against_the_layering(package):
    assert violations(package) == []


@pytest.mark.parametrize("package", ["configs", "bus", "perception", "drivers"])
def test_importing_a_package_pulls_no_forbidden_package(package):
    modules = sorted(
        "hilstack." + ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for p in (ROOT / package).rglob("*.py")
        if not p.name.startswith("_") or p.name == "__init__.py"
    )
    code = (
        "import importlib, json, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        f"print(json.dumps(sorted({{n.split('.')[1] for n in sys.modules if n.startswith('hilstack.')}})))"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    loaded = set(json.loads(r.stdout.strip().splitlines()[-1]))
    assert loaded - ALLOWED[package] - {package} == set()
