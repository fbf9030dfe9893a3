"""Backend registry: ``backend: real | emulated | sim`` in a robot config picks the class.

Entries are import strings so that choosing a backend imports only what it needs
(the sim backend pulls MuJoCo, the real one pyserial...). A backend class takes the
validated :class:`configs.RobotConfig` in ``from_config``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from hilstack.configs.schema import ConfigError, RobotConfig, blame_rig, load_robot

if TYPE_CHECKING:
    from hilstack.drivers.base import Driver

#: (robot, backend) -> "module:Class"
BACKENDS: dict[tuple[str, str], str] = {
    ("pointmass", "sim"): "hilstack.sim_backends.pointmass:PointMassSim",
    ("velociroach", "sim"): "hilstack.sim_backends.velociroach.backend:VelociRoachSim",
    ("velociroach", "emulated"): "hilstack.drivers.velociroach.driver:VelociRoachDriver",
    ("velociroach", "real"): "hilstack.drivers.velociroach.driver:VelociRoachDriver",
    ("mocap", "real"): "hilstack.drivers.mocap.driver:MocapDriver",
    ("camera", "real"): "hilstack.drivers.camera.driver:StereoCameraDriver",
    ("camera", "sim"): "hilstack.sim_backends.shadow_hand.cameras:StereoCameraSim",
    ("shadow_hand", "sim"): "hilstack.sim_backends.shadow_hand.backend:ShadowHandSim",
    ("shadow_hand", "emulated"): "hilstack.drivers.shadow_hand.driver:ShadowHandDriver",
    ("shadow_hand", "real"): "hilstack.drivers.shadow_hand.driver:ShadowHandDriver",
    ("widowx", "sim"): "hilstack.sim_backends.widowx.backend:WidowXSim",
    ("widowx", "emulated"): "hilstack.drivers.widowx.driver:WidowXDriver",
    ("widowx", "real"): "hilstack.drivers.widowx.driver:WidowXDriver",
    ("reset_mechanism", "sim"): "hilstack.sim_backends.widowx.backend:MechanismSim",
    ("reset_mechanism", "emulated"): "hilstack.drivers.widowx.driver:MechanismDriver",
    ("reset_mechanism", "real"): "hilstack.drivers.widowx.driver:MechanismDriver",
    ("sawyer", "sim"): "hilstack.sim_backends.sawyer.backend:SawyerSim",
    ("sawyer", "emulated"): "hilstack.drivers.sawyer.driver:SawyerDriver",
    ("sawyer", "real"): "hilstack.drivers.sawyer.driver:SawyerDriver",
    ("reset_arm", "sim"): "hilstack.sim_backends.reset_arm.backend:ResetArmSim",
    ("reset_arm", "emulated"): "hilstack.drivers.reset_arm.driver:ResetArmDriver",
    ("reset_arm", "real"): "hilstack.drivers.reset_arm.driver:ResetArmDriver",
}


def register_backend(robot: str, backend: str, target: str) -> None:
    """Add a backend (``target`` is ``"package.module:Class"``)."""
    BACKENDS[(robot, backend)] = target


def backends_of(robot: str) -> list[str]:
    return sorted(b for r, b in BACKENDS if r == robot)


def robots() -> list[str]:
    return sorted({r for r, _ in BACKENDS})


def resolve(robot: str, backend: str) -> type[Driver]:
    key = (robot, backend)
    if key not in BACKENDS:
        if robot not in robots():
            raise ConfigError(None, [("robot", f"unknown robot {robot!r}; known: {robots()}")])
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
