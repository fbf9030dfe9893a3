"""Is MB's failure the data's reach? Random rollouts plus rollouts of random shooting with the true
simulator as its model (a running cheetah), then MB's MPC on the unperturbed robot.

    python scripts/hc_mb_probes/expert.py RANDOM_ROLLOUTS TRUE_MODEL_ROLLOUTS    # e.g. 40 20
"""
import sys
import time
from dataclasses import replace

import mujoco
import numpy as np
import torch

from hilstack.control.planners import PDDM, RandomShooting
from hilstack.learning.adaptation import gym_suite as G
from hilstack.learning.adaptation.baselines import MbAdapter
from hilstack.learning.adaptation.gym_envs import GymBenchmarkEnv, disabled_joint
from hilstack.learning.datasets import Episode

torch.set_num_threads(1)

NR, NE, N = int(sys.argv[1]), int(sys.argv[2]), 150
cfg = replace(G.GymSuiteConfig(), random_rollouts=NR, epochs=60, hidden=(128, 128, 128))
env = GymBenchmarkEnv("half_cheetah")
m, d = env.env.model, env.env.data
A = 6
t0 = time.process_time()
eps = G.collect(env, cfg, [disabled_joint(6, None)] * NR, np.random.default_rng(0), 1000)
rng = np.random.default_rng(1)
rets = []
for k in range(NE):
    s = env.reset(3000 + k)
    S, Aa, R = [s], [], 0.0
    for _t in range(100):
        q0, v0 = d.qpos.copy(), d.qvel.copy()
        C = rng.uniform(-1, 1, (N, 10, A))
        Rn = np.zeros(N)
        for n in range(N):
            d.qpos[:], d.qvel[:] = q0, v0
            for h in range(10):
                d.ctrl[:] = C[n, h]
                mujoco.mj_step(m, d, nstep=5)
                Rn[n] += d.qvel[0] - 0.05 * (C[n, h] ** 2).sum()
        d.qpos[:], d.qvel[:] = q0, v0
        mujoco.mj_forward(m, d)
        a = C[Rn.argmax(), 0].astype(np.float32)
        s, r = env.step(a)
        R += r
        S.append(s)
        Aa.append(a)
    eps.append(Episode(np.array(S), np.array(Aa)))
    rets.append(R)
print(
    "true-model RS rollouts' returns",
    [round(x, 1) for x in rets],
    "cpu",
    round(time.process_time() - t0),
    flush=True,
)
mb, h = G.fit_mb("half_cheetah", cfg, eps, 0)
print("MB on", sum(len(e) for e in eps), "held-out", round(h["best_val"], 4), flush=True)
cost = G.reward_cost("half_cheetah")
for name, pl in (
    ("pddm g1 N200", PDDM(-1.0, 1.0, horizon=10, samples=200, gamma=1.0, beta=0.6, action_dim=A, seed=7)),
    ("rs N500", RandomShooting(-1.0, 1.0, horizon=10, samples=500, action_dim=A, seed=7)),
):
    r, _ = G.closed_loop(env, MbAdapter(mb), pl, cost, 200, 900_000, {0: disabled_joint(A, None)})
    print(f"MB {name}: return {r.sum():.1f} over 200 steps ({r.mean():.2f} per step)", flush=True)
