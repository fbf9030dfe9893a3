"""Every robot's ``params.emulator`` is typed on the shared base (hilstack.configs.schema.EmulatorParams):
a misspelt fault option is a one-line config error naming the field, before anything starts."""

from __future__ import annotations

import pytest

from hilstack.configs.schema import ConfigError, EmulatorParams
from hilstack.drivers.dynamixel.params import DynamixelEmulatorParams
from hilstack.drivers.registry import make_driver
from hilstack.drivers.sawyer.config import SawyerParams
from hilstack.drivers.shadow_hand.config import HandEmulatorParams, ShadowHandParams
from hilstack.drivers.velociroach.config import VelociRoachEmulatorParams, VelociRoachParams
from hilstack.drivers.widowx.config import MechanismParams, WidowXParams

#: robot config → a typo of one of its emulator's real options
TYPOS = {
    "velociroach": "corupt_every",
    "shadow_hand": "bus_of_after_s",
    "widowx": "missing_id",
    "reset_mechanism": "hardware_error",
    "sawyer": "keep_logs",
}


@pytest.mark.parametrize("robot,typo", sorted(TYPOS.items()))
def test_a_misspelt_emulator_option_is_refused_naming_it(robot, typo):
    with pytest.raises(ConfigError) as e:
        make_driver(robot, backend="emulated", emulator={typo: 1})
    msg = str(e.value)
    assert f"params.emulator.{typo}: unknown field" in msg
    assert f"configs/robots/{robot}.yaml" in msg
    # one problem, on one line below the header
    assert len(e.value.problems) == 1


@pytest.mark.parametrize("robot,field,bad", [
    ("widowx", "hardware_errors", {"6": "overheating"}),
    ("widowx", "corrupt_every", -1),
    ("shadow_hand", "drop_every", "often"),
    ("sawyer", "start_timeout_s", 0),
    ("velociroach", "keep_log", "maybe"),
])
def test_a_bad_emulator_value_is_refused_naming_the_field(robot, field, bad):
    with pytest.raises(ConfigError, match=rf"params\.emulator\.{field}"):
        make_driver(robot, backend="emulated", emulator={field: bad})


@pytest.mark.parametrize("params,emulator", [
    (VelociRoachParams, VelociRoachEmulatorParams), (ShadowHandParams, HandEmulatorParams),
    (WidowXParams, DynamixelEmulatorParams), (MechanismParams, DynamixelEmulatorParams),
    (SawyerParams, EmulatorParams),
])
def test_every_robot_uses_the_shared_base(params, emulator):
    field = params.model_fields["emulator"]
    assert field.annotation is emulator
    assert issubclass(emulator, EmulatorParams)
    e = params().emulator
    assert (e.start_timeout_s, e.keep_log) == (30.0, False)


def test_typed_options_reach_their_type():
    p = WidowXParams(emulator={"hardware_errors": {"6": 4}, "missing_ids": [4], "keep_log": True})
    assert p.emulator.hardware_errors == {6: 4}
    assert p.emulator.missing_ids == [4]
    assert p.emulator.keep_log is True
