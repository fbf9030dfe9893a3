"""PDDM on the Shadow Hand's Baoding balls (Nagabandi et al., CoRL 2019; thesis ch. 4),
with every node on the bus.

    random-policy data → [train the ensemble → R rollouts with PDDM → aggregate] × iterations

This is the MBRL loop of :mod:`hilstack.learning.mbrl` on a second robot: :class:`BaodingRun` is an
:class:`~hilstack.learning.mbrl.MbrlRun` (the same driver process, controller node, reset
supervisor, MCAP recordings, episode split and training); only the task differs: the
policy's cost (:class:`hilstack.control.costs.BaodingCost`), the random policy (uniform actions, as
the thesis) and the metrics (:func:`hilstack.control.costs.baoding_episode_metrics`). Episodes end
through the rig's reset supervisor (``reset:`` in configs/rigs/hand_sim.yaml: a 10 s
timeout and a drop detector on the ball heights; teleport on the sim rig) or at
``episode_steps``.

The model's state and action are the reference code's (google-research/pddm, issue 30):
:class:`BaodingFeatures` turns the hand's bus state (joints, ball positions) into 24 joint
angles, each ball's position and velocity (finite differences over the period, as a ball
tracker gives them), and optionally the joint velocities; :class:`HoldActionMap` makes the
planner's actions z ∈ [-1, 1] centred on the hold pose (z = ±1: 0.9 of the way to each
joint's limit). The driver, the recordings and the bus keep the hand's own units.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from pydantic import Field

from hilstack.configs.presets import Presets
from hilstack.configs.schema import BusConfig, Strict, load_task, parse_model
from hilstack.control.costs import BaodingCost, baoding_episode_metrics
from hilstack.control.planners import PddmConfig
from hilstack.control.policies import MpcPolicy
from hilstack.learning.datasets import Episode
from hilstack.learning.mbrl import (
    MbrlConfig,
    MbrlRun,
    RigError,
    _jsonable,
    _log,
    _progress,
    make_model,
    recording,
)
from hilstack.learning.recordings import episodes_from_mcap

#: the state channels Baoding needs: both balls' positions [m, world]
BALL_NAMES = tuple(f"ball{i}_{c}" for i in range(2) for c in "xyz")


class BaodingTaskParams(Strict):
    """``configs/tasks/baoding.yaml``: the task's geometry in the world frame (m, rad/s)."""

    task: str
    center_m: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius_m: float = Field(gt=0)
    radius_v_m: float | None = Field(None, gt=0)
    rate_rad_s: float
    phase0_rad: float = 0.0
    distance: Literal["3d", "plane"] = "3d"
    wrist_limit_rad: float | None = Field(None, ge=-0.7, le=0.5, description="WRJ0's range is [-0.698, 0.489] rad")
    max_lead_rad: float | None = Field(None, gt=0, le=np.pi)
    #: the hand's hold pose this geometry was read for (``params.hold_pose`` of the hand)
    hold_pose: str = "cupped"
    source: str | None = None


def baoding_task_params(name: str = "baoding") -> BaodingTaskParams:
    """A Baoding task config, checked (``configs/tasks/<name>.yaml``)."""
    raw = load_task(name)
    return parse_model(BaodingTaskParams, raw.model_dump(), raw.source)


def load_baoding_task(name: str = "baoding"):
    """The :class:`~hilstack.tasks.baoding.BaodingTask` of a task config."""
    from hilstack.tasks.baoding import BaodingTask

    p = baoding_task_params(name)
    return BaodingTask(center_m=np.array(p.center_m), axis=np.array(p.axis), radius_m=p.radius_m,
                       radius_v_m=p.radius_v_m, rate_rad_s=p.rate_rad_s, phase0_rad=p.phase0_rad,
                       distance=p.distance, wrist_limit_rad=p.wrist_limit_rad, max_lead_rad=p.max_lead_rad)


class UniformRandomPolicy:
    """Independent uniform actions in [low, high] every step (the thesis' random policy)."""

    def __init__(self, action_dim: int, seed: int = 0, low: float = -1.0, high: float = 1.0):
        self.rng = np.random.default_rng(seed)
        self.action_dim, self.low, self.high = action_dim, low, high

    def __call__(self, state: np.ndarray) -> np.ndarray:
        return self.rng.uniform(self.low, self.high, self.action_dim)


class ConstantPolicy:
    """The same action every step (the ``hold`` baseline: keep the start pose)."""

    def __init__(self, action: np.ndarray):
        self.action = np.asarray(action, dtype=np.float64).copy()

    def __call__(self, state: np.ndarray) -> np.ndarray:
        return self.action.copy()


class RandomWalkPolicy:
    """The reference code's random data policy (``rand_policy_sample_velocities``): every
    ``hold_steps`` steps each action channel draws a velocity of magnitude uniform in
    [``vel_min``, ``vel_max``] (normalized units per step) and random sign; the action walks
    from ``start`` with it, clipped to [-1, 1]. Uniform random targets throw the balls out
    within a second; a walk from the grasp covers the states where the balls are held."""

    def __init__(self, start: np.ndarray, seed: int = 0, vel_min: float = 0.05, vel_max: float = 0.15,
                 hold_steps: int = 2):
        self.rng = np.random.default_rng(seed)
        self.a = np.asarray(start, dtype=np.float64).copy()
        self.vel_min, self.vel_max, self.hold = vel_min, vel_max, max(1, hold_steps)
        self._k = 0
        self._v = np.zeros_like(self.a)

    def __call__(self, state: np.ndarray) -> np.ndarray:
        if self._k % self.hold == 0:
            mag = self.rng.uniform(self.vel_min, self.vel_max, self.a.shape)
            self._v = mag * self.rng.choice([-1.0, 1.0], self.a.shape)
        self._k += 1
        self.a = np.clip(self.a + self._v, -1.0, 1.0)
        return self.a.copy()


class HoldActionMap:
    """The reference code's action normalisation: z ∈ [-1, 1] about the hold pose,

        a = h + z·f·(1 − h)   (z > 0),    a = h + z·f·(h + 1)   (z ≤ 0)

    in the driver's normalized units ``a`` (−1/+1: a joint's lower/upper limit), with ``h``
    the hold pose and ``f`` = 0.9: z = 0 holds, z = ±1 goes 0.9 of the way to a limit."""

    def __init__(self, hold: np.ndarray, frac: float = 0.9):
        if not 0.0 < frac <= 1.0:
            raise ValueError(f"HoldActionMap: frac must be in (0, 1], got {frac}")
        self.hold = np.asarray(hold, dtype=np.float64).copy()
        self.up = frac * (1.0 - self.hold)
        self.down = frac * (self.hold + 1.0)

    def to_driver(self, z: np.ndarray) -> np.ndarray:
        z = np.clip(np.asarray(z, dtype=np.float64), -1.0, 1.0)
        return np.clip(self.hold + np.where(z > 0, z * self.up, z * self.down), -1.0, 1.0)

    def from_driver(self, a: np.ndarray) -> np.ndarray:
        d = np.asarray(a, dtype=np.float64) - self.hold
        z = np.where(d > 0, d / np.maximum(self.up, 1e-9), d / np.maximum(self.down, 1e-9))
        return np.clip(z, -1.0, 1.0)

    def reachable(self, step: np.ndarray):
        """The planner's reachable set under a driver rate limit of ``step`` per control step
        (driver units, ``action_rate_per_s · period_s``), as :class:`~hilstack.control.planners.PDDM`
        takes it: ``prev z [N, A] -> (lo, hi)``, the z whose driver action is within ``step``
        of ``prev``'s (exact: the map is monotone, piecewise linear)."""
        h = torch.as_tensor(self.hold, dtype=torch.float32)
        up = torch.as_tensor(np.maximum(self.up, 1e-9), dtype=torch.float32)
        down = torch.as_tensor(np.maximum(self.down, 1e-9), dtype=torch.float32)
        s = torch.as_tensor(np.broadcast_to(np.asarray(step, dtype=np.float64), self.hold.shape).copy(),
                            dtype=torch.float32)

        def to_z(a: torch.Tensor) -> torch.Tensor:
            d = a - h
            return torch.where(d > 0, d / up, d / down).clamp(-1.0, 1.0)

        def bounds(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            a = h + torch.where(z > 0, z * up, z * down)
            return to_z((a - s).clamp(min=-1.0)), to_z((a + s).clamp(max=1.0))

        return bounds


#: the robot config the Baoding task runs on (its spec gives the joints and the hold pose)
HAND = "shadow_hand"


def _rig_hand(rig: str, robot: str = "hand"):
    """Rig ``rig``'s config and its Shadow Hand ``robot``'s driver (built, never connected), or in
    the driver's place the reason it has none."""
    from hilstack.configs.schema import load_rig, load_robot, rig_robot_config
    from hilstack.drivers.registry import make_driver

    cfg = load_rig(rig)
    if robot not in cfg.robots:
        return cfg, f"rig {cfg.name} has no robot {robot!r} (robots: {', '.join(cfg.robots)}): Baoding runs on a Shadow Hand"
    rcfg = rig_robot_config(cfg, robot)
    if rcfg.robot != load_robot(HAND).robot:
        return cfg, f"rig {cfg.name}'s {robot} is a {rcfg.robot}, not a Shadow Hand ({HAND})"
    return cfg, make_driver(rcfg)


def baoding_rig_problem(rig: str, robot: str = "hand", task: str = "baoding") -> str | None:
    """Why rig ``rig`` cannot run Baoding, read from its config before anything starts (None: it
    can): no robot ``robot`` on it, or not a Shadow Hand; the hand's state without the balls'
    positions (its driver's spec, built and never connected: ``objects_in_state`` and ball
    trackers); no ``reset:`` section (an episode ends and the balls go back through the rig's
    reset procedure, docs/reset.md); a hand holding another pose than the one the task's
    geometry (targets, drop rule) was read for."""
    cfg, hand = _rig_hand(rig, robot)
    if isinstance(hand, str):
        return hand
    missing = [n for n in BALL_NAMES if n not in hand.spec.state.names]
    if missing:
        return (f"rig {cfg.name}: the {robot}'s state has no {', '.join(missing)} (Baoding needs the balls' positions "
                "in the hand's state: objects_in_state: true and ball trackers; docs/baoding.md)")
    if cfg.reset is None:
        return (f"rig {cfg.name} has no reset: section (Baoding ends episodes on a drop or a timeout and puts the "
                "balls back through the rig's reset procedure; docs/reset.md)")
    pose, want = hand.params.hold_pose, baoding_task_params(task).hold_pose
    if pose != want:
        return (f"rig {cfg.name}'s {robot} holds the {pose!r} pose but task {task}'s geometry is for {want!r} "
                f"(hil demo baoding --hold-pose {pose}; docs/baoding.md)")
    return None


def rig_hold_pose(rig: str, robot: str = "hand") -> str | None:
    """The hold pose (``params.hold_pose``) of rig ``rig``'s hand (its driver built, never
    connected); None when the rig has no such robot or it is not a Shadow Hand
    (:func:`baoding_rig_problem` says why)."""
    hand = _rig_hand(rig, robot)[1]
    return None if isinstance(hand, str) else hand.params.hold_pose


def rig_hand_spec(rig: str, robot: str = "hand"):
    """The spec of rig ``rig``'s hand with the rig's settings (its driver built, never
    connected): its hold pose (``home_action``) is the rig's ``params.hold_pose``."""
    from hilstack.configs.schema import load_rig, rig_robot_config
    from hilstack.drivers.registry import make_driver

    return make_driver(rig_robot_config(load_rig(rig), robot)).spec


def hold_pose_action(spec=None) -> np.ndarray:
    """The hand's hold pose (its spec's ``home_action``; default: the hand config's) in
    normalized action units [-1, 1]."""
    from hilstack.drivers.registry import spec_of

    spec = spec or spec_of(HAND)
    low, high = spec.action.low, spec.action.high
    return (np.asarray(spec.home_action, dtype=np.float64) - (high + low) / 2) / ((high - low) / 2)


def hold_action_map(frac: float = 0.9, spec=None) -> HoldActionMap:
    return HoldActionMap(hold_pose_action(spec), frac)


class BaodingFeatures:
    """The model's state from the hand's bus state (``state_names``): the 24 joint angles,
    then ball 0's position and velocity and ball 1's (``ball{i}_{x,y,z}``,
    ``ball{i}_v{x,y,z}``: m, m/s, world frame), and the 24 joint velocities after the joint
    angles when ``joint_velocities``. Ball velocities are finite differences of the tracked
    positions over ``period_s`` (zero at an episode's first state: the reset leaves the
    balls at rest). :meth:`__call__` is per step and keeps the previous balls
    (:meth:`reset` per episode); :meth:`episode` maps a recorded episode."""

    def __init__(self, state_names: list[str], period_s: float, joint_velocities: bool = False):
        from hilstack.drivers.registry import spec_of

        JOINT_NAMES = spec_of(HAND).joint_names()  # noqa: N806 - the hand's joints, in its spec's order
        names = list(state_names)
        want = [f"{j}_pos" for j in JOINT_NAMES] + (
            [f"{j}_vel" for j in JOINT_NAMES] if joint_velocities else []) + list(BALL_NAMES)
        missing = [n for n in want if n not in names]
        if missing:
            raise ValueError(f"Baoding features: the hand's state has no {', '.join(missing)}")
        self.period_s = float(period_s)
        njv = len(JOINT_NAMES) * (2 if joint_velocities else 1)
        self.joint_idx = np.array([names.index(n) for n in want[:njv]])
        self.ball_idx = np.array([names.index(n) for n in BALL_NAMES])
        self.names = want[:njv] + [f"ball{i}_{q}" for i in range(2) for q in ("x", "y", "z", "vx", "vy", "vz")]
        self._prev: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return len(self.names)

    def reset(self) -> None:
        self._prev = None

    def _assemble(self, joints: np.ndarray, balls: np.ndarray, vel: np.ndarray) -> np.ndarray:
        b = np.concatenate([balls.reshape(-1, 2, 3), vel.reshape(-1, 2, 3)], axis=-1).reshape(len(joints), 12)
        return np.concatenate([joints, b], axis=1)

    def transform(self, states: np.ndarray) -> np.ndarray:
        """Features ``[T, F]`` of one episode's states ``[T, S]`` (velocity 0 at the first)."""
        x = np.asarray(states, dtype=np.float64)
        balls = x[:, self.ball_idx]
        vel = np.zeros_like(balls)
        vel[1:] = (balls[1:] - balls[:-1]) / self.period_s
        return self._assemble(x[:, self.joint_idx], balls, vel)

    def __call__(self, state: np.ndarray) -> np.ndarray:
        x = np.asarray(state, dtype=np.float64)
        balls = x[self.ball_idx]
        vel = np.zeros(6) if self._prev is None else (balls - self._prev) / self.period_s
        self._prev = balls.copy()
        return self._assemble(x[None, self.joint_idx], balls[None], vel[None])[0]

    def swap_balls(self, ep: Episode) -> Episode:
        """``ep`` (feature states) with ball 0's and ball 1's channels (position and velocity)
        exchanged: the same physics with the balls' labels swapped (the reference code's
        ``duplicateData_switchObjs``). Named ``<name>#swapped``."""
        i0, i1 = self.names.index("ball0_x"), self.names.index("ball1_x")
        st = np.array(ep.states, copy=True)
        st[:, i0:i0 + 6], st[:, i1:i1 + 6] = ep.states[:, i1:i1 + 6], ep.states[:, i0:i0 + 6]
        return Episode(states=st, actions=ep.actions, times=ep.times, name=f"{ep.name}#swapped", meta=ep.meta)

    def episode(self, ep: Episode, amap: HoldActionMap | None = None) -> Episode:
        """``ep`` with feature states (and actions in the planner's units through ``amap``)."""
        acts = ep.actions if amap is None else amap.from_driver(ep.actions)
        return Episode(states=self.transform(ep.states), actions=acts, times=ep.times, name=ep.name,
                       meta={**ep.meta, "state_names": self.names})


class BaodingPolicy:
    """PDDM on the features, answering the hand's bus state with driver actions: the
    features of each state (:class:`BaodingFeatures`), the planner's action z mapped to the
    driver's units (:class:`HoldActionMap`); commands already sent (``committed``, driver
    units) go to the model in z. ``plan_stats`` holds (ESS, mean shift) per plan."""

    def __init__(self, mpc: MpcPolicy, features: BaodingFeatures, amap: HoldActionMap):
        self.mpc, self.features, self.amap = mpc, features, amap
        self.delay_steps = mpc.delay_steps
        self.planner = mpc.planner
        self.last_plan: np.ndarray | None = None
        self.last_predicted_states: np.ndarray | None = None
        self.last_cost = 0.0

    @property
    def plan_stats(self) -> list[tuple[float, float]]:
        return list(getattr(self.planner, "history", []))

    def reset(self) -> None:
        self.mpc.reset()
        self.features.reset()

    def __call__(self, state: np.ndarray, committed=None) -> np.ndarray:
        x = self.features(state)
        if committed is not None and len(committed):
            z = self.mpc(x, committed=[self.amap.from_driver(a) for a in committed])
        else:
            z = self.mpc(x)
        self.last_plan = np.stack([self.amap.to_driver(p) for p in self.mpc.last_plan])
        self.last_predicted_states = self.mpc.last_predicted_states
        self.last_cost = self.mpc.last_cost
        return self.amap.to_driver(z)


class MappedPolicy:
    """A policy in the planner's units z (``inner``) answering with driver actions."""

    def __init__(self, inner, amap: HoldActionMap):
        self.inner, self.amap = inner, amap

    def __call__(self, state: np.ndarray) -> np.ndarray:
        return self.amap.to_driver(self.inner(state))


def turn_rank_key(summary: dict[str, Any]) -> tuple[float, ...]:
    """Sort key (lower ranks first) of a policy's episode summary by turns: success_90, then
    success_180, then mean rotation in the targets' direction, then fewer drops. Return is
    not in it: a hand that holds still scores a good return and turns nothing."""
    return (-summary["success_90"], -summary["success_180"], -summary["mean_rotation_deg"], summary["drop_rate"])


@dataclass
class BaodingConfig(Presets):
    """One PDDM-on-Baoding run. Defaults are the thesis' (ch. 4); its "quick" preset scales down."""

    #: the presets of ``from_preset(name, **overrides)`` (configs/presets.py): overrides of the defaults
    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        # `hil demo baoding --quick`: ≤10 min on an idle 2-core machine. Scaled down from the
        # thesis: K=200 samples, 2x250 networks (the reference code's width), 6 iterations of 5
        # rollouts, 30/20 epochs; H and the ensemble of 3 as the default. The sampler is the
        # one measured best at this data size (docs/baoding.md, "Our numbers (quick run)"):
        # noise σ = 0.05 about the mean (planner units), the paper's noise filter with β = 0.7,
        # no low-noise share, and γ = 100 (thesis 20); the reference code's sampler (σ 0.9, the
        # action filter) and σ 0.2 dropped most episodes at ~3-5k points, and with γ 20 the
        # weights went soft (ESS 91-164 of 200) and the pair turned half as far.
        "quick": dict(rig="hand_sim", task="baoding",  # our cupped pose: the quick numbers were measured in it
                      random_rollouts=200, random_eval_rollouts=10, iterations=6, rollouts_per_iteration=5,
                      samples=200, hidden=(250, 250), epochs=30, retrain_epochs=20, train_steps=None, preset="quick",
                      random_rollouts_per_iteration=0, swap_balls=False,
                      sigma=0.05, filter="noise", beta=0.7, low_noise_fraction=0.0, gamma=100.0,
                      notes=["scaled down from the thesis to fit 10 min on 2 cores: 200 random-walk rollouts x 30 "
                             "steps, K=200 (thesis 700), 2x250 (thesis 2x500), 6 iterations x 5 rollouts (thesis R=30 "
                             "each), 30/20 epochs (40)",
                             "sampler sigma 0.05, noise filter, beta 0.7 (the reference code's sigma 0.9 and action "
                             "filter dropped 28 of 30 episodes at this data size; docs/baoding.md)",
                             "gamma 100 (thesis 20): with sigma 0.05 the samples' returns differ too little for gamma 20 "
                             "to move the mean (ESS rose to 91-164 of 200); gamma 100 turned the pair 2x further, "
                             "3 seeds (docs/baoding.md)",
                             "no ball-swap doubling and no per-iteration random walks (the thesis preset has both, "
                             "as the reference code): the quick numbers were measured without them"]),
        # A seconds-long smoke run of every stage (tests).
        "tiny": dict(rig="hand_sim", task="baoding", random_rollouts=3, random_steps=8, random_eval_rollouts=2, random_rollouts_per_iteration=1, episode_steps=12, iterations=1,
                     rollouts_per_iteration=2, samples=16, hidden=(16, 16), epochs=2, retrain_epochs=1,
                     train_steps=None, batch_size=64, preset="tiny", progress=False, notes=["smoke-test scale, not a result"]),
    }

    #: the thesis preset holds the PDDM reference code's pose (``params.hold_pose: pddm``): the
    #: pair turned in it and not in ours (docs/baoding.md, "Where the balls sit"); the rig's hand
    #: must hold the pose the task's geometry was read for (:func:`baoding_rig_problem`)
    rig: str = "hand_sim_pddm_pose"
    robot: str = "hand"
    task: str = "baoding_pddm_pose"
    seed: int = 0
    #: random-walk rollouts (:class:`RandomWalkPolicy`) collected before the first training
    #: (reference code: 100 x 30 steps)
    random_rollouts: int = 100
    random_steps: int = 30
    #: random-walk rollouts of ``episode_steps`` recorded after every iteration's PDDM rollouts
    #: and trained on from the next iteration (the reference code's train.py: 5 per iteration)
    random_rollouts_per_iteration: int = 5
    #: train on every episode twice, the second time with ball 0 and ball 1 swapped (the balls
    #: are alike; the reference code's ``duplicateData_switchObjs``); validation stays unswapped
    swap_balls: bool = True
    #: random-policy episodes scored as the `random_policy` baseline (not trained on)
    random_eval_rollouts: int = 10
    #: 10 s at 10 Hz (T=100); the supervisor's timeout ends episodes at 10 s too
    episode_steps: int = 100
    #: 33 x R=30 x T=100 ≈ 100k points: the thesis' budget (Fig. 4.9: solved at ~100k)
    iterations: int = 33
    #: PDDM rollouts per iteration (thesis R=30)
    rollouts_per_iteration: int = 30
    # the planner and its ensemble (thesis: H=7, K=700, γ=20, β=0.7, 3 x 2x500 ReLU MLP)
    horizon: int = 7
    samples: int = 700
    gamma: float = 20.0
    #: the reference code's β with its action filter (the thesis text: 0.7 on the noise)
    beta: float = 0.6
    ensemble: int = 3
    hidden: tuple[int, ...] = (500, 500)
    #: std of PDDM's white noise u, in the planner's units (z: ±1 = 0.9 of the way from the
    #: hold pose to a joint's limit); the reference code's noise magnitude 0.9
    sigma: float | None = 0.9
    #: the share of samples drawn with 0.3·sigma (the reference code: 10 %)
    low_noise_fraction: float = 0.1
    #: "actions": filter the actions from the one executed last (the reference code);
    #: "noise": filter the noise about the mean (the paper's text)
    filter: str = "actions"
    #: the planner's action units: "hold" = z about the hold pose (the reference code),
    #: "range" = the driver's units (−1/+1 = the joint's limits)
    action_units: str = "hold"
    #: the model's state: the joint velocities too (the reference code has none)
    joint_velocities: bool = False
    #: sample only what the hand can execute: every candidate sequence projected into the
    #: driver's rate limit (``action_rate_per_s``: a joint's full range in 0.5 s) from the
    #: action executed last (:meth:`HoldActionMap.reachable`); the reference code's hand has
    #: no rate limit, ours cuts the sampler's jumps, which the model then never saw executed
    rate_aware: bool = False
    #: the plan's first mean: "hold" = the hold pose (z = 0; the reference code's zeros),
    #: "mid" = the middle of every joint's range
    init_mean: str = "hold"
    # training (thesis: 40 epochs, Adam 1e-3, batch 500)
    epochs: int = 40
    retrain_epochs: int = 40
    #: a fixed number of gradient steps per iteration instead of the epochs (None: the
    #: epochs): the epochs become ceil(train_steps · batch / points), so training does not
    #: grow with the data (a lever for the thesis' scale on 2 cores, docs/baoding.md)
    train_steps: int | None = 200
    #: the model's inference precision in the planner: "fp32", "auto" (bf16 where the CPU has
    #: native bf16 and the model measured >= 1.25x faster in it, EnsembleDynamics.measure_dtypes)
    #: or "bf16"; training stays fp32
    inference_dtype: str = "auto"
    #: torch threads for the whole run (None: torch's default); on a loaded 2-core machine one
    #: thread planned 2-8x faster than two (docs/baoding.md, "The full run")
    torch_threads: int | None = 1
    batch_size: int = 500
    input_noise_std: float = 0.0
    #: the reference code's supervised-learning noise (``noiseToSignal`` 0.01): while training,
    #: Gaussian noise of this share of each channel's std on the model's state inputs and delta
    #: targets, not the actions (the reference scales by the channel's mean; docs/baoding.md,
    #: "Training noise"); 0 = none
    noise_to_signal: float = 0.0
    val_fraction: float = 0.1
    progress: bool = True
    rig_timeout_s: float = 60.0
    #: fields of the task (configs/tasks/<task>.yaml) replaced for this run, e.g.
    #: {"max_lead_rad": None} (targets by the clock alone), {"distance": "3d"}: the ablations
    #: of docs/baoding.md
    task_overrides: dict[str, Any] = field(default_factory=dict)
    #: the label of this run's scale in the report ("thesis", "quick", "tiny")
    preset: str = "thesis"
    notes: list[str] = field(default_factory=list)
    #: directories of recorded episodes (e.g. the oracle's turns, ``oracle-record``) mixed into
    #: every iteration's training split, never its validation: each directory's finished
    #: recordings (``*.mcap``, not ``*.unfinished*.mcap``). Demonstrations: not the thesis'
    #: method (the report says so); docs/baoding.md, "Does a run whose data hold turns bootstrap?"
    extra_recordings: list[str] = field(default_factory=list)
    #: each of those episodes enters the training split this many times (before the ball-swap doubling)
    extra_repeat: int = 1

    #: the settings a resumed run (``--resume``) may change; any other difference is refused
    RESUMABLE: ClassVar[tuple[str, ...]] = ("iterations", "progress", "extra_recordings", "extra_repeat")

    def __post_init__(self) -> None:
        problems = []
        if self.init_mean not in ("hold", "mid"):
            problems.append(f"init_mean must be 'hold' or 'mid', got {self.init_mean!r}")
        if self.filter not in ("actions", "noise"):
            problems.append(f"filter must be 'actions' or 'noise', got {self.filter!r}")
        if self.action_units not in ("hold", "range"):
            problems.append(f"action_units must be 'hold' or 'range', got {self.action_units!r}")
        if self.sigma is not None and not (np.isfinite(self.sigma) and self.sigma >= 0):
            problems.append(f"sigma must be finite and >= 0, got {self.sigma}")
        if not 0.0 <= self.low_noise_fraction <= 1.0:
            problems.append(f"low_noise_fraction must be in [0, 1], got {self.low_noise_fraction}")
        if not 0.0 < self.beta <= 1.0:
            problems.append(f"beta must be in (0, 1], got {self.beta}")
        if self.inference_dtype not in ("fp32", "bf16", "auto"):
            problems.append(f"inference_dtype must be 'fp32', 'bf16' or 'auto', got {self.inference_dtype!r}")
        if self.torch_threads is not None and self.torch_threads < 1:
            problems.append(f"torch_threads must be >= 1 or None, got {self.torch_threads}")
        if not (np.isfinite(self.noise_to_signal) and 0.0 <= self.noise_to_signal <= 1.0):
            problems.append(f"noise_to_signal must be in [0, 1], got {self.noise_to_signal}")
        if self.train_steps is not None and self.train_steps < 1:
            problems.append(f"train_steps must be >= 1 or None, got {self.train_steps}")
        if self.extra_repeat < 1:
            problems.append(f"extra_repeat must be >= 1, got {self.extra_repeat}")
        if self.random_rollouts_per_iteration < 0:
            problems.append(f"random_rollouts_per_iteration must be >= 0, got {self.random_rollouts_per_iteration}")
        for f in ("random_rollouts", "episode_steps", "horizon", "samples", "ensemble", "rollouts_per_iteration"):
            if getattr(self, f) < 1:
                problems.append(f"{f} must be >= 1, got {getattr(self, f)}")
        if problems:
            raise ValueError("BaodingConfig: " + "; ".join(problems))

    def pddm(self, state_dim: int, action_dim: int) -> PddmConfig:
        return PddmConfig(horizon=self.horizon, samples=self.samples, gamma=self.gamma, beta=self.beta,
                          ensemble=self.ensemble, hidden=tuple(self.hidden), state_dim=state_dim,
                          action_dim=action_dim, sigma=self.sigma, filter=self.filter,
                          low_noise_fraction=self.low_noise_fraction)

    def mbrl(self) -> MbrlConfig:
        """The shared loop's settings (:class:`MbrlRun` runs the rig, the episodes, training)."""
        return MbrlConfig(rig=self.rig, robot=self.robot, seed=self.seed, hidden=tuple(self.hidden),
                          ensemble=self.ensemble, epochs=self.epochs, retrain_epochs=self.retrain_epochs,
                          batch_size=self.batch_size, input_noise_std=self.input_noise_std,
                          noise_to_signal=self.noise_to_signal,
                          val_fraction=self.val_fraction, body_frame=False, invariant_inputs=(),
                          planner="pddm", samples=self.samples, horizon=self.horizon,
                          progress=self.progress, rig_timeout_s=self.rig_timeout_s)


def _mean_std(x: list[float]) -> dict[str, float]:
    a = np.asarray(x, dtype=np.float64)
    return {"mean": float(a.mean()) if a.size else float("nan"), "std": float(a.std()) if a.size else float("nan")}


def summarize(per_episode: list[dict[str, float]]) -> dict[str, Any]:
    """Mean ± std return, drops, rotation and 90°/180° success rates over episodes. ``held_90``:
    the episodes that turned 90° and never dropped (success_90 counts a turn before a drop, so a
    policy that turns the pair and then loses it scores there, not here)."""
    col = {k: [m[k] for m in per_episode] for k in ("return", "dropped", "rotation_deg", "turned_90", "turned_180",
                                                     "steps")}
    if not per_episode:
        raise ValueError("summarize: no episodes")
    return {"episodes": len(per_episode), "return": _mean_std(col["return"]),
            "mean_return": _mean_std(col["return"])["mean"],
            "drops": int(sum(col["dropped"])), "drop_rate": float(np.mean(col["dropped"])),
            "mean_rotation_deg": float(np.mean(col["rotation_deg"])),
            "success_90": float(np.mean(col["turned_90"])), "success_180": float(np.mean(col["turned_180"])),
            "held_90": float(np.mean(np.asarray(col["turned_90"], float) * (1.0 - np.asarray(col["dropped"], float)))),
            "mean_steps": float(np.mean(col["steps"]))}


def drop_prediction(model, episodes, task, ball_idx: list[int], horizon: int) -> dict[str, float]:
    """Does the model see drops coming? Over every ``horizon``-step open-loop window of
    ``episodes`` (the validation data), replaying the logged actions: ``drop_recall`` = the
    fraction of windows in which a ball truly drops whose ensemble-mean prediction also
    drops (the task's rule); ``false_drop_rate`` = predicted drops among windows without
    one; ``windows_with_drop``. A planner can only avoid the −500 the model predicts."""
    from hilstack.learning.dynamics import h_step_windows

    H = min(horizon, max((len(e) for e in episodes), default=0))
    if H < 1:
        return {"drop_recall": float("nan"), "false_drop_rate": float("nan"), "windows_with_drop": 0}
    start, actions, truth = h_step_windows(episodes, H, max_starts=2048)
    with torch.inference_mode():
        cur = torch.from_numpy(np.ascontiguousarray(start)).float()
        preds = []
        for h in range(H):
            cur = model.predict(cur, torch.from_numpy(np.ascontiguousarray(actions[:, h])).float())
            preds.append(cur.mean(0).numpy())
    pred = np.stack(preds, 1)  # [P, H, S]

    def drops(x: np.ndarray) -> np.ndarray:
        b = x[..., ball_idx].reshape(*x.shape[:2], 2, 3)
        return np.array([[task.dropped(bb) for bb in row] for row in b]).any(1)

    true_d, pred_d = drops(truth), drops(pred)
    n = int(true_d.sum())
    return {"drop_recall": float((pred_d & true_d).sum() / n) if n else float("nan"),
            "false_drop_rate": float((pred_d & ~true_d).sum() / max(1, int((~true_d).sum()))),
            "windows_with_drop": n}


def is_unfinished(path: str | Path) -> bool:
    """Whether a recording is a partial episode or a stopped iteration's (``*.unfinished*.mcap``),
    which every loader leaves out."""
    return ".unfinished" in Path(path).name


def finished_recordings(directory: str | Path) -> list[Path]:
    """The finished recordings of ``directory`` (``*.mcap``; a ``*.unfinished*.mcap`` is a
    partial episode or a stopped iteration, left out as every loader does); ValueError when
    there is none."""
    d = Path(directory)
    if not d.is_dir():
        raise ValueError(f"extra data {d}: not a directory")
    found = sorted(f for f in d.glob("*.mcap") if not is_unfinished(f))
    if not found:
        raise ValueError(f"extra data {d}: no finished recordings (*.mcap, not *.unfinished.mcap)")
    return found


def probe_model(model, episodes: list, task, horizon: int = 7, period_s: float = 0.1) -> dict[str, float]:
    """How well ``model`` predicts what the Baoding planner needs, on held-out model episodes
    (features; actions in the planner's units), in physical units so that models with other
    normalisations compare: the balls' one-step position error (mm RMS per ball) beside
    "the balls stay" and "the balls keep their velocity"; the joints' one-step error (rad RMS)
    beside "the joints stay"; over every ``horizon``-step open-loop window replaying the logged
    actions with both balls in the palm throughout, the balls' position error at step H beside
    "the balls stay", and how well the predicted turn of the pair over the window (Δ of
    ``task.pair_phase``) matches the true one: ``turn_r2`` (1 − SSE/SST; 0 = no better than
    predicting the mean turn, < 0 worse) and ``turn_corr``. A planner can only turn the pair
    with a model whose ``turn_r2`` is well above 0."""
    import torch

    from hilstack.learning.dynamics import h_step_windows

    names = list(episodes[0].meta["state_names"])
    bp = [names.index(f"ball{i}_{c}") for i in range(2) for c in "xyz"]
    bv = [names.index(f"ball{i}_v{c}") for i in range(2) for c in "xyz"]
    jn = [i for i, n in enumerate(names) if n.endswith("_pos") and not n.startswith("ball")]
    s = np.concatenate([e.states[:-1] for e in episodes])
    a = np.concatenate([e.actions for e in episodes])
    y = np.concatenate([e.states[1:] for e in episodes])
    with torch.inference_mode():
        p = model.predict(torch.from_numpy(s).float(), torch.from_numpy(a).float()).mean(0).double().numpy()

    def ball_rms_mm(x: np.ndarray) -> float:  # x: [N, 6] position errors → RMS per-ball distance
        return 1e3 * float(np.sqrt(np.mean(np.sum(x.reshape(-1, 2, 3) ** 2, -1))))

    out = {"transitions": int(len(s)),
           "ball_1step_mm": ball_rms_mm(p[:, bp] - y[:, bp]),
           "ball_1step_stay_mm": ball_rms_mm(s[:, bp] - y[:, bp]),
           "ball_1step_constvel_mm": ball_rms_mm(s[:, bp] + period_s * s[:, bv] - y[:, bp]),
           "joint_1step_rad": float(np.sqrt(np.mean((p[:, jn] - y[:, jn]) ** 2))),
           "joint_1step_stay_rad": float(np.sqrt(np.mean((s[:, jn] - y[:, jn]) ** 2)))}
    start, acts, truth = h_step_windows(episodes, horizon, max_starts=None)
    keep = np.array([all(task.in_palm(t[bp].reshape(2, 3)) for t in (st, *tr)) for st, tr in zip(start, truth, strict=True)])
    start, acts, truth = start[keep], acts[keep], truth[keep]
    if len(start) == 0:  # every window had a ball out of the palm: no turn to predict
        out.update({"windows": 0, "horizon": horizon, "turn_r2": float("nan"), "turn_corr": float("nan")})
        return out
    with torch.inference_mode():
        cur = torch.from_numpy(start).float()
        for h in range(horizon):
            cur = model.predict(cur, torch.from_numpy(np.ascontiguousarray(acts[:, h])).float())
        end = cur.mean(0).double().numpy()

    def turn(b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
        d = np.array([task.pair_phase(x[bp]) - task.pair_phase(z[bp]) for x, z in zip(b1, b0, strict=True)])
        return (d + np.pi) % (2 * np.pi) - np.pi

    true_turn, pred_turn = turn(start, truth[:, -1]), turn(start, end)
    sst = float(np.sum((true_turn - true_turn.mean()) ** 2))
    corr = float("nan")  # undefined when either side does not vary (a model predicting no turn)
    if len(start) > 2 and true_turn.std() > 0 and pred_turn.std() > 0:
        corr = float(np.corrcoef(pred_turn, true_turn)[0, 1])
    out.update({"windows": int(len(start)), "horizon": horizon,
                "ball_hstep_mm": ball_rms_mm(end[:, bp] - truth[:, -1, bp]),
                "ball_hstep_stay_mm": ball_rms_mm(start[:, bp] - truth[:, -1, bp]),
                "turn_true_std_deg": float(np.degrees(true_turn.std())),
                "turn_rmse_deg": float(np.degrees(np.sqrt(np.mean((pred_turn - true_turn) ** 2)))),
                "turn_r2": 1.0 - float(np.sum((pred_turn - true_turn) ** 2)) / max(sst, 1e-12),
                "turn_corr": corr})
    return out



def probe_turn(model, episodes: list[Episode], task, horizon: int = 7, period_s: float = 0.1) -> dict[str, float]:
    """The turn part of :func:`probe_model` on ``episodes`` (an iteration's own PDDM episodes,
    recorded after the model was trained): ``turn_r2``, ``turn_corr``, the true turns' std over
    H steps (°) and the windows; ``{"windows": 0}`` when no H-step window kept both balls in the palm."""
    eps = [e for e in episodes if len(e) > horizon]
    if not eps:
        return {"windows": 0}
    p = probe_model(model, eps, task, horizon, period_s)
    return {k: p[k] for k in ("windows", "turn_r2", "turn_corr", "turn_true_std_deg") if k in p}


class BaodingRun(MbrlRun):
    """The MBRL loop of :class:`MbrlRun` with the Baoding task (see the module docstring)."""

    def __init__(self, cfg: BaodingConfig, out_dir: Path, bus: BusConfig, resume: bool = False):
        super().__init__(cfg.mbrl(), out_dir, bus)
        self.bcfg = cfg
        #: continue the stopped run in ``out_dir`` after its last finished iteration (:meth:`load_checkpoint`)
        self.resume = bool(resume)
        self.task = replace(load_baoding_task(cfg.task), **cfg.task_overrides)
        self.plan_times_s: list[float] = []
        #: (ESS, mean shift, K) of every PDDM plan of the current phase (run_episodes)
        self.plan_stats: list[tuple[float, float, int]] = []
        #: the rig's hold pose in the driver's units (where every episode starts)
        self.hold = hold_pose_action(rig_hand_spec(cfg.rig, cfg.robot))
        self.amap = HoldActionMap(self.hold, 0.9) if cfg.action_units == "hold" else None
        self._features: BaodingFeatures | None = None
        #: the recorded episodes of ``extra_recordings`` (raw; loaded by :meth:`load_extra`)
        self.extra: list[Episode] = []
        self._extra_model: list[Episode] | None = None

    def balls(self, states: np.ndarray) -> np.ndarray:
        idx = [self.state_names.index(n) for n in BALL_NAMES]
        return np.asarray(states)[:, idx].reshape(-1, 2, 3)

    @property
    def features(self) -> BaodingFeatures:
        """The model's state (:class:`BaodingFeatures`) from this rig's hand state."""
        if self._features is None or self._features_for != self.state_names:
            self._features = BaodingFeatures(self.state_names, self.period_s, self.bcfg.joint_velocities)
            self._features_for = list(self.state_names)
        return self._features

    def model_episodes(self, eps: list[Episode]) -> list[Episode]:
        """Recorded episodes as the model sees them (features; actions in the planner's units)."""
        return [self.features.episode(e, self.amap) for e in eps]

    def to_driver(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z, dtype=np.float64) if self.amap is None else self.amap.to_driver(z)

    def run_episodes(self, make_policy, n: int, name: str, desc: str,
                     steps: int | None = None) -> tuple[Path, list[dict[str, float]]]:
        """``n`` episodes of at most ``steps`` (default ``episode_steps``) recorded to
        ``rec_dir/name.mcap``, each scored with the task's reward. PDDM episodes on a
        wall-clock hand refit K after each one (:meth:`MbrlRun.refit_samples`, from its plan
        times and late plans); the next episode's policy is made with the count of the moment
        (:meth:`pddm_samples`)."""
        path = self.rec_dir / f"{name}.mcap"
        scores = []
        self.plan_stats = []
        with recording(self.rig.name, path, self.bus):
            for i in _progress(range(n), self.cfg, desc):
                policy = make_policy(i)
                log = self.episode(policy, steps or self.bcfg.episode_steps, {})
                scores.append(self.score(np.array(log.states), log.times_s, self.last_end_reason))
                if log.plan_times_s and "mpc" in name:
                    self.plan_times_s += log.plan_times_s
                k = getattr(getattr(policy, "planner", None), "samples", None)
                self.plan_stats += [(*p, k) for p in getattr(policy, "plan_stats", [])]  # K per plan: it may change
                if k is not None:
                    self.refit_samples(log, f"{name} episode {i}")
        self.recordings.append(str(path))
        return path, scores

    def score(self, states: np.ndarray, times_s, end_reason: str) -> dict[str, float]:
        """The task's metrics of one episode (:func:`baoding_episode_metrics`). An episode the
        rig's drop detector ended (``end_reason`` "supervisor: drop: ...") counts as dropped
        even where the task's own rule has not fired: the rig's is a world height, the task's a
        depth along the palm normal, and they differ where the palm slopes (a ball on the
        fingertips); scored as held, a cut episode made the drop rate look better than it was."""
        m = baoding_episode_metrics(self.task, self.balls(states), times_s,
                                    wrist_rad=states[:, self.state_names.index("WRJ0_pos")], period_s=self.period_s)
        if not m["dropped"] and end_reason.startswith("supervisor: drop"):
            m["dropped"] = 1.0
        return m

    def _seed(self, offset: int, i: int) -> int:
        return int(np.random.SeedSequence([self.bcfg.seed, offset, i]).generate_state(1)[0])

    def random_policy(self, i: int) -> UniformRandomPolicy:
        return UniformRandomPolicy(len(self.action_names), seed=self._seed(2, i))

    def random_walk(self, i: int):
        """The reference code's random walk from the hold pose, in the planner's units."""
        if self.amap is None:
            return RandomWalkPolicy(self.hold, seed=self._seed(1, i))  # where every episode starts
        return MappedPolicy(RandomWalkPolicy(np.zeros(len(self.action_names)), seed=self._seed(1, i)), self.amap)

    def hold_policy(self, i: int) -> ConstantPolicy:
        return ConstantPolicy(self.hold)

    def pddm_config(self, samples: int | None = None) -> PddmConfig:
        """The planner's settings; ``samples`` instead of the configured K (wall-clock rigs:
        :meth:`fit_pddm_to_period`)."""
        pc = self.bcfg.pddm(self.features.dim, len(self.action_names))
        return pc if samples is None else replace(pc, samples=int(samples))

    def _init_mean(self) -> np.ndarray:
        # "hold": the first plan is centred on the pose the episode starts in, so a planner
        # with an untrained model perturbs a grasp instead of swinging every joint to mid-range
        if self.bcfg.init_mean == "hold":
            a = self.hold
        else:
            a = np.zeros(len(self.action_names))  # the middle of every joint's range
        return a if self.amap is None else self.amap.from_driver(a)

    def pddm_samples(self) -> int | None:
        """K of the moment on a wall-clock hand (fitted at the start, refitted after every PDDM
        episode); None on lockstep rigs (the configured K)."""
        return None if self.planner_fit is None else self.planner_fit["current_samples"]

    def pddm_policy(self, model, seed: int, samples: int | None = None) -> BaodingPolicy:
        """PDDM through ``model``; ``samples``: instead of the configured K (:meth:`fit_pddm_to_period`)."""
        planner = self.pddm_config(samples).planner(seed=seed, init_mean=self._init_mean(),  # a seed per rollout
                                                    reachable=self.reachable())
        feats = BaodingFeatures(self.state_names, self.period_s, self.bcfg.joint_velocities)
        # on a wall-clock rig the plan starts from the state after the command already sent
        mpc = MpcPolicy(model, planner, BaodingCost(self.task, feats.names, self.period_s),
                        delay_steps=self.command_delay)
        return BaodingPolicy(mpc, feats, self.amap or HoldActionMap(np.zeros(len(self.action_names)), 1.0))

    def reachable(self):
        """The planner's reachable set (``rate_aware``), or None: the driver's rate limit per
        control step in the planner's units (:meth:`HoldActionMap.reachable`)."""
        from hilstack.drivers.registry import spec_of

        if not self.bcfg.rate_aware:
            return None
        # the rig's spec once connected (a real hand's own limit), else the hand's config
        step = self.max_step if self.max_step is not None else spec_of(HAND).max_step_normalized()
        if step is None:
            return None
        step = np.where(np.isfinite(step), step, 2.0)
        return (self.amap or HoldActionMap(np.zeros(len(self.action_names)), 1.0)).reachable(step)

    def fit_pddm_to_period(self, model) -> int | None:
        """Wall-clock hands: PDDM's K cut until its median plan fits the period's budget on
        this machine (the thesis' K = 700 through 3 x 2x500 took ~200 ms per plan on one
        core here, twice the 100 ms period). None on lockstep rigs."""
        if self.pacing is not None and self.pacing.answered:
            return None
        cost = BaodingCost(self.task, self.features.names, self.period_s)
        init = self._init_mean()
        x = self.features.transform(np.asarray(self.ctl.next_state().state)[None])[0]
        ctl = self.ctl

        class _Features:  # realtime_samples times plans from the hand's state: give it the features
            def next_state(self):
                from types import SimpleNamespace

                return SimpleNamespace(state=x)

        self.ctl = _Features()
        try:
            return self.realtime_samples(model, make=lambda n: self.pddm_config(n).planner(seed=0, init_mean=init),
                                         cost=cost)
        finally:
            self.ctl = ctl

    def epochs_for(self, data: list[Episode], iteration: int) -> int:
        """The epochs of an iteration's training: the configured ones, or with ``train_steps``
        as many as make about that many gradient steps over ``data``."""
        c = self.bcfg
        if c.train_steps is None:
            return c.epochs if iteration == 1 else c.retrain_epochs
        points = (int(sum(len(e) for e in data) * (1.0 - self.cfg.val_fraction)) + self.extra_points()) \
            * (2 if c.swap_balls else 1)
        return max(1, int(np.ceil(c.train_steps * c.batch_size / max(1, points))))

    def load_extra(self) -> None:
        """The episodes of ``extra_recordings`` (each directory's finished recordings); ValueError
        for a directory without any. Called before the rig starts."""
        self.extra = [e for d in self.bcfg.extra_recordings for f in finished_recordings(d)
                      for e in episodes_from_mcap(f, self.cfg.robot)]
        self._extra_model = None

    def extra_points(self) -> int:
        """Transitions the extra episodes add to one training split (``extra_repeat`` times)."""
        return sum(len(e) for e in self.extra) * self.bcfg.extra_repeat

    def extra_model_episodes(self) -> list[Episode]:
        """The extra episodes as the model sees them, once (their state must be the rig's)."""
        if self._extra_model is None:
            for e in self.extra:
                if list(e.meta.get("state_names", self.state_names)) != list(self.state_names):
                    raise ValueError(f"extra data {e.meta.get('path', e.name)}: recorded with other state channels "
                                     f"than rig {self.rig.name}'s")
            self._extra_model = self.model_episodes(self.extra)
        return self._extra_model

    def demonstrations(self) -> dict[str, Any]:
        """What the report says of the mixed-in episodes ({} without any)."""
        if not self.extra:
            return {}
        dirs = ", ".join(self.bcfg.extra_recordings)
        return {"episodes": len(self.extra), "dirs": list(self.bcfg.extra_recordings), "repeat": self.bcfg.extra_repeat,
                "points": sum(len(e) for e in self.extra),
                "text": f"demonstrations: {len(self.extra)} episodes from {dirs}, repeated {self.bcfg.extra_repeat}×"}

    def train(self, model, eps: list[Episode], epochs: int) -> dict[str, float]:
        """One (re)fit on ``eps`` (model episodes): the fixed episode split of the MBRL loop,
        the extra episodes (``extra_recordings``, ``extra_repeat`` times) added to the training
        side only, which is then doubled with the balls swapped (``swap_balls``), validation
        unswapped."""
        from hilstack.learning.datasets import split_episodes

        train, val = split_episodes(eps, self.cfg.val_fraction, self.split_rng, self.val_assigned)
        if self.extra:
            train = train + self.extra_model_episodes() * self.bcfg.extra_repeat
        if self.bcfg.swap_balls:
            train = train + [self.features.swap_balls(e) for e in train]
        hist = model.fit(train, epochs=epochs, batch_size=self.cfg.batch_size, val=val or None,
                         horizon=self.cfg.horizon, progress=self.cfg.progress)
        last = hist[-1] if hist else {}
        return {k: float(v) for k, v in last.items() if isinstance(v, (int, float))}

    def plan_summary(self) -> dict[str, float]:
        """Per-plan weighting of the phase just run: effective sample size (mean, and as a
        share of K) and the mean's RMS shift (mean)."""
        if not self.plan_stats:
            return {"plans": 0}
        a = np.asarray(self.plan_stats, dtype=np.float64)
        return {"plans": int(len(a)), "ess_mean": float(a[:, 0].mean()), "ess_p10": float(np.percentile(a[:, 0], 10)),
                "ess_frac_mean": float((a[:, 0] / a[:, 2]).mean()), "mean_shift_rms": float(a[:, 1].mean())}

    def write_partial(self, report: dict[str, Any], t0: float) -> None:
        """``OUT/report.json`` after every iteration (``"partial": true``), so a run stopped
        early keeps its curve; the finished run's report replaces it."""
        import json

        part = {**report, "partial": True, "wall_s": time.monotonic() - t0, "recordings": list(self.recordings)}
        tmp = self.out / "report.json.tmp"
        tmp.write_text(json.dumps(_jsonable(part), indent=1))
        tmp.replace(self.out / "report.json")

    @contextlib.contextmanager
    def torch_threads(self):
        """The configured torch thread count (``torch_threads``) inside, the caller's after."""
        threads = torch.get_num_threads()
        if self.bcfg.torch_threads is not None:
            torch.set_num_threads(self.bcfg.torch_threads)
        try:
            yield
        finally:
            torch.set_num_threads(threads)

    def run(self) -> dict[str, Any]:
        with self.torch_threads():
            return self._run_baoding()

    def _run_baoding(self) -> dict[str, Any]:
        torch.manual_seed(self.bcfg.seed)
        t0 = time.monotonic()
        report: dict[str, Any] = {"config": _jsonable(asdict(self.bcfg)), "rig": self.rig.name}
        try:
            return self._baoding(report, t0)
        except TimeoutError as e:
            raise RigError(f"{e} (driver log: {self.out / 'logs' / 'driver.log'})") from None

    # -- checkpoints: a stopped run resumes after its last finished iteration -------------------
    @property
    def ckpt_dir(self) -> Path:
        return self.out / "checkpoint"

    def save_checkpoint(self, model, iteration: int, data_recordings: list[str], elapsed_s: float) -> None:
        """After iteration ``iteration``: the model (weights, normalisation, Adam's state, the
        bootstrap generator), the data's recordings, the fixed validation split and the time
        spent. ``state.json`` is written last (atomically): it is the commit point."""
        import json

        d = self.ckpt_dir
        d.mkdir(parents=True, exist_ok=True)
        model.save(d / "model.pt.tmp")
        (d / "model.pt.tmp").replace(d / "model.pt")
        opt = model._optimizer.state_dict() if model._optimizer is not None else None
        torch.save({"optimizer": opt, "generator": model._gen.get_state()}, d / "train_state.pt.tmp")
        (d / "train_state.pt.tmp").replace(d / "train_state.pt")
        state = {"iteration": iteration, "data_recordings": list(data_recordings), "recordings": list(self.recordings),
                 "val_assigned": self.val_assigned, "split_rng": self.split_rng.bit_generator.state,
                 "elapsed_s": elapsed_s, "plan_times_s": list(self.plan_times_s)}
        (d / "state.json.tmp").write_text(json.dumps(_jsonable(state)))
        (d / "state.json.tmp").replace(d / "state.json")

    def load_checkpoint(self) -> dict[str, Any]:
        """The saved state of a stopped run in ``out`` (:meth:`save_checkpoint`) and its
        partial report; ValueError naming what is missing or what differs in the config."""
        import json

        sp, rp = self.ckpt_dir / "state.json", self.out / "report.json"
        if not sp.exists() or not rp.exists():
            raise ValueError(f"--resume: {self.out} holds no finished iteration to resume from "
                             f"({'no ' + str(sp) if not sp.exists() else 'no ' + str(rp)})")
        state, report = json.loads(sp.read_text()), json.loads(rp.read_text())
        # the run's settings must be the same (BaodingConfig.RESUMABLE may change); a setting the
        # stopped run's config predates counts as its default (the behaviour before it existed)
        now = _jsonable(asdict(self.bcfg))
        defaults = _jsonable(asdict(type(self.bcfg)()))
        old = {**defaults, **report["config"]}
        diff = sorted(k for k in set(now) | set(old)
                      if k not in self.bcfg.RESUMABLE and now.get(k) != old.get(k))
        if diff:
            hint = ""
            if "task" in diff:  # a run from before the thesis preset held the reference's pose
                try:
                    pose = baoding_task_params(old["task"]).hold_pose
                    hint = f"; it held the {pose} pose: add --hold-pose {pose}"
                except (ValueError, OSError):
                    pass
            raise ValueError(f"--resume: {self.out} was run with other settings ({', '.join(diff)}); "
                             f"resume with the same preset and seed (only {', '.join(self.bcfg.RESUMABLE)} may change)"
                             f"{hint}")
        changed = {k: [old.get(k), now.get(k)] for k in self.bcfg.RESUMABLE
                   if k != "progress" and old.get(k) != now.get(k)}
        return {"state": state, "report": report, "changed": changed}

    def _rebased(self, paths: list[str]) -> list[str]:
        """A checkpoint's recordings, read from this run's ``recordings/`` where a file of that
        name is there (a run directory copied elsewhere keeps the paths of its original)."""
        return [str(self.rec_dir / Path(p).name) if (self.rec_dir / Path(p).name).exists() else p for p in paths]

    def _set_aside_unfinished(self, keep: list[str]) -> list[str]:
        """Recordings in ``rec_dir`` that no finished iteration holds (the iteration that was
        stopped) are renamed ``<name>.unfinished[-k].mcap``, never overwritten or deleted."""
        kept = {Path(k).resolve() for k in keep}
        moved = []
        for f in sorted(self.rec_dir.glob("*.mcap")):
            if f.resolve() in kept or is_unfinished(f):
                continue
            k, dst = 0, f.with_name(f"{f.stem}.unfinished.mcap")
            while dst.exists():
                k += 1
                dst = f.with_name(f"{f.stem}.unfinished-{k}.mcap")
            f.rename(dst)
            moved.append(str(dst))
        return moved

    def _baseline_phases(self, report: dict[str, Any]) -> list[str]:
        """The random-walk data and the two scored baselines; returns the data's recordings."""
        c = self.bcfg
        _log(self.cfg, f"collecting {c.random_rollouts} random-walk rollouts x ≤{c.random_steps} steps")
        rand_path, walk = self.run_episodes(self.random_walk, c.random_rollouts, "000-random",
                                            "random-walk rollouts", steps=c.random_steps)
        report["random_data"] = {"policy": "random walk from the hold pose (reference code's velocity sampling: "
                                           "|v| in [0.05, 0.15] per step, held 2 steps)",
                                 "rollouts": len(walk), "steps": c.random_steps,
                                 "points": int(sum(len(e) for e in episodes_from_mcap(rand_path, self.cfg.robot))),
                                 "drop_rate": float(np.mean([m["dropped"] for m in walk]))}
        _, rand_scores = self.run_episodes(self.random_policy, c.random_eval_rollouts,
                                           "001-random-eval", "uniform random policy (scored)")
        report["random_policy"] = summarize(rand_scores)
        # the do-nothing reference (as many episodes as PDDM's): a planner that only holds the grasp scores this
        _, hold_scores = self.run_episodes(self.hold_policy, c.rollouts_per_iteration,
                                           "002-hold-eval", "hold policy (scored)")
        report["hold_policy"] = summarize(hold_scores)
        _log(self.cfg, f"random policy: {report['random_policy']['mean_return']:.1f} mean return, "
                       f"{report['random_policy']['drops']} drops")
        return [str(rand_path)]

    def _baoding(self, report: dict[str, Any], t0: float) -> dict[str, Any]:
        c = self.bcfg
        resumed = self.load_checkpoint() if self.resume else None
        if resumed is None and (self.out / "report.json").exists():
            raise ValueError(f"{self.out} already holds a run (report.json): resume it (--resume) or choose another "
                             "--out; its recordings are not overwritten")
        self.load_extra()  # a directory without finished recordings is refused before the rig starts
        if self.extra:
            report["demonstrations"] = self.demonstrations()
        with self.session():
            missing = [n for n in BALL_NAMES if n not in self.state_names]
            if missing:
                raise RigError(f"rig {self.rig.name}: robot {self.cfg.robot}'s state has no {', '.join(missing)}: "
                               "Baoding needs the balls' positions in the hand's state (objects_in_state: true "
                               "and ball trackers; docs/baoding.md, 'Connecting a real hand')")
            model = make_model(self.cfg, self.features.names, self.action_names)
            if resumed is None:
                data_recs, first_it = self._baseline_phases(report), 1
            else:
                st, old = resumed["state"], resumed["report"]
                for k in ("random_data", "random_policy", "hold_policy", "inference_dtype"):
                    if k in old:
                        report[k] = old[k]
                report["iterations"] = old.get("iterations", [])[:st["iteration"]]
                report["resumed"] = [*old.get("resumed", []), {"after_iteration": st["iteration"],
                                                               "at": time.strftime("%Y-%m-%dT%H:%M:%S"),
                                                               **({"changed": resumed["changed"]}
                                                                  if resumed["changed"] else {})}]
                self.recordings = self._rebased(list(st["recordings"]))
                data_recs = self._rebased(list(st["data_recordings"]))
                report["set_aside"] = [*old.get("set_aside", []), *self._set_aside_unfinished(self.recordings)]
                self.val_assigned = dict(st["val_assigned"])
                self.split_rng.bit_generator.state = st["split_rng"]
                self.plan_times_s = list(st.get("plan_times_s", []))
                t0 -= st["elapsed_s"]
                model = type(model).load(self.ckpt_dir / "model.pt")
                ts = torch.load(self.ckpt_dir / "train_state.pt", weights_only=True)
                if ts["optimizer"] is not None:
                    model._optimizer = torch.optim.Adam(model.parameters(), lr=model.config["lr"],
                                                        weight_decay=model.config["weight_decay"])
                    model._optimizer.load_state_dict(ts["optimizer"])
                model._gen.set_state(ts["generator"])
                first_it = st["iteration"] + 1
                _log(self.cfg, f"resuming after iteration {st['iteration']} ({len(data_recs)} recordings of data)")
            data = [e for r in data_recs for e in episodes_from_mcap(r, self.cfg.robot)]
            # "auto" measures (EnsembleDynamics.measure_dtypes); a resumed run keeps the precision
            # it started with, so its plans do not change numerics half-way
            dtype = c.inference_dtype
            if resumed is not None and dtype == "auto" and "inference_dtype" in report:
                dtype = "bf16" if report["inference_dtype"] == "bfloat16" else "fp32"
            report["inference_dtype"] = str(model.set_inference_dtype(dtype)).removeprefix("torch.")
            report["inference_dtype_measured"] = model.dtype_measurement if dtype == "auto" else None
            samples = self.fit_pddm_to_period(model)  # timing needs the architecture, not trained weights
            iterations = report.setdefault("iterations", [])
            for it in range(first_it, c.iterations + 1):
                t_it = time.monotonic()
                train = self.train(model, self.model_episodes(data), self.epochs_for(data, it))
                t_train = time.monotonic() - t_it
                n_plans = len(self.plan_times_s)
                t_roll = time.monotonic()
                path, scores = self.run_episodes(
                    lambda i, m=model, it=it: self.pddm_policy(m, self._seed(10 + it, i), self.pddm_samples()),
                    c.rollouts_per_iteration, f"{it:03d}-mpc", f"iteration {it}: PDDM rollouts")
                t_roll = time.monotonic() - t_roll
                new = episodes_from_mcap(path, self.cfg.robot)
                val = self.model_episodes([e for e in data if self.val_assigned.get(e.name)])
                # the turn the model predicted on the episodes it has just planned (never trained on)
                own = probe_turn(model, self.model_episodes(new), self.task, c.horizon, self.period_s)
                idx = [self.features.names.index(n) for n in BALL_NAMES]
                steps = int(sum(m["steps"] for m in scores))
                pt = np.asarray(self.plan_times_s[n_plans:]) * 1e3
                row = {"iteration": it, "points": int(sum(len(e) for e in data)),
                       "model": {**{k: train[k] for k in ("train_loss", "val_1step", "val_h") if k in train},
                                 **drop_prediction(model, val, self.task, idx, c.horizon)},
                       **summarize(scores), "weights": self.plan_summary(), "own_turn": own,
                       # where the iteration's time went: training; per PDDM step, the plan and the
                       # rest (sim, bus round trip, policy wrapper, recording, resets)
                       "timing": {"plan_ms_p50": float(np.percentile(pt, 50)) if pt.size else None,
                                  "plan_ms_p99": float(np.percentile(pt, 99)) if pt.size else None,
                                  "steps": steps, "ms_per_step": 1e3 * t_roll / max(1, steps),
                                  "plan_ms_mean": float(pt.mean()) if pt.size else None,
                                  "loadavg": open("/proc/loadavg").read().split()[:3]
                                  if Path("/proc/loadavg").exists() else None},
                       "wall_s": {"train": t_train, "rollouts": t_roll}}
                data += new
                data_recs.append(str(path))
                if c.random_rollouts_per_iteration:
                    rpath, walk = self.run_episodes(lambda i, it=it: self.random_walk(1000 * it + i),
                                                    c.random_rollouts_per_iteration, f"{it:03d}-random",
                                                    f"iteration {it}: random-walk rollouts")
                    data += episodes_from_mcap(rpath, self.cfg.robot)
                    data_recs.append(str(rpath))
                    row["random_walk"] = {"rollouts": len(walk), "drop_rate": float(np.mean([m["dropped"] for m in walk])),
                                          "points": int(sum(m["steps"] for m in walk))}
                if self.extra:
                    own_pts = int(row["points"] * (1.0 - self.cfg.val_fraction))
                    row["demonstrations"] = {"episodes": len(self.extra), "repeat": c.extra_repeat,
                                             "share": self.extra_points() / max(1, own_pts + self.extra_points())}
                row["wall_s"].update(iteration=time.monotonic() - t_it, since_start=time.monotonic() - t0)
                iterations.append(row)
                self.write_partial(report, t0)
                self.save_checkpoint(model, it, data_recs, time.monotonic() - t0)
                _log(self.cfg, f"iteration {it}: trained on {row['points']} points (val_h {train.get('val_h', float('nan')):.3f}); "
                               f"PDDM {row['mean_return']:.1f} mean return, {row['drops']}/{len(scores)} drops, "
                               f"{row['mean_rotation_deg']:.0f}° mean rotation, success_90 {row['success_90']:.2f} "
                               f"(held {row['held_90']:.2f}), "
                               f"ESS {row['weights'].get('ess_mean', float('nan')):.1f}, "
                               f"shift {row['weights'].get('mean_shift_rms', float('nan')):.3f}, "
                               f"{row['timing']['ms_per_step']:.0f} ms/step (plan p50 {row['timing']['plan_ms_p50'] or 0:.0f} ms)")
            model.save(self.out / "model.pt")
        pc = self.pddm_config(samples)
        pt = np.asarray(self.plan_times_s) * 1e3
        report["iterations"] = iterations
        final = {"hold (keep the start pose)": report["hold_policy"], "random (uniform actions)": report["random_policy"]}
        if iterations:
            final[f"PDDM iteration {iterations[-1]['iteration']}"] = iterations[-1]
        report["ranking_by_turns"] = sorted(final, key=lambda k: turn_rank_key(final[k]))
        report["model_state"] = self.features.names
        report["planner"] = {**asdict(pc), "init_mean": c.init_mean, "action_units": c.action_units,
                             "plan_ms_p50": float(np.percentile(pt, 50)) if pt.size else None,
                             "plan_ms_p99": float(np.percentile(pt, 99)) if pt.size else None,
                             "plans": int(pt.size)}
        if self.planner_fit is not None:  # wall-clock rigs: K fitted to the period (configured: config.samples)
            report["planner"]["realtime_fit"] = self.planner_fit
        sup = self.supervisor
        report["resets"] = ({**{k: sup.stats.get(k, 0) for k in ("requested", "completed", "failed")},
                             "mean_duration_s": float(np.mean(sup.durations_s)) if sup.durations_s else 0.0}
                            if sup is not None else {"requested": 0, "completed": 0, "failed": 0, "mean_duration_s": 0.0})
        report["points"] = int(sum(len(e) for e in data))
        report["recordings"] = self.recordings
        report["model"] = str(self.out / "model.pt")
        report["wall_s"] = time.monotonic() - t0
        return report
