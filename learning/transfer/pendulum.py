"""GAT vs GARAT on gymnasium's MuJoCo InvertedPendulum-v5 (GARAT paper, Fig. 1).

Source: the stock model (pole 5.0 kg as compiled by MuJoCo from the stock XML). Target: the
same model with a heavier pole (``target_pole_mass_kg``, set with MjSpec and loaded through
``gym.make(..., xml_file=path)``). The agent's policy is SB3 PPO trained in the source.
Transitions of both systems are collected with that policy plus Gaussian action noise
(``action_noise``, env force units) so that the models see more than one action per state.

State s = (cart position [m], pole angle [rad], cart velocity [m/s], pole rate [rad/s]);
action: the env's force command in [-3, 3].
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np

from hilstack.learning.datasets import Transitions
from hilstack.learning.transfer.grounding import (
    GaratConfig,
    Gat,
    floor_error,
    train_garat,
    transition_error,
)

POLE_ANGLE_MAX_RAD = 0.2  # InvertedPendulum-v5 terminates beyond this


@dataclass(frozen=True)
class PendulumConfig:
    target_pole_mass_kg: float = 15.0  # the stock pole is 5.0 kg
    agent_timesteps: int = 30000  # PPO on the source for the agent's policy
    #: PPO's rollout length for the agent (SB3's default); PPO collects whole rollouts, so fewer
    #: ``agent_timesteps`` than this still collect and train on this many
    agent_n_steps: int = 2048
    target_sizes: tuple[int, ...] = (500, 2000, 5000)  # target transitions (the x axis of Fig. 1)
    source_transitions: int = 10000  # for GAT's inverse source model (source data is free)
    validation_transitions: int = 1000
    action_noise: float = 0.5
    max_episode_steps: int = 200
    gat_fit_steps: int = 2000
    gat_width: int = 64  # GAT's forward and inverse MLPs: width, hidden layers, Adam lr
    gat_layers: int = 2
    gat_lr: float = 3e-3
    gat_val_frac: float = 0.0  # early stopping of GAT's models on this held-out share of their data
    gat_alpha: float = 1.0  # GAT's action smoothing (Hanna & Stone)
    garat: GaratConfig = field(default_factory=GaratConfig)
    trace_steps: int = 100
    floor_grid: int = 61  # the floor's search per transition: grid points over [-3, 3], then bounded Brent (scipy)
    floor_iters: int = 40
    seed: int = 0


def make_env(pole_mass_kg: float | None, workdir: Path) -> gym.Env:
    """InvertedPendulum-v5, its pole mass set to ``pole_mass_kg`` (None: stock model)."""
    if pole_mass_kg is None:
        return gym.make("InvertedPendulum-v5")
    if not (math.isfinite(pole_mass_kg) and pole_mass_kg > 0):
        raise ValueError(f"pole mass must be a positive number of kg, got {pole_mass_kg}")
    stock = Path(gym.envs.mujoco.__file__).parent / "assets" / "inverted_pendulum.xml"
    spec = mujoco.MjSpec.from_file(str(stock))
    spec.geom("cpole").mass = pole_mass_kg
    path = Path(workdir) / f"inverted_pendulum_pole_{pole_mass_kg:g}kg.xml"
    path.write_text(spec.to_xml())
    return gym.make("InvertedPendulum-v5", xml_file=str(path))


class StepFrom:
    """``step(s, a) -> s'`` of an InvertedPendulum env from any state (set_state, then one env step)."""

    def __init__(self, env: gym.Env):
        self.env = env.unwrapped
        self.env.reset(seed=0)

    def __call__(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        e = self.env
        e.set_state(np.asarray(s[:2], float), np.asarray(s[2:], float))
        obs, *_ = e.step(np.asarray(a, np.float32).reshape(1))
        return np.asarray(obs, float)

    def reset_state(self, rng: np.random.Generator) -> np.ndarray:
        """The env's own reset distribution (±0.01 uniform around the upright rest state)."""
        e = self.env
        return np.concatenate([e.init_qpos + rng.uniform(-0.01, 0.01, e.model.nq),
                               e.init_qvel + rng.uniform(-0.01, 0.01, e.model.nv)])


def done(s: np.ndarray) -> bool:
    return bool(abs(s[1]) > POLE_ANGLE_MAX_RAD or not np.isfinite(s).all())


class Agent:
    """The agent's policy (deterministic PPO mean) with optional Gaussian exploration noise."""

    def __init__(self, model, noise: float):
        self.model, self.noise = model, noise

    def __call__(self, s: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        a, _ = self.model.predict(np.asarray(s, np.float32), deterministic=True)
        a = np.asarray(a, float).reshape(1)
        if rng is not None and self.noise > 0:
            a = a + rng.normal(0.0, self.noise, 1)
        return np.clip(a, -3.0, 3.0)


def collect(step: StepFrom, agent: Agent, n: int, max_steps: int, seed: int) -> Transitions:
    """``n`` transitions of ``agent`` (with its noise), episodes ending as the env's do."""
    rng = np.random.default_rng(seed)
    S, A, S1 = [], [], []
    s, t = step.reset_state(rng), 0
    while len(S) < n:
        a = agent(s, rng)
        s1 = step(s, a)
        S.append(s), A.append(a), S1.append(s1)
        t += 1
        if done(s1) or t >= max_steps:
            s, t = step.reset_state(rng), 0
        else:
            s = s1
    return Transitions(np.array(S), np.array(A), np.array(S1))


def train_agent(env: gym.Env, timesteps: int, seed: int, n_steps: int = 2048):
    from stable_baselines3 import PPO

    model = PPO("MlpPolicy", env, n_steps=n_steps, seed=seed, device="cpu", verbose=0)
    model.learn(timesteps)
    return model


def angle_trace(step: StepFrom, agent: Agent, s0: np.ndarray, steps: int, transform=None) -> list[float]:
    """Pole angle [rad] of the noiseless policy from ``s0`` (stops when the pole falls)."""
    s, out = np.asarray(s0, float), [float(s0[1])]
    for _ in range(steps):
        a = agent(s)
        if transform is not None:
            a = np.asarray(transform(s[None], a[None]))[0]
        s = step(s, a)
        out.append(float(s[1]))
        if done(s):
            break
    return out


def run(cfg: PendulumConfig, log=print) -> dict:
    """Per-step transition error on held-out target transitions for each target data size,
    none vs GAT vs GARAT, and angle traces from one start state."""
    with tempfile.TemporaryDirectory() as tmp:
        src_env, tgt_env = make_env(None, Path(tmp)), make_env(cfg.target_pole_mass_kg, Path(tmp))
        src, tgt = StepFrom(src_env), StepFrom(tgt_env)
        agent_model = train_agent(src_env, cfg.agent_timesteps, cfg.seed, cfg.agent_n_steps)
        agent = Agent(agent_model, cfg.action_noise)
        n_max = max(cfg.target_sizes)
        target_all = collect(tgt, agent, n_max, cfg.max_episode_steps, cfg.seed + 1)
        val = collect(tgt, agent, cfg.validation_transitions, cfg.max_episode_steps, cfg.seed + 2)
        source = collect(src, agent, cfg.source_transitions, cfg.max_episode_steps, cfg.seed + 3)
        low, high = np.array([-3.0]), np.array([3.0])
        none = transition_error(src, val)
        # the floor: the best any action transform can do on these transitions (no exact mapping
        # exists: one force cannot reproduce a heavier pole's whole state change)
        floor = floor_error(src, val, low, high, cfg.floor_grid, cfg.floor_iters)
        log(f"pendulum: floor of the per-step error (best ã per transition) {floor:.4f}, none {none:.4f}")
        curve = []
        gat = garat = None
        for n in sorted(cfg.target_sizes):
            target = target_all.subset(slice(0, n))
            gat = Gat(source, target, low, high, width=cfg.gat_width, layers=cfg.gat_layers, steps=cfg.gat_fit_steps,
                      seed=cfg.seed, lr=cfg.gat_lr, alpha=cfg.gat_alpha, val_frac=cfg.gat_val_frac)
            garat = train_garat(src, target, src.reset_state, agent, done, low, high, cfg.max_episode_steps,
                                cfg.garat)
            row = {"target_transitions": n, "none": none, "gat": transition_error(src, val, gat),
                   "garat": transition_error(src, val, garat), "floor": floor,
                   "garat_selected_update": garat.selected_update, "garat_disc_updates": garat.disc_updates}
            log(f"pendulum: {n} target transitions: error none {row['none']:.4f} gat {row['gat']:.4f} "
                f"garat {row['garat']:.4f} floor {floor:.4f}")
            curve.append(row)
        s0 = src.reset_state(np.random.default_rng(cfg.seed + 4))
        traces = {
            "target": angle_trace(tgt, agent, s0, cfg.trace_steps),
            "source": angle_trace(src, agent, s0, cfg.trace_steps),
            "gat": angle_trace(src, agent, s0, cfg.trace_steps, gat),
            "garat": angle_trace(src, agent, s0, cfg.trace_steps, garat),
        }
        src_env.close()
        tgt_env.close()
    last = curve[-1]
    return {"grounding_error": {k: last[k] for k in ("none", "gat", "garat", "floor")}, "curve": curve,
            "angle_traces_rad": traces, "target_pole_mass_kg": cfg.target_pole_mass_kg}
