"""The thesis' simulated adaptation benchmarks on gymnasium's half-cheetah (issue 24).

``hil demo adaptation --suite gym [--quick] --out DIR``. Per seed:

1. **Data** (the same for every method): ``random_rollouts`` rollouts of uniform random
   actions, each under one training condition, then ``onpolicy_rollouts`` rollouts of the
   MB controller under training conditions, in ``onpolicy_rounds`` rounds (each followed by
   a refit of the plain model on everything so far). The oracle gets the same budget (same counts, the same
   procedure) under the test condition.
2. **Models** (one architecture, ``hidden``; fixed unit variance): MB = the plain model
   (:func:`~hilstack.learning.adaptation.training.fit_plain`); MB+DE = MB's θ* with one SGD
   step of ``de_lr`` per control step, continuing (``baselines.MbDeAdapter``); GrBAL = MB's
   weights meta-trained with ψ (``grbal.meta_train``: adapt on the past M, score the next K);
   ReBAL = GRU context + MLP (``rebal.meta_train``); oracle = MB trained in the test condition.
3. **Closed loop**: every method plans with the same MPPI/PDDM planner
   (``control/planners.PDDM``, the same seed), from the same gymnasium start (same reset
   seed), and the return is the sum of the reference code's reward over ``test_steps``.
   ``normalized`` = return / the oracle's return of the same seed. Every disabled-joint
   benchmark also reports ``zero_action`` (the do-nothing floor, same condition and start).

Benchmarks (``benchmarks`` in the config):

* ``hc_normal``: the sanity check before any adaptation: MB's MPC on the unperturbed robot
  beside the do-nothing controller (zero action, the floor); no oracle, no ratio.
* ``hc_disabled_joint``: joint 0 (never disabled in training: 1..5 are) disabled from the
  start (the thesis' generalisation test).
* ``hc_disabled_joint_switch``: joint 2 (a training condition) for the first half, then
  joint 0 (fast adaptation, Fig. 5.7). The oracle uses the oracle model of the condition
  in force (it knows the switch).
* ``hc_malfunction_switch`` (MOLe, ch. 6.5, Fig. 6.6/6.7): the normal robot and a
  malfunction (the back leg's three motors negated) alternate every ``switch_every`` steps;
  MOLe against k-shot (GrBAL from θ* each step), continued adaptation (SGD steps from θ*
  that continue), MB and MB with online gradient steps (MB+DE), all with random shooting
  (the thesis' MOLe planner). The prior is meta-trained on random malfunctions (each motor
  negated with probability 0.3 per rollout). ``tasks_created`` and the posterior per step.

The budgets are scaled to fit 2 CPU cores (stated in the report's config and
docs/adaptation.md); they are the same for every method.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from hilstack.configs.presets import Presets
from hilstack.control.planners import PDDM, RandomShooting
from hilstack.learning.adaptation import grbal, rebal
from hilstack.learning.adaptation.base import Adapter
from hilstack.learning.adaptation.baselines import MbAdapter, MbDeAdapter
from hilstack.learning.adaptation.gym_envs import ENVS, GymBenchmarkEnv, disabled_joint, malfunction
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.mole import MoleAdapter
from hilstack.learning.adaptation.rebal import ContextEncoder, RebalAdapter
from hilstack.learning.adaptation.training import fit_plain
from hilstack.learning.datasets import Episode, split_episodes

JOINT_METHODS = ("mb", "mb_de", "grbal", "rebal", "oracle")
MOLE_METHODS = ("mole", "continued", "k_shot", "mb", "mb_online")
BENCHMARKS = ("hc_normal", "hc_disabled_joint", "hc_disabled_joint_switch", "hc_malfunction_switch",
              "hc_disabled_joint_next_k")
JOINT_BENCHMARKS = ("hc_normal", "hc_disabled_joint", "hc_disabled_joint_switch", "hc_disabled_joint_next_k")
MALFUNCTION_A = (0, 1, 2)  # the back leg's motors, negated


@dataclass(frozen=True)
class GymSuiteConfig(Presets):
    #: the presets of ``from_preset(name, **overrides)`` (configs/presets.py): overrides of the defaults
    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "quick": dict(seeds=(0,), random_rollouts=30, onpolicy_rollouts=5, meta_steps=300, rebal_steps=800,
                      test_steps=300, switch_every=500, switch_segments=3, rs_samples=300),
        "tiny": dict(benchmarks=("hc_normal", "hc_disabled_joint", "hc_malfunction_switch", "hc_disabled_joint_next_k"),
                     seeds=(0,), onpolicy_rounds=2, hidden=(32, 32),
                     random_rollouts=4, onpolicy_rollouts=1, rollout_len=40, epochs=2, window=8, future=8,
                     meta_steps=5, meta_batch=4, rebal_steps=5, context_dim=4, samples=20, horizon=4,
                     rs_samples=20, test_steps=30, switch_every=15, switch_segments=3),
    }

    benchmarks: tuple[str, ...] = BENCHMARKS
    seeds: tuple[int, ...] = (0, 1, 2)
    hidden: tuple[int, ...] = (128, 128, 128)
    random_rollouts: int = 40
    onpolicy_rollouts: int = 8   # per on-policy round
    onpolicy_rounds: int = 1     # rounds of MB's MPC rollouts aggregated into the data, each followed by a refit
    rollout_len: int = 100
    epochs: int = 40
    window: int = 16          # M (and MOLe's K)
    future: int = 16          # K of GrBAL's meta-training
    meta_steps: int = 600
    meta_batch: int = 32
    meta_lr: float = 1e-3
    psi_init: float = 0.01
    rebal_steps: int = 1500
    context_dim: int = 16
    de_lr: float = 0.01       # thesis: the model lr of the online gradient steps
    mole_lr: float = 0.01
    mole_alpha: float = 1.0
    samples: int = 200        # PDDM/MPPI
    horizon: int = 10
    gamma: float = 1.0       # chosen by MB's closed loop on normal/training conditions (docs/adaptation.md)
    beta: float = 0.6
    rs_samples: int = 500     # random shooting (MOLe; thesis 1000)
    test_steps: int = 400
    switch_every: int = 500
    switch_segments: int = 3  # normal, malfunction, normal: the return to a condition met before
    threads: int = 1


# -- pieces -------------------------------------------------------------------------------------------
def reward_cost(env_name: str) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The planners' cost: minus the predicted return (forward velocity of the predicted
    states, minus the control cost, plus the alive bonus)."""
    sp = ENVS[env_name]
    vi, cc, ab = sp.velocity_index, sp.ctrl_cost, sp.alive_bonus

    def cost(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        vel = states[..., 1:, vi].sum(-1)                       # [E, N]
        ctrl = (actions * actions).sum((-1, -2))                 # [N]
        return -(vel - cc * ctrl + ab * actions.shape[1])
    return cost


def new_model(env_name: str, cfg: GymSuiteConfig, seed: int, context_dim: int = 0) -> AdaptiveMLP:
    sp = ENVS[env_name]
    return AdaptiveMLP([f"o{i}" for i in range(sp.state_dim)], sp.action_dim, hidden=cfg.hidden, body_frame=False,
                       seed=seed, context_dim=context_dim)


def pddm(cfg: GymSuiteConfig, action_dim: int, seed: int) -> PDDM:
    return PDDM(-1.0, 1.0, horizon=cfg.horizon, samples=cfg.samples, gamma=cfg.gamma, beta=cfg.beta,
                action_dim=action_dim, seed=seed)


def random_shooting(cfg: GymSuiteConfig, action_dim: int, seed: int) -> RandomShooting:
    return RandomShooting(-1.0, 1.0, horizon=cfg.horizon, samples=cfg.rs_samples, action_dim=action_dim, seed=seed)


def rollout(env: GymBenchmarkEnv, steps: int, reset_seed: int, schedule: dict[int, np.ndarray],
            act: Callable[[int, np.ndarray], np.ndarray], adapters: dict[int, Adapter] | Adapter | None = None,
            on_update: Callable[[int, Any], None] | None = None) -> tuple[Episode, np.ndarray]:
    """One rollout; ``schedule``: step → condition multipliers (step 0 required).
    ``act(t, s)`` returns the action; an adapter (or one per schedule step: the oracle's
    model of the condition in force) observes every transition and updates."""
    s = env.reset(reset_seed)
    states, actions, rewards = [s], [], []
    ad = None
    for t in range(steps):
        if t in schedule:
            env.set_condition(schedule[t])
            if isinstance(adapters, dict):
                ad = adapters[t]
                ad.reset()
        if t == 0 and isinstance(adapters, Adapter):
            ad = adapters
            ad.reset()
        a = act(t, s)
        n, r = env.step(a)
        if ad is not None:
            ad.observe(s, a, n)
            u = ad.update()
            if on_update is not None:
                on_update(t, (ad, u))
        states.append(n)
        actions.append(np.asarray(a, dtype=np.float32))
        rewards.append(r)
        s = n
    return Episode(np.array(states), np.array(actions)), np.array(rewards)


class Controller:
    """MPC with an adapter: plans with ``adapter.dynamics(last update)``."""

    def __init__(self, adapter: Adapter, planner, cost):
        self.adapter, self.planner, self.cost = adapter, planner, cost
        self.update = None

    def reset(self) -> None:
        self.planner.reset()
        self.update = None

    def on_update(self, t: int, au) -> None:
        self.adapter, self.update = au

    def act(self, t: int, s: np.ndarray) -> np.ndarray:
        return self.planner(self.adapter.dynamics(self.update), self.cost, s)


def closed_loop(env, adapters, planner, cost, steps, reset_seed, schedule) -> tuple[np.ndarray, list]:
    """Rewards per step of an adapted MPC rollout; and the updates' info per step."""
    first = adapters if isinstance(adapters, Adapter) else adapters[0]
    c = Controller(first, planner, cost)
    c.reset()
    infos: list[dict] = []

    def on_update(t, au):
        c.on_update(t, au)
        infos.append(au[1].info)
    _, r = rollout(env, steps, reset_seed, schedule, c.act, adapters, on_update)
    return r, infos


def collect(env, cfg: GymSuiteConfig, conditions: list[np.ndarray], rng: np.random.Generator, seed_base: int,
            model: AdaptiveMLP | None = None, planner_seed: int = 0) -> list[Episode]:
    """One rollout per condition: uniform random actions, or MB's MPC when ``model`` is given."""
    eps = []
    A = env.spec.action_dim
    cost = reward_cost(env.name)
    for i, m in enumerate(conditions):
        if model is None:
            ep, r = rollout(env, cfg.rollout_len, seed_base + i, {0: m}, lambda t, s: rng.uniform(-1, 1, A))
        else:
            ad = MbAdapter(model)
            pl = pddm(cfg, A, planner_seed + i)
            c = Controller(ad, pl, cost)
            c.reset()
            ep, r = rollout(env, cfg.rollout_len, seed_base + i, {0: m}, c.act)
        ep.meta["return"] = float(r.sum())
        eps.append(ep)
    return eps


def fit_mb(env_name: str, cfg: GymSuiteConfig, eps: list[Episode], seed: int) -> tuple[AdaptiveMLP, dict]:
    model = new_model(env_name, cfg, seed)
    tr, va = split_episodes(eps, 0.15, seed)
    h: dict = {}
    fit_plain(model, tr, epochs=cfg.epochs, batch_size=256, seed=seed, val=va, patience=5, history=h)
    return model, h


def dataset(env, cfg: GymSuiteConfig, sample_condition: Callable[[np.random.Generator], np.ndarray],
            seed: int, tag: int) -> tuple[list[Episode], AdaptiveMLP, dict]:
    """Random rollouts, MB on them, then ``onpolicy_rounds`` rounds of ``onpolicy_rollouts``
    rollouts of MB's MPC, each aggregated and followed by a refit (the thesis' iterated MBRL):
    (episodes, MB model, the last fit's history with ``onpolicy_returns`` per round)."""
    rng = np.random.default_rng([seed, tag])
    base = 100_000 * (tag + 1) + 1000 * seed
    eps = collect(env, cfg, [sample_condition(rng) for _ in range(cfg.random_rollouts)], rng, base)
    model, h = fit_mb(env.name, cfg, eps, seed)
    returns = []
    for k in range(cfg.onpolicy_rounds if cfg.onpolicy_rollouts else 0):
        new = collect(env, cfg, [sample_condition(rng) for _ in range(cfg.onpolicy_rollouts)], rng,
                      base + 500 + 50 * k, model=model, planner_seed=base + 50 * k)
        returns.append(float(np.mean([e.meta["return"] for e in new])))
        eps += new
        model, h = fit_mb(env.name, cfg, eps, seed)
    h["onpolicy_returns"] = returns
    return eps, model, h


def meta_grbal(cfg: GymSuiteConfig, mb: AdaptiveMLP, eps: list[Episode], seed: int) -> tuple[AdaptiveMLP, dict, list]:
    model = AdaptiveMLP.from_checkpoint(mb.to_checkpoint())  # warm start from MB's θ (same data)
    tr, va = split_episodes(eps, 0.15, seed)
    seg = grbal.segments(tr, cfg.window, cfg.future, stride=2)
    val = grbal.segments(va, cfg.window, cfg.future, stride=4)
    psi, hist = grbal.meta_train(model, seg, steps=cfg.meta_steps, meta_batch=cfg.meta_batch, lr=cfg.meta_lr,
                                 psi_init=cfg.psi_init, seed=seed, val=val, eval_every=max(1, cfg.meta_steps // 10),
                                 patience=4)
    return model, psi, hist


def meta_rebal(env_name: str, cfg: GymSuiteConfig, mb: AdaptiveMLP, eps: list[Episode], seed: int):
    model = new_model(env_name, cfg, seed, context_dim=cfg.context_dim)
    for k in ("input_mean", "input_std", "delta_mean", "delta_std"):
        getattr(model, k).copy_(getattr(mb, k))
    enc = ContextEncoder(model, cfg.context_dim)
    tr, va = split_episodes(eps, 0.15, seed)
    hist = rebal.meta_train(model, enc, grbal.segments(tr, cfg.window, cfg.future, stride=2), steps=cfg.rebal_steps,
                            seed=seed, val=grbal.segments(va, cfg.window, cfg.future, stride=4),
                            eval_every=max(1, cfg.rebal_steps // 10), patience=4)
    return model, enc, hist


def _timed(timing: dict, key: str, t0: float) -> float:
    timing[key] = round(time.monotonic() - t0, 1)
    return time.monotonic()


# -- benchmarks -----------------------------------------------------------------------------------------
def run_disabled_joint(cfg: GymSuiteConfig, seed: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Both disabled-joint benchmarks of one seed (one training, two tests)."""
    env = GymBenchmarkEnv("half_cheetah")
    A, cost = env.spec.action_dim, reward_cost("half_cheetah")
    timing: dict[str, float] = {}
    t = time.monotonic()
    eps, mb, mb_hist = dataset(env, cfg, lambda r: disabled_joint(A, int(r.integers(1, A))), seed, 0)
    t = _timed(timing, "data_and_mb", t)
    log(f"  seed {seed}: MB on {sum(len(e) for e in eps)} transitions, held-out {mb_hist.get('best_val', float('nan')):.4f}, "
        f"mean return of its MPC rollouts per on-policy round {[round(x, 1) for x in mb_hist['onpolicy_returns']]}")
    out: dict[str, Any] = {}
    training = {"mb": mb_hist, "transitions": int(sum(len(e) for e in eps))}
    if "hc_normal" in cfg.benchmarks:
        # the sanity check before any adaptation: does MB's MPC run on the unperturbed robot at this
        # budget? The do-nothing controller (zero action) is the floor.
        sched = {0: disabled_joint(A, None)}
        r_mb, _ = closed_loop(env, MbAdapter(mb, cfg.window), pddm(cfg, A, 7 + seed), cost, cfg.test_steps,
                              900_000 + seed, sched)
        _, r_0 = rollout(env, cfg.test_steps, 900_000 + seed, sched, lambda t, s: np.zeros(A, dtype=np.float32))
        out["hc_normal"] = {m: {"return": float(r.sum()), "return_per_segment": [float(r.sum())], "normalized": None}
                            for m, r in (("mb", r_mb), ("zero_action", r_0))}
        log(f"  seed {seed} hc_normal: MB {r_mb.sum():.1f} ({r_mb.mean():.2f} per step), "
            f"zero action {r_0.sum():.1f}")
        t = _timed(timing, "hc_normal", t)
    if not set(cfg.benchmarks) & {"hc_disabled_joint", "hc_disabled_joint_switch", "hc_disabled_joint_next_k"}:
        env.close()
        return {"results": out, "timing_s": timing, "training": training}
    gmodel, psi, ghist = meta_grbal(cfg, mb, eps, seed)
    t = _timed(timing, "grbal_meta_train", t)
    rmodel, enc, rhist = meta_rebal("half_cheetah", cfg, mb, eps, seed)
    t = _timed(timing, "rebal_meta_train", t)
    oracles = {j: dataset(env, cfg, lambda r, j=j: disabled_joint(A, j), seed, 10 + j)[1] for j in (0, 2)}
    t = _timed(timing, "oracles", t)
    log(f"  seed {seed}: trained (MB held-out {mb_hist.get('best_val', float('nan')):.4f}; "
        f"GrBAL next-K {ghist[-1]['before']:.4f} -> {ghist[-1]['after']:.4f})")

    def adapters(schedule_steps: list[int], joints: list[int]) -> dict[str, Any]:
        return {"mb": MbAdapter(mb, cfg.window), "mb_de": MbDeAdapter(mb, cfg.window, lr=cfg.de_lr),
                "grbal": grbal.GrbalAdapter(gmodel, psi, cfg.window), "rebal": RebalAdapter(rmodel, enc, cfg.window),
                "oracle": {s: MbAdapter(oracles[j], cfg.window) for s, j in zip(schedule_steps, joints, strict=True)}}

    if "hc_disabled_joint_next_k" in cfg.benchmarks:
        out["hc_disabled_joint_next_k"] = next_k_errors(env, cfg, seed, mb, gmodel, psi, rmodel, enc, oracles[0])
        t = _timed(timing, "hc_disabled_joint_next_k", t)
        log(f"  seed {seed} next-K error under joint 0: " + ", ".join(
            f"{m} {v['next_k_error']:.4f}" for m, v in out["hc_disabled_joint_next_k"].items()))
    tests = {"hc_disabled_joint": ([0], [0]), "hc_disabled_joint_switch": ([0, cfg.test_steps // 2], [2, 0])}
    for name, (steps, joints) in tests.items():
        if name not in cfg.benchmarks:
            continue
        schedule = {s: disabled_joint(A, j) for s, j in zip(steps, joints, strict=True)}
        res = {}
        for m, ad in adapters(steps, joints).items():
            r, _ = closed_loop(env, ad, pddm(cfg, A, 7 + seed), cost, cfg.test_steps, 900_000 + seed, schedule)
            res[m] = {"return": float(r.sum()), "return_per_segment": [float(r[a:b].sum()) for a, b in
                                                                       zip(steps, [*steps[1:], cfg.test_steps],
                                                                           strict=True)]}
            log(f"  seed {seed} {name} {m}: return {r.sum():.1f}")
        _, r0 = rollout(env, cfg.test_steps, 900_000 + seed, schedule, lambda t, s: np.zeros(A, dtype=np.float32))
        res["zero_action"] = {"return": float(r0.sum()), "return_per_segment": [
            float(r0[a:b].sum()) for a, b in zip(steps, [*steps[1:], cfg.test_steps], strict=True)]}
        for m in res:
            res[m]["normalized"] = res[m]["return"] / res["oracle"]["return"] if res["oracle"]["return"] > 0 else None
        out[name] = res
        t = _timed(timing, name, t)
    env.close()
    return {"results": out, "timing_s": timing,
            "training": {**training, "grbal": ghist[-1], "rebal": rhist[-1] if rhist else {},
                         "grbal_psi_mean": float(torch.cat([v.reshape(-1) for v in psi.values()]).mean())}}


def next_k_errors(env, cfg: GymSuiteConfig, seed: int, mb, gmodel, psi, rmodel, enc, oracle) -> dict[str, Any]:
    """Open loop, under the unseen disabled joint 0 (thesis Figs 5.4, 5.5): on windows of
    random rollouts (the same for every method), each method's loss on the next K
    transitions after its update from the past M: MB θ*; MB+DE one SGD step of ``de_lr``
    from θ* (its first step); GrBAL θ* − ψ ⊙ ∇L; ReBAL the GRU context; the oracle's θ."""
    A = env.spec.action_dim
    rng = np.random.default_rng([seed, 77])
    eps = collect(env, cfg, [disabled_joint(A, 0)] * 10, rng, 700_000 + 100 * seed)
    seg = grbal.segments(eps, cfg.window, cfg.future, stride=4)

    def ev(model, step: float | None, p=None) -> float:
        ps = p if p is not None else {k: torch.full_like(v, step or 0.0) for k, v in model.params().items()}
        e = grbal.evaluate(model, model.params(), ps, seg, max_tasks=512)
        return e["after"] if (step or p is not None) else e["before"]
    return {"mb": {"next_k_error": ev(mb, None)}, "mb_de": {"next_k_error": ev(mb, cfg.de_lr)},
            "grbal": {"next_k_error": ev(gmodel, None, psi), "grbal_before": ev(gmodel, None)},
            "rebal": {"next_k_error": rebal.evaluate(rmodel, enc, seg, max_tasks=512)["after"]},
            "oracle": {"next_k_error": _raw_next_k(oracle, mb, seg)}}


def _raw_next_k(model: AdaptiveMLP, ref: AdaptiveMLP, seg) -> float:
    """``model``'s (θ, no update) loss on the next K in ``ref``'s normalized delta units (the
    oracle has its own normalization; the others share MB's)."""
    s, a, n = seg.future(torch.arange(min(len(seg), 512)))
    with torch.no_grad():
        pred = model.step(model.params(), s, a)
    return float((((pred - n) / ref.delta_std) ** 2).mean())


def run_malfunction(cfg: GymSuiteConfig, seed: int, log: Callable[[str], None]) -> dict[str, Any]:
    """MOLe on the half-cheetah's motor malfunctions switching every ``switch_every`` steps."""
    env = GymBenchmarkEnv("half_cheetah")
    A, cost = env.spec.action_dim, reward_cost("half_cheetah")
    timing: dict[str, float] = {}
    t = time.monotonic()

    def sample(r: np.random.Generator) -> np.ndarray:
        return malfunction(A, [j for j in range(A) if r.random() < 0.3])
    eps, mb, _ = dataset(env, cfg, sample, seed, 1)
    t = _timed(timing, "data_and_mb", t)
    gmodel, psi, ghist = meta_grbal(cfg, mb, eps, seed)
    t = _timed(timing, "grbal_meta_train", t)
    names = ["normal", "malfunction"]
    conds = [np.ones(A, dtype=np.float32), malfunction(A, MALFUNCTION_A)]
    seq = [i % 2 for i in range(cfg.switch_segments)]
    steps = cfg.switch_every * cfg.switch_segments
    schedule = {k * cfg.switch_every: conds[c] for k, c in enumerate(seq)}
    methods = {"mole": MoleAdapter(gmodel, psi, cfg.window, lr=cfg.mole_lr, alpha=cfg.mole_alpha),
               "continued": MbDeAdapter(gmodel, cfg.window, lr=cfg.de_lr),
               "k_shot": grbal.GrbalAdapter(gmodel, psi, cfg.window),
               "mb": MbAdapter(mb, cfg.window), "mb_online": MbDeAdapter(mb, cfg.window, lr=cfg.de_lr)}
    res: dict[str, Any] = {}
    for m, ad in methods.items():
        r, infos = closed_loop(env, ad, random_shooting(cfg, A, 11 + seed), cost, steps, 800_000 + seed, schedule)
        seg = [float(r[k * cfg.switch_every:(k + 1) * cfg.switch_every].sum()) for k in range(cfg.switch_segments)]
        res[m] = {"return": float(r.sum()), "return_per_segment": seg}
        if m == "mole":
            res[m]["tasks_created"] = int(infos[-1]["tasks_created"])
            res[m]["posterior_trace"] = [[round(p, 4) for p in i["posterior"]] for i in infos]
            res[m]["task_trace"] = [int(i["task"]) for i in infos]
            # the task MOLe used most in each segment: one per condition, recalled on return
            res[m]["task_per_segment"] = [int(np.bincount(res[m]["task_trace"][k * cfg.switch_every:
                                                                              (k + 1) * cfg.switch_every]).argmax())
                                          for k in range(cfg.switch_segments)]
        log(f"  seed {seed} hc_malfunction_switch {m}: return {r.sum():.1f} per segment "
            + ", ".join(f"{x:.0f}" for x in seg)
            + (f"; tasks {res[m]['tasks_created']}, task per segment {res[m]['task_per_segment']}" if m == "mole" else ""))
    timing["closed_loop"] = round(time.monotonic() - t, 1)
    env.close()
    return {"results": {"hc_malfunction_switch": res}, "timing_s": timing,
            "conditions": [names[c] for c in seq], "training": {"grbal": ghist[-1]}}


def run_seed(cfg: GymSuiteConfig, seed: int, log: Callable[[str], None]) -> dict[str, Any]:
    torch.manual_seed(seed)
    r: dict[str, Any] = {"seed": seed, "results": {}, "timing_s": {}, "training": {}}
    if set(JOINT_BENCHMARKS) & set(cfg.benchmarks):
        d = run_disabled_joint(cfg, seed, log)
        r["results"].update(d["results"])
        r["timing_s"]["disabled_joint"] = d["timing_s"]
        r["training"]["disabled_joint"] = d["training"]
    if "hc_malfunction_switch" in cfg.benchmarks:
        d = run_malfunction(cfg, seed, log)
        r["results"].update(d["results"])
        r["timing_s"]["malfunction"] = d["timing_s"]
        r["training"]["malfunction"] = d["training"]
        r["switch_conditions"] = d["conditions"]
    return r


def _ms(x: list[float]) -> tuple[float, float]:
    a = np.asarray(x, dtype=float)
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0


def aggregate(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """``benchmarks: {env: {method: {return_mean, return_std, normalized, normalized_std, seeds}}}``."""
    out: dict[str, Any] = {}
    for name in per_seed[0]["results"]:
        out[name] = {}
        for m in per_seed[0]["results"][name]:
            rows = [s["results"][name][m] for s in per_seed]
            if "return" not in rows[0]:  # open-loop numbers: mean, std and the seeds of each
                out[name][m] = {k: {"mean": _ms([x[k] for x in rows])[0], "std": _ms([x[k] for x in rows])[1],
                                    "seeds": [x[k] for x in rows]} for k in rows[0]}
                continue
            rm, rs = _ms([x["return"] for x in rows])
            cell: dict[str, Any] = {"return_mean": rm, "return_std": rs, "seeds": [x["return"] for x in rows],
                                    "return_per_segment_mean": np.mean([x["return_per_segment"] for x in rows],
                                                                       0).tolist()}
            norms = [x.get("normalized") for x in rows]
            cell["normalized"], cell["normalized_seeds"] = None, norms
            if all(v is not None for v in norms):  # None: an oracle return <= 0 (no ratio to take)
                cell["normalized"], cell["normalized_std"] = _ms(norms)
            if m == "mole":
                cell["tasks_created"] = [x["tasks_created"] for x in rows]
                cell["task_per_segment"] = [x["task_per_segment"] for x in rows]
                cell["posterior_trace"] = [x["posterior_trace"] for x in rows]
            out[name][m] = cell
        if name != "hc_normal" and "oracle" not in out[name] and all("return_mean" in c for c in out[name].values()):
            best = max(c["return_mean"] for c in out[name].values())
            for c in out[name].values():
                c["normalized"] = c["return_mean"] / best if best > 0 else None
                c["normalized_by"] = "the best method's mean return (no oracle in this benchmark)"
    return out


def plots(report: dict[str, Any], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    b = report["benchmarks"]
    joint = [n for n in ("hc_disabled_joint", "hc_disabled_joint_switch") if n in b]
    if joint:
        fig, ax = plt.subplots(figsize=(8, 3.5))
        w = 0.8 / len(JOINT_METHODS)
        for i, m in enumerate(JOINT_METHODS):
            ax.bar(np.arange(len(joint)) + i * w, [b[n][m].get("normalized") or 0 for n in joint], w,
                   yerr=[b[n][m].get("normalized_std", 0) for n in joint], label=m)
        ax.set_xticks(np.arange(len(joint)) + 0.4 - w / 2, joint)
        ax.set_ylabel("return / oracle's")
        ax.set_title("half-cheetah disabled joint (cf. thesis Fig. 5.7)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "gym_disabled_joint.png", dpi=90)
        plt.close(fig)
        files.append("gym_disabled_joint.png")
    if "hc_malfunction_switch" in b:
        mo = b["hc_malfunction_switch"]
        fig, axes = plt.subplots(1, 2, figsize=(13, 4))
        for m in MOLE_METHODS:
            axes[0].plot(mo[m]["return_per_segment_mean"], "o-", label=m)
        axes[0].set_xticks(range(len(report["switch_conditions"])), report["switch_conditions"])
        axes[0].set_title("HC malfunctions switching: return per segment (cf. Fig. 6.6)")
        axes[0].legend(fontsize=8)
        trace = mo["mole"]["posterior_trace"][0]
        L = max(len(p) for p in trace)
        P = np.zeros((len(trace), L))
        for i, p in enumerate(trace):
            P[i, :len(p)] = p
        axes[1].stackplot(np.arange(len(trace)), P.T, labels=[f"task {i}" for i in range(L)])
        for k in range(1, len(report["switch_conditions"])):
            axes[1].axvline(k * report["config"]["switch_every"], color="k", lw=0.8)
        axes[1].set_title("MOLe task posterior over time, seed 0 (cf. Fig. 6.7)")
        axes[1].set_xlabel("step")
        axes[1].legend(fontsize=8, loc="upper right")
        fig.tight_layout()
        fig.savefig(out / "gym_mole_posterior.png", dpi=90)
        plt.close(fig)
        files.append("gym_mole_posterior.png")
    return files


def summary_lines(r: dict[str, Any]) -> list[str]:
    """One line per benchmark (what the CLI prints)."""
    out = []
    for name, row in r["benchmarks"].items():
        cells = []
        for m, c in row.items():
            if "return_mean" in c:
                n = c.get("normalized")
                cells.append(f"{m} {c['return_mean']:.0f}" + (f" ({n:.2f})" if n is not None else ""))
            else:
                cells.append(f"{m} {c['next_k_error']['mean']:.4f}")
        out.append(f"{name}: " + ", ".join(cells))
    return out


def report_markdown(r: dict[str, Any]) -> str:
    lines = [f"# Gym adaptation suite ({r['preset']}, seeds {r['seeds']}, {r['elapsed_s'] / 60:.1f} min)", ""]
    for name, row in r["benchmarks"].items():
        if not all("return_mean" in c for c in row.values()):
            keys = list(dict.fromkeys(k for c in row.values() for k in c))
            lines += [f"## {name} (open loop)", "", "| method | " + " | ".join(keys) + " |", "|---" * (1 + len(keys)) + "|"]
            for m, c in row.items():
                lines.append(f"| {m} | " + " | ".join(f"{c[k]['mean']:.4f} ± {c[k]['std']:.4f}" if k in c else "-"
                                                      for k in keys) + " |")
            lines.append("")
            continue
        lines += [f"## {name}", "", "| method | return (mean ± std) | normalized | per seed |", "|---|---|---|---|"]
        for m, c in row.items():
            n = c.get("normalized")
            ns = "-" if n is None else f"{n:.3f}" + (f" ± {c['normalized_std']:.3f}" if "normalized_std" in c else "")
            lines.append(f"| {m} | {c['return_mean']:.1f} ± {c['return_std']:.1f} | {ns} | "
                         + ", ".join(f"{x:.1f}" for x in c["seeds"]) + " |")
        if "mole" in row:
            lines += ["", f"MOLe tasks created per seed: {row['mole']['tasks_created']}; most-used task per segment "
                      f"({', '.join(r['switch_conditions'])}): {row['mole']['task_per_segment']}",
                      "Return per segment (mean over seeds): " + "; ".join(
                          f"{m} " + ", ".join(f"{x:.0f}" for x in c["return_per_segment_mean"]) for m, c in row.items())]
        lines.append("")
    lines += ["Plots: " + ", ".join(f"![]({f})" for f in r.get("plots", []))]
    return "\n".join(lines) + "\n"


def finish(cfg: GymSuiteConfig, per_seed: list[dict[str, Any]], out: Path, preset: str, elapsed_s: float,
           cpu_s: float) -> dict[str, Any]:
    """The report from the seeds' results: report.json, report.md, plots."""
    r = {"suite": "gym", "preset": preset, "seeds": [s["seed"] for s in per_seed], "config": asdict(cfg),
         "benchmarks": aggregate(per_seed), "switch_conditions": per_seed[0].get("switch_conditions", []),
         "elapsed_s": elapsed_s, "cpu_s": cpu_s,
         "per_seed": [{k: v for k, v in s.items() if k != "results"} for s in per_seed]}
    r["plots"] = plots(r, out)
    (out / "report.json").write_text(json.dumps(r, indent=1))
    (out / "report.md").write_text(report_markdown(r))
    return r


def merge(parts: list[Path], out: Path, cfg: GymSuiteConfig, preset: str = "full") -> dict[str, Any]:
    """One report from runs of parts of the suite in separate processes (``python -m
    hilstack.learning.adaptation.gym_suite OUT --seed S --part joint|malfunction``): the
    ``gym_seed*.json`` of every directory in ``parts``, merged per seed. ``elapsed_s`` is
    the longest part's wall time, ``cpu_s`` the sum of the parts' CPU seconds."""
    by_seed: dict[int, dict[str, Any]] = {}
    wall, cpu = 0.0, 0.0
    for d in parts:
        for f in sorted(Path(d).glob("gym_seed*.json")):
            s = json.loads(f.read_text())
            m = by_seed.setdefault(s["seed"], {"seed": s["seed"], "results": {}, "timing_s": {}, "training": {}})
            for k in ("results", "timing_s", "training"):
                m[k].update(s[k])
            if "switch_conditions" in s:
                m["switch_conditions"] = s["switch_conditions"]
            wall, cpu = max(wall, s.get("elapsed_s", 0.0)), cpu + s.get("cpu_s", 0.0)
    if not by_seed:
        raise FileNotFoundError(f"no gym_seed*.json in {[str(p) for p in parts]}")
    out.mkdir(parents=True, exist_ok=True)
    return finish(replace(cfg, seeds=tuple(sorted(by_seed))), [by_seed[k] for k in sorted(by_seed)], out, preset,
                  wall, cpu)


def run(cfg: GymSuiteConfig, out: Path, log: Callable[[str], None] = print, preset: str = "full") -> dict[str, Any]:
    unknown = set(cfg.benchmarks) - set(BENCHMARKS)
    if unknown:
        raise ValueError(f"unknown gym benchmarks {sorted(unknown)}; known: {list(BENCHMARKS)}")
    torch.set_num_threads(cfg.threads)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    c0 = time.process_time()
    per_seed = []
    for s in cfg.seeds:
        t1, c1 = time.monotonic(), time.process_time()
        per_seed.append(run_seed(cfg, s, log))
        per_seed[-1].update(elapsed_s=time.monotonic() - t1, cpu_s=time.process_time() - c1)
        (out / f"gym_seed{s}.json").write_text(json.dumps(per_seed[-1]))
        log(f"seed {s} done ({(time.monotonic() - t0) / 60:.1f} min)")
    return finish(cfg, per_seed, out, preset, time.monotonic() - t0, time.process_time() - c0)


def config_for(quick: bool, tiny: bool = False, seed: int = 0, **kw: Any) -> GymSuiteConfig:
    if tiny:
        return GymSuiteConfig.from_preset("tiny", seeds=(seed,), **kw)
    if quick:
        return GymSuiteConfig.from_preset("quick", seeds=(seed,), **kw)
    return replace(GymSuiteConfig(), seeds=(seed, seed + 1, seed + 2), **kw)


PARTS = {"normal": ("hc_normal",), "joint": ("hc_normal", "hc_disabled_joint", "hc_disabled_joint_switch"),
         "malfunction": ("hc_malfunction_switch",), "openloop": ("hc_disabled_joint_next_k",)}


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``FIELD=VALUE`` strings → GymSuiteConfig overrides, typed like the field's default
    (tuples: comma-separated). An unknown field or a bad value is a one-line ValueError."""
    defaults = asdict(GymSuiteConfig())
    out: dict[str, Any] = {}
    for it in items:
        k, sep, v = it.partition("=")
        if not sep or k not in defaults or k in ("seeds", "benchmarks"):
            raise ValueError(f"--set {it!r}: expected FIELD=VALUE with FIELD one of "
                             f"{sorted(set(defaults) - {'seeds', 'benchmarks'})}")
        d = defaults[k]
        try:
            if isinstance(d, tuple):
                out[k] = tuple(type(d[0])(x) for x in v.split(","))
            else:
                out[k] = type(d)(v)
        except ValueError:
            raise ValueError(f"--set {it!r}: {v!r} is not a {type(d).__name__}") from None
        if isinstance(out[k], (int, float)) and not np.isfinite(out[k]):
            raise ValueError(f"--set {it!r}: not finite")
    return out


def main(argv: list[str] | None = None) -> None:
    """Parts of the full suite in separate processes, and their merge (docs/adaptation.md)::

        python -m hilstack.learning.adaptation.gym_suite DIR --seed S --part joint|malfunction [--quick]
        python -m hilstack.learning.adaptation.gym_suite OUT --merge DIR1 DIR2 ... [--quick]
    """
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.learning.adaptation.gym_suite")
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--part", choices=sorted(PARTS))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--merge", type=Path, nargs="+")
    ap.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE",
                    help="override GymSuiteConfig fields, e.g. onpolicy_rounds=4 hidden=256,256,256")
    a = ap.parse_args(argv)
    try:
        over = parse_overrides(a.set)
    except ValueError as e:
        ap.error(str(e))
    preset = "quick" if a.quick else "full"
    if a.merge:
        cfg = config_for(a.quick, **over)
        r = merge(a.merge, a.out, cfg, preset)
        print((a.out / "report.md").read_text())
        return
    if a.part is None:
        ap.error("give --part (or --merge)")
    cfg = replace(config_for(a.quick, seed=a.seed, **over), seeds=(a.seed,), benchmarks=PARTS[a.part])
    r = run(cfg, a.out, lambda m: print(f"[{time.strftime('%H:%M:%S')} cpu {time.process_time():.0f} s] {m}",
                                        flush=True), preset)
    print(f"done: {r['elapsed_s'] / 60:.1f} min wall, {r['cpu_s'] / 60:.1f} min CPU")


if __name__ == "__main__":
    main()
