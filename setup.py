"""The package list only (everything else is in pyproject.toml).

Each top-level folder installs as ``hilstack.<folder>`` (``package-dir`` in pyproject.toml);
its sub-packages (and data-only sub-folders) are found here, so a new sub-folder needs no edit.
"""

from setuptools import find_namespace_packages, setup

FOLDERS = ("bus", "configs", "tasks", "perception", "drivers", "sim_backends", "control", "learning", "calibration", "tools")

# namespace discovery, so data-only folders (configs/robots, perception/weights, ...) ship their files
PACKAGES = [p for p in find_namespace_packages(include=[f"{f}*" for f in FOLDERS]) if "__pycache__" not in p]

setup(packages=["hilstack"] + [f"hilstack.{p}" for p in PACKAGES])
