"""The time model: one driver-node step, ordered by the driver's pacing (drivers/base.py: Pacing).

Measured through the bus, the way a controller sees it: a command sent in answer to the
state of period k is first carried (``RobotState.action``, the command held during the
period that ended with the state) by the state of period k + 1 + delay. The delay must be
the pacing's ``command_delay_periods`` on a sim backend and on an emulated one, and the
controller must read that pacing from the spec the driver node publishes (what the MPC is
told: ``ControllerNode.pacing``, ``MbrlRun.command_delay``).
"""

from __future__ import annotations

import threading
import time
import uuid

import numpy as np
import pytest

from hilstack.drivers.base import Pacing


def _measured_delay(rig_name: str, bus) -> tuple[int, Pacing, Pacing]:
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
            # the spec again until the controller has it: its subscription reaches the node's session
            # a moment after both exist, and a spec put before that is lost (on two xdist workers
            # beside a Baoding run, once: no spec in 10 s); the node itself repeats it only while it steps
            deadline = time.monotonic() + 10
            while True:
                node.publish_spec()
                try:
                    ctl.wait_ready(0.5)
                    break
                except TimeoutError:
                    if time.monotonic() > deadline:
                        raise
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
            return carried_at - answered - 1, drv.pacing, ctl.pacing
    finally:
        try:
            drv.cleanup()
        finally:
            node.close()


@pytest.mark.parametrize("rig_name", ["roach_sim", "roach_emulated"])
def test_command_delay_is_the_pacings(rig_name, rig_bus):
    delay, pacing, on_the_bus = _measured_delay(rig_name, rig_bus(rig_name))
    assert pacing is (Pacing.STEPPED if rig_name == "roach_sim" else Pacing.WALL_CLOCK)
    assert delay == pacing.command_delay_periods
    assert on_the_bus is pacing  # the controller learns it from the spec, not from the rig file


def test_pacing_of_each_backend_kind_and_pace():
    assert Pacing.of_backend("sim") is Pacing.STEPPED
    assert Pacing.of_backend("sim", "lockstep") is Pacing.LOCKSTEP
    for b in ("real", "emulated"):
        p = Pacing.of_backend(b)
        assert p is Pacing.WALL_CLOCK and p.read_before_apply and p.command_delay_periods == 1 and not p.stepped
        with pytest.raises(ValueError, match="lockstep.*needs a sim"):
            Pacing.of_backend(b, "lockstep")
    assert Pacing.of_backend("sim", "lockstep", follower=True) is Pacing.FOLLOWER
    assert Pacing.of_backend("sim", "realtime", follower=True) is Pacing.STEPPED
    for p in (Pacing.STEPPED, Pacing.LOCKSTEP, Pacing.FOLLOWER):
        assert p.stepped and not p.read_before_apply and p.command_delay_periods == 0
    # stepped on the answer to the last state (robot time, no wall-clock deadline) or on the clock
    assert [p for p in Pacing if p.answered] == [Pacing.LOCKSTEP, Pacing.FOLLOWER]


def test_a_follower_is_declared_with_a_bounded_command_wait():
    """A sim in another sim's world declares it (``Driver.follower``), with a finite, bounded
    command wait; only a sim may declare it (checked when the class is made)."""
    from hilstack.drivers.base import MAX_FOLLOW_COMMAND_WAIT_S, Follower
    from hilstack.drivers.registry import make_driver, resolve
    from hilstack.sim_backends.pointmass import PointMassSim

    for bad in (0.0, -0.01, float("nan"), float("inf"), MAX_FOLLOW_COMMAND_WAIT_S * 2, "0.01", None):
        with pytest.raises(ValueError, match="command_wait_s must be a number in"):
            Follower(bad)
    assert Follower(MAX_FOLLOW_COMMAND_WAIT_S).command_wait_s == MAX_FOLLOW_COMMAND_WAIT_S
    with pytest.raises(TypeError, match="only a sim follows"):
        type("RealFollower", (resolve("velociroach", "emulated"),), {"follower": Follower(0.01)})
    with pytest.raises(TypeError, match="must be a Follower"):
        type("LooseFollower", (PointMassSim,), {"follower": 0.01})  # the old undeclared attribute's shape
    arm, hand = make_driver("reset_arm", "sim"), make_driver("shadow_hand", "sim")
    assert arm.follower is not None and hand.follower is None
    assert arm.pacing_at("lockstep") is Pacing.FOLLOWER and hand.pacing_at("lockstep") is Pacing.LOCKSTEP
    assert arm.pacing is hand.pacing is Pacing.STEPPED  # on the wall clock its tick follows the world too


class _FollowingPointMass:
    """A point mass declaring itself a follower (its own world: the node's rule is what is tested)."""

    @staticmethod
    def make(follower):
        from hilstack.sim_backends.pointmass import PointMassSim

        cls = type("FollowingPointMass", (PointMassSim,), {"follower": follower})
        return cls()


@pytest.mark.parametrize("follows", [False, True])
def test_a_lockstep_sim_never_steps_without_an_answer_a_follower_steps_on(follows, bus):
    """The lockstep rule holds (a ``LOCKSTEP`` node times out, counts it and waits on); a
    ``FOLLOWER`` node steps with the command it holds after its declared command wait, and
    its spec on the bus says it runs as a follower."""
    from hilstack.bus import keys
    from hilstack.bus.node import Node
    from hilstack.bus.schemas import SpecMsg
    from hilstack.drivers.base import Follower
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver
    from tests.helpers import wait_for

    drv = _FollowingPointMass.make(Follower(0.02)) if follows else make_driver("pointmass", "sim")
    node = DriverNode(drv, "pace", "pm", bus, pace="lockstep", lockstep_timeout_s=0.05, handle_signals=False,
                      estop_sync_s=0.05)
    try:
        assert node.pacing is (Pacing.FOLLOWER if follows else Pacing.LOCKSTEP)
        assert node.lockstep_timeout_s == (0.02 if follows else 0.05)
        with Node("probe", "pace", bus, handle_signals=False) as probe:
            spec = probe.subscribe(keys.spec("pace", "pm"), SpecMsg)
            drv.configure()
            drv.activate()
            node.publish_spec()
            t0 = drv.now()
            th = threading.Thread(target=lambda: [node.step() for _ in range(4)], daemon=True)
            th.start()  # nobody answers
            wait_for(lambda: node.stats.lockstep_timeouts >= 4, 10, "four lockstep timeouts")
            if follows:
                th.join(5)
                assert drv.now() - t0 == pytest.approx(4 * drv.spec.period_s)  # it stepped on, each time
                assert node.stats.steps == 4
            else:
                assert drv.now() == t0 and node.stats.steps == 0  # the sim stood still, waiting on
                node.stop_event.set()
                th.join(5)
            m = wait_for(lambda: spec.poll() or spec.last, 5, "the node's spec")
            assert m.spec["pacing"] == ("follower" if follows else "lockstep")
    finally:
        node.stop_event.set()
        drv.cleanup()
        node.close()


def test_the_spec_carries_the_pacing_across_the_bus():
    """A driver's spec carries its backend's pacing (before connecting); the driver node's
    spec the one it runs (lockstep for a sim in ``pace: lockstep``); the dict on the bus
    round-trips it, and a bad value is a one-line error naming it."""
    from hilstack.drivers.base import RobotSpec
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver

    sim, emu = make_driver("pointmass", "sim"), make_driver("velociroach", "emulated")
    assert sim.spec.pacing is Pacing.STEPPED and emu.spec.pacing is Pacing.WALL_CLOCK
    d = sim.spec.with_pacing(Pacing.LOCKSTEP).to_dict()
    assert d["pacing"] == "lockstep" and RobotSpec.from_dict(d).pacing is Pacing.LOCKSTEP
    del d["pacing"]
    assert RobotSpec.from_dict(d).pacing is None  # a recording from before specs carried it
    with pytest.raises(ValueError, match="pacing 'sometimes' is not one of"):
        RobotSpec.from_dict({**d, "pacing": "sometimes"})
    with pytest.raises(ValueError, match="pace 'lockstep' needs a sim backend; roach is emulated"):
        DriverNode(emu, "r", "roach", pace="lockstep")


def test_a_follower_in_a_world_that_stands_still_still_answers_the_estop(bus, monkeypatch):
    """The hand's reset arm follows the hand's scene: its ``tick()`` waits for the hand's node
    to advance it (up to its follow timeout). When that world stands still (the hand e-stopped
    first, or nobody commands it) the arm's node still acknowledges an engage and a release at
    once: it waits for its world in slices (``Driver.tick_ready``) and serves e-stops between.
    The follow timeout is made long here, so a node stuck in ``tick()`` cannot answer in time."""
    from hilstack.bus.estop import command_estop
    from hilstack.bus.node import Node
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver
    from hilstack.sim_backends.reset_arm import backend as arm_backend
    from tests.helpers import wait_for

    monkeypatch.setattr(arm_backend, "FOLLOW_TIMEOUT_S", 60.0)
    world = f"still-{uuid.uuid4().hex[:8]}"
    hand = make_driver("shadow_hand", "sim", sim={"reset_station": True, "world": world})
    hand.configure()  # nobody advances it
    arm = make_driver("reset_arm", "sim", world=world)
    node = DriverNode(arm, "still", "arm", bus, pace="lockstep", handle_signals=False, estop_sync_s=0.05)
    th = threading.Thread(target=node.serve, daemon=True)
    try:
        assert node.pacing is Pacing.FOLLOWER
        th.start()
        wait_for(lambda: arm.waiting_for_s is not None, 30, "the arm waiting for its world")
        with Node("operator", "still", bus, handle_signals=False) as op:
            engaged = command_estop(op, True, reason="test", timeout_s=5.0)
            assert engaged.ok, engaged
            assert node.estopped and not arm.active
            released = command_estop(op, False, reason="fixed", timeout_s=5.0)
            assert released.ok, released
            assert not node.estopped and arm.active
        assert node.stats.steps == 0  # it never stepped: the world stood still throughout
    finally:
        node.stop_event.set()
        th.join(10)
        assert not th.is_alive(), "the node did not stop while its world stood still"
        node.close()
        hand.cleanup()
