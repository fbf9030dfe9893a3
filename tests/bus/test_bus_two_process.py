"""The bus across processes: a driver node (`hil up`) in a subprocess, this test as controller."""

from __future__ import annotations

import math

import pytest

from hilstack.bus import keys
from hilstack.bus.node import Node, alive_nodes
from hilstack.bus.schemas import Command, EStop, RobotState
from tests.helpers import wait_for

RIG = "pointmass_sim"
PERIOD_S = 0.02  # configs/robots/pointmass.yaml


@pytest.fixture
def rig(bus, spawn):
    proc = spawn("up", RIG, "--endpoint", bus.endpoint)
    node = Node("test-ctl", RIG, bus, handle_signals=False)
    state = node.subscribe(keys.state(RIG, "pm"), RobotState, latest=False)
    cmd = node.publisher(keys.cmd(RIG, "pm"), Command)
    estop = node.publisher(keys.estop(RIG), EStop)
    wait_for(lambda: _states(state), 20, "first state from the driver node")
    yield node, state, cmd, estop, proc
    node.close()


def _states(sub) -> list[RobotState]:
    from hilstack.bus.schemas import decode

    return [decode(p, RobotState) for _, p in sub.drain()]


def _collect(sub, until, timeout_s=30.0) -> list[RobotState]:
    got: list[RobotState] = []

    def cond():
        got.extend(_states(sub))
        return until(got)

    wait_for(cond, timeout_s, "states")
    return got


def _drive_until_held(sub, cmd, action, timeout_s=20.0) -> list[RobotState]:
    """Send ``action`` (again at each poll) until a state holding it arrives; the states seen
    up to and including that one.

    A condition, not a count: under load the test may be descheduled for longer than the
    driver's 3-period watchdog, so the states drained right after a send can be ones published
    while the robot was (correctly) stopped as stale, before the new command reached it."""
    got: list[RobotState] = []

    def holds(s: RobotState) -> bool:
        return s.action == pytest.approx(list(action)) and s.stopped_reason == ""

    def cond():
        cmd.put(Command(robot="pm", action=list(action)))
        got.extend(_states(sub))
        return any(holds(s) for s in got)

    wait_for(cond, timeout_s, f"a state holding {action}")
    return got[: next(i for i, s in enumerate(got) if holds(s)) + 1]


def test_typed_messages_both_ways_and_motion(rig):
    node, state, cmd, _, _ = rig
    seen: list[RobotState] = []
    for _ in range(30):
        cmd.put(Command(robot="pm", action=[2.0, 0.0]))
        seen += _collect(state, lambda g: len(g) >= 1)
    seen += _drive_until_held(state, cmd, [2.0, 0.0])
    last = seen[-1]
    assert last.robot == "pm" and last.active and last.stopped_reason == ""
    assert last.state[0] > 0.05  # pushed along +x
    assert last.action == pytest.approx([2.0, 0.0])
    seqs = [s.seq for s in seen]
    assert seqs == sorted(seqs)


def test_liveliness_appears_and_disappears(rig):
    node, _, _, _, proc = rig
    assert "driver-pm" in alive_nodes(node.session, RIG)
    assert proc.stop() == 0  # SIGTERM: clean shutdown
    wait_for(lambda: "driver-pm" not in alive_nodes(node.session, RIG, 0.5), 10, "token gone")


def test_estop_stops_within_two_periods_and_latches(rig):
    node, state, cmd, estop, _ = rig
    release = node.publisher(keys.estop_release(RIG, node.user), EStop)
    for _ in range(10):
        cmd.put(Command(robot="pm", action=[2.0, 0.0]))
        _collect(state, lambda g: len(g) >= 1)
    _states(state)
    estop.put(EStop(reason="test"))
    got = _collect(state, lambda g: any(s.stopped_reason == "estop" for s in g))
    first = next(i for i, s in enumerate(got) if s.stopped_reason == "estop")
    assert first <= 2, f"e-stop took {first + 1} periods"
    assert not got[first].active and got[first].action == [0.0, 0.0]
    # latched: commands are ignored until released
    for _ in range(5):
        cmd.put(Command(robot="pm", action=[2.0, 0.0]))
        after = _collect(state, lambda g: len(g) >= 1)
    assert after[-1].stopped_reason == "estop" and after[-1].action == [0.0, 0.0]
    release.put(EStop(engaged=False))
    _collect(state, lambda g: any(s.active for s in g))
    cmd.put(Command(robot="pm", action=[1.0, 0.0]))
    _collect(state, lambda g: any(s.action and s.action[0] > 0 for s in g))


def test_stale_commands_stop_the_robot(rig):
    _, state, cmd, _, _ = rig
    for _ in range(10):
        cmd.put(Command(robot="pm", action=[2.0, 0.0]))
        _collect(state, lambda g: len(g) >= 1)
    _states(state)
    # stop sending: the watchdog (3 periods) must hold the safe action
    got = _collect(state, lambda g: any(s.stopped_reason == "stale" for s in g))
    first = next(i for i, s in enumerate(got) if s.stopped_reason == "stale")
    assert first <= 3 + 1
    assert got[first].action == [0.0, 0.0]
    assert got[-1].health["stale_stops"] >= 1


def test_malformed_and_invalid_commands_are_counted_not_fatal(rig):
    node, state, cmd, _, proc = rig
    node.session.put(keys.cmd(RIG, "pm"), b"\x00garbage\xff")
    _collect(state, lambda g: bool(g) and g[-1].health["bus_malformed"] >= 1)
    # (a latest-value queue keeps only the newest payload: send the next one separately)
    cmd.put(Command(robot="pm", action=[math.nan, 0.0]))
    got = _collect(state, lambda g: bool(g) and g[-1].health["commands_rejected"] >= 1)
    assert got[-1].action == [0.0, 0.0]
    # still alive and obeying (a condition: see _drive_until_held)
    got = _drive_until_held(state, cmd, [1.0, 0.0])
    assert got[-1].action == pytest.approx([1.0, 0.0]) and got[-1].active
    assert proc.p.poll() is None
