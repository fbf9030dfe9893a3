"""Unit tests of the contract's own logic on a trivial in-memory driver (no I/O)."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.drivers.base import (
    Driver,
    Flag,
    Freshness,
    Inputs,
    Lifecycle,
    LifecycleError,
    LinkError,
    Observation,
    RobotSpec,
    Space,
)


class Fake(Driver):
    backend = "sim"

    def __init__(self, fail_read=False, rate=1.0, limit=1.0):
        super().__init__()
        self.spec = RobotSpec(
            name="fake",
            state=Space.build([("q", "rad", -1, 1)]),
            action=Space.build([("q_cmd", "rad", -limit, limit)]),
            period_s=0.1,
            action_rate_per_s=np.array([rate]),
            safe_action=None,
        )
        self.q = 0.3
        self.sent = []
        self.stopped = 0
        self.t = 0.0
        self.fail_read = fail_read

    def now(self):
        return self.t

    def tick(self):
        self.t += 0.1

    def _read(self):
        if self.fail_read:
            raise OSError("port vanished")
        return Observation(self.t, np.array([self.q]), 0)

    def _write(self, a):
        self.sent.append(a.copy())

    def _stop(self):
        self.stopped += 1

    def _hold_command(self, obs):
        return obs.state  # position robot: hold where it is


def test_activation_holds_measured_state_and_rate_limits_from_there():
    d = Fake()
    with d:
        assert d.held_command == pytest.approx([0.3])
        a = d.write([1.0])  # 1 rad/s * 0.1 s from 0.3
        assert a == pytest.approx([0.4])
        d.tick()
        assert d.write([-1.0]) == pytest.approx([0.3])
        last = d.held_command
    assert d.lifecycle is Lifecycle.UNCONFIGURED
    # a position robot's stop on exit holds the held target (sent again), not a measurement
    assert d.sent[-1] == pytest.approx(last)


def test_writes_at_one_instant_cannot_add_up_to_more_than_one_period():
    # the review's case: held -15, rate·period = 15; the old limiter let -15 -> 0 -> 15
    d = Fake(rate=150.0, limit=15.0)
    d.q = -15.0
    with d:
        assert d.held_command == pytest.approx([-15.0])
        got = [d.write([15.0])[0] for _ in range(5)]
        assert got == pytest.approx([0.0] * 5)
        # and back down at the same instant: still within one period's worth of every value
        assert d.write([-15.0]) == pytest.approx([-15.0])
        assert d.write([15.0]) == pytest.approx([0.0])


def test_applied_command_change_is_bounded_over_any_interval():
    """Random write bursts and clock steps: every pair of applied values (t_i, a_i), (t_j, a_j)
    satisfies |a_j - a_i| <= r·(|t_j - t_i| + p) (the issue's bound), and
    the command still reaches its target."""
    rng = np.random.default_rng(0)
    r, p = 2.0, 0.1
    d = Fake(rate=r, limit=1.0)
    with d:
        hist = [(d.t, d.held_command[0])]
        for _ in range(300):
            d.t += float(rng.choice([0.0, 0.0, 0.01, 0.05, 0.1, 0.3]))
            hist.append((d.t, d.write([rng.uniform(-3, 3)])[0]))
        t = np.array([h[0] for h in hist])
        a = np.array([h[1] for h in hist])
        bound = r * (np.abs(t[:, None] - t[None, :]) + p)
        assert np.all(np.abs(a[:, None] - a[None, :]) <= bound + 1e-9)
        # a held target is reached at the rate, not faster: from the last value to -1
        start = a[-1]
        steps = 0
        while d.write([-1.0])[0] > -1.0 + 1e-12:
            d.t += p
            steps += 1
        assert steps <= int(np.ceil((start + 1.0) / (r * p)))


def test_a_ramp_from_activation_moves_one_step_every_period():
    """One write per period from the held command (0.3): r·p per period, no stall after activation
    (the held command and the first write share an instant)."""
    d = Fake(rate=1.0, limit=1.0)
    with d:
        got = []
        for _ in range(5):
            got.append(d.write([1.0])[0])
            d.t += 0.1
        assert got == pytest.approx([0.4, 0.5, 0.6, 0.7, 0.8])  # from the held 0.3


def test_clock_going_back_restarts_the_limit_from_the_held_command():
    d = Fake(rate=1.0)
    with d:
        d.t = 5.0
        assert d.write([1.0]) == pytest.approx([1.0])
        d.t = 0.0  # a sim reset: time starts again; the limit restarts from the held 1.0
        assert d.write([-1.0]) == pytest.approx([0.9])
        assert d.write([-1.0]) == pytest.approx([0.9])


def test_stop_reanchors_the_limit_at_the_safe_action():
    d = Fake(rate=1.0)
    d.spec = RobotSpec(name="fake", state=d.spec.state, action=d.spec.action, period_s=0.1,
                       action_rate_per_s=np.array([1.0]), safe_action=np.array([0.0]))
    with d:
        d.write([1.0])
        d.stop()
        assert d.held_command == pytest.approx([0.0])
        assert d.write([-1.0]) == pytest.approx([-0.1])


def test_flag_vocabulary_is_enforced():
    Observation(0.0, np.zeros(1), 0, flags={Flag.STALE_POSE: True, "watchdog": False})
    with pytest.raises(ValueError, match="vocabulary"):
        Observation(0.0, np.zeros(1), 0, flags={"telemetry_fresh": True})
    o = Observation(0.0, np.zeros(1), 0, flags={Flag.SIM_DIVERGED: True})
    assert o.flag(Flag.SIM_DIVERGED) and not o.flag(Flag.STALE_POSE)
    assert all(type(k) is str for k in o.flags)


def test_nonfinite_state_is_never_ok():
    d = Fake()
    with d:
        d.q = float("nan")
        o = d.read()
        assert o.ok is False and o.flags["nonfinite_input"]


def test_freshness_deadlines_and_ages():
    pose = Freshness("pose", deadline_s=0.2, stale_flag=Flag.STALE_POSE, fail_after_s=1.0)
    tel = Freshness("telemetry", deadline_s=0.3, stale_flag=Flag.STALE_TELEMETRY)
    ins = Inputs(pose, tel)
    ins.start(10.0)
    ok, flags = ins.assess(10.0)
    assert not ok and flags == {"stale_pose": True, "stale_telemetry": True, "nonfinite_input": False,
                              "invalid_input": False}
    assert ins.ages(10.0) == {"pose_age_s": None, "pose_nonfinite_samples": 0, "pose_invalid_samples": 0,
                              "pose_last_invalid": None, "telemetry_age_s": None,
                              "telemetry_nonfinite_samples": 0, "telemetry_invalid_samples": 0,
                              "telemetry_last_invalid": None}
    assert ins.expired(10.9) is None and ins.expired(11.1) is pose  # never arrived counts from start
    pose.update(11.0)
    tel.update(11.0)
    assert ins.assess(11.2) == (True, {"stale_pose": False, "stale_telemetry": False, "nonfinite_input": False,
                                     "invalid_input": False})
    pose.update(11.1, finite=False)  # a NaN sample: flagged, and it does not refresh the pose
    pose.update(11.12)  # a good one right after: the NaN is still reported once
    ok, flags = ins.assess(11.15)
    assert not ok and flags["nonfinite_input"] and not flags["stale_pose"]
    assert ins.assess(11.15, report=True)[1]["nonfinite_input"]  # read() reports it ...
    assert ins.assess(11.15) == (True, {"stale_pose": False, "stale_telemetry": False, "nonfinite_input": False,
                                     "invalid_input": False})
    assert ins.ages(11.15)["pose_age_s"] == pytest.approx(0.03) and ins.ages(11.15)["pose_nonfinite_samples"] == 1
    pose.update(11.16, finite=False)
    assert ins.ages(11.2)["pose_age_s"] == pytest.approx(0.08)  # ... and the NaN did not refresh it
    assert ins.assess(11.35)[1]["stale_pose"]  # the deadline counts from the last usable one
    assert ins.expired(12.1) is None and ins.expired(12.15) is pose  # 1 s after the last usable sample


def test_a_robot_without_safe_action_must_say_what_it_holds():
    class NoHold(Fake):
        _hold_command = Driver._hold_command

    d = NoHold()
    d.configure()
    with pytest.raises(NotImplementedError, match="_hold_command"):
        d.activate()  # never a silent hold of zeros (a jump for position control)
    assert d.lifecycle is Lifecycle.UNCONFIGURED and d.held_command is None


def test_failing_stop_is_reported_in_last_error():
    class BrokenStop(Fake):
        def _stop(self):
            raise OSError("port gone")

    d = BrokenStop()
    d.configure()
    d.fail("reader crashed")
    assert d.lifecycle is Lifecycle.UNCONFIGURED
    assert "reader crashed" in d.last_error and "stop was not sent" in d.last_error


def test_nothing_reaches_the_wire_on_bad_input():
    d = Fake()
    with d:
        for bad in ([np.inf], [np.nan], [1.0, 2.0], "x", None):
            with pytest.raises(ValueError):
                d.write(bad)
        assert d.sent == []


def test_error_path_stops_and_goes_unconfigured():
    d = Fake(fail_read=True)
    d.configure()
    with pytest.raises(OSError):
        d.activate()
    assert d.lifecycle is Lifecycle.UNCONFIGURED
    assert d.stopped == 1 and "port vanished" in d.health().last_error


def test_space_checks():
    with pytest.raises(ValueError, match="low > high"):
        Space.build([("a", "m", 1, 0)])
    s = Space.build([("a", "m", 0, 1), ("b", "m", 0, 1)])
    assert s.index("b") == 1
    with pytest.raises(KeyError, match="channels are"):
        s.index("c")


def test_realtime_pacer_follows_the_wall_clock_and_slips_instead_of_bursting():
    from hilstack.sim_backends.base import RealtimePacer

    pacer = RealtimePacer(sim_time_s=5.0, tick_s=0.001, max_catchup_s=0.05, now_s=100.0)
    assert pacer.due(100.0, 5.0) == 0
    assert pacer.due(100.010, 5.0) == 10  # 10 ms of wall time: 10 ticks
    assert pacer.due(100.010, 5.010) == 0  # caught up
    # a 1 s stall: only 50 ms is integrated, the rest is given up and counted
    assert pacer.due(101.010, 5.010) == 50
    assert pacer.slip_s == pytest.approx(0.95)
    assert pacer.due(101.020, 5.060) == 10  # then it runs on from the new origin
    double = RealtimePacer(sim_time_s=0.0, tick_s=0.001, realtime_factor=2.0, now_s=0.0)
    assert double.due(0.010, 0.0) == 20


class HoldsMeasured(Fake):
    """A position robot whose own ``_stop`` holds the measured position, as the hand's,
    the reset arm's and the mechanism's do; its reading can be stale."""

    def _stop(self):
        self.stopped += 1
        a = np.array([self.q])
        self.sent.append(a)
        return a


def test_a_position_stop_holds_the_held_target_not_a_stale_measured_pose():
    """The review's case: the measured pose is stale (0.3, the reading stopped updating)
    while the commands ramped the target to 0.8; a stop that held the measured pose sent
    0.3 at once, a jump of 0.5 where the rate limit allows 0.1 per period. The stop holds
    the last target instead, and the next write ramps from there."""
    d = HoldsMeasured(rate=1.0)
    with d:
        for _ in range(5):
            d.write([1.0])
            d.t += 0.1
        last = d.held_command
        assert last == pytest.approx([0.8])
        d.stop()
        step = 1.0 * d.spec.period_s
        assert abs(d.sent[-1][0] - last[0]) <= step + 1e-12, f"stop sent {d.sent[-1]} after {last}"
        assert d.held_command == pytest.approx(last) and d.stopped == 0
        assert d.write([-1.0]) == pytest.approx([0.7])  # the rate limit restarts from the hold
    # not active (never activated, or deactivated): nothing held of this activation, the device's own stop
    d2 = HoldsMeasured()
    d2.configure()
    d2.stop()
    assert d2.stopped == 1 and d2.sent[-1] == pytest.approx([0.3])
    d2.cleanup()

def test_the_error_path_of_a_position_robot_holds_the_held_target_not_a_stale_measured_pose():
    """A device that stopped answering (the error path, fail_link): its measured pose is the
    stale 0.3 while the target had ramped to 0.8; the stop sent on the way down holds 0.8."""
    d = HoldsMeasured(rate=1.0)
    d.configure()
    d.activate()
    for _ in range(5):
        d.write([1.0])
        d.t += 0.1
    last = d.held_command
    with pytest.raises(LinkError):
        d.fail_link("no usable telemetry")
    assert d.lifecycle is Lifecycle.UNCONFIGURED and d.stopped == 0
    assert d.sent[-1] == pytest.approx(last), f"error path sent {d.sent[-1]} after {last}"


def test_rejected_samples_are_flagged_counted_and_do_not_refresh():
    pose = Freshness("pose", deadline_s=0.2, stale_flag=Flag.STALE_POSE)
    ins = Inputs(pose)
    ins.start(0.0)
    pose.update(1.0)
    pose.reject("zero quaternion")
    ok, flags = ins.assess(1.1, report=True)
    assert not ok and flags["invalid_input"] and not flags["stale_pose"]
    assert ins.assess(1.1) == (True, {"stale_pose": False, "nonfinite_input": False, "invalid_input": False})
    pose.reject("outside the arena")
    assert ins.ages(1.3) == {"pose_age_s": pytest.approx(0.3), "pose_nonfinite_samples": 0,
                             "pose_invalid_samples": 2, "pose_last_invalid": "outside the arena"}
    assert ins.assess(1.3)[1]["stale_pose"]  # rejected samples never refresh the input


def test_error_deadline_in_periods_is_finite_bounded_and_beyond_the_stale_deadline():
    f = Freshness.fail_after_periods("telemetry", 0.1, Flag.STALE_TELEMETRY, 10, 0.1)
    assert f.fail_after_s == pytest.approx(1.0)
    with pytest.raises(ValueError, match="must exceed the stale deadline"):
        Freshness.fail_after_periods("telemetry", 0.5, Flag.STALE_TELEMETRY, 2, 0.1)
    with pytest.raises(ValueError, match="finite number of periods"):
        Freshness.fail_after_periods("telemetry", 0.1, Flag.STALE_TELEMETRY, 10, float("inf"))


class Streaming(Fake):
    """A device that streams one input; the test decides when samples arrive."""

    def __init__(self):
        super().__init__()
        self.inputs = Inputs(Freshness.fail_after_periods("telemetry", 0.25, Flag.STALE_TELEMETRY, 5, 0.1))
        self.cleaned = 0

    def _on_configure(self):
        self.inputs.start(self.t)
        self.inputs["telemetry"].update(self.t)

    def _on_cleanup(self):
        self.cleaned += 1

    def _read(self):
        ok, flags = self.inputs.assess(self.t, report=True)
        return Observation(self.t, np.array([self.q]), 0, ok=ok, flags=flags)


def test_an_input_silent_for_its_periods_takes_the_error_path_from_read_and_write():
    d = Streaming()
    with d:
        for _ in range(3):  # 0.3 s without telemetry: stale, still active
            d.tick()
        obs = d.read()
        assert not obs.ok and obs.flags["stale_telemetry"] and d.active
        d.tick()
        d.tick()
        d.tick()  # 0.6 s > 5 periods
        held = d.held_command
        with pytest.raises(LinkError, match=r"no usable telemetry for 0.60 s \(limit: 5 control periods"):
            d.write([0.3])  # a dead robot is never commanded
        # the error path's stop: a position robot holds its held target (not a stale measured pose)
        assert d.lifecycle is Lifecycle.UNCONFIGURED and d.cleaned == 1
        assert "no usable telemetry" in d.last_error
        assert d.stopped == 0 and len(d.sent) == 1 and d.sent[0] == pytest.approx(held), "0.3 was never sent"
        with pytest.raises(LifecycleError):
            d.read()
    d = Streaming()
    d.configure()
    for _ in range(6):
        d.tick()
    with pytest.raises(LinkError, match="frozen, switched off or unreachable"):
        d.read()
    assert d.lifecycle is Lifecycle.UNCONFIGURED and d.stopped == 1


@pytest.mark.parametrize("where", ["read", "write"])
def test_a_link_error_raised_inside_a_backend_call_takes_the_error_path(where):
    """A device killed mid-write (the port's write fails with EIO) surfaces as a LinkError raised
    by the backend's own _write/_read, not through fail_link: the contract still stops the robot,
    goes UNCONFIGURED, keeps last_error, and never commands the dead device again."""
    from hilstack.drivers.base import LifecycleError, LinkError

    class DiesMidCall(Fake):
        dead = False

        def _read(self):
            if self.dead and where == "read":
                raise LinkError("serial port: read failed (EIO)")
            return super()._read()

        def _write(self, a):
            if self.dead and where == "write":
                raise LinkError("serial port: write failed (EIO)")
            super()._write(a)

    d = DiesMidCall()
    with d:
        d.write([0.3])
        d.dead = True
        with pytest.raises(LinkError, match="failed"):
            d.read() if where == "read" else d.write([0.3])
        assert d.lifecycle is Lifecycle.UNCONFIGURED and "EIO" in d.last_error
        if where == "read":  # the port still writes: the held target was re-sent as the stop
            assert len(d.sent) == 2
        else:  # the stop was tried on the dead port, and that is reported
            assert "the stop was not sent" in d.last_error
        n_sent = len(d.sent)
        with pytest.raises(LifecycleError):
            d.write([0.3])
        assert len(d.sent) == n_sent



def test_optional_capabilities_are_declared_on_the_contract_not_probed():
    """What `hil up` and `hil drive` ask a driver (its shared device bus, its tracking
    error) is declared on the base class with a 'none' default, and a robot that has it
    overrides it: the Dynamixel arms share their adapter, the hand reports its tracking."""
    from hilstack.configs.schema import load_robot
    from hilstack.drivers.registry import make_driver, resolve
    from hilstack.drivers.shadow_hand.config import hold_pose_action

    roach, arm = load_robot("velociroach", backend="emulated"), load_robot("widowx", backend="emulated")
    assert resolve("velociroach", "emulated").shared_bus_key(roach) is None
    assert resolve("widowx", "emulated").shared_bus_key(arm) == resolve("reset_mechanism", "emulated").shared_bus_key(
        load_robot("reset_mechanism", backend="emulated"))  # one adapter, one process
    roach_sim, hand = make_driver("velociroach", "sim"), make_driver("shadow_hand", "sim")
    assert roach_sim.tracking_error(np.zeros(roach_sim.spec.state.dim), np.zeros(2)) is None
    te = hand.tracking_error(np.zeros(hand.spec.state.dim), hold_pose_action())
    assert te["max_rad"] > 0 and len(te["per_joint_rad"]) == 20
