"""Shared fixtures: a GrBAL model meta-trained once per session on the toy robot."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.learning.adaptation.grbal import meta_train, segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.training import fit_plain
from tests.adaptation import toy

M = K = 8


def train_episodes():
    rng = np.random.default_rng(0)
    eps = []
    for i in range(40):  # one condition per episode: speed gain and a turn bias
        eps += toy.episodes(1, 40, seed=i, gain=rng.uniform(0.5, 1.5), turn_bias=rng.uniform(-1, 1))
    return eps


@pytest.fixture(scope="session")
def meta():
    """(meta-trained model, the plain model it started from, ψ, history)."""
    torch.manual_seed(0)
    eps = train_episodes()
    model = AdaptiveMLP(toy.NAMES, 2, hidden=(64, 64), seed=0)
    fit_plain(model, eps, epochs=20, batch_size=128)
    plain = AdaptiveMLP.from_checkpoint(model.to_checkpoint())  # the MB model, before meta-training
    psi, hist = meta_train(model, segments(eps, M, K, stride=4), steps=150, meta_batch=16, lr=1e-3, psi_init=0.01)
    return model, plain, psi, hist
