"""Backend registry: ``backend: real | emulated | sim`` in a robot config picks the class.

Entries are import strings so that choosing a backend imports only what it needs
(the sim backend pulls MuJoCo, the real one pyserial...). They are the package's
``hilstack.backends`` entry points (pyproject.toml), so another package can add a robot
without editing this one. A backend class takes the validated :class:`configs.RobotConfig`
in ``from_config``.
"""

from __future__ import annotations

import functools
import importlib
from importlib.metadata import entry_points
from types import ModuleType
from typing import TYPE_CHECKING

from hilstack.configs.schema import ConfigError, RobotConfig, blame_rig, load_robot

if TYPE_CHECKING:
    from hilstack.drivers.base import Driver, RobotSpec

#: the entry-point group every backend is registered in (pyproject.toml: "robot.backend" = "module:Class")
GROUP = "hilstack.backends"


#: robot-provided parts that code above the drivers runs without importing the robot's package
#: (pyproject.toml: "robot.part" = "module"), e.g. the reset arm's pick-and-place script
SKILLS = "hilstack.skills"


def entry_point_map(group: str) -> dict[str, str]:
    """name -> value of one entry-point group: the installed package's metadata, overlaid by the
    source checkout's pyproject.toml when hilstack runs from one (a robot added there is found
    before the editable install is refreshed: one registration line is all it takes)."""
    import hilstack

    out = {ep.name: ep.value for ep in entry_points(group=group)}
    tree = getattr(hilstack, "SOURCE_TREE", None)
    if tree is not None:
        import tomllib

        with open(tree / "pyproject.toml", "rb") as f:
            eps = tomllib.load(f).get("project", {}).get("entry-points", {})
        out.update(eps.get(group, {}))
    return out


def _registered() -> dict[tuple[str, str], str]:
    out: dict[tuple[str, str], str] = {}
    for name, value in entry_point_map(GROUP).items():
        robot, _, backend = name.rpartition(".")
        if robot and backend:
            out[(robot, backend)] = value
    return out


#: (robot, backend) -> "module:Class", read from the installed package's entry points (so this
#: module names no backend package: drivers never import sim_backends)
BACKENDS: dict[tuple[str, str], str] = _registered()


def backends_of(robot: str) -> list[str]:
    return sorted(b for r, b in BACKENDS if r == robot)


def robots() -> list[str]:
    return sorted({r for r, _ in BACKENDS})


def resolve(robot: str, backend: str) -> type[Driver]:
    key = (robot, backend)
    if key not in BACKENDS:
        if not BACKENDS:
            raise ConfigError(None, [("robot", f"no robot is registered (entry points {GROUP!r}): install "
                                               "hilstack (pip install -e .) so its metadata exists")])
        if robot not in robots():
            raise ConfigError(None, [("robot", f"unknown robot {robot!r}; known: {robots()} (a new one needs "
                                               f"its {GROUP!r} entry point and a re-install)")])
        raise ConfigError(None, [("backend", f"robot {robot!r} has no {backend!r} backend; has {backends_of(robot)}")])
    mod, _, cls = BACKENDS[key].partition(":")
    return getattr(importlib.import_module(mod), cls)


def make_driver(cfg: RobotConfig | str, backend: str | None = None, **params: object) -> Driver:
    """Build an (unconfigured) driver from a config, a config name or a path."""
    if not isinstance(cfg, RobotConfig):
        cfg = load_robot(cfg, backend=backend, params=params or None)
    elif backend or params:
        cfg = cfg.model_copy(update={"backend": backend or cfg.backend, "params": {**cfg.params, **params}})
    try:
        cls = resolve(cfg.robot, cfg.backend)
    except ConfigError as e:
        raise blame_rig(cfg, ConfigError(cfg.source, e.problems)) from None
    try:
        return cls.from_config(cfg)
    except ConfigError as e:  # what a rig's entry set is the rig file's fault
        raise blame_rig(cfg, e) from None


@functools.cache
def spec_of(robot: str, backend: str | None = None) -> RobotSpec:
    """A robot's spec by config name (``configs/robots/<robot>.yaml``), read before connecting:
    how code above the drivers learns a robot's constants (joint names, home pose, limits)
    without importing the robot's package. ``backend`` None: the real driver's when there is
    one (built, never connected: no MuJoCo to load), else the sim's; the contract makes the
    spec the same on every backend of a robot."""
    cfg = load_robot(robot)
    if backend is None:
        backend = "real" if "real" in backends_of(cfg.robot) else "sim"
    return make_driver(cfg, backend).spec


def make_backend(robot: str, backend: str = "sim", **params: object) -> Driver:
    """An (unconfigured) driver of a robot by config name with ``params`` over its config's:
    how learning gets an in-process sim (``make_backend("velociroach", "sim", sim={...})``)."""
    return make_driver(robot, backend, **params)


def skill(robot: str, name: str) -> ModuleType:
    """The module of a part a robot provides (entry points ``hilstack.skills``,
    ``"robot.name" = "module"``), e.g. ``skill("reset_arm", "pick_place")``."""
    mod = entry_point_map(SKILLS).get(f"{robot}.{name}")
    if mod is None:
        raise ConfigError(None, [("robot", f"robot {robot!r} provides no {name!r} (entry points {SKILLS!r})")])
    return importlib.import_module(mod)
