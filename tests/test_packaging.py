"""The distribution installs one top-level package, ``hilstack`` (docs/architecture.md, "One namespace").

Built as a wheel from this tree (no network: the venv's setuptools, no build isolation); the
wheel's top-level entries are what ``pip install .`` puts into site-packages.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_wheel_installs_hilstack_alone_with_its_data(tmp_path):
    # a copy, so the build's scratch folders stay out of the checkout
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".venv", ".git", "out", "runs", "build", "*.egg-info",
                                                              "__pycache__", "tests"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                        "-w", str(tmp_path), str(src)], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = tmp_path.glob("hilstack-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    top = {n.split("/")[0] for n in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"hilstack"}
    # every folder under its hilstack name, data files included (configs, MJCF, DBC, weights)
    for must in ("hilstack/control/planners.py", "hilstack/tools/cli.py", "hilstack/configs/robots/widowx.yaml",
                 "hilstack/perception/weights/keypoint_net.pt", "hilstack/drivers/velociroach/driver.py",
                 "hilstack/tasks/baoding.py", "hilstack/sim_backends/dynamixel/firmware.py"):
        assert must in names, must
    assert not any(n.startswith(("hilstack/tests/", "tests/")) for n in names)
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "hil = hilstack.tools.cli:main" in zipfile.ZipFile(whl).read(entry).decode()
