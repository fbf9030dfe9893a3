"""VelociRoACH episodes with a known hidden change, generated in-process by the sim backend.

Used by the tests and the docs' example: each episode starts from rest at a random pose and
drives random leg-velocity steps (both sides independently, so the robot runs straight and
turns). The sim runs with its sensor noise on; ``hidden`` changes ``params.sim`` (e.g.
``{"payload_kg": 0.03}`` or ``{"friction": 1.6}``) and is what calibration must recover.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hilstack.calibration.data import Recording


@dataclass
class RoachSynthConfig:
    """Episodes: ``n_episodes`` of ``duration_s`` [s]; commands held ``hold_s`` [s] each,
    uniform in ``cmd_range_rps`` [rev/s]; ``hidden``: params.sim overrides of the 'real' robot."""

    n_episodes: int = 12
    duration_s: float = 3.0
    hold_s: float = 0.5
    cmd_range_rps: tuple[float, float] = (3.0, 13.0)
    seed: int = 0
    hidden: dict = field(default_factory=dict)
    arena_m: float = 1.0


def generate(cfg: RoachSynthConfig) -> list[Recording]:
    from hilstack.drivers.velociroach.config import STATE_NAMES, VelociRoachParams
    from hilstack.sim_backends.velociroach.backend import VelociRoachSim

    rng = np.random.default_rng(cfg.seed)
    out = []
    sim = VelociRoachSim(VelociRoachParams(sim={"seed": cfg.seed, **cfg.hidden}))
    sim.configure()
    period = sim.spec.period_s
    n_steps = int(round(cfg.duration_s / period))
    hold = max(1, int(round(cfg.hold_s / period)))
    names = sim.spec.action.names
    for i in range(cfg.n_episodes):
        if sim.active:
            sim.deactivate()
        x0, y0 = rng.uniform(-cfg.arena_m, cfg.arena_m, 2)
        sim.reset(float(x0), float(y0), float(rng.uniform(-np.pi, np.pi)))
        sim.activate()
        states = [sim.read().state]
        times = [sim.sim_time_s]
        actions = []
        cmd = rng.uniform(*cfg.cmd_range_rps, 2)
        for k in range(n_steps):
            if k % hold == 0:
                cmd = rng.uniform(*cfg.cmd_range_rps, 2)
            actions.append(sim.write(cmd))  # the applied (rate-limited) command is what a rig records
            sim.tick()
            obs = sim.read()
            states.append(obs.state)
            times.append(obs.t_s)
        acts = np.asarray(actions)
        out.append(Recording(
            name=f"roach_seed{cfg.seed}_ep{i}",
            t_s=np.asarray(times) - times[0],
            u=np.concatenate([acts[:, 0], acts[-1:, 0]]),
            x=np.asarray(states)[:, 0],
            meta={"source": "hilstack.calibration.synthetic_velociroach", "hidden": dict(cfg.hidden)},
            states=np.asarray(states),
            actions=np.concatenate([acts, acts[-1:]]),
            state_names=tuple(STATE_NAMES),
            action_names=tuple(names),
        ))
    sim.cleanup()
    return out


def write_mcap(episodes: list[Recording], path: str | Path, robot: str = "roach", rig: str = "calib") -> Path:
    """Write episodes as a rig recording: a spec message, then one RobotState per period
    carrying the action held during the period that ended with it and an episode counter."""
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import RobotState, SpecMsg
    from hilstack.drivers.velociroach.config import VelociRoachParams, velociroach_spec

    spec = velociroach_spec(VelociRoachParams()).to_dict()
    seq = 0
    t_base = 0.0
    with McapLog(path) as log:
        log.write(keys.spec(rig, robot), SpecMsg(robot=robot, spec=spec, seq=1))
        for ep_i, e in enumerate(episodes):
            for k in range(e.n):
                seq += 1
                action = [] if k == 0 else [float(v) for v in e.actions[k - 1]]
                t = t_base + float(e.t_s[k])
                log.write(keys.state(rig, robot),
                          RobotState(robot=robot, t_s=t, state=[float(v) for v in e.states[k]], action=action,
                                     episode=ep_i, seq=seq, stamp_s=1000.0 + t, active=True))
            t_base += float(e.t_s[-1]) + 1.0
    return Path(path)
