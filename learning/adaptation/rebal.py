"""ReBAL: recurrence-based adaptive learner (Nagabandi, Clavera et al. 2019; thesis ch. 5).

The adaptation rule is learned as a recurrent network: a GRU reads the past M transitions
(each as the model's normalized input and normalized target delta) and its final hidden
state ``h`` is an extra input of the dynamics MLP. Meta-training (:func:`meta_train`) fits
the GRU and the MLP end to end so that ``h`` from the past M transitions predicts the next
K of the same condition. At run time the "update" is the GRU run over the last M
transitions from a zero state (as in training), and :class:`ModelUpdate` carries only
``{"h": h}``: a context of ``context_dim`` floats, the smallest message of all methods.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from hilstack.learning.adaptation.base import Adapter, DynamicsFn, ModelUpdate
from hilstack.learning.adaptation.grbal import Segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.early_stopping import EarlyStopping, due


class ContextEncoder(nn.Module):
    """GRU over transitions ``[B, T, S + A + S]`` (normalized input and target) → ``h [B, C]``."""

    def __init__(self, model: AdaptiveMLP, context_dim: int):
        super().__init__()
        S, A = model.state_dim, model.action_dim
        self.gru = nn.GRU(S + A + S, context_dim, batch_first=True)

    def forward(self, model: AdaptiveMLP, s: torch.Tensor, a: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        x = torch.cat([model.inputs(s, a), model.targets(s, n)], dim=-1)
        _, h = self.gru(x)
        return h[-1]


def meta_train(model: AdaptiveMLP, encoder: ContextEncoder, seg: Segments, *, steps: int = 500,
               batch: int = 32, lr: float = 1e-3, seed: int = 0, val: Segments | None = None,
               eval_every: int | None = None, patience: int | None = None) -> list[dict[str, float]]:
    """Fit the GRU and the MLP (in place): predict the next K from the context of the past M.

    History: every ``eval_every`` steps (default 10 % of ``steps``) the batch loss and, with
    ``val``, the held-out loss (``val_loss``). With ``val`` and ``patience``: stop after
    ``patience`` evaluations without a new best held-out loss and keep the best weights."""
    opt = torch.optim.Adam([*model.net.parameters(), *encoder.parameters()], lr=lr)
    params = dict(model.net.named_parameters())
    gen = torch.Generator().manual_seed(seed)
    hist = []
    every = max(1, eval_every or steps // 10)
    es = EarlyStopping(model, encoder, patience=patience) if val is not None and patience is not None else None
    for it in range(steps):
        idx = torch.randint(len(seg), (min(batch, len(seg)),), generator=gen)
        loss = _loss(model, encoder, params, seg, idx)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if due(it, steps, every):
            h = {"step": it + 1, "loss": float(loss.detach())}
            if val is not None:
                h["val_loss"] = evaluate(model, encoder, val)["after"]
            hist.append(h)
            if es is not None and es.update(h["val_loss"]):
                break
    if es is not None and es.restore():
        hist.append({"best_step": hist[es.best_index - 1]["step"], **hist[es.best_index - 1]})
    return hist


def _loss(model, encoder, params, seg: Segments, idx) -> torch.Tensor:
    h = encoder(model, *seg.past(idx))                       # [B, C]
    sf, af, nf = seg.future(idx)                              # [B, K, ...]
    return model.loss(params, sf, af, nf, context=h[:, None, :])


def evaluate(model: AdaptiveMLP, encoder: ContextEncoder, seg: Segments, max_tasks: int = 256) -> dict[str, float]:
    """Loss on the next K with the context from the past M (``after``) and a zero context (``before``)."""
    idx = torch.arange(min(len(seg), max_tasks))
    with torch.no_grad():
        after = _loss(model, encoder, model.params(), seg, idx)
        sf, af, nf = seg.future(idx)
        zero = torch.zeros(1, 1, encoder.gru.hidden_size)
        before = model.loss(model.params(), sf, af, nf, context=zero)
    return {"before": float(before), "after": float(after)}


class RebalAdapter(Adapter):
    """The GRU's hidden state over the last M transitions is the adaptation."""

    name = "rebal"

    def __init__(self, model: AdaptiveMLP, encoder: ContextEncoder, window: int = 16):
        super().__init__(model, window)
        if not model.config["context_dim"]:
            raise ValueError("ReBAL needs a model with context_dim > 0")
        self.encoder = encoder
        self.context_dim = encoder.gru.hidden_size

    def _update(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        if not self._buf:
            return {"h": torch.zeros(self.context_dim)}, {}
        s, a, n = self.window_tensors()
        with torch.no_grad():
            h = self.encoder(self.model, s[None], a[None], n[None])[0]
        return {"h": h}, {}

    def dynamics(self, update: ModelUpdate | None) -> DynamicsFn:
        if update is not None and update.method != self.name:
            raise ValueError(f"{self.name} adapter got an update of method {update.method!r}")
        h = torch.zeros(self.context_dim) if update is None or "h" not in update.tensors else \
            torch.as_tensor(update.tensors["h"], dtype=torch.float32)
        if h.shape != (self.context_dim,):
            raise ValueError(f"rebal update h has shape {tuple(h.shape)}, expected ({self.context_dim},)")
        params, model = self.theta_star, self.model

        def dyn(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
            with torch.no_grad():
                return model.step(params, state, action, context=h)
        return dyn

    def checkpoint(self) -> dict[str, Any]:
        return {**super().checkpoint(), "encoder": {k: v.clone() for k, v in self.encoder.state_dict().items()}}

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any]) -> RebalAdapter:
        if "encoder" not in ck:
            raise ValueError("checkpoint has no GRU encoder: it is not a ReBAL checkpoint")
        model = AdaptiveMLP.from_checkpoint(ck["model"])
        enc = ContextEncoder(model, model.config["context_dim"])
        enc.load_state_dict(ck["encoder"])
        return cls(model, enc, window=ck["window"])
