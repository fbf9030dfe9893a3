"""Optional dependencies: which `pip install` brings each one, and the one error every feature
raises when its dependency is missing.

Every optional import goes through :func:`require` (or, for a module imported at the top of a
file, its import error is translated by :func:`missing_extra`): the `hil` program prints the
:class:`MissingExtra` as one line naming the extra, never a traceback (tools/common.py,
``user_errors``). It lives in configs/, the floor of the layering, so every package can use it.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys

#: import name -> (pip distribution, how to install it). The extras are pyproject.toml's
#: [project.optional-dependencies]; metaworld is no extra: its wheel pins mujoco==3.3.0, so it
#: installs without its dependencies (scripts/setup.sh), for its assets only.
OPTIONAL: dict[str, tuple[str, str]] = {
    "cv2": ("opencv-python-headless", "pip install 'hilstack[camera]'"),
    "natnet": ("natnet", "pip install 'hilstack[mocap]'"),
    "pytorch_mppi": ("pytorch-mppi", "pip install 'hilstack[bench]'"),
    "atheris": ("atheris", "pip install 'hilstack[fuzz]'"),
    "textual": ("textual", "pip install 'hilstack[operator]'"),
    "evdev": ("evdev", "pip install 'hilstack[operator]'"),
    "numba": ("numba", "pip install 'hilstack[speed]'"),
    "metaworld": ("metaworld", "pip install --no-deps metaworld==3.1.1 (no extra: its pins would "
                               "downgrade MuJoCo; scripts/setup.sh installs it)"),
}


class MissingExtra(ModuleNotFoundError):
    """An optional dependency is not installed; the message is one line naming what installs it."""


def install_hint(module: str) -> str | None:
    """How to install the optional dependency imported as ``module`` (its top-level name), or None."""
    entry = OPTIONAL.get(module.split(".")[0])
    return None if entry is None else entry[1]


def _installed(module: str) -> bool:
    if module in sys.modules:
        return sys.modules[module] is not None  # None: import blocked (how the tests hide a package)
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def missing_extra(feature: str, module: str) -> MissingExtra:
    """The error to raise when ``feature`` cannot run without ``module``."""
    dist, hint = OPTIONAL.get(module.split(".")[0], (module, f"pip install {module}"))
    return MissingExtra(f"{feature} needs {dist}, which is not installed: {hint}", name=module)


def require(module: str, feature: str, *, load: bool = True):  # noqa: ANN201 - the module, or its spec
    """Import ``module`` for ``feature``, or raise :class:`MissingExtra` naming its extra.
    ``load=False`` only checks that it is installed and returns its import spec (for a package
    used for its files, whose import is heavy)."""
    if not _installed(module):
        raise missing_extra(feature, module)
    if not load:
        return importlib.util.find_spec(module)
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] == module.split(".")[0]:
            raise missing_extra(feature, module) from None
        raise
