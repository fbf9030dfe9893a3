"""Backend registry: ``backend: real | emulated | sim`` in a robot config picks the class.

Entries are import strings so that choosing a backend imports only what it needs
(the sim backend pulls MuJoCo, the real one pyserial...). They are the package's
``hilstack.backends`` entry points (pyproject.toml), so another package can add a robot
without editing this one. A backend class takes the validated :class:`configs.RobotConfig`
in ``from_config``.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import TYPE_CHECKING

from hilstack.configs.schema import ConfigError, RobotConfig, blame_rig, load_robot

if TYPE_CHECKING:
    from hilstack.drivers.base import Driver

#: the entry-point group every backend is registered in (pyproject.toml: "robot.backend" = "module:Class")
GROUP = "hilstack.backends"


def _registered() -> dict[tuple[str, str], str]:
    out: dict[tuple[str, str], str] = {}
    for ep in entry_points(group=GROUP):
        robot, _, backend = ep.name.rpartition(".")
        if robot and backend:
            out[(robot, backend)] = ep.value
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
