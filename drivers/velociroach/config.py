"""VelociRoACH settings and spec, shared by every backend (real, emulated, sim).

State: the 24-D state of Nagabandi's thesis (ch. 3). Action: leg-velocity setpoints
[rev/s of the crank] or direct PWM duty [-1, 1], chosen by ``action_mode``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field

from hilstack.configs.schema import (
    EmulatorParams,
    EmulatorS,
    FailAfterS,
    Params,
    Periods,
    RateHz,
    StaleS,
    TimeoutS,
    WatchdogS,
    finite,
)
from hilstack.drivers.base import Flag, RobotSpec, Space
from hilstack.drivers.velociroach.mavlink import mav

STATE_CHANNELS: list[tuple[str, str]] = [
    ("x", "m"), ("y", "m"), ("z", "m"),
    ("vx", "m/s"), ("vy", "m/s"), ("vz", "m/s"),
    ("cos_roll", "1"), ("sin_roll", "1"),
    ("cos_pitch", "1"), ("sin_pitch", "1"),
    ("cos_yaw", "1"), ("sin_yaw", "1"),
    ("wx", "rad/s"), ("wy", "rad/s"), ("wz", "rad/s"),
    ("cos_crank_l", "1"), ("sin_crank_l", "1"),
    ("cos_crank_r", "1"), ("sin_crank_r", "1"),
    ("crank_vel_l", "rev/s"), ("crank_vel_r", "rev/s"),
    ("bemf_l", "V"), ("bemf_r", "V"),
    ("vbat", "V"),
]
STATE_NAMES = tuple(n for n, _ in STATE_CHANNELS)


#: the firmware's fault bits (defined once: the ROACH_FAULT enum of dialect/velociroach.xml)
#: as the contract's flags; every backend reports all of them
FAULT_FLAGS: dict[int, Flag] = {
    mav.ROACH_FAULT_WATCHDOG: Flag.WATCHDOG,
    mav.ROACH_FAULT_LOW_BATTERY: Flag.LOW_BATTERY,
    mav.ROACH_FAULT_MOTOR: Flag.MOTOR_FAULT,
    mav.ROACH_FAULT_RX_CORRUPT: Flag.RX_CORRUPT,
    mav.ROACH_FAULT_SENSOR: Flag.SENSOR_FAULT,
}


#: crank speed limit [rev/s]
LegVelRps = finite(gt=0, le=20.0, source=(
    "the 7 mm coreless motors' no-load crank speed, ≈ 20 rev/s at 4 V (docs/velociroach.md, 'Model')"))
#: leg-velocity rate limit [rev/s²]
LegAccelRps2 = finite(gt=0, le=120.0, source=(
    "the largest setpoint step the firmware PID turns into a current spike below its 1.4 A over-current fault "
    "is 12.3 rev/s; at the slowest allowed period (0.1 s) that is 123 rev/s² (docs/velociroach.md, 'Rate limit')"))
#: VelociRoACH control period [s]
RoachPeriodS = finite(ge=0.001, le=0.1, source=(
    "≤ 0.1 s (the thesis' 10 Hz): the rate limit's bound (≤ 12 rev/s per step at ≤ 120 rev/s²) holds only at "
    "10 Hz or faster"))
#: the emulator's pacing [sim s per wall-clock s] (not a safety value)
RealtimeFactor = finite(gt=0, le=100.0, source="emulator pacing: up to 100× the wall clock (not a safety value)")


def fault_flags(bits: int) -> dict[str, bool]:
    """The firmware's fault bitmask as contract flags (all five, each True or False)."""
    return {f.value: bool(bits & bit) for bit, f in FAULT_FLAGS.items()}


class VelociRoachEmulatorParams(EmulatorParams):
    """``params.emulator``: how the driver starts the firmware emulator (backend emulated;
    start timeout and log from the shared :class:`hilstack.configs.schema.EmulatorParams`) and the
    faults it injects. Unknown keys are errors."""

    pose: bool = Field(True, description="stream the sim's mocap pose to the driver over UDP")
    connect_timeout_s: TimeoutS = Field(10.0, description="time for the first heartbeat and telemetry")
    realtime_factor: RealtimeFactor = Field(1.0, description="sim seconds per wall-clock second")
    pose_hz: RateHz = Field(100.0, description="rate of the UDP pose stream")
    seed: int = Field(0, description="seed of the fault injection's noise")
    physics: str | None = Field(None, pattern=r"^[\w.]+:\w+$", description="module:Class of the physics")
    lab_fixture: bool = Field(
        True, description="serve the lab fixture beside the robot (drivers/fixture.py): the stand-in for "
                          "the lab's hands that puts a robot on its back onto its legs; its UDP port is in the "
                          "driver's health as lab_fixture_port")
    # fault injection
    corrupt_every: int = Field(0, ge=0, description="break every N-th frame sent (0: never)")
    garbage: bool = Field(False, description="noise bytes between frames")
    silence_after_s: EmulatorS | None = Field(
        None, description="radio outage both ways S s after the first command (the mocap keeps streaming)")
    pose_silence_after_s: EmulatorS | None = Field(
        None, description="mocap outage: the pose stream stops S s after the first command")
    nonfinite_telemetry_every: int = Field(0, ge=0, description="every N-th telemetry carries NaN sensor values")
    start_upside_down: bool = Field(False, description="the robot starts on its back, as after a flip")


class VelociRoachParams(Params):
    """Everything configurable about the robot and its link. Units in names."""

    action_mode: Literal["leg_velocity", "pwm"] = "leg_velocity"
    max_leg_vel_rps: LegVelRps = Field(15.0, description="crank rev/s at action +1")
    max_leg_accel_rps2: LegAccelRps2 = Field(
        120.0,
        description="rate limit on leg-velocity commands [rev/s²]; one period's worth (12 rev/s at 10 Hz) is the "
                    "largest setpoint step the firmware PID turns into a current spike below the over-current "
                    "fault (docs/velociroach.md, 'Rate limit')")
    period_s: RoachPeriodS = Field(0.1, description="control period (thesis: 10 Hz)")
    # link (real/emulated)
    port: str | None = Field(None, description="serial port of the base-station XBee, e.g. /dev/ttyUSB0")
    baudrate: int = Field(230400, gt=0)
    robot_addr64: str = Field("0013A20040A1B2C3", pattern=r"^[0-9A-Fa-f]{16}$")
    telemetry_hz: RateHz = 100.0
    write_timeout_s: FailAfterS = Field(
        0.5, description="a write to the serial port not done within this is a link failure; pyserial counts "
                               "the writing thread's own scheduling stalls in it (docs/reset.md, 'CPU stalls')")
    telemetry_deadline_s: StaleS = Field(
        0.3, description="telemetry older than this is stale: ok=False, flags.stale_telemetry")
    link_timeout_periods: Periods = Field(
        10, description="no usable telemetry for this many control periods with the link open: error path")
    pose_deadline_s: StaleS = Field(
        0.25, description="a mocap pose older than this is stale: ok=False, flags.stale_pose (mocap >= 10 Hz)")
    firmware_watchdog_s: WatchdogS = 0.5
    tlog: str | None = Field(None, description="write every MAVLink frame to this .tlog")
    mocap_udp_port: int | None = Field(
        None, ge=0, le=65535, description="real: receive the robot's mocap pose here (hilstack.drivers.mocap.udp stream)")
    # sim (ignored by the real driver); the sim backend reads the rest from here too
    sim: dict = Field(default_factory=dict, description="sim backend settings (terrain, motor, battery...)")
    emulator: VelociRoachEmulatorParams = Field(default_factory=VelociRoachEmulatorParams,
                                                description="emulator settings and fault injection")


def velociroach_spec(p: VelociRoachParams) -> RobotSpec:
    lo = np.full(len(STATE_CHANNELS), -np.inf)
    hi = np.full(len(STATE_CHANNELS), np.inf)
    for i, (n, _) in enumerate(STATE_CHANNELS):
        if n.startswith(("cos_", "sin_")):
            lo[i], hi[i] = -1.0, 1.0
    state = Space(STATE_NAMES, tuple(u for _, u in STATE_CHANNELS), lo, hi)
    if p.action_mode == "leg_velocity":
        m = p.max_leg_vel_rps
        action = Space.build([("leg_vel_l", "rev/s", -m, m), ("leg_vel_r", "rev/s", -m, m)])
        rate = np.full(2, p.max_leg_accel_rps2)
    else:
        action = Space.build([("duty_l", "1", -1.0, 1.0), ("duty_r", "1", -1.0, 1.0)])
        rate = np.full(2, p.max_leg_accel_rps2 / p.max_leg_vel_rps)
    return RobotSpec(
        name="velociroach",
        state=state,
        action=action,
        period_s=p.period_s,
        action_rate_per_s=rate,
        safe_action=np.zeros(2),
        description="VelociRoACH hexapod, 2 motors driving 3 legs each",
    )


def quat_to_rpy(q_wxyz) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) [rad] of a unit quaternion (w, x, y, z): how
    every backend turns a pose into the state's orientation channels."""
    w, x, y, z = (float(v) for v in q_wxyz)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw
