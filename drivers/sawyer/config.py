"""Sawyer settings and spec, shared by every backend.

State (21): joint positions [rad], velocities [rad/s], efforts [N·m] of right_j0..right_j6.
Action (7): joint velocities [rad/s] (intera joint velocity mode).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field, model_validator

from hilstack.configs.schema import EmulatorParams, Params, Periods, StaleS, finite
from hilstack.drivers.base import RobotSpec, Space

JOINTS = tuple(f"right_j{i}" for i in range(7))
#: Rethink's joint velocity limits [rad/s]
VELOCITY_LIMITS_RAD_S = (1.74, 1.328, 1.957, 1.957, 3.485, 3.485, 4.545)
#: joint position limits [rad] (Sawyer URDF, as in metaworld's model)
POSITION_LIMITS_RAD = ((-3.0503, 3.0503), (-3.8, -0.5), (-3.0426, 3.0426), (-3.0439, 3.0439),
                       (-2.9761, 2.9761), (-2.9761, 2.9761), (-4.7124, 4.7124))


#: Sawyer command period [s]
SawyerPeriodS = finite(ge=0.001, le=0.15, source=(
    "intera stops the arm when joint commands are more than 0.2 s apart; ≤ 0.15 s leaves a margin for jitter"))
#: Sawyer joint velocity limit [rad/s]
SawyerVelRadS = finite(gt=0, le=4.545, source="Rethink's fastest joint velocity limit (right_j6, 4.545 rad/s)")
#: Sawyer joint velocity rate limit [rad/s²]
SawyerAccelRadS2 = finite(gt=0, le=180.0, source=(
    "the fastest joint's whole range (±4.545 rad/s) within one default 50 ms period: a larger rate limit never "
    "binds at 20 Hz, it would be off"))


class SawyerParams(Params):
    period_s: SawyerPeriodS = Field(0.05, description="command period; intera stops the arm if "
                            "commands are more than 0.2 s apart")
    max_joint_vel_rad_s: SawyerVelRadS = Field(0.5, description="action limit (also capped by each joint's limit)")
    max_joint_accel_rad_s2: SawyerAccelRadS2 = 3.0
    joint_states_stale_s: StaleS = Field(0.1, description="joint_states older than this: reading not ok")
    link_timeout_periods: Periods = Field(
        20, description="no usable joint_states for this many control periods (a frozen or dead "
                        "robot, bridge or link): the error path (stop, UNCONFIGURED, LinkError)")
    # Zenoh / ROS 2 bridge (real; the emulated backend sets these itself)
    zenoh_mode: str = Field("client", pattern="^(client|peer)$")
    zenoh_connect: list[str] = Field(default_factory=list, description="e.g. ['tcp/192.168.1.20:7447'], "
                                     "the zenoh-bridge-ros2dds next to the robot PC")
    namespace: str = Field("", description="the bridge's namespace, if it was started with one")
    joint_states_topic: str = "/robot/joint_states"
    joint_command_topic: str = "/robot/limb/right/joint_command"
    #: the emulator has no fault injection yet: the shared settings only
    emulator: EmulatorParams = Field(default_factory=EmulatorParams, description="emulator process settings")
    sim: dict = Field(default_factory=dict)

    @model_validator(mode="after")
    def _error_deadline_after_stale(self) -> SawyerParams:
        if not self.link_timeout_periods * self.period_s > self.joint_states_stale_s:
            raise ValueError(f"link_timeout_periods: {self.link_timeout_periods} periods of {self.period_s:g} s must "
                             f"exceed joint_states_stale_s ({self.joint_states_stale_s:g} s)")
        return self


def sawyer_spec(p: SawyerParams) -> RobotSpec:
    vmax = [min(p.max_joint_vel_rad_s, v) for v in VELOCITY_LIMITS_RAD_S]
    state = Space.build([(f"{j}_pos", "rad", lo, hi) for j, (lo, hi) in zip(JOINTS, POSITION_LIMITS_RAD, strict=True)]
                        + [(f"{j}_vel", "rad/s", -math.inf, math.inf) for j in JOINTS]
                        + [(f"{j}_effort", "N·m", -math.inf, math.inf) for j in JOINTS])
    action = Space.build([(f"{j}_vel", "rad/s", -v, v) for j, v in zip(JOINTS, vmax, strict=True)])
    return RobotSpec(name="sawyer", state=state, action=action, period_s=p.period_s,
                     action_rate_per_s=np.full(7, p.max_joint_accel_rad_s2), safe_action=np.zeros(7),
                     description="Rethink Sawyer 7-DoF, joint velocity control through ROS 2 (intera) over Zenoh")
