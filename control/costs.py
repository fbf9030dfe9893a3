"""Task costs for MPC, vectorized in torch over [E, N, H].

Path following (Nagabandi et al. 2018, VelociRoACH). For each predicted state ``s_h``
(h = 1..H) of a candidate, with ``p_h`` the (x, y) position and ``ψ_h`` the yaw:

* the closest segment of the waypoint polyline to ``p_h`` (unit direction ``t̂``, angle θ),
* ``perp_h``     = distance from ``p_h`` to that segment (m),
* ``heading_h``  = |wrap(ψ_h − θ)| (rad),
* ``progress_h`` = (p_h − p_{h−1}) · t̂ (m, forward motion along that segment),

    c = Σ_h  f_p · perp_h + f_h · heading_h − f_f · progress_h

with the thesis weights f_p = 50, f_f = 10, f_h = 5. The same function scores an executed
trajectory (:func:`evaluate_path_following`), so MPC and baselines are compared with one
metric.

Limitation: the closest segment is the global one, so on self-crossing paths (figure-8)
a state at the crossing may be matched to either branch.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

__all__ = ["PathCost", "closest_segment", "evaluate_path_following", "state_index"]


def state_index(state_names: Sequence[str], *candidates: str) -> int:
    """Index of the first of ``candidates`` found in ``state_names`` (case-insensitive)."""
    lower = [n.lower() for n in state_names]
    for c in candidates:
        if c.lower() in lower:
            return lower.index(c.lower())
    raise KeyError(f"none of {candidates} in state names {list(state_names)}")


def closest_segment(p: torch.Tensor, a: torch.Tensor, d: torch.Tensor):
    """Closest polyline segment to each point.

    Args:
        p: ``[..., 2]`` points; ``a``: ``[G, 2]`` segment starts; ``d``: ``[G, 2]`` segment vectors.
    Returns:
        ``(index [...], distance [...], unit direction [..., 2])`` of the closest segment.
    """
    rel = p.unsqueeze(-2) - a  # [..., G, 2]
    len2 = (d * d).sum(-1).clamp_min(1e-12)  # [G]
    t = ((rel * d).sum(-1) / len2).clamp(0.0, 1.0)  # [..., G]
    diff = rel - t.unsqueeze(-1) * d
    dist2 = (diff * diff).sum(-1)
    dist2_min, idx = dist2.min(dim=-1)
    unit = d / len2.sqrt().unsqueeze(-1)
    return idx, dist2_min.sqrt(), unit[idx]


class PathCost:
    """Path-following cost ``cost(states [E,N,H+1,S], actions [N,H,A]) -> [E,N]``.

    Args:
        waypoints: ``[P, 2]`` polyline in metres (see :mod:`control.paths`).
        state_names: names of the S state channels; the x, y, cos(yaw), sin(yaw) channels are
            looked up by name (``x``/``y``/``cos_yaw``/``sin_yaw`` by default, override with
            ``x=``, ``y=``, ``cos_yaw=``, ``sin_yaw=``).
        f_p, f_h, f_f: weights of perpendicular distance (1/m), heading error (1/rad) and
            forward progress (1/m).
    """

    def __init__(
        self,
        waypoints,
        state_names: Sequence[str],
        f_p: float = 50.0,
        f_h: float = 5.0,
        f_f: float = 10.0,
        *,
        x: str = "x",
        y: str = "y",
        cos_yaw: str = "cos_yaw",
        sin_yaw: str = "sin_yaw",
    ) -> None:
        wp = torch.as_tensor(np.asarray(waypoints, dtype=np.float32))
        if wp.dim() != 2 or wp.shape[1] != 2 or wp.shape[0] < 2:
            raise ValueError(f"waypoints must be [P>=2, 2], got {tuple(wp.shape)}")
        self.waypoints = wp
        self.seg_start = wp[:-1]
        self.seg_vec = wp[1:] - wp[:-1]
        self.f_p, self.f_h, self.f_f = float(f_p), float(f_h), float(f_f)
        self.ix = state_index(state_names, x)
        self.iy = state_index(state_names, y)
        self.ic = state_index(state_names, cos_yaw, "cos yaw", "yaw_cos")
        self.is_ = state_index(state_names, sin_yaw, "sin yaw", "yaw_sin")

    def terms(self, states: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per-step terms for ``states [..., H+1, S]``: each ``[..., H]`` (steps 1..H)."""
        p = states[..., [self.ix, self.iy]]  # [..., H+1, 2]
        _, perp, unit = closest_segment(p[..., 1:, :], self.seg_start, self.seg_vec)
        progress = ((p[..., 1:, :] - p[..., :-1, :]) * unit).sum(-1)
        c, s = states[..., 1:, self.ic], states[..., 1:, self.is_]
        # angle between the heading (c, s) and the segment direction, without unwrapping
        heading = torch.atan2(c * unit[..., 1] - s * unit[..., 0], c * unit[..., 0] + s * unit[..., 1]).abs()
        return {"perp_m": perp, "heading_rad": heading, "progress_m": progress}

    def step_cost(self, states: torch.Tensor) -> torch.Tensor:
        """Cost of each step ``[..., H]`` for ``states [..., H+1, S]``."""
        t = self.terms(states)
        return self.f_p * t["perp_m"] + self.f_h * t["heading_rad"] - self.f_f * t["progress_m"]

    def __call__(self, states: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
        """``states [E, N, H+1, S]`` (actions unused) → ``[E, N]``."""
        return self.step_cost(states).sum(-1)


def evaluate_path_following(states, cost: PathCost) -> dict[str, float]:
    """Score an executed trajectory ``states [T+1, S]`` with the planner's own cost.

    Returns ``cost`` (the summed path cost: lower is better, comparable between MPC and
    baselines on the same path and duration), the mean perpendicular error (m), the mean
    heading error (rad) and the total forward progress (m).
    """
    s = torch.as_tensor(np.asarray(states, dtype=np.float32))
    if s.dim() != 2 or s.shape[0] < 2:
        raise ValueError(f"states must be [T+1>=2, S], got {tuple(s.shape)}")
    t = cost.terms(s)
    return {
        "cost": float(cost.step_cost(s).sum()),
        "perp_mean_m": float(t["perp_m"].mean()),
        "heading_mean_rad": float(t["heading_rad"].mean()),
        "progress_m": float(t["progress_m"].sum()),
        "steps": int(s.shape[0] - 1),
    }
