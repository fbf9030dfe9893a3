"""Excitation recordings of a robot's bench for `hil calibrate --model <robot config>`.

:func:`record_excitation` drives a robot's sim backend (the real driver code over the
in-process bus on the bench's MuJoCo world and servo firmware, in lockstep: the physics the
bus emulator process runs, without the pty's real-time pacing) with a smooth random
multi-sine tracked by a proportional command, and writes what a rig recording holds (a
spec message, then one RobotState per period with the action held during it) to an MCAP.
The bench can carry effects its MuJoCo model lacks (``effects``: for the WidowX, gearbox
friction, damping, an input delay, see :data:`hilstack.sim_backends.dynamixel.firmware.EFFECTS`),
so that calibration has something to find.

The robot comes from the driver registry, so this works for any robot whose sim backend
takes ``params.sim.effects`` and has joint-velocity actions over position/velocity state.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: a mid-range pose of the WidowX (rad), away from the limits, torqued at start
WIDOWX_MID_POSE = {"waist": 0.0, "shoulder": -0.3, "elbow": 0.3, "forearm_roll": 0.0, "wrist_angle": 0.4,
                   "wrist_rotate": 0.0}


def excitation_targets(n_joints: int, duration_s: float, seed: int, amplitude_rad: float = 0.35,
                       f_lo_hz: float = 0.08, f_hi_hz: float = 0.6, n_sines: int = 4):
    """A random multi-sine per joint: returns f(t) -> (q_ref offset [rad], dq_ref [rad/s]).

    Peak offset stays below ``amplitude_rad`` (the sines' amplitudes sum to it)."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(f_lo_hz, f_hi_hz, (n_joints, n_sines))
    ph = rng.uniform(0, 2 * np.pi, (n_joints, n_sines))
    a = rng.uniform(0.3, 1.0, (n_joints, n_sines))
    a *= amplitude_rad / a.sum(1, keepdims=True)

    def ref(t: float) -> tuple[np.ndarray, np.ndarray]:
        w = 2 * np.pi * f
        return (a * np.sin(w * t + ph)).sum(1), (a * w * np.cos(w * t + ph)).sum(1)

    del duration_s  # the sines are defined for all t
    return ref


def record_excitation(path: str | Path, duration_s: float = 60.0, seed: int = 0, robot: str = "widowx",
                      effects: dict[str, float] | None = None, period_s: float = 0.02, gain_1_s: float = 2.0,
                      rig: str = "calib", overwrite: bool = False, mjcf: str | None = None,
                      backend: str = "sim") -> Path:
    """Drive ``robot``'s sim bench with a random multi-sine for ``duration_s`` (sim time) and write
    the rig recording to ``path`` (an existing file is refused unless ``overwrite``).

    Commands: joint velocities ``dq_ref + gain_1_s·(q_mid + q_ref − q)``, within the driver's
    limits (the driver clamps and rate-limits them as on the rig; the applied action is recorded).

    ``backend="emulated"``: the real driver over a pty to the bus emulator process, whose servos
    carry ``effects`` (``params.emulator.effects``); paced in real time (``duration_s`` of wall clock).
    """
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import RobotState, SpecMsg
    from hilstack.drivers.registry import make_driver

    bench = {"start_holding": WIDOWX_MID_POSE, "effects": dict(effects or {})}
    if mjcf is not None:
        bench["mjcf"] = str(mjcf)
    if backend not in ("sim", "emulated"):
        raise ValueError(f"backend must be 'sim' or 'emulated', got {backend!r}")
    # a bus name of its own: never share a world with another robot of this process
    # a reading older than 5 periods is stale (it must be shorter than the link's error deadline)
    d = make_driver(robot, backend=backend, bus_name=f"excite-{seed}-{id(bench)}", period_s=period_s,
                    telemetry_stale_s=min(0.25, 5 * period_s),
                    **({"sim": bench} if backend == "sim" else {"emulator": bench}))
    names = list(d.spec.state.names)
    n = d.spec.action.dim
    mid = np.array([WIDOWX_MID_POSE.get(nm, 0.0) for nm in names[:n]])
    ref = excitation_targets(n, duration_s, seed)
    steps = int(round(duration_s / period_s))
    with d, McapLog(path, overwrite=overwrite, foxglove=False) as log:
        log.write(keys.spec(rig, robot), SpecMsg(robot=robot, spec=d.spec.to_dict(), seq=1))
        obs = d.read()
        t0 = obs.t_s
        applied: list[float] = []
        for k in range(steps + 1):
            log.write(keys.state(rig, robot),
                      RobotState(robot=robot, t_s=obs.t_s - t0, state=[float(v) for v in obs.state],
                                 action=applied, episode=0, seq=k + 2, stamp_s=1000.0 + obs.t_s - t0,
                                 active=True, ok=obs.ok))
            if k == steps:
                break
            q_off, dq = ref(obs.t_s - t0)
            u = dq + gain_1_s * (mid + q_off - np.asarray(obs.state[:n]))
            applied = [float(v) for v in d.write(u)]
            d.tick()
            obs = d.read()
    return Path(path)
