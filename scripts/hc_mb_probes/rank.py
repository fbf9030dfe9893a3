"""How well MB ranks candidate plans: Spearman of predicted vs true 10-step return of 200 random
plans from 12 states (true returns from MuJoCo reset to each state).

    python scripts/hc_mb_probes/rank.py RANDOM_ROLLOUTS HIDDEN     # e.g. 400 256,256,256
"""
import sys
import time
from dataclasses import replace

import mujoco
import numpy as np
import torch
from scipy.stats import spearmanr

from hilstack.learning.adaptation import gym_suite as G
from hilstack.learning.adaptation.gym_envs import GymBenchmarkEnv, disabled_joint

torch.set_num_threads(1)

H_ = tuple(int(x) for x in sys.argv[2].split(","))
cfg = replace(G.GymSuiteConfig(), random_rollouts=int(sys.argv[1]), epochs=60, hidden=H_)
env = GymBenchmarkEnv("half_cheetah")
m, d = env.env.model, env.env.data
t0 = time.process_time()
eps = G.collect(env, cfg, [disabled_joint(6, None)] * cfg.random_rollouts, np.random.default_rng(0), 1000)
mb, h = G.fit_mb("half_cheetah", cfg, eps, 0)
print(
    "n",
    sum(len(e) for e in eps),
    "fit cpu",
    round(time.process_time() - t0),
    "val",
    round(h["best_val"], 4),
    flush=True,
)
# test states: from a truth-RS-like trajectory? use states from a rollout of smooth random actions plus the start
rng = np.random.default_rng(5)
cors = []
top = []
for k in range(12):
    env.reset(100 + k)
    for _ in range(int(rng.integers(0, 60))):
        env.step(rng.uniform(-1, 1, 6))
    q0, v0 = d.qpos.copy(), d.qvel.copy()
    s0 = np.append(env.env._get_obs(), d.qvel[0]).astype(np.float32)  # the suite's state (18)
    A = rng.uniform(-1, 1, (200, 10, 6)).astype(np.float32)
    R = np.zeros(200)
    for n in range(200):
        d.qpos[:], d.qvel[:] = q0, v0
        for hh in range(10):
            d.ctrl[:] = A[n, hh]
            mujoco.mj_step(m, d, nstep=5)
            R[n] += d.qvel[0] - 0.05 * (A[n, hh] ** 2).sum()
    with torch.no_grad():
        s = torch.as_tensor(s0).expand(200, -1)
        P = torch.zeros(200)
        for hh in range(10):
            s = mb.step(mb.params(), s, torch.as_tensor(A[:, hh]))
            P += s[:, 8] - 0.05 * (torch.as_tensor(A[:, hh]) ** 2).sum(-1)
    cors.append(spearmanr(R, P.numpy())[0])
    top.append(R[int(P.argmax())] - R.mean())
print(
    f"spearman true vs predicted return of 200 random plans: {np.mean(cors):.3f} ± {np.std(cors):.3f}; "
    f"true gain of the predicted best over the mean {np.mean(top):.2f} (truth best {np.nan})",
    flush=True,
)
