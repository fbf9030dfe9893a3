"""Online adaptation: the interface between the learners and the adaptation node.

An :class:`Adapter` turns the robot's recent transitions into an adapted dynamics model for
the MPC. The adaptation node (``hil/<rig>/model/update``) drives it; the demo
(``tools/demo_adaptation.py``) drives it in process. The call sequence, once per control step::

    adapter = load_adapter("meta.pt")            # the method named in the checkpoint
    adapter.reset()                              # θ* / the prior; empty window
    ...
    adapter.observe(s_prev, a_prev, s_now)       # numpy, the model's units (below)
    update = adapter.update(state_stamp_ns)      # adapt from the last M transitions now
    dynamics = adapter.dynamics(update)          # what control/planners.py's planners take
    action = planner(dynamics, cost, s_now)

``update`` runs where the data is (the adaptation node); ``dynamics(update)`` runs where the
planner is (the MPC node), on an adapter built from the same checkpoint. So an
:class:`ModelUpdate` carries only what the MPC side cannot know: the adapted parameters
(or a subset of them) or a context (ReBAL's GRU state), never the checkpoint itself.

Units: states in the robot spec's units, world frame (``state_names`` in the checkpoint);
actions normalized to [-1, 1] of the spec's limits (what the MBRL loop and the planners use).

Methods (``method`` in the checkpoint and in every update):

* ``mb``: no adaptation (θ* always); ``tensors`` is empty.
* ``mb_de``: one gradient step per control step on the last M transitions, continuing
  from the previous step's parameters ("dynamic evaluation"); ``tensors`` = all parameters.
* ``grbal``: one meta-learned gradient step θ' = θ* − ψ ⊙ ∇θ L(θ*, last M) from θ* at every
  step (``learning/adaptation/grbal.py``); ``tensors`` = the adapted parameters.
* ``rebal``: a GRU over the transitions whose hidden state is the adaptation
  (``learning/adaptation/rebal.py``); ``tensors`` = ``{"h": hidden state}``.
* ``mole``: a mixture of models adapted from a meta-learned prior with a CRP prior and
  online EM (``learning/adaptation/mole.py``); ``tensors`` = the parameters of the most
  probable task's model, ``info["posterior"]`` the task posterior.

Checkpoints are ``torch.save`` dicts with ``format``/``version``/``method``; :func:`load_adapter`
builds the adapter a checkpoint names from :data:`ADAPTERS` (import strings, resolved on use).
"""

from __future__ import annotations

import abc
import collections
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hilstack.control.planners import DynamicsFn
from hilstack.learning.adaptation.model import AdaptiveMLP, Params
from hilstack.learning.datasets import Transitions

__all__ = ["ModelUpdate", "Adapter", "DynamicsFn", "ADAPTERS", "load_adapter", "save_checkpoint",
           "CHECKPOINT_FORMAT"]

CHECKPOINT_FORMAT = "hilstack.adaptation"
CHECKPOINT_VERSION = 1

#: method name → "module:Class" (resolved when a checkpoint asks for it)
ADAPTERS: dict[str, str] = {
    "mb": "hilstack.learning.adaptation.baselines:MbAdapter",
    "mb_de": "hilstack.learning.adaptation.baselines:MbDeAdapter",
    "grbal": "hilstack.learning.adaptation.grbal:GrbalAdapter",
    "rebal": "hilstack.learning.adaptation.rebal:RebalAdapter",
    "mole": "hilstack.learning.adaptation.mole:MoleAdapter",
}


@dataclass
class ModelUpdate:
    """What the adaptation node publishes on ``hil/<rig>/model/update``.

    Attributes:
        method: ``"mb" | "mb_de" | "grbal" | "rebal" | "mole"``.
        seq: increases by one per update of an adapter (reset keeps counting).
        state_stamp_ns: stamp of the newest state the update used (the MPC measures the
            state-to-model delay from it), ns on the rig's clock; 0 when unknown.
        tensors: adapted parameters by name (float32 numpy; a subset of the model's
            parameters is allowed, the rest stay θ*), or a context (``{"h": ...}``).
        info: small JSON-able facts: ``window`` (transitions used), ``step_size``,
            MOLe's ``posterior`` (list per task), ``task``, ``tasks_created``...
    """

    method: str
    seq: int
    state_stamp_ns: int = 0
    tensors: dict[str, np.ndarray] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def nbytes(self) -> int:
        """Size of the tensors in bytes (what choosing a subset saves)."""
        return int(sum(np.asarray(v).nbytes for v in self.tensors.values()))


class Adapter(abc.ABC):
    """Base of every online-adaptation method.

    Keeps the last ``window`` (M) transitions; subclasses implement :meth:`_update` and,
    when the update is not a parameter dict, :meth:`dynamics`.

    Args:
        model: the dynamics model (θ* and normalization).
        window: M, transitions the update uses.
    """

    name: str = "adapter"

    def __init__(self, model: AdaptiveMLP, window: int = 16):
        if window < 1:
            raise ValueError(f"window (M) must be >= 1, got {window}")
        self.model = model
        self.window = int(window)
        self.theta_star: Params = model.params()
        self._buf: collections.deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = collections.deque(maxlen=self.window)
        self._seq = 0

    # -- the interface -------------------------------------------------------------------------
    def reset(self) -> None:
        """Back to θ* / the prior; clears the window."""
        self._buf.clear()

    def observe(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray) -> None:
        """One transition (numpy; state in spec units, action normalized). Non-finite or
        wrongly shaped input is refused with a one-line error (the window stays clean)."""
        self._buf.append(self._checked(state, action, next_state))

    def observe_transitions(self, tr: Transitions) -> None:
        """Every transition of the record (:class:`hilstack.learning.datasets.Transitions`, the
        one transition record; what the adaptation node builds), in order. Its channel names,
        when it carries them, must be the model's; a bad row (non-finite, wrong shape) refuses
        the whole record with a one-line error and the window stays as it was."""
        if tr.state_names is not None and list(tr.state_names) != list(self.model.state_names):
            raise ValueError(f"{self.name}.observe_transitions: states {list(tr.state_names)}, "
                             f"the model's are {list(self.model.state_names)}")
        rows = [self._checked(s, a, n) for s, a, n in zip(*tr.arrays(), strict=True)]
        self._buf.extend(rows)

    def _checked(self, state, action, next_state) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = np.asarray(state, dtype=np.float32).reshape(-1)
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        n = np.asarray(next_state, dtype=np.float32).reshape(-1)
        S, A = self.model.state_dim, self.model.action_dim
        if s.shape[0] != S or n.shape[0] != S or a.shape[0] != A:
            raise ValueError(f"{self.name}.observe: expected state [{S}], action [{A}], next_state [{S}]; "
                             f"got {s.shape[0]}, {a.shape[0]}, {n.shape[0]}")
        for what, v in (("state", s), ("action", a), ("next_state", n)):
            if not np.all(np.isfinite(v)):
                raise ValueError(f"{self.name}.observe: non-finite {what} {v.tolist()}")
        return s, a, n

    def update(self, state_stamp_ns: int = 0) -> ModelUpdate:
        """Adapt from the last M transitions now and say what changed."""
        tensors, info = self._update()
        info = {"window": len(self._buf), **info}
        self._seq += 1
        return ModelUpdate(self.name, self._seq, int(state_stamp_ns),
                           {k: v.detach().cpu().numpy().astype(np.float32) for k, v in tensors.items()}, info)

    def dynamics(self, update: ModelUpdate | None) -> DynamicsFn:
        """Batched ``(state [B, S], action [B, A]) -> next_state [B, S]`` (torch, no grad)
        under the update's parameters (θ* for the ones it does not carry)."""
        params = self.params_of(update)
        model = self.model

        def dyn(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
            with torch.no_grad():
                return model.step(params, state, action)
        return dyn

    # -- helpers ---------------------------------------------------------------------------------
    def params_of(self, update: ModelUpdate | None) -> Params:
        """θ* overlaid with the update's parameter tensors."""
        params = dict(self.theta_star)
        if update is None:
            return params
        if update.method != self.name:
            raise ValueError(f"{self.name} adapter got an update of method {update.method!r}")
        for k, v in update.tensors.items():
            if k not in params:
                raise KeyError(f"update carries unknown parameter {k!r}; the model has {sorted(params)}")
            t = torch.as_tensor(np.asarray(v), dtype=params[k].dtype)
            if t.shape != params[k].shape:
                raise ValueError(f"update parameter {k!r} has shape {tuple(t.shape)}, model {tuple(params[k].shape)}")
            params[k] = t
        return params

    def window_tensors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The window as torch ``[m, S]``, ``[m, A]``, ``[m, S]`` (m ≤ M)."""
        s, a, n = zip(*self._buf, strict=True)
        return (torch.as_tensor(np.stack(s)), torch.as_tensor(np.stack(a)), torch.as_tensor(np.stack(n)))

    @abc.abstractmethod
    def _update(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """(tensors to publish, info)."""

    # -- checkpoints -----------------------------------------------------------------------------
    def checkpoint(self) -> dict[str, Any]:
        """Everything :meth:`from_checkpoint` needs (the base: model and window)."""
        return {"model": self.model.to_checkpoint(), "window": self.window}

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any]) -> Adapter:
        return cls(AdaptiveMLP.from_checkpoint(ck["model"]), window=ck["window"])

    def save(self, path: str | Path) -> None:
        save_checkpoint(path, self.name, self.checkpoint())


def save_checkpoint(path: str | Path, method: str, body: dict[str, Any]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "method": method, **body}, path)


def _resolve(method: str) -> Callable[..., Adapter]:
    if method not in ADAPTERS:
        raise ValueError(f"unknown adaptation method {method!r}; known: {sorted(ADAPTERS)}")
    mod, _, cls = ADAPTERS[method].partition(":")
    return getattr(importlib.import_module(mod), cls)


def load_adapter(path: str | Path, method: str | None = None) -> Adapter:
    """The adapter a checkpoint names (``method`` overrides it: e.g. run ``mb`` or ``mb_de``
    on a meta-trained θ*). One-line errors for a missing or foreign file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"adaptation checkpoint {path} does not exist")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - any unpickling failure is a bad file
        raise ValueError(f"{path}: not a readable torch checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not an adaptation checkpoint (format {ck.get('format') if isinstance(ck, dict) else None!r}, "
                         f"expected {CHECKPOINT_FORMAT!r})")
    if ck.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {ck.get('version')}, this code reads {CHECKPOINT_VERSION}")
    return _resolve(method or ck["method"]).from_checkpoint(ck)
