"""Supervised training of the plain model (θ* of MB and MB+DE) and data helpers.

Transitions are numpy arrays ``states [N, S]``, ``actions [N, A]``, ``next_states [N, S]``
(spec units; actions normalized). Episodes are :class:`learning.datasets.Episode`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from learning.adaptation.model import AdaptiveMLP
from learning.datasets import Episode


def transitions(episodes: Sequence[Episode]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All ``(s, a, s')`` of the episodes, stacked (float32)."""
    s = np.concatenate([e.states[:-1] for e in episodes]).astype(np.float32)
    a = np.concatenate([e.actions for e in episodes]).astype(np.float32)
    n = np.concatenate([e.states[1:] for e in episodes]).astype(np.float32)
    return s, a, n


def fit_plain(model: AdaptiveMLP, episodes: Sequence[Episode], epochs: int = 30, batch_size: int = 256,
              lr: float = 1e-3, seed: int = 0, normalize: bool = True) -> list[float]:
    """Adam on the model's loss over all transitions (the MB model); returns the loss per epoch."""
    s, a, n = (torch.as_tensor(x) for x in transitions(episodes))
    if normalize:
        model.set_normalization(s.numpy(), a.numpy(), n.numpy())
    opt = torch.optim.Adam(model.net.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    params = dict(model.net.named_parameters())
    hist = []
    for _ in range(epochs):
        perm = torch.randperm(s.shape[0], generator=gen)
        tot, cnt = 0.0, 0
        for i in range(0, s.shape[0], batch_size):
            idx = perm[i:i + batch_size]
            loss = model.loss(params, s[idx], a[idx], n[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            tot += float(loss.detach()) * idx.shape[0]
            cnt += idx.shape[0]
        hist.append(tot / max(cnt, 1))
    return hist
