"""Which change makes MB drive the unperturbed half-cheetah (issue 24, docs/adaptation.md "The
reference code's settings line by line"): one setting at a time against the reference code's (iclavera/learning_to_adapt).

    python scripts/hc_mb_probes/levers.py seed=0 vi=17 random=40 len=100 rounds=3 onpol=4 \
        hidden=128,128,128 planner=rs N=1000 H=10 ens=1 steps=200

vi: the state channel the planner's reward reads (17: the mean forward velocity over the step,
Δx/dt, the rewarded quantity; 8: the instantaneous qvel[0], the suite's channel before);
fs: MuJoCo steps per action (gymnasium 5: 0.05 s; the reference code's XML has none: 1, 0.01 s);
ens: E models (different init and a bootstrap of the episodes each), trajectory sampling
TS∞ with one particle per member (the planner averages the members' returns); rounds of
``onpol`` MPC rollouts (len steps each) aggregated and refitted. Prints the evaluation return
(``steps`` from the benchmark's start, reward = Δx/dt − 0.05 Σ a²) after each round, and CPU.
"""
import sys
import time
from dataclasses import replace

import numpy as np
import torch

from hilstack.control.planners import PDDM, RandomShooting
from hilstack.learning.adaptation import gym_suite as G
from hilstack.learning.adaptation.gym_envs import GymBenchmarkEnv, disabled_joint

torch.set_num_threads(1)
args = dict(a.split("=") for a in sys.argv[1:])
seed = int(args.get("seed", 0))
vi = int(args.get("vi", 17))
E = int(args.get("ens", 1))
cfg = replace(G.GymSuiteConfig(), random_rollouts=int(args.get("random", 40)), rollout_len=int(args.get("len", 100)),
              hidden=tuple(int(x) for x in args.get("hidden", "128,128,128").split(",")),
              epochs=int(args.get("epochs", 60)))
N, H, steps = int(args.get("N", 1000)), int(args.get("H", 10)), int(args.get("steps", 200))
env = GymBenchmarkEnv("half_cheetah", frame_skip=int(args["fs"]) if "fs" in args else None)
A = 6
normal = disabled_joint(A, None)


def cost(states, actions):
    return -(states[..., 1:, vi].sum(-1) - 0.05 * (actions * actions).sum((-1, -2)))


def fit(eps):
    rng = np.random.default_rng([seed, len(eps)])
    models = []
    for e in range(E):
        sub = eps if E == 1 else [eps[i] for i in rng.integers(0, len(eps), len(eps))]
        m, h = G.fit_mb("half_cheetah", cfg, sub, seed * 100 + e)
        models.append(m)
    return models, h.get("best_val")


def dynamics(models):
    ps = [m.params() for m in models]

    def dyn(s, a):
        with torch.no_grad():
            if len(models) == 1:
                return models[0].step(ps[0], s, a)
            if s.dim() == 2:
                return torch.stack([m.step(p, s, a) for m, p in zip(models, ps, strict=True)])
            return torch.stack([m.step(p, s[i], a) for i, (m, p) in enumerate(zip(models, ps, strict=True))])
    return dyn


def planner(k):
    if args.get("planner", "rs") == "rs":
        return RandomShooting(-1.0, 1.0, horizon=H, samples=N, action_dim=A, seed=k)
    return PDDM(-1.0, 1.0, horizon=H, samples=N, gamma=float(args.get("gamma", 10)), beta=float(args.get("beta", 0.6)),
                action_dim=A, seed=k)


def mpc(models, k, reset_seed, n_steps):
    pl, dyn = planner(k), dynamics(models)
    pl.reset()
    return G.rollout(env, n_steps, reset_seed, {0: normal}, lambda t, s: pl(dyn, cost, s))


t0 = time.process_time()
rng = np.random.default_rng([seed, 1])
eps = G.collect(env, cfg, [normal] * cfg.random_rollouts, rng, 1000 * (seed + 1))
models, val = fit(eps)
_, r0 = G.rollout(env, steps, 900_000 + seed, {0: normal}, lambda t, s: np.zeros(A))
print(f"args {args}; zero action {r0.sum():.1f}", flush=True)
for k in range(int(args.get("rounds", 3)) + 1):
    t = time.process_time()
    _, r = mpc(models, 7 + seed, 900_000 + seed, steps)
    print(f"round {k}: {sum(len(e) for e in eps)} transitions, held-out {val:.4f}, eval return {r.sum():.1f} "
          f"({r.mean():.3f} per step), eval cpu {time.process_time() - t:.0f} s, total cpu {time.process_time() - t0:.0f} s",
          flush=True)
    if k == int(args.get("rounds", 3)):
        break
    new = []
    for i in range(int(args.get("onpol", 4))):
        ep, rr = mpc(models, 1000 + 10 * k + i, 50_000 + 100 * k + i + 1000 * seed, cfg.rollout_len)
        new.append(ep)
    eps += new
    models, val = fit(eps)
print(f"done: cpu {time.process_time() - t0:.0f} s")
