"""The reset supervisor on the simulated VelociRoACH (lockstep): the whole cycle, and faults.

Every test runs the real driver bridge, supervisor and controller nodes over Zenoh."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from hilstack.bus import keys
from hilstack.bus.estop import command_estop
from hilstack.bus.node import Node
from hilstack.bus.recording import Recorder, read_messages
from hilstack.bus.schemas import ResetTransition, decode
from hilstack.control.reset.steps import MECHANISMS, TaskResetMechanism, register_mechanism
from tests.helpers import wait_for

FULL_CYCLE = ["episode_end", "paused", "resetting", "verifying", "resumed", "running"]


def _ended_by_supervisor(ctl):
    """stop_if for run_lockstep: the supervisor published end_episode."""
    sub = ctl.subscribe(keys.reset_transition(ctl.rig), ResetTransition, latest=False, capacity=64)

    def stop(_state) -> bool:
        return any(decode(p, ResetTransition).dest == "episode_end" for _, p in sub.drain())

    return stop


def drive_out(rig, steps=60, action=(0.8, 0.6), stop_if=None):
    s = rig.ctl.next_state()
    return rig.ctl.run_lockstep(lambda x: np.array(action), steps, s, stop_if=stop_if)


def test_leaving_the_arena_ends_the_episode_and_the_robot_is_driven_back(supervised_rig, tmp_path):
    rig = supervised_rig()
    rec = Recorder(rig.rig.name, tmp_path / "r.mcap", session=rig.ctl.session, handle_signals=False)
    th = threading.Thread(target=rec.record, daemon=True)
    th.start()
    log = drive_out(rig, steps=200, stop_if=_ended_by_supervisor(rig.ctl))
    # the arena detector (radius 0.6 m) ended the episode well before 200 steps
    assert len(log.actions) < 200
    xy_end = log.states[-1][:2]
    assert math.hypot(*xy_end) > 0.6
    first = rig.ctl.reset(timeout_s=60, x=0.0, y=0.0, yaw=1.0)
    assert first.episode == 1
    assert math.hypot(first.state[0], first.state[1]) <= 0.25
    yaw = math.atan2(first.state[11], first.state[10])
    assert abs(math.remainder(yaw - 1.0, math.tau)) <= 0.5
    assert rig.dests() == FULL_CYCLE
    assert "arena" in rig.sup.history[0].reason
    assert rig.sup.stats == {"requested": 1, "completed": 1, "failed": 0}
    # the next episode runs on from the verified pose, and a second reset works too
    drive_out(rig, steps=10)
    first = rig.ctl.reset(timeout_s=60, x=0.3, y=0.0, yaw=0.0)
    assert first.episode == 2 and abs(first.state[0] - 0.3) <= 0.25
    time.sleep(0.3)
    rec.stop_event.set()
    th.join(10)
    rec.close()
    recorded = [m.msg for m in read_messages(tmp_path / "r.mcap").messages if isinstance(m.msg, ResetTransition)]
    assert [t.dest for t in recorded] == FULL_CYCLE * 2
    assert recorded[-1].trigger == "resume"


class NeverDone(TaskResetMechanism):
    """A task-reset mechanism that never gets there (a stuck fixture)."""

    def __init__(self, params):
        self.begun = self.aborted = 0

    def begin(self, pose):
        self.begun += 1

    def poll(self) -> bool:
        return False

    def abort(self) -> None:
        self.aborted += 1


@pytest.fixture
def never_done():
    made: list[NeverDone] = []

    def factory(params):
        made.append(NeverDone(params))
        return made[-1]

    register_mechanism("test-stuck", factory)
    yield made
    MECHANISMS.pop("test-stuck", None)


def _stuck_step(timeout_s=60.0, retries=0):
    return [{"kind": "task_reset", "timeout_s": timeout_s, "retries": retries, "params": {"mechanism": "test-stuck"}}]


def _estop_engaged(rig) -> bool:
    s = rig.ctl._state.last
    return s is not None and s.stopped_reason == "estop"


def test_a_step_that_times_out_is_retried_then_the_rig_is_stopped(supervised_rig, never_done):
    rig = supervised_rig(steps=_stuck_step(timeout_s=0.5, retries=1))
    drive_out(rig, steps=5)
    with pytest.raises(RuntimeError, match=r"task_reset failed after 2 attempts: timed out after 0.5 s"):
        rig.ctl.reset(timeout_s=30)
    assert rig.dests()[:5] == ["episode_end", "paused", "resetting", "resetting", "failed"]
    assert never_done[0].begun == 2 and never_done[0].aborted >= 2
    # the supervisor engaged the rig's e-stop: the driver node holds the robot stopped
    wait_for(lambda: rig.driver.estopped, 10, "driver e-stopped")
    wait_for(lambda: rig.sup.state == "estopped", 10, "supervisor estopped")
    assert "timed out" in rig.sup.last_failure
    # a new request is refused with the reason until the operator releases the e-stop
    with pytest.raises(RuntimeError, match="rig stopped"):
        rig.ctl.reset(timeout_s=10)


def test_an_estop_during_a_reset_wins(supervised_rig, never_done, bus):
    rig = supervised_rig(steps=_stuck_step())
    drive_out(rig, steps=5)
    got: dict = {}
    th = threading.Thread(target=lambda: got.update(err=_catch(lambda: rig.ctl.reset(timeout_s=30))))
    th.start()
    wait_for(lambda: rig.sup.state == "resetting", 20, "resetting")
    with Node("operator", rig.rig.name, bus, handle_signals=False) as op:
        res = command_estop(op, True, reason="test")
    assert res.ok
    th.join(30)
    assert "e-stop engaged" in str(got["err"]) and "during the reset" in str(got["err"])
    assert rig.dests()[-1] == "estopped"
    assert never_done[0].aborted == 1
    # no command from the supervisor after the e-stop
    n = rig.driver.stats.estop_refused
    time.sleep(0.3)
    assert rig.driver.stats.estop_refused == n
    # releasing the e-stop brings the supervisor back to running
    with Node("operator2", rig.rig.name, bus, handle_signals=False) as op:
        assert command_estop(op, False, reason="fixed").ok
    wait_for(lambda: rig.sup.state == "running", 10, "running again")


def test_the_driver_disappearing_during_a_reset_fails_it(supervised_rig, never_done):
    rig = supervised_rig(steps=_stuck_step())
    drive_out(rig, steps=5)
    got: dict = {}
    th = threading.Thread(target=lambda: got.update(err=_catch(lambda: rig.ctl.reset(timeout_s=30))))
    th.start()
    wait_for(lambda: rig.sup.state == "resetting", 20, "resetting")
    rig.stop_driver()  # its liveliness token goes with it
    th.join(30)
    assert "driver-roach disappeared (liveliness lost)" in str(got["err"])
    assert "failed" in rig.dests()
    assert never_done[0].aborted >= 1
    # the e-stop is latched on the remaining nodes: a restarted driver starts stopped
    assert rig.ctl.estop.engaged and "liveliness lost" in rig.ctl.estop.latched.reason


def test_a_reset_that_fails_verification_stops_the_rig(supervised_rig):
    # drive back without turning, then ask for the opposite heading within 0.1 rad
    rig = supervised_rig(steps=[{"kind": "drive_to_start", "timeout_s": 20}], verify={"position_tol_m": 0.25,
                                                                                     "yaw_tol_rad": 0.1})
    drive_out(rig, steps=30)
    s = rig.ctl.next_state()
    yaw_now = math.atan2(s.state[11], s.state[10])
    with pytest.raises(RuntimeError, match="failed verification: heading"):
        rig.ctl.reset(timeout_s=30, x=0.0, y=0.0, yaw=yaw_now + math.pi)
    assert rig.dests()[:5] == ["episode_end", "paused", "resetting", "verifying", "failed"]
    wait_for(lambda: rig.driver.estopped, 10, "driver e-stopped")
    assert rig.driver.episode == 0  # no new episode after a failed reset


def _catch(fn):
    try:
        fn()
    except Exception as e:  # the thread hands the error to the test
        return e
    return None


class Broken(TaskResetMechanism):
    def __init__(self, params):
        pass

    def begin(self, pose):
        pass

    def poll(self) -> bool:
        raise KeyError("bug in the mechanism")


def test_a_crashing_step_still_stops_the_rig_and_tells_the_controller(bus):
    from tests.reset.conftest import SupervisedRig, rig_config

    register_mechanism("test-broken", Broken)
    try:
        rig = SupervisedRig(bus, rig_config(steps=[{"kind": "task_reset", "params": {"mechanism": "test-broken"}}]),
                            serve=True)
        try:
            drive_out(rig, steps=5)
            with pytest.raises(RuntimeError, match="reset supervisor error: KeyError"):
                rig.ctl.reset(timeout_s=20)
            wait_for(lambda: rig.driver.estopped, 10, "driver e-stopped")
            wait_for(lambda: rig.crash, 10, "supervisor loop re-raised")
            assert isinstance(rig.crash[0], KeyError)
        finally:
            rig.close()
    finally:
        MECHANISMS.pop("test-broken", None)


def test_teleport_step_puts_the_sim_robot_at_the_pose_through_the_driver_node(supervised_rig):
    rig = supervised_rig(steps=[{"kind": "teleport", "timeout_s": 5}], detectors=[])
    drive_out(rig, steps=20)
    first = rig.ctl.reset(timeout_s=30, x=0.4, y=-0.2, yaw=0.3)
    assert first.episode == 1  # one new episode, from the supervisor's "episode" request only
    assert first.state[0] == pytest.approx(0.4, abs=0.05) and first.state[1] == pytest.approx(-0.2, abs=0.05)
    assert rig.dests() == FULL_CYCLE


def test_a_lockstep_controller_may_pause_longer_than_the_state_timeout_before_asking(supervised_rig):
    """A lockstep robot publishes nothing while its controller trains between episodes; the
    supervisor's no-state clock starts at the request, not at the last state before the pause."""
    # the default no-state limit (2 s): every lockstep round trip of the reset (a command, the
    # state it steps to) must fit in it, on a loaded machine too (0.5 s did not: one verifying
    # round trip took longer at a load of ~20 on 2 cores). The pause exceeds it, so a clock
    # counted from the last state before the pause fails at the request, every time.
    timeout_s = 2.0
    rig = supervised_rig(steps=[{"kind": "teleport", "timeout_s": 5}], detectors=[], state_timeout_s=timeout_s)
    drive_out(rig, steps=5)
    time.sleep(timeout_s + 0.5)  # the controller trains a model: longer than state_timeout_s
    first = rig.ctl.reset(timeout_s=30, x=0.0, y=0.0, yaw=0.0)
    assert first.episode == 1
    assert rig.sup.stats["failed"] == 0 and rig.dests() == FULL_CYCLE


class _AnswerFirst:
    """The supervisor's state subscription, except that while a teleport is answered the state
    after it is taken only 0.2 s after the answer: on a loaded machine the answer, sent after that
    state, came through its own subscription's thread first (a Zenoh callback runs on a thread of
    its own per subscription), and the reset's settling was timed from the state before the
    teleport (the sim's clock restarts there): 1.9 s instead of 0.3 s."""

    def __init__(self, sup):
        self.sub, self.sup = sup._state, sup
        self.held = None
        self.answered_at: float | None = None
        answer = sup.driver_answer

        def driver_answer():
            a = answer()
            if a is not None and self.answered_at is None:
                self.answered_at = time.monotonic()
            return a

        sup.driver_answer = driver_answer

    def poll(self):
        m = self.sub.poll()
        if m is not None and self.sup.state == "resetting" and self.held is None and self.answered_at is None:
            self.held, m = m, None  # the state after the teleport: on its way
        if m is None and self.held is not None and self.answered_at is not None \
                and time.monotonic() - self.answered_at > 0.2:
            m, self.held = self.held, None
        return m

    def wait(self, timeout_s=None):
        deadline = time.monotonic() + (timeout_s or 0.0)
        while True:
            m = self.poll()
            if m is not None or time.monotonic() >= deadline:
                return m
            time.sleep(0.01)


def test_settling_is_timed_from_the_state_after_the_teleport_when_its_answer_comes_first(supervised_rig):
    rig = supervised_rig(steps=[{"kind": "teleport", "timeout_s": 5}], detectors=[])
    drive_out(rig, steps=10)  # robot time 1 s; the teleport restarts the sim's clock
    gate = _AnswerFirst(rig.sup)
    rig.sup._state = gate
    first = rig.ctl.reset(timeout_s=30, x=0.0, y=0.0, yaw=0.0)
    assert gate.answered_at is not None and gate.held is None  # the answer came first, the state after it
    settle_s, period_s = rig.sup.settle_s, rig.driver.spec.period_s
    # the new episode starts after settle_s of robot time since the teleport, not 1 s + settle_s
    assert first.t_s == pytest.approx(settle_s, abs=period_s + 1e-9), first.t_s
    assert rig.sup.stats["failed"] == 0 and rig.dests() == FULL_CYCLE
    assert rig.sup.report()["teleport_answer_before_its_state"] == 1
