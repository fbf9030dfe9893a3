"""Task costs for MPC, vectorized in torch over [E, N, H], and the metrics that compare
controllers on a path.

Path following (Nagabandi et al. 2018, VelociRoACH). For each predicted state ``s_h``
(h = 1..H) of a candidate, with ``p_h`` the (x, y) position and ``ψ_h`` the yaw:

* the closest segment of the waypoint polyline to ``p_h`` *within the progress window*
  (unit direction ``t̂``, angle θ),
* ``perp_h``     = distance from ``p_h`` to that segment (m),
* ``heading_h``  = |wrap(ψ_h − θ)| (rad),
* ``progress_h`` = (p_h − p_{h−1}) · t̂ (m, forward motion along that segment),

    c = Σ_h  f_p · perp_h + f_h · heading_h − f_f · progress_h

with the thesis weights f_p = 50, f_f = 10, f_h = 5.

**Tipping term** (issue 29; off by default, the thesis has none). A roach turning hard at
speed rolls over (the emulated rig ends an episode at cos_roll < 0.7, |roll| > 46°). With
``f_tip > 0`` each step adds

    f_tip · ( max(0, |roll_h| − θ_tip) + max(0, |pitch_h| − θ_tip) )

from the state's ``cos_roll``/``sin_roll`` and ``cos_pitch``/``sin_pitch`` channels: free
below ``θ_tip`` (straight running pitches ~11° on the sim), linear in the excess beyond it,
so the planner prefers a plan that turns less at speed or slows into the turn.
:class:`~hilstack.control.baselines.DifferentialDriveController` is given the same
threshold (:func:`tilt_excess_rad` on its measured state).

**Progress window.** The thesis matches each state to the globally closest segment; on a
self-crossing path (figure-8) a state at the crossing then jumps to the other branch, and
a robot near a corner can be matched to a segment it has not reached. Here the robot's
place on the path is tracked: :meth:`PathCost.observe` moves the current segment ``k``
forward to the closest segment among those starting less than ``window_m`` of arc length
after segment ``k`` ends, never backward; the planner's predicted states are matched
within the same window. The controller calls ``observe`` once per control step (the
baseline and :class:`~hilstack.control.policies.MpcPolicy` do), and the evaluation replays the
same tracking over the executed trajectory.

**Metrics** (:func:`evaluate_path_following`): the summed cost alone rewards a robot that
parks on the line (no perpendicular error, no cost) over one that finishes with some
error. Every episode therefore also reports ``completed`` (reached the end of the path
within the time limit), ``progress_m`` (arc length along the path reached at the end) and
``cost_per_m`` (cost per metre of progress). Controllers are ranked by completions first,
then ``cost_per_m`` (:func:`rank_key`): a controller that stops never beats one that
finishes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

__all__ = ["PathCost", "closest_segment", "tilt_excess_rad", "evaluate_path_following", "rank_key", "state_index",
           "summarize_paths", "MIN_PROGRESS_M"]

#: ``cost_per_m`` divides by at least this much progress (m), so a robot that never moved
#: gets a large finite cost per metre rather than a division by zero.
MIN_PROGRESS_M = 0.01


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
        ``(index [...], distance [...], unit direction [..., 2])`` of the closest segment
        (ties go to the lower index).
    """
    rel = p.unsqueeze(-2) - a  # [..., G, 2]
    len2 = (d * d).sum(-1).clamp_min(1e-12)  # [G]
    t = ((rel * d).sum(-1) / len2).clamp(0.0, 1.0)  # [..., G]
    diff = rel - t.unsqueeze(-1) * d
    dist2 = (diff * diff).sum(-1)
    dist2_min, idx = dist2.min(dim=-1)
    unit = d / len2.sqrt().unsqueeze(-1)
    return idx, dist2_min.sqrt(), unit[idx]


def tilt_excess_rad(states: torch.Tensor, idx: tuple[int, int, int, int], threshold_rad: float) -> torch.Tensor:
    """``max(0, |roll| − θ) + max(0, |pitch| − θ)`` (rad) of ``states [..., S]`` → ``[...]``;
    ``idx`` = the (cos_roll, sin_roll, cos_pitch, sin_pitch) channels."""
    cr, sr, cp, sp = (states[..., i] for i in idx)
    roll, pitch = torch.atan2(sr, cr).abs(), torch.atan2(sp, cp).abs()
    return (roll - threshold_rad).clamp_min(0.0) + (pitch - threshold_rad).clamp_min(0.0)


class PathCost:
    """Path-following cost ``cost(states [E,N,H+1,S], actions [N,H,A]) -> [E,N]``.

    Args:
        waypoints: ``[P, 2]`` polyline in metres, world frame (see :mod:`hilstack.control.paths`).
        state_names: names of the S state channels; the x, y, cos(yaw), sin(yaw) channels are
            looked up by name (``x``/``y``/``cos_yaw``/``sin_yaw`` by default, override with
            ``x=``, ``y=``, ``cos_yaw=``, ``sin_yaw=``).
        f_p, f_h, f_f: weights of perpendicular distance (1/m), heading error (1/rad) and
            forward progress (1/m).
        window_m: arc length (m) past the end of the current segment within which states
            are matched to segments (see the module docstring). ``None``: the globally
            closest segment (the thesis' definition; wrong at self-crossings).
        end_tol_m: the path counts as completed once the robot is past the last waypoint
            along the last segment or within this distance (m) of it.
        f_tip: weight (1/rad) of the tipping term (module docstring); 0 (default): none,
            the thesis' cost. > 0 needs ``cos_roll``, ``sin_roll``, ``cos_pitch``,
            ``sin_pitch`` channels.
        tip_threshold_rad: roll or pitch (rad) beyond which the tipping term counts.

    The object is stateful (the tracked segment): use one per episode, or :meth:`reset`.
    """

    def __init__(
        self,
        waypoints,
        state_names: Sequence[str],
        f_p: float = 50.0,
        f_h: float = 5.0,
        f_f: float = 10.0,
        *,
        window_m: float | None = 0.5,
        end_tol_m: float = 0.05,
        f_tip: float = 0.0,
        tip_threshold_rad: float = 0.35,
        x: str = "x",
        y: str = "y",
        cos_yaw: str = "cos_yaw",
        sin_yaw: str = "sin_yaw",
    ) -> None:
        wp = torch.as_tensor(np.asarray(waypoints, dtype=np.float32))
        if wp.dim() != 2 or wp.shape[1] != 2 or wp.shape[0] < 2:
            raise ValueError(f"waypoints must be [P>=2, 2], got {tuple(wp.shape)}")
        if window_m is not None and window_m < 0:
            raise ValueError(f"window_m must be >= 0 or None, got {window_m}")
        self.waypoints = wp
        self.seg_start = wp[:-1]
        self.seg_vec = wp[1:] - wp[:-1]
        seg_len = self.seg_vec.norm(dim=-1).double()
        self.seg_len_m = seg_len.numpy()
        #: arc length (m) at the start of each segment, and the path's total length
        self.seg_s0_m = np.concatenate([[0.0], np.cumsum(self.seg_len_m)[:-1]])
        self.length_m = float(seg_len.sum())
        self.window_m = window_m
        self.end_tol_m = float(end_tol_m)
        self.f_p, self.f_h, self.f_f = float(f_p), float(f_h), float(f_f)
        self.ix = state_index(state_names, x)
        self.iy = state_index(state_names, y)
        self.ic = state_index(state_names, cos_yaw, "cos yaw", "yaw_cos")
        self.is_ = state_index(state_names, sin_yaw, "sin yaw", "yaw_sin")
        if not (np.isfinite(f_tip) and f_tip >= 0):
            raise ValueError(f"f_tip must be finite and >= 0, got {f_tip}")
        if not (np.isfinite(tip_threshold_rad) and 0.0 <= tip_threshold_rad < np.pi / 2):
            raise ValueError(f"tip_threshold_rad must be in [0, pi/2), got {tip_threshold_rad}")
        self.f_tip, self.tip_threshold_rad = float(f_tip), float(tip_threshold_rad)
        self.tilt_idx: tuple[int, int, int, int] | None = None
        if self.f_tip > 0:
            try:
                self.tilt_idx = tuple(state_index(state_names, n)  # type: ignore[assignment]
                                      for n in ("cos_roll", "sin_roll", "cos_pitch", "sin_pitch"))
            except KeyError as e:
                raise ValueError(f"f_tip > 0 needs roll and pitch channels: {e.args[0]}") from None
        self.segment = 0

    # -- tracking the robot's place on the path ---------------------------------------------
    def reset(self) -> None:
        """Back to the first segment (a new episode)."""
        self.segment = 0

    def window(self, k: int | None = None) -> slice:
        """Segments a state may be matched to while the robot is on segment ``k``."""
        G = self.seg_start.shape[0]
        if self.window_m is None:
            return slice(0, G)
        k = self.segment if k is None else k
        end_k = self.seg_s0_m[k] + self.seg_len_m[k]
        last = int(np.searchsorted(self.seg_s0_m, end_k + self.window_m, side="left"))
        return slice(k, max(k + 1, min(G, last)))

    def _match(self, p: torch.Tensor, k: int | None = None):
        w = self.window(k)
        idx, dist, unit = closest_segment(p, self.seg_start[w], self.seg_vec[w])
        return idx + w.start, dist, unit

    def observe(self, state) -> int:
        """Advance the tracked segment for the robot's measured ``state [S]``; returns it."""
        s = torch.as_tensor(np.asarray(state, dtype=np.float32))
        idx, _, _ = self._match(s[[self.ix, self.iy]])
        self.segment = max(self.segment, int(idx)) if self.window_m is not None else int(idx)
        return self.segment

    def arc_length(self, p_xy, k: int | None = None) -> float:
        """Arc length (m) along the path of ``p_xy`` projected on segment ``k`` (default: tracked)."""
        k = self.segment if k is None else k
        a, d = self.seg_start[k].double().numpy(), self.seg_vec[k].double().numpy()
        t = float(np.clip((np.asarray(p_xy, dtype=np.float64) - a) @ d / max(float(d @ d), 1e-12), 0.0, 1.0))
        return float(self.seg_s0_m[k] + t * self.seg_len_m[k])

    def at_end(self, p_xy, k: int | None = None) -> bool:
        """True once the robot on segment ``k`` has passed the end of the path."""
        k = self.segment if k is None else k
        G = self.seg_start.shape[0]
        if k != G - 1:
            return False
        p = np.asarray(p_xy, dtype=np.float64)
        a, d = self.seg_start[k].double().numpy(), self.seg_vec[k].double().numpy()
        along = float((p - a) @ d / max(float(d @ d), 1e-12))
        return along >= 1.0 or float(np.linalg.norm(p - (a + d))) < self.end_tol_m

    def track(self, states) -> np.ndarray:
        """Replay :meth:`observe` over a trajectory ``[T, S]`` from the first segment:
        the tracked segment index after each state ``[T]``. Leaves ``self`` reset."""
        s = np.asarray(states, dtype=np.float32)
        self.reset()
        out = np.array([self.observe(x) for x in s], dtype=np.int64)
        self.reset()
        return out

    # -- the cost -----------------------------------------------------------------------------
    def terms(self, states: torch.Tensor, segments: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Per-step terms for ``states [..., H+1, S]``: each ``[..., H]`` (steps 1..H).

        ``segments [..., H]`` fixes the segment of each step (an executed trajectory's
        tracked segments); otherwise each state is matched within the current window.
        """
        p = states[..., [self.ix, self.iy]]  # [..., H+1, 2]
        if segments is None:
            _, perp, unit = self._match(p[..., 1:, :])
        else:
            a, d = self.seg_start[segments], self.seg_vec[segments]
            rel = p[..., 1:, :] - a
            t = ((rel * d).sum(-1) / (d * d).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
            perp = (rel - t.unsqueeze(-1) * d).norm(dim=-1)
            unit = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        progress = ((p[..., 1:, :] - p[..., :-1, :]) * unit).sum(-1)
        c, s = states[..., 1:, self.ic], states[..., 1:, self.is_]
        # angle between the heading (c, s) and the segment direction, without unwrapping
        heading = torch.atan2(c * unit[..., 1] - s * unit[..., 0], c * unit[..., 0] + s * unit[..., 1]).abs()
        out = {"perp_m": perp, "heading_rad": heading, "progress_m": progress}
        if self.tilt_idx is not None:
            out["tilt_excess_rad"] = tilt_excess_rad(states[..., 1:, :], self.tilt_idx, self.tip_threshold_rad)
        return out

    def step_cost(self, states: torch.Tensor, segments: torch.Tensor | None = None) -> torch.Tensor:
        """Cost of each step ``[..., H]`` for ``states [..., H+1, S]``."""
        t = self.terms(states, segments)
        c = self.f_p * t["perp_m"] + self.f_h * t["heading_rad"] - self.f_f * t["progress_m"]
        if "tilt_excess_rad" in t:
            c = c + self.f_tip * t["tilt_excess_rad"]
        return c

    def __call__(self, states: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
        """``states [E, N, H+1, S]`` (actions unused) → ``[E, N]``."""
        return self.step_cost(states).sum(-1)


def evaluate_path_following(states, cost: PathCost, period_s: float | None = None,
                            time_limit_s: float | None = None) -> dict[str, float]:
    """Score an executed trajectory ``states [T+1, S]`` with the planner's own cost.

    The robot's place on the path is tracked from the first segment as during the
    episode (:meth:`PathCost.track`). Returns:

    * ``cost``: the summed path cost (lower is better);
    * ``completed``: the robot reached the end of the path (:meth:`PathCost.at_end`)
      within ``time_limit_s`` (when given);
    * ``progress_m``: arc length along the path (m) reached at the end of the episode;
    * ``cost_per_m``: ``cost / max(progress_m, MIN_PROGRESS_M)``;
    * ``time_s``: episode duration, ``T · period_s`` (when ``period_s`` is given);
    * ``perp_mean_m``, ``heading_mean_rad``, ``steps``.
    """
    s = torch.as_tensor(np.asarray(states, dtype=np.float32))
    if s.dim() != 2 or s.shape[0] < 2:
        raise ValueError(f"states must be [T+1>=2, S], got {tuple(s.shape)}")
    seg = torch.as_tensor(cost.track(s.numpy()))
    t = cost.terms(s, seg[1:])
    xy = s[:, [cost.ix, cost.iy]].double().numpy()
    reached = [i for i in range(len(xy)) if cost.at_end(xy[i], int(seg[i]))]
    steps = int(s.shape[0] - 1)
    time_s = steps * period_s if period_s is not None else float("nan")
    completed = bool(reached) and (time_limit_s is None or period_s is None
                                   or reached[0] * period_s <= time_limit_s + 1e-9)
    progress = cost.length_m if reached else cost.arc_length(xy[-1], int(seg[-1]))
    total = float(cost.step_cost(s, seg[1:]).sum())
    return {
        "cost": total,
        "completed": completed,
        "progress_m": float(progress),
        "cost_per_m": total / max(float(progress), MIN_PROGRESS_M),
        "time_s": float(time_s),
        "perp_mean_m": float(t["perp_m"].mean()),
        "heading_mean_rad": float(t["heading_rad"].mean()),
        "steps": steps,
    }


def summarize_paths(per_path: dict[str, dict]) -> dict[str, float]:
    """Over paths: ``completed`` (count), ``cost`` (mean) and ``cost_per_m`` (total cost over
    total progress, so a path with almost no progress does not dominate a mean of ratios)."""
    total_cost = sum(m["cost"] for m in per_path.values())
    total_progress = sum(max(m["progress_m"], 0.0) for m in per_path.values())
    return {
        "completed": int(sum(bool(m["completed"]) for m in per_path.values())),
        "cost": total_cost / max(len(per_path), 1),
        "cost_per_m": total_cost / max(total_progress, MIN_PROGRESS_M),
    }


def rank_key(summary: dict[str, float]) -> tuple[int, float]:
    """Sort key (lower is better): more completed paths first, then lower ``cost_per_m``."""
    return (-int(summary["completed"]), float(summary["cost_per_m"]))


# ---------------------------------------------------------------------------- Baoding balls
class BaodingCost:
    """PDDM's Baoding cost (Nagabandi et al. 2019; thesis ch. 4) over predicted states:
    ``cost(states [E,N,H+1,S], actions [N,H,A]) -> [E,N]`` = −Σ_{h=1..H} r(s_h, φ_h) with

        r(s, φ) = −5·Σ_i d(ball_i, target_i(φ)) − 10·1(WRJ0 > limit),  or −500 from the
                  first predicted drop on (the reference code's sticky "done")

    the reward of :class:`hilstack.tasks.baoding.BaodingTask` (targets, distance,
    drop rule and wrist term from it), evaluated on the ball channels ``ball{0,1}_{x,y,z}``
    of the state (and ``WRJ0_pos`` for the wrist term). The targets' phases ``φ_h`` come
    from :class:`~hilstack.tasks.baoding.TargetPhase`: the clock at step
    ``k + h`` (``k`` the control steps of this episode so far), led by at most the task's
    ``max_lead_rad`` ahead of the pair's measured phase. :meth:`observe` is called once per
    step with the state planned from (:class:`~hilstack.control.policies.MpcPolicy`);
    :meth:`reset` at the start of an episode.
    """

    def __init__(self, task, state_names: Sequence[str], period_s: float):
        from hilstack.tasks.baoding import (
            REWARD_DIST_WEIGHT,
            REWARD_DROP_PENALTY,
            REWARD_WRIST_PENALTY,
            TargetPhase,
        )

        names = list(state_names)
        missing = [f"ball{i}_{c}" for i in range(2) for c in "xyz" if f"ball{i}_{c}" not in names]
        if missing:
            raise ValueError(f"Baoding cost: the state has no {missing} (set objects_in_state on the hand)")
        self.idx = torch.tensor([names.index(f"ball{i}_{c}") for i in range(2) for c in "xyz"])
        self.wrist = names.index("WRJ0_pos") if task.wrist_limit_rad is not None and "WRJ0_pos" in names else None
        if task.wrist_limit_rad is not None and self.wrist is None:
            raise ValueError("Baoding cost: the task has a wrist term and the state has no WRJ0_pos")
        self.task = task
        self.period_s = float(period_s)
        self.w_dist, self.w_drop, self.w_wrist = REWARD_DIST_WEIGHT, REWARD_DROP_PENALTY, REWARD_WRIST_PENALTY
        self.center = torch.as_tensor(np.asarray(task.center_m), dtype=torch.float32)
        n = np.asarray(task.axis, dtype=np.float64)
        self.normal = torch.as_tensor(n / np.linalg.norm(n), dtype=torch.float32)
        self.phase = TargetPhase(task, period_s)

    @property
    def steps(self) -> int:
        return self.phase.steps

    def reset(self) -> None:
        self.phase.reset()

    def observe(self, state) -> None:
        """One control step passed (the state is the one the planner plans from; None: no
        measurement, the targets follow the clock)."""
        balls = None if state is None else np.asarray(state, dtype=np.float64)[self.idx.numpy()].reshape(2, 3)
        self.phase.observe(balls)

    def targets(self, horizon: int) -> torch.Tensor:
        """[H, 2, 3] targets of the predicted states 1..H (m, world frame)."""
        return torch.as_tensor(self.task.targets_at(self.phase.phases(horizon)), dtype=torch.float32)

    def step_reward(self, balls: torch.Tensor, targets: torch.Tensor, wrist: torch.Tensor | None = None) -> torch.Tensor:
        """r for balls ``[..., 2, 3]``, targets broadcastable to them and the wrist angle
        ``[...]`` (rad; None: no wrist term) -> ``[...]``."""
        r, drop = self._terms(balls, targets, wrist)
        return r - self.w_drop * drop.to(r.dtype)

    def _terms(self, balls: torch.Tensor, targets: torch.Tensor, wrist: torch.Tensor | None):
        """(r without the drop term, drop [bool]) per step."""
        diff = balls - targets
        if self.task.distance == "plane":
            diff = diff - (diff @ self.normal).unsqueeze(-1) * self.normal
        dist = torch.linalg.vector_norm(diff, dim=-1).sum(-1)
        d = balls - self.center
        h = d @ self.normal  # height above the palm centre along its normal [..., 2]
        side = torch.linalg.vector_norm(d - h.unsqueeze(-1) * self.normal, dim=-1)
        drop = ((h < -self.task.drop_below_m) | (side > self.task.drop_radius_m)).any(-1)
        r = -self.w_dist * dist
        if wrist is not None and self.task.wrist_limit_rad is not None:
            r = r - self.w_wrist * (wrist > self.task.wrist_limit_rad).to(dist.dtype)
        return r, drop

    def __call__(self, states: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
        """Σ_h cost of the predicted steps 1..H. A predicted drop ends the prediction as it ends
        the episode: from the first predicted drop on, every step costs the drop penalty alone,
        whatever the model predicts after it (the reference code's sticky ``dones``,
        google-research/pddm ``calculate_costs.py``), so a model that lets a fallen ball bounce
        back into the palm cannot buy the penalty back."""
        H = states.shape[-2] - 1
        nxt = states[..., 1:, :]
        balls = nxt[..., self.idx].reshape(*states.shape[:-2], H, 2, 3)
        wrist = None if self.wrist is None else nxt[..., self.wrist]
        r, drop = self._terms(balls, self.targets(H), wrist)
        done = drop.cumsum(-1) > 0
        return -torch.where(done, torch.full_like(r, -self.w_drop), r).sum(-1)


def baoding_episode_metrics(task, balls_m, t_s, wrist_rad=None, period_s: float = 0.1,
                            rise_limit_m: float | None = None) -> dict[str, float]:
    """Score one executed Baoding episode with the task's own reward (numpy).

    ``balls_m``: ``[T+1, 2, 3]`` ball positions (m, world frame) of the episode's states,
    ``t_s``: their times (s); ``wrist_rad``: ``[T+1]`` WRJ0 angles (the wrist term; None:
    none). Reward step ``k`` uses the targets' phase the planner had for it (the clock, led
    by at most ``max_lead_rad`` ahead of the pair measured at step ``k − 1``:
    :class:`~hilstack.tasks.baoding.TargetPhase` at ``period_s``). The
    episode is cut at the first drop (it ends there, penalty counted once). Returns
    ``return`` (Σ r), ``dropped``, ``steps`` (steps held: until the drop or the end),
    ``rotation_deg`` (how far the pair turned along the targets' direction by the end,
    unwrapped, before any drop, counting only steps with both balls in the palm:
    ``task.in_palm``, so the spin of a ball flying off is not a turn), ``max_rotation_deg`` (the most it had turned at any step)
    and ``turned_90`` / ``turned_180`` (1.0 when the pair turned at least 90° / 180° along
    the targets without a drop first: the thesis' success measure for its real-hand turns).
    ``max_rise_m``: the most either ball rose along the palm normal above its height at the
    first state (before any drop). ``rise_limit_m``: count a step's turn only while both balls
    are within that rise as well (``task.in_palm`` has no upper bound: a ball lifted or thrown
    over the other still turns the pair in the palm's plane); None = no limit.
    """
    from hilstack.tasks.baoding import TargetPhase

    b = np.asarray(balls_m, dtype=np.float64).reshape(-1, 2, 3)
    del t_s  # the steps are the control periods; the phase replays them
    ph = TargetPhase(task, period_s)
    ret, dropped, rot, best = 0.0, False, 0.0, 0.0
    steps = 0
    ph.observe(b[0])
    rise = (b - b[:1]) @ task.normal  # [T+1, 2] along the palm normal, from the first state
    low = np.ones(len(b), bool) if rise_limit_m is None else (rise <= rise_limit_m).all(1)
    max_rise = 0.0
    for k in range(1, len(b)):
        steps = k
        ret += task.reward(b[k], wrist_rad=None if wrist_rad is None else float(wrist_rad[k]),
                           phase_rad=float(ph.phases(1)[0]))
        ph.observe(b[k])
        if task.dropped(b[k]):
            dropped = True
            break
        max_rise = max(max_rise, float(rise[k].max()))
        # a ball flying off spins; that is no turn
        if task.in_palm(b[k - 1]) and task.in_palm(b[k]) and low[k - 1] and low[k]:
            rot += task.rotation_rad(b[k - 1], b[k])
        best = max(best, rot)
    return {"return": float(ret), "dropped": float(dropped), "steps": float(steps), "max_rise_m": max_rise,
            "rotation_deg": float(np.degrees(rot)), "max_rotation_deg": float(np.degrees(best)),
            "turned_90": float(np.degrees(best) >= 90.0), "turned_180": float(np.degrees(best) >= 180.0)}
