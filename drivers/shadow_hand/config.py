"""Shadow Hand settings and spec, shared by every backend (real, emulated, sim).

State (48-D): the 24 joint angles [rad] then the 24 joint velocities [rad/s], in
``JOINT_NAMES`` order (wrist, first/middle/ring/little finger, thumb; the Shadow
naming: J0 is the distal joint). The ball positions of the Baoding task come from a
tracker (sim: the simulator, in ``Observation.extras``), not from the hand; with
``objects_in_state`` they are also appended to the state (``BALL_CHANNELS``, 54-D), as
the roach's driver fuses its mocap pose into its state, so they reach the bus, the
recordings and the reset supervisor's drop detector.

Action (20-D): one normalized position target in [-1, 1] per actuated joint
(``ACTUATED_JOINTS``), mapped linearly onto the joint's range: -1 → lower limit,
+1 → upper limit. The distal joints FFJ0/MFJ0/RFJ0/LFJ0 are not actuated: each is
coupled to its J1 (J0 ≈ 1.14·J1 in the model, one tendon pair on the real hand), so
the thesis' "24-D action" is 20 independent targets on this hand (docs/shadow_hand.md).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from hilstack.configs.schema import (
    EmulatorParams,
    EmulatorS,
    Params,
    PeriodS,
    Periods,
    RateHz,
    StaleS,
    TimeoutS,
    WatchdogS,
    finite,
)
from hilstack.drivers.base import RobotSpec, Space

JOINT_NAMES: tuple[str, ...] = (
    "WRJ1", "WRJ0",
    "FFJ3", "FFJ2", "FFJ1", "FFJ0",
    "MFJ3", "MFJ2", "MFJ1", "MFJ0",
    "RFJ3", "RFJ2", "RFJ1", "RFJ0",
    "LFJ4", "LFJ3", "LFJ2", "LFJ1", "LFJ0",
    "THJ4", "THJ3", "THJ2", "THJ1", "THJ0",
)
ACTUATED_JOINTS: tuple[str, ...] = (
    "WRJ1", "WRJ0",
    "FFJ3", "FFJ2", "FFJ1",
    "MFJ3", "MFJ2", "MFJ1",
    "RFJ3", "RFJ2", "RFJ1",
    "LFJ4", "LFJ3", "LFJ2", "LFJ1",
    "THJ4", "THJ3", "THJ2", "THJ1", "THJ0",
)
#: uncoupled distal joint -> the actuated joint that drives it
COUPLED_JOINTS: dict[str, str] = {"FFJ0": "FFJ1", "MFJ0": "MFJ1", "RFJ0": "RFJ1", "LFJ0": "LFJ1"}
#: index into JOINT_NAMES of each actuated joint
ACT_INDEX = np.array([JOINT_NAMES.index(j) for j in ACTUATED_JOINTS])

#: joint ranges [rad] of the Shadow E-series hand (as in gymnasium-robotics' MJCF, which
#: takes them from Shadow's description), JOINT_NAMES order
JOINT_LOW_RAD = np.array([
    -0.489, -0.698,
    -0.349, 0.0, 0.0, 0.0,
    -0.349, 0.0, 0.0, 0.0,
    -0.349, 0.0, 0.0, 0.0,
    0.0, -0.349, 0.0, 0.0, 0.0,
    -1.047, 0.0, -0.209, -0.524, -1.571,
])
JOINT_HIGH_RAD = np.array([
    0.14, 0.489,
    0.349, 1.571, 1.571, 1.571,
    0.349, 1.571, 1.571, 1.571,
    0.349, 1.571, 1.571, 1.571,
    0.785, 0.349, 1.571, 1.571, 1.571,
    1.047, 1.222, 0.209, 0.524, 0.0,
])

#: hold poses [rad] (actuated joints only; the rest are 0 or follow their coupling), by name:
#: ``params.hold_pose``, the spec's ``home_action`` (where every Baoding episode starts and what
#: the planner's action units centre on).
#:
#: * ``cupped`` (ours, the default): palm up, fingers curled at J2 to make a wall at the
#:   fingertips, thumb opposed to close the side. With the sim's palm tilt (0.15 rad) two balls
#:   rest in it > 10 s under a hold (tests/shadow_hand/test_sim.py), one behind the other in the palm.
#: * ``pddm``: the public PDDM reference code's keyframe (google-research/pddm,
#:   ``pddm/envs/baoding/assets/shadowhand_baoding_2.xml``, ``key_qpos[0]``; the two models share
#:   joint order and axes) clipped to our ranges (FFJ3 0.379 → 0.349, MFJ2 −0.136 → 0, LFJ4
#:   −0.022 → 0, LFJ3 −0.368 → −0.349), J1 kept and J0 coupled (the reference's J0 are free:
#:   ours follow 1.142·J1, so our fingertips curl more): knuckles straight, middle joints hooked
#:   ~1.15 rad, wrist flexed −0.398 rad (the fingers slope 23° down on a level mount). The balls
#:   rest side by side on the fingers (docs/baoding.md, "Where the balls sit").
HOLD_POSES: dict[str, dict[str, float]] = {
    "cupped": {
        "FFJ2": 0.45, "FFJ1": 0.3, "MFJ2": 0.45, "MFJ1": 0.3, "RFJ2": 0.45, "RFJ1": 0.3,
        "LFJ4": 0.3, "LFJ2": 0.45, "LFJ1": 0.3,
        "THJ4": 0.9, "THJ3": 0.9, "THJ1": 0.3, "THJ0": -0.3,
    },
    "pddm": {
        "WRJ1": 0.0126, "WRJ0": -0.398, "FFJ3": 0.349, "FFJ2": 0.0564, "FFJ1": 1.167, "MFJ3": 0.265, "MFJ2": 0.0,
        "MFJ1": 1.144, "RFJ3": 0.074, "RFJ2": 0.139, "RFJ1": 1.112, "LFJ4": 0.0, "LFJ3": -0.349, "LFJ2": 0.0,
        "LFJ1": 1.25, "THJ4": -0.021, "THJ3": 0.374, "THJ2": 0.0939, "THJ1": -0.126, "THJ0": -0.536,
    },
}
HoldPose = Literal["cupped", "pddm"]

#: the state channels ``objects_in_state`` appends: ball 0 then ball 1, x y z [m, world frame]
BALL_CHANNELS: tuple[str, ...] = tuple(f"ball{i}_{c}" for i in range(2) for c in "xyz")

#: rate limit of the normalized joint targets [1/s]
ActionRatePerS = finite(gt=0, le=20.0, source=(
    "the whole target range [-1, 1] within one 10 Hz period (2 / 0.1 s): a larger rate limit never binds at the "
    "hand's period, it would be off"))
#: hand telemetry rate [Hz]
HandTelemetryHz = finite(ge=0.1, le=200.0, source=(
    "the CAN bus load: at 200 Hz the telemetry takes 49.4 % of the 1 Mbit/s bus, the most a CAN bus should carry "
    "(~50 %; docs/shadow_hand.md, bus load)"))

Transport = Literal["socketcan", "slcan", "udp_multicast"]


class HandEmulatorParams(EmulatorParams):
    """``params.emulator`` (sim_backends/shadow_hand/emulator.py): the process and its fault
    injection, counted from the first target frame. Unknown keys are errors."""

    spawn: bool = Field(True, description="start the emulator; false: ``channel`` names one already running")
    udp_port: int | None = Field(None, ge=0, le=65535, description="udp_multicast transport: the bus's port")
    balls: bool = Field(True, description="the emulator streams its sim's balls as the ball tracker")
    connect_timeout_s: TimeoutS = Field(10.0, description="time for the first telemetry [s]")
    corrupt_every: int = Field(0, ge=0, description="every N-th telemetry frame is broken (0: never)")
    drop_every: int = Field(0, ge=0, description="every N-th telemetry frame is not sent (0: never)")
    bus_off_after_s: EmulatorS | None = Field(None, description="the CAN controller goes bus-off after S s")
    bus_off_s: EmulatorS = Field(1.0, description="how long the bus-off lasts [s]")
    motor_fault_after_s: EmulatorS | None = Field(None, description="a motor goes limp after S s")
    motor_fault_joint: int = Field(0, ge=0, description="index of the actuated joint whose motor fails")
    arm_port: int | None = Field(None, ge=0, le=65535, description="also run the reset arm's controller on this "
                                 "UDP port (needs params.sim.reset_station; sim_backends/reset_arm/server.py)")
    lab_fixture: bool = Field(False, description="serve the lab fixture beside the hand (drivers/fixture.py, op "
                              "place): the stand-in for the lab's hands that put the balls back in the palm; its UDP "
                              "port is in the driver's health as lab_fixture_port")


class ShadowHandParams(Params):
    """Everything configurable about the hand and its CAN link. Units in names."""

    period_s: PeriodS = Field(0.1, description="control period (thesis: planner at 10 Hz, zero-order hold)")
    max_action_rate_per_s: ActionRatePerS = Field(
        4.0, description="rate limit on the normalized targets [1/s]: 4/s crosses a joint's full range in 0.5 s")
    # link (real/emulated)
    transport: Transport = Field("socketcan", description="python-can interface of the CAN link")
    channel: str | None = Field(None, description="can0 (socketcan), /dev/ttyACM0 (slcan), 239.74.163.2 (udp_multicast)")
    bitrate: int = Field(1_000_000, gt=0, description="CAN bit rate [bit/s] (classic CAN, 1 Mbit/s)")
    telemetry_hz: HandTelemetryHz = Field(50.0, description="hand telemetry rate (docs/shadow_hand.md: bus load)")
    heartbeat_hz: RateHz = Field(10.0, description="host heartbeat rate (feeds the firmware watchdog)")
    firmware_watchdog_s: WatchdogS = Field(0.5, description="firmware holds position after this long without commands")
    driver_watchdog_s: WatchdogS = Field(
        1.0, description="driver sends stop (hold measured) when the caller has not written for this long")
    telemetry_deadline_s: StaleS = Field(
        0.1, description="telemetry older than this makes a reading stale (ok=False)")
    link_timeout_periods: Periods = Field(
        10, description="no complete telemetry cycle for this many control periods with the link "
                        "open (a frozen or dead hand): the error path (stop, UNCONFIGURED, LinkError)")
    ball_tracker_ports: list[int] | None = Field(
        None, description="real: UDP ports where a ball tracker streams ball 0 and ball 1 (hilstack.drivers.mocap.udp "
                          "format); emulated: the emulator streams its sim's balls unless emulator.balls is false")
    hold_pose: HoldPose = Field(
        "cupped", description="the hold pose (HOLD_POSES): the spec's home_action, where the sim's reset puts the hand "
                              "and its balls; cupped (ours) or pddm (the PDDM reference code's keyframe; docs/baoding.md)")
    objects_in_state: bool = Field(
        False, description="append the two Baoding balls' positions [m, world frame] to the state (54-D): the "
                           "task's state, for learning and the drop detector (docs/baoding.md); needs a ball source "
                           "(sim, the emulator's streams, or ball_tracker_ports)")
    # sim (ignored by the real driver) and emulator settings
    sim: dict = Field(default_factory=dict, description="sim backend settings (palm tilt, gains, seed...)")
    emulator: HandEmulatorParams = Field(default_factory=HandEmulatorParams, description="emulator settings and fault injection")

    @model_validator(mode="after")
    def _error_deadline_after_stale(self) -> ShadowHandParams:
        if not self.link_timeout_periods * self.period_s > self.telemetry_deadline_s:
            raise ValueError(f"link_timeout_periods: {self.link_timeout_periods} periods of {self.period_s:g} s must "
                             f"exceed telemetry_deadline_s ({self.telemetry_deadline_s:g} s)")
        return self


def to_joint_rad(action: np.ndarray) -> np.ndarray:
    """Normalized action [-1, 1] (20,) -> joint position targets [rad] (20,)."""
    lo, hi = JOINT_LOW_RAD[ACT_INDEX], JOINT_HIGH_RAD[ACT_INDEX]
    return lo + (np.asarray(action, dtype=np.float64) + 1.0) * 0.5 * (hi - lo)


def to_action(q_act_rad: np.ndarray) -> np.ndarray:
    """Actuated joint angles [rad] (20,) -> normalized action [-1, 1] (clipped)."""
    lo, hi = JOINT_LOW_RAD[ACT_INDEX], JOINT_HIGH_RAD[ACT_INDEX]
    return np.clip(2.0 * (np.asarray(q_act_rad, dtype=np.float64) - lo) / (hi - lo) - 1.0, -1.0, 1.0)


def hold_pose_action(name: HoldPose = "cupped") -> np.ndarray:
    """A hold pose of :data:`HOLD_POSES` as a normalized action (20,)."""
    q = np.zeros(len(ACTUATED_JOINTS))
    for k, v in HOLD_POSES[name].items():
        q[ACTUATED_JOINTS.index(k)] = v
    return to_action(q)


def shadow_hand_spec(p: ShadowHandParams) -> RobotSpec:
    # unbounded on purpose: a real joint may read a little past its nominal range
    # (JOINT_LOW_RAD/JOINT_HIGH_RAD), and a reading is never clipped
    state = Space.build([(f"{j}_pos", "rad", -np.inf, np.inf) for j in JOINT_NAMES]
                        + [(f"{j}_vel", "rad/s", -np.inf, np.inf) for j in JOINT_NAMES]
                        + [(c, "m", -np.inf, np.inf) for c in (BALL_CHANNELS if p.objects_in_state else ())])
    action = Space.build([(f"{j}_target", "1", -1.0, 1.0) for j in ACTUATED_JOINTS])
    return RobotSpec(
        name="shadow_hand",
        state=state,
        action=action,
        period_s=p.period_s,
        action_rate_per_s=np.full(action.dim, p.max_action_rate_per_s),
        safe_action=None,  # stop = hold the measured position
        description="Shadow Dexterous Hand, 24 joints (20 actuated), joint position control",
        home_action=hold_pose_action(p.hold_pose),  # where every Baoding episode starts
    )


def joint_tracking_error(state: np.ndarray, action: np.ndarray) -> dict:
    """How far the measured actuated joints are from the commanded targets [rad]:
    ``max_rad``, ``rms_rad``, ``worst_joint`` and ``per_joint_rad`` (measured − target)."""
    q = np.asarray(state, dtype=np.float64)[ACT_INDEX]
    err = q - to_joint_rad(action)
    k = int(np.argmax(np.abs(err)))
    return {"max_rad": float(np.abs(err).max()), "rms_rad": float(np.sqrt(np.mean(err ** 2))),
            "worst_joint": ACTUATED_JOINTS[k],
            "per_joint_rad": {j: float(e) for j, e in zip(ACTUATED_JOINTS, err, strict=True)}}
