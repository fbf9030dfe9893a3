"""MELD's meta-training (thesis Algorithm 7) and meta-test (Algorithm 8), for any agent of
:mod:`.agents` on any :class:`ImageTaskEnv`.

Algorithm 7, as run here::

    for each training task: collect ``initial_episodes`` with random actions into its buffer
    repeat until ``env_samples`` are spent:
        for ``tasks_per_epoch`` training tasks drawn at random: set the task, run one episode
            with the agent (its belief filtered online, actions sampled), add it to that task's buffer
        ``train_steps_per_epoch`` gradient steps (model on the ELBO + SAC on the beliefs)
        every ``eval_every`` epochs: Algorithm 8 on the held-out tasks

Algorithm 8: on each held-out task, reset the belief and act with the mean action for one
episode; no gradient steps (all adaptation is in the belief). Success is the task's own test
on the last state of the episode.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from hilstack.learning.meld.replay import ImageEpisode, TaskReplay


class ImageTaskEnv(Protocol):
    """A family of tasks seen through a camera. Tasks are indices into ``task_params``."""

    action_dim: int
    episode_steps: int
    task_params: np.ndarray          #: [n_tasks, P] what distinguishes the tasks (for the task probe)
    task_param_names: Sequence[str]
    train_tasks: Sequence[int]
    test_tasks: Sequence[int]

    def set_task(self, task: int) -> None: ...
    def reset(self) -> tuple[np.ndarray, float]: ...          # (image u8 [H, W, 3], reward)
    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, dict[str, Any]]: ...  # info: success
    def close(self) -> None: ...                             # release renderers, drivers


@dataclass
class MetaTrainConfig:
    env_samples: int = 50_000        #: the thesis' real-WidowX budget
    initial_episodes: int = 1        #: random episodes per training task before learning
    tasks_per_epoch: int = 4
    train_steps_per_epoch: int = 40
    eval_every: int = 5              #: epochs between held-out evaluations
    eval_tasks: int | None = None    #: held-out tasks per evaluation (None: all)
    #: stop once on-policy collection + gradient steps took this wall time (random start and
    #: evaluations not counted); the samples reached are reported
    time_budget_s: float | None = None
    seed: int = 0


def run_episode(env: ImageTaskEnv, task: int, policy: Callable[[], np.ndarray] | None, agent: Any = None,
                rng: np.random.Generator | None = None) -> tuple[ImageEpisode, dict[str, Any]]:
    """One episode on ``task``. ``policy=None``: uniform random actions. The agent (if any)
    observes every image and reward."""
    env.set_task(task)
    img, r = env.reset()
    images, rewards, actions = [img], [r], []
    if agent is not None:
        agent.reset()
        agent.observe(img, r)
    info: dict[str, Any] = {}
    for _ in range(env.episode_steps):
        a = rng.uniform(-1.0, 1.0, env.action_dim) if policy is None else policy()
        img, r, info = env.step(a)
        images.append(img), rewards.append(r), actions.append(np.asarray(a, dtype=np.float32))
        if agent is not None:
            agent.observe(img, r)
    ep = ImageEpisode(np.stack(images), np.asarray(rewards, np.float32), np.stack(actions), task,
                      bool(info.get("success", False)))
    return ep, info


def meta_test(env: ImageTaskEnv, agent: Any, tasks: Sequence[int]) -> dict[str, Any]:
    """Algorithm 8 on ``tasks``: success rate and mean episode reward (sum over steps)."""
    succ, rew, final_d = [], [], []
    for task in tasks:
        ep, info = run_episode(env, task, lambda: agent.act(deterministic=True), agent)
        succ.append(ep.success)
        rew.append(float(ep.rewards[1:].sum()))
        if "distance_m" in info:
            final_d.append(float(info["distance_m"]))
    out = {"success_rate": float(np.mean(succ)), "reward": float(np.mean(rew)), "episodes": len(tasks)}
    if final_d:
        out["final_distance_m"] = float(np.mean(final_d))
    return out


def meta_train(env: ImageTaskEnv, agent: Any, cfg: MetaTrainConfig, log: Callable[[str], None] | None = None,
               initial_replay: TaskReplay | None = None) -> dict[str, Any]:
    """Algorithm 7. Returns the learning curve ``[{samples, success_rate, reward, ...}]``, the
    final held-out evaluation and wall times. ``initial_replay``: start from these episodes
    (several methods sharing one random start); its samples count in the budget."""
    if not 1 <= cfg.tasks_per_epoch <= len(env.train_tasks):
        raise ValueError(f"MetaTrainConfig.tasks_per_epoch {cfg.tasks_per_epoch}: must be 1..{len(env.train_tasks)} "
                         "(the number of training tasks)")
    rng = np.random.default_rng(cfg.seed)
    replay = initial_replay if initial_replay is not None else TaskReplay()
    t0 = time.perf_counter()
    t_collect = t_train = t_eval = t_learn = 0.0
    test_tasks = list(env.test_tasks)
    if cfg.eval_tasks is not None:
        test_tasks = test_tasks[: cfg.eval_tasks]

    def evaluate(epoch: int) -> dict[str, Any]:
        nonlocal t_eval
        te = time.perf_counter()
        res = meta_test(env, agent, test_tasks)
        t_eval += time.perf_counter() - te
        point = {"epoch": epoch, "samples": replay.n_samples, **res}
        if log:
            log(f"[{agent.name}] samples {replay.n_samples}: held-out success {res['success_rate']:.2f}, "
                f"reward {res['reward']:.1f} ({time.perf_counter() - t0:.0f} s)")
        return point

    tc = time.perf_counter()
    for task in env.train_tasks:
        for _ in range(cfg.initial_episodes):
            replay.add(run_episode(env, task, None, rng=rng)[0])
    t_collect += time.perf_counter() - tc
    curve = [evaluate(0)]
    epoch = 0
    stats: dict[str, float] = {}
    stopped_by_time = False
    while replay.n_samples < cfg.env_samples:
        if cfg.time_budget_s is not None and t_learn > cfg.time_budget_s:
            stopped_by_time = True
            break
        epoch += 1
        tc = time.perf_counter()
        for task in rng.choice(list(env.train_tasks), size=cfg.tasks_per_epoch, replace=False):
            replay.add(run_episode(env, int(task), lambda: agent.act(deterministic=False), agent)[0])
        t_collect += time.perf_counter() - tc
        tt = time.perf_counter()
        for _ in range(cfg.train_steps_per_epoch):
            stats = agent.train_step(replay, rng)
        t_train += time.perf_counter() - tt
        t_learn += time.perf_counter() - tc
        if epoch % cfg.eval_every == 0:
            curve.append(evaluate(epoch))
    if curve[-1]["samples"] != replay.n_samples:
        curve.append(evaluate(epoch))
    return {"curve": curve, "final": curve[-1], "samples": replay.n_samples, "epochs": epoch,
            "gradient_steps": epoch * cfg.train_steps_per_epoch, "stopped_by_time": stopped_by_time,
            "wall_s": {"total": time.perf_counter() - t0, "collect": t_collect, "train": t_train, "eval": t_eval},
            "last_stats": stats, "replay": replay}


def task_probe(features: np.ndarray, params: np.ndarray, ridge: float = 1e-3) -> np.ndarray:
    """Linear read-out of the task from belief features: ridge regression ``W`` with
    ``[features, 1] @ W ≈ params`` (least squares, fitted on training tasks' episodes)."""
    x = np.concatenate([features, np.ones((len(features), 1))], 1)
    return np.linalg.solve(x.T @ x + ridge * np.eye(x.shape[1]), x.T @ params)


def apply_probe(w: np.ndarray, features: np.ndarray) -> np.ndarray:
    return np.concatenate([features, np.ones((len(features), 1))], 1) @ w
