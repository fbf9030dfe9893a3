"""The realtime hand rig (configs/rigs/hand_emulated_arm.yaml) resets itself through the
arm on the bus: the real CAN driver over SLCAN to the hand's firmware emulator process,
whose scene holds the ramp and the arm; the arm's real UDP driver to its controller in
that process; driver nodes on the wall clock, the reset supervisor and a controller.

About 30 s of wall clock: the pick-and-place of two balls takes that long in real time."""

from __future__ import annotations

import copy
import threading
from pathlib import Path

import numpy as np
import yaml

from hilstack.bus.session import open_session
from hilstack.configs.schema import RigConfig, parse_model, rig_robot_config
from hilstack.control.controller_node import ControllerNode
from hilstack.control.reset.config import load_reset
from hilstack.control.reset.supervisor import ResetSupervisor
from hilstack.drivers.bridge import DriverNode
from hilstack.drivers.registry import make_driver
from tests.helpers import free_port
from tests.reset.test_hand_arm import tip_the_palm

RIG = Path(__file__).resolve().parents[2] / "configs" / "rigs" / "hand_emulated_arm.yaml"


def rig_config() -> RigConfig:
    data = yaml.safe_load(RIG.read_text())
    port = free_port()  # a UDP port for the arm controller; parallel runs do not collide
    data["robots"]["hand"]["params"]["emulator"]["arm_port"] = port
    data["robots"]["arm"]["params"]["port"] = port
    return parse_model(RigConfig, copy.deepcopy(data), RIG)


def test_the_emulated_hand_resets_itself_through_the_arm_on_the_wall_clock(rig_bus):
    rig = rig_config()
    bus = rig_bus(str(RIG))  # its access control: both driver nodes share the rig's router, as in `hil up`
    router = open_session(bus, server=True, rig=rig.name, robots=["hand", "arm"])
    nodes, threads = [], []
    sup = ctl = None
    try:
        for name in ("hand", "arm"):  # the hand's driver starts the emulator the arm talks to
            node = DriverNode(make_driver(rig_robot_config(rig, name)), rig.name, name, bus, pace="realtime",
                              handle_signals=False, estop_sync_s=0.3, session=router)
            th = threading.Thread(target=node.serve, daemon=True, name=f"driver-{name}")
            th.start()
            nodes.append(node)
            threads.append(th)
            if name == "hand":
                ctl = ControllerNode(rig.name, "hand", bus, handle_signals=False, state_timeout_s=30)
                ctl.wait_ready(60)
        sup = ResetSupervisor(rig.name, load_reset(rig), bus, handle_signals=False)
        sup.wait_ready(60)
        def spin():
            while not sup.stop_event.is_set():
                sup.spin_once()

        threading.Thread(target=spin, daemon=True, name="supervisor").start()
        ctl.run_realtime(tip_the_palm(), 60, stop_if=lambda _x: sup.state != "running")
        assert sup.history and sup.history[0].dest == "episode_end", [t.dest for t in sup.history]
        assert "drop: ball" in sup.history[0].reason
        first = ctl.reset(timeout_s=150)
        assert first.episode == 1
        assert [t.dest for t in sup.history] == ["episode_end", "paused", "resetting", "verifying", "resumed",
                                                 "running"]
        assert sup.stats["completed"] == 1 and sup.stats["failed"] == 0
        balls = np.asarray(sup.links["arm"].state().state[15:21]).reshape(2, 3)
        palm = sup.steps[0].script.center  # the rig's palm_center_m: both balls are back in the palm
        assert np.all(np.linalg.norm(balls - palm, axis=1) < 0.06)
        # the arm put back what fell: on the wall clock the episode ends at the first drop, and the
        # ball nestled deeper in the palm may stay there (one pick) or follow it (two)
        assert sup.steps[0].script.log.count("release") in (1, 2)
    finally:
        if ctl is not None:
            ctl.close()
        if sup is not None:
            sup.stop_event.set()
            sup.close()
        for node, th in zip(reversed(nodes), reversed(threads), strict=True):
            node.stop_event.set()
            th.join(15)
            node.close()
        router.close()
