"""A tiny planar robot for the adaptation tests: fast, exact, with a perturbation knob.

State ``[x, y, vx, vy, cos_yaw, sin_yaw]`` (m, m/s, world frame); action ``[speed, turn]``
normalized to [-1, 1]. ``gain`` scales the speed (a payload or a lost leg), ``turn_bias``
adds a turn the action did not ask for (an asymmetric leg).
"""

from __future__ import annotations

import numpy as np

from hilstack.learning.datasets import Episode

NAMES = ["x", "y", "vx", "vy", "cos_yaw", "sin_yaw"]
DT_S = 0.1


def step(s: np.ndarray, a: np.ndarray, gain: float = 1.0, turn_bias: float = 0.0) -> np.ndarray:
    yaw = np.arctan2(s[5], s[4]) + DT_S * (2.0 * a[1] + turn_bias)
    v = 0.5 * gain * a[0]
    vx, vy = v * np.cos(yaw), v * np.sin(yaw)
    return np.array([s[0] + DT_S * vx, s[1] + DT_S * vy, vx, vy, np.cos(yaw), np.sin(yaw)], dtype=np.float32)


def episodes(n: int, steps: int, seed: int, gain: float = 1.0, turn_bias: float = 0.0) -> list[Episode]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        yaw = rng.uniform(-np.pi, np.pi)
        s = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 0, 0, np.cos(yaw), np.sin(yaw)], dtype=np.float32)
        states, actions = [s], []
        for _ in range(steps):
            a = rng.uniform(-1, 1, 2).astype(np.float32)
            s = step(s, a, gain, turn_bias)
            states.append(s)
            actions.append(a)
        out.append(Episode(np.array(states), np.array(actions), name=f"toy{seed}-{i}"))
    return out
