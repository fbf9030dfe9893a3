"""The controller node on unhealthy states and late plans: nothing is planned from a state
that is not ok (realtime: nothing sent), and a late plan's fallback is the command the robot
holds or the shifted last plan, never a normalized zero (the middle of a position robot's
range)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.schemas import Command, RobotState, SpecMsg, decode
from hilstack.control.controller_node import ControllerNode
from tests.helpers import wait_for

RIG = "unhealthy_ctl"
PERIOD_S = 0.02
#: a position robot: targets in [0, 2] rad, so the normalized zero is 1.0 rad; it holds 0.2
SPEC = {"name": "pos", "period_s": PERIOD_S,
        "state": {"names": ["q0", "q1"], "units": ["rad", "rad"], "low": [0.0, 0.0], "high": [2.0, 2.0]},
        "action": {"names": ["q0_cmd", "q1_cmd"], "units": ["rad", "rad"], "low": [0.0, 0.0], "high": [2.0, 2.0]},
        "action_rate_per_s": [1.0, 1.0], "safe_action": None}
HELD = [0.2, 0.3]


class FakeDriverNode:
    """Publishes the spec and a state every period (a driver node's stream); a state is not ok
    (and NaN) while ``bad(k)`` for its index k. ``lockstep``: the next state waits for the
    command answering the last one. Every command is kept with the state it answered."""

    def __init__(self, bus, bad, lockstep: bool = False, spec: dict | None = None, held=None):
        self.node = Node("driver-pos", RIG, bus, handle_signals=False)
        self.spec = self.node.publisher(keys.spec(RIG, "pos"), SpecMsg, reliable=True)
        self.state = self.node.publisher(keys.state(RIG, "pos"), RobotState, reliable=True)
        self.cmd = self.node.subscribe(keys.cmd(RIG, "pos"), Command, latest=False, capacity=4096)
        self.bad, self.lockstep = bad, lockstep
        self.spec_dict, self.held = spec or SPEC, list(held or HELD)
        self.sent: dict[int, RobotState] = {}  # seq -> state
        self.answers: list[Command] = []
        self.stop = threading.Event()
        self.th = threading.Thread(target=self._run, daemon=True)
        self.th.start()

    def _run(self) -> None:
        k, spec_t = 0, 0.0
        while not self.stop.is_set():
            if time.monotonic() - spec_t > 0.2:
                self.spec.put(SpecMsg(robot="pos", spec=self.spec_dict))
                spec_t = time.monotonic()
            ok = not self.bad(k)
            m = self.state.put(RobotState(robot="pos", t_s=k * PERIOD_S, state=[0.2, 0.3] if ok else [np.nan] * 2,
                                          ok=ok, active=True, action=list(self.held)))
            self.sent[m.seq] = m
            if self.lockstep:  # k counts answered states: unanswered ones are sent again after 1 s
                deadline = time.monotonic() + 1.0
                while not self.stop.is_set() and time.monotonic() < deadline:
                    c = self.cmd.wait(0.05)
                    if c is not None:
                        self.answers.append(c)
                        if c.state_seq >= m.seq:
                            k += 1
                            break
            else:
                k += 1
                self.stop.wait(PERIOD_S)
                self.answers += [decode(p, Command) for _, p in self.cmd.drain()]

    def close(self) -> None:
        self.stop.set()
        self.th.join(5)
        self.node.close()


class Planner:
    """Records what it plans from; the first call is late (``first_sleep_s``)."""

    def __init__(self, first_sleep_s: float = 0.0):
        self.seen: list[np.ndarray] = []
        self.first_sleep_s = first_sleep_s
        self.last_plan = None

    def __call__(self, s):
        self.seen.append(np.asarray(s).copy())
        if len(self.seen) == 1:
            time.sleep(self.first_sleep_s)
        return np.array([0.5, 0.5])


def test_realtime_plans_and_sends_nothing_for_a_state_that_is_not_ok(bus):
    drv = FakeDriverNode(bus, bad=lambda k: 40 <= k < 60)
    try:
        with ControllerNode(RIG, "pos", bus, handle_signals=False, state_timeout_s=10) as ctl:
            ctl.wait_ready(20)
            wait_for(lambda: ctl._state.poll() is not None, 10, "states")
            pol = Planner()
            log = ctl.run_realtime(pol, 80)
        time.sleep(0.1)
    finally:
        drv.close()
    bad_seqs = {seq for seq, m in drv.sent.items() if not m.ok}
    assert bad_seqs
    assert all(np.all(np.isfinite(x)) for x in pol.seen)  # never planned from a not-ok state
    assert not [c.state_seq for c in drv.answers if c.state_seq in bad_seqs]  # nor answered one
    assert all(np.all(np.isfinite(x)) for x in log.states[:-1])
    assert log.unhealthy_states >= 5


def test_a_late_first_plan_sends_the_held_command_not_a_normalized_zero(bus):
    """The first plan misses its deadline and there is no earlier plan to shift: the node sent
    normalized zeros, 1.0 rad here, a jump of 0.8 rad for a robot holding 0.2."""
    drv = FakeDriverNode(bus, bad=lambda k: False)
    try:
        with ControllerNode(RIG, "pos", bus, handle_signals=False, state_timeout_s=10) as ctl:
            ctl.wait_ready(20)
            wait_for(lambda: ctl._state.poll() is not None, 10, "states")
            log = ctl.run_realtime(Planner(first_sleep_s=4 * PERIOD_S), 12)
    finally:
        drv.close()
    assert log.late_plans >= 2
    late = [a for a in log.actions if not np.allclose(a, [1.0, 1.0])]  # 0.5 normalized is 1.5 rad
    np.testing.assert_allclose(log.actions[0], HELD, atol=1e-9)
    assert all(np.allclose(a, HELD) or np.allclose(a, [1.5, 1.5]) for a in late)
    assert not any(np.allclose(a, [1.0, 1.0]) for a in log.actions)


def test_a_late_first_plan_stops_a_velocity_robot_with_its_safe_action(bus):
    """A velocity robot whose range is not symmetric (leg speeds in [-1, 3]: the normalized zero
    is 1.0, not a stop), moving at 2.5: with no plan to shift, the node sends the spec's safe
    action, what ``stop()`` holds, not the normalized zero and not the speed it was running."""
    spec = {**SPEC, "action": {**SPEC["action"], "low": [-1.0, -1.0], "high": [3.0, 3.0]},
            "safe_action": [0.0, 0.0]}
    drv = FakeDriverNode(bus, bad=lambda k: False, spec=spec, held=[2.5, 2.5])
    try:
        with ControllerNode(RIG, "pos", bus, handle_signals=False, state_timeout_s=10) as ctl:
            ctl.wait_ready(20)
            wait_for(lambda: ctl._state.poll() is not None, 10, "states")
            log = ctl.run_realtime(Planner(first_sleep_s=4 * PERIOD_S), 12)
    finally:
        drv.close()
    assert log.late_plans >= 2
    np.testing.assert_allclose(log.actions[0], [0.0, 0.0], atol=1e-9)
    # the plan's 0.5 (normalized) is 2.0; everything else sent is the safe action
    assert all(np.allclose(a, [0.0, 0.0]) or np.allclose(a, [2.0, 2.0]) for a in log.actions)


def test_lockstep_answers_a_not_ok_state_with_the_held_command_without_planning(bus):
    drv = FakeDriverNode(bus, bad=lambda k: 5 <= k < 9, lockstep=True)
    try:
        with ControllerNode(RIG, "pos", bus, handle_signals=False, state_timeout_s=10) as ctl:
            ctl.wait_ready(20)
            pol = Planner()
            log = ctl.run_lockstep(pol, 15)
    finally:
        drv.close()
    assert all(np.all(np.isfinite(x)) for x in pol.seen)
    for c in drv.answers:
        m = drv.sent.get(c.state_seq)
        if m is not None and not m.ok:
            assert c.action == pytest.approx(HELD)  # a position robot: its stop holds its target
    # (a state answered after the fake's 1 s re-send, on a loaded machine, counts twice)
    assert log.unhealthy_states >= 4 and len(pol.seen) + log.unhealthy_states == 15


def test_late_plans_on_the_hand_sim_hold_its_targets(bus, spawn, tmp_path):
    """The simulated Shadow Hand (position control) on the wall clock behind its driver node
    (`hil up`), with a planner whose first plan is late: the node sends the hand's held targets
    while it waits, and the hand's applied targets do not move towards the middle of the joint
    ranges (the normalized zero it was sent before)."""
    rig = tmp_path / "hand_rt.yaml"
    rig.write_text("name: hand_rt\nrobots:\n  hand: {config: shadow_hand, backend: sim}\n"
                   "watchdog_periods: 3\npace: realtime\n")
    spawn("up", str(rig), "--endpoint", bus.endpoint)
    with ControllerNode("hand_rt", "hand", bus, handle_signals=False, state_timeout_s=20) as ctl:
        spec = ctl.wait_ready(60)
        wait_for(lambda: ctl._state.poll() is not None, 30, "states")
        held = np.asarray(ctl.next_state().action)
        held_norm = ctl.spec.action.normalize(held)
        assert np.abs(held_norm).max() > 0.3  # the hold pose is far from the middle of the ranges

        class LatePlanner:
            calls = 0

            def __call__(self, s):
                self.calls += 1
                if self.calls == 1:
                    time.sleep(5 * spec.period_s)
                return held_norm  # then: hold where it is

        log = ctl.run_realtime(LatePlanner(), 8)
        after = ctl.next_state()
    assert log.late_plans >= 3
    for a in log.actions:
        np.testing.assert_allclose(a, held, atol=1e-6)
    np.testing.assert_allclose(after.action, held, atol=1e-6)  # applied: the hand kept its targets
