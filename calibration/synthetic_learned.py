"""A tiny system for the ``checkpoint`` model: a 1-D point mass with an input a learned model may lack.

State [x [m], v [m/s]], action u (a normalized force command in [-1, 1]), period 0.05 s:

    v_{k+1} = v_k + dt·(gain·u_eff − drag·v_k) + w_k,   x_{k+1} = x_k + dt·v_{k+1}

with u_eff = u_k (no hidden dependence), u_{k-1} (``hidden="delay"``: actuation one period
late) or u_k·vbat_k/7.4 V (``hidden="vbat"``: the force scales with a battery voltage that
starts between 6.6 and 8.4 V and sags through the episode). w is process noise only (no
measurement noise: noisy measurements would make the lagged state change genuinely
informative, which is a real effect, not the negative control's "nothing").

Actions are random steps held 1-4 periods, so a_{k-1} differs from a_k about half the time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hilstack.calibration.data import Recording

PERIOD_S = 0.05
STATE_NAMES = ("x", "v")
ACTION_NAMES = ("u",)
VBAT_NOMINAL_V = 7.4


def generate(n_episodes: int = 24, steps: int = 100, hidden: str = "none", seed: int = 0,
             gain: float = 4.0, drag: float = 1.5, noise_mps: float = 0.01) -> list[Recording]:
    """Calibration episodes (states/actions with names; vbat logged in every case)."""
    if hidden not in ("none", "delay", "vbat"):
        raise ValueError(f"hidden must be none, delay or vbat, got {hidden!r}")
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_episodes):
        u = np.empty(steps)
        k = 0
        while k < steps:
            hold = int(rng.integers(1, 5))
            u[k:k + hold] = rng.uniform(-1, 1)
            k += hold
        vbat0 = rng.uniform(6.6, 8.4)
        vbat = vbat0 - 0.6 * np.linspace(0, 1, steps + 1) + 0.01 * rng.standard_normal(steps + 1)
        x, v = np.zeros(steps + 1), np.zeros(steps + 1)
        x[0], v[0] = rng.uniform(-0.5, 0.5), 0.0
        for t in range(steps):
            ue = {"none": u[t], "delay": u[t - 1] if t > 0 else 0.0, "vbat": u[t] * vbat[t] / VBAT_NOMINAL_V}[hidden]
            v[t + 1] = v[t] + PERIOD_S * (gain * ue - drag * v[t]) + noise_mps * rng.standard_normal()
            x[t + 1] = x[t] + PERIOD_S * v[t + 1]
        t_s = PERIOD_S * np.arange(steps + 1)
        states = np.stack([x, v], axis=1)
        actions = np.concatenate([u, u[-1:]])[:, None]  # last row repeats: no next state
        out.append(Recording(name=f"{hidden}{i:03d}", t_s=t_s, u=actions[:, 0], x=x, vbat_v=vbat,
                           meta={"source": "synthetic_learned", "hidden": hidden}, states=states, actions=actions,
                           state_names=STATE_NAMES, action_names=ACTION_NAMES))
    return out


def train_checkpoint(path: str | Path, n_episodes: int = 40, steps: int = 100, seed: int = 100,
                     hidden_sizes: tuple[int, ...] = (64, 64), ensemble: int = 2, epochs: int = 40,
                     data_hidden: str = "none") -> Path:
    """Train a small EnsembleDynamics on (s_t, a_t) only and save it: the nominal learned model.

    ``data_hidden`` is the system it is trained on: a model trained on a delayed system
    still lacks a_{t-1} and learns the average response, as a real checkpoint would.
    """
    import torch

    from hilstack.learning.dynamics import EnsembleDynamics

    eps = generate(n_episodes, steps, hidden=data_hidden, seed=seed)
    train = [e.transitions() for e in eps]
    torch.manual_seed(seed)
    net = EnsembleDynamics(2, 1, ensemble, hidden_sizes, state_names=STATE_NAMES, action_names=ACTION_NAMES,
                           state_units=["m", "m/s"], action_units=["1"], seed=seed)
    net.fit(train, epochs=epochs, batch_size=256, progress=False)
    path = Path(path)
    net.save(path)
    return path


def write_csv(episodes: list[Recording], path: str | Path) -> Path:
    """One CSV with columns episode, time, pos_m, vel_mps, cmd, vbat_v (names differ from the
    checkpoint's x, v, u on purpose: the CLI maps them with --map x=pos_m,v=vel_mps,u=cmd,t=time)."""
    import pandas as pd

    rows = [pd.DataFrame({"episode": i, "time": e.t_s, "pos_m": e.states[:, 0], "vel_mps": e.states[:, 1],
                          "cmd": e.actions[:, 0], "vbat_v": e.vbat_v}) for i, e in enumerate(episodes)]
    path = Path(path)
    pd.concat(rows).to_csv(path, index=False)
    return path
