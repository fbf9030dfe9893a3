"""YAML configs (robots/, rigs/, tasks/) and their validated schemas.

``load_robot("pointmass")`` finds ``configs/robots/pointmass.yaml``; any path works too.
Errors are :class:`ConfigError` naming the file, the field and what was expected.
"""

from configs.schema import (
    BusConfig,
    ConfigError,
    RigConfig,
    RobotConfig,
    TaskConfig,
    config_path,
    load_rig,
    load_robot,
    load_task,
    load_yaml_model,
    parse_model,
)

__all__ = [
    "BusConfig",
    "ConfigError",
    "RigConfig",
    "RobotConfig",
    "TaskConfig",
    "config_path",
    "load_rig",
    "load_robot",
    "load_task",
    "load_yaml_model",
    "parse_model",
]
