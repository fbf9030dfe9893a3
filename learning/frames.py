"""Body-frame dynamics for planar mobile robots.

A legged or wheeled robot on flat ground moves the same way wherever it is and
whichever way it faces. Learning in the world frame wastes data on re-learning that
for every position and heading. :class:`BodyFrameDynamics` wraps a dynamics model so
the network only ever sees the state in the robot's own frame at time t:

    x, y        → 0                        (position relative to itself)
    vx, vy      → R(ψ)ᵀ (vx, vy)           (body-frame velocity)
    cos ψ, sin ψ → 1, 0                    (heading relative to itself)

and the next state in that same frame (displacement and heading change since t).
Predictions are mapped back to the world frame. Other channels pass through.
Channels are found by name (x, y, vx, vy, cos_yaw, sin_yaw).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from hilstack.learning.datasets import Episode
from hilstack.learning.dynamics import EnsembleDynamics, h_step_error, h_step_windows


class PlanarFrame:
    def __init__(self, state_names: Sequence[str]):
        names = list(state_names)
        try:
            self.ix, self.iy = names.index("x"), names.index("y")
            self.ivx, self.ivy = names.index("vx"), names.index("vy")
            self.ic, self.is_ = names.index("cos_yaw"), names.index("sin_yaw")
        except ValueError as e:
            raise ValueError(f"body-frame dynamics need x, y, vx, vy, cos_yaw, sin_yaw channels: {e}") from None

    def _cs(self, ref):
        c, s = ref[..., self.ic], ref[..., self.is_]
        n = torch.sqrt(c * c + s * s).clamp_min(1e-6) if isinstance(ref, torch.Tensor) else np.maximum(np.hypot(c, s), 1e-6)
        return c / n, s / n

    def to_body(self, state, ref):
        """``state`` expressed in the frame of ``ref`` (same leading shape)."""
        c, s = self._cs(ref)
        out = state.clone() if isinstance(state, torch.Tensor) else state.copy()
        dx = state[..., self.ix] - ref[..., self.ix]
        dy = state[..., self.iy] - ref[..., self.iy]
        out[..., self.ix] = c * dx + s * dy
        out[..., self.iy] = -s * dx + c * dy
        vx, vy = state[..., self.ivx], state[..., self.ivy]
        out[..., self.ivx] = c * vx + s * vy
        out[..., self.ivy] = -s * vx + c * vy
        qc, qs = state[..., self.ic], state[..., self.is_]
        out[..., self.ic] = c * qc + s * qs  # cos(ψ − ψ_ref)
        out[..., self.is_] = c * qs - s * qc  # sin(ψ − ψ_ref)
        return out

    def to_world(self, body, ref):
        """Inverse of :meth:`to_body`."""
        c, s = self._cs(ref)
        out = body.clone() if isinstance(body, torch.Tensor) else body.copy()
        bx, by = body[..., self.ix], body[..., self.iy]
        out[..., self.ix] = ref[..., self.ix] + c * bx - s * by
        out[..., self.iy] = ref[..., self.iy] + s * bx + c * by
        vx, vy = body[..., self.ivx], body[..., self.ivy]
        out[..., self.ivx] = c * vx - s * vy
        out[..., self.ivy] = s * vx + c * vy
        qc, qs = body[..., self.ic], body[..., self.is_]
        out[..., self.ic] = c * qc - s * qs  # cos(ψ_ref + δ)
        out[..., self.is_] = s * qc + c * qs
        return out


class BodyFrameDynamics:
    """``predict(state, action)`` like :class:`EnsembleDynamics`, learned in the body frame."""

    def __init__(self, model: EnsembleDynamics, state_names: Sequence[str], train_horizon: int | None = None):
        self.model = model
        if train_horizon is not None:
            if not 1 <= int(train_horizon) <= 50:
                raise ValueError(f"train_horizon must be in 1..50, got {train_horizon}")
            model.config["train_horizon"] = int(train_horizon)
        self.frame = PlanarFrame(state_names)
        self.state_names = list(state_names)
        if model.state_names is None:
            model.state_names = list(state_names)  # the checkpoint needs them to rebuild the frame
        model.config["body_frame"] = True

    @property
    def history(self) -> list[dict]:
        return self.model.history

    def body_episodes(self, episodes: Sequence[Episode]) -> list[Episode]:
        """Each transition as a one-step episode in the frame of its first state."""
        out = []
        for ep in episodes:
            s = ep.states.astype(np.float64)
            cur = self.frame.to_body(s[:-1], s[:-1])
            nxt = self.frame.to_body(s[1:], s[:-1])
            for t in range(len(ep)):
                out.append(Episode(np.stack([cur[t], nxt[t]]), ep.actions[t : t + 1], name=f"{ep.name}#{t}"))
        return out

    def fit(self, episodes: Sequence[Episode], val: Sequence[Episode] | None = None, **kw) -> list[dict]:
        """Train the wrapped model on one-step body-frame transitions.

        With ``val``, the last history entry gets the real ``horizon``-step open-loop error
        (thesis Eqn 2.2, :func:`hilstack.learning.dynamics.h_step_error`) of this world-frame model on
        the validation episodes, in two frames:

        * ``val_h`` (and ``val_h_raw``): world frame, normalized by the per-channel std of
          the training states;
        * ``val_h_body``: predictions and truth expressed in the body frame of each
          window's start state, normalized by the std of the training states in the frame
          of the state before them;
        * ``val_h_xy_mse_m2``: squared position error [m²] after the ``horizon`` steps.

        ``val_1step`` stays the wrapped model's one-step loss (body frame, normalized).
        """
        horizon = kw.pop("horizon", 4)
        hist = self.model.fit(self.body_episodes(episodes), val=self.body_episodes(val) if val else None,
                              horizon=1, **kw)
        if self.train_horizon > 1 and hist:
            hist[-1]["train_h_loss"] = self.fit_open_loop(episodes, self.train_horizon, kw.get("epochs", 50),
                                                          kw.get("batch_size", 512))
        if val and hist:
            hist[-1].update(self.validation_errors(episodes, val, horizon))
        return hist

    @property
    def train_horizon(self) -> int:
        """H of the open-loop training loss (:meth:`fit_open_loop`); 1: one-step training only."""
        return int(self.model.config.get("train_horizon", 1))

    def fit_open_loop(self, episodes: Sequence[Episode], horizon: int, epochs: int, batch_size: int = 512) -> float:
        """Train on the ``horizon``-step open-loop error, after the one-step fit (multi-step loss).

        From every start state ``s_t`` of the episodes the model is rolled out through the
        logged actions as the planner rolls it (each step in the body frame of its own
        predicted state), and the loss is the mean over steps of the squared error in the
        body frame of ``s_t``, per channel divided by the one-step delta std and weighted by
        the model's ``loss_weights``: errors that compound over the planner's horizon (a
        roll building up in a turn) are trained on directly, not only one step at a time.
        Uses the model's optimizer (Adam). Returns the last epoch's mean loss.
        """
        m = self.model
        start, actions, truth = h_step_windows(episodes, horizon, max_starts=None)
        s0 = torch.as_tensor(start, dtype=torch.float32)
        a = torch.as_tensor(actions, dtype=torch.float32)
        y = torch.as_tensor(truth, dtype=torch.float32)
        P, E = s0.shape[0], m.ensemble
        scale = m.delta_std.clamp_min(1e-6)
        w = m.loss_weight_tensor()
        opt = m._optimizer
        if opt is None:
            raise RuntimeError("fit_open_loop follows a one-step fit (it continues its optimizer)")
        gen = torch.Generator().manual_seed(2 + int(m.config.get("seed") or 0))
        last = float("nan")
        m.train()
        for _ in range(int(epochs)):
            order = torch.randperm(P, generator=gen)
            total, n = 0.0, 0
            for i in range(0, P, batch_size):
                idx = order[i : i + batch_size]
                ref = s0[idx].unsqueeze(0).expand(E, -1, -1)
                cur, loss = ref, 0.0
                for k in range(horizon):
                    nxt = m._predict_diff(self.frame.to_body(cur, cur), a[idx, k])
                    cur = self.frame.to_world(nxt, cur)
                    d = (self.frame.to_body(cur, ref) - self.frame.to_body(y[idx, k].expand(E, -1, -1), ref)) / scale
                    loss = loss + ((d**2) * w).mean(dim=(1, 2)).sum() / horizon
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total, n = total + float(loss.detach()) / E, n + 1
            last = total / max(n, 1)
        m._fast = None
        m.eval()
        return last

    def validation_errors(self, train: Sequence[Episode], val: Sequence[Episode], horizon: int) -> dict[str, float]:
        """The open-loop errors :meth:`fit` reports (see there)."""
        windows = h_step_windows(val, horizon)
        st = np.concatenate([e.states for e in train]).astype(np.float32)
        world_std = torch.as_tensor(st.std(0)).clamp_min(1e-6)
        body = np.concatenate([self.frame.to_body(e.states[1:], e.states[:-1]) for e in train]).astype(np.float32)
        body_std = torch.as_tensor(body.std(0)).clamp_min(1e-6)
        val_h, val_h_raw = h_step_error(self, *windows, state_std=world_std)
        val_h_body, _ = h_step_error(self, *windows, state_std=body_std, frame=self.frame.to_body)
        return {"val_h": val_h, "val_h_raw": val_h_raw, "val_h_body": val_h_body,
                "val_h_xy_mse_m2": self.h_step_xy_error(val, horizon), "horizon": horizon}

    def predict(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        body = self.frame.to_body(state, state)
        nxt = self.model.predict(body, action)  # [E, B, S]
        ref = state if state.dim() == 3 else state.unsqueeze(0).expand_as(nxt)
        return self.frame.to_world(nxt, ref)

    def h_step_xy_error(self, episodes: Sequence[Episode], horizon: int = 4) -> float:
        """Mean squared open-loop error after ``horizon`` steps in x, y [m²], world frame."""
        errs = []
        with torch.inference_mode():
            for ep in episodes:
                T = len(ep)
                if T < horizon:
                    continue
                starts = np.arange(0, T - horizon + 1)
                s = torch.as_tensor(ep.states[starts], dtype=torch.float32)
                for h in range(horizon):
                    a = torch.as_tensor(ep.actions[starts + h], dtype=torch.float32)
                    s = self.predict(s, a).mean(0)
                true = ep.states[starts + horizon]
                d = s.numpy()[:, [self.frame.ix, self.frame.iy]] - true[:, [self.frame.ix, self.frame.iy]]
                errs.append((d**2).sum(-1))
        return float(np.concatenate(errs).mean()) if errs else float("nan")

    def save(self, path: str | Path) -> None:
        self.model.save(path)


def ensemble_of(model: EnsembleDynamics | BodyFrameDynamics) -> EnsembleDynamics:
    """The network a dynamics model learns with: the model itself, or the one a
    :class:`BodyFrameDynamics` wraps (its weights, normalizers, config and channel names)."""
    if isinstance(model, BodyFrameDynamics):
        return model.model
    if isinstance(model, EnsembleDynamics):
        return model
    raise TypeError(f"expected an EnsembleDynamics or a BodyFrameDynamics, got {type(model).__name__}")


def load_dynamics(path: str | Path):
    """Load a checkpoint; body-frame models come back wrapped."""
    m = EnsembleDynamics.load(path)
    if m.config.get("body_frame"):
        return BodyFrameDynamics(m, m.state_names)
    return m
