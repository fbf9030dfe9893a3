"""GAT vs GARAT with the VelociRoACH MuJoCo sim as the source (GARAT paper, Fig. 3 protocol).

Source: the nominal sim (``sim_backends/velociroach``, carpet). Target: the same sim with a
physical change set by config, by default the left side's legs at 60 % of the commanded speed
(``params.sim.leg_speed_scale`` = (0.6, 1)): the robot then turns left under equal leg
commands, an effect an action transformation of the source (ã_left = 0.6 a_left, always in the command
range) reproduces exactly. The earlier target, the left middle leg missing (``missing_leg``, the
backend's perturbation), is still available; it is not an action transformation in disguise,
and neither grounding recovered its turn (docs/transfer.md).

Task: run straight. Episode of ``episode_steps`` control periods (0.1 s) from a reset at a
random heading; return = progress along the start heading − ``lateral_weight`` · |sideways
offset| at the end [m] (from the state's mocap x, y).

Agent policy: a two-parameter open-loop gait (left and right leg-velocity commands [rev/s],
held constant; searched as mean speed and left − right difference), trained by the
cross-entropy method (CEM) with the same budget in every
simulator (source, target, GAT-grounded source, GARAT-grounded source). PPO on the full sim
for a neural policy is too slow for two shared cores (docs/transfer.md).

Grounding (learning/transfer/grounding.py): transitions are the 7 features of ``features``
(body-frame velocity, yaw rate, crank rates, left-right crank phase) under the source-trained
gait plus Gaussian command noise. GAT = inverse source model ∘ forward target model; GARAT =
PPO on −log D(s, a, s') with D updated once per PPO update. The source sim is stateful, so
the grounded "step" continues the running episode (``RoachStep``) instead of starting from s.

Normalised target return (Fig. 3): (R − R_source-trained) / (R_target-trained − R_source-trained),
all evaluated in the target on the same start headings.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from hilstack.drivers.registry import make_backend, spec_of
from hilstack.learning.datasets import Transitions
from hilstack.learning.transfer.grounding import GaratConfig, Gat, train_garat
from hilstack.tasks.perturbations import LEG_NAMES

#: the roach's state channel -> index (its spec's, filled on first use: the registry builds its driver)
_I: dict[str, int] = {}
FEATURE_NAMES = ("v_fwd", "v_lat", "wz", "crank_vel_l", "crank_vel_r", "cos_dphase", "sin_dphase")


def features(state: np.ndarray) -> np.ndarray:
    """Heading-invariant features of the 24-D state: body-frame velocity [m/s], yaw rate
    [rad/s], crank rates [rev/s], cos/sin of the left minus right crank angle."""
    if not _I:
        _I.update({n: i for i, n in enumerate(spec_of("velociroach").state.names)})
    s = np.asarray(state, float)
    c, si = s[_I["cos_yaw"]], s[_I["sin_yaw"]]
    n = math.hypot(c, si) or 1.0
    c, si = c / n, si / n
    vx, vy = s[_I["vx"]], s[_I["vy"]]
    pl = math.atan2(s[_I["sin_crank_l"]], s[_I["cos_crank_l"]])
    pr = math.atan2(s[_I["sin_crank_r"]], s[_I["cos_crank_r"]])
    return np.array([c * vx + si * vy, -si * vx + c * vy, s[_I["wz"]], s[_I["crank_vel_l"]],
                     s[_I["crank_vel_r"]], math.cos(pl - pr), math.sin(pl - pr)])


class RoachStep:
    """The VelociRoACH sim as a stateful ``step(s, a) -> s'`` over ``features``: ``s`` must be
    the features it returned last (the sim cannot start from an arbitrary state); ``a`` is the
    (left, right) leg-velocity command [rev/s], held one control period."""

    def __init__(self, missing_leg: str | None = None, seed: int = 0,
                 leg_speed_scale: tuple[float, float] | None = None):
        if missing_leg is not None and missing_leg not in LEG_NAMES:
            raise ValueError(f"missing_leg must be one of {list(LEG_NAMES)} or None, got {missing_leg!r}")
        sim: dict = {"seed": seed}
        if leg_speed_scale is not None:
            sim["leg_speed_scale"] = tuple(leg_speed_scale)  # validated by the sim's params
        self.sim = make_backend("velociroach", "sim", sim=sim)
        self.params = self.sim.params
        self.sim.configure()
        self.sim.activate()
        if missing_leg is not None:
            self.sim.set_perturbation("missing_leg", missing_leg)
        self.vmax = self.params.max_leg_vel_rps
        self._raw: np.ndarray | None = None
        self.start_xy = np.zeros(2)
        self.start_yaw = 0.0

    def reset_state(self, rng: np.random.Generator) -> np.ndarray:
        self.start_yaw = float(rng.uniform(-math.pi, math.pi))
        self.sim.reset(yaw=self.start_yaw)
        self._raw = self.sim.read().state
        self.start_xy = self._raw[:2].copy()
        return features(self._raw)

    def __call__(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        if self._raw is None:
            raise RuntimeError("RoachStep: call reset_state() first")
        a = np.asarray(a, float).reshape(2)
        if not np.isfinite(a).all():
            raise ValueError(f"RoachStep: non-finite command {a}")
        self.sim.write(np.clip(a, -self.vmax, self.vmax))
        self.sim.tick()
        self._raw = self.sim.read().state
        return features(self._raw)

    def progress(self) -> tuple[float, float]:
        """(forward, sideways) displacement [m] since the reset, in the start heading's frame."""
        d = self._raw[:2] - self.start_xy
        c, si = math.cos(self.start_yaw), math.sin(self.start_yaw)
        return float(c * d[0] + si * d[1]), float(-si * d[0] + c * d[1])

    def close(self) -> None:
        self.sim.cleanup()


@dataclass(frozen=True)
class RoachGaratConfig:
    # the target's change: a per-side leg-speed scaling (params.sim.leg_speed_scale; left side at
    # 60 %) and/or a missing leg (backend perturbation missing_leg, e.g. "lm"); None = unchanged
    leg_speed_scale: tuple[float, float] | None = (0.6, 1.0)
    missing_leg: str | None = None
    episode_steps: int = 30  # 3 s
    lateral_weight: float = 1.0
    v_min_rps: float = 0.0  # the gait's command range [v_min, v_max] (forward only)
    v_max_rps: float = 15.0
    cem_population: int = 10
    cem_iterations: int = 8
    cem_elites: int = 3
    cem_episodes: int = 2  # per candidate (returns of one gait vary by ~0.5 m between episodes)
    max_diff_rps: float = 6.0  # |left − right| of the gait
    cem_init_std_rps: tuple[float, float] = (3.0, 1.5)  # (mean speed, difference)
    cem_min_std_rps: float = 0.2
    eval_episodes: int = 5
    target_transitions: int = 1500  # 50 episodes of 3 s = 2.5 min of target robot time
    source_transitions: int = 3000  # for GAT's inverse source model (source data is free)
    action_noise_rps: float = 2.0  # exploration noise on the gait's commands for the grounding data
    gat_fit_steps: int = 1500
    gat_width: int = 64  # GAT's MLPs (the pendulum's tuned settings carry over; not tuned on the roach)
    gat_layers: int = 2
    gat_val_frac: float = 0.0
    garat: GaratConfig = field(default_factory=lambda: GaratConfig(total_timesteps=16384, log_std_init=-2.0))
    seed: int = 0


class Gait:
    """The agent's policy: constant (left, right) commands θ, plus optional Gaussian noise."""

    def __init__(self, theta: np.ndarray, noise: float, low: float, high: float):
        self.theta, self.noise, self.low, self.high = np.asarray(theta, float), noise, low, high

    def __call__(self, s: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        a = self.theta.copy()
        if rng is not None and self.noise > 0:
            a = a + rng.normal(0.0, self.noise, 2)
        return np.clip(a, self.low, self.high)


def episode_return(step: RoachStep, theta: np.ndarray, cfg: RoachGaratConfig, rng: np.random.Generator,
                   transform: Callable | None = None) -> float:
    """One episode of the constant gait θ (through the grounding ``transform`` if given)."""
    s = step.reset_state(rng)
    a = np.clip(np.asarray(theta, float), cfg.v_min_rps, cfg.v_max_rps)
    for _ in range(cfg.episode_steps):
        at = a if transform is None else np.asarray(transform(s[None], a[None]))[0]
        s = step(s, at)
    fwd, lat = step.progress()
    return fwd - cfg.lateral_weight * abs(lat)


def evaluate(step: RoachStep, theta: np.ndarray, cfg: RoachGaratConfig, seed: int) -> float:
    """Mean return over ``eval_episodes`` start headings (the same ones for every θ given ``seed``)."""
    rng = np.random.default_rng(seed)
    return float(np.mean([episode_return(step, theta, cfg, rng) for _ in range(cfg.eval_episodes)]))


def gait_commands(p: np.ndarray, cfg: RoachGaratConfig) -> np.ndarray:
    """(mean speed v, left − right difference d) [rev/s] → (left, right) commands in range."""
    v = np.clip(p[..., 0], cfg.v_min_rps, cfg.v_max_rps)
    d = np.clip(p[..., 1], -cfg.max_diff_rps, cfg.max_diff_rps)
    return np.clip(np.stack([v + d / 2, v - d / 2], -1), cfg.v_min_rps, cfg.v_max_rps)


def cem(step: RoachStep, cfg: RoachGaratConfig, seed: int, transform: Callable | None = None) -> np.ndarray:
    """Cross-entropy method over (v, d) (``gait_commands``), ``cem_episodes`` episodes per
    candidate from start headings shared by all candidates of an iteration;
    returns the final mean as (left, right) commands [rev/s]. Searching mean speed and
    difference separately matters: the good gaits lie on a narrow ridge of small left −
    right differences (a difference of 1 rev/s already turns the robot)."""
    rng = np.random.default_rng(seed)
    mean = np.array([0.6 * cfg.v_max_rps, 0.0])
    std = np.array(cfg.cem_init_std_rps, float)
    for _ in range(cfg.cem_iterations):
        cand = mean + std * rng.normal(size=(cfg.cem_population, 2))
        cand[:, 0] = np.clip(cand[:, 0], cfg.v_min_rps, cfg.v_max_rps)
        cand[:, 1] = np.clip(cand[:, 1], -cfg.max_diff_rps, cfg.max_diff_rps)
        heads = rng.integers(0, 2**31, cfg.cem_episodes)  # common start headings for the candidates
        scores = np.array([np.mean([episode_return(step, gait_commands(c, cfg), cfg, np.random.default_rng(h),
                                                   transform) for h in heads]) for c in cand])
        elite = cand[np.argsort(scores)[-cfg.cem_elites:]]
        mean, std = elite.mean(0), np.maximum(elite.std(0), cfg.cem_min_std_rps)
    return gait_commands(mean, cfg)


def collect(step: RoachStep, gait: Gait, n: int, episode_steps: int, seed: int) -> Transitions:
    """``n`` feature transitions of the noisy gait, episodes of ``episode_steps``."""
    rng = np.random.default_rng(seed)
    S, A, S1 = [], [], []
    while len(S) < n:
        s = step.reset_state(rng)
        for _ in range(min(episode_steps, n - len(S))):
            a = gait(s, rng)
            s1 = step(s, a)
            S.append(s), A.append(a), S1.append(s1)
            s = s1
    return Transitions(np.array(S), np.array(A), np.array(S1))


def run_seed(cfg: RoachGaratConfig, log=print) -> dict:
    """One seed: train the gait in source and target, ground the source with GAT and GARAT,
    retrain the gait in each grounded source, evaluate every gait in the target."""
    sd = cfg.seed
    src, tgt = RoachStep(None, sd), RoachStep(cfg.missing_leg, sd, cfg.leg_speed_scale)
    lo, hi = np.full(2, cfg.v_min_rps), np.full(2, cfg.v_max_rps)
    try:
        theta = {"source": cem(src, cfg, sd * 1000 + 1), "target": cem(tgt, cfg, sd * 1000 + 2)}
        explore = Gait(theta["source"], cfg.action_noise_rps, cfg.v_min_rps, cfg.v_max_rps)
        target = collect(tgt, explore, cfg.target_transitions, cfg.episode_steps, sd * 1000 + 3)
        source = collect(src, explore, cfg.source_transitions, cfg.episode_steps, sd * 1000 + 4)
        gat = Gat(source, target, lo, hi, width=cfg.gat_width, layers=cfg.gat_layers, steps=cfg.gat_fit_steps, seed=sd,
                  val_frac=cfg.gat_val_frac)
        garat = train_garat(src, target, src.reset_state, explore, lambda s: False, lo, hi, cfg.episode_steps,
                            replace(cfg.garat, seed=sd))
        theta["gat"] = cem(src, cfg, sd * 1000 + 5, gat)
        theta["garat"] = cem(src, cfg, sd * 1000 + 6, garat)
        ret = {k: evaluate(tgt, th, cfg, sd * 1000 + 7) for k, th in theta.items()}
        ret_src = {k: evaluate(src, th, cfg, sd * 1000 + 7) for k, th in theta.items()}
    finally:
        src.close()
        tgt.close()
    gap = ret["target"] - ret["source"]
    norm = normalise(ret)
    log(f"roach seed {sd}: target return source-trained {ret['source']:.3f} target-trained {ret['target']:.3f} "
        f"gat {ret['gat']:.3f} garat {ret['garat']:.3f} m; normalised gat {norm['gat']} garat {norm['garat']}")
    return {"seed": sd, "theta_rps": {k: [round(float(v), 3) for v in th] for k, th in theta.items()},
            "target_return_m": ret, "source_return_m": ret_src, "gap_m": gap, "normalised_return": norm,
            "garat_disc_updates": garat.disc_updates}


def target_description(cfg: RoachGaratConfig) -> str:
    """The target's change in words (plots, report)."""
    parts = []
    if cfg.leg_speed_scale is not None:
        parts.append(f"leg speed scale (left, right) = ({cfg.leg_speed_scale[0]:g}, {cfg.leg_speed_scale[1]:g})")
    if cfg.missing_leg is not None:
        parts.append(f"leg {cfg.missing_leg} missing")
    return ", ".join(parts) or "unchanged"


def normalise(ret: dict[str, float], min_gap: float = 0.0) -> dict[str, float | None]:
    """Fig. 3's normalisation of target returns: source-trained gait 0, target-trained 1.
    None for every method when the target-trained gait is not better by more than ``min_gap``
    (then the scale means nothing)."""
    gap = ret["target"] - ret["source"]
    return {k: (ret[k] - ret["source"]) / gap if gap > min_gap else None for k in ("source", "gat", "garat")}


def summarise(rows: list[dict]) -> dict:
    """Mean ± std over seeds of the normalised target return (seeds without a gap are left out)."""
    ok = [r for r in rows if r["normalised_return"]["gat"] is not None]
    out: dict = {"seeds": [r["seed"] for r in rows], "seeds_with_gap": [r["seed"] for r in ok]}
    mean, std = {}, {}
    for k in ("source", "gat", "garat"):
        v = np.array([r["normalised_return"][k] for r in ok], float)
        mean[k] = float(v.mean()) if len(v) else None
        std[k] = float(v.std()) if len(v) else None
    out["normalised_return"], out["normalised_return_std"] = mean, std
    out["per_seed"] = rows
    return out
