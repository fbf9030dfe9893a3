"""The Sawyer in MuJoCo, from the assets metaworld ships (assets only: its env classes do
not run on MuJoCo 4; docs/arms.md).

``sawyer_xyz/sawyer_reach_v3.xml`` drives the hand with a mocap weld; here the weld is
removed and each arm joint ``right_j0..right_j6`` gets a velocity actuator, as the
vendor controller behind intera's joint velocity mode behaves. The arm bodies are
gravity-compensated (the real controller compensates gravity too). Timestep 0.0025 s,
as metaworld's Sawyer tasks use.
"""

from __future__ import annotations

from pathlib import Path

import mujoco

JOINTS = tuple(f"right_j{i}" for i in range(7))
#: Rethink's joint velocity limits [rad/s] (intera SDK URDF / Sawyer hardware spec)
VELOCITY_LIMITS_RAD_S = (1.74, 1.328, 1.957, 1.957, 3.485, 3.485, 4.545)
ASSET = "sawyer_xyz/sawyer_reach_v3.xml"


def asset_path(name: str = ASSET) -> Path:
    from hilstack.configs.extras import missing_extra, require

    spec = require("metaworld", "the Sawyer model (metaworld's assets)", load=False)
    if spec.origin is None:
        raise missing_extra("the Sawyer model (metaworld's assets)", "metaworld")
    return Path(spec.origin).parent / "assets" / name


def build_model(kv_nm_s: float = 80.0, max_torque_nm: float = 80.0) -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_file(str(asset_path()))
    for eq in list(spec.equalities):
        spec.delete(eq)  # the mocap weld: the joints are driven instead
    arm_bodies = {"right_arm_base_link", "right_l0", "right_l1", "right_l2", "right_l3", "right_l4", "right_l5",
                  "right_l6", "right_hand", "hand", "rightclaw", "leftclaw", "rightpad", "leftpad", "right_wrist",
                  "right_hand_camera", "right_arm_itb", "right_torso_itb", "right_l1_2", "right_l2_2", "right_l4_2"}
    for b in spec.bodies:
        if b.name in arm_bodies:
            b.gravcomp = 1.0
    for j in JOINTS:
        spec.add_actuator(name=f"{j}_vel", target=j, trntype=mujoco.mjtTrn.mjTRN_JOINT,
                          gaintype=mujoco.mjtGain.mjGAIN_FIXED, biastype=mujoco.mjtBias.mjBIAS_AFFINE,
                          gainprm=[kv_nm_s] + [0] * 9, biasprm=[0, 0, -kv_nm_s] + [0] * 7,
                          forcerange=[-max_torque_nm, max_torque_nm],
                          forcelimited=mujoco.mjtLimited.mjLIMITED_TRUE)
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST  # stiff velocity servos at 2.5 ms
    return spec.compile()


def kinematics_model() -> mujoco.MjModel:
    """The arm as a MuJoCo model for kinematics above the drivers (the reach task's end
    effector): the ``sawyer.kinematics`` skill (pyproject.toml)."""
    return build_model()
