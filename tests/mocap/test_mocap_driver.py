"""The mocap sensor driver over a real UDP pose stream on loopback."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import CommandError
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
