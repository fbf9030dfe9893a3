"""The Baoding task: two balls rotating in the palm (Nagabandi et al., PDDM, CoRL 2019).

Pure functions, no MuJoCo: the sim backend, the emulator's tracker and the learning
code all use them.

* Targets: the two balls' target positions lie on an ellipse about ``center_m`` in the
  plane normal to ``axis`` (the palm normal): semi-axis ``radius_m`` along ``u`` (world x
  projected on the palm plane: across the palm) and ``radius_v_m`` along ``v = n × u``
  (along the fingers; ``None``: a circle), diametrically opposite, the phase turning at
  ``rate_rad_s`` (positive: counter-clockwise seen from above the palm). The reference code
  (google-research/pddm ``baoding_env.py``) uses 0.02 m × 0.036 m and a turn per 60 steps
  (6 s); configs/tasks/baoding.yaml sets those.
* Reward (thesis ch. 4; reference code): r = −5·Σ_i d(ball_i, target_i) − 500·1(drop)
  − 10·1(wrist > ``wrist_limit_rad``), positions in m; ``distance="plane"`` measures d in
  the palm plane (the reference's x-y distance), ``"3d"`` in space; the wrist term only
  when ``wrist_limit_rad`` is set (the reference penalises its wrist joint WRJ0 lifting
  past 0.15 rad).
* Drop: a ball is dropped once it is more than ``drop_below_m`` below the palm centre or
  more than ``drop_radius_m`` from it sideways; an episode ends at a drop or at 10 s.
* Target phase (``max_lead_rad``): the targets follow the clock, but never lead the pair's
  measured phase by more than ``max_lead_rad`` (:class:`TargetPhase`); without it a pair
  that lags by more than half a turn is pulled backwards (issue 30, item 5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REWARD_DIST_WEIGHT = 5.0
REWARD_DROP_PENALTY = 500.0
REWARD_WRIST_PENALTY = 10.0
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
    radius_v_m: float | None = None
    distance: str = "3d"
    wrist_limit_rad: float | None = None
    max_lead_rad: float | None = None
    #: a ball is "in the palm" (its turns count) within this of the palm centre sideways and
    #: no lower than ``in_palm_below_m`` below it; a ball flying off spins but is not turned
    in_palm_radius_m: float = 0.06
    in_palm_below_m: float = 0.02

    def __post_init__(self) -> None:
        if self.distance not in ("3d", "plane"):
            raise ValueError(f"BaodingTask.distance must be '3d' or 'plane', got {self.distance!r}")

    @property
    def radii(self) -> tuple[float, float]:
        return float(self.radius_m), float(self.radius_m if self.radius_v_m is None else self.radius_v_m)

    def _basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = np.asarray(self.axis, dtype=np.float64)
        n = n / np.linalg.norm(n)
        ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = ref - n * (ref @ n)
        u /= np.linalg.norm(u)
        return u, np.cross(n, u), n

    @property
    def normal(self) -> np.ndarray:
        """The palm's unit normal (``axis`` normalised): "up" out of the palm."""
        return self._basis()[2]

    def clock_phase(self, t_s: float) -> float:
        """The targets' phase [rad] at task time ``t_s`` by the clock alone."""
        return self.phase0_rad + self.rate_rad_s * t_s

    def targets_at(self, phase_rad) -> np.ndarray:
        """(..., 2, 3) target positions [m] at the targets' phase (scalar or array)."""
        u, v, _ = self._basis()
        ru, rv = self.radii
        th = np.asarray(phase_rad, dtype=np.float64)[..., None]
        c = np.asarray(self.center_m, dtype=np.float64)
        p = ru * np.cos(th) * u + rv * np.sin(th) * v
        return np.stack([c + p, c - p], axis=-2)

    def targets(self, t_s: float) -> np.ndarray:
        """(2, 3) target positions [m] at task time ``t_s`` (the clock's phase)."""
        return self.targets_at(self.clock_phase(t_s))

    def pair_phase(self, balls_m: np.ndarray) -> float:
        """The pair's phase [rad] on the targets' ellipse: the parameter θ whose targets
        point the same way as ball 0 − ball 1, in (−π, π]."""
        u, v, _ = self._basis()
        ru, rv = self.radii
        b = np.asarray(balls_m, dtype=np.float64).reshape(2, 3)
        d = 0.5 * (b[0] - b[1])
        return float(np.arctan2((d @ v) / rv, (d @ u) / ru))

    def distances(self, balls_m: np.ndarray, targets_m: np.ndarray) -> np.ndarray:
        """(2,) distance [m] of each ball to its target (in the palm plane or in space)."""
        d = np.asarray(balls_m, dtype=np.float64).reshape(2, 3) - np.asarray(targets_m).reshape(2, 3)
        if self.distance == "plane":
            _, _, n = self._basis()
            d = d - np.outer(d @ n, n)
        return np.linalg.norm(d, axis=1)

    def dropped(self, balls_m: np.ndarray) -> bool:
        """True when either ball left the hand (see module docstring)."""
        _, _, n = self._basis()
        d = np.asarray(balls_m, dtype=np.float64).reshape(2, 3) - np.asarray(self.center_m)
        h = d @ n
        side = np.linalg.norm(d - np.outer(h, n), axis=1)
        return bool(np.any(h < -self.drop_below_m) or np.any(side > self.drop_radius_m))

    def in_palm(self, balls_m: np.ndarray) -> bool:
        """True when both balls are in the palm (see the fields); stricter than not dropped."""
        _, _, n = self._basis()
        d = np.asarray(balls_m, dtype=np.float64).reshape(2, 3) - np.asarray(self.center_m)
        h = d @ n
        side = np.linalg.norm(d - np.outer(h, n), axis=1)
        return bool(np.all(h >= -self.in_palm_below_m) and np.all(side <= self.in_palm_radius_m))

    def reward(self, balls_m: np.ndarray, t_s: float | None = None, wrist_rad: float | None = None,
               phase_rad: float | None = None) -> float:
        """r at task time ``t_s`` (the clock's targets) or at the targets' ``phase_rad``;
        ``wrist_rad``: the wrist joint WRJ0 [rad], for the wrist term (when the task has one)."""
        b = np.asarray(balls_m, dtype=np.float64).reshape(2, 3)
        tgt = self.targets_at(self.clock_phase(t_s) if phase_rad is None else phase_rad)
        dist = float(self.distances(b, tgt).sum())
        r = -REWARD_DIST_WEIGHT * dist - REWARD_DROP_PENALTY * float(self.dropped(b))
        if self.wrist_limit_rad is not None and wrist_rad is not None and wrist_rad > self.wrist_limit_rad:
            r -= REWARD_WRIST_PENALTY
        return r

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


class TargetPhase:
    """The targets' phase for the plans of one episode (``max_lead_rad`` of the task).

    :meth:`observe` is called with each measured state's balls, once per control step (the
    first call is step 0, task time 0). :meth:`phases` gives the phases of steps
    ``k+1 .. k+H`` after step ``k``'s observation:

        φ_h = clock(k + h)                                      without ``max_lead_rad``
        φ_h = min(clock(k + h), θ_k + max_lead + ω·h·period)     with it (for ω > 0; mirrored for ω < 0)

    with θ_k the pair's measured phase, unwrapped over the episode from the clock's start.
    The targets then lead a lagging pair forward instead of, once it is more than half a
    turn behind, pulling it back the short way round.
    """

    def __init__(self, task: BaodingTask, period_s: float):
        self.task, self.period_s = task, float(period_s)
        self.reset()

    def reset(self) -> None:
        self.steps = 0
        self.theta: float | None = None

    def observe(self, balls_m: np.ndarray | None) -> None:
        if balls_m is not None and np.all(np.isfinite(balls_m)):
            th = self.task.pair_phase(balls_m)
            ref = self.task.phase0_rad if self.theta is None else self.theta
            self.theta = ref + float((th - ref + np.pi) % (2 * np.pi) - np.pi)
        self.steps += 1

    def phases(self, horizon: int) -> np.ndarray:
        """(H,) phases [rad] of the targets of steps k+1 .. k+H."""
        t, w = self.task, self.task.rate_rad_s
        k = max(self.steps - 1, 0)
        h = np.arange(1, horizon + 1, dtype=np.float64)
        clock = t.clock_phase(0.0) + w * (k + h) * self.period_s
        if t.max_lead_rad is None or self.theta is None:
            return clock
        lead = self.theta + np.sign(w) * t.max_lead_rad + w * h * self.period_s
        return np.minimum(clock, lead) if w >= 0 else np.maximum(clock, lead)
