"""MBRL and model-free fine-tuning (Mb-Mf) on gymnasium's MuJoCo benchmarks (thesis ch. 2).

``hil demo mbrl-gym`` (tools/demo_mbmf.py) runs, per environment and seed, three learners
and records each one's evaluation return against the environment steps it has used:

* **MB**: the thesis' model-based loop on the environment's own reward. Random rollouts,
  fit a dynamics model, then iterations of random-shooting MPC rollouts aggregated into the
  data and a warm-started refit. The model is :class:`~hilstack.learning.dynamics.EnsembleDynamics`
  (one member), fitted with :func:`hilstack.learning.mbrl.fit_episodes` (the roach loop's
  fitting), and the planner is :class:`hilstack.control.planners.RandomShooting`; the cost is
  minus the benchmark's reward computed from the predicted states (:func:`reward_cost`).
* **MF**: TRPO (``sb3_contrib.TRPO``) from scratch, a 2×64 tanh Gaussian policy.
* **Mb-Mf**: the last ``saved_rollouts`` MPC rollouts of MB are imitated by the same
  policy (behaviour cloning: the Gaussian's likelihood of the MPC's actions, Adam 1e-4,
  batch 500); then
  ``dagger_iters`` DAgger iterations: run the policy, label every state it visited with the
  MPC's action from that state (no environment step: the MPC plans on the model),
  aggregate, refit. The policy's std is then set to 1.0 and TRPO fine-tunes it, with the
  same hyperparameters as MF. Its steps are MB's plus the DAgger rollouts' plus TRPO's.

An evaluation return is the mean undiscounted return of ``eval_episodes`` episodes of
``episode_len`` steps (fewer when the environment terminates: hopper and ant fall) with
the policy's mean action; evaluation episodes are not counted as training steps. MB's
points are the returns of the MPC rollouts of each iteration (they are its training data
too, and counted). Thesis Table 2.7 settings and the scaling to 2 cores: docs/mbrl.md.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hilstack.control.planners import RandomShooting
from hilstack.learning.datasets import Episode
from hilstack.learning.dynamics import EnsembleDynamics
from hilstack.learning.mbrl import fit_episodes

__all__ = ["GymTask", "TASKS", "MbmfConfig", "reward_cost", "make_env", "run_episode", "run_mb", "new_trpo",
           "behaviour_clone", "dagger_iteration", "reset_policy_std", "run_mf", "run_mbmf", "do_nothing_return",
           "METHODS"]

METHODS = ("mb", "mf", "mbmf")


@dataclass(frozen=True)
class GymTask:
    """A gymnasium v5 locomotion benchmark and its reward written on the observation.

    ``velocity_index``: the root's forward velocity (qvel[0]) in the observation;
    reward per step = v − ``ctrl_cost``·|a|² + ``healthy_reward`` (while healthy); an
    unhealthy state (hopper, ant: fallen) ends the episode. ``z_index``/``angle_index``:
    the torso height and pitch in the observation, with gymnasium's healthy ranges.
    """

    gym_id: str
    obs_dim: int
    action_dim: int
    velocity_index: int
    ctrl_cost: float
    healthy_reward: float = 0.0
    z_index: int | None = None
    z_range: tuple[float, float] = (-math.inf, math.inf)
    angle_index: int | None = None
    angle_range: tuple[float, float] = (-math.inf, math.inf)
    #: |obs[1:]| below this to be healthy (hopper: gymnasium checks qpos[2:], qvel)
    state_bound: float | None = None
    gamma: float = 0.99
    kwargs: tuple[tuple[str, Any], ...] = ()

    @property
    def terminates(self) -> bool:
        return self.z_index is not None or self.angle_index is not None


TASKS: dict[str, GymTask] = {
    # obs qpos[2:] (3) + qvel (5); swimmer needs γ≈1 for policy gradients (rl-baselines3-zoo: 0.9999)
    "swimmer": GymTask("Swimmer-v5", 8, 2, 3, 1e-4, gamma=0.9999),
    # obs qpos[1:] (8) + qvel (9)
    "half_cheetah": GymTask("HalfCheetah-v5", 17, 6, 8, 0.1),
    # obs qpos[1:] (5: z, pitch, joints) + qvel (6, clipped to ±10)
    "hopper": GymTask("Hopper-v5", 11, 3, 5, 1e-3, 1.0, z_index=0, z_range=(0.7, math.inf), angle_index=1,
                      angle_range=(-0.2, 0.2), state_bound=100.0),
    # obs qpos[2:] (13) + qvel (14): the contact forces are left out of the observation
    # (their small cost, 5e-4·|F|², stays in the environment's reward, not in the planner's)
    "ant": GymTask("Ant-v5", 27, 8, 13, 0.5, 1.0, z_index=0, z_range=(0.2, 1.0),
                   kwargs=(("include_cfrc_ext_in_observation", False),)),
}


@dataclass(frozen=True)
class MbmfConfig:
    """Budgets of one (environment, seed) run; every count is per seed."""

    episode_len: int = 250
    # MB
    random_rollouts: int = 8
    mb_iterations: int = 2
    mpc_rollouts: int = 2            # per MB iteration
    hidden: tuple[int, ...] = (256, 256)
    epochs: int = 100               # ~500-700 Adam steps per fit at these data sizes
    batch_size: int = 512
    val_fraction: float = 0.1
    samples: int = 300               # random shooting N
    horizon: int = 10                # H
    # Mb-Mf (thesis Table 2.7: 30 saved rollouts, 3 DAgger iterations, Adam 1e-4, batch 500)
    saved_rollouts: int = 4
    dagger_iters: int = 3
    dagger_rollouts: int = 1
    bc_epochs: int = 1000            # passes over the aggregated data per (re)fit (2-4k Adam steps)
    bc_lr: float = 1e-4
    bc_batch: int = 500
    policy_hidden: tuple[int, ...] = (64, 64)
    # TRPO (MF, and Mb-Mf's fine-tuning); sb3-contrib defaults otherwise
    mf_steps: int = 60_000
    ft_steps: int = 16_000           # with MB's ≤ 3.75k: Mb-Mf uses ≤ a third of MF's budget
    n_steps: int = 1024
    eval_every: int = 5_000
    eval_episodes: int = 3
    threads: int = 1

    @classmethod
    def quick(cls, **kw: Any) -> MbmfConfig:
        base = dict(mf_steps=30_000, ft_steps=8_000, eval_every=3_000)
        return cls(**{**base, **kw})

    @classmethod
    def tiny(cls, **kw: Any) -> MbmfConfig:
        base = dict(episode_len=40, random_rollouts=3, mb_iterations=1, mpc_rollouts=1, hidden=(32, 32), epochs=3,
                    samples=30, horizon=4, saved_rollouts=1, dagger_iters=1, dagger_rollouts=1, bc_epochs=2,
                    mf_steps=256, ft_steps=128, n_steps=64, eval_every=128, eval_episodes=1)
        return cls(**{**base, **kw})


# -- the benchmark's reward on predicted states ---------------------------------------------------------
def healthy(task: GymTask, states: torch.Tensor) -> torch.Tensor:
    """Boolean ``[...]``: gymnasium's healthy test of each state ``[..., S]`` (all True for
    the environments that never terminate)."""
    ok = torch.isfinite(states).all(-1)
    if task.z_index is not None:
        z = states[..., task.z_index]
        ok &= (z > task.z_range[0]) & (z < task.z_range[1])
    if task.angle_index is not None:
        ang = states[..., task.angle_index]
        ok &= (ang > task.angle_range[0]) & (ang < task.angle_range[1])
    if task.state_bound is not None:
        ok &= (states[..., 1:].abs() < task.state_bound).all(-1)
    return ok


def step_rewards(task: GymTask, next_states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Per-step reward ``[..., H]`` of reaching ``next_states`` ``[..., H, S]`` with
    ``actions`` ``[..., H, A]``; after the first unhealthy state the rewards are 0 (the
    episode would have ended)."""
    r = next_states[..., task.velocity_index] - task.ctrl_cost * (actions * actions).sum(-1)
    if task.healthy_reward or task.terminates:
        ok = healthy(task, next_states).to(next_states.dtype)
        r = (r + task.healthy_reward) * torch.cumprod(ok, dim=-1)
    return r


def reward_cost(task: GymTask) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The planner's cost: minus the predicted return over the horizon (``[E, N]``)."""
    def cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        return -step_rewards(task, states[..., 1:, :], actions.unsqueeze(0)).sum(-1)
    return cost


# -- environment --------------------------------------------------------------------------------------
def make_env(name: str, episode_len: int):
    import gymnasium as gym

    if name not in TASKS:
        raise ValueError(f"unknown benchmark {name!r}; known: {', '.join(TASKS)}")
    task = TASKS[name]
    env = gym.make(task.gym_id, max_episode_steps=int(episode_len), **dict(task.kwargs))
    if env.observation_space.shape != (task.obs_dim,):
        raise RuntimeError(f"{task.gym_id} observation is {env.observation_space.shape}, expected ({task.obs_dim},)")
    return env


def run_episode(env, act: Callable[[np.ndarray], np.ndarray], seed: int) -> tuple[Episode, float]:
    """One episode (until termination or the time limit): the Episode and its return."""
    s, _ = env.reset(seed=int(seed))
    states, actions, ret = [s], [], 0.0
    while True:
        a = np.clip(np.asarray(act(s), dtype=np.float32), -1.0, 1.0)
        s, r, term, trunc, _ = env.step(a)
        states.append(s)
        actions.append(a)
        ret += float(r)
        if term or trunc:
            break
    return Episode(np.array(states), np.array(actions), name=f"ep{seed}"), ret


def do_nothing_return(name: str, episode_len: int, seeds=(0, 1, 2)) -> dict[str, float]:
    """Mean ± std return of the zero action (the do-nothing controller) and of uniform random actions."""
    env = make_env(name, episode_len)
    A = TASKS[name].action_dim
    zero = [run_episode(env, lambda s: np.zeros(A), 900 + i)[1] for i in seeds]
    rng = np.random.default_rng(0)
    rand = [run_episode(env, lambda s: rng.uniform(-1, 1, A), 900 + i)[1] for i in seeds]
    env.close()
    return {"zero_mean": float(np.mean(zero)), "zero_std": float(np.std(zero)),
            "random_mean": float(np.mean(rand)), "random_std": float(np.std(rand))}


# -- MB ---------------------------------------------------------------------------------------------------
@dataclass
class MbResult:
    model: EnsembleDynamics
    planner: RandomShooting
    cost: Callable
    episodes: list[Episode]
    mpc_episodes: list[Episode]
    steps: int
    curve: list[dict[str, float]] = field(default_factory=list)

    def expert(self, state: np.ndarray) -> np.ndarray:
        """The MPC's action from ``state`` (plans on the model; no environment step)."""
        return self.planner(self.model.predict, self.cost, state)


def _named(ep: Episode, name: str) -> Episode:
    ep.name = name
    return ep


def run_mb(name: str, cfg: MbmfConfig, seed: int, log: Callable[[str], None] = print) -> MbResult:
    """The model-based loop; ``curve``: ``{steps, return_mean, return_std}`` per MPC iteration."""
    task = TASKS[name]
    env = make_env(name, cfg.episode_len)
    rng = np.random.default_rng(seed)
    A = task.action_dim
    eps: list[Episode] = []
    for i in range(cfg.random_rollouts):
        ep, _ = run_episode(env, lambda s: rng.uniform(-1, 1, A), 10_000 * seed + i)
        eps.append(_named(ep, f"random{i}"))
    steps = sum(len(e) for e in eps)
    model = EnsembleDynamics(task.obs_dim, A, ensemble=1, hidden=cfg.hidden, seed=seed)
    planner = RandomShooting(-1.0, 1.0, horizon=cfg.horizon, samples=cfg.samples, action_dim=A, seed=seed)
    cost = reward_cost(task)
    split_rng, assigned = np.random.default_rng([seed, 1]), {}
    res = MbResult(model, planner, cost, eps, [], steps)
    fit = fit_episodes(model, eps, cfg.epochs, cfg.batch_size, cfg.val_fraction, split_rng, assigned,
                       horizon=cfg.horizon)
    log(f"  mb {name} s{seed}: random {steps} steps, fit {fit.get('val_h', float('nan')):.3g} (val H-step)")
    for it in range(cfg.mb_iterations):
        rets = []
        for j in range(cfg.mpc_rollouts):
            planner.reset()
            ep, ret = run_episode(env, res.expert, 10_000 * seed + 1000 * (it + 1) + j)
            eps.append(_named(ep, f"mpc{it}_{j}"))
            res.mpc_episodes.append(ep)
            rets.append(ret)
            res.steps += len(ep)
        res.curve.append({"steps": res.steps, "return_mean": float(np.mean(rets)), "return_std": float(np.std(rets))})
        log(f"  mb {name} s{seed} iteration {it}: {res.steps} steps, MPC return {np.mean(rets):.1f}")
        if it < cfg.mb_iterations - 1:  # the last rollouts are not followed by a refit: nothing uses it
            fit_episodes(model, eps, cfg.epochs, cfg.batch_size, cfg.val_fraction, split_rng, assigned,
                         horizon=cfg.horizon)
    env.close()
    return res


# -- policies ---------------------------------------------------------------------------------------------
def new_trpo(name: str, cfg: MbmfConfig, seed: int):
    """sb3-contrib's TRPO with the thesis' 2×64 tanh Gaussian policy (std 1 at init)."""
    try:
        from sb3_contrib import TRPO
    except ImportError as e:  # pragma: no cover - a dependency of the package
        raise RuntimeError("sb3-contrib is missing: install hilstack (pip install -e .)") from e
    task = TASKS[name]
    env = make_env(name, cfg.episode_len)
    kw = dict(net_arch=dict(pi=list(cfg.policy_hidden), vf=list(cfg.policy_hidden)), activation_fn=torch.nn.Tanh,
              log_std_init=0.0)
    return TRPO("MlpPolicy", env, n_steps=cfg.n_steps, batch_size=min(128, cfg.n_steps), gamma=task.gamma, policy_kwargs=kw, seed=seed, device="cpu",
                verbose=0)


def policy_mean(policy, states: np.ndarray | torch.Tensor) -> torch.Tensor:
    """The Gaussian policy's mean action (differentiable) for ``states`` ``[B, S]``."""
    obs = torch.as_tensor(np.asarray(states), dtype=torch.float32)
    features = policy.extract_features(obs, policy.pi_features_extractor)
    return policy.action_net(policy.mlp_extractor.forward_actor(features))


def policy_act(policy) -> Callable[[np.ndarray], np.ndarray]:
    def act(s: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return policy_mean(policy, s[None])[0].numpy()
    return act


def behaviour_clone(policy, states: np.ndarray, actions: np.ndarray, epochs: int, lr: float, batch: int,
                    seed: int) -> float:
    """Fit the Gaussian policy to ``actions`` by maximum likelihood with Adam: the mean
    network and the (state-independent) log std move, so the std shrinks to the imitation
    error (and :func:`reset_policy_std` sets it back before fine-tuning). Returns the last
    epoch's mean squared error of the mean action."""
    params = (list(policy.mlp_extractor.policy_net.parameters()) + list(policy.action_net.parameters())
              + [policy.log_std])
    opt = torch.optim.Adam(params, lr=lr)
    x = torch.as_tensor(states, dtype=torch.float32)
    y = torch.as_tensor(np.clip(actions, -1, 1), dtype=torch.float32)
    gen = torch.Generator().manual_seed(seed)
    mse = math.nan
    for _ in range(epochs):
        perm = torch.randperm(len(x), generator=gen)
        sq, n = 0.0, 0
        for i in range(0, len(x), batch):
            idx = perm[i:i + batch]
            err = policy_mean(policy, x[idx]) - y[idx]
            nll = (0.5 * (err / policy.log_std.exp()) ** 2 + policy.log_std).mean()
            opt.zero_grad()
            nll.backward()
            opt.step()
            sq, n = sq + (err.detach() ** 2).mean().item() * len(idx), n + len(idx)
        mse = sq / max(n, 1)
    return float(mse)


def dagger_iteration(env, act: Callable[[np.ndarray], np.ndarray], expert: Callable[[np.ndarray], np.ndarray],
                     rollouts: int, seed: int) -> tuple[np.ndarray, np.ndarray, list[float], int]:
    """Run the learner ``act`` for ``rollouts`` episodes and label every state it visited
    with the ``expert``'s action from that state: ``(states, labels, returns, env steps)``."""
    states, labels, rets, steps = [], [], [], 0
    for j in range(rollouts):
        ep, ret = run_episode(env, act, seed + j)
        visited = ep.states[:-1]
        states.append(visited)
        labels.append(np.stack([np.asarray(expert(s), dtype=np.float32) for s in visited]))
        rets.append(ret)
        steps += len(ep)
    return np.concatenate(states), np.concatenate(labels), rets, steps


def reset_policy_std(policy, std: float = 1.0) -> None:
    """Set the Gaussian policy's (state-independent) std to ``std`` on every action dimension."""
    with torch.no_grad():
        policy.log_std.fill_(math.log(std))


def evaluate(env, act, episodes: int, seed: int) -> tuple[float, float]:
    rets = [run_episode(env, act, seed + i)[1] for i in range(episodes)]
    return float(np.mean(rets)), float(np.std(rets))


def _trpo_curve(algo, name: str, cfg: MbmfConfig, steps: int, offset: int, seed: int,
                curve: list[dict[str, float]], log: Callable[[str], None], tag: str,
                on_point: Callable[[list], None] | None = None) -> None:
    """``algo.learn(steps)`` with an evaluation every ``eval_every`` steps (and at 0);
    ``on_point(curve)`` after each evaluation."""
    from stable_baselines3.common.callbacks import BaseCallback

    eval_env = make_env(name, cfg.episode_len)
    base = algo.num_timesteps

    def point() -> None:
        n = algo.num_timesteps - base
        m, s = evaluate(eval_env, policy_act(algo.policy), cfg.eval_episodes, 50_000 + 100 * seed)
        curve.append({"steps": offset + n, "return_mean": m, "return_std": s})
        log(f"  {tag} {name} s{seed}: {offset + n} steps, return {m:.1f}")
        if on_point is not None:
            on_point(curve)

    class Every(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next = cfg.eval_every

        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            if algo.num_timesteps - base >= self.next:
                point()
                self.next += cfg.eval_every

    point()
    algo.learn(steps, callback=Every(), reset_num_timesteps=False)
    if curve[-1]["steps"] != offset + algo.num_timesteps - base:
        point()
    eval_env.close()


def run_mf(name: str, cfg: MbmfConfig, seed: int, log: Callable[[str], None] = print,
           on_point: Callable[[list], None] | None = None) -> list[dict[str, float]]:
    """TRPO from scratch: its evaluation curve."""
    torch.manual_seed(seed)
    algo = new_trpo(name, cfg, seed)
    curve: list[dict[str, float]] = []
    _trpo_curve(algo, name, cfg, cfg.mf_steps, 0, seed, curve, log, "mf", on_point)
    algo.env.close()
    return curve


def run_mbmf(name: str, cfg: MbmfConfig, seed: int, mb: MbResult, log: Callable[[str], None] = print,
             on_point: Callable[[list], None] | None = None) -> tuple[list[dict[str, float]], dict[str, Any]]:
    """Imitation of MB's MPC with DAgger, std → 1, TRPO fine-tuning: (curve, info). The
    curve's first points are the DAgger rollouts' returns (the policy's mean action, counted
    steps), then the fine-tuning's evaluations."""
    torch.manual_seed(seed)
    algo = new_trpo(name, cfg, seed)
    pol = algo.policy
    saved = mb.mpc_episodes[-cfg.saved_rollouts:]
    X = np.concatenate([e.states[:-1] for e in saved])
    Y = np.concatenate([e.actions for e in saved])
    info: dict[str, Any] = {"saved_rollouts": len(saved), "bc_loss": [], "dagger_returns": []}
    info["bc_loss"].append(behaviour_clone(pol, X, Y, cfg.bc_epochs, cfg.bc_lr, cfg.bc_batch, seed))
    env = make_env(name, cfg.episode_len)
    steps, curve = mb.steps, []
    for it in range(cfg.dagger_iters):
        mb.planner.reset()
        xs, ys, rets, n = dagger_iteration(env, policy_act(pol), mb.expert, cfg.dagger_rollouts,
                                           20_000 + 100 * seed + 10 * it)
        steps += n
        X, Y = np.concatenate([X, xs]), np.concatenate([Y, ys])
        info["dagger_returns"].append(float(np.mean(rets)))
        curve.append({"steps": steps, "return_mean": float(np.mean(rets)), "return_std": float(np.std(rets))})
        info["bc_loss"].append(behaviour_clone(pol, X, Y, cfg.bc_epochs, cfg.bc_lr, cfg.bc_batch, seed + it + 1))
        log(f"  mbmf {name} s{seed} DAgger {it}: policy return {np.mean(rets):.1f}, {steps} steps, "
            f"bc loss {info['bc_loss'][-1]:.3g}")
    env.close()
    info["std_before_finetune"] = float(pol.log_std.detach().exp().mean())
    reset_policy_std(pol, 1.0)
    info["imitation_steps"] = steps
    info["finetune_start_index"] = len(curve)  # the curve's points before: the DAgger rollouts
    _trpo_curve(algo, name, cfg, cfg.ft_steps, steps, seed, curve, log, "mbmf", on_point)
    algo.env.close()
    return curve, info


# -- one (env, seed) and the results on disk ---------------------------------------------------------------
def run_seed(name: str, cfg: MbmfConfig, seed: int, out: Path, log: Callable[[str], None] = print) -> dict[str, Any]:
    """MB, Mb-Mf (from that MB) and MF for one seed; each method's result is written to
    ``out/runs/<env>_<method>_s<seed>.json`` when it finishes, and a finished one with
    the same config is reused (an interrupted run continues)."""
    torch.set_num_threads(cfg.threads)
    runs = out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    conf = _jsonable(asdict(cfg))
    res: dict[str, Any] = {}

    def cached(method: str) -> dict[str, Any] | None:
        p = runs / f"{name}_{method}_s{seed}.json"
        if not p.exists():
            return None
        d = json.loads(p.read_text())
        if d.get("config") != conf:
            raise ValueError(f"{p} was written with another config; use another --out")
        log(f"  reusing {p.name}")
        return d

    def save(method: str, d: dict[str, Any]) -> dict[str, Any]:
        d = {"env": name, "method": method, "seed": seed, "config": conf, **d}
        p = runs / f"{name}_{method}_s{seed}.json"
        tmp = p.with_suffix(".tmp")
        tmp.write_text(json.dumps(_jsonable(d), indent=1))
        tmp.replace(p)
        return d

    def partial(method: str):
        """Writes the curve so far to ``<env>_<method>_s<seed>.partial.json`` (kept if the run is
        interrupted; not read by the report)."""
        def write(curve: list) -> None:
            p = runs / f"{name}_{method}_s{seed}.partial.json"
            p.write_text(json.dumps(_jsonable({"env": name, "method": method, "seed": seed, "curve": curve})))
        return write

    def timing(t: float, c: float) -> dict[str, float]:
        return {"wall_s": round(time.monotonic() - t, 1), "cpu_s": round(time.process_time() - c, 1)}

    mb_d, mbmf_d = cached("mb"), cached("mbmf")
    if mb_d is None or mbmf_d is None:
        t, c = time.monotonic(), time.process_time()
        mb = run_mb(name, cfg, seed, log)
        mb_d = save("mb", {"curve": mb.curve, **timing(t, c)})
        t, c = time.monotonic(), time.process_time()
        curve, info = run_mbmf(name, cfg, seed, mb, log, partial("mbmf"))
        mbmf_d = save("mbmf", {"curve": curve, "info": info, **timing(t, c)})
    res["mb"], res["mbmf"] = mb_d, mbmf_d
    mf_d = cached("mf")
    if mf_d is None:
        t, c = time.monotonic(), time.process_time()
        mf_d = save("mf", {"curve": run_mf(name, cfg, seed, log, partial("mf")), **timing(t, c)})
    res["mf"] = mf_d
    return res


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return o


# -- the comparison ------------------------------------------------------------------------------------------
def mean_curve(curves: list[list[dict[str, float]]]) -> list[dict[str, float]]:
    """Seeds' curves aggregated point by point (the i-th evaluation of every seed; as many
    points as the shortest curve): mean steps, mean ± std over seeds of the returns."""
    n = min(len(c) for c in curves)
    out = []
    for i in range(n):
        r = np.array([c[i]["return_mean"] for c in curves])
        out.append({"steps": float(np.mean([c[i]["steps"] for c in curves])), "return_mean": float(r.mean()),
                    "return_std": float(r.std()), "seeds": len(curves)})
    return out


def steps_to_reach(curve: list[dict[str, float]], target: float) -> float | None:
    """Environment steps of the first point whose return is ≥ ``target`` (None: never)."""
    for p in curve:
        if p["return_mean"] >= target:
            return float(p["steps"])
    return None


def compare(runs: dict[str, list[dict[str, Any]]], ratio: float = 3.0) -> dict[str, Any]:
    """MB, MF and Mb-Mf of one environment from their runs (``method → [run per seed]``).

    ``mf_final``: MF's mean return (over seeds) at the last evaluation of its budget.
    ``mbmf_steps_to_mf_final``: the first point of Mb-Mf's mean curve at or above it;
    ``speedup_vs_mf_budget`` = MF's budget / that, ``speedup_vs_mf_first_reach`` = the steps
    at which MF's own mean curve first reached its final value / that (the smaller, honest
    one; MF's curve is noisy). ``mf_converged``: MF's last point is within 5 % (of the
    range from its start) of its best over the last third of its budget and of the third
    before, i.e. the curve had flattened (otherwise MF's final reward is not its asymptote).
    """
    c = {m: mean_curve([r["curve"] for r in runs[m]]) for m in runs if runs[m]}
    res: dict[str, Any] = {"curves": c, "seeds": {m: sorted(r["seed"] for r in runs[m]) for m in runs}}
    if "mf" not in c or "mbmf" not in c:
        return res
    mf = c["mf"]
    target = mf[-1]["return_mean"]
    budget = mf[-1]["steps"]
    first = steps_to_reach(mf, target)
    at = steps_to_reach(c["mbmf"], target)
    span = max(abs(target - mf[0]["return_mean"]), 1e-9)
    third = [p["return_mean"] for p in mf if p["steps"] >= budget * 2 / 3]
    before = [p["return_mean"] for p in mf if budget / 3 <= p["steps"] < budget * 2 / 3]
    converged = bool(before) and abs(max(third) - max(before)) <= 0.05 * span
    per_seed = {}
    for r in runs["mbmf"]:
        s = steps_to_reach(r["curve"], target)
        per_seed[str(r["seed"])] = s
    res.update({
        "mf_final": target, "mf_final_std": mf[-1]["return_std"], "mf_budget": budget,
        "mf_first_reach": first, "mf_converged": converged,
        "mbmf_final": c["mbmf"][-1]["return_mean"], "mbmf_final_std": c["mbmf"][-1]["return_std"],
        "mbmf_steps_to_mf_final": at, "mbmf_steps_to_mf_final_per_seed": per_seed,
        "mbmf_imitation_steps": float(np.mean([r["info"]["imitation_steps"] for r in runs["mbmf"]])),
        "mbmf_after_imitation": c["mbmf"][min(runs["mbmf"][0]["info"].get("finetune_start_index", 0),
                                             len(c["mbmf"]) - 1)]["return_mean"],
        "speedup_vs_mf_budget": None if at is None else budget / at,
        "speedup_vs_mf_first_reach": None if at is None or first is None else first / at,
    })
    res["reached_ratio"] = bool(at is not None and first is not None and first / at >= ratio)
    return res
