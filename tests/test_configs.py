"""Config errors name the file, the field and what was expected."""

from __future__ import annotations

import pytest

from hilstack.configs.schema import ConfigError, load_rig, load_robot
from hilstack.drivers.registry import make_driver


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_shipped_configs_load():
    assert load_robot("pointmass").robot == "pointmass"
    rig = load_rig("pointmass_sim")
    assert "pm" in rig.robots and rig.watchdog_periods == 3


def test_unknown_backend_names_file_and_field(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: pointmass\nbackend: hardware\n")
    with pytest.raises(ConfigError) as e:
        load_robot(p)
    msg = str(e.value)
    assert str(p) in msg and "backend" in msg and "'real', 'emulated' or 'sim'" in msg


def test_bad_robot_param_names_params_field(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: pointmass\nparams:\n  mass_kg: -1\n")
    with pytest.raises(ConfigError) as e:
        make_driver(load_robot(p))
    assert str(p) in str(e.value) and "params.mass_kg" in str(e.value) and "greater than 0" in str(e.value)
    p = _write(tmp_path, "r2.yaml", "robot: pointmass\nparams:\n  mas_kg: 1\n")
    with pytest.raises(ConfigError, match="params.mas_kg"):
        make_driver(load_robot(p))


def test_unknown_robot_and_missing_backend(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: teapot\n")
    with pytest.raises(ConfigError, match="unknown robot 'teapot'"):
        make_driver(load_robot(p))
    p = _write(tmp_path, "r.yaml", "robot: pointmass\nbackend: real\n")
    with pytest.raises(ConfigError, match="no 'real' backend"):
        make_driver(load_robot(p))


def test_rig_errors(tmp_path):
    p = _write(tmp_path, "rig.yaml", "name: bad name\nrobots: {}\nbus:\n  endpoint: localhost\n  colour: red\n")
    with pytest.raises(ConfigError) as e:
        load_rig(p)
    msg = str(e.value)
    assert "name" in msg and "bus.endpoint" in msg and "tcp/127.0.0.1:7447" in msg and "bus.colour" in msg


def test_yaml_syntax_error_has_line(tmp_path):
    p = _write(tmp_path, "r.yaml", "robot: [pointmass\n")
    with pytest.raises(ConfigError, match=r"line \d+"):
        load_robot(p)


def test_unknown_config_name_lists_known():
    with pytest.raises(ConfigError, match="pointmass"):
        load_robot("no_such_robot")
