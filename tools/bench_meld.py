"""`hil bench meld`: what bounds MELD on this machine.

* collection: policy-rate samples per second of random episodes on each image task through the
  driver contract, rendering included, beside the same loop with the cameras off (the peer: the
  ratio is the rendering's share);
* learning: gradient steps per second of each learner (MELD's model + SAC step, SLAC's, the
  history SAC's) at each image size, beside MELD at the smallest size (the peer).

Run alone for clean numbers: the machine's load is printed with them.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np


def _collect_rate(task_name: str, camera_px: int, cameras: bool, episodes: int) -> float:
    from hilstack.learning.meld.train import run_episode
    from hilstack.tools.meld_tasks import TASKS

    env = TASKS[task_name](camera_px=camera_px, cameras=cameras)
    rng = np.random.default_rng(0)
    try:
        run_episode(env, env.train_tasks[0], None, rng=rng)  # warm-up (renderer, first task)
        t = time.perf_counter()
        for i in range(episodes):
            run_episode(env, env.train_tasks[i % 2], None, rng=rng)
        return episodes * env.episode_steps / (time.perf_counter() - t)
    finally:
        env.close()


def _grad_rate(method: str, camera_px: int, steps: int, batch: int, seq_len: int) -> float:
    import torch

    from hilstack.learning.meld.agents import AGENTS, AgentConfig
    from hilstack.learning.meld.model import LatentConfig
    from hilstack.learning.meld.replay import ImageEpisode, TaskReplay

    rng = np.random.default_rng(0)
    rp = TaskReplay()
    hw = (camera_px, 2 * camera_px)
    for task in range(4):
        rp.add(ImageEpisode(rng.integers(0, 255, (41, *hw, 3), dtype=np.uint8), rng.normal(size=41).astype(np.float32),
                            rng.uniform(-1, 1, (40, 6)).astype(np.float32), task))
    torch.manual_seed(0)
    agent = AGENTS[method](AgentConfig(latent=LatentConfig(image_hw=hw, action_dim=6), batch=batch, seq_len=seq_len))
    agent.train_step(rp, rng)
    t = time.perf_counter()
    for _ in range(steps):
        agent.train_step(rp, rng)
    return steps / (time.perf_counter() - t)


def _policy_step_ms(camera_px: int, n: int = 50) -> dict[str, float]:
    """One acting step of a MELD policy: the belief update on a new image and reward + the actor
    (what a controller node would run each 0.3 s period on the WidowX), p50/p99 [ms]."""
    import torch

    from hilstack.learning.meld.agents import AgentConfig, MeldAgent
    from hilstack.learning.meld.model import LatentConfig

    agent = MeldAgent(AgentConfig(latent=LatentConfig(image_hw=(camera_px, 2 * camera_px), action_dim=6)))
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (camera_px, 2 * camera_px, 3), dtype=np.uint8)
    agent.reset()
    ts = []
    with torch.no_grad():
        for _ in range(n):
            t = time.perf_counter()
            agent.observe(img, 0.5)
            agent.act(deterministic=True)
            ts.append(time.perf_counter() - t)
    return {"p50": 1e3 * float(np.percentile(ts, 50)), "p99": 1e3 * float(np.percentile(ts, 99))}


def run_bench_meld(episodes: int = 2, steps: int = 3, sizes: tuple[int, ...] = (32, 64), threads: int = 2,
                   batch: int = 32, seq_len: int = 8, tasks: tuple[str, ...] = ("widowx_port", "sawyer_reach")) -> dict[str, Any]:
    import torch

    os.environ.setdefault("MUJOCO_GL", "egl")
    torch.set_num_threads(threads)
    out: dict[str, Any] = {"load_avg_1min": os.getloadavg()[0], "threads": threads, "batch_sequences": batch,
                           "seq_len": seq_len, "collection_samples_per_s": {}, "gradient_steps_per_s": {}}
    for task in tasks:
        c = out["collection_samples_per_s"][task] = {}
        c["no_cameras"] = _collect_rate(task, sizes[0], False, episodes)
        for px in sizes:
            c[f"{px}x{2 * px}"] = _collect_rate(task, px, True, episodes)
            c[f"{px}x{2 * px}_vs_no_cameras"] = c[f"{px}x{2 * px}"] / c["no_cameras"]
    g = out["gradient_steps_per_s"]
    for px in sizes:
        for m in ("meld", "slac", "sac_history"):
            g[f"{m}_{px}x{2 * px}"] = _grad_rate(m, px, steps, batch, seq_len)
    out["policy_step_ms"] = {f"{px}x{2 * px}": _policy_step_ms(px) for px in sizes}
    out["policy_period_ms_widowx"] = 300.0
    peer = g[f"meld_{sizes[0]}x{2 * sizes[0]}"]
    out["gradient_ratio_vs_meld_smallest"] = {k: v / peer for k, v in g.items()}
    out["load_avg_1min_after"] = os.getloadavg()[0]
    return out
