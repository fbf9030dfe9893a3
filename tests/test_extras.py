"""Missing optional dependencies: one line naming what installs them (configs/extras.py)."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from hilstack.configs import extras
from hilstack.tools.common import user_errors

ROOT = Path(__file__).resolve().parents[1]


def test_every_named_extra_exists_in_pyproject_and_readme_names_no_other():
    declared = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
    named = {h.split("[")[1].split("]")[0] for _, h in extras.OPTIONAL.values() if "hilstack[" in h}
    assert named and named <= declared
    readme = (ROOT / "README.md").read_text().split("## Dependencies", 1)[1].split("##", 1)[0]
    import re

    in_readme = set(re.findall(r"`(\w+)` \(", readme))
    assert in_readme and in_readme <= declared, in_readme - declared


def test_require_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "cv2", None)  # the import is blocked, as if not installed
    with pytest.raises(extras.MissingExtra) as e:
        extras.require("cv2", "the stereo camera")
    msg = str(e.value)
    assert "\n" not in msg and "hilstack[camera]" in msg and "the stereo camera" in msg
    assert extras.require("json", "x").dumps([1]) == "[1]"  # an installed module is returned


def test_sawyer_model_without_metaworld_is_one_line(monkeypatch):
    from hilstack.sim_backends.sawyer import model

    monkeypatch.setitem(sys.modules, "metaworld", None)
    with pytest.raises(extras.MissingExtra, match="pip install --no-deps metaworld"):
        model.asset_path()


def test_cli_prints_one_line_for_a_missing_optional_module():
    app = typer.Typer()

    @app.command()
    @user_errors
    def go(what: str) -> None:
        if what == "cv2":
            raise ModuleNotFoundError("No module named 'cv2'", name="cv2")  # a module-level import
        raise ModuleNotFoundError("No module named 'nonesuch'", name="nonesuch")

    r = CliRunner().invoke(app, ["cv2"])
    assert r.exit_code == 2
    assert r.output.strip().count("\n") == 0 and "hilstack[camera]" in r.output
    r = CliRunner().invoke(app, ["other"])  # not an optional dependency: a bug, its traceback
    assert r.exit_code == 1 and isinstance(r.exception, ModuleNotFoundError)
