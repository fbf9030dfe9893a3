"""Diagnostics of what limits MELD on a task (docs/meld.md, "What limits it"): SAC on the
*true* state and task (the joint angles and the goal; no images, no inference) on the same
episodes, rewards and success test. Its learning curve is a lower bound on what MELD needs:
MELD must learn the same controller from a belief it infers from images and rewards.

Knobs measured here (the issue's candidates): updates per environment sample, reward scale,
entropy target, batch size. Each run reports held-out success against environment samples and
gradient steps, and the wall time of collection and of learning.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from hilstack.learning.meld.sac import Sac, SacConfig


@dataclass(frozen=True)
class StateSacConfig:
    samples: int = 8000
    updates_per_sample: float = 1.0    #: gradient steps per environment sample (UTD)
    batch: int = 256
    reward_scale: float = 1.0
    target_entropy_per_dim: float = -1.0   #: SAC's usual −1 per action dimension
    random_episodes: int = 20           #: random-action episodes before learning (one per training task)
    eval_every: int = 40                #: episodes between held-out evaluations
    seed: int = 0


class _Buffer:
    def __init__(self, n: int, obs_dim: int, act_dim: int):
        self.o, self.a = np.zeros((n, obs_dim), np.float32), np.zeros((n, act_dim), np.float32)
        self.r, self.o2, self.d = np.zeros(n, np.float32), np.zeros((n, obs_dim), np.float32), np.zeros(n, np.float32)
        self.n = 0

    def add(self, o, a, r, o2, done) -> None:
        i = self.n % len(self.r)
        self.o[i], self.a[i], self.r[i], self.o2[i], self.d[i] = o, a, r, o2, done
        self.n += 1

    def sample(self, rng: np.random.Generator, b: int):
        idx = rng.integers(min(self.n, len(self.r)), size=b)
        return [torch.as_tensor(x[idx]) for x in (self.o, self.a, self.r, self.o2, self.d)]


def _obs(env: Any) -> np.ndarray:
    return np.concatenate([env.state(), env.goal_features()]).astype(np.float32)


def _episode(env: Any, task: int, act: Callable[[np.ndarray], np.ndarray], buf: _Buffer | None,
             scale: float) -> dict[str, Any]:
    env.set_task(task)
    env.reset()
    o = _obs(env)
    ret, info = 0.0, {}
    for _ in range(env.episode_steps):
        a = act(o)
        _, r, info = env.step(a)
        o2 = _obs(env)
        if buf is not None:  # no terminal state: episodes end by time, the value bootstraps
            buf.add(o, a, scale * r, o2, 0.0)
        o, ret = o2, ret + r
    return {"return": ret, "success": bool(info["success"]), "distance_m": float(info["distance_m"])}


def state_sac(env: Any, cfg: StateSacConfig, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """SAC on (joint angles, goal) of ``env`` (an ``ImageTaskEnv`` built with ``cameras=False``
    that has ``state()`` and ``goal_features()``). Returns the held-out learning curve."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    env.set_task(env.train_tasks[0])
    env.reset()
    obs_dim, act_dim = len(_obs(env)), env.action_dim
    sac = Sac(obs_dim, act_dim, SacConfig())
    sac.target_entropy = cfg.target_entropy_per_dim * act_dim
    buf = _Buffer(max(cfg.samples, 1), obs_dim, act_dim)
    t_collect = t_learn = 0.0
    grad_steps, owed = 0, 0.0
    curve = []

    def evaluate(episodes: int) -> None:
        res = [_episode(env, t, lambda o: sac.act(torch.as_tensor(o), deterministic=True), None, 1.0)
               for t in env.test_tasks]
        pt = {"samples": buf.n, "episodes": episodes, "gradient_steps": grad_steps,
              "success_rate": float(np.mean([r["success"] for r in res])),
              "final_distance_m": float(np.mean([r["distance_m"] for r in res])),
              "return": float(np.mean([r["return"] for r in res]))}
        curve.append(pt)
        if log:
            log(f"[state sac] {pt['samples']} samples, {grad_steps} steps: held-out success {pt['success_rate']:.2f}, "
                f"final distance {100 * pt['final_distance_m']:.1f} cm")

    ep = 0
    while buf.n < cfg.samples:
        task = int(rng.choice(env.train_tasks))
        t0 = time.perf_counter()
        if ep < cfg.random_episodes:
            _episode(env, task, lambda o: rng.uniform(-1, 1, act_dim), buf, cfg.reward_scale)
        else:
            _episode(env, task, lambda o: sac.act(torch.as_tensor(o)), buf, cfg.reward_scale)
        t1 = time.perf_counter()
        t_collect += t1 - t0
        if ep >= cfg.random_episodes - 1:
            owed += cfg.updates_per_sample * env.episode_steps
            while owed >= 1.0:
                sac.update(*sac_batch(buf, rng, cfg.batch))
                grad_steps += 1
                owed -= 1.0
        t_learn += time.perf_counter() - t1
        ep += 1
        if ep % cfg.eval_every == 0:
            evaluate(ep)
    if not curve or curve[-1]["samples"] != buf.n:
        evaluate(ep)
    return {"config": asdict(cfg), "curve": curve, "final": curve[-1],
            "wall_s": {"collect": t_collect, "learn": t_learn}}


def sac_batch(buf: _Buffer, rng: np.random.Generator, b: int):
    o, a, r, o2, d = buf.sample(rng, b)
    return o, a, r, o2, 1.0 - d
