"""Excitation recordings of a robot's bench for `hil calibrate --model <robot config>`.

:func:`record_excitation` drives a robot's sim backend (the real driver code over the
in-process bus on the bench's MuJoCo world and servo firmware, in lockstep: the physics the
bus emulator process runs, without the pty's real-time pacing) with a smooth random
multi-sine tracked by a proportional command, and writes what a rig recording holds (a
spec message, then one RobotState per period with the action held during it) to an MCAP.
The bench can carry effects its MuJoCo model lacks (``effects``: for the WidowX, gearbox
friction, damping, an input delay, see :data:`hilstack.sim_backends.dynamixel.firmware.EFFECTS`),
so that calibration has something to find.

The robot comes from the driver registry; what its bench needs is its sim backend's
``calibration_bench()["excite"]`` (where its effects go per backend, the driver settings and
bench options of an excitation, its mid pose): the WidowX (joint-velocity actions tracking the
multi-sine) and the Shadow Hand (normalized joint-position targets on the multi-sine, balls
parked; the efforts its motors report are appended to the recorded state, as the calibration
needs them to start the firmware loops' integrators).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


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


def record_excitation(path: str | Path, duration_s: float = 60.0, seed: int = 0, robot: object = "widowx",
                      effects: dict[str, float] | None = None, period_s: float | None = 0.02,
                      gain_1_s: float = 2.0, rig: str = "calib", overwrite: bool = False, mjcf: str | None = None,
                      backend: str | None = None, progress=None) -> Path:
    """Drive ``robot``'s bench with a random multi-sine for ``duration_s`` and write the rig
    recording to ``path`` (an existing file is refused unless ``overwrite``).

    ``robot``: a robot config name or path, or a ``RobotConfig`` (a rig's entry,
    ``configs.schema.rig_robot_config``: its backend and params are kept). ``backend``: sim
    (default for a name; lockstep, ``duration_s`` of sim time) or emulated (the real driver over
    a pty to the bus emulator process, whose servos carry ``effects`` as
    ``params.emulator.effects``; paced on the wall clock, ``duration_s`` of it).

    Commands: joint velocities ``dq_ref + gain_1_s·(q_mid + q_ref − q)`` (the WidowX) or position
    targets ``q_mid + q_ref`` (the hand, normalized), within the driver's limits (the driver clamps
    and rate-limits them as on the rig; the applied action is recorded).
    ``period_s`` None: the robot config's control period. ``progress(k, steps)`` is called every
    50 periods.
    """
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import NO_DEVICE_CLOCK, RobotState, SpecMsg
    from hilstack.calibration.mjcf_robot import CalibrationBench
    from hilstack.configs.schema import RobotConfig, load_robot
    from hilstack.drivers.registry import make_driver, resolve

    cfg = robot if isinstance(robot, RobotConfig) else load_robot(str(robot), backend=backend or "sim")
    backend = backend or cfg.backend
    if backend not in ("sim", "emulated"):
        raise ValueError(f"backend must be 'sim' or 'emulated' (an excitation with effects injected), got {backend!r}")
    sim_cls = resolve(cfg.robot, "sim")
    if not issubclass(sim_cls, CalibrationBench):
        raise ValueError(f"robot {cfg.robot!r}: its sim backend has no calibration_bench() (nothing to excite for)")
    layout = sim_cls.calibration_bench()
    ex = layout["excite"]
    place = ex["place"][backend]
    own = dict(cfg.params.get(place) or {})
    bench = {**own, **ex.get("bench", {}), "effects": {**(own.get("effects") or {}), **(effects or {})}}
    if mjcf is not None:
        bench["mjcf"] = str(mjcf)
    period_s = float(period_s or cfg.params.get("period_s") or 0.02)
    drv_params = {k: (v.format(seed=seed, uid=id(bench)) if isinstance(v, str) else v)
                  for k, v in ex.get("driver", {}).items()}
    if "telemetry_stale_s" in drv_params:  # a reading older than 5 periods is stale (before the link's error deadline)
        drv_params["telemetry_stale_s"] = min(float(drv_params["telemetry_stale_s"]), 5 * period_s)
    d = make_driver(cfg, backend=backend, period_s=period_s, **drv_params, **{place: bench})
    name = cfg.robot
    spec = d.spec.to_dict()
    extra = ex.get("extra_state")  # an Observation.extras entry appended to the state (the hand's efforts)
    if extra:
        spec["state"]["names"] = list(spec["state"]["names"]) + list(ex["extra_names"])
        for key, fill in (("units", ex.get("extra_unit", "")), ("low", -np.inf), ("high", np.inf)):
            spec["state"][key] = list(spec["state"][key]) + [fill] * len(ex["extra_names"])
    n = d.spec.action.dim
    mid = np.asarray(ex["mid"], float)
    position = ex["command"] == "position"
    ref = excitation_targets(n, duration_s, seed, amplitude_rad=float(ex.get("amplitude", 0.35)))
    steps = int(round(duration_s / period_s))

    # a device whose clock stamps the whole reading (the hand: one telemetry cycle, sampled at one
    # firmware tick) can have a reading that is not ok only because it reached the host late
    # (stale_telemetry): it stays not ok, and is marked late so that the loader keeps it on the
    # device clock (learning/recordings.py). A WidowX reading is not: its stamp is the first
    # servo's, and a stale reading there is one whose other servos did not all answer.
    whole = bool(ex.get("whole_reading_clock"))

    def late(obs) -> bool:
        return (whole and not obs.ok and obs.device_t_s is not None and obs.flag("stale_telemetry")
                and not obs.flag("nonfinite_input") and not obs.flag("invalid_input"))

    def state_of(obs) -> list[float]:
        st = [float(v) for v in obs.state]
        if extra:
            st += [float(v) for v in np.ravel(obs.extras[extra])]
        return st

    with d, McapLog(path, overwrite=overwrite, foxglove=False) as log:
        log.write(keys.spec(rig, name), SpecMsg(robot=name, spec=spec, seq=1))
        obs = d.read()
        t0 = obs.t_s
        dev0 = obs.device_t_s
        applied: list[float] = []
        for k in range(steps + 1):
            dev = NO_DEVICE_CLOCK if dev0 is None or obs.device_t_s is None else obs.device_t_s - dev0
            log.write(keys.state(rig, name),
                      RobotState(robot=name, t_s=obs.t_s - t0, state=state_of(obs), device_t_s=dev,
                                 action=applied, episode=0, seq=k + 2, stamp_s=1000.0 + obs.t_s - t0,
                                 active=True, ok=obs.ok, health={"late": True} if late(obs) else {}))
            if k == steps:
                break
            if progress is not None and k % 50 == 0:
                progress(k, steps)
            q_off, dq = ref(obs.t_s - t0)
            if position:  # targets on the multi-sine (normalized), the driver rate-limits them
                u = mid + q_off
            else:  # joint velocities tracking it
                u = dq + gain_1_s * (mid + q_off - np.asarray(obs.state[:n]))
            applied = [float(v) for v in d.write(u)]
            d.tick()
            obs = d.read()
    return Path(path)
