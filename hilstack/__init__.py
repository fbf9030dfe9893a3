"""hilstack: a hardware-in-the-loop robot stack for model-based learning and control.

Every package of the repository imports under this one name (``hilstack.drivers``,
``hilstack.control``, ...). The folders themselves stay at the repository's top level;
``pyproject.toml`` maps each to ``hilstack.<folder>`` (setuptools ``package-dir``), so an
install puts nothing into site-packages but ``hilstack``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("hilstack")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

#: the subpackages, each a top-level folder of the repository
SUBPACKAGES = ("bus", "configs", "tasks", "perception", "drivers", "sim_backends", "control", "learning", "calibration",
               "tools")

# A source checkout (the folders beside this package, e.g. a git worktree run with
# PYTHONPATH=. or pytest's pythonpath): the sub-packages are the sibling folders of this
# tree, not whichever tree an editable install points at. An installed wheel holds them
# inside this package and has no pyproject.toml beside it.
_tree = __import__("pathlib").Path(__file__).resolve().parent.parent
#: the source checkout this package runs from (its pyproject.toml's entry points count before an
#: install has caught up with them, drivers/registry.py); None for an installed wheel
SOURCE_TREE = None
if (_tree / "pyproject.toml").is_file() and (_tree / "drivers" / "__init__.py").is_file():
    __path__.append(str(_tree))
    SOURCE_TREE = _tree
del _tree
