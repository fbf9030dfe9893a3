"""Grounding a source simulator to a target system by an action transformer π_g(ã | s, a).

* GAT (Hanna & Stone): π_g(s, a) = g_src(s, f_tgt(s, a)), an inverse source model (which
  action takes s to s' in the source) composed with a forward target model (where the
  target goes from s under a). Both are small MLPs fitted by regression (``fit_mlp``);
  optional action smoothing ã = α·π_g(s, a) + (1 − α)·a (Hanna & Stone's α).
* GARAT (Desai et al.): π_g is a stochastic policy trained with PPO
  (stable-baselines3) in the source simulator on the reward −log D(s, a, s'), where D is a
  GAIfO-style discriminator giving the probability that a transition (s, a, s') came from
  the grounded source rather than from the target. D is updated once per π_g update
  (after each PPO rollout, ``disc_steps`` minibatch steps on that rollout against target
  data).

Everything here is generic over a source step function ``step(s, a) -> s'`` that can start
from any state (MuJoCo ``set_state``), so the per-step transition error of a grounding is
measured on held-out target transitions: ‖step(s, π_g(s, a)) − s'_target‖.

Units are the environment's (InvertedPendulum: cart position m, pole angle rad, their rates;
force command in the env's action units).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from hilstack.learning.datasets import Transitions
from hilstack.learning.early_stopping import EarlyStopping, due

StepFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


class Mlp(nn.Module):
    """y = MLP((x − μ)/σ)·σ_y + μ_y, normalisation from the training data."""

    def __init__(self, x: np.ndarray, y: np.ndarray, width: int, layers: int):
        super().__init__()
        mods: list[nn.Module] = []
        d = x.shape[1]
        for _ in range(layers):
            mods += [nn.Linear(d, width), nn.SiLU()]
            d = width
        mods.append(nn.Linear(d, y.shape[1]))
        self.net = nn.Sequential(*mods)
        for name, v in (("xm", x.mean(0)), ("xs", x.std(0) + 1e-6), ("ym", y.mean(0)), ("ys", y.std(0) + 1e-6)):
            self.register_buffer(name, torch.as_tensor(v, dtype=torch.float32))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net((x - self.xm) / self.xs) * self.ys + self.ym

    @torch.no_grad()
    def __call__(self, x: np.ndarray) -> np.ndarray:  # type: ignore[override]
        return self.forward(torch.as_tensor(np.asarray(x, np.float32))).numpy().astype(np.float64)


def fit_mlp(x: np.ndarray, y: np.ndarray, width: int = 64, layers: int = 2, steps: int = 2000,
            lr: float = 3e-3, batch: int = 256, seed: int = 0, val_frac: float = 0.0) -> Mlp:
    """Least-squares MLP regression (Adam, cosine-decayed learning rate). With ``val_frac`` > 0
    that share of the samples (random) is held out and the weights with the lowest held-out
    error (checked every ``steps // 20`` steps) are kept: early stopping."""
    if not 0.0 <= val_frac < 1.0:
        raise ValueError(f"val_frac must be in [0, 1), got {val_frac}")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n_val = int(round(val_frac * len(x)))
    if n_val > 0:
        idx = rng.permutation(len(x))
        tr, va = idx[n_val:], idx[:n_val]
    else:  # no draw: the same minibatches as without early stopping
        tr, va = np.arange(len(x)), np.arange(0)
    m = Mlp(x[tr], y[tr], width, layers)
    xt, yt = torch.as_tensor(x[tr], dtype=torch.float32), torch.as_tensor(y[tr], dtype=torch.float32)
    xv, yv = torch.as_tensor(x[va], dtype=torch.float32), torch.as_tensor(y[va], dtype=torch.float32)
    opt = torch.optim.Adam(m.net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    every, es = max(1, steps // 20), EarlyStopping(m, patience=None)  # keeps the best, never stops
    for k in range(steps):
        i = rng.integers(0, len(xt), min(batch, len(xt)))
        loss = (((m.forward(xt[i]) - yt[i]) / m.ys) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if len(va) and due(k, steps, every):
            with torch.no_grad():
                es.update(float((((m.forward(xv) - yv) / m.ys) ** 2).mean()))
    es.restore()
    return m


class Gat:
    """GAT's action transformer: inverse source model ∘ forward target model."""

    def __init__(self, source: Transitions, target: Transitions, a_low: np.ndarray, a_high: np.ndarray,
                 width: int = 64, layers: int = 2, steps: int = 2000, seed: int = 0, lr: float = 3e-3,
                 alpha: float = 1.0, val_frac: float = 0.0):
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"GAT smoothing alpha must be in [0, 1], got {alpha}")
        self.alpha = alpha  # Hanna & Stone's action smoothing: ã = α·g(s, f(s, a)) + (1 − α)·a
        # forward target model: Δs = f(s, a); inverse source model: a = g(s, Δs)
        # (val_frac: early stopping of both on a held-out share of their data)
        source, target = source.finite(), target.finite()
        self.fwd = fit_mlp(np.hstack([target.states, target.actions]), target.deltas, width, layers, steps, lr,
                           seed=seed, val_frac=val_frac)
        self.inv = fit_mlp(np.hstack([source.states, source.deltas]), source.actions, width, layers, steps, lr,
                           seed=seed, val_frac=val_frac)
        self.a_low, self.a_high = np.asarray(a_low, float), np.asarray(a_high, float)

    def __call__(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        s, a = np.atleast_2d(s), np.atleast_2d(a)
        ds_target = self.fwd(np.hstack([s, a]))
        at = self.alpha * self.inv(np.hstack([s, ds_target])) + (1.0 - self.alpha) * a
        return np.clip(at, self.a_low, self.a_high)


def transition_error(step: StepFn, data: Transitions, transform: Callable | None = None) -> float:
    """Mean ‖step(s, π_g(s, a)) − s'‖ over ``data`` (π_g = identity when ``transform`` is None)."""
    errs = []
    for s, a, s1 in zip(data.states, data.actions, data.next_states, strict=True):
        at = a if transform is None else np.asarray(transform(s[None], a[None]))[0]
        errs.append(np.linalg.norm(step(s, at) - s1))
    return float(np.mean(errs))


class Discriminator(nn.Module):
    """Logit of "this (s, a, s') came from the grounded source" (GAIfO-style, with the action)."""

    def __init__(self, target: Transitions, width: int = 64):
        super().__init__()
        x = self.inputs(target)
        self.register_buffer("xm", torch.as_tensor(x.mean(0), dtype=torch.float32))
        self.register_buffer("xs", torch.as_tensor(x.std(0) + 1e-6, dtype=torch.float32))
        self.net = nn.Sequential(nn.Linear(x.shape[1], width), nn.Tanh(), nn.Linear(width, width), nn.Tanh(),
                                 nn.Linear(width, 1))

    @staticmethod
    def inputs(t: Transitions) -> np.ndarray:
        return np.hstack([t.states, t.actions, t.next_states - t.states]).astype(np.float32)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net((x - self.xm) / self.xs)

    @torch.no_grad()
    def reward(self, t: Transitions) -> np.ndarray:
        """−log D(s, a, s') = softplus(−logit): high where the transition looks like the target's."""
        return nn.functional.softplus(-self.forward(torch.as_tensor(self.inputs(t)))).numpy()[:, 0]


def discriminator_update(disc: Discriminator, opt: torch.optim.Optimizer, grounded: Transitions,
                         target: Transitions, steps: int, rng: np.random.Generator, batch: int = 256,
                         label_smoothing: float = 0.0, grad_penalty: float = 0.0) -> float:
    """``steps`` minibatch steps of binary cross-entropy: grounded source 1, target 0.

    ``label_smoothing`` ε: labels 1 − ε and ε instead of 1 and 0. ``grad_penalty`` λ: adds
    λ·E‖∇_x logit‖² on the target samples (the zero-centred R1 penalty, in the normalised
    input units), which keeps D smooth so that its reward stays informative."""
    if not 0.0 <= label_smoothing < 0.5:
        raise ValueError(f"label_smoothing must be in [0, 0.5), got {label_smoothing}")
    if grad_penalty < 0:
        raise ValueError(f"grad_penalty must be >= 0, got {grad_penalty}")
    bce = nn.functional.binary_cross_entropy_with_logits
    xg, xt = torch.as_tensor(disc.inputs(grounded)), torch.as_tensor(disc.inputs(target))
    loss = torch.zeros(())
    for _ in range(steps):
        ig = rng.integers(0, len(xg), min(batch, len(xg)))
        it = rng.integers(0, len(xt), min(batch, len(xt)))
        xti = xt[it].clone().requires_grad_(grad_penalty > 0)
        lt = disc(xti)
        loss = (bce(disc(xg[ig]), torch.full((len(ig), 1), 1.0 - label_smoothing))
                + bce(lt, torch.full((len(it), 1), label_smoothing)))
        if grad_penalty > 0:
            (g,) = torch.autograd.grad(lt.sum(), xti, create_graph=True)
            loss = loss + grad_penalty * ((g * disc.xs) ** 2).sum(1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(loss.detach())


class GroundingEnv(gym.Env):
    """The source simulator seen by π_g: observation (s, a) with a from the agent's policy,
    action δ ∈ [-1, 1]^m, ã = clip(a + δ·(high − low)/2), reward −log D(s, a, s').

    ``reset_state(rng)`` draws a start state, ``agent(s, rng)`` the agent's (noisy) action,
    ``done(s)`` ends an episode (the same rule as in the target data), ``max_steps`` truncates.
    Transitions are kept in ``buffer`` for the discriminator update."""

    def __init__(self, step: StepFn, reset_state: Callable, agent: Callable, done: Callable[[np.ndarray], bool],
                 disc: Discriminator, a_low: np.ndarray, a_high: np.ndarray, n_state: int, max_steps: int,
                 seed: int = 0):
        super().__init__()
        self._step, self._reset_state, self._agent, self._done = step, reset_state, agent, done
        self.disc = disc
        self.a_low, self.a_high = np.asarray(a_low, float), np.asarray(a_high, float)
        m = len(self.a_low)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (n_state + m,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (m,), np.float32)
        self.max_steps = max_steps
        self.rng = np.random.default_rng(seed)
        self.buffer: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._s = self._a = None
        self._t = 0

    def transform(self, a: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return np.clip(a + np.clip(delta, -1, 1) * 0.5 * (self.a_high - self.a_low), self.a_low, self.a_high)

    def _obs(self) -> np.ndarray:
        return np.concatenate([self._s, self._a]).astype(np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self._s = np.asarray(self._reset_state(self.rng), float)
        self._a = np.asarray(self._agent(self._s, self.rng), float)
        self._t = 0
        return self._obs(), {}

    def step(self, action):
        s, a = self._s, self._a
        s1 = np.asarray(self._step(s, self.transform(a, np.asarray(action, float))), float)
        self.buffer.append((s, a, s1))
        r = float(self.disc.reward(Transitions(s[None], a[None], s1[None]))[0])
        self._t += 1
        self._s = s1
        self._a = np.asarray(self._agent(s1, self.rng), float)
        return self._obs(), r, bool(self._done(s1)), self._t >= self.max_steps, {}


@dataclass(frozen=True)
class GaratConfig:
    """PPO and discriminator settings (the paper gives none; ours are documented in docs/transfer.md)."""

    total_timesteps: int = 49152
    n_steps: int = 1024  # PPO rollout length = transitions per discriminator update
    batch_size: int = 128
    n_epochs: int = 5
    learning_rate: float = 3e-4
    gamma: float = 0.5  # a short horizon: the reward judges single transitions (0.9 grounded worse, docs)
    log_std_init: float = -1.5  # start near the identity transform (ã ≈ a)
    disc_steps: int = 50  # minibatch steps of the once-per-update discriminator update
    disc_lr: float = 1e-3
    width: int = 64  # π_g's MLP (2 hidden layers) and, unless disc_width is set, D's
    disc_width: int | None = None
    disc_grad_penalty: float = 0.0  # λ of the R1 gradient penalty on target samples (0: none)
    disc_label_smoothing: float = 0.0
    ent_coef: float = 0.0  # PPO's entropy bonus
    #: checkpoint selection: hold out this share of the TARGET TRAINING transitions (random; D
    #: never sees them) and keep the π_g with the lowest per-step error on them, checked every
    #: ``select_every`` discriminator updates (GARAT's analogue of GAT's early stopping; 0: last π_g)
    select_frac: float = 0.0
    select_every: int = 4
    seed: int = 0


class _DiscCallback:
    """Built lazily so that importing this module does not import stable-baselines3."""

    @staticmethod
    def make(env: GroundingEnv, target: Transitions, cfg: GaratConfig, step: StepFn | None = None,
             held_out: Transitions | None = None):
        from stable_baselines3.common.callbacks import BaseCallback

        class DiscUpdate(BaseCallback):
            def __init__(self):
                super().__init__()
                self.opt = torch.optim.Adam(env.disc.parameters(), lr=cfg.disc_lr)
                self.rng = np.random.default_rng(cfg.seed)
                self.updates = 0
                self.select_errors: list[tuple[int, float]] = []  # (π_g updates so far, held-out error)
                self.best: tuple[float, int, dict] | None = None

            def _on_step(self) -> bool:
                return True

            def _on_rollout_end(self) -> None:  # once per π_g update
                s, a, s1 = (np.asarray(v) for v in zip(*env.buffer, strict=True))
                env.buffer.clear()
                discriminator_update(env.disc, self.opt, Transitions(s, a, s1), target, cfg.disc_steps, self.rng,
                                     label_smoothing=cfg.disc_label_smoothing, grad_penalty=cfg.disc_grad_penalty)
                self.updates += 1
                # the π_g about to be updated is the one trained by ``updates − 1`` PPO updates
                if held_out is not None and (self.updates - 1) % cfg.select_every == 0:
                    self.check(self.updates - 1)

            def check(self, n_updates: int) -> None:
                err = transition_error(step, held_out, Garat(env, self.model, n_updates))
                self.select_errors.append((n_updates, err))
                if self.best is None or err < self.best[0]:
                    state = {k: v.detach().clone() for k, v in self.model.policy.state_dict().items()}
                    self.best = (err, n_updates, state)

        return DiscUpdate()


class Garat:
    """GARAT's action transformer: the deterministic (mean) action of the trained PPO policy."""

    def __init__(self, env: GroundingEnv, model, disc_updates: int, selected_update: int | None = None,
                 select_errors: list[tuple[int, float]] | None = None):
        self.env, self.model, self.disc_updates = env, model, disc_updates
        self.selected_update = selected_update  # PPO updates of the kept π_g (None: no selection, the last)
        self.select_errors = select_errors or []

    def __call__(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        s, a = np.atleast_2d(s), np.atleast_2d(a)
        delta, _ = self.model.predict(np.hstack([s, a]).astype(np.float32), deterministic=True)
        return self.env.transform(a, delta)


def train_garat(step: StepFn, target: Transitions, reset_state: Callable, agent: Callable,
                done: Callable[[np.ndarray], bool], a_low, a_high, max_steps: int, cfg: GaratConfig) -> Garat:
    """Train π_g with PPO against a discriminator updated once per PPO update.

    With ``cfg.select_frac`` > 0 a random share of ``target`` is held out (D trains on the
    rest) and the π_g with the lowest per-step error on it is returned."""
    from stable_baselines3 import PPO

    if not 0.0 <= cfg.select_frac < 1.0:
        raise ValueError(f"select_frac must be in [0, 1), got {cfg.select_frac}")
    if cfg.select_every < 1:
        raise ValueError(f"select_every must be >= 1, got {cfg.select_every}")
    torch.manual_seed(cfg.seed)
    target = target.finite()
    held_out = None
    n_sel = int(round(cfg.select_frac * len(target)))
    if n_sel > 0:
        idx = np.random.default_rng(cfg.seed + 7919).permutation(len(target))
        held_out, target = target.subset(idx[:n_sel]), target.subset(idx[n_sel:])
    disc = Discriminator(target, cfg.disc_width or cfg.width)
    env = GroundingEnv(step, reset_state, agent, done, disc, a_low, a_high, target.states.shape[1], max_steps, cfg.seed)
    cb = _DiscCallback.make(env, target, cfg, step, held_out)
    model = PPO("MlpPolicy", env, n_steps=cfg.n_steps, batch_size=cfg.batch_size, n_epochs=cfg.n_epochs,
                learning_rate=cfg.learning_rate, gamma=cfg.gamma, ent_coef=cfg.ent_coef, seed=cfg.seed, device="cpu",
                verbose=0, policy_kwargs={"log_std_init": cfg.log_std_init, "net_arch": [cfg.width, cfg.width]})
    model.learn(cfg.total_timesteps, callback=cb)
    if held_out is None:
        return Garat(env, model, cb.updates)
    cb.check(cb.updates)  # the final π_g too
    _, best_update, state = cb.best
    model.policy.load_state_dict(state)
    return Garat(env, model, cb.updates, selected_update=best_update, select_errors=cb.select_errors)


def best_action(step: StepFn, s: np.ndarray, s1: np.ndarray, a_low: float, a_high: float, grid: int = 61,
                iters: int = 40) -> tuple[float, float]:
    """(ã*, error) minimising ‖step(s, ã) − s'‖ over ã in [a_low, a_high] for a 1-D action: the
    best grid point (the error need not be unimodal over the whole range), then SciPy's bounded
    Brent search (``minimize_scalar``, at most ``iters`` evaluations) between its two neighbours."""
    from scipy.optimize import minimize_scalar

    if grid < 2:
        raise ValueError(f"grid needs at least 2 points, got {grid}")

    def err(x: float) -> float:
        return float(np.linalg.norm(step(s, np.array([x])) - s1))

    xs = np.linspace(a_low, a_high, grid)
    es = np.array([err(x) for x in xs])
    k = int(np.argmin(es))
    lo, hi = float(xs[max(k - 1, 0)]), float(xs[min(k + 1, grid - 1)])
    r = minimize_scalar(err, bounds=(lo, hi), method="bounded", options={"maxiter": iters, "xatol": 1e-9})
    if float(r.fun) < float(es[k]):
        return float(r.x), float(r.fun)
    return float(xs[k]), float(es[k])


def floor_error(step: StepFn, data: Transitions, a_low, a_high, grid: int = 61, iters: int = 40) -> float:
    """The floor of the per-step transition error: mean over ``data`` of min over ã of
    ‖step(s, ã) − s'‖ (1-D action; ``best_action`` per transition). No action transform, of
    any form, can have a lower mean error on ``data``."""
    if data.actions.shape[1] != 1:
        raise ValueError(f"floor_error searches a 1-D action, got {data.actions.shape[1]}-D")
    lo, hi = float(np.ravel(a_low)[0]), float(np.ravel(a_high)[0])
    return float(np.mean([best_action(step, s, s1, lo, hi, grid, iters)[1] for s, s1 in zip(data.states, data.next_states,
                                                                                             strict=True)]))
