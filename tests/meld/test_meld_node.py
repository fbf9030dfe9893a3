"""MELD's controller node on the emulated WidowX rig (the real Dynamixel drivers over a virtual
link to the bench's emulator process), the task set by the task-reset mechanism.

Robust on loaded cores: every wait is on a condition with a bound (learning/meld/node.py:
meld_rig), and nothing asserts wall-clock timing; what the driver held is read from the states
the controller acted on, not from a state fetched after the episode (which may already show
the stop)."""

import math

import numpy as np
import pytest

from hilstack.learning.meld.agents import AgentConfig, MeldAgent
from hilstack.learning.meld.model import LatentConfig
from hilstack.learning.meld.node import meld_rig
from hilstack.tools.meld_tasks import BenchView

RIG = "arm_widowx_emulated"


def test_meld_node_commands_the_emulated_rig_and_the_mechanism_moves_the_task(rig_bus):
    import torch

    torch.manual_seed(0)
    agent = MeldAgent(AgentConfig(latent=LatentConfig(image_hw=(16, 32), action_dim=6, channels=(16, 32))))
    view = BenchView(camera_px=16)
    steps = 2
    try:
        # the rig's bus with its access control: the controller logs in as operator
        with meld_rig(RIG, rig_bus(RIG), agent, view, bus_name="t_meld_node") as ctl:
            goals = []
            for target in ([-math.radians(8), -0.01], [math.radians(8), 0.01]):
                pose = ctl.set_task(np.array(target), tol=np.array([0.01, 0.001]), timeout_s=30.0)
                assert pose == pytest.approx(target, abs=0.011)
                ep = ctl.episode(steps=steps)
                goals.append(ep["infos"][0])
                assert len(ep["inference_s"]) == steps and ep["commands"] == steps * ctl.hold
                # each action is held for `hold` driver periods (more when states come late, never fewer)
                assert np.all(np.diff(ep["state_seq"]) >= ctl.hold), ep["state_seq"]
                # the driver applied MELD's commands: at the end of each hold the state reports the
                # command it holds, each joint MELD's or zero (the joint-limit guard stops motion into
                # a limit: the sleep pose rests on limits; a watchdog stop on a starved core holds
                # zero), and MELD's on most joints for at least one action of the episode
                ours_held = []
                for held, ours in zip(ep["held"], ep["actions"], strict=True):
                    assert np.all(np.isclose(held, ours, atol=1e-6) | (held == 0.0)), (held, ours)
                    ours_held.append(np.isclose(held, ours, atol=1e-6).sum() >= 4)
                assert any(ours_held), (ep["held"], ep["actions"])
                assert agent.task_features().shape == (steps, 32)  # the belief was filtered on every image
            # the mechanism moved the task between the episodes: the port turned 16° and slid 2 cm
            first, second = goals
            assert first["position_m"] != pytest.approx(second["position_m"], abs=1e-4)
            u = [np.array([math.cos(t), math.sin(t)]) for t in (-math.radians(8), math.radians(8))]
            assert math.degrees(math.acos(float(u[0] @ u[1]))) == pytest.approx(16.0)
    finally:
        view.close()


def test_meld_rig_names_the_driver_that_failed(rig_bus, monkeypatch):
    """A driver node whose serve fails: the rig's bring-up says which robot and why in one line,
    instead of the controller's state timeout that follows."""
    from hilstack.drivers.bridge import DriverNode

    def serve(self, *a, **kw):
        if self.robot == "mechanism":
            raise RuntimeError("link down")
        self.stop_event.wait(30.0)  # the arm's node stays up (without starting its emulator: a short test)

    monkeypatch.setattr(DriverNode, "serve", serve)
    agent = MeldAgent(AgentConfig(latent=LatentConfig(image_hw=(16, 32), action_dim=6, channels=(16, 32))))
    with pytest.raises(RuntimeError, match="rig arm_widowx_emulated: mechanism failed: RuntimeError: link down") as e:
        with meld_rig(RIG, rig_bus(RIG), agent, lambda q, m: None, bus_name="t_meld_fail", ready_timeout_s=20.0):
            pass
    # the wait ended on the failure, not on the readiness timeout
    assert "a driver node failed" in str(e.value.__cause__)
