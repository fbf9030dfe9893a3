"""The time model: one driver-node step, ordered by the driver's pacing (drivers/base.py: Pacing).

Measured through the bus, the way a controller sees it: a command sent in answer to the
state of period k is first carried (``RobotState.action``, the command held during the
period that ended with the state) by the state of period k + 1 + delay. The delay must be
the pacing's ``command_delay_periods`` on a sim backend and on an emulated one, and what
the MPC is told (``learning/mbrl.py: command_delay_steps``).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from hilstack.drivers.base import Pacing


def _measured_delay(rig_name: str, bus) -> tuple[int, Pacing]:
    from hilstack.configs.schema import load_rig, rig_robot_config
    from hilstack.control.controller_node import ControllerNode
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver

    rig = load_rig(rig_name)
    drv = make_driver(rig_robot_config(rig, "roach"))
    node = DriverNode(drv, rig.name, "roach", bus, handle_signals=False, estop_sync_s=0.05, watchdog_periods=100)
    try:
        with ControllerNode(rig.name, "roach", bus, handle_signals=False, state_timeout_s=10) as ctl:
            drv.configure()
            drv.activate()
            drv.stop()
            node.publish_spec()
            ctl.wait_ready(10)
            # settle: states flow and are ok (an emulated pose arrives after a few periods),
            # the robot holds its safe action (zero leg speeds)
            period = drv.spec.period_s
            for _ in range(200):
                node.step()
                time.sleep(period)
                if node._ok_run >= 5 and not node.unhealthy:
                    break
            assert not node.unhealthy, node.stats.last_unhealthy
            s = ctl.next_state(timeout_s=5)
            while (m := ctl._state.poll()) is not None:  # the newest state: the one answered
                s = m
            answered = s.seq
            ctl.send(np.array([0.4, 0.4]), answered)
            time.sleep(0.3)  # the command reaches the node before its next step (no clock inside step)
            carried_at = None
            for _ in range(4):
                node.step()
                time.sleep(period)
                m = ctl.next_state(after_seq=s.seq, timeout_s=5)
                s = m
                if carried_at is None and m.action and m.action[0] > 1e-6:  # any of it (rate limited)
                    carried_at = m.seq
            assert carried_at is not None, "the command never reached a state"
            return carried_at - answered - 1, drv.pacing
    finally:
        try:
            drv.cleanup()
        finally:
            node.close()


@pytest.mark.parametrize("rig_name", ["roach_sim", "roach_emulated"])
def test_command_delay_is_the_pacings(rig_name, rig_bus):
    from hilstack.configs.schema import load_rig
    from hilstack.learning.mbrl import command_delay_steps

    delay, pacing = _measured_delay(rig_name, rig_bus(rig_name))
    assert pacing is (Pacing.STEPPED if rig_name == "roach_sim" else Pacing.WALL_CLOCK)
    assert delay == pacing.command_delay_periods
    assert command_delay_steps(load_rig(rig_name), "roach") == delay


def test_pacing_of_each_backend_kind():
    assert Pacing.of_backend("sim") is Pacing.STEPPED
    for b in ("real", "emulated"):
        p = Pacing.of_backend(b)
        assert p is Pacing.WALL_CLOCK and p.read_before_apply and p.command_delay_periods == 1
    assert not Pacing.STEPPED.read_before_apply and Pacing.STEPPED.command_delay_periods == 0
