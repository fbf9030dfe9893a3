"""Package layering: dependencies point one way (docs/architecture.md, "Layout").

Two checks: a static one over every import statement (names the file and line of a
violation, even inside a function) and a runtime one (importing every module of a
package in a fresh interpreter pulls no forbidden package, transitively).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOP = ("drivers", "sim_backends", "control", "learning", "calibration", "perception", "bus", "tools", "configs")

#: package -> packages it must never import
FORBIDDEN: dict[str, set[str]] = {
    "drivers": {"sim_backends", "control", "learning", "calibration", "tools"},
    "bus": {"drivers", "sim_backends", "control", "learning", "calibration", "perception", "tools"},
    "configs": {"drivers", "sim_backends", "control", "learning", "calibration", "perception", "bus", "tools"},
    # beside bus, under the drivers (the camera driver and the hand sim use it); its training
    # script renders with sim_backends, imported inside the function that runs it
    "perception": {"drivers", "control", "learning", "calibration", "bus", "tools"},
}


def _package(dotted: str) -> str:
    """The hilstack sub-package a module name is in (``hilstack.bus.node`` -> ``bus``), else its top name."""
    parts = dotted.split(".")
    return parts[1] if parts[0] == "hilstack" and len(parts) > 1 else parts[0]


def imported_top_packages(path: Path) -> list[tuple[int, str]]:
    """(line, package) of every absolute import in a file, at any depth (hilstack.<pkg> -> pkg)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, _package(a.name)) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "hilstack":
                out += [(node.lineno, a.name) for a in node.names]
            else:
                out.append((node.lineno, _package(node.module)))
    return out


def violations(package: str) -> list[str]:
    bad = []
    for f in sorted((ROOT / package).rglob("*.py")):
        for line, top in imported_top_packages(f):
            if top in FORBIDDEN[package]:
                bad.append(f"{f.relative_to(ROOT)}:{line} imports {top}")
    return bad


def test_the_static_check_sees_an_import_inside_a_function(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import os\n\ndef g():\n    from hilstack.sim_backends.base import LockstepSim\n")
    assert imported_top_packages(f) == [(1, "os"), (4, "sim_backends")]


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_import_against_the_layering(package):
    assert violations(package) == []


@pytest.mark.parametrize("package", ["drivers", "bus", "perception"])
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
    assert loaded & FORBIDDEN[package] == set()
