"""The wheeled robot of the SIDM setting (sim_backends/wheeled) and its expert/novice pairs."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from hilstack.drivers.registry import make_backend
from hilstack.learning.transfer import wheeled_pairs as W


def _sim(**params):
    sim = make_backend("wheeled", "sim", **params)
    sim.configure()
    sim.activate()
    return sim


def _drive(sim, cmd, steps):
    out = []
    for _ in range(steps):
        sim.write(np.asarray(cmd, float))
        sim.tick()
        out.append(sim.read().state)
    return np.array(out)


@pytest.mark.parametrize("pair", ["expert", "similar", "dissimilar"])
def test_every_suspension_rests_mid_travel_on_flat_ground(pair):
    ov = W.EXPERT if pair == "expert" else W.PAIRS[pair]
    sim = _sim(**ov, terrain_rms_m=0.0)
    sim.reset(settle_s=2.0)
    s = sim.read().state
    assert np.all(np.abs(s[12:16]) < 0.1 * ov["travel_m"]), s[12:16]  # preloaded to mid-travel
    assert abs(s[3]) < 1e-3 and abs(s[4]) < 1e-3  # level
    sim.cleanup()


def test_drives_at_wheel_speed_times_radius_and_turns_left_on_a_right_wheel_lead():
    sim = _sim(terrain_rms_m=0.0)
    sim.reset()
    s = _drive(sim, (10.0, 10.0), 20)
    assert s[-1, 6] == pytest.approx(10.0 * sim.params.wheel_radius_m, rel=0.1)  # body-frame forward speed
    assert abs(s[-1, 7]) < 0.05 and abs(s[-1, 11]) < 0.05
    sim.reset()
    s = _drive(sim, (-10.0, 10.0), 10)
    assert s[-1, 11] > 0.1 and s[-1, 5] > 0.05  # counter-clockwise: yaw rate and yaw grow (skid steering)
    sim.reset()
    assert _drive(sim, (10.0, -10.0), 10)[-1, 11] < -0.1
    sim.cleanup()


def test_stiffer_suspension_deflects_less_on_rough_ground():
    stds = {}
    for name, ov in (("expert", W.EXPERT), ("similar", W.PAIRS["similar"]), ("dissimilar", W.PAIRS["dissimilar"])):
        sim = _sim(**ov, terrain_rms_m=0.03, seed=3)
        sim.reset(yaw=0.5)
        s = _drive(sim, (15.0, 15.0), 30)
        stds[name] = float(s[:, 12:16].std())
        assert np.all(np.abs(s[:, 12:16]) <= ov["travel_m"] + 2e-3)  # within travel (soft limits)
        sim.cleanup()
    assert stds["expert"] > 1.5 * stds["similar"] > 1.5 * 20 * stds["dissimilar"], stds


def test_patch_is_the_ground_around_the_chassis_in_its_yaw_frame():
    sim = _sim(terrain_rms_m=0.03, seed=5)
    sim.reset(x=1.0, y=-2.0, yaw=2.0)
    m, d = sim.model, sim.data
    patch = sim.terrain_patch_m(W.PATCH_XY_M)
    yaw = sim.read().state[5]
    c, s = math.cos(yaw), math.sin(yaw)
    ground = m.geom("ground").id
    geomid = np.zeros(1, np.int32)
    for (dx, dy), h in zip(W.PATCH_XY_M, patch, strict=True):
        x, y = d.qpos[0] + c * dx - s * dy, d.qpos[1] + s * dx + c * dy
        top = 1.0
        # cast against group 0 only: the terrain (the robot's geoms are group 1)
        dist = mujoco.mj_ray(m, d, np.array([x, y, top]), np.array([0.0, 0.0, -1.0]),
                             np.array([1, 0, 0, 0, 0, 0], np.uint8), 1, -1, geomid)
        assert geomid[0] == ground
        assert top - dist - d.qpos[2] == pytest.approx(h, abs=3e-3)  # bilinear vs MuJoCo's triangles
    sim.cleanup()


def test_state_change_is_in_the_start_yaw_frame_and_wraps_yaw():
    s0 = np.zeros((2, 24))
    s1 = np.zeros((2, 24))
    s0[0, 5], s1[0, :2], s1[0, 5] = math.pi / 2, (0.0, 1.0), math.pi / 2  # moved along +y facing +y: forward
    s0[1, 5], s1[1, 5] = 3.1, -3.1  # across ±π: a small left turn
    d = W.state_change(s0, s1)
    np.testing.assert_allclose(d[0, :2], (1.0, 0.0), atol=1e-12)
    assert d[1, 5] == pytest.approx(2 * math.pi - 6.2)
