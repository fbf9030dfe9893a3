"""Batched open-loop rollouts through MuJoCo's ``rollout`` module (C loop, optional threads).

For data that does not need the bus or a per-step Python loop: random-action data for a
dynamics model, when the backend's command goes straight into ``data.ctrl`` and is held
for a control period (no firmware between the command and the actuators). A backend with
an on-board loop in Python (the VelociRoACH's 1 kHz PID, the servo firmware of the arms
and the hand) does not qualify: its actuator input depends on the state every tick.

:func:`rollout_held` steps ``B`` copies of a model from one or ``B`` initial states with
``B`` command sequences, each command held for ``substeps`` physics steps, and returns
the full physics state after every control period. :func:`rate_bounded_walk` makes the
commands a random-data collector sends: a random walk inside the action bounds whose steps
stay within the rate limit, so the contract's limiter would apply them unchanged.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

__all__ = ["STATE_SPEC", "physics_state", "rate_bounded_walk", "rollout_held"]

#: what a rollout state holds: time, qpos, qvel, act (and plugin state)
STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS


def physics_state(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """The full physics state of ``data`` (the layout :func:`rollout_held` returns)."""
    out = np.empty(mujoco.mj_stateSize(model, STATE_SPEC))
    mujoco.mj_getState(model, data, out, STATE_SPEC)
    return out


def rollout_held(model: mujoco.MjModel, initial_state: np.ndarray, commands: np.ndarray, substeps: int,
                 threads: int = 1) -> np.ndarray:
    """Roll out ``commands`` ``[B, T, nu]`` (each held for ``substeps`` physics steps) from
    ``initial_state`` (``[nstate]`` or ``[B, nstate]``, see :func:`physics_state`).

    Returns ``[B, T + 1, nstate]``: the initial state, then the state after each period.
    ``threads`` > 1 runs the batch on that many threads (MuJoCo's thread pool)."""
    commands = np.asarray(commands, dtype=np.float64)
    if commands.ndim != 3 or commands.shape[2] != model.nu:
        raise ValueError(f"commands must be [B, T, nu={model.nu}], got shape {commands.shape}")
    if substeps < 1 or threads < 1:
        raise ValueError(f"substeps and threads must be >= 1, got {substeps} and {threads}")
    b, t, _ = commands.shape
    init = np.asarray(initial_state, dtype=np.float64)
    nstate = mujoco.mj_stateSize(model, STATE_SPEC)
    if init.shape[-1] != nstate or init.ndim not in (1, 2) or (init.ndim == 2 and init.shape[0] not in (1, b)):
        raise ValueError(f"initial_state must be [{nstate}] or [B={b}, {nstate}], got shape {init.shape}")
    init = np.broadcast_to(init.reshape(-1, nstate), (b, nstate)).copy()
    ctrl = np.repeat(commands, substeps, axis=1)  # [B, T*substeps, nu]
    datas = [mujoco.MjData(model) for _ in range(threads)]
    states, _ = mj_rollout.rollout(model, datas if threads > 1 else datas[0], init, ctrl)
    out = np.empty((b, t + 1, nstate))
    out[:, 0] = init
    out[:, 1:] = states[:, substeps - 1::substeps]
    return out


def rate_bounded_walk(low: np.ndarray, high: np.ndarray, max_step: np.ndarray | None, batch: int, steps: int,
                      rng: np.random.Generator, start: np.ndarray | None = None) -> np.ndarray:
    """``[batch, steps, A]`` random commands: each step a uniform draw of at most
    ``max_step`` per channel (rate × period; None: anywhere in the bounds), clipped to
    ``[low, high]``, starting from ``start`` (default zeros, clipped)."""
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    a = np.clip(np.zeros_like(low) if start is None else np.asarray(start, dtype=np.float64), low, high)
    if max_step is None:
        return rng.uniform(low, high, size=(batch, steps, low.shape[0]))
    step = np.minimum(np.asarray(max_step, dtype=np.float64), high - low)
    out = np.empty((batch, steps, low.shape[0]))
    cur = np.broadcast_to(a, (batch, low.shape[0])).copy()
    for k in range(steps):
        cur = np.clip(cur + rng.uniform(-step, step, size=cur.shape), low, high)
        out[:, k] = cur
    return out
