"""MB's MPC on the unperturbed half-cheetah (docs/adaptation.md, "Does MB drive the unperturbed
half-cheetah"): zero-action and random-action floors, then MB (PDDM and, with rs=1, random
shooting) after each on-policy round.

    python scripts/hc_mb_probes/probe.py random=40 rounds=4 onpol=5 rs=1 epochs=100 hidden=256,256,256
"""
import sys
import time
from dataclasses import replace

import numpy as np
import torch

from hilstack.control.planners import PDDM, RandomShooting
from hilstack.learning.adaptation import gym_suite as G
from hilstack.learning.adaptation.baselines import MbAdapter
from hilstack.learning.adaptation.gym_envs import GymBenchmarkEnv, disabled_joint

torch.set_num_threads(1)

args = dict(a.split("=") for a in sys.argv[1:])
R = int(args.get("random", 40))
n_onpol = int(args.get("onpol", 8))
L = int(args.get("len", 100))
H = tuple(int(x) for x in args.get("hidden", "128,128,128").split(","))
steps = int(args.get("steps", 200))
seed = int(args.get("seed", 0))
cfg = replace(
    G.GymSuiteConfig(),
    random_rollouts=R,
    onpolicy_rollouts=0,
    rollout_len=L,
    hidden=H,
    epochs=int(args.get("epochs", 40)),
    samples=int(args.get("samples", 500)),
    gamma=float(args.get("gamma", 10)),
    horizon=int(args.get("horizon", 10)),
)
env = GymBenchmarkEnv("half_cheetah")
A = 6
cost = G.reward_cost("half_cheetah")


def normal(r):
    return disabled_joint(A, None)


t0 = time.process_time()
eps, mb, h = G.dataset(env, cfg, normal, seed, 0)
print(
    "data+fit cpu",
    round(time.process_time() - t0),
    "best_val",
    h if not h else h.get("best_val"),
    "n",
    sum(len(e) for e in eps),
    flush=True,
)


def run(planner, model, name):
    t = time.process_time()
    if planner is None:
        act = (
            (lambda t, s: np.zeros(A))
            if name == "zero"
            else (lambda t, s, g=np.random.default_rng(0): g.uniform(-1, 1, A))
        )
        _, r = G.rollout(env, steps, 900_000 + seed, {0: normal(None)}, act)
    else:
        r, _ = G.closed_loop(env, MbAdapter(model), planner, cost, steps, 900_000 + seed, {0: normal(None)})
    print(
        f"{name}: return {r.sum():.1f} mean v/step {r.mean():.3f} cpu {time.process_time() - t:.0f}s",
        flush=True,
    )
    return r.sum()


run(None, None, "zero")
run(None, None, "random")
rounds = int(args.get("rounds", 1))


def pl():
    return PDDM(
        -1.0,
        1.0,
        horizon=cfg.horizon,
        samples=cfg.samples,
        gamma=cfg.gamma,
        beta=float(args.get("beta", 0.6)),
        action_dim=A,
        seed=7,
    )


for k in range(rounds + 1):
    run(pl(), mb, f"round{k} pddm N{cfg.samples} H{cfg.horizon} g{cfg.gamma}")
    if "rs" in args:
        run(
            RandomShooting(-1.0, 1.0, horizon=cfg.horizon, samples=cfg.samples, action_dim=A, seed=7),
            mb,
            f"round{k} rs",
        )
    if k == rounds:
        break
    rng = np.random.default_rng([seed, 5, k])
    eps += G.collect(
        env, cfg, [normal(None)] * n_onpol, rng, 50_000 + 100 * k, model=mb, planner_seed=k * 100
    )
    mb, h = G.fit_mb("half_cheetah", cfg, eps, seed)
    print("refit", len(eps), h.get("best_val"), flush=True)
