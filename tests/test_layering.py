"""Package layering: dependencies point one way (docs/architecture.md, "Layout").

The whole rule set, per package: which hilstack packages it may depend on. A dependency is an
import statement anywhere in a file (inside functions too) or a module name ``hilstack.<pkg>``
in a string that is not a docstring (an import string, ``python -m`` line or registry entry is a
dependency as real as an import). control/ and learning/ also never name a robot's own
sub-package of drivers/ or sim_backends/ (ROBOT_FREE), counted the same way, with no list of
exceptions. A static check names the file and line of a violation; a
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
#: tasks (task definitions: Baoding, the roach's conditions) is on the ground floor beside configs,
#: so a sim, a cost and an experiment share a task without importing one another.
ALLOWED: dict[str, set[str]] = {
    "configs": set(),
    "tasks": {"configs"},
    "bus": {"configs"},
    "perception": {"configs"},
    "drivers": {"bus", "configs", "perception", "tasks"},
    "sim_backends": {"drivers", "bus", "configs", "perception", "tasks"},
    "control": {"sim_backends", "drivers", "bus", "configs", "perception", "tasks"},
    "learning": {"control", "sim_backends", "drivers", "bus", "configs", "perception", "tasks"},
    "calibration": {"learning", "control", "sim_backends", "drivers", "bus", "configs", "perception", "tasks"},
    "tools": {"calibration", "learning", "control", "sim_backends", "drivers", "bus", "configs", "perception",
              "tasks"},
}
#: packages that use drivers/ and sim_backends/ only through their generic modules (the contract
#: drivers/base.py, bridge, registry, emulator_process, fixture; sim_backends/base.py...), never a
#: robot's own sub-package (drivers/<robot>/, sim_backends/<robot>/): a robot reaches them through
#: the registry and its spec, a task through tasks/
ROBOT_FREE = ("control", "learning")
ROBOT_HOMES = ("drivers", "sim_backends")
PACKAGES = tuple(ALLOWED)
_IN_STRING = re.compile(r"\bhilstack\.(\w+(?:\.\w+)*)")


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


def modules(path: Path) -> list[tuple[int, str, str]]:
    """(line, module, how) of every ``hilstack.*`` module a file names, at any depth: an import
    (``from hilstack.a import b`` names ``hilstack.a.b``, which may be a module) or a string."""
    tree = ast.parse(path.read_text(), filename=str(path))
    docs = _docstrings(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, "import") for a in node.names if a.name.startswith("hilstack.")]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "hilstack" or node.module.startswith("hilstack."):
                out += [(node.lineno, f"{node.module}.{a.name}", "import") for a in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            out += [(node.lineno, "hilstack." + m, "string") for m in _IN_STRING.findall(node.value)]
    return out


def dependencies(path: Path) -> list[tuple[int, str, str]]:
    """(line, package, how) of every hilstack package a file depends on, at any depth."""
    return [(line, p, how) for line, m, how in modules(path) if (p := _package(m))]


def robot_packages(root: Path = ROOT) -> set[str]:
    """``hilstack.drivers.<robot>`` and ``hilstack.sim_backends.<robot>``: every sub-package."""
    return {f"hilstack.{home}.{d.name}" for home in ROBOT_HOMES for d in (root / home).iterdir()
            if (d / "__init__.py").is_file()}


def robot_uses(package: str, root: Path = ROOT) -> list[str]:
    """Where a package names a robot's own sub-package (import anywhere or module string)."""
    robots = robot_packages(root)
    bad = []
    for f in sorted((root / package).rglob("*.py")):
        for line, m, how in modules(f):
            hit = next((r for r in robots if m == r or m.startswith(r + ".")), None)
            if hit:
                bad.append(f"{f.relative_to(root)}:{line} uses the robot package {hit} ({how})")
    return bad


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


def test_a_deliberately_added_robot_import_fails_the_robot_rule(tmp_path):
    for d in ("drivers/velociroach", "sim_backends/widowx", "control", "learning"):
        (tmp_path / d).mkdir(parents=True)
    (tmp_path / "drivers" / "velociroach" / "__init__.py").write_text("")
    (tmp_path / "sim_backends" / "widowx" / "__init__.py").write_text("")
    (tmp_path / "control" / "ok.py").write_text("from hilstack.drivers.base import RobotSpec\n"
                                                 "from hilstack.drivers import registry\n")
    assert robot_uses("control", tmp_path) == []
    (tmp_path / "control" / "up.py").write_text("def f():\n    from hilstack.drivers import velociroach\n")
    (tmp_path / "learning" / "up.py").write_text('X = "hilstack.sim_backends.widowx.world:ArmWorld"\n')
    assert robot_uses("control", tmp_path) == [
        "control/up.py:2 uses the robot package hilstack.drivers.velociroach (import)"]
    assert robot_uses("learning", tmp_path) == [
        "learning/up.py:1 uses the robot package hilstack.sim_backends.widowx (string)"]


@pytest.mark.parametrize("package", ROBOT_FREE)
def test_no_concrete_robot_below_calibration(package):
    assert robot_uses(package) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_dependency_against_the_layering(package):
    assert violations(package) == []


@pytest.mark.parametrize("package", ["configs", "tasks", "bus", "perception", "drivers"])
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
