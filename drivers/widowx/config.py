"""WidowX 250 6DOF and task-reset mechanism: settings and specs, shared by every backend.

Both are robots on one Dynamixel bus (one USB-serial adapter): the arm's six joints
(IDs of Trossen's wx250s defaults; the shoulder and elbow each have a second "shadow"
servo that follows its master in the servo itself) and the mechanism's two servos.

WidowX state (18): joint positions [rad], velocities [rad/s], currents [A], in joint
order ``JOINTS``. Action (6): joint velocities [rad/s] sent to the servos' velocity PI
loops (the thesis' "joint velocities to a low-level PID").

Mechanism state (4): housing rotation [rad] about z, rail offset [m] along world y, and
their rates. Action (2): target rotation [rad] (±8°) and offset [m] (±1 cm); the
servos run in position mode.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from hilstack.configs.schema import (
    JointRangeRad,
    PeriodS,
    finite,
)
from hilstack.drivers.base import RobotSpec, Space
from hilstack.drivers.dynamixel.params import BusParams, check_watchdog
from hilstack.drivers.widowx.description import WX250S_LINKS

#: joint, default ID, default servo model, stall torque at the joint [N·m] (2 servos: 2×)
JOINTS: list[tuple[str, int, str, float]] = [
    ("waist", 1, "XM430-W350", 4.1),
    ("shoulder", 2, "XM430-W350", 8.2),
    ("elbow", 4, "XM430-W350", 8.2),
    ("forearm_roll", 6, "XM430-W350", 4.1),
    ("wrist_angle", 7, "XM430-W350", 4.1),
    ("wrist_rotate", 8, "XM430-W350", 4.1),
]
JOINT_NAMES = tuple(j[0] for j in JOINTS)
#: mechanism servos: rotate the housing, drive the rail pinion
MECH_JOINTS = ("mech_rotate", "mech_rail")
MECH_DEFAULT_IDS = {"mech_rotate": 10, "mech_rail": 11}


#: XM430-W350 joint velocity limit [rad/s]
JointVelRadS = finite(gt=0, le=4.8, source="XM430-W350 no-load speed at 12 V: 46 rev/min = 4.8 rad/s (ROBOTIS e-Manual)")
#: joint velocity rate limit [rad/s²]
JointAccelRadS2 = finite(gt=0, le=96.0, source=(
    "the XM430's whole speed (4.8 rad/s) within one default 50 ms period: a larger rate limit never binds at 20 Hz, "
    "it would be off"))
#: slow-down margin before a joint limit [rad]
LimitMarginRad = finite(ge=0, le=0.5, source="≤ 0.5 rad: a margin wider would eat most of the wrist's 3.9 rad range")
#: the housing's rotation range, each way [deg]
RotateHalfRangeDeg = finite(ge=1.0, le=45.0, source=(
    "≥ 1°: about 11 steps of the XM430's 0.088° resolution, a range it can hold; ≤ 45°: the housing's stops"))
#: the rail's travel, each way [m]
RailHalfTravelM = finite(ge=0.001, le=0.1, source=(
    "≥ 1 mm: a travel the pinion resolves (0.088° on a ≤ 5 cm pinion: 0.08 mm); ≤ 10 cm: the rail's length"))
#: mechanism housing rotation rate [rad/s]
RotateRateRadS = finite(gt=0, le=4.8, source="XM430-W350 no-load speed (4.8 rad/s)")
#: rail pinion radius [m]
PinionRadiusM = finite(gt=0, le=0.05, source="≤ 5 cm: a pinion on an XM430's horn")
#: rail offset rate [m/s]
RailRateMS = finite(gt=0, le=0.24, source="XM430 no-load speed × the largest pinion radius: 4.8 rad/s × 0.05 m")
class WidowXParams(BusParams):
    ids: dict[str, int] = Field(default_factory=lambda: {n: i for n, i, _, _ in JOINTS})
    period_s: PeriodS = Field(0.05, description="driver control period (MELD acts at 3.3 Hz above it)")
    max_joint_vel_rad_s: JointVelRadS = Field(1.0, description="action limit (XM430 no-load: 4.8 rad/s)")
    max_joint_accel_rad_s2: JointAccelRadS2 = Field(6.0, description="rate limit on velocity commands")
    #: joints slow to zero when moving towards a limit within this margin
    limit_margin_rad: LimitMarginRad = 0.05
    joint_limits_rad: dict[str, JointRangeRad] = Field(
        default_factory=dict, description="narrow the description's limits (within them; low < high)")

    @field_validator("ids")
    @classmethod
    def _ids(cls, v: dict[str, int]) -> dict[str, int]:
        missing = [n for n in JOINT_NAMES if n not in v]
        if missing:
            raise ValueError(f"ids lacks joints {missing}")
        if len(set(v.values())) != len(v) or not all(0 <= i <= 252 for i in v.values()):
            raise ValueError(f"ids must be distinct and within 0..252, got {v}")
        return v

    @field_validator("period_s")
    @classmethod
    def _watchdog_vs_period(cls, v: float, info: ValidationInfo) -> float:
        return check_watchdog(v, info)
    @field_validator("joint_limits_rad")
    @classmethod
    def _limits(cls, v: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
        hw = {name: rng for name, _, _, rng, *_ in WX250S_LINKS}
        for n, (lo, hi) in v.items():
            if n not in hw:
                raise ValueError(f"unknown joint {n!r}; joints: {list(hw)}")
            if lo < hw[n][0] or hi > hw[n][1]:
                raise ValueError(f"{n}: [{lo:g}, {hi:g}] leaves the hardware's range "
                                 f"[{hw[n][0]:g}, {hw[n][1]:g}] rad")
        return v


class MechanismParams(BusParams):
    ids: dict[str, int] = Field(default_factory=lambda: dict(MECH_DEFAULT_IDS))
    period_s: PeriodS = 0.05
    rotate_half_range_deg: RotateHalfRangeDeg = 8.0
    rail_half_travel_m: RailHalfTravelM = 0.01
    rail_pinion_radius_m: PinionRadiusM = Field(0.01, description="rail offset = pinion radius × servo angle")
    rotate_rate_rad_s: RotateRateRadS = Field(0.5, description="rate limit of the rotation target")
    rail_rate_m_s: RailRateMS = Field(0.02, description="rate limit of the offset target")

    @field_validator("period_s")
    @classmethod
    def _watchdog_vs_period(cls, v: float, info: ValidationInfo) -> float:
        return check_watchdog(v, info)


def joint_limits(p: WidowXParams) -> dict[str, tuple[float, float]]:
    lim = {name: rng for name, _, _, rng, *_ in WX250S_LINKS}
    lim.update({k: tuple(v) for k, v in p.joint_limits_rad.items()})
    return lim


def widowx_spec(p: WidowXParams) -> RobotSpec:
    lim = joint_limits(p)
    v, big_a = p.max_joint_vel_rad_s, 30.0
    state = Space.build(
        [(f"{n}_pos", "rad", lim[n][0], lim[n][1]) for n in JOINT_NAMES]
        + [(f"{n}_vel", "rad/s", -math.inf, math.inf) for n in JOINT_NAMES]
        + [(f"{n}_current", "A", -big_a, big_a) for n in JOINT_NAMES])
    action = Space.build([(f"{n}_vel", "rad/s", -v, v) for n in JOINT_NAMES])
    return RobotSpec(name="widowx", state=state, action=action, period_s=p.period_s,
                     action_rate_per_s=np.full(len(JOINT_NAMES), p.max_joint_accel_rad_s2),
                     safe_action=np.zeros(len(JOINT_NAMES)),
                     description="Trossen WidowX 250 6DOF, joint velocity control over Dynamixel Protocol 2.0",
                     chain=tuple((n, tuple(off), tuple(axis)) for n, off, axis, *_ in WX250S_LINKS))


def mechanism_spec(p: MechanismParams) -> RobotSpec:
    rot = math.radians(p.rotate_half_range_deg)
    rail = p.rail_half_travel_m
    state = Space.build([("rotate", "rad", -rot, rot), ("offset", "m", -rail, rail),
                         ("rotate_vel", "rad/s", -math.inf, math.inf), ("offset_vel", "m/s", -math.inf, math.inf)])
    action = Space.build([("rotate", "rad", -rot, rot), ("offset", "m", -rail, rail)])
    # safe_action None: stop holds the measured pose
    return RobotSpec(name="reset_mechanism", state=state, action=action, period_s=p.period_s,
                     action_rate_per_s=np.array([p.rotate_rate_rad_s, p.rail_rate_m_s]),
                     description="task-reset mechanism: switch housing rotation and rail offset (2 Dynamixels)")
