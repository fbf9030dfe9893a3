"""What code above the drivers asks the registry and the contract for, instead of importing a
robot: a robot's spec by name, its parts (skills), an in-process sim and its sim controls."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers import registry
from hilstack.drivers.base import RobotSpec, Space, perturbable, sim_controls
from tests.helpers import ROOT


def test_every_entry_point_in_the_source_tree_is_found_without_a_reinstall():
    """A robot added to pyproject.toml is found at once from a checkout (the editable install's
    metadata lags until pip install -e . runs again)."""
    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    for group in (registry.GROUP, registry.SKILLS, "hilstack.emulators"):
        assert eps[group].items() <= registry.entry_point_map(group).items(), group
    assert ("pan_unit", "emulated") in registry.BACKENDS


def test_spec_of_gives_a_robots_constants_by_name():
    from hilstack.drivers.shadow_hand.config import JOINT_NAMES, hold_pose_action

    spec = registry.spec_of("shadow_hand")
    assert spec.joint_names() == list(JOINT_NAMES)
    np.testing.assert_allclose(spec.home_action, hold_pose_action())
    assert spec.to_dict()["home_action"] == pytest.approx(list(hold_pose_action()))
    assert registry.spec_of("pan_unit").home_action is None  # a robot without a home pose


def test_home_action_must_fit_the_action_space():
    with pytest.raises(ValueError, match="home_action has 2 entries, action space has 1"):
        RobotSpec(name="x", state=Space.build([("q", "rad", -1, 1)]), action=Space.build([("a", "rad", -1, 1)]),
                  period_s=0.1, home_action=np.zeros(2))


def test_skill_finds_a_robots_part_and_names_what_is_missing():
    assert hasattr(registry.skill("reset_arm", "pick_place"), "PickPlaceScript")
    with pytest.raises(ConfigError, match="robot 'pan_unit' provides no 'kinematics'"):
        registry.skill("pan_unit", "kinematics")


def test_sim_controls_are_a_declared_capability_of_sim_backends_only():
    sim = registry.make_backend("velociroach", "sim", sim={"seed": 3})
    assert sim_controls(sim) is sim and perturbable(sim) is sim
    real = registry.make_backend("velociroach", "real")
    assert sim_controls(real) is None and perturbable(real) is None
    arm = registry.make_backend("pan_unit", "sim")
    assert sim_controls(arm) is arm and perturbable(arm) is None  # no perturbations modelled
    sim.configure()
    sim.activate()
    sim_controls(sim).reset(x=0.2, y=-0.1, yaw=0.0)
    np.testing.assert_allclose(sim.read().state[:2], [0.2, -0.1], atol=0.01)
    sim.cleanup()


def test_every_backend_is_built_from_its_config_by_the_one_from_config():
    """``Driver.from_config`` is written once: each registered class names its params model
    (``params_type``) and gets its config's backend kind, source file and parsed params; a
    bad value is a ConfigError naming the file and ``params.<field>``; a class without a
    params model says so."""
    from hilstack.configs.schema import load_robot
    from hilstack.drivers.base import Driver

    for robot, backend in sorted(registry.BACKENDS):
        cls = registry.resolve(robot, backend)
        assert "from_config" not in cls.__dict__, f"{cls.__name__} writes its own from_config"
        cfg = load_robot(robot, backend=backend)
        d = cls.from_config(cfg)
        assert isinstance(d.params, cls.params_type) and d.backend == backend, (robot, backend)
        assert str(d.source) == str(cfg.source), (robot, backend)
    with pytest.raises(ConfigError, match=r"pan_unit\.yaml.*params\.pan_rate_rad_s"):
        registry.make_driver("pan_unit", "emulated", pan_rate_rad_s=float("nan"))

    class NoParams(Driver):
        _read = _write = _stop = None

    with pytest.raises(TypeError, match="NoParams cannot be built from a config: it sets no params_type"):
        NoParams.from_config(load_robot("pan_unit"))
