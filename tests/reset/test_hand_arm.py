"""The Shadow Hand resets itself through its reset arm on the bus (lockstep sim rig
configs/rigs/hand_sim_arm.yaml): the hand and arm driver nodes, the reset supervisor and
a controller, each with its own Zenoh session, on real MuJoCo."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from configs.schema import load_rig, rig_robot_config
from control.controller_node import ControllerNode
from control.reset.config import load_reset
from control.reset.supervisor import ResetSupervisor
from drivers.bridge import DriverNode
from drivers.registry import make_driver
from drivers.shadow_hand.config import hold_pose_action

RIG = Path(__file__).resolve().parents[2] / "configs" / "rigs" / "hand_sim_arm.yaml"
FULL_CYCLE = ["episode_end", "paused", "resetting", "verifying", "resumed", "running"]


class HandArmRig:
    def __init__(self, bus, rig=None, **reset_overrides):
        rig = rig or load_rig(str(RIG))
        if reset_overrides:
            rig = rig.model_copy(update={"reset": {**rig.reset, **reset_overrides}})
        self.rig = rig
        self.nodes = {}
        self.threads = {}
        for name in ("hand", "arm"):  # the hand first: its scene holds the arm
            node = DriverNode(make_driver(rig_robot_config(rig, name)), rig.name, name, bus, pace="lockstep",
                              handle_signals=False, estop_sync_s=0.3, lockstep_timeout_s=1.0)
            th = threading.Thread(target=node.serve, daemon=True, name=f"driver-{name}")
            th.start()
            self.nodes[name], self.threads[name] = node, th
        self.sup = ResetSupervisor(rig.name, load_reset(rig), bus, handle_signals=False)
        self.sup.wait_ready(30)
        self._st = threading.Thread(target=self._spin, daemon=True, name="supervisor")
        self._st.start()
        self.ctl = ControllerNode(rig.name, "hand", bus, handle_signals=False, state_timeout_s=20)
        self.ctl.wait_ready(30)

    @property
    def hand(self):
        return self.nodes["hand"].driver

    def _spin(self):
        while not self.sup.stop_event.is_set():
            self.sup.spin_once()

    def dests(self) -> list[str]:
        return [t.dest for t in list(self.sup.history)]

    def knock_balls_off(self, v_m_s=((-0.6, 0.0, 0.3), (0.5, 0.0, 0.3))):
        """A disturbance: both balls pushed out of the palm (test setup), velocities [m/s, world]."""
        h = self.hand
        with h.world_lock:
            for v, dadr in zip(v_m_s, h.hand.ball_dof_adr, strict=True):
                h.data.qvel[dadr:dadr + 3] = v

    def stop_node(self, name):
        self.nodes[name].stop_event.set()
        self.threads[name].join(10)
        self.nodes[name].close()

    def close(self):
        self.ctl.close()
        self.sup.stop_event.set()
        self._st.join(10)
        self.sup.close()
        for name in ("arm", "hand"):
            if not self.nodes[name]._closed:
                self.stop_node(name)


@pytest.fixture
def hand_arm_rig(bus):
    rigs = []

    def start(**overrides):
        rigs.append(HandArmRig(bus, **overrides))
        return rigs[-1]

    yield start
    for r in rigs:
        r.close()


def hold(_x):
    return hold_pose_action()


def test_a_drop_ends_the_episode_and_the_arm_puts_both_balls_back_in_the_palm(hand_arm_rig):
    rig = hand_arm_rig()
    s = rig.ctl.next_state()
    rig.knock_balls_off()
    ended = []

    def stop(_x):
        ended.append(rig.sup.state)
        return rig.sup.state != "running"

    rig.ctl.run_lockstep(hold, 40, s, stop_if=stop)
    assert rig.sup.history and rig.sup.history[0].dest == "episode_end"
    assert "drop: ball" in rig.sup.history[0].reason
    first = rig.ctl.reset(timeout_s=120)
    assert first.episode == 1
    assert rig.dests() == FULL_CYCLE
    assert rig.sup.stats == {"requested": 1, "completed": 1, "failed": 0}
    balls = rig.hand.balls_m()
    center = rig.hand.task.center_m
    assert np.all(np.linalg.norm(balls - center, axis=1) < 0.06)
    assert not rig.hand.task.dropped(balls)
    # the arm really did it: it picked and placed two balls (no teleport on this rig)
    step = rig.sup.steps[0]
    assert step.script.log.count("release") == 2 and step.script.log[-1] == "park"
