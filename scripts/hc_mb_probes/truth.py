"""Random shooting (N = 300, H = 10) with the true simulator as its model, 100 steps from rest.

    python scripts/hc_mb_probes/truth.py
"""
import time

import mujoco
import numpy as np

from hilstack.learning.adaptation.gym_envs import GymBenchmarkEnv

env = GymBenchmarkEnv("half_cheetah")
e = env.env
m, d = e.model, e.data
N, H, steps = 300, 10, 100
rng = np.random.default_rng(0)
s = env.reset(1)
ret = 0
t0 = time.time()
for _t in range(steps):
    q0, v0 = d.qpos.copy(), d.qvel.copy()
    A = rng.uniform(-1, 1, (N, H, 6))
    R = np.zeros(N)
    for n in range(N):
        d.qpos[:], d.qvel[:] = q0, v0
        for h in range(H):
            d.ctrl[:] = A[n, h]
            mujoco.mj_step(m, d, nstep=5)
            R[n] += d.qvel[0] - 0.05 * (A[n, h] ** 2).sum()
    d.qpos[:], d.qvel[:] = q0, v0
    mujoco.mj_forward(m, d)
    s, r = env.step(A[R.argmax(), 0])
    ret += r
print("truth RS return", ret, "per step", ret / steps, time.time() - t0)
