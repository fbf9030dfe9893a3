"""The Baoding task: two balls rotating in the palm (Nagabandi et al., PDDM, CoRL 2019).

Pure functions, no MuJoCo: the sim backend, the emulator's tracker and the learning
code all use them.

* Targets: the two balls' target positions lie on a circle of radius ``radius_m`` about
  ``center_m`` in the plane normal to ``axis`` (the palm normal), diametrically opposite,
  rotating at ``rate_rad_s`` (positive: counter-clockwise seen from above the palm).
* Reward (thesis ch. 4): r = −5·Σ_i ‖ball_i − target_i‖ − 500·1(drop), positions in m.
* Drop: a ball is dropped once it is more than ``drop_below_m`` below the palm centre or
  more than ``drop_radius_m`` from it sideways; an episode ends at a drop or at 10 s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REWARD_DIST_WEIGHT = 5.0
REWARD_DROP_PENALTY = 500.0
EPISODE_S = 10.0


@dataclass(frozen=True)
class BaodingTask:
    """Geometry of the task in the world frame [m]; ``axis`` is the palm normal (unit)."""

    center_m: np.ndarray
    axis: np.ndarray
    radius_m: float = 0.025
    rate_rad_s: float = np.pi / 5.0  # half a turn in 5 s
    phase0_rad: float = 0.0
    drop_below_m: float = 0.04
    drop_radius_m: float = 0.12

    def _basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = np.asarray(self.axis, dtype=np.float64)
        n = n / np.linalg.norm(n)
        ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = ref - n * (ref @ n)
        u /= np.linalg.norm(u)
        return u, np.cross(n, u), n

    def targets(self, t_s: float) -> np.ndarray:
        """(2, 3) target positions [m] at task time ``t_s``."""
        u, v, _ = self._basis()
        th = self.phase0_rad + self.rate_rad_s * t_s
        c = np.asarray(self.center_m, dtype=np.float64)
        p = self.radius_m * (np.cos(th) * u + np.sin(th) * v)
        return np.stack([c + p, c - p])

    def dropped(self, balls_m: np.ndarray) -> bool:
        """True when either ball left the hand (see module docstring)."""
        _, _, n = self._basis()
        d = np.asarray(balls_m, dtype=np.float64).reshape(2, 3) - np.asarray(self.center_m)
        h = d @ n
        side = np.linalg.norm(d - np.outer(h, n), axis=1)
        return bool(np.any(h < -self.drop_below_m) or np.any(side > self.drop_radius_m))

    def reward(self, balls_m: np.ndarray, t_s: float) -> float:
        b = np.asarray(balls_m, dtype=np.float64).reshape(2, 3)
        dist = float(np.linalg.norm(b - self.targets(t_s), axis=1).sum())
        return -REWARD_DIST_WEIGHT * dist - REWARD_DROP_PENALTY * float(self.dropped(b))

    def rotation_rad(self, balls_start_m: np.ndarray, balls_m: np.ndarray) -> float:
        """How far the pair turned about the palm normal [rad] between two samples, in
        (−π, π], positive in the targets' direction of rotation."""
        u, v, _ = self._basis()

        def ang(b: np.ndarray) -> float:
            d = b[0] - b[1]
            return float(np.arctan2(d @ v, d @ u))

        da = ang(np.asarray(balls_m).reshape(2, 3)) - ang(np.asarray(balls_start_m).reshape(2, 3))
        da = (da + np.pi) % (2 * np.pi) - np.pi
        return da if self.rate_rad_s >= 0 else -da
