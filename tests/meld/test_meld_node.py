"""MELD's controller node on the emulated WidowX rig (the real Dynamixel drivers over a virtual
link to the bench's emulator process), the task set by the task-reset mechanism."""

import math
import threading

import numpy as np
import pytest

from hilstack.bus.session import open_session
from hilstack.drivers.bridge import DriverNode
from hilstack.drivers.registry import make_driver
from hilstack.learning.meld.agents import AgentConfig, MeldAgent
from hilstack.learning.meld.model import LatentConfig
from hilstack.learning.meld.node import MeldRigController
from hilstack.tools.meld_tasks import BenchView


def test_meld_node_commands_the_emulated_rig_and_the_mechanism_moves_the_task(rig_bus):
    import torch

    torch.manual_seed(0)
    rig = "arm_widowx_emulated"
    bus = rig_bus(rig)  # its access control: the controller logs in as operator
    # generous link timeouts: the 2 shared cores can starve the emulator process for a second
    drivers = {"arm": make_driver("widowx", backend="emulated", bus_name="t_meld_node", link_timeout_periods=100),
               "mechanism": make_driver("reset_mechanism", backend="emulated", bus_name="t_meld_node",
                                         link_timeout_periods=100)}
    # the rig's router: one server session its driver nodes share, as `hil up` runs them
    session = open_session(bus, server=True, rig=rig, robots=list(drivers))
    nodes = [DriverNode(d, rig, name, bus, handle_signals=False, session=session) for name, d in drivers.items()]
    threads = [threading.Thread(target=n.serve, daemon=True) for n in nodes]
    for th in threads:
        th.start()
    agent = MeldAgent(AgentConfig(latent=LatentConfig(image_hw=(16, 32), action_dim=6, channels=(16, 32))))
    view = BenchView(camera_px=16)
    try:
        with MeldRigController(rig, agent, view, bus, state_timeout_s=30.0) as ctl:
            ctl.wait_ready(timeout_s=60.0)
            goals = []
            for target in ([-math.radians(8), -0.01], [math.radians(8), 0.01]):
                pose = ctl.set_task(np.array(target), tol=np.array([0.01, 0.001]))
                assert pose == pytest.approx(target, abs=0.011)
                ep = ctl.episode(steps=3)
                goals.append(ep["infos"][0])
                # the driver applied MELD's commands: the state reports the held command, each joint
                # MELD's or zero (the driver's joint-limit guard stops motion into a limit)
                held, ours = np.asarray(ctl.arm.next_state().action), ep["actions"][-1]
                assert ep["commands"] == 3 * ctl.hold
                assert np.all(np.isclose(held, ours, atol=1e-6) | (held == 0.0)), (held, ours)
                assert np.isclose(held, ours, atol=1e-6).sum() >= 4
                assert len(ep["inference_s"]) == 3 and ep["policy_period_s"] == pytest.approx(0.3, abs=0.06)
                assert agent.task_features().shape == (3, 32)  # the belief was filtered on every image
            # the mechanism moved the task between the episodes: the port turned 16° and slid 2 cm
            first, second = goals
            assert first["position_m"] != pytest.approx(second["position_m"], abs=1e-4)
            u = [np.array([math.cos(t), math.sin(t)]) for t in (-math.radians(8), math.radians(8))]
            assert math.degrees(math.acos(float(u[0] @ u[1]))) == pytest.approx(16.0)
    finally:
        view.close()
        for n in nodes:
            n.stop_event.set()
        for th in threads:
            th.join(30)
        for n in nodes:
            n.close()
        session.close()
