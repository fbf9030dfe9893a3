"""Every ``python -m hilstack.<module>`` entry module (outside the ``hil`` typer CLI) parses its
arguments one way: argparse in ``main(argv)``, with ``--help``; none reads ``sys.argv`` by hand."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("bus", "configs", "perception", "drivers", "sim_backends", "control", "learning", "calibration", "tools")
#: the typer CLI (`hil`): its verbs stay as they are
TYPER = {"tools/cli.py"}


def _entry_modules() -> list[str]:
    out = []
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT).as_posix()
            if rel in TYPER:
                continue
            tree = ast.parse(f.read_text())
            for node in tree.body:
                if (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
                        and ast.unparse(node.test) in ('__name__ == "__main__"', "__name__ == '__main__'")):
                    out.append(rel)
    return out


ENTRIES = _entry_modules()


def test_the_entry_modules_are_found():
    assert {"tools/bench_sim.py", "tools/bench_bus.py", "calibration/emps.py"} <= set(ENTRIES)


@pytest.mark.parametrize("rel", ENTRIES)
def test_entry_module_has_argparse_help_and_reads_no_argv_by_hand(rel, capsys):
    src = (ROOT / rel).read_text()
    # sys.argv[1:] only as argparse's own default (``argv is None``)
    assert not re.search(r"sys\.argv\[[1-9]\]|sys\.argv\[[2-9]:|len\(sys\.argv\)", src), \
        f"{rel} reads sys.argv by hand"
    mod = importlib.import_module("hilstack." + rel[:-3].replace("/", "."))
    assert callable(getattr(mod, "main", None)), f"{rel}: no main(argv)"
    with pytest.raises(SystemExit) as e:
        mod.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: python -m hilstack."), out[:200]
