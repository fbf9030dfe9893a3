"""Supervised training of the plain model (θ* of MB and MB+DE) and data helpers.

Transitions are :class:`hilstack.learning.datasets.Transitions` (``states [N, S]``,
``actions [N, A]``, ``next_states [N, S]``; spec units, actions normalized). Episodes are
:class:`hilstack.learning.datasets.Episode`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.datasets import Episode, Transitions
from hilstack.learning.early_stopping import EarlyStopping


def fit_plain(model: AdaptiveMLP, episodes: Sequence[Episode], epochs: int = 30, batch_size: int = 256,
              lr: float = 1e-3, seed: int = 0, normalize: bool = True, val: Sequence[Episode] | None = None,
              patience: int = 5, history: dict | None = None) -> list[float]:
    """Adam on the model's loss over all transitions (the MB model); returns the loss per epoch.

    ``val``: held-out rollouts. Then ``epochs`` is the maximum: after each epoch the loss on
    ``val`` is measured, training stops after ``patience`` epochs without a new best, and
    the model keeps the best epoch's weights (early stopping). ``history`` (a dict) receives
    ``val`` (loss per epoch), ``best_epoch`` and ``best_val``."""
    s, a, n = (torch.as_tensor(x) for x in Transitions.from_episodes(episodes).arrays())
    if normalize:
        model.set_normalization(s.numpy(), a.numpy(), n.numpy())
    opt = torch.optim.Adam(model.net.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    params = dict(model.net.named_parameters())
    vt = None if not val else tuple(torch.as_tensor(x) for x in Transitions.from_episodes(val).arrays())
    es, vhist = EarlyStopping(params, patience=patience), []
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
        if vt is not None:
            with torch.no_grad():
                v = float(model.loss(params, *vt))
            vhist.append(v)
            if es.update(v):
                break
    es.restore()
    if history is not None:
        history.update({"val": vhist, "best_epoch": es.best_index, "best_val": es.best if vt is not None else None,
                        "epochs_run": len(hist)})
    return hist
