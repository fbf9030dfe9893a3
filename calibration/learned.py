"""The ``checkpoint`` nominal model: a learned dynamics checkpoint, where an effect is a missing input.

A checkpoint is what :meth:`hilstack.learning.dynamics.EnsembleDynamics.save` writes (loaded with
:func:`hilstack.learning.frames.load_dynamics`: an ``EnsembleDynamics`` or a ``BodyFrameDynamics``
wrapper). It predicts s_{t+1} from (s_t, a_t). What such a model can lack is an *input*: the
next state may depend on something it never sees. The candidates (``LEARNED_CATALOGUE``):

* ``vbat``: battery voltage [V] (the ``vbat`` channel of a recording, a ``vbat=`` column);
* ``action_lag1`` / ``action_lag2``: the previous actions a_{t-1}, a_{t-2} (transport delay);
* ``state_delta_lag1``: the previous state change s_t − s_{t-1} (actuator lag, unobserved
  velocity-like state); in open-loop replays it is taken from the model's own predictions;
* ``time_since_reset``: t − t_0 [s] (warm-up, drift within an episode).

Fitting a candidate set = retraining the network with the extra inputs appended to the action
vector (an ``EnsembleDynamics`` with action_dim A + k and the checkpoint's hyper-parameters).
Every fit, with or without extra inputs, starts from the checkpoint's weights (the extra input
rows of the first layer at zero, so it starts as exactly the checkpoint) and trains the same
number of epochs with the same seed on the same episodes: a candidate's held-out gain is
then the gain of the input, not of retraining on new data. ``hidden`` smaller than the
checkpoint's (tests) trains from scratch instead.

Scores (like the other models): one-step prediction from the logged state and multi-step
open-loop windows of ``horizon`` steps replaying the logged actions (and exogenous extras),
NMSE per state channel. The selection (folds, locked test set, paired test, bootstrap,
look-alikes, black box) is :func:`hilstack.calibration.selection.select_effects`, unchanged.

The primary parameter of every candidate is ``shuffle_loss_increase``: the relative increase
of the one-step loss when that input's values are shuffled across transitions, measured on
episodes the fit did not train on (the out-of-bag episodes of a bootstrap replicate; the
training episodes when there are none). No effect = 0: for an input the model does not
need, intact and shuffled values predict equally well out of sample.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hilstack.calibration import axis
from hilstack.calibration.data import DataError, Recording
from hilstack.calibration.effects import EffectSpec
from hilstack.calibration.model_api import (
    DescribesVelocity,
    ExportsAugmented,
    LoadsEpisodes,
    NominalModel,
    OwnDetectionLimits,
    OwnPlots,
    ResidualRows,
)
from hilstack.learning.frames import ensemble_of


class CheckpointError(DataError):
    """The checkpoint file is missing or is not a dynamics checkpoint."""


_PRIMARY = "shuffle_loss_increase"
LEARNED_CATALOGUE: dict[str, EffectSpec] = {
    e.name: e
    for e in [
        EffectSpec("vbat", "battery/supply voltage as an extra input [V]", _PRIMARY, "1", 0.0, needs=("vbat",),
                   diagnostic="one-step residual vs battery voltage"),
        EffectSpec("action_lag1", "previous action a_{t-1} as an extra input (transport delay)", _PRIMARY, "1", 0.0,
                   diagnostic="residual correlated with the previous action"),
        EffectSpec("action_lag2", "action a_{t-2} as an extra input (a delay of more than one period)", _PRIMARY,
                   "1", 0.0, diagnostic="residual correlated with the action two periods back"),
        EffectSpec("state_delta_lag1", "previous state change s_t - s_{t-1} as an extra input (actuator lag, "
                   "an unobserved state)", _PRIMARY, "1", 0.0, diagnostic="residual correlated with the last change"),
        EffectSpec("time_since_reset", "time since the episode started [s] as an extra input (warm-up, drift)",
                   _PRIMARY, "1", 0.0, diagnostic="residual vs time in episode"),
    ]
}

LEARNED_LOOK_ALIKES: dict[frozenset, str] = {
    frozenset({"action_lag1", "state_delta_lag1"}):
        "action steps while the state is steady and state changes without action steps (a delay follows the "
        "command, a lag follows the state's own history)",
    frozenset({"vbat", "time_since_reset"}):
        "episodes that start on batteries of different charge (voltage and time in episode then stop moving "
        "together)",
    frozenset({"action_lag1", "action_lag2"}):
        "action steps held for a single period (a one-period and a two-period delay then differ)",
}

#: candidates computed from logged signals only (no model state): replayed as recorded
_EXOGENOUS = ("vbat", "action_lag1", "action_lag2", "time_since_reset")


def _lagged(a: np.ndarray, lag: int) -> np.ndarray:
    """a shifted by ``lag`` rows; zeros before the episode (it starts from rest)."""
    out = np.zeros_like(a)
    out[lag:] = a[: a.shape[0] - lag]
    return out


# ----------------------------------------------------------------------------- data


@dataclass
class LearnedPrepared:
    """One episode in the checkpoint's channel order, with every candidate input precomputed."""

    ep: Recording
    key: int
    period_s: float
    states: np.ndarray  # [T+1, S] float32, checkpoint state order
    actions: np.ndarray  # [T, A] float32, checkpoint action order
    features: dict[str, np.ndarray]  # candidate -> [T, k] (state_delta_lag1: from the logged states)

    @property
    def n(self) -> int:
        return int(self.states.shape[0])

    @property
    def T(self) -> int:
        return int(self.actions.shape[0])


def candidate_features(states: np.ndarray, actions: np.ndarray, t_s: np.ndarray | None,
                       vbat_v: np.ndarray | None) -> dict[str, np.ndarray]:
    """Every candidate input per transition t (T rows), from a logged episode.

    ``states`` [T+1, S], ``actions`` [T, A], ``t_s`` [T+1] (None: no time feature), ``vbat_v`` [T+1]
    or None. Used for training rows and by :class:`AugmentedDynamics` on new data.
    """
    s = np.asarray(states, np.float32)
    a = np.asarray(actions, np.float32)
    f = {
        "action_lag1": _lagged(a, 1),
        "action_lag2": _lagged(a, 2),
        "state_delta_lag1": np.vstack([np.zeros((1, s.shape[1]), np.float32), np.diff(s[:-1], axis=0)]),
    }
    if t_s is not None:
        f["time_since_reset"] = (np.asarray(t_s[:-1], float) - float(t_s[0])).astype(np.float32)[:, None]
    if vbat_v is not None:
        f["vbat"] = np.asarray(vbat_v[:-1], np.float32)[:, None]
    return f


def feature_columns(name: str, state_names: list[str], action_names: list[str]) -> list[str]:
    if name in ("action_lag1", "action_lag2"):
        return [f"{a}_lag{name[-1]}" for a in action_names]
    if name == "state_delta_lag1":
        return [f"d_{s}_lag1" for s in state_names]
    return {"vbat": ["vbat_v"], "time_since_reset": ["t_since_reset_s"]}[name]


# ----------------------------------------------------------------------------- fitted model


@dataclass
class FittedLearned:
    """A retrained network with extra inputs ``effects`` (appended to the action, in this order)."""

    effects: list[str]
    net: Any  # EnsembleDynamics or BodyFrameDynamics
    eval_preps: list[LearnedPrepared] = field(default_factory=list)  # out-of-bag (or training) episodes
    eval_is_oob: bool = False
    norm_one: np.ndarray | None = None  # one-step normalizer (variance per state channel)
    base_action_dim: int = 0
    state_names: list[str] = field(default_factory=list)
    action_names: list[str] = field(default_factory=list)
    checkpoint: str = ""
    _primary: dict[str, float] = field(default_factory=dict)

    def extras(self, p: LearnedPrepared) -> np.ndarray:
        cols = [p.features[e] for e in self.effects]
        return np.concatenate(cols, axis=1) if cols else np.zeros((p.T, 0), np.float32)

    def one_step(self, p: LearnedPrepared, extras: np.ndarray | None = None) -> np.ndarray:
        """Predicted s_{t+1} [T, S] from the logged s_t (ensemble mean)."""
        ex = self.extras(p) if extras is None else extras
        with torch.no_grad():
            s = torch.from_numpy(np.ascontiguousarray(p.states[:-1]))
            a = torch.from_numpy(np.ascontiguousarray(np.concatenate([p.actions, ex], axis=1), np.float32))
            return self.net.predict(s, a).mean(0).numpy()

    def rollout(self, p: LearnedPrepared, horizon: int, starts: np.ndarray) -> np.ndarray:
        """Open-loop windows [len(starts), H, S]: from the logged s_k, replay logged actions and
        exogenous extras; ``state_delta_lag1`` comes from the predicted trajectory."""
        H = horizon
        ex = self.extras(p)
        cols = {}
        c = 0
        for e in self.effects:
            k = p.features[e].shape[1]
            cols[e] = slice(c, c + k)
            c += k
        E = ensemble_of(self.net).ensemble
        with torch.no_grad():
            cur = torch.from_numpy(p.states[starts]).unsqueeze(0).expand(E, -1, -1).contiguous()
            prev = torch.from_numpy(p.states[np.maximum(starts - 1, 0)]).unsqueeze(0).expand(E, -1, -1)
            # at t=0 there is no previous state: the logged feature (zero) is used, as in training
            prev = torch.where(torch.from_numpy(starts == 0)[None, :, None], cur, prev)
            out = []
            for h in range(H):
                idx = starts + h
                a = torch.from_numpy(np.concatenate([p.actions[idx], ex[idx]], axis=1).astype(np.float32))
                a = a.unsqueeze(0).expand(E, -1, -1).clone()
                if "state_delta_lag1" in cols:
                    a[..., self.base_action_dim + cols["state_delta_lag1"].start:
                      self.base_action_dim + cols["state_delta_lag1"].stop] = cur - prev
                nxt = self.net.predict(cur, a)
                prev, cur = cur, nxt
                out.append(nxt.mean(0))
            return torch.stack(out, dim=1).numpy()

    def one_step_loss(self, preps: list[LearnedPrepared], nm_one: np.ndarray, shuffle: str | None = None,
                      seed: int = 0) -> float:
        """Summed one-step NMSE over channels on ``preps``; ``shuffle`` permutes one input's rows
        across all their transitions (jointly for multi-column inputs)."""
        exs = [self.extras(p) for p in preps]
        if shuffle is not None:
            i0 = self.effects.index(shuffle)
            c0 = sum(preps[0].features[e].shape[1] for e in self.effects[:i0])
            c1 = c0 + preps[0].features[shuffle].shape[1]
            allv = np.concatenate([x[:, c0:c1] for x in exs])
            allv = allv[np.random.default_rng(seed).permutation(allv.shape[0])]
            out, o = [], 0
            for x in exs:
                x = x.copy()
                x[:, c0:c1] = allv[o:o + x.shape[0]]
                o += x.shape[0]
                out.append(x)
            exs = out
        sse, n = 0.0, 0
        for p, x in zip(preps, exs, strict=True):
            pred = self.one_step(p, x)
            sse += np.sum((pred - p.states[1:]) ** 2 / nm_one)
            n += p.T
        return float(sse / max(n, 1))

    def primary(self, name: str) -> float:
        if name not in self._primary:
            # average over a few permutations: one shuffle of a few hundred rows is noisy
            base = self.one_step_loss(self.eval_preps, self.norm_one)
            vals = [self.one_step_loss(self.eval_preps, self.norm_one, shuffle=name, seed=s) for s in range(3)]
            self._primary[name] = float(np.mean(vals) / max(base, 1e-300) - 1.0)
        return self._primary[name]

    def effect_params(self, name: str) -> dict[str, float]:
        return {_PRIMARY: self.primary(name)}

    def extra_inputs(self) -> list[dict]:
        """Description of the extra inputs, in the order they follow the action."""
        out, c = [], self.base_action_dim
        for e in self.effects:
            cols = feature_columns(e, self.state_names, self.action_names)
            out.append({"name": e, "description": LEARNED_CATALOGUE[e].description, "columns": cols,
                        "action_index": [c, c + len(cols)]})
            c += len(cols)
        return out

    def to_dict(self) -> dict:
        return {"model": "checkpoint", "checkpoint": self.checkpoint, "effects": list(self.effects),
                "extra_inputs": self.extra_inputs(), "state_names": self.state_names,
                "action_names": self.action_names}

    def save(self, path: str | Path) -> Path:
        """Save as a dynamics checkpoint whose config names the extra inputs (load_augmented)."""
        path = Path(path)
        inner = ensemble_of(self.net)
        inner.config["extra_inputs"] = self.extra_inputs()
        inner.config["base_action_dim"] = int(self.base_action_dim)
        inner.config["calibrated_from"] = self.checkpoint
        self.net.save(path)
        return path


# ----------------------------------------------------------------------------- reloading


class AugmentedDynamics:
    """A saved augmented model: ``predict(state, action, extras)`` like the checkpoint plus extras.

    ``extra_inputs`` lists the inputs (name, columns, slice of the augmented action vector);
    :meth:`features` builds them from a logged episode, :meth:`rollout` replays one open loop.
    """

    def __init__(self, net, extra_inputs: list[dict], base_action_dim: int):
        self.net = net
        self.extra_inputs = extra_inputs
        self.base_action_dim = base_action_dim
        inner = ensemble_of(net)
        self.state_names = list(inner.state_names or [])
        self.action_names = list(inner.action_names or [])[:base_action_dim]
        self.extra_dim = sum(len(e["columns"]) for e in extra_inputs)

    @property
    def effects(self) -> list[str]:
        return [e["name"] for e in self.extra_inputs]

    def features(self, states: np.ndarray, actions: np.ndarray, t_s: np.ndarray | None = None,
                 vbat_v: np.ndarray | None = None) -> np.ndarray:
        """The extra-input rows [T, extra_dim] of a logged episode (states [T+1,S], actions [T,A])."""
        f = candidate_features(states, actions, t_s, vbat_v)
        missing = [e for e in self.effects if e not in f]
        if missing:
            raise ValueError(f"extra inputs {missing} need " + ", ".join(
                {"vbat": "vbat_v", "time_since_reset": "t_s"}[m] for m in missing))
        cols = [f[e] for e in self.effects]
        return np.concatenate(cols, axis=1) if cols else np.zeros((len(actions), 0), np.float32)

    def predict(self, state: torch.Tensor, action: torch.Tensor, extras: torch.Tensor) -> torch.Tensor:
        """[E, B, S] next states from state [B,S], action [B,A] and extras [B, extra_dim]."""
        if extras.shape[-1] != self.extra_dim:
            raise ValueError(f"extras must have {self.extra_dim} columns "
                             f"({[c for e in self.extra_inputs for c in e['columns']]}), got {extras.shape[-1]}")
        return self.net.predict(state, torch.cat([action, extras.to(action.dtype)], dim=-1))

    def rollout(self, states: np.ndarray, actions: np.ndarray, t_s: np.ndarray | None = None,
                vbat_v: np.ndarray | None = None) -> np.ndarray:
        """Whole-episode open-loop replay from states[0]: predicted states [T+1, S]."""
        p = LearnedPrepared(None, 0, 0.0, np.asarray(states, np.float32), np.asarray(actions, np.float32),
                            candidate_features(states, actions, t_s, vbat_v))
        fit = FittedLearned(self.effects, self.net, base_action_dim=self.base_action_dim)
        traj = fit.rollout(p, p.T, np.array([0]))[0]
        return np.vstack([p.states[:1], traj])


def load_checkpoint(path: str | Path):
    """load_dynamics with clear errors (missing file, not a dynamics checkpoint)."""
    from hilstack.learning.frames import load_dynamics

    p = Path(path)
    if not p.exists():
        raise CheckpointError(f"checkpoint not found: {p}")
    if not p.is_file():
        raise CheckpointError(f"checkpoint {p} is not a file")
    try:
        net = load_dynamics(p)
    except Exception as e:  # torch.load raises many types on foreign files (pickle, zip, key errors)
        raise CheckpointError(f"{p} is not a dynamics checkpoint (hilstack.learning.dynamics.EnsembleDynamics.save): "
                              f"{type(e).__name__}: {str(e)[:200]}") from None
    inner = ensemble_of(net)
    if not inner.state_names or not inner.action_names:
        raise CheckpointError(f"{p}: the checkpoint has no state_names/action_names, so recorded channels "
                              "cannot be matched to its inputs; save it from a dataset with channel names")
    return net


def load_augmented(path: str | Path) -> AugmentedDynamics:
    """Load ``model_augmented.pt`` written by the calibration (or any checkpoint: no extras)."""
    net = load_checkpoint(path)
    inner = ensemble_of(net)
    extra = list(inner.config.get("extra_inputs") or [])
    base = int(inner.config.get("base_action_dim", inner.action_dim))
    return AugmentedDynamics(net, extra, base)


# ----------------------------------------------------------------------------- the model


@dataclass
class _Norms:
    one: np.ndarray  # variance of the one-step increment, per state channel
    multi: np.ndarray  # variance of the state, per channel


def _safe_var(x: np.ndarray) -> np.ndarray:
    v = np.var(x, axis=0).astype(float)
    # a constant channel would divide by zero: weigh its (tiny) errors in its own units
    return np.where(v < 1e-12, 1.0, v)


class CheckpointModel(NominalModel, LoadsEpisodes, OwnDetectionLimits, ResidualRows, OwnPlots, ExportsAugmented,
                      DescribesVelocity):
    """A learned dynamics checkpoint as calibration nominal model (see module docstring).

    Args:
        checkpoint: path of the ``.pt`` file.
        epochs: training epochs of every fit (the same with and without a candidate).
        batch_size: transitions per gradient step.
        hidden: hidden widths of the retrained networks (default: the checkpoint's; a
            different size trains from scratch instead of from the checkpoint's weights).
        ensemble: members of the retrained networks (default: the checkpoint's).
        normalized_actions: MCAP input: actions in [-1, 1] of the robot's spec (as
            ``hilstack.learning.mbrl`` trains) or in robot units; default: the checkpoint config's
            ``actions_normalized``, else True.
        max_starts: multi-step window starts per episode (evenly spaced).
    """

    name = "checkpoint"
    catalogue = LEARNED_CATALOGUE
    look_alikes = LEARNED_LOOK_ALIKES
    segmentable = False
    velocity_source = "recorded state channels (the checkpoint's state_names)"

    def __init__(self, checkpoint: str | Path, epochs: int = 40, batch_size: int = 256,
                 hidden: list[int] | tuple[int, ...] | None = None, ensemble: int | None = None,
                 normalized_actions: bool | None = None, max_starts: int = 16, min_episodes: int = 10):
        self.path = Path(checkpoint)
        self.net0 = load_checkpoint(self.path)
        self.inner0 = ensemble_of(self.net0)
        self.body_frame = self.inner0 is not self.net0
        self.state_names = list(self.inner0.state_names)
        self.action_names = list(self.inner0.action_names)
        self.epochs = int(epochs)
        self.batch_size = int(batch_size)
        cfg = self.inner0.config
        self.hidden = [int(h) for h in (hidden or cfg["hidden"])]
        self.ensemble = int(ensemble or cfg["ensemble"])
        self.warm = self.hidden == list(cfg["hidden"]) and self.ensemble == cfg["ensemble"]
        self.normalized_actions = (bool(cfg.get("actions_normalized", True)) if normalized_actions is None
                                   else bool(normalized_actions))
        self.max_starts = int(max_starts)
        self.min_episodes = int(min_episodes)
        self._cache: dict[tuple, FittedLearned] = {}
        self._nm: _Norms | None = None
        self.n_fits = 0

    # ------------------------------------------------------------------ data
    def load_episodes(self, path, column_map=None, robot: str | None = None) -> list[Recording]:
        """MCAP via hilstack.calibration.data.load_episodes, CSV/Parquet via :func:`load_state_action_table`."""
        from hilstack.calibration.data import load_episodes

        p = Path(path)
        if p.suffix.lower() == ".mcap":
            return load_episodes(p, column_map, robot=robot, normalize_actions=self.normalized_actions)
        return load_state_action_table(p, self.state_names, self.action_names, column_map)

    def prepare(self, episodes: list[Recording]) -> list[LearnedPrepared]:
        if len(episodes) < self.min_episodes:
            raise DataError(f"too few episodes: {len(episodes)}; the checkpoint model needs at least "
                            f"{self.min_episodes} whole episodes (a locked test set and cross-validation "
                            "folds are made of whole episodes); record more episodes")
        out = []
        for i, e in enumerate(episodes):
            if e.states is None or e.actions is None:
                raise DataError(f"{e.name}: model 'checkpoint' needs state/action channels (an .mcap recording "
                                "or a table mapped to the checkpoint's state_names/action_names)")
            ms = [n for n in self.state_names if n not in e.state_names]
            ma = [n for n in self.action_names if n not in e.action_names]
            if ms or ma:
                raise DataError(f"{e.name}: the data lacks the checkpoint's " + "; ".join(
                    s for s in (f"state channels {ms}" if ms else "", f"action channels {ma}" if ma else "") if s)
                    + f" (data has states {list(e.state_names)}, actions {list(e.action_names)})")
            if e.n < 3:
                raise DataError(f"{e.name}: only {e.n} samples; need at least 3")
            tr = e.transitions(self.state_names, self.action_names)  # N states, the N-1 actions between
            states, actions = tr.states, tr.actions
            feats = candidate_features(states, actions, e.t_s, e.vbat_v)
            out.append(LearnedPrepared(e, i, e.period_s, states, actions, feats))
        return out

    def candidate_effects(self, episodes: list[LearnedPrepared], accepted: tuple[str, ...] = ()
                          ) -> tuple[list[str], dict[str, str]]:
        names, skipped = [], {}
        inputs = set(self.state_names) | set(self.action_names)
        for name in LEARNED_CATALOGUE:
            if name == "vbat" and not all("vbat" in p.features for p in episodes):
                skipped[name] = "needs a battery voltage (a vbat channel in the recording, or --map vbat=COLUMN)"
            elif name == "vbat" and inputs & {"vbat", "vbat_v"}:
                skipped[name] = "battery voltage is already an input of the checkpoint"
            elif name == "action_lag2" and "action_lag1" not in accepted:
                skipped[name] = "tested once action_lag1 is accepted (a longer delay on top of one period)"
            elif name == "state_delta_lag1" and self.body_frame:
                skipped[name] = "not offered for body-frame checkpoints (the lagged change would need the frame " \
                                "of s_{t-1})"
            else:
                names.append(name)
        return names, skipped

    # ------------------------------------------------------------------ losses
    def norms(self, pool: list[LearnedPrepared]) -> _Norms:
        self._nm = _Norms(_safe_var(np.concatenate([np.diff(p.states, axis=0) for p in pool])),
                          _safe_var(np.concatenate([p.states for p in pool])))
        return self._nm

    def _starts(self, p: LearnedPrepared, horizon: int) -> tuple[np.ndarray, int]:
        H = max(1, min(horizon, p.T))
        last = p.T - H
        n = min(self.max_starts, last + 1)
        return np.unique(np.linspace(0, last, n).round().astype(int)), H

    def _errors(self, p: LearnedPrepared, fitted: FittedLearned, horizon: int):
        one = np.sum((fitted.one_step(p) - p.states[1:]) ** 2, axis=0)
        starts, H = self._starts(p, horizon)
        traj = fitted.rollout(p, H, starts)
        truth = p.states[starts[:, None] + np.arange(1, H + 1)[None, :]]
        multi = np.sum((traj - truth) ** 2, axis=(0, 1))
        return one, p.T, multi, traj.shape[0] * H

    def episode_loss(self, prep: LearnedPrepared, fitted: FittedLearned, horizon: int, nm: _Norms) -> float:
        """Mean NMSE over state channels, one-step and multi-step weighted alike."""
        one, n1, multi, nm_ = self._errors(prep, fitted, horizon)
        return float(0.5 * (np.mean(one / n1 / nm.one) + np.mean(multi / nm_ / nm.multi)))

    def oob_loss(self, prep: LearnedPrepared, fitted: FittedLearned, nm: _Norms) -> float:
        return float(np.mean(np.sum((fitted.one_step(prep) - prep.states[1:]) ** 2, axis=0) / nm.one))

    def score(self, prep: LearnedPrepared, fitted: FittedLearned, horizon: int) -> axis.Scores:
        one, n1, multi, nm_ = self._errors(prep, fitted, horizon)
        return axis.Scores(one_sse=dict(zip(self.state_names, map(float, one), strict=True)), one_n=n1,
                           multi_sse=dict(zip(self.state_names, map(float, multi), strict=True)), multi_n=nm_)

    def channel_sd(self, preps: list[LearnedPrepared]) -> dict[str, dict[str, float]]:
        d = _safe_var(np.concatenate([np.diff(p.states, axis=0) for p in preps]))
        m = _safe_var(np.concatenate([p.states for p in preps]))
        return {"one": dict(zip(self.state_names, map(float, np.sqrt(d)), strict=True)),
                "multi": dict(zip(self.state_names, map(float, np.sqrt(m)), strict=True))}

    # ------------------------------------------------------------------ fitting
    def _new_net(self, effects: list[str], extra_dim: int):
        from hilstack.learning.dynamics import EnsembleDynamics
        from hilstack.learning.frames import BodyFrameDynamics

        cfg = self.inner0.config
        names = [c for e in effects for c in feature_columns(e, self.state_names, self.action_names)]
        S, A = len(self.state_names), len(self.action_names)
        net = EnsembleDynamics(
            S, A + extra_dim, self.ensemble, self.hidden, lr=cfg["lr"], weight_decay=cfg["weight_decay"],
            input_noise_std=cfg["input_noise_std"], bootstrap=cfg["bootstrap"] if self.warm else None,
            norm_update=cfg["norm_update"], inference_dtype="fp32", state_names=self.state_names,
            action_names=self.action_names + names, state_units=self.inner0.state_units,
            action_units=(self.inner0.action_units + ["input"] * extra_dim) if self.inner0.action_units else None,
            seed=cfg.get("seed", 0))
        if cfg.get("ignore_inputs"):
            net.ignore_inputs(cfg["ignore_inputs"])
        if self.warm:
            with torch.no_grad():
                for dst, src in zip(net.weights, self.inner0.weights, strict=True):
                    dst[:, : src.shape[1]].copy_(src)
                    dst[:, src.shape[1]:].zero_()  # extra input rows: start as exactly the checkpoint
                for dst, src in zip(net.biases, self.inner0.biases, strict=True):
                    dst.copy_(src)
                net.input_mean[: S + A].copy_(self.inner0.input_mean)
                net.input_std[: S + A].copy_(self.inner0.input_std)
                net.delta_mean.copy_(self.inner0.delta_mean)
                net.delta_std.copy_(self.inner0.delta_std)
                net.state_std.copy_(self.inner0.state_std)
                net.fitted.fill_(True)
            net._fast = None
        return BodyFrameDynamics(net, self.state_names) if self.body_frame else net

    def fit(self, episodes: list[LearnedPrepared], effects: list[str], weights=None, refine: bool = True,
            start: FittedLearned | None = None, search: list[str] | None = None) -> FittedLearned:
        """Retrain with ``effects`` as extra inputs on ``episodes`` (bootstrap ``weights`` repeat
        episodes). ``start``/``search``/``refine`` do not apply: every fit starts from the checkpoint
        and trains the same epochs, so fits with and without a candidate differ only in the input."""
        from hilstack.learning.datasets import Episode as LEpisode

        if self._nm is None:
            self.norms(episodes)
        w = np.ones(len(episodes), int) if weights is None else np.asarray(np.round(weights), int)
        key = (tuple(p.key for p in episodes), hashlib.sha1(w.tobytes()).hexdigest(), tuple(effects))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        train, oob = [], []
        for wi, p in zip(w, episodes, strict=True):
            if wi <= 0:
                oob.append(p)
                continue
            ex = np.concatenate([p.features[e] for e in effects], axis=1) if effects else np.zeros((p.T, 0))
            le = LEpisode(p.states, np.concatenate([p.actions, ex], axis=1), name=str(p.key))
            train.extend([le] * int(wi))
        extra_dim = sum(episodes[0].features[e].shape[1] for e in effects)
        torch.manual_seed(0)
        net = self._new_net(list(effects), extra_dim)
        n = sum(len(e) for e in train)
        net.fit(train, epochs=self.epochs, batch_size=min(self.batch_size, max(32, n // 4)), progress=False)
        self.n_fits += 1
        fitted = FittedLearned(list(effects), net, eval_preps=oob or [p for wi, p in zip(w, episodes, strict=True)
                                                                      if wi > 0],
                               eval_is_oob=bool(oob), norm_one=self._nm.one, base_action_dim=len(self.action_names),
                               state_names=self.state_names, action_names=self.action_names,
                               checkpoint=str(self.path))
        if len(self._cache) > 256:  # bootstrap replicates are never reused: bound the memory
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = fitted
        return fitted

    # ------------------------------------------------------------------ diagnostics
    def residual_rows(self, p: LearnedPrepared, fitted: FittedLearned) -> tuple[np.ndarray, np.ndarray]:
        """Black-box rows: state, action, every candidate input that exists; target: the summed
        normalized one-step residual of the final model."""
        cols = [p.states[:-1], p.actions] + [p.features[n] for n in LEARNED_CATALOGUE if n in p.features]
        res = (p.states[1:] - fitted.one_step(p)) / np.sqrt(self._nm.one)
        return np.concatenate(cols, axis=1).astype(float), res.sum(axis=1).astype(float)

    def detection_limits(self, pool, fitted, candidates, skipped, cfg) -> dict:
        """Not a parameter limit (a network input has no physical scale): the smallest held-out gain
        the paired test would detect is reported instead, from the spread of per-episode losses."""
        from scipy import stats as st

        losses = np.array([self.oob_loss(p, fitted, self._nm) for p in pool])
        m = max(1, len(candidates))
        z = st.norm.ppf(1 - cfg.alpha / m) + st.norm.ppf(cfg.power)
        # paired test on n episodes: detectable mean loss change ≈ z·sd/√n, relative to the mean loss
        sd = float(np.std(losses)) if losses.size > 1 else float("nan")
        rel = float(z * sd / math.sqrt(max(losses.size, 1)) / max(float(np.mean(losses)), 1e-300))
        out = {}
        for name in list(candidates) + [s for s in skipped if s not in candidates]:
            entry = {"param": "heldout_gain", "unit": "1", "value": None}
            if name in skipped:
                entry["note"] = skipped[name]
            elif name in fitted.effects:
                entry["note"] = "accepted; see its bootstrap interval"
            else:
                entry["value"] = max(rel, cfg.min_gain)
                entry["note"] = ("smallest relative held-out (one-step) gain detectable with these episodes "
                                 "(paired-test power approximation); min_gain is the floor")
            out[name] = entry
        return {"per_effect": out, "sigma_eff": sd, "autocorr_inflation": 1.0, "z": float(z)}

    def export_augmented(self, out: Path, fitted: FittedLearned, report: dict, test: list[LearnedPrepared]) -> dict:
        """Save ``model_augmented.pt`` and describe its extra inputs (report.json ``augmented_model``)."""
        path = fitted.save(Path(out) / "model_augmented.pt")
        extras = fitted.extra_inputs()
        if test and self._nm is not None:
            for e in extras:
                # on the locked test set: how much the accepted input matters out of sample
                ev = FittedLearned(fitted.effects, fitted.net, eval_preps=test, norm_one=self._nm.one,
                                   base_action_dim=fitted.base_action_dim)
                e["shuffle_loss_increase_test"] = ev.primary(e["name"])
        base = self._as_is_scores(test, report)
        return {"path": str(path), "extra_inputs": extras, "checkpoint": str(self.path),
                "retrained": {"epochs": self.epochs, "hidden": self.hidden, "ensemble": self.ensemble,
                              "init": "checkpoint weights" if self.warm else "scratch",
                              "body_frame": self.body_frame, "n_fits": self.n_fits},
                "checkpoint_as_is": base,
                "load": "hilstack.calibration.learned.load_augmented(path).predict(state, action, extras); "
                        ".features(states, actions, t_s, vbat_v) builds extras from a log"}

    def _as_is_scores(self, test: list[LearnedPrepared], report: dict) -> dict | None:
        """The unmodified checkpoint on the locked test set (before it is retrained on this data)."""
        if not test:
            return None
        as_is = FittedLearned([], self.net0, base_action_dim=len(self.action_names))
        h = int(report["folds"]["horizon_steps"])
        sd = self.channel_sd(test)
        out = {}
        for kind, idx in (("one_step_nrmse", 0), ("multi_step_nrmse", 2)):
            errs = [self._errors(p, as_is, h) for p in test]
            sse = np.sum([e[idx] for e in errs], axis=0)
            n = sum(e[idx + 1] for e in errs)
            per = {c: float(math.sqrt(sse[i] / n) / sd["one" if idx == 0 else "multi"][c])
                   for i, c in enumerate(self.state_names)}
            out[kind] = {"mean": float(np.mean(list(per.values()))), "per_channel": per}
        return out

    def plots(self, out: Path, sel, preps, pool, test) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        p = test[0] if test else pool[0]
        t = p.ep.t_s[: p.n] - p.ep.t_s[0]
        S = len(self.state_names)
        fig, ax = plt.subplots(S, 1, figsize=(9, 2.4 * S), squeeze=False)
        for fitted, label in ((sel.nominal, "before (retrained, no extra input)"),
                              (sel.final, f"after (+{', '.join(sel.final.effects) or 'nothing'})")):
            traj = fitted.rollout(p, p.T, np.array([0]))[0]
            for i in range(S):
                ax[i, 0].plot(t[1:], traj[:, i], lw=1.0, label=label)
        for i, n in enumerate(self.state_names):
            ax[i, 0].plot(t, p.states[:, i], "k", lw=0.8, label="measured")
            ax[i, 0].set_ylabel(n)
            ax[i, 0].legend(fontsize=7)
        ax[-1, 0].set_xlabel("t [s]")
        ax[0, 0].set_title(f"whole-episode open-loop replay: {p.ep.name}", fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "residual_before_after.png", dpi=90)
        plt.close(fig)


# ----------------------------------------------------------------------------- tables


def load_state_action_table(path: str | Path, state_names: list[str], action_names: list[str],
                            column_map: str | dict | Path | None = None) -> list[Recording]:
    """CSV/Parquet (a file or a directory) with one column per checkpoint channel.

    ``column_map``: ``NAME=column`` pairs (``x=pos_m,u=cmd``) for checkpoint channel names whose
    column is named differently, plus ``t=`` (time [s]; default column ``t``, ``time`` or
    ``t_s``), ``episode=`` (default ``episode`` if present) and ``vbat=`` (battery voltage [V],
    optional; default ``vbat`` if present). Unmapped channels are looked up by their own name.
    Row k holds s_k and the action a_k applied after it (the last row's action is unused).
    """
    from hilstack.calibration.data import _read_table

    p = Path(path)
    if not p.exists():
        raise DataError(f"data path not found: {p}")
    mapping = _parse_map(column_map)
    unknown = sorted(set(mapping) - set(state_names) - set(action_names) - {"t", "episode", "vbat"})
    if unknown:
        raise DataError(f"column map keys {unknown} are neither checkpoint channels (states {state_names}, "
                        f"actions {action_names}) nor t/episode/vbat")
    files = sorted(f for f in p.iterdir() if f.suffix.lower() in (".csv", ".parquet", ".pq")) if p.is_dir() else [p]
    if not files:
        raise DataError(f"no .csv or .parquet files in directory {p}")
    out: list[Recording] = []
    for f in files:
        df = _read_table(f)
        cols = list(df.columns)

        def col(key: str, cols=cols) -> str | None:
            return mapping.get(key, key if key in cols else None)

        missing_s = [n for n in state_names if col(n) not in cols]
        missing_a = [n for n in action_names if col(n) not in cols]
        if missing_s or missing_a:
            parts = [f"state channels {[(n, col(n) or n) for n in missing_s]}" if missing_s else "",
                     f"action channels {[(n, col(n) or n) for n in missing_a]}" if missing_a else ""]
            raise DataError(f"{f}: no column for the checkpoint's " + " and ".join(x for x in parts if x)
                            + f" (channel, column looked for); columns: {cols}; map them with --map NAME=COLUMN")
        tcol = mapping.get("t") or next((c for c in ("t", "time", "t_s") if c in cols), None)
        if tcol is None or tcol not in cols:
            raise DataError(f"{f}: no time column (looked for {tcol or 't, time, t_s'}); map it with --map t=COLUMN")
        vcol = mapping.get("vbat", "vbat" if "vbat" in cols else None)
        if vcol is not None and vcol not in cols:
            raise DataError(f"{f}: battery voltage column {vcol!r} not found; columns: {cols}")
        ecol = mapping.get("episode", "episode" if "episode" in cols else None)
        if ecol is not None and ecol not in cols:
            raise DataError(f"{f}: episode column {ecol!r} not found; columns: {cols}")
        groups = [(None, df)] if ecol is None else list(df.groupby(ecol, sort=True))
        for ep_id, g in groups:
            name = f.name if ep_id is None else f"{f.name}#episode={ep_id}"

            def arr(c: str, g=g, name=name, f=f) -> np.ndarray:
                a = np.asarray(g[c].to_numpy(), float)
                bad = np.flatnonzero(~np.isfinite(a))
                if bad.size:
                    raise DataError(f"{f}: non-finite value in column {c!r} at row {int(bad[0])} of {name}")
                return a

            t = arr(tcol)
            if np.any(np.diff(t) <= 0):
                raise DataError(f"{f}: time column {tcol!r} not strictly increasing in {name}")
            states = np.stack([arr(col(n)) for n in state_names], axis=1)
            actions = np.stack([arr(col(n)) for n in action_names], axis=1)
            vb = arr(vcol) if vcol is not None else None
            out.append(Recording(name=name, t_s=t, u=actions[:, 0], x=states[:, 0], vbat_v=vb,
                               meta={"source": str(f)}, states=states, actions=actions,
                               state_names=tuple(state_names), action_names=tuple(action_names)))
    return out


def _parse_map(spec) -> dict[str, str]:
    if spec is None:
        return {}
    if isinstance(spec, dict):
        return {str(k): str(v) for k, v in spec.items()}
    text = str(spec)
    if text.endswith((".yaml", ".yml")):
        import yaml

        if not Path(text).exists():
            raise DataError(f"column map file not found: {text}")
        return {str(k): str(v) for k, v in (yaml.safe_load(Path(text).read_text()) or {}).items()}
    out = {}
    for part in (x.strip() for x in text.split(",")):
        if not part:
            continue
        if "=" not in part:
            raise DataError(f"bad column map entry {part!r}: expected NAME=column")
        k, v = part.split("=", 1)
        out[k.strip()] = v.strip()
    return out
