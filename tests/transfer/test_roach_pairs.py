"""VelociRoACH expert/novice pairs: the configs load, the heightfield patch reads the ground."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from hilstack.drivers.velociroach.config import VelociRoachParams
from hilstack.learning.transfer.roach_pairs import (
    EXPERT,
    PAIRS,
    PATCH_XY_M,
    collect,
    terrain_patch_m,
    transitions,
)
from hilstack.sim_backends.velociroach.backend import VelociRoachSim


def ground_height_m(sim: VelociRoachSim, x: float, y: float) -> float:
    """Height of the ground under (x, y) by a downward MuJoCo ray from 0.5 m."""
    geomid = np.zeros(1, np.int32)
    dist = mujoco.mj_ray(sim.model, sim.data, np.array([x, y, 0.5]), np.array([0.0, 0.0, -1.0]),
                         None, 1, sim.model.body("chassis").id, geomid)
    return 0.5 - dist


@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_patch_is_the_ground_under_the_body_frame_grid(yaw):
    sim = VelociRoachSim(VelociRoachParams(sim={"terrain": "gravel", "terrain_half_size_m": 0.5, "seed": 3}))
    sim.configure()
    sim.reset(x=0.13, y=-0.21, yaw=yaw)
    sim.data.qpos[2] = 1.0  # lift the robot out of the rays' way (x, y and yaw unchanged)
    mujoco.mj_forward(sim.model, sim.data)
    patch = terrain_patch_m(sim)
    c, s = math.cos(yaw), math.sin(yaw)
    want = [ground_height_m(sim, 0.13 + c * dx - s * dy, -0.21 + s * dx + c * dy) for dx, dy in PATCH_XY_M]
    assert np.ptp(want) > 1e-4  # the terrain is rough here: the comparison means something
    np.testing.assert_allclose(patch, want, atol=3e-4)  # bilinear vs MuJoCo's triangles
    sim.cleanup()


def test_patch_is_zero_on_a_plane():
    sim = VelociRoachSim(VelociRoachParams(sim={"terrain": "carpet"}))
    sim.configure()
    assert np.all(terrain_patch_m(sim) == 0.0)
    sim.cleanup()


def test_pairs_load_and_collect_transitions():
    for ov in (EXPERT, *PAIRS.values()):
        VelociRoachSim(VelociRoachParams(**ov))  # config validates
    r = collect(PAIRS["dissimilar"], minutes=2.0 / 60.0, seed=0, episode_s=1.0)
    assert r.states.shape == (2, 11, 24) and r.actions.shape == (2, 10, 2) and r.patches.shape == (2, 10, 9)
    assert np.abs(r.actions).max() <= 10.0 + 1e-9  # the novice's leg-speed scaling
    tr = transitions(r)
    assert tr.x.shape == (20, 33) and tr.y.shape == (20, 24)
    np.testing.assert_allclose(tr.y, (r.states[:, 1:] - r.states[:, :-1]).reshape(-1, 24), rtol=1e-5, atol=1e-6)
