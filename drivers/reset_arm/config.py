"""The hand's reset arm: settings, spec and kinematic description, shared by every backend.

A 7-DoF arm (joint axes z-y-z-y-z-y-z from the base, a Panda-like layout) with a
parallel-jaw gripper, standing beside the Shadow Hand's ramp: it picks the balls the
ramp funnels to the pick-up spot and puts them back in the palm (control/reset/steps.py,
``arm_pick_place``).

State (21): 7 joint angles [rad], 7 joint velocities [rad/s], the gripper opening [m]
(the distance between the jaws), then both balls' positions [m, world frame] as the
station sees them (``ball0_x`` .. ``ball1_z``: in sim from the world, on a real rig from
the camera tracker's stream). Action (8): 7 joint position targets [rad] and the
gripper opening target [m]; the arm's own position loops track them (gravity
compensated), the gripper closes with a bounded force.

Frames: world z up (the hand scene's frame); the arm's base at ``base_pos_m``.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field, model_validator

from hilstack.configs.schema import Params, PeriodS, Periods, StaleS, TimeoutS, finite
from hilstack.drivers.base import RobotSpec, Space

JOINTS = tuple(f"j{i}" for i in range(1, 8))
#: joint axes in the parent link frame, from the base
AXES = ("z", "y", "z", "y", "z", "y", "z")
#: link offsets [m] along the parent's z from each joint to the next (the arm is straight up at q = 0):
#: base→j1, j1→j2 (shoulder height), j2→j3, j3→j4 (upper arm), j4→j5, j5→j6 (forearm), j6→j7
LINK_OFFSETS_M = (0.05, 0.20, 0.20, 0.20, 0.20, 0.20, 0.06)
#: j7 → the tool centre point between the jaw pads [m] (flange, gripper palm, fingers)
TCP_OFFSET_M = 0.13
#: joint limits [rad]
JOINT_LIMITS_RAD = ((-2.9, 2.9), (-1.8, 1.8), (-2.9, 2.9), (-2.6, 2.6), (-2.9, 2.9), (-2.6, 2.6), (-2.9, 2.9))
#: peak joint torque [N·m] (the position loops saturate there)
TORQUE_LIMITS_NM = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
#: gripper opening range [m] (jaw-to-jaw distance)
GRIPPER_OPEN_M = 0.08
#: the state's ball channels
BALL_CHANNELS = tuple(f"ball{i}_{a}" for i in (0, 1) for a in "xyz")


#: joint target rate limit [rad/s]
ArmJointRateRadS = finite(gt=0, le=2.61, source=(
    "the fastest joint velocity limit of the Franka Panda, whose layout this arm copies (2.61 rad/s)"))
#: gripper opening rate limit [m/s]
GripperRateMS = finite(gt=0, le=0.2, source="a parallel-jaw gripper's jaws at 0.1 m/s each (the Panda hand's speed)")


class ResetArmParams(Params):
    """``params`` of the reset arm (units in names)."""

    period_s: PeriodS = Field(0.1, description="control period (the hand's: one answer per hand state)")
    max_joint_rate_rad_s: ArmJointRateRadS = Field(1.5, description="rate limit of the joint targets [rad/s]")
    max_gripper_rate_m_s: GripperRateMS = Field(0.2, description="rate limit of the gripper target [m/s]")
    base_pos_m: tuple[float, float, float] = Field((1.62, 0.95, -0.22), description="arm base in the world [m]")
    host: str = Field("127.0.0.1", description="emulated/real: the arm controller's address (UDP)")
    port: int | None = Field(None, ge=1, le=65535, description="emulated/real: the arm controller's UDP port "
                             "(emulated: the hand emulator's params.emulator.arm_port)")
    state_deadline_s: StaleS = Field(0.2, description="a state older than this makes a reading stale")
    link_timeout_periods: Periods = Field(
        10, description="emulated/real: no valid state for this many control periods (the controller "
                        "frozen or dead, the link down): the error path (stop, UNCONFIGURED, LinkError)")
    connect_timeout_s: TimeoutS = Field(10.0, description="configure() waits this long for the first state")
    world: str = Field("hand", description="sim: the simulated hand whose scene holds the arm (same process)")
    world_wait_s: TimeoutS = Field(10.0, description="sim: how long configure() waits for the hand's scene")
    sim: dict = Field(default_factory=dict)

    @model_validator(mode="after")
    def _error_deadline_after_stale(self) -> ResetArmParams:
        if not self.link_timeout_periods * self.period_s > self.state_deadline_s:
            raise ValueError(f"link_timeout_periods: {self.link_timeout_periods} periods of {self.period_s:g} s must "
                             f"exceed state_deadline_s ({self.state_deadline_s:g} s)")
        return self


def reset_arm_spec(p: ResetArmParams) -> RobotSpec:
    state = Space.build([(f"{j}_pos", "rad", lo, hi) for j, (lo, hi) in zip(JOINTS, JOINT_LIMITS_RAD, strict=True)]
                        + [(f"{j}_vel", "rad/s", -math.inf, math.inf) for j in JOINTS]
                        + [("gripper_m", "m", 0.0, GRIPPER_OPEN_M)]
                        + [(c, "m", -math.inf, math.inf) for c in BALL_CHANNELS])
    action = Space.build([(f"{j}_target", "rad", lo, hi) for j, (lo, hi) in zip(JOINTS, JOINT_LIMITS_RAD, strict=True)]
                         + [("gripper_target", "m", 0.0, GRIPPER_OPEN_M)])
    rate = np.array([p.max_joint_rate_rad_s] * 7 + [p.max_gripper_rate_m_s])
    return RobotSpec(name="reset_arm", state=state, action=action, period_s=p.period_s, action_rate_per_s=rate,
                     safe_action=None,  # stop = hold the measured joints
                     description="7-DoF reset arm with a parallel-jaw gripper, joint position control")
