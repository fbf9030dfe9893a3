"""Learned model + planner: the MBRL pieces fit together on a 1-D point mass."""

import numpy as np
import torch

from hilstack.control.planners import PDDM
from hilstack.learning.datasets import Episode, TransitionDataset
from hilstack.learning.dynamics import EnsembleDynamics

DT = 0.1


def true_step(s, u):
    return np.array([s[0] + DT * s[1], 0.9 * s[1] + DT * u[0]], dtype=np.float32)


def random_episodes(n, T, rng):
    eps = []
    for _ in range(n):
        s = [rng.uniform(-1, 2, 2).astype(np.float32) * [1, 0.5]]
        a = rng.uniform(-1, 1, (T, 1)).astype(np.float32)
        for t in range(T):
            s.append(true_step(s[-1], a[t]))
        eps.append(Episode(np.stack(s), a))
    return eps


def test_pddm_on_a_learned_ensemble_reaches_the_goal():
    rng = np.random.default_rng(0)
    train, val = TransitionDataset(random_episodes(30, 40, rng), state_names=["x", "v"]).split(0.2)
    model = EnsembleDynamics(2, 1, ensemble=2, hidden=(64, 64), seed=0)
    hist = model.fit(train, epochs=40, batch_size=64, progress=False, val=val, horizon=10)
    assert hist[-1]["val_h"] < hist[0]["val_h"]

    def cost(states, actions):
        return ((states[..., 1:, 0] - 1.0) ** 2 + 0.1 * states[..., 1:, 1] ** 2).sum(-1)

    planner = PDDM(-1.0, 1.0, horizon=10, samples=100, gamma=10.0, beta=0.7, sigma=0.5, action_dim=1, seed=0)
    s = np.zeros(2, np.float32)
    for _ in range(80):
        s = true_step(s, planner(model, cost, s))
    assert abs(s[0] - 1.0) < 0.15
    assert planner.last_predicted_states.shape == (2, 11, 2)
    assert torch.is_tensor(planner.last_plan) and planner.last_plan.shape == (10, 1)
