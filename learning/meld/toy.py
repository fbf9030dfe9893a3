"""A point reacher drawn in tiny images: the point is visible, the goal (the task) is not, so
only the reward tells tasks apart, as in MELD's reacher. Used by tests and as a fast check of
the learners (seconds, no MuJoCo)."""

from __future__ import annotations

from typing import Any

import numpy as np


class ToyReach:
    """A point in [−1, 1]² moved by actions × ``step``; the image is ``hw`` with a bright
    square at the point on the left half (the 'fixed camera') and the right half blank.
    Reward ``−(d² + log(d + 1e-5))`` (thesis ch. 7); success ``d < success_d`` at the end."""

    action_dim = 2
    task_param_names = ("goal_x", "goal_y")

    def __init__(self, hw: tuple[int, int] = (8, 16), episode_steps: int = 10, n_train: int = 4, n_test: int = 2,
                 step: float = 0.25, success_d: float = 0.25, seed: int = 0):
        rng = np.random.default_rng(seed)
        n = n_train + n_test
        ang = rng.uniform(0, 2 * np.pi, n)
        self.task_params = np.stack([0.7 * np.cos(ang), 0.7 * np.sin(ang)], 1)
        self.train_tasks, self.test_tasks = list(range(n_train)), list(range(n_train, n))
        self.hw, self.episode_steps, self.step_size, self.success_d = hw, episode_steps, step, success_d
        self.goal = self.task_params[0]
        self.p = np.zeros(2)

    def set_task(self, task: int) -> None:
        self.goal = self.task_params[task]

    def _obs(self) -> tuple[np.ndarray, float]:
        h, w = self.hw
        img = np.zeros((h, w, 3), np.uint8)
        i = int(np.clip((self.p[1] + 1) / 2 * (h - 1), 0, h - 1))
        j = int(np.clip((self.p[0] + 1) / 2 * (w // 2 - 1), 0, w // 2 - 1))
        img[max(i - 1, 0):i + 1, max(j - 1, 0):j + 1] = 255
        d = float(np.linalg.norm(self.p - self.goal))
        return img, -(d * d + np.log(d + 1e-5))

    def reset(self) -> tuple[np.ndarray, float]:
        self.p = np.zeros(2)
        return self._obs()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, dict[str, Any]]:
        self.p = np.clip(self.p + self.step_size * np.clip(action, -1, 1), -1, 1)
        img, r = self._obs()
        d = float(np.linalg.norm(self.p - self.goal))
        return img, r, {"success": d < self.success_d, "distance_m": d}

    def close(self) -> None:
        """Nothing to release (:class:`~hilstack.learning.meld.train.ImageTaskEnv`)."""
