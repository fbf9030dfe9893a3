"""The gym suite's closed loop (Controller, reward_cost, the planners) with a perfect model: the true
simulator as the batched dynamics.

    python scripts/hc_mb_probes/pipe.py
"""
import time

import mujoco
import numpy as np
import torch

from hilstack.control.planners import PDDM, RandomShooting
from hilstack.learning.adaptation import gym_suite as G
from hilstack.learning.adaptation.gym_envs import GymBenchmarkEnv, disabled_joint

torch.set_num_threads(1)

env = GymBenchmarkEnv("half_cheetah")
sim = GymBenchmarkEnv("half_cheetah")
m, d = sim.env.model, sim.env.data
sim.reset(0)


class Truth:
    def reset(self):
        pass

    def observe(self, *a):
        pass

    def update(self, *a):
        return None

    def dynamics(self, u):
        def dyn(s, a):
            out = np.empty_like(s.numpy())
            for i, (si, ai) in enumerate(zip(s.numpy(), a.numpy(), strict=True)):
                d.qpos[0] = 0
                d.qpos[1:] = si[:8]
                d.qvel[:] = si[8:17]
                d.ctrl[:] = np.clip(ai, -1, 1)
                mujoco.mj_step(m, d, nstep=5)
                out[i, :8] = d.qpos[1:]
                out[i, 8:17] = d.qvel
                out[i, 17] = d.qpos[0] / 0.05  # the mean forward velocity over the step (x started at 0)
            return torch.as_tensor(out)

        return dyn


t = time.process_time()
for name, pl in (
    ("rs N150", RandomShooting(-1.0, 1.0, horizon=10, samples=150, action_dim=6, seed=7)),
    ("pddm g1 N150", PDDM(-1.0, 1.0, horizon=10, samples=150, gamma=1.0, beta=0.6, action_dim=6, seed=7)),
):
    c = G.Controller(Truth(), pl, G.reward_cost("half_cheetah"))
    c.reset()
    _, r = G.rollout(env, 100, 900_000, {0: disabled_joint(6, None)}, c.act)
    print(
        f"perfect model through gym_suite's loop, {name}: return {r.sum():.1f} over 100 steps ({r.mean():.2f} per step) cpu {time.process_time() - t:.0f}",
        flush=True,
    )
