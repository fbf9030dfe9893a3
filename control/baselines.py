"""Hand-designed baselines for comparison with MPC.

Differential-drive path follower (the thesis' VelociRoACH baseline): steer toward the
current segment's direction, corrected by the signed perpendicular error, and drive the
two leg sets at ``ω_nom ± d``. The current segment is tracked with the cost's progress
window (:meth:`hilstack.control.costs.PathCost.observe`), so at a figure-8 crossing the baseline
follows the branch it is on:

    e_ψ   = wrap(θ_seg − ψ)                 heading error to the current segment (rad)
    e_⊥   = t̂ × (p − p_closest)             signed lateral offset, >0 = robot left of path (m)
    d     = clip(k_ψ e_ψ − k_⊥ e_⊥, −d_max, d_max)
    left  = ω_nom − d,   right = ω_nom + d  (clipped to ±max_action, the speed setting)

A positive ``d`` turns the robot left (right legs faster).

Tipping (issue 29): given ``tip_threshold_rad`` (the MPC cost's θ_tip, the same
information), the correction is scaled by ``max(0, 1 − e/θ_tip)`` where ``e`` is the
measured roll and pitch beyond θ_tip (:func:`hilstack.control.costs.tilt_excess_rad`): the
robot stops turning harder as it rolls past the threshold and runs straight at 2·θ_tip. Actions are normalized leg
speed commands in [−1, 1] (the driver maps them to rad/s).

Default gains (normalized action per unit error): ``omega_nom = 0.6``, ``k_heading = 0.8``
per rad, ``k_perp = 4.0`` per m, ``d_max = 0.4``: at 10 cm lateral error the correction
equals ~0.5 rad of heading error, and ``d`` never exceeds what still leaves both leg sets
moving forward at ``omega_nom``. These are starting points, not tuned values: `hil demo`
tunes them per speed (:meth:`hilstack.learning.mbrl.MbrlRun.tune_baseline`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from hilstack.control.costs import PathCost, state_index, tilt_excess_rad

__all__ = ["DifferentialDriveController"]


class DifferentialDriveController:
    """``controller(state [S]) -> action [2]`` (left, right) in [−1, 1]. See module docstring."""

    def __init__(
        self,
        waypoints,
        state_names: Sequence[str],
        omega_nom: float = 0.6,
        k_heading: float = 0.8,
        k_perp: float = 4.0,
        d_max: float = 0.4,
        *,
        max_action: float = 1.0,
        tip_threshold_rad: float | None = None,
        x: str = "x",
        y: str = "y",
        cos_yaw: str = "cos_yaw",
        sin_yaw: str = "sin_yaw",
    ) -> None:
        # the path geometry and channel lookup are the cost's: both see the same path
        self.path = path = PathCost(waypoints, state_names, x=x, y=y, cos_yaw=cos_yaw, sin_yaw=sin_yaw)
        self.seg_start, self.seg_vec = path.seg_start, path.seg_vec
        self.ix, self.iy, self.ic, self.is_ = path.ix, path.iy, path.ic, path.is_
        self.omega_nom, self.k_heading, self.k_perp, self.d_max = omega_nom, k_heading, k_perp, d_max
        self.max_action = float(max_action)  # the speed setting: the same bound MPC plans within
        self.tip_threshold_rad = None if tip_threshold_rad is None else float(tip_threshold_rad)
        if self.tip_threshold_rad is not None:
            if not 0.0 < self.tip_threshold_rad < np.pi / 2:
                raise ValueError(f"tip_threshold_rad must be in (0, pi/2), got {tip_threshold_rad}")
            try:
                self.tilt_idx = tuple(state_index(state_names, n)
                                      for n in ("cos_roll", "sin_roll", "cos_pitch", "sin_pitch"))
            except KeyError as e:
                raise ValueError(f"tip_threshold_rad needs roll and pitch channels: {e.args[0]}") from None

    def params(self) -> dict[str, float]:
        """The tunable gains (what a tuning search records)."""
        return {"omega_nom": self.omega_nom, "k_heading": self.k_heading, "k_perp": self.k_perp, "d_max": self.d_max}

    def reset(self) -> None:
        """A new episode: back to the path's first segment."""
        self.path.reset()

    def errors(self, state) -> tuple[float, float]:
        """``(heading error rad, signed lateral offset m)`` for one state ``[S]`` (world frame);
        advances the tracked segment."""
        s = torch.as_tensor(np.asarray(state, dtype=np.float32))
        p = s[[self.ix, self.iy]]
        idx = self.path.observe(s)
        a, d = self.seg_start[idx], self.seg_vec[idx]
        unit = d / d.norm().clamp_min(1e-12)
        t = ((p - a) @ d / (d @ d).clamp_min(1e-12)).clamp(0, 1)
        off = p - (a + t * d)
        lateral = float(unit[0] * off[1] - unit[1] * off[0])
        c, sn = float(s[self.ic]), float(s[self.is_])
        ux, uy = float(unit[0]), float(unit[1])
        heading = float(np.arctan2(c * uy - sn * ux, c * ux + sn * uy))  # wrap(θ − ψ)
        return heading, lateral

    def __call__(self, state) -> np.ndarray:
        e_h, e_p = self.errors(state)
        d = float(np.clip(self.k_heading * e_h - self.k_perp * e_p, -self.d_max, self.d_max))
        if self.tip_threshold_rad is not None:
            s = torch.as_tensor(np.asarray(state, dtype=np.float32))
            excess = float(tilt_excess_rad(s, self.tilt_idx, self.tip_threshold_rad))
            d *= max(0.0, 1.0 - excess / self.tip_threshold_rad)
        a = np.array([self.omega_nom - d, self.omega_nom + d], dtype=np.float32)
        return np.clip(a, -self.max_action, self.max_action)
