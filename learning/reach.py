"""Reach-to-goal on the arms with a learned dynamics model and MPC (`hil demo arms`).

    random joint-velocity data through the driver bridge (recorded to MCAP)
    → dynamics learned at the policy rate (joint positions and velocities → the same)
    → CEM MPC on the reward of MELD's reaching tasks
    vs a damped-least-squares IK controller (gains tuned by a random search) and a
    random policy, on goals from the task distribution.

Everything runs over the bus as in :mod:`hilstack.learning.mbrl` (whose rig processes, episodes,
model and training this module calls): the arm's driver bridge in its own process, the
controllers here. The drivers run at their own period (20 Hz); the policies act at the
thesis' rates (WidowX 3.3 Hz, Sawyer 4 Hz, Zhao et al. / MELD, Nagabandi's thesis ch. 7)
by holding each action for ``hold`` driver periods, as MELD's joint-velocity policy sits
above the robots' low-level PID loops. The learned model therefore predicts one policy
step (``hold`` driver periods) ahead.

Reward (thesis ch. 7, the simulated Sawyer tasks): ``r = −(d² + log(d + 1e-5))`` with
``d`` the end-effector distance to the goal [m]; MPC minimizes ``Σ_h d_h² + log(d_h + 1e-5)``
over its horizon. The end effector comes from forward kinematics of the MuJoCo model
(:class:`hilstack.learning.kinematics.ChainKinematics`), never from the simulator's state, so the
same code runs on a real arm. Success: ``d < 2 cm`` at the end of the 40-step episode.

Goals: on the WidowX the task-reset mechanism (its own robot on the bus) is driven to a
random pose (rotation within ±8°, rail offset within ±1 cm) and the goal is the switch
port at the measured pose; on the Sawyer one of three target boxes.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

import numpy as np
import torch

from hilstack.configs.presets import Presets
from hilstack.configs.schema import BusConfig
from hilstack.control.controller_node import ControllerNode
from hilstack.control.planners import CEM
from hilstack.control.policies import MpcPolicy
from hilstack.control.policy_api import PlanDetails, PlanningPolicy, Resettable
from hilstack.learning.datasets import Episode
from hilstack.learning.kinematics import ChainKinematics
from hilstack.learning.mbrl import MbrlConfig, MbrlRun, RigError, _jsonable, make_model, recording
from hilstack.learning.progress import progress
from hilstack.learning.recordings import episodes_from_mcap

#: success: the end effector within this distance of the goal at the episode end [m]
SUCCESS_M = 0.02


def reach_cost(d: torch.Tensor) -> torch.Tensor:
    """MELD's reaching cost (the negated reward) of an end-effector distance ``d`` [m]:
    ``d² + log(d + 1e-5)``; the log term keeps a gradient of the cost near the goal."""
    return d * d + torch.log(d + 1e-5)


# ---------------------------------------------------------------------------- the arms
@dataclass(frozen=True)
class ArmTask:
    """What differs between the arms. ``model`` builds the MuJoCo model whose kinematics
    give the end effector (and, on the WidowX, the switch port)."""

    name: str
    rig: str
    robot: str                       #: the arm's key in the rig
    joints: tuple[str, ...]          #: MuJoCo joint names, in the spec's joint order
    ee_site: str
    policy_period_s: float           #: the thesis' control period (3.3 Hz / 4 Hz)
    mechanism: str | None = None     #: the task-reset mechanism's key in the rig (WidowX)
    #: Sawyer: target box centres [m, world frame] (the task distribution's three goals)
    boxes: tuple[tuple[float, float, float], ...] = ()
    #: random data with scaled magnitudes (:class:`RandomPolicy`). Measured in quick runs
    #: (docs/arms.md): the Sawyer starts mid-workspace and uniform actions carry it far from
    #: the boxes (MPC 1/3 at 2.0 cm, scaled 3/3 at 0.8 cm); the WidowX starts folded and
    #: needs the large motions to reach the switch (uniform 4/5 at 1.3 cm, scaled 0/5 at 3.2 cm)
    random_scaled: bool = False

    def model(self):
        """The arm's kinematics skill (registry: ``<robot>.kinematics``)."""
        from hilstack.drivers.registry import skill

        return skill(self.name, "kinematics").kinematics_model()


def _joints(robot: str) -> tuple[str, ...]:
    from hilstack.drivers.registry import spec_of

    return tuple(spec_of(robot).joint_names())


def widowx_task() -> ArmTask:
    return ArmTask("widowx", "arm_widowx_sim", "arm", _joints("widowx"), "ee", 0.3, mechanism="mechanism")


#: three boxes in front of the Sawyer at table height, 15 cm apart (our choice: the thesis
#: does not give their coordinates); the arm starts with its hand at (0.0, 0.59, 0.18)
SAWYER_BOXES = ((-0.15, 0.75, 0.10), (0.0, 0.80, 0.10), (0.15, 0.75, 0.10))


def sawyer_task() -> ArmTask:
    return ArmTask("sawyer", "arm_sawyer_sim", "arm", _joints("sawyer"), "endEffector", 0.25, boxes=SAWYER_BOXES,
                   random_scaled=True)


ARMS = {"widowx": widowx_task, "sawyer": sawyer_task}


# ---------------------------------------------------------------------------- config
#: IK gain search space: (low, high); gain [1/s] turns the position error into a
#: Cartesian velocity, damping [m] regularizes the pseudo-inverse near singularities
IK_SEARCH: dict[str, tuple[float, float]] = {"gain_per_s": (0.3, 4.0), "damping_m": (0.002, 0.1)}
IK_DEFAULT = {"gain_per_s": 1.0, "damping_m": 0.02}


@dataclass
class ReachConfig(Presets):
    #: the presets of ``from_preset(name, **overrides)`` (configs/presets.py): overrides of the defaults
    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "quick": dict(random_episodes=40, eval_goals=5),
        "full": dict(random_episodes=150, epochs=200, ensemble=3, eval_goals=10, seeds=(0, 1, 2)),
    }

    arm: str = "widowx"
    #: seeds of the evaluation: each trains its own model on its own random data
    seeds: tuple[int, ...] = (0,)
    episode_steps: int = 40          #: policy steps per episode (thesis: 40)
    random_episodes: int = 60
    #: random data: each action times a uniform factor in [0, 1] (small commands, the ones
    #: near the goal, covered better) instead of the thesis' uniform actions; None: the
    #: arm's choice (:attr:`ArmTask.random_scaled`)
    random_scaled: bool | None = None
    hidden: tuple[int, ...] = (128, 128)
    ensemble: int = 1
    epochs: int = 120
    batch_size: int = 256
    samples: int = 300
    horizon: int = 5
    #: CEM refits; σ restarts at a quarter of the range every step, so the iterations set the
    #: precision near the goal (3, the roach's, stopped ~1.5 cm short on the WidowX; 6 ~0.8 cm)
    cem_iterations: int = 6
    cem_elites: int = 50
    eval_goals: int = 6              #: WidowX: mechanism poses per seed (the Sawyer has its 3 boxes)
    tune_goals: int = 3              #: goals of the IK search (not evaluation goals)
    #: IK candidates; the search runs ``tune_candidates × tune_goals`` episodes, at least
    #: the random episodes the MPC's model was trained on (the same robot time)
    tune_candidates: int = 0
    #: WidowX: driver periods the mechanism gets to reach a new pose
    mechanism_settle_steps: int = 40
    progress: bool = True
    rig_timeout_s: float = 60.0

    def __post_init__(self) -> None:
        problems = []
        if self.arm not in ARMS:
            problems.append(f"arm: unknown {self.arm!r}, choose from {list(ARMS)}")
        if not self.seeds:
            problems.append("seeds: need at least one")
        if self.tune_goals < 1 or self.eval_goals < 1 or self.random_episodes < 2:
            problems.append("tune_goals, eval_goals >= 1 and random_episodes >= 2")
        if problems:
            raise ValueError("ReachConfig: " + "; ".join(problems))
        if self.tune_candidates <= 0:  # the same robot time as the MPC's data
            self.tune_candidates = int(np.ceil(self.random_episodes / self.tune_goals))

    def mbrl(self, task: ArmTask, seed: int) -> MbrlConfig:
        """The shared loop's settings (rig, model, planner) for this arm."""
        return MbrlConfig(rig=task.rig, robot=task.robot, seed=seed, hidden=self.hidden, ensemble=self.ensemble,
                          epochs=self.epochs, batch_size=self.batch_size, body_frame=False, invariant_inputs=(),
                          planner="cem", samples=self.samples, horizon=self.horizon, progress=self.progress,
                          rig_timeout_s=self.rig_timeout_s)


# ---------------------------------------------------------------------------- policies
class HeldPolicy:
    """Acts every ``hold`` calls (the policy rate) on the model's channels of the state
    and repeats that action in between (the driver rate)."""

    def __init__(self, inner: Any, hold: int, channels: Sequence[int]):
        self.inner, self.hold, self.channels = inner, int(hold), np.asarray(channels)
        self._n = 0
        self._a: np.ndarray | None = None

    # to the controller node it is a PlanningPolicy with PlanDetails (control/policy_api.py): the
    # inner MPC's plan is published. It calls the inner policy with the state alone.

    def reset(self) -> None:
        self._n = 0
        if isinstance(self.inner, Resettable):
            self.inner.reset()

    def __call__(self, state: np.ndarray) -> np.ndarray:
        if self._n % self.hold == 0:
            self._a = np.asarray(self.inner(np.asarray(state)[self.channels]), dtype=np.float64)
        self._n += 1
        return self._a

    # the controller node publishes the MPC's plan when there is one
    @property
    def last_plan(self):
        return self.inner.last_plan if isinstance(self.inner, PlanningPolicy) else None

    @property
    def last_predicted_states(self):
        return self.inner.last_predicted_states if isinstance(self.inner, PlanDetails) else None

    @property
    def last_cost(self) -> float:
        return self.inner.last_cost if isinstance(self.inner, PlanDetails) else 0.0


class RandomPolicy:
    """Uniform normalized joint velocities (a new one each policy step); with ``scaled``,
    each is multiplied by a uniform factor in [0, 1], so that small commands, the ones MPC
    needs near the goal, are as common as large ones."""

    def __init__(self, action_dim: int, seed: int, scaled: bool = False):
        self.dim, self.rng, self.scaled = action_dim, np.random.default_rng(seed), scaled

    def __call__(self, state: np.ndarray) -> np.ndarray:
        a = self.rng.uniform(-1.0, 1.0, self.dim)
        return a * self.rng.uniform() if self.scaled else a


class ReachCost:
    """The planner's cost: ``Σ_{h=1..H} reach_cost(‖fk(q_h) − goal‖)`` over predicted
    model states ``[E, N, H+1, S]`` (joint positions in the first ``n_joints`` channels)."""

    def __init__(self, fk: ChainKinematics, goal: np.ndarray, n_joints: int):
        self.fk, self.n = fk, n_joints
        self.goal = torch.as_tensor(np.asarray(goal), dtype=torch.float32)

    def __call__(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        ee = self.fk(states[..., 1:, : self.n])
        return reach_cost(torch.linalg.vector_norm(ee - self.goal, dim=-1)).sum(-1)


class IkController:
    """Damped least squares on the end-effector position: ``q̇ = J⊤ (J J⊤ + λ² I)⁻¹ · k · (goal − x)``,
    clipped to the joint velocity limits, as a normalized action (``vel_limit_rad_s`` per joint
    is action 1)."""

    def __init__(self, fk: ChainKinematics, goal: np.ndarray, vel_limit_rad_s: np.ndarray,
                 gain_per_s: float, damping_m: float):
        self.fk, self.goal = fk, np.asarray(goal, dtype=np.float64)
        self.vmax = np.asarray(vel_limit_rad_s, dtype=np.float64)
        self.gain, self.damping = float(gain_per_s), float(damping_m)

    def __call__(self, state: np.ndarray) -> np.ndarray:
        q = np.asarray(state[: len(self.vmax)], dtype=np.float64)
        j = self.fk.jacobian(q)
        err = self.goal - self.fk.position(q)
        qd = j.T @ np.linalg.solve(j @ j.T + self.damping**2 * np.eye(3), self.gain * err)
        return np.clip(qd / self.vmax, -1.0, 1.0)


def ik_candidates(n: int, seed: int) -> list[dict[str, float]]:
    """``n`` IK gain sets: :data:`IK_DEFAULT` first, then a Latin hypercube over
    :data:`IK_SEARCH` (scipy.stats.qmc; the damping on a log scale)."""
    from scipy.stats import qmc

    out = [dict(IK_DEFAULT)]
    if n > 1:
        (g_lo, g_hi), (d_lo, d_hi) = IK_SEARCH["gain_per_s"], IK_SEARCH["damping_m"]
        for u in qmc.LatinHypercube(d=2, seed=seed).random(n - 1):
            out.append({"gain_per_s": float(g_lo + u[0] * (g_hi - g_lo)),
                        "damping_m": float(np.exp(np.log(d_lo) + u[1] * (np.log(d_hi) - np.log(d_lo))))})
    return out


def policy_rate_episode(ep: Episode, hold: int, channels: Sequence[int]) -> Episode:
    """A driver-rate episode as seen by a policy acting every ``hold`` periods: every
    ``hold``-th state (model channels only) and, per block, the action the driver applied
    last in it. Recordings hold the *applied* action, which the driver's rate limit ramps
    towards the held command over the first periods of a block: its last value is the
    command itself unless the step was larger than the limit allows in one block."""
    n = (len(ep.actions) // hold) * hold
    meta = dict(ep.meta)
    for k in ("state_names", "state_units"):
        if meta.get(k) is not None:
            meta[k] = [meta[k][i] for i in channels]
    times = None if ep.times is None else ep.times[: n + 1 : hold]
    return Episode(ep.states[: n + 1 : hold][:, channels], ep.actions[hold - 1 : n : hold], times=times, name=ep.name,
                   meta=meta)


def summarize(final_d_m: Sequence[float]) -> dict[str, Any]:
    d = np.asarray(final_d_m, dtype=np.float64)
    return {"episodes": int(d.size), "success_rate": float(np.mean(d < SUCCESS_M)),
            "final_distance_m": {"mean": float(d.mean()), "std": float(d.std())}}


# ---------------------------------------------------------------------------- the loop
class ReachRun:
    """One arm, one seed: random data → model → MPC, tuned IK and random on the goals."""

    def __init__(self, cfg: ReachConfig, task: ArmTask, out_dir: Path, bus: BusConfig, seed: int):
        self.cfg, self.task, self.seed = cfg, task, seed
        self.out = Path(out_dir)
        self.loop = MbrlRun(cfg.mbrl(task, seed), self.out, bus)
        model = task.model()
        self.fk = ChainKinematics(model, task.ee_site, task.joints)
        self.port_fk = ChainKinematics(model, "port", ("mech_rail", "mech_rotate")) if task.mechanism else None
        self.mech: ControllerNode | None = None
        self.rng = np.random.default_rng([seed, 7])

    def _log(self, msg: str) -> None:
        if self.cfg.progress:
            print(f"[reach {self.task.name} {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)

    @contextlib.contextmanager
    def session(self) -> Iterator[None]:
        with self.loop.session():
            names = self.loop.state_names
            n = len(self.task.joints)
            self.channels = [names.index(f"{j}_pos") for j in self._spec_joints()] + \
                            [names.index(f"{j}_vel") for j in self._spec_joints()]
            self.n_joints = n
            self.model_names = [names[i] for i in self.channels]
            self.hold = int(round(self.task.policy_period_s / self.loop.period_s))
            if abs(self.hold * self.loop.period_s - self.task.policy_period_s) > 1e-6:
                raise ValueError(f"{self.task.name}: the driver period {self.loop.period_s} s does not divide "
                                 f"the policy period {self.task.policy_period_s} s")
            self.vel_limit = self.loop.ctl.spec.action.high.copy()
            if self.task.mechanism:
                with ControllerNode(self.loop.rig.name, self.task.mechanism, self.loop.bus, name="reach-mechanism",
                                    handle_signals=False, state_timeout_s=20.0) as mech:
                    mech.wait_ready(timeout_s=self.cfg.rig_timeout_s)
                    self.mech = mech
                    try:
                        yield
                    finally:
                        self.mech = None
            else:
                yield

    def _spec_joints(self) -> list[str]:
        """The spec's joint names (channel ``<joint>_pos``), in the MuJoCo joints' order."""
        names = self.loop.state_names
        out = [n[: -len("_pos")] for n in names if n.endswith("_pos")]
        if tuple(out) != tuple(self.task.joints):
            raise ValueError(f"{self.task.name}: spec has joints {out}, the model {list(self.task.joints)}")
        return out

    # -- goals ------------------------------------------------------------------------
    def goals(self, n: int) -> list[dict[str, Any]]:
        """``n`` goals of the task distribution (not yet applied to the robot)."""
        if self.task.mechanism:
            return [{"mechanism_target": self.rng.uniform(-1.0, 1.0, 2).tolist()} for _ in range(n)]
        return [{"box": i % len(self.task.boxes)} for i in range(n)]

    def apply_goal(self, g: dict[str, Any]) -> np.ndarray:
        """Set the task up on the rig and return the goal position [m, world]. WidowX: the
        mechanism moves to its target (normalized rotation, offset) and the goal is the port
        at the pose it measures."""
        if self.task.mechanism:
            target = np.asarray(g["mechanism_target"], dtype=np.float64)
            log = self.mech.run_episode(lambda s: target, self.cfg.mechanism_settle_steps)
            rotate, offset = (float(v) for v in log.states[-1][:2])
            g["mechanism_pose"] = {"rotate_rad": rotate, "offset_m": offset}
            return self.port_fk.position(np.array([offset, rotate]))
        # the IK search's goals are boxes moved by a jitter (not the evaluation goals)
        return np.asarray(self.task.boxes[g["box"]], dtype=np.float64) + np.asarray(g.get("box_jitter_m", np.zeros(3)))

    # -- episodes -----------------------------------------------------------------------
    def run_episode(self, inner: Any) -> dict[str, Any]:
        pol = HeldPolicy(inner, self.hold, self.channels)
        log = self.loop.episode(pol, self.cfg.episode_steps * self.hold, {})
        states = np.asarray(log.states)[:: self.hold][:, self.channels]
        # the policy's own steps only (HeldPolicy runs its inner policy on every hold-th call):
        # the held calls in between take no planning. Selected by the call each time measured,
        # not by its position in the list, which a call with no time would shift
        plan_s = [t for t, c in zip(log.plan_times_s, log.plan_calls, strict=True) if c % self.hold == 0]
        return {"q": states[:, : self.n_joints], "plan_s": plan_s, "late_plans": log.late_plans}

    def score(self, q: np.ndarray, goal: np.ndarray) -> dict[str, Any]:
        d = np.linalg.norm(self.fk.position(q) - goal, axis=-1)
        return {"final_distance_m": float(d[-1]), "success": bool(d[-1] < SUCCESS_M),
                "return": float(-reach_cost(torch.as_tensor(d[1:])).sum()), "distance_m": d.round(4).tolist()}

    def collect_random(self) -> list[Episode]:
        path = self.loop.rec_dir / "000-random.mcap"
        scaled = self.task.random_scaled if self.cfg.random_scaled is None else self.cfg.random_scaled
        pol = RandomPolicy(len(self.vel_limit), self.seed, scaled=scaled)
        with recording(self.loop.rig.name, path, self.loop.bus):
            for _ in self._progress(range(self.cfg.random_episodes), f"random episodes → {path.name}"):
                self.run_episode(pol)
        self.loop.recordings.append(str(path))
        eps = episodes_from_mcap(path, self.task.robot)
        return [policy_rate_episode(e, self.hold, self.channels) for e in eps]

    def evaluate(self, make_inner, goals: list[dict[str, Any]], after=None) -> list[dict[str, Any]]:
        """One episode per goal, scored; ``after(r, i)`` is told each episode's result."""
        out = []
        for i, g in enumerate(goals):
            goal = self.apply_goal(g)
            r = self.run_episode(make_inner(goal))
            if after is not None:
                after(r, i)
            out.append({**g, "goal_m": goal.round(4).tolist(),
                        **self.score(r["q"], goal),
                        "plan_ms_p50": float(np.percentile(r["plan_s"], 50) * 1e3) if r["plan_s"] else 0.0})
        return out

    def refit_mpc(self, planner: Any, r: dict[str, Any], i: int) -> int | None:
        """Wall-clock arms: the MPC's sample count follows the load, refitted after every MPC
        episode ``r`` (:meth:`run_episode`'s result: its policy steps' plan times and late plans;
        :meth:`MbrlRun.refit_samples`) and set on ``planner`` for the next goal. None on lockstep."""
        n = self.loop.refit_samples(SimpleNamespace(plan_times_s=r["plan_s"], late_plans=r["late_plans"],
                                                    actions=r["plan_s"]), f"mpc goal {i}")
        if n is not None:
            planner.set_samples(n)
        return n

    def tune_ik(self, goals: list[dict[str, Any]]) -> dict[str, Any]:
        """Random search over the IK gains on ``goals``: ranked by successes, then mean final distance."""
        scored = []
        for p in self._progress(ik_candidates(self.cfg.tune_candidates, self.seed), "tuning IK"):
            res = self.evaluate(lambda goal, p=p: IkController(self.fk, goal, self.vel_limit, **p), goals)
            d = [r["final_distance_m"] for r in res]
            scored.append({"params": p, "successes": int(sum(r["success"] for r in res)), "mean_final_m": float(np.mean(d))})
        best = min(scored, key=lambda s: (-s["successes"], s["mean_final_m"]))
        return {"best_params": best["params"], "best": best, "default": scored[0], "candidates": scored,
                "episodes": len(scored) * len(goals)}

    def run(self) -> dict[str, Any]:
        torch.manual_seed(self.seed)
        t0 = time.monotonic()
        rep: dict[str, Any] = {"seed": self.seed}
        try:
            return self._run(rep, t0)
        except TimeoutError as e:
            raise RigError(f"{e} (driver log: {self.out / 'logs' / 'driver.log'})") from None

    def _run(self, rep: dict[str, Any], t0: float) -> dict[str, Any]:
        cfg = self.cfg
        with self.session():
            data = self.collect_random()
            rep["random_transitions"] = int(sum(len(e) for e in data))
            self._log(f"{len(data)} random episodes, {rep['random_transitions']} transitions at "
                      f"{1 / self.task.policy_period_s:.2f} Hz")
            model = make_model(self.loop.cfg, self.model_names, self.loop.action_names)
            rep["training"] = self.loop.train(model, data, cfg.epochs)
            self._log(f"trained: {rep['training']}")
            model.save(self.out / "model.pt")

            tune_goals = self.goals(cfg.tune_goals)
            if not self.task.mechanism:  # the Sawyer's task has 3 goals: tune on nearby others
                for g in tune_goals:
                    g["box_jitter_m"] = self.rng.uniform(-0.05, 0.05, 3).tolist()
            eval_goals = self.goals(len(self.task.boxes) if self.task.boxes else cfg.eval_goals)
            tune_path = self.loop.rec_dir / "800-tune-ik.mcap"
            with recording(self.loop.rig.name, tune_path, self.loop.bus):
                rep["ik_tuning"] = self.tune_ik(tune_goals)
            self.loop.recordings.append(str(tune_path))
            self._log(f"IK: default {rep['ik_tuning']['default']} → best {rep['ik_tuning']['best']}")

            ik = rep["ik_tuning"]["best_params"]
            def cem(n: int) -> CEM:  # elites in the configured proportion (50 of 300)
                return CEM(action_low=-1.0, action_high=1.0, horizon=cfg.horizon, samples=n, seed=self.seed,
                           action_dim=len(self.vel_limit), iterations=cfg.cem_iterations,
                           elites=max(1, min(n, round(cfg.cem_elites * n / cfg.samples))))

            # wall-clock arms: the samples cut until the median plan fits the period (hilstack.learning.mbrl)
            fitted = self.loop.realtime_samples(model, make=cem, cost=ReachCost(self.fk, np.zeros(3), self.n_joints))  # any goal times it
            planner = cem(cfg.samples if fitted is None else fitted)
            if self.loop.planner_fit is not None:
                rep["planner_realtime"] = self.loop.planner_fit
            rand = RandomPolicy(len(self.vel_limit), self.seed + 1000)  # one stream: other actions every episode
            controllers = {
                # wall-clock rigs: plan from the state after the command already sent (hilstack.learning.mbrl)
                "mpc": lambda goal: MpcPolicy(model, planner, ReachCost(self.fk, goal, self.n_joints),
                                              delay_steps=self.loop.command_delay),
                "ik": lambda goal: IkController(self.fk, goal, self.vel_limit, **ik),
                "random": lambda goal: rand,
            }
            eval_path = self.loop.rec_dir / "900-eval.mcap"
            with recording(self.loop.rig.name, eval_path, self.loop.bus):
                rep["episodes"] = {}
                for name, make in controllers.items():
                    rep["episodes"][name] = self.evaluate(make, [dict(g) for g in eval_goals],
                                                          after=partial(self.refit_mpc, planner) if name == "mpc" else None)
                    self._log(f"{name}: {summarize([e['final_distance_m'] for e in rep['episodes'][name]])}")
            self.loop.recordings.append(str(eval_path))
        rep["recordings"] = self.loop.recordings
        rep["wall_s"] = time.monotonic() - t0
        return rep

    def _progress(self, it, desc: str):
        return progress(it, desc=desc, file=sys.stderr) if self.cfg.progress else it


def run_arm(cfg: ReachConfig, out: Path, bus: BusConfig) -> dict[str, Any]:
    """Every seed of one arm; the report (``out/report.json``) pools goals and seeds."""
    task = ARMS[cfg.arm]()
    runs = [ReachRun(cfg, task, out / f"seed{s}", bus, s).run() for s in cfg.seeds]
    report: dict[str, Any] = {"arm": task.name, "rig": task.rig, "config": _jsonable(asdict(cfg)),
                              "task": _jsonable(asdict(task)), "success_m": SUCCESS_M,
                              "policy_hz": 1 / task.policy_period_s, "seeds": runs}
    report["summary"] = {c: summarize([e["final_distance_m"] for r in runs for e in r["episodes"][c]])
                         for c in ("mpc", "ik", "random")}
    return report


__all__ = ["ARMS", "ArmTask", "ChainKinematics", "HeldPolicy", "IkController", "ReachConfig", "ReachCost",
           "ReachRun", "reach_cost", "run_arm"]
