"""GrBAL: gradient-based adaptive learner (Nagabandi, Clavera et al. 2019; thesis ch. 5).

Meta-training learns θ* and a step size ψ such that ONE gradient step on the past M
transitions of a condition predicts the next K transitions of that same condition well:

    θ'(τ) = θ − ψ ⊙ ∇θ L(θ; τ_past M)                 inner step (ψ elementwise: one step size
                                                       per parameter entry, Meta-SGD style)
    min_{θ, ψ}  E_τ [ L(θ'(τ); τ_next K) ]             outer objective

``L`` is the model's loss (mean squared normalized delta: the Gaussian NLL with fixed
variance, so ``−ψ∇L`` is the thesis' ``+ψ∇ log p̂``). Everything is ``torch.func``: the
inner step is ``grad`` of ``functional_call`` through the model, batched over the tasks of
a meta-batch with ``vmap``; the outer gradient is second order (it differentiates through
the inner gradient).

At run time :class:`GrbalAdapter` re-adapts from θ* at every step on the last M
transitions (never from the previous step's θ': the meta-training made one step from θ*
good, and a run of steps drifts).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.func import grad, vmap

from hilstack.learning.adaptation.base import Adapter
from hilstack.learning.adaptation.model import AdaptiveMLP, Params
from hilstack.learning.datasets import Episode
from hilstack.learning.early_stopping import EarlyStopping, due
from hilstack.learning.progress import progress as progress_output


@dataclass
class Segments:
    """Windows of M + K consecutive transitions, each from one episode (one condition).

    ``states [N, M+K+1, S]``, ``actions [N, M+K, A]`` (float32 torch)."""

    states: torch.Tensor
    actions: torch.Tensor
    M: int
    K: int

    def __len__(self) -> int:
        return int(self.states.shape[0])

    def past(self, idx) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        s, a, M = self.states[idx], self.actions[idx], self.M
        return s[:, :M], a[:, :M], s[:, 1:M + 1]

    def future(self, idx) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        s, a, M = self.states[idx], self.actions[idx], self.M
        return s[:, M:-1], a[:, M:], s[:, M + 1:]


def segments(episodes: Sequence[Episode], M: int, K: int, stride: int = 1) -> Segments:
    """Every window of ``M + K`` transitions (start every ``stride`` steps) inside one episode."""
    L = M + K
    st, ac = [], []
    for ep in episodes:
        for t in range(0, len(ep) - L + 1, stride):
            st.append(ep.states[t:t + L + 1])
            ac.append(ep.actions[t:t + L])
    if not st:
        raise ValueError(f"no episode has the {L} transitions a segment of M={M} + K={K} needs")
    return Segments(torch.as_tensor(np.stack(st)), torch.as_tensor(np.stack(ac)), M, K)


def clip_factor(g: Params, clip: float | None) -> torch.Tensor | float:
    """``min(1, clip / ‖g‖)`` with ‖g‖ the global L2 norm over every tensor of ``g`` (1 when
    ``clip`` is None): the factor that caps the inner gradient's norm at ``clip``."""
    if clip is None:
        return 1.0
    norm = torch.sqrt(sum((v * v).sum() for v in g.values()))
    return torch.clamp(clip / (norm + 1e-12), max=1.0)


def adapt(model: AdaptiveMLP, params: Params, psi: Params, s, a, n,
          names: Sequence[str] | None = None, clip: float | None = None) -> Params:
    """One inner step ``θ − ψ ⊙ ∇θ L(θ; s, a, n)`` (differentiable in θ and ψ).

    ``names``: adapt only these parameters (None: all). The gradient is taken with respect
    to that subset only (``torch.func.grad`` of a function of the subset), so adapting the
    last layer backpropagates through the last layer only; the others stay θ.
    ``clip``: cap the norm of the inner gradient (over the adapted parameters) at this value
    (None: no cap). A window whose loss is far above what meta-training saw has a gradient
    many times larger than ψ was learned for, and the uncapped step overshoots
    (docs/adaptation.md, "Why one GrBAL step ...")."""
    if names is None:
        g = grad(model.loss)(params, s, a, n)
        f = clip_factor(g, clip)
        return {k: params[k] - psi[k] * g[k] * f for k in params}
    sub = {k: params[k] for k in names}
    rest = {k: v for k, v in params.items() if k not in sub}
    g = grad(lambda p: model.loss({**rest, **p}, s, a, n))(sub)
    f = clip_factor(g, clip)
    return {**rest, **{k: sub[k] - psi[k] * g[k] * f for k in sub}}


def gradient_norms(model: AdaptiveMLP, params: Params, seg: Segments, names: Sequence[str] | None = None,
                   max_tasks: int = 512) -> np.ndarray:
    """The inner gradient's norm (over ``names``; None: all) on the past M of each of (at
    most ``max_tasks``, evenly spaced over all) segments: what :func:`adapt`'s ``clip`` is chosen from."""
    idx = torch.unique(torch.linspace(0, len(seg) - 1, min(len(seg), max_tasks)).round().long())
    keys = list(params) if names is None else list(names)
    rest = {k: v for k, v in params.items() if k not in keys}

    def one(s, a, n):
        g = grad(lambda p: model.loss({**rest, **p}, s, a, n))({k: params[k] for k in keys})
        return torch.sqrt(sum((v * v).sum() for v in g.values()))

    return vmap(one)(*seg.past(idx)).detach().numpy()


def task_losses(model: AdaptiveMLP, params: Params, psi: Params, seg: Segments, idx,
                names: Sequence[str] | None = None, clip: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per task of ``idx``: (loss on the next K after adapting ``names`` on the past M, loss before adapting)."""
    past, fut = seg.past(idx), seg.future(idx)

    def one(sp, ap, np_, sf, af, nf):
        adapted = adapt(model, params, psi, sp, ap, np_, names, clip)
        return model.loss(adapted, sf, af, nf), model.loss(params, sf, af, nf)

    return vmap(one)(*past, *fut)


def meta_train(model: AdaptiveMLP, seg: Segments, *, steps: int = 500, meta_batch: int = 16, lr: float = 1e-3,
               psi_init: float = 0.01, psi_lr: float | None = None, seed: int = 0, val: Segments | None = None,
               progress: bool = False, adapt_params: Sequence[str] | None = None, eval_every: int | None = None,
               patience: int | None = None, clip: float | None = None) -> tuple[Params, list[dict[str, float]]]:
    """Meta-train θ (in place in ``model``) and ψ; returns (ψ, history).

    ``model`` should carry its normalization already (``set_normalization``); θ starts from
    its current weights (a supervised warm start saves meta-steps on 2 CPU cores).
    History: per 10 % of the steps, the outer loss (``after``) and the loss of θ without
    adaptation on the same K transitions (``before``), on ``val`` when given.
    ``adapt_params``: the parameters the inner step adapts (None: all); ψ of the others is
    returned as 0. ``psi_lr``: Adam's step for ψ (default ``lr``). ``clip``: the inner
    gradient's norm cap (:func:`adapt`), the same in meta-training as at run time.
    ``eval_every``: steps between history entries (default 10 % of ``steps``). With ``val``
    and ``patience``: early stopping on the held-out outer loss (``after`` on ``val``): stop
    after ``patience`` evaluations without a new best and return the best evaluation's θ
    (written back into ``model``) and ψ.
    """
    params = {k: v for k, v in model.net.named_parameters()}
    names = list(params) if adapt_params is None else list(adapt_params)
    unknown = set(names) - set(params)
    if unknown:
        raise ValueError(f"adapt_params names unknown parameters {sorted(unknown)}; the model has {sorted(params)}")
    psi = {k: torch.full_like(params[k], psi_init, requires_grad=True) for k in names}
    opt = torch.optim.Adam([{"params": list(params.values()), "lr": lr},
                            {"params": list(psi.values()), "lr": psi_lr if psi_lr is not None else lr}])
    sub = None if adapt_params is None else names
    gen = torch.Generator().manual_seed(seed)
    hist: list[dict[str, float]] = []
    every = max(1, eval_every or steps // 10)
    # early stopping watches θ and ψ; only with both a held-out set and a patience
    es = EarlyStopping(params, psi, patience=patience) if val is not None and patience is not None else None
    it_range = progress_output(range(steps), total=steps, desc="GrBAL meta-training") if progress else range(steps)
    for it in it_range:
        idx = torch.randint(len(seg), (min(meta_batch, len(seg)),), generator=gen)
        after, _ = task_losses(model, params, psi, seg, idx, sub, clip)
        loss = after.mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if due(it, steps, every):
            ev = evaluate(model, {k: v.detach() for k, v in params.items()}, {k: v.detach() for k, v in psi.items()},
                          val or seg, names=sub, clip=clip)
            hist.append({"step": it + 1, **ev})
            if es is not None and es.update(ev["after"]):
                break
    if es is not None and es.restore():
        hist.append({"best_step": hist[es.best_index - 1]["step"], **hist[es.best_index - 1]})
    return {k: (psi[k].detach().clone() if k in psi else torch.zeros_like(v.detach())) for k, v in params.items()}, hist


def evaluate(model: AdaptiveMLP, params: Params, psi: Params, seg: Segments, max_tasks: int = 256,
             names: Sequence[str] | None = None, clip: float | None = None) -> dict[str, float]:
    """Mean loss on the next K transitions before and after one adaptation step of ``names``
    (None: all parameters) on a fixed subset of the segments."""
    idx = torch.arange(min(len(seg), max_tasks))
    after, before = task_losses(model, params, psi, seg, idx, names, clip)
    return {"before": float(before.mean()), "after": float(after.mean())}


class GrbalAdapter(Adapter):
    """θ' = θ* − ψ ⊙ ∇θ L(θ*; last M) at every update, from θ*.

    Args:
        psi: the meta-learned step sizes (same keys and shapes as the parameters).
        adapt_params: which parameters to adapt and publish (None: all). Publishing only
            the last layer shrinks an update from ~2 MB (3 x 512) to ~50 KB; the node picks
            by measurement.
        clip: the inner gradient's norm cap the checkpoint was meta-trained with (None: none).
    """

    name = "grbal"

    def __init__(self, model: AdaptiveMLP, psi: Params, window: int = 16, adapt_params: Sequence[str] | None = None,
                 clip: float | None = None):
        super().__init__(model, window)
        if clip is not None and not clip > 0:
            raise ValueError(f"clip must be a positive gradient norm or None, got {clip!r}")
        self.clip = None if clip is None else float(clip)
        missing = set(self.theta_star) - set(psi)
        if missing:
            raise ValueError(f"psi lacks step sizes for {sorted(missing)}")
        self.psi = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in psi.items()}
        self.adapt_params = list(adapt_params) if adapt_params is not None else list(self.theta_star)
        unknown = set(self.adapt_params) - set(self.theta_star)
        if unknown:
            raise ValueError(f"adapt_params names unknown parameters {sorted(unknown)}")

    def _update(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        if not self._buf:
            return {}, {}
        adapted = adapt(self.model, self.theta_star, self.psi, *self.window_tensors(), names=self.adapt_params,
                        clip=self.clip)
        return {k: adapted[k] for k in self.adapt_params}, {"step_size_mean": float(
            torch.cat([self.psi[k].reshape(-1) for k in self.adapt_params]).mean())}

    def checkpoint(self) -> dict[str, Any]:
        return {**super().checkpoint(), "psi": {k: v.clone() for k, v in self.psi.items()},
                "adapt_params": self.adapt_params, "clip": self.clip}

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any]) -> GrbalAdapter:
        if "psi" not in ck:
            raise ValueError("checkpoint has no meta-learned step size psi: it is not a GrBAL checkpoint")
        return cls(AdaptiveMLP.from_checkpoint(ck["model"]), ck["psi"], window=ck["window"],
                   adapt_params=ck.get("adapt_params"), clip=ck.get("clip"))
