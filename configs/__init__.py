"""YAML configs (robots/, rigs/, tasks/) and their validated schemas.

``load_robot("pointmass")`` finds ``configs/robots/pointmass.yaml``; any path works too.
Errors are :class:`ConfigError` naming the file, the field and what was expected.
"""

from hilstack.configs.schema import (
    BusConfig,
    ConfigError,
    Params,
    RigConfig,
    RobotConfig,
    TaskConfig,
    config_path,
    load_rig,
    load_robot,
    load_task,
    load_yaml_model,
    parse_model,
    parse_params,
)

__all__ = [
    "BusConfig",
    "ConfigError",
    "Params",
    "RigConfig",
    "RobotConfig",
    "TaskConfig",
    "config_path",
    "load_rig",
    "load_robot",
    "load_task",
    "load_yaml_model",
    "parse_model",
    "parse_params",
]
