"""The dynamics model every adapter shares: a plain MLP whose parameters are a dict.

GrBAL, MB+DE and MOLe adapt the model's parameters at run time with ``torch.func``
(``functional_call``, ``grad``, ``vmap``), so the network is a plain ``nn.Sequential`` of
``nn.Linear`` layers and every forward pass takes the parameters as an argument
(:meth:`AdaptiveMLP.step`). :class:`hilstack.learning.dynamics.EnsembleDynamics` keeps its members
in batched ``[E, in, out]`` tensors behind a fused inference path; that is the right
layout for planning with ensembles, the wrong one for per-step functional adaptation.

Units and frames (the same as the MBRL loop's body-frame model, ``learning/frames.py``):

* state ``s``: the robot's state in its spec units, world frame (``state_names``);
* action ``a``: normalized to [-1, 1] of the spec's limits (what the planners sample);
* the network sees ``[to_body(s, s), a]`` normalized by ``input_mean``/``input_std`` and
  predicts the body-frame change ``to_body(s', s) - to_body(s, s)`` normalized by
  ``delta_mean``/``delta_std``; predictions are mapped back to the world frame.

The loss is the mean squared normalized delta error: the negative log-likelihood of a
Gaussian with fixed unit variance (the thesis' "fixed variance"), up to a constant.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.func import functional_call

from hilstack.learning.frames import PlanarFrame

Params = dict[str, torch.Tensor]


def _safe_std(x: torch.Tensor) -> torch.Tensor:
    """Per-channel std with constant channels (< 1e-6) set to 1, the rule of
    ``hilstack.learning.datasets.NormStats``. Constant inputs exist by construction (the body-frame
    x, y are 0 and cos yaw is 1 for the state itself); a tiny std there would blow the
    slightest deviation of a *predicted* state (a cos/sin pair off the unit circle) up by
    1e6 and make multi-step rollouts diverge."""
    std = x.std(0)
    return torch.where(std < 1e-6, torch.ones_like(std), std)


class AdaptiveMLP(nn.Module):
    """MLP dynamics over (state, normalized action), predicting the body-frame delta.

    Args:
        state_names: names of the S state channels (need x, y, vx, vy, cos_yaw, sin_yaw
            for the body frame; ``body_frame=False`` learns in the world frame).
        action_dim: A.
        hidden: hidden widths (thesis GrBAL: 3 x 512; MOLe: 3 x 500).
        context_dim: width of an extra input the caller supplies (ReBAL's GRU state); 0: none.
        seed: weight init.
    """

    def __init__(self, state_names: Sequence[str], action_dim: int, hidden: Sequence[int] = (512, 512, 512),
                 body_frame: bool = True, seed: int = 0, context_dim: int = 0):
        super().__init__()
        self.state_names = list(state_names)
        self.config = dict(state_names=self.state_names, action_dim=int(action_dim), hidden=[int(h) for h in hidden],
                           body_frame=bool(body_frame), seed=int(seed), context_dim=int(context_dim))
        S, A = len(self.state_names), int(action_dim)
        self.frame = PlanarFrame(self.state_names) if body_frame else None
        torch.manual_seed(seed)
        sizes = [S + A + int(context_dim), *self.config["hidden"], S]
        layers: list[nn.Module] = []
        for i, (fi, fo) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            layers.append(nn.Linear(fi, fo))
            if i < len(sizes) - 2:
                layers.append(nn.ReLU())
        self.net = nn.Sequential(*layers)
        self.register_buffer("input_mean", torch.zeros(S + A))
        self.register_buffer("input_std", torch.ones(S + A))
        self.register_buffer("delta_mean", torch.zeros(S))
        self.register_buffer("delta_std", torch.ones(S))

    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def action_dim(self) -> int:
        return self.config["action_dim"]

    # -- parameters as a dict ---------------------------------------------------------------
    def params(self) -> Params:
        """θ as a dict name → tensor (the trained parameters, detached)."""
        return {k: v.detach() for k, v in self.net.named_parameters()}

    # -- frames and normalization ---------------------------------------------------------------
    def _body(self, state: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        return self.frame.to_body(state, ref) if self.frame is not None else state

    def _world(self, body: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        return self.frame.to_world(body, ref) if self.frame is not None else body

    def inputs(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Normalized network input for ``state [..., S]`` and ``action [..., A]``."""
        x = torch.cat([self._body(state, state), action], dim=-1)
        return (x - self.input_mean) / self.input_std

    def targets(self, state: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """Normalized body-frame delta the network is trained to output."""
        d = self._body(next_state, state) - self._body(state, state)
        return (d - self.delta_mean) / self.delta_std

    def set_normalization(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> None:
        """Fit the input/output statistics to transitions (numpy ``[N, S]``, ``[N, A]``, ``[N, S]``)."""
        s = torch.as_tensor(states, dtype=torch.float32)
        a = torch.as_tensor(actions, dtype=torch.float32)
        n = torch.as_tensor(next_states, dtype=torch.float32)
        x = torch.cat([self._body(s, s), a], dim=-1)
        d = self._body(n, s) - self._body(s, s)
        self.input_mean.copy_(x.mean(0))
        self.input_std.copy_(_safe_std(x))
        self.delta_mean.copy_(d.mean(0))
        self.delta_std.copy_(_safe_std(d))

    # -- functional forward and loss ------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def _net_in(self, state, action, context):
        x = self.inputs(state, action)
        if self.config["context_dim"]:
            if context is None:
                raise ValueError("this model needs a context (ReBAL hidden state)")
            x = torch.cat([x, context.expand(*x.shape[:-1], context.shape[-1])], dim=-1)
        return x

    def step(self, params: Params, state: torch.Tensor, action: torch.Tensor,
             context: torch.Tensor | None = None) -> torch.Tensor:
        """Next state (world frame, spec units) under parameters ``params``; any leading batch
        shape (``context``: ``[C]`` or broadcastable to the batch)."""
        y = functional_call(self.net, params, (self._net_in(state, action, context),))
        body_next = self._body(state, state) + y * self.delta_std + self.delta_mean
        return self._world(body_next, state)

    def loss(self, params: Params, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
             context: torch.Tensor | None = None) -> torch.Tensor:
        """Mean squared normalized delta error (Gaussian NLL with fixed unit variance, up to a constant)."""
        y = functional_call(self.net, params, (self._net_in(state, action, context),))
        return ((y - self.targets(state, next_state)) ** 2).mean()

    # -- checkpoint ---------------------------------------------------------------------------
    def to_checkpoint(self) -> dict[str, Any]:
        return {"config": dict(self.config), "state_dict": {k: v.clone() for k, v in self.state_dict().items()}}

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any]) -> AdaptiveMLP:
        c = ck["config"]
        m = cls(c["state_names"], c["action_dim"], c["hidden"], c["body_frame"], c["seed"], c.get("context_dim", 0))
        m.load_state_dict(ck["state_dict"])
        return m
