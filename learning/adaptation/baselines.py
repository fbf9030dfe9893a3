"""The baselines of the thesis' adaptation experiments (ch. 5): MB and MB+DE.

* :class:`MbAdapter` (``mb``): the model-based controller without adaptation; every update
  is θ* (an empty ``tensors``).
* :class:`MbDeAdapter` (``mb_de``): "dynamic evaluation": one plain gradient step per control
  step on the last M transitions, each step continuing from the previous one's parameters
  (the model keeps drifting with the data; :meth:`reset` returns to θ*). The gradient is
  ``torch.func.grad`` of the model's loss through ``functional_call``.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch.func import grad

from hilstack.learning.adaptation.base import Adapter
from hilstack.learning.adaptation.model import AdaptiveMLP, Params


class MbAdapter(Adapter):
    """No adaptation: the MPC keeps θ*."""

    name = "mb"

    def _update(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        return {}, {}


class MbDeAdapter(Adapter):
    """One SGD step of size ``lr`` per update on the last M transitions, from the current parameters.

    Args:
        lr: step size of the gradient step on the normalized-delta MSE (thesis half-cheetah
            inner lr: 0.01); 0 is MB (no adaptation), the lower end of the demo's step-size grid.
    """

    name = "mb_de"

    def __init__(self, model: AdaptiveMLP, window: int = 16, lr: float = 0.01):
        super().__init__(model, window)
        if not (math.isfinite(lr) and lr >= 0):
            raise ValueError(f"mb_de lr must be finite and >= 0, got {lr}")
        self.lr = float(lr)
        self.current: Params = dict(self.theta_star)
        self._grad = grad(model.loss)

    def reset(self) -> None:
        super().reset()
        self.current = dict(self.theta_star)

    def _update(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        if self._buf:
            g = self._grad(self.current, *self.window_tensors())
            self.current = {k: (v - self.lr * g[k]).detach() for k, v in self.current.items()}
        return dict(self.current), {"step_size": self.lr}

    def checkpoint(self) -> dict[str, Any]:
        return {**super().checkpoint(), "de_lr": self.lr}

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any]) -> MbDeAdapter:
        return cls(AdaptiveMLP.from_checkpoint(ck["model"]), window=ck["window"], lr=ck.get("de_lr", 0.01))
