"""WidowX and mechanism drivers: the real code over the emulator (pty) and over the sim bus."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import Lifecycle, LinkError
from hilstack.drivers.dynamixel.control_table import OPERATING_MODES
from hilstack.drivers.registry import make_driver
from hilstack.drivers.widowx.config import JOINT_NAMES
from hilstack.sim_backends.widowx.world import SLEEP_POSE_RAD
from hilstack.tools.cmd_drive import drive_run

HELD = {"shoulder": -0.5, "elbow": 0.5, "wrist_angle": 0.3}


def _sim(bus_name: str, **params):
    return make_driver("widowx", backend="sim", bus_name=bus_name, **params)


def test_hil_drive_emulated_has_zero_link_errors_and_reports_tracking():
    out = drive_run("widowx", "emulated", None, 1.0)
    lk = out["link"]
    assert lk["ok"] and lk["corrupt_frames"] == 0 and lk["dropped_frames"] == 0
    assert lk["frames_received"] > 20 and lk["latency_s"] is not None
    assert set(out["tracking_rms"]) == {f"{n}_vel" for n in JOINT_NAMES}
    # the free joints follow 0.3 rad/s closely; it moved the waist the commanded way
    assert out["tracking_rms"]["waist_vel"] < 0.1
    assert out["final_state"]["waist_pos"] > 0.1
    assert set(lk["temperatures_c"]) == set(JOINT_NAMES)


def test_activation_holds_the_measured_pose_and_stop_holds_position():
    d = _sim("t_hold", sim={"start_holding": HELD})
    with d:
        q0 = d.read().state[:6]
        assert np.allclose(d.held_command, 0.0, atol=0.05)  # measured velocities: at rest
        for _ in range(10):
            d.tick()
        q1 = d.read().state[:6]
        assert np.abs(q1 - q0).max() < 0.02  # activation did not drop the held arm
        for _ in range(10):
            d.write(np.full(6, 0.5))
            d.tick()
        d.stop()
        w = d.world
        modes = {w.servos[i].get("Operating Mode") for i in d.ids.values()}
        assert modes == {OPERATING_MODES["position"]}
        q_stop = d.read().state[:6]
        for _ in range(20):
            d.tick()
        assert np.abs(d.read().state[:6] - q_stop).max() < 0.03  # held, not drifting
        np.testing.assert_allclose(d.held_command, 0.0)
        # the next command goes back to velocity mode
        d.write(np.zeros(6))
        assert {w.servos[i].get("Operating Mode") for i in d.ids.values()} == {OPERATING_MODES["velocity"]}


def test_joint_limit_guard_stops_motion_into_a_limit_only():
    d = _sim("t_guard")
    with d:
        for _ in range(10):
            d.tick()
        q = d.read().state[:6]
        e = JOINT_NAMES.index("elbow")
        assert q[e] == pytest.approx(SLEEP_POSE_RAD["elbow"], abs=0.02)  # resting on its upper limit
        a = d.write(np.full(6, 0.2))
        assert a[e] == 0.0 and a[0] > 0
        for _ in range(5):
            d.tick()
            a = d.write(np.full(6, -0.2))
        assert a[e] < 0  # away from the limit is allowed


def test_hardware_error_while_active_stops_the_rest_and_names_the_joint():
    d = _sim("t_hw", sim={"start_holding": HELD})
    d.configure()
    d.activate()
    d.write(np.full(6, 0.2))
    d.tick()
    w = d.world
    w.servos[d.ids["elbow"]].inject_hardware_error(0x20)
    with pytest.raises(LinkError, match=r"elbow \(ID 4\): overload"):
        d.read()
    assert d.lifecycle is Lifecycle.UNCONFIGURED
    # the error path stopped the others: zero velocity, then position hold
    others = [w.servos[d.ids[n]] for n in JOINT_NAMES if n != "elbow"]
    assert all(s.get("Goal Velocity") == 0 or s.get("Operating Mode") == OPERATING_MODES["position"]
               for s in others)
    assert all(s.get("Operating Mode") == OPERATING_MODES["position"] and s.torque_on for s in others)


def test_silent_servo_makes_readings_stale_not_wrong():
    d = _sim("t_stale", sim={"start_holding": HELD}, telemetry_stale_s=0.2)
    with d:
        w = d.world
        gone = w.servos.pop(d.ids["wrist_rotate"])  # unplugged mid-run
        try:
            obs = d.read()
            assert obs.ok  # its last value is still fresh
            for _ in range(6):
                d.tick()
            obs = d.read()
            assert not obs.ok and obs.flags["stale_telemetry"] and obs.extras["telemetry_age_s"] > 0.2
            assert np.all(np.isfinite(obs.state))  # the last good value, flagged; not NaN, not zero
            h = d.health()
            assert not h.ok and h.dropped_frames > 0
        finally:
            w.servos[d.ids["wrist_rotate"]] = gone


def test_emulated_hardware_error_at_configure_needs_a_reboot_decision():
    d = make_driver("widowx", backend="emulated", bus_name="t_hwcfg",
                    emulator={"hardware_errors": {"6": 0x04}})
    with pytest.raises(LinkError, match=r"forearm_roll.*ID 6.*overheating.*reboot"):
        d.configure()
    assert d.lifecycle is Lifecycle.UNCONFIGURED
    d = make_driver("widowx", backend="emulated", bus_name="t_hwcfg", reboot_on_hardware_error=True,
                    emulator={"hardware_errors": {"6": 0x04}})
    with d:
        assert d.health().ok
        assert d.bus.read(6, "Hardware Error Status") == 0


def test_emulated_missing_servo_is_a_one_line_error():
    d = make_driver("widowx", backend="emulated", bus_name="t_missing", emulator={"missing_ids": [4]})
    with pytest.raises(LinkError, match=r"joint 'elbow' \(ID 4\) does not answer on the emulator"):
        d.configure()


def test_real_backend_without_a_port_says_which_field():
    with pytest.raises(ConfigError, match="params.port"):
        make_driver("widowx", backend="real").configure()


def test_mechanism_moves_the_switch_in_sim():
    arm = _sim("t_mech")
    mech = make_driver("reset_mechanism", backend="sim", bus_name="t_mech")
    with arm, mech:
        assert mech.world is arm.world  # one bench
        p0, yaw0 = arm.world.port_pose()
        target = np.array([math.radians(6.0), 0.008])
        for _ in range(30):
            mech.write(target)
            mech.tick()
        s = mech.read().state
        assert abs(s[0] - target[0]) < 0.005 and abs(s[1] - target[1]) < 0.0005
        p1, yaw1 = arm.world.port_pose()
        assert yaw1 - yaw0 == pytest.approx(math.radians(6.0), abs=0.005)
        # the port (offset -3 cm along the housing's x) moves with the rail and the rotation
        expect_dy = 0.008 + (-0.03) * math.sin(math.radians(6.0))
        assert p1[1] - p0[1] == pytest.approx(expect_dy, abs=0.001)
        # beyond ±8° / ±1 cm is clamped to the range
        applied = mech.write([1.0, 1.0])
        assert applied[0] <= math.radians(8.0) + 1e-9 and applied[1] <= 0.01 + 1e-12


def test_link_loss_takes_the_error_path_with_a_one_line_error():
    d = make_driver("widowx", backend="emulated", bus_name="t_loss")
    d.configure()
    d.activate()
    d.write(np.full(6, 0.1))
    emu = d.bus.emulator
    emu.kill()  # the adapter is gone: the pty reads fail with EIO
    emu.proc.wait()
    with pytest.raises(LinkError, match="failed") as ei:
        d.read()
    assert "\n" not in str(ei.value)
    assert d.lifecycle is Lifecycle.UNCONFIGURED and d.last_error
    d.cleanup()


def test_resetting_the_arm_leaves_the_mechanism_working():
    arm = _sim("t_reset", sim={"start_holding": HELD})
    mech = make_driver("reset_mechanism", backend="sim", bus_name="t_reset")
    with arm, mech:
        for _ in range(10):
            arm.write(np.full(6, 0.3))
            mech.write([0.05, 0.004])
            arm.tick()
        arm.reset()
        assert arm.active
        np.testing.assert_allclose(arm.read().state[1:3], [HELD["shoulder"], HELD["elbow"]], atol=0.02)
        for _ in range(20):
            mech.write([0.1, 0.008])
            mech.tick()
        assert abs(mech.read().state[1] - 0.008) < 0.001  # its servos were not power-cycled


def test_sim_renders_fixed_and_wrist_cameras_side_by_side():
    arm = _sim("t_cam", sim={"cameras": True, "start_holding": HELD})
    with arm:
        img0 = arm.read().extras["image"]
        assert img0.shape == (64, 128, 3) and img0.dtype == np.uint8
        for _ in range(10):
            arm.write(np.array([0.5, 0, 0, 0, 0, 0]))
            arm.tick()
        img1 = arm.read().extras["image"]
        # the waist turned: both views changed (the fixed camera sees the arm move)
        assert np.abs(img1[:, :64].astype(int) - img0[:, :64]).mean() > 0.5
        assert np.abs(img1[:, 64:].astype(int) - img0[:, 64:]).mean() > 0.5


def test_bridge_publishes_the_camera_image_on_the_bus():
    from hilstack.bus import keys
    from hilstack.bus.node import Node
    from hilstack.bus.schemas import Image
    from hilstack.configs.schema import BusConfig
    from hilstack.drivers.bridge import DriverNode
    from hilstack.tools.demo import free_endpoint

    bus = BusConfig(endpoint=free_endpoint())
    arm = _sim("t_bridge", sim={"cameras": True})
    with arm, DriverNode(arm, "benchcam", "arm", bus=bus, handle_signals=False) as node, \
            Node("viewer", "benchcam", bus=bus, handle_signals=False) as viewer:
        sub = viewer.subscribe(keys.image("benchcam", "arm"), Image)
        got = None
        for _ in range(100):
            node.step()
            got = sub.wait(0.05)
            if got is not None:
                break
        assert got is not None and (got.height, got.width) == (64, 128)
        assert len(got.data) == 64 * 128 * 3


def test_configure_waits_for_a_slow_first_answer_as_it_does_for_the_pings(monkeypatch):
    """A device that answers a sync read only after 100 ms (an emulator starved by a loaded CPU;
    the control loop waits 0.8 of the 50 ms period for it) still configures: the first reading
    waits as long as the pings. The loop's reads stay bounded by the period."""
    from hilstack.sim_backends.dynamixel.backend import SimBus

    answer_after_ms = 100.0
    bounds: list[float | None] = []
    fast = SimBus.sync_read

    def slow(self, ids, first, last, timeout_margin_ms=None):
        bounds.append(timeout_margin_ms)
        if timeout_margin_ms is not None and timeout_margin_ms < answer_after_ms:
            return {}, {}  # given up before the answers came
        return fast(self, ids, first, last, timeout_margin_ms)

    monkeypatch.setattr(SimBus, "sync_read", slow)
    d = _sim("slow-first")
    d.configure()
    try:
        assert np.all(np.isfinite(d.read().state))  # the reading configure took
        assert bounds[0] is None and bounds[-1] == pytest.approx(0.8 * d.spec.period_s * 1000.0)
    finally:
        d.cleanup()
