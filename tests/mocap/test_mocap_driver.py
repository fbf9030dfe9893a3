"""The mocap sensor driver over a real UDP pose stream on loopback."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import CommandError, Lifecycle, LinkError
from hilstack.drivers.mocap.udp import PoseStreamServer
from hilstack.drivers.registry import make_driver
from tests.helpers import free_port, wait_for


def test_pose_health_staleness_and_corruption():
    port = free_port()
    with make_driver("mocap", port=port, stale_after_s=0.05) as d, PoseStreamServer("127.0.0.1", port) as srv:
        first = d.read()  # nothing yet
        assert not first.ok and first.flags["stale_pose"] and d.health().extra["pose_age_s"] is None
        srv.send(1.0, [0.5, -0.25, 0.1], [0.0, 0.0, 0.0, 1.0])
        obs = wait_for(lambda: (o := d.read()).ok and o, 2.0, "first pose")
        np.testing.assert_allclose(obs.state, [0.5, -0.25, 0.1, 0.0, 0.0, 0.0, 1.0])
        assert obs.extras["source_t_s"] == 1.0
        srv.send_raw(b"\x00" * 10)  # corrupt datagram
        srv.skip(3)  # three lost samples
        srv.send(1.1, [0.6, -0.25, 0.1], [0.0, 0.0, 0.0, 1.0])
        wait_for(lambda: d.health().corrupt_frames == 1 and d.health().dropped_frames == 3, 2.0, "counters")
        time.sleep(0.1)  # no new pose: stale
        obs = d.read()
        assert not obs.ok and obs.flags["stale_pose"] and not obs.flags["nonfinite_input"]
        assert not d.health().ok and d.health().extra["pose_age_s"] > 0.05
        with pytest.raises(CommandError, match="shape"):
            d.write([0.0])


def test_nonfinite_pose_is_flagged_and_not_used():
    port = free_port()
    with make_driver("mocap", port=port, stale_after_s=0.5) as d, PoseStreamServer("127.0.0.1", port) as srv:
        srv.send(1.0, [0.5, 0.0, 0.1], [1.0, 0.0, 0.0, 0.0])
        wait_for(lambda: d.read().ok, 2.0, "first pose")
        srv.send(1.01, [float("nan"), 0.0, 0.1], [1.0, 0.0, 0.0, 0.0])
        obs = wait_for(lambda: (o := d.read()).flags["nonfinite_input"] and o, 2.0, "the NaN pose")
        assert obs.ok is False and not obs.flags["stale_pose"]
        np.testing.assert_allclose(obs.state, [0.5, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])  # the last finite pose
        assert obs.extras["source_t_s"] == 1.0
        assert d.health().extra["pose_nonfinite_samples"] == 1
        srv.send(1.02, [0.6, 0.0, 0.1], [1.0, 0.0, 0.0, 0.0])
        # (the NaN is flagged on one read; a read before the new pose arrives is ok with the old one)
        obs = wait_for(lambda: (o := d.read()).state[0] == pytest.approx(0.6) and o, 2.0, "a finite pose again")
        assert obs.ok and not obs.flags["nonfinite_input"]


def test_bad_source_is_a_config_error():
    with pytest.raises(ConfigError, match="params.source"):
        make_driver("mocap", source="vicon")


def _use_a_pose_then(srv, d, t, position, quaternion, what):
    """A good pose (read ok), then the bad one: returns the reading that reports it."""
    srv.send(t, [0.5, 0.0, 0.1], [1.0, 0.0, 0.0, 0.0])
    wait_for(lambda: (o := d.read()).ok and o.extras["source_t_s"] == t, 2.0, f"a good pose before {what}")
    before = d.health().extra["pose_invalid_samples"]
    srv.send(t + 0.001, position, quaternion)
    obs = wait_for(lambda: (o := d.read()).flags["invalid_input"] and o, 2.0, f"{what} flagged")
    assert d.health().extra["pose_invalid_samples"] == before + 1, what
    return obs


BAD_POSES = [
    ("a zero quaternion", [0.5, 0.0, 0.1], [0.0, 0.0, 0.0, 0.0], "norm 0"),
    ("a half-norm quaternion", [0.5, 0.0, 0.1], [0.5, 0.0, 0.0, 0.0], "norm 0.5"),
    ("a position 1e30 m away", [1e30, 0.0, 0.1], [1.0, 0.0, 0.0, 0.0], "outside the volume"),
    ("a position below the floor", [0.5, 0.0, -3.0], [1.0, 0.0, 0.0, 0.0], "outside the volume"),
]


def test_impossible_poses_over_udp_are_rejected_counted_and_do_not_refresh():
    """Issue 22, item 4: a zero quaternion or a pose far outside the arena is not a healthy
    reading: not used, flagged invalid_input, counted; a stream of them goes stale and then
    takes the error path after link_timeout_periods."""
    port = free_port()
    with make_driver("mocap", port=port, stale_after_s=0.2, link_timeout_periods=100) as d, \
            PoseStreamServer("127.0.0.1", port) as srv:
        for k, (what, pos, quat, why) in enumerate(BAD_POSES):
            obs = _use_a_pose_then(srv, d, float(k), pos, quat, what)
            assert obs.ok is False and not obs.flags["nonfinite_input"], what
            np.testing.assert_allclose(obs.state, [0.5, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])  # the last usable pose
            assert obs.extras["source_t_s"] == float(k), what
            assert why in d.health().extra["pose_last_invalid"], what
        # only bad poses now: they do not refresh the pose, it goes stale, then the error path
        t0 = time.monotonic()

        def bad_stream():
            srv.send(10.0 + time.monotonic() - t0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0])
            return d.read()

        stale = wait_for(lambda: (o := bad_stream()).flags["stale_pose"] and o, 3.0, "stale under bad poses")
        assert stale.ok is False and d.health().extra["pose_age_s"] > 0.2
        with pytest.raises(LinkError, match=r"no usable pose for .* 100 control periods"):
            wait_for(lambda: bad_stream() is None, 10.0, "the error path")
        assert d.lifecycle is Lifecycle.UNCONFIGURED


def test_impossible_poses_from_natnet_are_rejected(monkeypatch):
    """The NatNet source (frames as the natnet package hands them to its callback; no Motive
    server here): its conversion keeps a broken quaternion broken, and the driver rejects it."""
    from types import SimpleNamespace

    from hilstack.drivers.mocap.natnet_client import NatNetPoseSource

    monkeypatch.setattr(NatNetPoseSource, "connect", lambda self, timeout_s=5.0: None)
    monkeypatch.setattr(NatNetPoseSource, "close", lambda self: None)
    with make_driver("mocap", source="natnet", up_axis="z", stale_after_s=0.5) as d:
        src = d.pose_source

        def frame(n, pos, rot_xyzw):
            rb = SimpleNamespace(id_num=1, pos=pos, rot=rot_xyzw, tracking_valid=True)
            src._on_frame(SimpleNamespace(prefix=SimpleNamespace(frame_number=n),
                                          suffix=SimpleNamespace(timestamp=n / 120), rigid_bodies=[rb]))

        frame(1, (0.5, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0))
        assert d.read().ok
        for n, (what, pos, quat, why) in enumerate(BAD_POSES, start=2):
            frame(n, tuple(pos), (*quat[1:], quat[0]))  # NatNet sends x, y, z, w
            obs = d.read()
            assert obs.flags["invalid_input"] and not obs.ok, what
            assert why in d.health().extra["pose_last_invalid"], what
            np.testing.assert_allclose(obs.state, [0.5, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0])
        assert d.health().extra["pose_invalid_samples"] == len(BAD_POSES)
        # its counters reach the driver's health (a declared PoseSource.stats()): frames of the
        # body, and the frames a jump in the frame number says were missed
        frame(len(BAD_POSES) + 5, (0.5, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0))
        h = d.health()
        assert (h.frames_received, h.dropped_frames) == (len(BAD_POSES) + 2, 3)
        assert d.port is None  # NatNet listens on the server's ports, none of its own


def test_volume_tolerance_and_timeout_are_bounded_config_values():
    for bad in ({"volume_min_m": [0, 0, 0], "volume_max_m": [1, 1, 0]}, {"volume_max_m": [1e30, 1, 1]},
                {"quat_norm_tol": 0.5}, {"quat_norm_tol": 0}, {"link_timeout_periods": 5},
                {"link_timeout_periods": 10**6}, {"stale_after_s": float("inf")}):
        with pytest.raises(ConfigError, match="params"):
            make_driver("mocap", **bad)
