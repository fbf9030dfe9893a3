"""Sawyer: ROS 2 messages over Zenoh (real driver ↔ emulator process), and its sim backend."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import Lifecycle
from hilstack.drivers.registry import make_driver
from hilstack.drivers.sawyer import ros
from hilstack.drivers.sawyer.config import JOINTS
from hilstack.sim_backends.sawyer.controller import COMMAND_TIMEOUT_S, POSITION_MODE, VELOCITY_MODE, SawyerArm


def test_cdr_round_trip_and_bridge_keys():
    raw = ros.encode_joint_command(ros.VELOCITY_MODE, JOINTS, np.arange(7) * 0.1, stamp_s=12.5)
    m = ros.decode_joint_command(raw)
    assert m.mode == 2 and list(m.names) == list(JOINTS) and len(m.position) == 0
    np.testing.assert_allclose(m.velocity, np.arange(7) * 0.1)
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (12, 500_000_000)
    js = ros.decode_joint_state(ros.encode_joint_state(["head_pan", *JOINTS], np.arange(8), np.ones(8), np.zeros(8)))
    assert js.name[0] == "head_pan" and js.position[3] == 3.0
    # zenoh-bridge-ros2dds: topic without its leading slash, under the bridge namespace
    assert ros.bridge_key("/robot/joint_states") == "robot/joint_states"
    assert ros.bridge_key("/robot/limb/right/joint_command", "/lab2/") == "lab2/robot/limb/right/joint_command"


def test_vendor_controller_tracks_velocity_and_holds_on_timeout():
    a = SawyerArm()
    for _ in range(8):
        assert a.command(VELOCITY_MODE, list(JOINTS), np.full(7, 0.2), a.time_s)
        a.advance(0.05)
    assert np.all(np.abs(a.qd() - 0.2) < 0.05)
    a.advance(COMMAND_TIMEOUT_S + 0.3)  # commands stopped: the controller holds
    assert a.timeouts == 1 and np.abs(a.qd()).max() < 0.02
    assert not a.command(VELOCITY_MODE, list(JOINTS), np.array([np.nan] * 7), a.time_s)
    assert not a.command(POSITION_MODE, ["j0"], np.zeros(1), a.time_s)
    assert a.rejected == 2


def test_emulated_sawyer_moves_and_stop_holds():
    # a loaded CI machine can delay the emulator's 100 Hz stream: allow 0.5 s before "stale"
    d = make_driver("sawyer", backend="emulated", namespace="benchA", joint_states_stale_s=0.5)
    with d:
        q0 = d.read().state[:7]
        assert d.health().extra["keys"]["joint_states"] == "benchA/robot/joint_states"
        for _ in range(10):
            d.read()
            d.write(np.full(7, 0.3))
            d.tick()
        obs = d.read()
        assert obs.ok and np.all(obs.state[:7] - q0 > 0.05)
        d.stop()
        d.tick()
        d.tick()
        q_stop = d.read().state[:7]
        for _ in range(6):
            d.tick()
        assert np.abs(d.read().state[:7] - q_stop).max() < 0.02
        h = d.health()
        assert h.ok and h.corrupt_frames == 0 and h.frames_received > 20
    assert d.lifecycle is Lifecycle.UNCONFIGURED


def test_foreign_or_corrupt_joint_states_are_counted_not_used():
    """The newest sample is decoded in read(); one without our joints, or not CDR at all,
    leaves the last good state in place, counted as corrupt."""
    import time

    from hilstack.drivers.sawyer.driver import SawyerDriver

    d = SawyerDriver()
    good = ros.encode_joint_state(JOINTS, np.arange(7) * 0.1, np.zeros(7), np.zeros(7))
    for raw in (good, ros.encode_joint_state(["head_pan"], [0.0], [0.0], [0.0]), b"\x00\x01not cdr"):
        d._latest = (raw, time.monotonic())
        time.sleep(0.001)
        d._decode()
    assert d.health().corrupt_frames == 2
    np.testing.assert_allclose(d._state[:7], np.arange(7) * 0.1)
    assert "joint_states not usable" in d.health().last_error


def test_real_sawyer_without_endpoint_names_the_field():
    with pytest.raises(ConfigError, match="params.zenoh_connect"):
        make_driver("sawyer", backend="real").configure()
