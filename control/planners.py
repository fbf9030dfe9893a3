"""Sampling-based MPC planners over a learned (ensemble) dynamics model.

Three planners share one rollout-and-score core, all batched in torch over
samples (N) × ensemble members (E) × horizon (H):

* :class:`RandomShooting`: N action sequences uniform in the bounds (optionally within
  the actuator's reachable set, ``max_step``); execute the first action of the cheapest
  one (Nagabandi et al. 2018; VelociRoACH: N=500, H=4).
* :class:`CEM`: cross-entropy method; Gaussian over sequences refit to the ``elites``
  cheapest samples for ``iterations`` rounds.
* :class:`PDDM`: Nagabandi et al. 2019. Temporally filtered noise around a mean sequence
  and a reward-weighted mean (Shadow Hand Baoding balls: N=700, H=7, γ=20, β=0.7, E=3).

Usage (the whole API)::

    planner = PDDM(action_low=-1, action_high=1, horizon=7, samples=700, gamma=20, beta=0.7)
    action = planner(dynamics, cost, state)          # numpy [A], inside the bounds

with the two user functions

    dynamics(state, action) -> next_state
        state:  [N, S] (first step: the current state broadcast to every sample) or
                [E, N, S] (later steps: what the previous call returned)
        action: [N, A]
        returns [E, N, S] for an ensemble of E models, or [N, S] for a single model
        (then E = 1 and later calls also get [N, S]).
        ``hilstack.learning.dynamics.EnsembleDynamics`` (or its ``.predict``) fits as is.
    cost(states, actions) -> [E, N]   (or [N] when the cost ignores the member)
        states:  [E, N, H+1, S], states[:, :, 0] is the current state and states[:, :, h]
                 the prediction after h actions
        actions: [N, H, A], the candidate action sequences (already clipped)
        Lower is better. Both tensors are buffers reused by the next call: read them,
        do not keep references.

Every candidate's cost is averaged over the ensemble members (all members see the same
action sequence); ``risk_k > 0`` adds ``risk_k · std`` over members (pessimism where the
models disagree). After a call the planner keeps ``last_plan`` ([H, A] torch, the sequence
whose first action was returned), ``last_predicted_states`` ([E, H+1, S] torch, the
predictions of the best-scoring sample, for visualization) and ``last_costs`` ([N]).
CEM and PDDM warm start: the mean is shifted one step and the last action repeated, ready
for the next control step. ``reset()`` forgets that (call it between episodes).

Everything runs under ``torch.inference_mode`` with buffers allocated once per shape;
the only host round trip per call is the returned numpy action.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

__all__ = [
    "Planner", "RandomShooting", "CEM", "PDDM", "PddmConfig", "BAODING_PDDM",
    "filtered_noise", "reward_weighted_mean",
]

DynamicsFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
CostFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _vec(x, dim: int | None, name: str) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x, dtype=np.float32))
    if t.dim() == 0 and dim is not None:
        t = t.expand(dim).clone()
    if t.dim() != 1:
        raise ValueError(f"{name} must be a scalar or a 1-D sequence, got shape {tuple(t.shape)}")
    if dim is not None and t.shape[0] != dim:
        if t.shape[0] != 1:
            raise ValueError(f"{name} has {t.shape[0]} entries, the action has {dim} (set action_dim?)")
        t = t.expand(dim).clone()
    return t


# -- the reference math, as pure functions ---------------------------------------------------
def filtered_noise(u: torch.Tensor, beta: float) -> torch.Tensor:
    """PDDM's temporally correlated noise along the horizon axis (dim -2).

    ``n_0 = β u_0``, ``n_t = β u_t + (1-β) n_{t-1}``. For white ``u ~ N(0, σ²)`` the variance
    is ``Var n_t = β² σ² Σ_{k=0..t} (1-β)^{2k}`` → ``σ² β / (2 - β)`` as t grows.
    ``u``: ``[..., H, A]``; returns a new tensor of the same shape.
    """
    n = torch.empty_like(u)
    prev = torch.zeros_like(u[..., 0, :])
    for t in range(u.shape[-2]):  # H is small (4-30); a scan would not pay off
        prev = beta * u[..., t, :] + (1.0 - beta) * prev
        n[..., t, :] = prev
    return n


def reward_weighted_mean(actions: torch.Tensor, rewards: torch.Tensor, gamma: float) -> torch.Tensor:
    """``Σ_k w_k a_k / Σ_k w_k`` with ``w_k = exp(γ (R_k - max R))``.

    Subtracting ``max R`` does not change the result (it cancels in the ratio) but keeps
    ``exp`` from overflowing. ``actions``: ``[N, H, A]``, ``rewards``: ``[N]`` → ``[H, A]``.
    """
    w = torch.exp(gamma * (rewards - rewards.max()))
    return torch.einsum("n,nha->ha", w, actions) / w.sum()


class Planner:
    """Common configuration, rollout and scoring. Subclasses implement :meth:`_plan`.

    Args:
        action_low, action_high: bounds, scalars or ``[A]`` (actions are always clipped).
        horizon: H, steps per candidate sequence.
        samples: N, candidate sequences per iteration.
        iterations: refinement rounds per call (CEM, PDDM).
        risk_k: cost = mean over members + ``risk_k`` · std over members.
        seed: seeds the planner's own ``torch.Generator`` (``None``: nondeterministic).
        action_dim: A, needed only when both bounds are scalars.
    """

    name = "planner"

    def __init__(
        self,
        action_low: float | Sequence[float] = -1.0,
        action_high: float | Sequence[float] = 1.0,
        horizon: int = 10,
        samples: int = 500,
        *,
        iterations: int = 1,
        risk_k: float = 0.0,
        seed: int | None = 0,
        action_dim: int | None = None,
    ) -> None:
        low = np.asarray(action_low, dtype=np.float32)
        high = np.asarray(action_high, dtype=np.float32)
        dim = action_dim or max(low.size, high.size)
        self.action_low = _vec(low, dim, "action_low")
        self.action_high = _vec(high, dim, "action_high")
        if self.action_low.shape != self.action_high.shape:
            raise ValueError("action_low and action_high have different lengths")
        if bool((self.action_low > self.action_high).any()):
            raise ValueError("action_low must be <= action_high")
        self.action_dim = self.action_low.shape[0]
        self.horizon = int(horizon)
        self.samples = int(samples)
        self.iterations = int(iterations)
        self.risk_k = float(risk_k)
        self.seed = seed
        self.generator = torch.Generator()
        self._buffers: dict[str, torch.Tensor] = {}
        self.reset()

    # -- lifecycle -----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the warm start and the last plan; re-seed the generator."""
        if self.seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(int(self.seed))
        self.last_plan: torch.Tensor | None = None
        self._applied = 0  # periods moved along last_plan (shift)
        self.last_predicted_states: torch.Tensor | None = None
        self.last_costs: torch.Tensor | None = None
        self._reset_distribution()

    def _reset_distribution(self) -> None:
        pass

    def config(self) -> dict:
        """The planner's settings as plain Python values."""
        return {
            "planner": self.name,
            "horizon": self.horizon,
            "samples": self.samples,
            "iterations": self.iterations,
            "action_low": self.action_low.tolist(),
            "action_high": self.action_high.tolist(),
            "risk_k": self.risk_k,
            "seed": self.seed,
        }

    def set_samples(self, samples: int) -> None:
        """Plan with ``samples`` candidate sequences from the next call on (a wall-clock
        refit, :mod:`hilstack.control.sample_refit`); the warm start is kept."""
        if int(samples) < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        self.samples = int(samples)

    def _buffer(self, key: str, shape: tuple[int, ...]) -> torch.Tensor:
        buf = self._buffers.get(key)
        if buf is None or buf.shape != shape:
            buf = torch.empty(shape)
            self._buffers[key] = buf
        return buf

    # -- the user-facing call ------------------------------------------------------------
    def __call__(self, dynamics: DynamicsFn, cost: CostFn, state) -> np.ndarray:
        """Plan from ``state`` ([S], numpy or torch) and return the action to apply now ([A] numpy)."""
        with torch.inference_mode():
            s0 = torch.as_tensor(state, dtype=torch.float32).reshape(-1)
            plan = self._plan(dynamics, cost, s0)
            self.last_plan = plan.clone()
            self._applied = 0
            self._warm_start(plan, 0)
            return plan[0].numpy().copy()

    # -- moving in time: the planner owns its warm start ---------------------------------
    def shift(self, n: int = 1) -> None:
        """Move ``n`` more control periods along the last plan (as pytorch_mppi's
        ``shift_nominal_trajectory``).

        A plan is taken as applied from its first step at once (``__call__`` warm-starts the
        next plan from ``last_plan[1:]``). When it was applied late (a realtime plan that came
        in ``n`` periods after its state: its first ``n`` steps were never sent), the step
        acting now is ``last_plan[n]``: the warm start moves on to ``last_plan[n+1:]`` (the
        last step repeated) and a rate-limited sampler anchors at ``last_plan[n]``.
        Shifts add up until the next plan; no-op before the first plan."""
        if n < 0:
            raise ValueError(f"shift needs n >= 0 control periods, got {n}")
        if n == 0 or self.last_plan is None:
            return
        self._applied += n
        self._warm_start(self.last_plan, self._applied)

    def _warm_start(self, plan: torch.Tensor, k: int) -> None:
        """Set what the next plan starts from, with ``plan[k]`` the step acting now
        (``plan[-1]`` past its end). Default: a planner without memory."""

    @staticmethod
    def _after(plan: torch.Tensor, k: int) -> torch.Tensor:
        """``plan`` from step ``k + 1`` on, its last step repeated to keep the length."""
        H = plan.shape[0]
        rest = plan[k + 1:] if k + 1 < H else plan[-1:]
        return torch.cat([rest, rest[-1:].expand(H - rest.shape[0], -1)], dim=0)

    @staticmethod
    def _step(plan: torch.Tensor, k: int) -> torch.Tensor:
        return plan[min(k, plan.shape[0] - 1)].clone()

    def _plan(self, dynamics: DynamicsFn, cost: CostFn, s0: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    # -- shared core: roll out N sequences through E models and score them ----------------
    def rollout(self, dynamics: DynamicsFn, s0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Predicted states ``[E, N, H+1, S]`` of ``actions`` ``[N, H, A]`` from ``s0`` ``[S]``.

        The returned tensor is a reused buffer (valid until the next rollout).
        """
        N, H, _ = actions.shape
        S = s0.shape[0]
        nxt = dynamics(s0.expand(N, S), actions[:, 0])
        single = nxt.dim() == 2  # a single model returning [N, S]
        nxt3 = nxt.unsqueeze(0) if single else nxt
        E = nxt3.shape[0]
        states = self._buffer("states", (E, N, H + 1, S))
        states[:, :, 0] = s0
        states[:, :, 1] = nxt3
        for t in range(1, H):
            nxt = dynamics(nxt, actions[:, t])
            states[:, :, t + 1] = nxt.unsqueeze(0) if single else nxt
        return states

    def score(self, cost: CostFn, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Cost per candidate ``[N]``: mean over members (+ ``risk_k`` · std over members)."""
        c = cost(states, actions)
        if c.dim() == 1:
            return c
        if c.dim() != 2 or c.shape[1] != actions.shape[0]:
            raise ValueError(f"cost must return [E, N] or [N], got {tuple(c.shape)}")
        total = c.mean(dim=0)
        if self.risk_k and c.shape[0] > 1:
            total = total + self.risk_k * c.std(dim=0, unbiased=False)
        return total

    def _evaluate(self, dynamics: DynamicsFn, cost: CostFn, s0: torch.Tensor, actions: torch.Tensor):
        states = self.rollout(dynamics, s0, actions)
        total = self.score(cost, states, actions)
        best = int(torch.argmin(total))
        self.last_costs = total
        self.last_predicted_states = states[:, best].clone()
        return total, best

    def _clip(self, actions: torch.Tensor) -> torch.Tensor:
        return torch.maximum(torch.minimum(actions, self.action_high), self.action_low, out=actions)



class RandomShooting(Planner):
    """Uniform random sequences in the bounds; the first action of the cheapest one.

    ``a_{n,h} ~ U(low, high)``, ``n* = argmin_n cost_n``, returns ``a_{n*,0}``.

    With ``max_step`` (per-step change bound ``r``, scalar or ``[A]``, in action units per
    control step: the actuator's rate limit times the period) the sequences are drawn
    from the actuator's reachable set instead: each step is uniform within ``±r`` of the
    step before, the first within ``±r`` of the previously returned action (anywhere in
    the bounds after :meth:`reset`), all clipped to the bounds:

        a_{n,h} ~ U(max(low, a_{n,h-1} − r), min(high, a_{n,h-1} + r))

    so no candidate scores a jump the rate limit would not let the robot make.
    """

    name = "random_shooting"

    def __init__(self, *args, max_step: float | Sequence[float] | None = None, **kwargs) -> None:
        self._max_step_arg = max_step
        super().__init__(*args, **kwargs)
        self.max_step = None if max_step is None else _vec(max_step, self.action_dim, "max_step")
        if self.max_step is not None and bool((self.max_step <= 0).any()):
            raise ValueError(f"max_step must be > 0, got {self.max_step.tolist()}")

    def _reset_distribution(self) -> None:
        self.previous: torch.Tensor | None = None

    def config(self) -> dict:
        return {**super().config(), "max_step": None if self.max_step is None else self.max_step.tolist()}

    def _plan(self, dynamics, cost, s0):
        N, H, A = self.samples, self.horizon, self.action_dim
        actions = self._buffer("actions", (N, H, A))
        actions.uniform_(0.0, 1.0, generator=self.generator)
        if self.max_step is None:
            actions.mul_(self.action_high - self.action_low).add_(self.action_low)
        else:
            prev = None if self.previous is None else self.previous.expand(N, A)
            for h in range(H):
                if prev is None:
                    lo, hi = self.action_low, self.action_high
                else:
                    lo = torch.maximum(prev - self.max_step, self.action_low)
                    hi = torch.minimum(prev + self.max_step, self.action_high)
                actions[:, h].mul_(hi - lo).add_(lo)
                prev = actions[:, h]
        _, best = self._evaluate(dynamics, cost, s0, actions)
        return actions[best].clone()

    def _warm_start(self, plan, k):
        self.previous = self._step(plan, k)


class CEM(Planner):
    """Cross-entropy method over action sequences.

    For ``iterations`` rounds: sample ``a = clip(μ + σ ε)``, ``ε ~ N(0, I)`` ([N, H, A]),
    take the ``elites`` cheapest, and refit ``μ, σ`` to their mean and (population) std,
    smoothed by ``alpha`` (``μ ← α μ + (1-α) mean_elites``). Returns ``μ_0``. Warm start:
    ``μ`` is shifted one step; ``σ`` restarts at ``sigma`` each call.

    Args (beyond :class:`Planner`):
        elites: number of elite samples (≤ samples).
        sigma: initial std, scalar or ``[A]``; default a quarter of the action range.
        alpha: smoothing of the refit (0 = no memory).
    """

    name = "cem"

    def __init__(self, *args, elites: int = 50, sigma: float | Sequence[float] | None = None,
                 alpha: float = 0.0, iterations: int = 5, **kwargs) -> None:
        self.elites = int(elites)
        self._sigma_arg = sigma
        self.alpha = float(alpha)
        super().__init__(*args, iterations=iterations, **kwargs)
        if not 1 <= self.elites <= self.samples:
            raise ValueError(f"elites must be in [1, samples={self.samples}], got {self.elites}")
        self._elite_share = self.elites / self.samples

    def set_samples(self, samples: int) -> None:
        """As :meth:`Planner.set_samples`; the elites keep their share of the samples."""
        super().set_samples(samples)
        self.elites = max(1, min(self.samples, round(self._elite_share * self.samples)))

    def _reset_distribution(self) -> None:
        rng = self.action_high - self.action_low
        self.sigma = (rng / 4) if self._sigma_arg is None else _vec(self._sigma_arg, self.action_dim, "sigma")
        self.mean = ((self.action_low + self.action_high) / 2).expand(self.horizon, -1).clone()

    def config(self) -> dict:
        return {**super().config(), "elites": self.elites, "sigma": self.sigma.tolist(), "alpha": self.alpha}

    def _plan(self, dynamics, cost, s0):
        N, H, A = self.samples, self.horizon, self.action_dim
        mean = self.mean
        std = self.sigma.expand(H, A).clone()
        actions = self._buffer("actions", (N, H, A))
        for _ in range(self.iterations):
            torch.randn(actions.shape, generator=self.generator, out=actions)
            self._clip(actions.mul_(std).add_(mean))
            total, _ = self._evaluate(dynamics, cost, s0, actions)
            elite = actions[torch.topk(total, self.elites, largest=False).indices]  # [K, H, A]
            mean = self.alpha * mean + (1 - self.alpha) * elite.mean(dim=0)
            std = self.alpha * std + (1 - self.alpha) * elite.std(dim=0, unbiased=False)
        return mean.clone()

    def _warm_start(self, plan, k):
        self.mean = self._after(plan, k)


class PDDM(Planner):
    """PDDM (Nagabandi et al. 2019): filtered-noise sampling and a reward-weighted mean.

    For ``iterations`` rounds (1 in the paper):

        u_{n,t} ~ N(0, σ_n²)                                white noise [N, H, A]
        filter="noise" (the paper's text):
            n_{n,t} = β u_{n,t} + (1-β) n_{n,t-1},  n_{n,-1}=0;   a_n = clip(μ + n_n)
        filter="actions" (the reference code, google-research/pddm ``mppi.py``):
            a_{n,t} = β (μ_t + u_{n,t}) + (1-β) a_{n,t-1},  a_{n,-1} = the action executed last
            (``init_mean`` after :meth:`reset`);             a_n = clip(a_n)
        R_n     = -cost_n
        w_n     = e^{γ (R_n - max R)};   μ ← Σ_n w_n a_n / Σ_n w_n

    σ_n = σ except for the last ``low_noise_fraction`` of the samples, which get
    ``low_noise_scale``·σ (the reference code keeps 10 % at 0.3 σ). Returns ``μ_0``; warm
    start shifts ``μ`` one step and repeats the last action.

    After each plan ``last_ess`` (effective sample size of the weights, (Σw)²/Σw², in [1, N])
    and ``last_shift`` (RMS over [H, A] of the new mean minus the mean sampled about) are set,
    and appended to ``history`` (cleared by :meth:`reset`): a near-uniform weighting (ESS ≈ N)
    with a tiny shift is the "too soft, minimal movement" case of the thesis.

    Args (beyond :class:`Planner`):
        gamma: reward-weighting sharpness γ (large → best sample only, 0 → plain mean).
        beta: filter coefficient β in (0, 1] (1 → no filtering).
        sigma: std of ``u``, scalar or ``[A]``; default a quarter of the action range.
        init_mean: first mean action ``[A]`` (default: middle of the bounds).
        filter: ``"noise"`` or ``"actions"`` (above).
        low_noise_fraction, low_noise_scale: the low-noise share of the samples (above).
        reachable: the actuator's reachable set, ``prev [N, A] -> (lo, hi)`` (each ``[N, A]``):
            the actions it can execute one step after ``prev``. Given, every sampled sequence
            is projected into it step by step from the action executed last
            (``a_{n,t} ← clip(a_{n,t}, lo(a_{n,t-1}), hi(a_{n,t-1}))``, after the filter), so
            no candidate is scored with a jump a rate-limited actuator would cut; the
            weighted mean of reachable sequences stays reachable (the set is a box per step).
    """

    name = "pddm"

    def __init__(self, *args, gamma: float = 20.0, beta: float = 0.7,
                 sigma: float | Sequence[float] | None = None,
                 init_mean: Sequence[float] | None = None, filter: str = "noise",
                 low_noise_fraction: float = 0.0, low_noise_scale: float = 0.3,
                 reachable: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]] | None = None,
                 **kwargs) -> None:
        if not 0.0 < beta <= 1.0:
            raise ValueError(f"beta must be in (0, 1], got {beta}")
        if filter not in ("noise", "actions"):
            raise ValueError(f"filter must be 'noise' or 'actions', got {filter!r}")
        if not 0.0 <= low_noise_fraction <= 1.0:
            raise ValueError(f"low_noise_fraction must be in [0, 1], got {low_noise_fraction}")
        if not low_noise_scale >= 0.0:
            raise ValueError(f"low_noise_scale must be >= 0, got {low_noise_scale}")
        self.gamma = float(gamma)
        self.beta = float(beta)
        self.filter = filter
        self.low_noise_fraction = float(low_noise_fraction)
        self.low_noise_scale = float(low_noise_scale)
        self.reachable = reachable
        self._sigma_arg = sigma
        self._init_mean = init_mean
        super().__init__(*args, **kwargs)

    def _reset_distribution(self) -> None:
        rng = self.action_high - self.action_low
        self.sigma = (rng / 4) if self._sigma_arg is None else _vec(self._sigma_arg, self.action_dim, "sigma")
        init = (self.action_low + self.action_high) / 2 if self._init_mean is None else _vec(
            self._init_mean, self.action_dim, "init_mean")
        self.mean = init.expand(self.horizon, -1).clone()
        #: the action executed last (the anchor of filter="actions"); the first mean after a reset
        self.previous = self.mean[0].clone()
        self.last_ess: float | None = None
        self.last_shift: float | None = None
        self.history: list[tuple[float, float]] = []

    def config(self) -> dict:
        return {**super().config(), "gamma": self.gamma, "beta": self.beta, "sigma": self.sigma.tolist(),
                "filter": self.filter, "low_noise_fraction": self.low_noise_fraction,
                "low_noise_scale": self.low_noise_scale}

    def sample(self, mean: torch.Tensor) -> torch.Tensor:
        """Candidate sequences ``[N, H, A]`` around ``mean`` (a reused buffer)."""
        N, H, A = self.samples, self.horizon, self.action_dim
        u = self._buffer("noise", (N, H, A))
        torch.randn(u.shape, generator=self.generator, out=u)
        u.mul_(self.sigma)
        n_low = int(self.low_noise_fraction * N)
        if n_low:
            u[N - n_low:].mul_(self.low_noise_scale)
        actions = self._buffer("actions", (N, H, A))
        b = self.beta
        if self.filter == "actions":  # smooth the actions, from the one executed last
            prev = self.previous.expand(N, A)
            for t in range(H):
                prev = b * (mean[t] + u[:, t]) + (1.0 - b) * prev
                actions[:, t] = prev
            return self._reach(self._clip(actions))
        # smooth the noise, written straight into the action buffer, then shifted by the mean
        prev = torch.zeros(N, A)
        for t in range(H):
            prev = b * u[:, t] + (1.0 - b) * prev
            actions[:, t] = prev
        return self._reach(self._clip(actions.add_(mean)))

    def _reach(self, actions: torch.Tensor) -> torch.Tensor:
        """``actions`` projected into :attr:`reachable` step by step from the action executed last."""
        if self.reachable is None:
            return actions
        prev = self.previous.expand(actions.shape[0], -1)
        for t in range(actions.shape[1]):
            lo, hi = self.reachable(prev)
            actions[:, t] = torch.minimum(torch.maximum(actions[:, t], lo), hi)
            prev = actions[:, t]
        return actions

    def _plan(self, dynamics, cost, s0):
        mean = self.mean
        for _ in range(self.iterations):
            actions = self.sample(mean)
            total, _ = self._evaluate(dynamics, cost, s0, actions)
            w = torch.exp(self.gamma * (total.min() - total))  # e^{γ (R - max R)}, R = -cost
            new = torch.einsum("n,nha->ha", w, actions) / w.sum()
            self.last_ess = float(w.sum() ** 2 / (w * w).sum())
            self.last_shift = float((new - mean).pow(2).mean().sqrt())
            self.history.append((self.last_ess, self.last_shift))
            mean = new
        return self._clip(mean.clone())

    def _warm_start(self, plan, k):
        self.previous = self._step(plan, k)
        self.mean = self._after(plan, k)


@dataclass(frozen=True)
class PddmConfig:
    """A PDDM planner and the size of the ensemble it plans through, in one place.

    ``planner()`` builds the :class:`PDDM`; ``model_kwargs()`` are the
    ``hilstack.learning.dynamics.EnsembleDynamics`` arguments (``state_dim, action_dim, ensemble,
    hidden``). Actions are normalized to ``[action_low, action_high]`` (unitless; the hand
    maps [-1, 1] to each joint's range). ``sigma=None`` keeps PDDM's default (a quarter of
    the action range).
    """

    horizon: int
    samples: int
    gamma: float
    beta: float
    ensemble: int
    hidden: tuple[int, ...]
    state_dim: int
    action_dim: int
    sigma: float | None = None
    action_low: float = -1.0
    action_high: float = 1.0
    #: "noise" (the paper's text) or "actions" (the reference code): see :class:`PDDM`
    filter: str = "noise"
    low_noise_fraction: float = 0.0
    low_noise_scale: float = 0.3

    def planner(self, seed: int | None = 0, init_mean: Sequence[float] | None = None,
                reachable: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]] | None = None) -> PDDM:
        """The planner; ``init_mean``: its first mean action (default the middle of the bounds);
        ``reachable``: the actuator's reachable set (:class:`PDDM`)."""
        return PDDM(self.action_low, self.action_high, horizon=self.horizon, samples=self.samples,
                    gamma=self.gamma, beta=self.beta, sigma=self.sigma, action_dim=self.action_dim,
                    seed=seed, init_mean=init_mean, filter=self.filter,
                    low_noise_fraction=self.low_noise_fraction, low_noise_scale=self.low_noise_scale,
                    reachable=reachable)

    def model_kwargs(self) -> dict:
        return {"state_dim": self.state_dim, "action_dim": self.action_dim,
                "ensemble": self.ensemble, "hidden": self.hidden}


#: PDDM on the Shadow Hand Baoding balls: the thesis' sizes (H=7, K=700, γ=20, an ensemble of
#: 3 ReLU MLPs of 2x500; the public reference code used 2x250) with the reference code's
#: sampler (google-research/pddm: the actions filtered from the one executed last, β=0.6,
#: noise 0.9 about the hold pose, 10 % of the samples at 0.3 of it) on the model's state of
#: learning/baoding.py (``BaodingFeatures``: 24 joint angles + 2 balls x (position, velocity)
#: = 36) and the hand's 20 position targets. The single definition used by ``hil bench
#: plan`` (its ``baoding`` entry) and by ``hil demo baoding`` (learning/baoding.py).
BAODING_PDDM = PddmConfig(horizon=7, samples=700, gamma=20.0, beta=0.6, ensemble=3,
                          hidden=(500, 500), state_dim=36, action_dim=20, sigma=0.9, filter="actions",
                          low_noise_fraction=0.1)
