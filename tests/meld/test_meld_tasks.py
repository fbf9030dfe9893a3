"""The image tasks of `hil demo meld` on the sim backends, built through the registry."""

import math

import numpy as np
import pytest

from hilstack.tools.meld_tasks import TASKS, reach_reward


def test_widowx_port_tasks_are_set_by_the_mechanism():
    env = TASKS["widowx_port"](camera_px=16)
    try:
        assert len(env.train_tasks) == 20 and len(env.test_tasks) == 10
        env.set_task(0)   # −8°, −1 cm
        g0 = env.goal.copy()
        rot, off = (float(v) for v in env.mech.read().state[:2])
        assert rot == pytest.approx(-math.radians(8), abs=0.01) and off == pytest.approx(-0.01, abs=0.001)
        env.set_task(19)  # +8°, +1 cm
        g19 = env.goal.copy()
        # the port is 3 cm in front of the housing's axis: y = offset − 0.03·sin(rotation)
        assert g19[1] - g0[1] == pytest.approx(0.02 - 2 * 0.03 * math.sin(math.radians(8)), abs=0.002)
        # the port the mechanism measured is the port in the simulated world
        assert np.allclose(env.goal, env.arm.world.port_pose()[0], atol=1e-3)
        img, r = env.reset()
        assert img.shape == (16, 32, 3) and img.dtype == np.uint8
        img2, r2, info = env.step(np.ones(env.action_dim))
        assert r2 == pytest.approx(reach_reward(info["distance_m"]))
        assert info["distance_m"] == pytest.approx(float(np.linalg.norm(env.arm.world.ee_pos() - env.goal)), abs=1e-3)
        assert not np.array_equal(img, img2)  # the arm moved in the pictures
    finally:
        env.close()


def test_sawyer_reach_tasks_from_images():
    pytest.importorskip("metaworld", reason="the Sawyer model needs metaworld's assets")
    env = TASKS["sawyer_reach"](camera_px=16)
    try:
        env.set_task(3)
        img, r = env.reset()
        assert img.shape == (16, 32, 3)
        _, r2, info = env.step(-np.ones(env.action_dim))
        ee = np.asarray(env.arm.read().extras["ee_pos_m"])
        assert info["distance_m"] == pytest.approx(float(np.linalg.norm(ee - env.task_params[3])), abs=1e-3)
        assert info["success"] == (info["distance_m"] < 0.1)
        # holding still succeeds on no task: every goal is beyond the success radius of the start
        env.reset()
        start = np.asarray(env.arm.read().extras["ee_pos_m"])
        assert min(np.linalg.norm(env.task_params - start, axis=1)) > env.success_m
    finally:
        env.close()
