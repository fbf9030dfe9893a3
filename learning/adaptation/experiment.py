"""The adaptation experiment behind `hil demo adaptation` (thesis ch. 5-6 on the sim VelociRoACH).

1. Random data on the training terrains under conditions sampled from the presets'
   training range (``configs/perturbations/velociroach.yaml``).
2. Train the plain model (MB, MB+DE), meta-train GrBAL (θ*, ψ) and ReBAL (GRU); MOLe uses
   GrBAL's θ* and ψ as its prior. Checkpoints go to ``<out>/checkpoints``.
3. Per test perturbation (and the held-out terrain): MB, MB+DE, GrBAL, ReBAL and MOLe with
   the same planner on the same paths, scored with the roach evaluation's completion-aware
   metrics (``hilstack.control.costs.evaluate_path_following``, ``summarize_paths``), plus each
   method's online prediction error on the next K transitions.
4. ``k_step_error_before_after``: GrBAL's loss on the next K transitions before and after
   its update, on random rollouts under each perturbation (thesis Figs 5.4, 5.5).
5. Switching: normal and disabled-leg conditions alternate every N steps on one long
   straight path; MOLe against k-shot (GrBAL from θ* each step) and continued adaptation
   (gradient steps that continue from the previous step's parameters, from θ*).

The planner runs in this process on the lockstep MuJoCo sim (no bus) for speed; the
adaptation node (``hil/<rig>/model/update``) runs the same adapters on a live rig.
"""

from __future__ import annotations

import collections
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from hilstack.configs.presets import Presets
from hilstack.control.costs import PathCost, evaluate_path_following, summarize_paths
from hilstack.control.paths import fillet, make_path, path_length, straight
from hilstack.control.policies import SafeRandomPolicy
from hilstack.control.policy_api import Resettable
from hilstack.drivers.registry import make_backend
from hilstack.learning.adaptation import grbal, rebal
from hilstack.learning.adaptation.base import Adapter
from hilstack.learning.adaptation.baselines import MbAdapter, MbDeAdapter
from hilstack.learning.adaptation.grbal import GrbalAdapter, segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.mole import MoleAdapter
from hilstack.learning.adaptation.rebal import ContextEncoder, RebalAdapter
from hilstack.learning.adaptation.training import fit_plain
from hilstack.learning.datasets import Episode, Transitions, split_episodes
from hilstack.learning.experiments import mean_std
from hilstack.learning.mbrl import MbrlConfig, PathEnd, _jsonable, make_planner, path_start_pose
from hilstack.tasks.perturbations import (
    PerturbationPresets,
    PerturbationSettings,
    load_presets,
)

METHODS = ("mb", "mb_de", "grbal", "rebal", "mole", "oracle")
#: random shooting's speed along the paths on the sim roach (m/s; issue 24, measured by review in the
#: real sim): the time limits' speed keeps headroom below it
RANDOM_SHOOTING_SPEED_MPS = 0.19
SWITCHING_METHODS = ("mole", "k_shot", "continued")


#: the presets' step-size multipliers (:func:`tune_rates`): x0 is no adaptation (MB+DE at x0 is
#: MB; GrBAL, MOLe and continued adaptation at x0 plan with θ* unchanged), so every adaptive
#: method can fall back to it; ×0.25 / ×1 / ×4 until issue 24's fifth session, where ×0.25
#: (the lowest) won nearly every time
RATE_GRID = (0.0, 0.0625, 0.125, 0.25, 1.0, 4.0)

#: the data and training sizes of the quick and full presets: 8 min of random robot time per
#: training terrain (12 conditions x 8 rollouts x 5 s, half of the conditions unperturbed;
#: the thesis: ~30 min, terrains only; 15 rollouts before issue 24's fourth session, cut with
#: the 10 starts per condition so that --quick fits 20 min of 2 cores), 10 % of the rollouts
#: held out for early stopping of MB, GrBAL and ReBAL; the oracle gets 50 rollouts (4.2 min)
#: of its one condition; paths at scale 0.5 (about 1 m), 5 starts each. GrBAL: its
#: inner gradient's norm capped at the median of the training windows' (``grbal_clip_quantile``),
#: θ's meta learning rate 1e-4 (ψ's 1e-2): the open-loop screen in docs/adaptation.md, "Why one
#: GrBAL step ...". docs/adaptation.md, "Sizes".
_SCALED: dict[str, Any] = dict(
    conditions_per_terrain=12, unperturbed_fraction=0.5, rollouts_per_condition=8, hidden=(256, 256, 256),
    plain_epochs=200, plain_batch=512, plain_patience=5, meta_steps=1500, rebal_steps=1500,
    meta_eval_every=50, meta_patience=4, oracle_rollouts=50, paths=("straight", "left"),
    path_scale=0.5, before_after_rollouts=10, switching_every_steps=50, switching_segments=4,
    grbal_clip_quantile=0.5, grbal_meta_lr=1e-4, starts_per_path=5, rate_grid=RATE_GRID, tune_rollouts=4)


@dataclass
class AdaptationConfig(Presets):
    """Sizes of one run. ``AdaptationConfig.from_preset("quick" | "full" | "tiny")`` are the demo's presets."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        # quick over 3 seeds (≈ 30-45 CPU-min, estimated; seed 0 is the quick run exactly): the
        # dataclass defaults (3 x 512, 3 paths, switching every 500 steps) take hours here
        "full": {**_SCALED, "seeds": (0, 1, 2)},
        "quick": {**_SCALED, "seeds": (0,)},
        # seconds: the CLI test (numbers meaningless); the last two run those code paths
        "tiny": dict(seeds=(0,), conditions_per_terrain=2, rollouts_per_condition=1, rollout_steps=12,
                     before_after_rollouts=1, hidden=(16, 16), M=4, K=4, plain_epochs=2, meta_steps=2, rebal_steps=2,
                     context_dim=4, samples=32, paths=("straight",), path_scale=0.2, time_limit_speed_mps=0.5,
                     switching_every_steps=4, switching_segments=2, grbal_clip_quantile=0.5,
                     train_leg_speed_scale=(0.8, 1.2), rate_grid=(0.5, 2.0), tune_rollouts=1),
    }

    presets: str = "velociroach"
    seeds: tuple[int, ...] = (0, 1, 2)
    # data: per training terrain, this many conditions, each with this many random rollouts
    # of rollout_steps at 10 Hz; a fraction of them unperturbed (the thesis' terrain-only data;
    # always at least the first), the others sampled from the presets' training range
    conditions_per_terrain: int = 12
    unperturbed_fraction: float = 0.0
    rollouts_per_condition: int = 8
    rollout_steps: int = 50
    before_after_rollouts: int = 6
    # model (thesis GrBAL: 3 x 512 ReLU, fixed variance)
    hidden: tuple[int, ...] = (512, 512, 512)
    M: int = 16
    K: int = 16
    plain_epochs: int = 40  # the maximum: early stopping on held-out rollouts (plain_patience)
    plain_batch: int = 256
    plain_patience: int = 8
    # a random val_fraction of the rollouts is held out: early stopping of MB (and the oracle),
    # GrBAL's meta-training and ReBAL (on their next-K loss every meta_eval_every steps)
    val_fraction: float = 0.1
    meta_eval_every: int = 50
    meta_patience: int = 6
    # the oracle's random rollouts per test condition (None: as many as the training set)
    oracle_rollouts: int | None = None
    meta_steps: int = 1000
    meta_batch: int = 16
    meta_lr: float = 1e-3
    grbal_meta_lr: float | None = None  # Adam's step for GrBAL's θ (None: meta_lr; ReBAL always uses meta_lr)
    psi_init: float = 0.01
    psi_lr: float | None = 1e-2  # Adam's step for ψ (None: meta_lr); docs/adaptation.md, "Why one step ..."
    # which parameters GrBAL adapts: "all", or "last" (the output layer's weight and bias)
    grbal_adapt: str = "last"
    # cap on the norm of GrBAL's inner gradient (meta-training and run time alike): this
    # quantile of the norms on the training segments' past M at the warm start (None: no cap);
    # docs/adaptation.md, "Why one GrBAL step ..."
    grbal_clip_quantile: float | None = None
    # meta-training only: each perturbed training condition also runs each drive side's crank
    # at a factor drawn uniformly from this range (params.sim.leg_speed_scale, a miscalibrated
    # drive side; None: nominal). No test condition changes it (configs/perturbations).
    train_leg_speed_scale: tuple[float, float] | None = None
    rebal_steps: int = 1000
    context_dim: int = 32
    de_lr: float = 0.01
    mole_lr: float = 0.01
    # planner and paths (random shooting as on the real roach)
    samples: int = 500
    horizon: int = 4
    speed: float = 0.5
    paths: tuple[str, ...] = ("straight", "left", "right")
    path_scale: float = 1.5
    # the time limit is the path's length at this speed: about half random shooting's speed
    # on the roach (RANDOM_SHOOTING_SPEED_MPS), so the limit does not decide completions (issue 24, item 3)
    time_limit_speed_mps: float = 0.1
    # starts per path (issue 24: >= 10 starts per condition): the first at the path's start
    # pose, the others offset sideways by up to start_offset_m and turned by up to
    # start_yaw_deg, drawn once per seed: every method meets the same starts
    starts_per_path: int = 1
    start_offset_m: float = 0.05
    start_yaw_deg: float = 15.0
    # weight (1/rad) of the cost's heading term, in the planner's cost and the evaluation
    # alike (control/costs.py: thesis f_h = 5). 0: the cost reads only the positions, which the
    # pose miscalibration (a rotated reported heading) leaves true; with 5 an accurate model
    # under the miscalibration parks (docs/adaptation.md, "The roach suite's design")
    heading_weight: float = 0.0
    # equal adaptation budgets (issue 24, item 4): every adaptive method's step size (MB+DE's
    # and continued adaptation's lr, GrBAL's ψ, MOLe's M-step lr) is scaled by the multiplier
    # of this grid with the lowest online next-K error on tune_rollouts held-out rollouts of
    # the *training* conditions (the same grid, data and criterion for every method); None: x1
    rate_grid: tuple[float, ...] | None = None
    tune_rollouts: int = 10
    # subsets (None: all): the test conditions run (in this order), and the methods run on them
    conditions: tuple[str, ...] | None = None
    methods: tuple[str, ...] | None = None
    # switching (None: the presets' every_steps / segments)
    switching_every_steps: int | None = None
    switching_segments: int | None = None
    threads: int = 1


# ---------------------------------------------------------------------------- the sim
class RoachSim:
    """The VelociRoACH MuJoCo backend on one terrain, driven through the driver contract."""

    def __init__(self, terrain: str, seed: int):
        self.sim = make_backend("velociroach", "sim", sim={"terrain": terrain, "seed": seed})
        self.sim.configure()
        self.sim.activate()
        spec = self.sim.spec
        self.state_names = list(spec.state.names)
        self.action_space = spec.action
        self.period_s = float(spec.period_s)
        self.max_step = spec.max_step_normalized()

    def start(self, pose: dict[str, float], settings: PerturbationSettings) -> np.ndarray:
        self.sim.apply_perturbations(settings)
        self.sim.reset(**pose)
        return self.sim.read().state.copy()

    def set_leg_speed_scale(self, left: float, right: float) -> None:
        """Each drive side's crank runs at this factor times its command (``params.sim.leg_speed_scale``)."""
        self.sim.sim = self.sim.sim.model_copy(update={"leg_speed_scale": (float(left), float(right))})

    def apply(self, settings: PerturbationSettings) -> None:
        self.sim.apply_perturbations(settings)

    def step(self, a_norm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply a normalized action; returns (the action actually applied, normalized; next state)."""
        applied = self.sim.write(self.action_space.denormalize(a_norm))
        self.sim.tick()
        return self.action_space.normalize(applied).astype(np.float32), self.sim.read().state.copy()

    def close(self) -> None:
        self.sim.deactivate()
        self.sim.cleanup()


def random_episodes(env: RoachSim, settings: PerturbationSettings, n: int, steps: int, seed: int,
                    name: str) -> list[Episode]:
    """``n`` random rollouts (the MBRL loop's safe random policy) under one condition."""
    pol = SafeRandomPolicy(env.state_names, 2, 3.0, hold_steps=6, forward_fraction=0.6, seed=seed)
    rng = np.random.default_rng([seed, 7])
    out = []
    for i in range(n):
        s = env.start({"x": 0.0, "y": 0.0, "yaw": float(rng.uniform(-np.pi, np.pi))}, settings)
        if isinstance(pol, Resettable):
            pol.reset()
        states, actions = [s], []
        for _ in range(steps):
            a, s = env.step(pol(s))
            states.append(s)
            actions.append(a)
        out.append(Episode(np.array(states), np.array(actions), name=f"{name}#{i}",
                           meta={"condition": settings.model_dump()}))
    return out


# ---------------------------------------------------------------------------- online error
class KStepError:
    """Each published model's error on the K transitions that follow its update.

    ``add(dyn)`` at every update; ``observe(s, a, s')`` at every transition scores it with
    the last K models. The error is the mean over channels of ``((ŝ' − s') / scale)²``
    (one-step predictions, the GrBAL objective), ``scale``: std of the training deltas."""

    def __init__(self, K: int, scale: np.ndarray):
        self.K = K
        self.scale = torch.as_tensor(scale, dtype=torch.float32)
        self.live: collections.deque = collections.deque()
        self.done: list[float] = []

    def add(self, dyn) -> None:
        self.live.append((dyn, []))

    def observe(self, s, a, n) -> None:
        s_t, a_t, n_t = (torch.as_tensor(x, dtype=torch.float32)[None] for x in (s, a, n))
        for dyn, errs in self.live:
            errs.append(float((((dyn(s_t, a_t) - n_t) / self.scale) ** 2).mean()))
        while self.live and len(self.live[0][1]) >= self.K:
            self.done.append(float(np.mean(self.live.popleft()[1])))

    def mean(self) -> float:
        vals = self.done + [float(np.mean(e)) for _, e in self.live if e]
        return float(np.mean(vals)) if vals else float("nan")


def drive(env: RoachSim, adapter: Adapter, planner, cost: PathCost, s: np.ndarray, steps: int, kerr: KStepError,
          stop_if: Callable[[np.ndarray], bool] | None = None, on_step: Callable[[int, Any], None] | None = None):
    """The control loop: observe → update → dynamics → plan → act, per step. Returns
    (states [T+1, S], timings {adapt_ms, plan_ms})."""
    adapter.reset()
    planner.reset()
    cost.reset()
    states = [s]
    prev = None
    t_adapt, t_plan = [], []
    for t in range(steps):
        t0 = time.perf_counter()
        if prev is not None:
            adapter.observe(*prev, s)
            kerr.observe(*prev, s)
        upd = adapter.update(state_stamp_ns=t)
        dyn = adapter.dynamics(upd)
        t1 = time.perf_counter()
        kerr.add(dyn)
        cost.observe(s)
        a = planner(dyn, cost, s)
        t2 = time.perf_counter()
        a_applied, s_next = env.step(a)
        prev = (s, a_applied)
        s = s_next
        states.append(s)
        t_adapt.append(t1 - t0)
        t_plan.append(t2 - t1)
        if on_step is not None:
            on_step(t, upd)
        if stop_if is not None and stop_if(s):
            break
    if prev is not None:
        kerr.observe(*prev, s)
    return np.array(states), {"adapt_ms_p50": 1e3 * float(np.median(t_adapt)), "plan_ms_p50": 1e3 * float(np.median(t_plan))}


# ---------------------------------------------------------------------------- the run
class Phases:
    """Wall-clock and CPU seconds (this process) summed per named phase."""

    def __init__(self) -> None:
        self.totals: dict[str, dict[str, float]] = {}

    def __call__(self, name: str):
        return _Phase(self, name)

    def add(self, name: str, wall: float, cpu: float) -> None:
        d = self.totals.setdefault(name, {"wall_s": 0.0, "cpu_s": 0.0})
        d["wall_s"] += wall
        d["cpu_s"] += cpu

    def line(self) -> str:
        return ", ".join(f"{k} {v['wall_s']:.0f}/{v['cpu_s']:.0f}" for k, v in self.totals.items())


class _Phase:
    def __init__(self, owner: Phases, name: str):
        self.owner, self.name = owner, name

    def __enter__(self):
        self.w, self.c = time.monotonic(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.monotonic() - self.w, time.process_time() - self.c
        self.owner.add(self.name, self.wall, self.cpu)
        return False


@dataclass
class Trained:
    plain: AdaptiveMLP
    meta: AdaptiveMLP
    psi: dict[str, torch.Tensor]
    rebal_model: AdaptiveMLP
    encoder: ContextEncoder
    delta_scale: np.ndarray
    history: dict[str, Any] = field(default_factory=dict)
    # the oracle of the condition being tested (an MB model trained on that condition's data)
    oracle: AdaptiveMLP | None = None
    adapt_params: list[str] | None = None  # GrBAL's adapted subset (None: all)
    clip: float | None = None  # GrBAL's inner-gradient norm cap (None: none)
    # each adaptive method's step-size multiplier (tune_rates; missing: 1)
    rates: dict[str, float] = field(default_factory=dict)

    def adapter(self, method: str, cfg: AdaptationConfig, rate: float | None = None) -> Adapter:
        """``method``'s adapter; ``rate``: its step-size multiplier (None: the tuned one, :func:`tune_rates`)."""
        g = float(self.rates.get(RATE_KEY.get(method, method), 1.0) if rate is None else rate)
        if method == "mb":
            return MbAdapter(self.plain, window=cfg.M)
        if method == "oracle":
            if self.oracle is None:
                raise ValueError("no oracle model trained for this condition")
            return MbAdapter(self.oracle, window=cfg.M)
        if method == "mb_de":
            return MbDeAdapter(self.plain, window=cfg.M, lr=cfg.de_lr * g)
        if method in ("grbal", "k_shot"):
            psi = self.psi if g == 1.0 else {k: v * g for k, v in self.psi.items()}
            return GrbalAdapter(self.meta, psi, window=cfg.M, adapt_params=self.adapt_params, clip=self.clip)
        if method == "rebal":
            return RebalAdapter(self.rebal_model, self.encoder, window=cfg.M)
        if method == "mole":
            return MoleAdapter(self.meta, self.psi, window=cfg.K, lr=cfg.mole_lr * g, alpha=1.0,
                               adapt_params=self.adapt_params, clip=self.clip)
        if method == "continued":
            return MbDeAdapter(self.meta, window=cfg.K, lr=cfg.mole_lr * g)
        raise ValueError(f"unknown method {method!r}")


#: the methods whose step size :func:`tune_rates` tunes, and whose tuned rate each method uses
#: (k-shot is GrBAL's step from θ* every step)
TUNED_METHODS = ("mb_de", "grbal", "mole", "continued")
RATE_KEY = {"k_shot": "grbal"}


def online_error(adapter: Adapter, episodes: list[Episode], K: int, scale: np.ndarray) -> float:
    """The adapter replayed over recorded rollouts as in :func:`drive` (observe → update →
    publish, per step): the mean error of every published model on the K transitions that
    followed it (:class:`KStepError`), averaged over the rollouts."""
    errs = []
    for ep in episodes:
        adapter.reset()
        kerr = KStepError(K, scale)
        for t in range(len(ep.actions)):
            s, a, n = ep.states[t], ep.actions[t], ep.states[t + 1]
            kerr.add(adapter.dynamics(adapter.update(state_stamp_ns=t)))
            kerr.observe(s, a, n)
            adapter.observe(s, a, n)
        errs.append(kerr.mean())
    return float(np.mean(errs))


def tune_rates(cfg: AdaptationConfig, tr: Trained, episodes: list[Episode],
               methods: tuple[str, ...] = TUNED_METHODS) -> dict[str, Any]:
    """Equal adaptation budgets (issue 24, item 4): each method's step-size multiplier from
    ``cfg.rate_grid``, the one with the lowest :func:`online_error` on ``episodes`` (held-out
    rollouts of the training conditions: never a test condition). The same grid, rollouts and
    criterion for every method. x0 (no adaptation) may be a grid point.

    Returns ``{method: {"rate": chosen, "errors": {rate: error}, "edge": "lower" | "upper" | None,
    "warning": str | None}}`` and sets ``tr.rates``. A choice on the grid's edge is reported as
    such (``edge`` and a one-line ``warning``): the optimum may lie beyond the grid, except at
    x0, below which there is nothing (the training conditions then ask for no adaptation)."""
    grid = tuple(float(g) for g in (cfg.rate_grid or (1.0,)))
    if not grid or not all(np.isfinite(g) and g >= 0 for g in grid) or len(set(grid)) != len(grid):
        raise ValueError(f"rate_grid must be distinct finite multipliers >= 0, got {grid}")
    out = {}
    for m in methods:
        errs = {g: online_error(tr.adapter(m, cfg, rate=g), episodes, cfg.K, tr.delta_scale) for g in grid}
        # ties: the multiplier nearest x1 (in log; x0 last)
        best = min(errs, key=lambda g: (errs[g] if np.isfinite(errs[g]) else np.inf,
                                        abs(np.log(g)) if g > 0 else np.inf))
        edge = rate_edge(grid, best)
        out[m] = {"rate": best, "errors": errs, "edge": edge, "warning": rate_edge_warning(m, best, edge)}
        tr.rates[m] = best
    return out


def rate_edge(grid: tuple[float, ...], rate: float) -> str | None:
    """``"lower"`` / ``"upper"`` when ``rate`` is the grid's lowest / highest point (None inside,
    or for a one-point grid, which tunes nothing)."""
    if len(grid) < 2:
        return None
    return "lower" if rate == min(grid) else "upper" if rate == max(grid) else None


def rate_edge_warning(method: str, rate: float, edge: str | None) -> str | None:
    """The one-line warning for a tuned step on the grid's edge (None inside the grid)."""
    if edge is None:
        return None
    if rate == 0.0:
        return (f"{method}: x0 (no adaptation) chosen, the grid's lower edge: no step of the grid lowered the "
                "online error on the training conditions")
    beyond = "below" if edge == "lower" else "above"
    return (f"{method}: x{rate:g} is the grid's {edge} edge: its best step may lie {beyond} the grid "
            "(extend rate_grid)")


def fit_mb(cfg: AdaptationConfig, model: AdaptiveMLP, tr_eps: list[Episode], va_eps: list[Episode],
           seed: int) -> dict[str, Any]:
    """The plain (MB) model trained to convergence: at most ``plain_epochs`` epochs, early
    stopping on the held-out rollouts ``va_eps`` (``split_episodes``). Returns the history."""
    h: dict[str, Any] = {}
    h["train"] = fit_plain(model, tr_eps, epochs=cfg.plain_epochs, batch_size=cfg.plain_batch, seed=seed,
                           val=va_eps or None, patience=cfg.plain_patience, history=h)
    return h


def meta_train_grbal(cfg: AdaptationConfig, plain: AdaptiveMLP, seg, vseg, seed: int,
                     clip_quantile: float | None | str = "cfg", theta_lr: float | None = None,
                     log: Callable[[str], None] | None = None):
    """GrBAL meta-trained from the plain model's weights (a copy; ``plain`` is left as it is).

    ``clip_quantile``: the inner gradient's norm cap as this quantile of the norms on the
    training segments' past M at the warm start (None: no cap; default ``cfg.grbal_clip_quantile``);
    ``theta_lr``: Adam's step for θ (default ``cfg.grbal_meta_lr``, or ``cfg.meta_lr``).
    Returns (θ* as a model, ψ, the cap, the adapted parameters' names, the history)."""
    q = cfg.grbal_clip_quantile if clip_quantile == "cfg" else clip_quantile
    if theta_lr is None:
        theta_lr = cfg.meta_lr if cfg.grbal_meta_lr is None else cfg.grbal_meta_lr
    if not (np.isfinite(theta_lr) and theta_lr >= 0):
        raise ValueError(f"GrBAL's θ meta learning rate must be finite and >= 0, got {theta_lr}")
    meta = AdaptiveMLP.from_checkpoint(plain.to_checkpoint())
    if cfg.grbal_adapt not in ("all", "last"):
        raise ValueError(f"grbal_adapt must be 'all' or 'last', got {cfg.grbal_adapt!r}")
    adapt_params = None if cfg.grbal_adapt == "all" else list(meta.params())[-2:]
    clip = None
    if q is not None:
        if not 0.0 < q <= 1.0:
            raise ValueError(f"grbal_clip_quantile must be in (0, 1] or None, got {q}")
        norms = grbal.gradient_norms(meta, meta.params(), seg, adapt_params)
        clip = float(np.quantile(norms, q))
        if log is not None:
            log(f"GrBAL inner-gradient cap: {clip:.4f} (quantile {q} of {len(norms)} training "
                f"windows; median {np.median(norms):.4f})")
    psi, h_meta = grbal.meta_train(meta, seg, steps=cfg.meta_steps, meta_batch=cfg.meta_batch, lr=theta_lr,
                                   psi_init=cfg.psi_init, psi_lr=cfg.psi_lr, seed=seed, adapt_params=adapt_params,
                                   val=vseg, eval_every=cfg.meta_eval_every, patience=cfg.meta_patience, clip=clip)
    return meta, psi, clip, adapt_params, h_meta


def train(cfg: AdaptationConfig, episodes: list[Episode], state_names: list[str], seed: int, ckpt_dir: Path,
          log: Callable[[str], None], phases: Phases | None = None) -> Trained:
    torch.manual_seed(seed)
    phases = phases or Phases()
    plain = AdaptiveMLP(state_names, 2, hidden=cfg.hidden, seed=seed)
    tr_eps, va_eps = split_episodes(episodes, cfg.val_fraction, seed)
    with phases("mb_training") as ph:
        h_plain = fit_mb(cfg, plain, tr_eps, va_eps, seed)
    bv = h_plain.get("best_val")
    log(f"plain model: {h_plain['epochs_run']} epochs (best {h_plain['best_epoch']}), train loss "
        f"{h_plain['train'][-1]:.4f}, held-out {bv if bv is None else round(bv, 4)} ({ph.wall:.0f} s, cpu {ph.cpu:.0f} s)")
    seg = segments(tr_eps, cfg.M, cfg.K, stride=2)
    vseg = segments(va_eps, cfg.M, cfg.K, stride=4) if va_eps else None
    with phases("grbal_meta_training") as ph:
        meta, psi, clip, adapt_params, h_meta = meta_train_grbal(cfg, plain, seg, vseg, seed, log=log)
    last = h_meta[-1]
    log(f"GrBAL meta-training: {last.get('best_step', last['step'])} steps kept of "
        f"{h_meta[-2]['step'] if 'best_step' in last else last['step']}, held-out next-K loss before/after "
        f"{last['before']:.4f}/{last['after']:.4f} ({ph.wall:.0f} s, cpu {ph.cpu:.0f} s)")
    # ReBAL starts as the plain model: the context's input columns start at zero
    rm = AdaptiveMLP(state_names, 2, hidden=cfg.hidden, seed=seed, context_dim=cfg.context_dim)
    sd = plain.state_dict()
    with torch.no_grad():
        for k, v in rm.state_dict().items():
            if k == "net.0.weight":
                v.zero_()
                v[:, :sd[k].shape[1]] = sd[k]
            else:
                v.copy_(sd[k])
    enc = ContextEncoder(rm, cfg.context_dim)
    with phases("rebal_training") as ph:
        h_rebal = rebal.meta_train(rm, enc, seg, steps=cfg.rebal_steps, lr=cfg.meta_lr, seed=seed, val=vseg,
                                   eval_every=cfg.meta_eval_every, patience=cfg.meta_patience)
    last = h_rebal[-1] if h_rebal else {}
    log(f"ReBAL training: {last.get('best_step', last.get('step'))} steps kept, held-out loss "
        f"{last.get('val_loss', float('nan')):.4f} ({ph.wall:.0f} s, cpu {ph.cpu:.0f} s)")
    s, _, n = Transitions.from_episodes(episodes).arrays()
    tr = Trained(plain, meta, psi, rm, enc, np.maximum((n - s).std(0), 1e-6),
                 {"plain": h_plain, "grbal": h_meta, "rebal": h_rebal}, adapt_params=adapt_params, clip=clip)
    for m in ("mb_de", "grbal", "rebal", "mole"):
        tr.adapter(m, cfg).save(ckpt_dir / f"seed{seed}_{m}.pt")
    return tr


def unperturbed_conditions(cfg: AdaptationConfig) -> set[int]:
    """Indices (per terrain) of the unperturbed training conditions: the first, and
    ``unperturbed_fraction`` of them spread evenly."""
    if not 0.0 <= cfg.unperturbed_fraction <= 1.0:
        raise ValueError(f"unperturbed_fraction must be in [0, 1], got {cfg.unperturbed_fraction}")
    n = cfg.conditions_per_terrain
    k = max(1, int(round(cfg.unperturbed_fraction * n)))
    return {int(i) for i in np.floor(np.arange(k) * n / k)}


def save_episodes(path: Path, episodes: list[Episode]) -> None:
    """The random rollouts as one ``.npz`` (``states [N, T+1, S]``, ``actions [N, T, A]``,
    ``names``, ``conditions`` as JSON): the meta-training data of a run is kept."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, states=np.stack([e.states for e in episodes]).astype(np.float32),
                        actions=np.stack([e.actions for e in episodes]).astype(np.float32),
                        names=np.array([e.name for e in episodes]),
                        conditions=np.array([json.dumps(e.meta.get("condition")) for e in episodes]))


def load_episodes(path: Path) -> list[Episode]:
    """The inverse of :func:`save_episodes`."""
    z = np.load(path)
    return [Episode(s, a, name=str(n), meta={"condition": json.loads(str(c))})
            for s, a, n, c in zip(z["states"], z["actions"], z["names"], z["conditions"], strict=True)]


def _conditions(p: PerturbationPresets) -> dict[str, tuple[str, PerturbationSettings]]:
    """Test name → (terrain, condition): ``normal`` (the first training terrain, unperturbed:
    the reference), each test condition, and the held-out terrain."""
    base = p.training_terrains[0]
    out = {"normal": (base, PerturbationSettings())}
    out.update({name: (base, s) for name, s in p.tests.items()})
    out[f"terrain_{p.heldout_terrain}"] = (p.heldout_terrain, PerturbationSettings())
    return out


def run_seed(cfg: AdaptationConfig, seed: int, out: Path, log: Callable[[str], None]) -> dict[str, Any]:
    p = load_presets(cfg.presets)
    rng = np.random.default_rng(seed)
    envs: dict[str, RoachSim] = {}

    def env(terrain: str) -> RoachSim:
        if terrain not in envs:
            envs[terrain] = RoachSim(terrain, seed)
        return envs[terrain]

    phases = Phases()
    episodes: list[Episode] = []
    scale_range = cfg.train_leg_speed_scale
    if scale_range is not None and not 0.0 < scale_range[0] <= scale_range[1] <= 2.0:
        raise ValueError(f"train_leg_speed_scale must be (low, high) with 0 < low <= high <= 2, got {scale_range}")
    scale_rng = np.random.default_rng([seed, 99])  # its own stream: the other draws stay as without it
    with phases("gathering") as ph:
        for terrain in p.training_terrains:
            clean = unperturbed_conditions(cfg)
            for c in range(cfg.conditions_per_terrain):
                settings = PerturbationSettings() if c in clean else p.training.sample(rng)
                scale = (1.0, 1.0)
                if scale_range is not None and c not in clean:
                    scale = tuple(float(x) for x in scale_rng.uniform(*scale_range, 2))
                env(terrain).set_leg_speed_scale(*scale)
                eps = random_episodes(env(terrain), settings, cfg.rollouts_per_condition, cfg.rollout_steps,
                                      seed=int(rng.integers(1 << 30)), name=f"{terrain}-c{c}")
                for e in eps:
                    e.meta["condition"] = {**e.meta["condition"], "leg_speed_scale": list(scale)}
                episodes += eps
            env(terrain).set_leg_speed_scale(1.0, 1.0)  # the tests run the nominal robot
    names = env(p.training_terrains[0]).state_names
    n_steps = sum(len(e) for e in episodes)
    log(f"seed {seed}: {len(episodes)} random rollouts ({n_steps} steps = "
        f"{n_steps * env(p.training_terrains[0]).period_s / 60:.0f} min of robot time) in {ph.wall:.0f} s, cpu {ph.cpu:.0f} s")
    save_episodes(out / "data" / f"seed{seed}_training.npz", episodes)
    tr = train(cfg, episodes, names, seed, out / "checkpoints", log, phases)
    tuning = {}
    if cfg.rate_grid is not None:
        with phases("rate_tuning") as ph:
            # held-out rollouts of the training conditions (the split train() made): never a test condition
            va_eps = split_episodes(episodes, cfg.val_fraction, seed)[1][:cfg.tune_rollouts]
            if not va_eps:
                raise ValueError("rate tuning needs held-out training rollouts: val_fraction is 0 or too small")
            tuning = tune_rates(cfg, tr, va_eps)
        for m in ("mb_de", "grbal", "mole"):  # the checkpoints carry the tuned step sizes
            tr.adapter(m, cfg).save(out / "checkpoints" / f"seed{seed}_{m}.pt")
        log(f"rate tuning on {len(va_eps)} held-out training rollouts ({ph.wall:.0f} s, cpu {ph.cpu:.0f} s): " +
            ", ".join(f"{m} x{v['rate']:g} " + "/".join(f"{e:.4f}" for e in v["errors"].values())
                      for m, v in tuning.items()))
        for v in tuning.values():
            if v["warning"]:
                log(f"WARNING rate tuning, seed {seed}: {v['warning']}")

    conds = _conditions(p)
    if cfg.conditions is not None:
        unknown = set(cfg.conditions) - set(conds)
        if unknown:
            raise ValueError(f"unknown conditions {sorted(unknown)}; known: {list(conds)}")
        conds = {k: conds[k] for k in dict.fromkeys(cfg.conditions)}  # in the order asked for
    methods = method_list(cfg)
    starts = start_poses(cfg, seed)
    before_after, results, oracle_hist = {}, {}, {}
    for name, (terrain, settings) in conds.items():
        with phases("before_after"):
            eps = random_episodes(env(terrain), settings, cfg.before_after_rollouts, cfg.rollout_steps,
                                  seed=int(rng.integers(1 << 30)), name=name)
            before_after[name] = grbal.evaluate(tr.meta, tr.meta.params(), tr.psi,
                                                segments(eps, cfg.M, cfg.K, stride=2), names=tr.adapt_params,
                                                clip=tr.clip)
        # the oracle: an MB model of the same size, trained like MB (same early stopping) on
        # oracle_rollouts (default: as many as the training set) all under this test condition
        n_or = cfg.oracle_rollouts or len(episodes)
        with phases("oracle_gathering") as ph_g:
            or_eps = random_episodes(env(terrain), settings, n_or, cfg.rollout_steps, seed=int(rng.integers(1 << 30)),
                                     name=f"oracle-{name}")
        tr.oracle = AdaptiveMLP(names, 2, hidden=cfg.hidden, seed=seed)
        with phases("oracle_training") as ph_t:
            h_or = fit_mb(cfg, tr.oracle, *split_episodes(or_eps, cfg.val_fraction, seed), seed)
        oracle_hist[name] = {k: h_or[k] for k in ("best_epoch", "best_val", "epochs_run")}
        log(f"  {name:>16} oracle model: {n_or} rollouts ({ph_g.wall:.0f} s, cpu {ph_g.cpu:.0f} s), "
            f"{h_or['epochs_run']} epochs (best {h_or['best_epoch']}), held-out {h_or['best_val'] or float('nan'):.4f} "
            f"({ph_t.wall:.0f} s, cpu {ph_t.cpu:.0f} s)")
        results[name] = {}
        for method in methods:
            with phases("closed_loop") as ph:
                results[name][method] = run_paths(cfg, env(terrain), settings, tr, method, starts)
            r = results[name][method]
            log(f"  {name:>16} {method:>6}: completed {r['completed']}/{r['runs']} progress {r['progress_m']:.2f} m "
                f"cost_per_m {r['cost_per_m']:.1f} k_step_error {r['k_step_error']:.3f} ({ph.wall:.0f} s, cpu {ph.cpu:.0f} s)")
    with phases("switching"):
        switching = run_switching(cfg, p, env(p.training_terrains[0]), tr, log)
    for e in envs.values():
        e.close()
    log(f"seed {seed} phases (wall/cpu s): {phases.line()}")
    return {"perturbations": results, "k_step_error_before_after": before_after, "switching": switching,
            "timing": phases.totals,
            "training": {"rollouts": len(episodes), "steps": int(n_steps), "plain_history": tr.history["plain"],
                         "oracle_history": oracle_hist,
                         "grbal_history": tr.history["grbal"], "rebal_history": tr.history["rebal"],
                         "psi_mean": {k: float(v.mean()) for k, v in tr.psi.items()}, "grbal_clip": tr.clip,
                         "rate_tuning": tuning, "rates": dict(tr.rates)}}


def method_list(cfg: AdaptationConfig) -> tuple[str, ...]:
    """The methods run on every condition (``cfg.methods``, default :data:`METHODS`)."""
    ms = tuple(cfg.methods) if cfg.methods is not None else METHODS
    unknown = set(ms) - set(METHODS)
    if unknown or not ms:
        raise ValueError(f"methods must be a non-empty subset of {list(METHODS)}, got {list(ms)}")
    return ms


def start_poses(cfg: AdaptationConfig, seed: int) -> dict[str, list[dict[str, float]]]:
    """Per path, ``starts_per_path`` start poses: the path's start pose, then poses offset
    sideways (uniform within ±``start_offset_m``, perpendicular to the first segment) and
    turned (±``start_yaw_deg``), drawn from the seed alone: every method meets the same starts."""
    if cfg.starts_per_path < 1:
        raise ValueError(f"starts_per_path must be >= 1, got {cfg.starts_per_path}")
    if not (0 <= cfg.start_offset_m <= 0.5 and 0 <= cfg.start_yaw_deg <= 90):
        raise ValueError(f"start offsets must be in [0, 0.5] m and [0, 90] deg, got {cfg.start_offset_m}, "
                         f"{cfg.start_yaw_deg}")
    rng = np.random.default_rng([seed, 24])
    out = {}
    for path in cfg.paths:
        wp = make_path(path, scale=cfg.path_scale)
        p0 = path_start_pose(wp)
        poses = [p0]
        for _ in range(cfg.starts_per_path - 1):
            off = float(rng.uniform(-cfg.start_offset_m, cfg.start_offset_m))
            dyaw = float(np.radians(rng.uniform(-cfg.start_yaw_deg, cfg.start_yaw_deg)))
            poses.append({"x": p0["x"] - off * np.sin(p0["yaw"]), "y": p0["y"] + off * np.cos(p0["yaw"]),
                          "yaw": p0["yaw"] + dyaw})
        out[path] = poses
    return out


def path_cost(cfg: AdaptationConfig, waypoints, state_names) -> PathCost:
    """The suite's path cost (planner and evaluation): the thesis' weights, the heading term's ``cfg.heading_weight``."""
    if not (np.isfinite(cfg.heading_weight) and cfg.heading_weight >= 0):
        raise ValueError(f"heading_weight must be finite and >= 0, got {cfg.heading_weight}")
    return PathCost(waypoints, state_names, f_h=cfg.heading_weight)


def run_paths(cfg: AdaptationConfig, env: RoachSim, settings: PerturbationSettings, tr: Trained,
              method: str, starts: dict[str, list[dict[str, float]]] | None = None) -> dict[str, Any]:
    """``method`` from every start of every path (``starts``: :func:`start_poses`; None: each
    path's start pose). Every run resets the sim (its noise streams reseeded) and the
    planner (its generator reseeded): common random numbers across methods."""
    per_path, kerrs, timing = {}, [], []
    mcfg = MbrlConfig(planner="random_shooting", samples=cfg.samples, horizon=cfg.horizon, seed=0)
    for path in cfg.paths:
        wp = make_path(path, scale=cfg.path_scale)
        ref = fillet(wp, mcfg.reference_corner_radius_m)
        limit_s = path_length(wp) / cfg.time_limit_speed_mps
        steps = int(np.ceil(limit_s / env.period_s - 1e-9))
        poses = starts[path] if starts is not None else [path_start_pose(wp)]
        for i, pose in enumerate(poses):
            planner = make_planner(mcfg, cfg.speed, 2, env.max_step)
            kerr = KStepError(cfg.K, tr.delta_scale)
            s = env.start(pose, settings)
            states, tm = drive(env, tr.adapter(method, cfg), planner, path_cost(cfg, ref, env.state_names), s, steps,
                               kerr, stop_if=PathEnd(path_cost(cfg, wp, env.state_names)))
            m = evaluate_path_following(states, path_cost(cfg, wp, env.state_names), period_s=env.period_s,
                                        time_limit_s=limit_s)
            m["xy"] = states[:, :2].tolist()
            m["start"] = pose
            per_path[path if len(poses) == 1 else f"{path}#{i}"] = m
            kerrs.append(kerr.mean())
            timing.append(tm)
    sm = summarize_paths(per_path)
    return {"cost_per_m": sm["cost_per_m"], "completed": sm["completed"], "runs": len(per_path),
            "k_step_error": float(np.mean(kerrs)),
            "progress_m": float(sum(m["progress_m"] for m in per_path.values())),
            "adapt_ms_p50": float(np.median([t["adapt_ms_p50"] for t in timing])),
            "plan_ms_p50": float(np.median([t["plan_ms_p50"] for t in timing])), "paths": per_path}


def run_switching(cfg: AdaptationConfig, p: PerturbationPresets, env: RoachSim, tr: Trained,
                  log: Callable[[str], None]) -> dict[str, Any]:
    """Conditions alternate every N steps on one long straight path; reward = progress
    along the path (m) per segment."""
    every = cfg.switching_every_steps or p.switching.every_steps
    nseg = cfg.switching_segments or p.switching.segments
    conds = [p.switching.conditions[i % len(p.switching.conditions)] for i in range(nseg)]
    steps = every * nseg
    # long enough never to end: 1.5 m/s for the whole run
    wp = straight(length_m=1.5 * steps * env.period_s, points=max(2, int(steps * env.period_s)))
    mcfg = MbrlConfig(planner="random_shooting", samples=cfg.samples, horizon=cfg.horizon, seed=0)
    out = {}
    for method in SWITCHING_METHODS:
        t0 = time.monotonic()
        planner = make_planner(mcfg, cfg.speed, 2, env.max_step)
        kerr = KStepError(cfg.K, tr.delta_scale)
        s = env.start(path_start_pose(wp), p.condition(conds[0]))
        posts, tasks = [], []

        def on_step(t: int, upd, conds=conds, posts=posts, tasks=tasks) -> None:
            if (t + 1) % every == 0 and (t + 1) // every < nseg:
                env.apply(p.condition(conds[(t + 1) // every]))
            posts.append(upd.info.get("posterior", []))
            tasks.append(upd.info.get("task", 0))

        adapter = tr.adapter(method, cfg)
        states, tm = drive(env, adapter, planner, path_cost(cfg, wp, env.state_names), s, steps, kerr, on_step=on_step)
        track = PathCost(wp, env.state_names)
        arc = []
        for st in states:
            track.observe(st)
            arc.append(track.arc_length(st[:2]))
        arc = np.array(arc)
        reward = [float(arc[min((i + 1) * every, len(arc) - 1)] - arc[i * every]) for i in range(nseg)]
        out[method] = {"reward_per_segment": reward,
                       "tasks_created": (posts and len(posts[-1])) if method == "mole" else None,
                       "conditions": conds, "k_step_error": kerr.mean(), **tm}
        if method == "mole":
            out[method]["task_per_step"] = tasks
            out[method]["posterior_per_step"] = posts
        log(f"  switching {method:>9}: reward per segment {[round(r, 2) for r in reward]} "
            f"tasks {out[method]['tasks_created']} ({time.monotonic() - t0:.0f} s)")
    return out


# ---------------------------------------------------------------------------- seeds
def _cell(vals: list[dict[str, Any]]) -> dict[str, Any]:
    out = {}
    for k in ("cost_per_m", "completed", "k_step_error", "progress_m", "adapt_ms_p50", "plan_ms_p50"):
        ms = mean_std([v[k] for v in vals])
        out[k] = ms["mean"]
        out[f"{k}_std"] = ms["std"]
    out["seeds"] = len(vals)
    out["runs"] = vals[0].get("runs", len(vals[0].get("paths", {})))
    return out


def run(cfg: AdaptationConfig, out: Path, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every seed; the report (issue 12's keys) with means and sample stds over seeds."""
    torch.set_num_threads(cfg.threads)
    out = Path(out)
    t0 = time.monotonic()
    per_seed = []
    for s in cfg.seeds:
        per_seed.append(run_seed(cfg, s, out, log))
        # each finished seed on disk at once: a run stopped later keeps it
        (out / f"seed{s}.json").write_text(json.dumps(_jsonable(per_seed[-1])))
        log(f"seed {s} done ({(time.monotonic() - t0) / 60:.1f} min): {out / f'seed{s}.json'}")
    return {**aggregate(per_seed), "config": _jsonable(asdict(cfg)), "seeds": list(cfg.seeds),
            "elapsed_s": time.monotonic() - t0, "per_seed": per_seed}


def aggregate(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Means and sample stds over seeds of :func:`run_seed`'s results (the report's tables)."""
    first = per_seed[0]
    perts = {name: {m: _cell([r["perturbations"][name][m] for r in per_seed]) for m in first["perturbations"][name]}
             for name in first["perturbations"]}
    ba = {}
    for name in first["k_step_error_before_after"]:
        b = mean_std([r["k_step_error_before_after"][name]["before"] for r in per_seed])
        a = mean_std([r["k_step_error_before_after"][name]["after"] for r in per_seed])
        ba[name] = {"before": b["mean"], "after": a["mean"], "before_std": b["std"], "after_std": a["std"]}
    sw = {}
    for m in SWITCHING_METHODS:
        rows = np.array([r["switching"][m]["reward_per_segment"] for r in per_seed])
        tc = [r["switching"][m]["tasks_created"] for r in per_seed]
        sw[m] = {"reward_per_segment": rows.mean(0).tolist(), "reward_per_segment_std":
                 (rows.std(0, ddof=1) if len(rows) > 1 else np.zeros(rows.shape[1])).tolist(),
                 "tasks_created": None if tc[0] is None else float(np.mean(tc)),
                 "conditions": first["switching"][m]["conditions"]}
    return {"perturbations": perts, "k_step_error_before_after": ba, "switching": sw,
            "benchmarks": benchmarks(per_seed)}


def mean_std_cell(ret: list[float]) -> dict[str, float]:
    ms = mean_std(ret)
    return {"return_mean": ms["mean"], "return_std": ms["std"]}


def benchmarks(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Issue 24's cross-suite view: ``{condition: {method: {return_mean, return_std,
    normalized, normalized_std, seeds}}}``. The roach's return is the progress along the
    paths within their time limits (m, summed over the paths; higher is better, 0 for a robot
    that does not move); ``normalized`` = return / the oracle's return of the same seed (None
    when the oracle made no progress), mean ± sample std over seeds. ``switching``: the
    progress summed over the segments (no oracle: ``normalized`` is None)."""
    out: dict[str, Any] = {}
    for name in per_seed[0]["perturbations"]:
        row = {}
        for m in per_seed[0]["perturbations"][name]:
            ret = [float(r["perturbations"][name][m]["progress_m"]) for r in per_seed]
            if "oracle" not in per_seed[0]["perturbations"][name]:
                row[m] = {**mean_std_cell(ret), "seeds": ret, "normalized": None}
                continue
            orc = [float(r["perturbations"][name]["oracle"]["progress_m"]) for r in per_seed]
            ms = mean_std(ret)
            cell = {"return_mean": ms["mean"], "return_std": ms["std"], "seeds": ret, "normalized": None}
            if all(o > 0 for o in orc):
                ns = mean_std([x / o for x, o in zip(ret, orc, strict=True)])
                cell["normalized"], cell["normalized_std"] = ns["mean"], ns["std"]
            row[m] = cell
        out[name] = row
    sw = {}
    for m in SWITCHING_METHODS:
        ret = [float(sum(r["switching"][m]["reward_per_segment"])) for r in per_seed]
        ms = mean_std(ret)
        sw[m] = {"return_mean": ms["mean"], "return_std": ms["std"], "seeds": ret, "normalized": None}
    out["switching"] = sw
    return out




__all__ = ["AdaptationConfig", "run", "aggregate", "METHODS", "SWITCHING_METHODS", "tune_rates", "online_error",
           "start_poses", "path_cost"]
