"""The reset arm built with ``mujoco.MjSpec``: 7 revolute joints and a parallel-jaw gripper.

Used twice: added to the Shadow Hand's scene (sim_backends/shadow_hand/station.py, the
arm that the sim backend drives) and alone as the kinematic model of the arm's IK
(:func:`build_arm_kinematics`; the reset step solves IK on it, off the bus, from joint
angles only). Both come from :func:`add_arm`, so the IK model is the simulated arm.

Kinematics from drivers/reset_arm/config.py. The links are gravity compensated
(``gravcomp``), as a real arm's controller does; each joint has a position servo
(``kp``) with its torque limit and viscous damping in the joint (implicit in MuJoCo's
Euler integrator, which the hand's scene uses). Only the gripper collides (links are
visual): the arm's scripted paths stay above the hand and the ramp.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hilstack.drivers.reset_arm.config import (
    AXES,
    GRIPPER_OPEN_M,
    JOINT_LIMITS_RAD,
    JOINTS,
    LINK_OFFSETS_M,
    TCP_OFFSET_M,
    TORQUE_LIMITS_NM,
)

PREFIX = "arm:"
#: jaw force limit [N]: 10 N with the pads' friction 1.5 holds a 0.05 kg ball through the
#: arm's accelerations (6 N let it slip when the arm lagged its command; docs/reset.md)
DEFAULT_GRIPPER_FORCE_N = 10.0
#: link masses [kg] (body k carries joint k)
LINK_MASSES_KG = (3.0, 3.0, 2.0, 2.0, 1.5, 1.0, 0.6)
#: position gains [N·m/rad] and joint damping [N·m·s/rad], armature [kg·m²]
KP_NM_PER_RAD = (400.0, 400.0, 300.0, 300.0, 60.0, 60.0, 30.0)
DAMPING_NMS = (40.0, 40.0, 30.0, 30.0, 6.0, 6.0, 3.0)
ARMATURE_KGM2 = 0.1
#: jaw servo gain [N/m] and damping [N·s/m]
FINGER_KP_N_PER_M = 400.0
FINGER_DAMPING_NS_PER_M = 20.0
PAD_HALF_M = (0.010, 0.005, 0.008)  # pad half sizes: along x, jaw thickness (y), height (z)
#: the pads' contact (stiffer than MuJoCo's default 0.02 s, which lets a squeezed ball sink
#: 6 mm into each pad and slip out); ``priority`` 1 makes the pad's parameters win in a
#: pad-ball contact, so the balls' own contact parameters (the Baoding task's) stay as they are
PAD_SOLREF = (0.004, 1.0)
#: and harder (impedance near 1): MuJoCo's friction is a soft constraint too, and with the
#: default impedance a gripped ball crept out of the jaws within 1.5 s of jerky carrying
PAD_SOLIMP = (0.99, 0.999, 0.001, 0.5, 2.0)
_AXIS = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}


def add_arm(parent: mujoco.MjsBody, spec: mujoco.MjSpec, base_pos_m, gripper_force_n: float = DEFAULT_GRIPPER_FORCE_N,
            prefix: str = PREFIX) -> None:
    """Add the arm under ``parent`` with its base at ``base_pos_m`` [m, parent frame].

    Names: joints ``<prefix>j1..j7``, ``<prefix>finger_l/_r``; actuators the same; the
    tool centre point site ``<prefix>tcp`` (between the pads, z along the approach)."""
    base = parent.add_body(name=f"{prefix}base", pos=list(base_pos_m))
    base.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.08, 0.025, 0], pos=[0, 0, 0.025],
                  contype=0, conaffinity=0, rgba=[0.3, 0.3, 0.3, 1], mass=5.0)
    body = base
    for k, name in enumerate(JOINTS):
        body = body.add_body(name=f"{prefix}link{k + 1}", pos=[0, 0, LINK_OFFSETS_M[k]])
        body.gravcomp = 1.0
        nxt = LINK_OFFSETS_M[k + 1] if k + 1 < len(LINK_OFFSETS_M) else 0.05
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, 0, 0, nxt], size=[0.035 if k < 4 else 0.028, 0, 0],
                      mass=LINK_MASSES_KG[k], contype=0, conaffinity=0, rgba=[0.9, 0.55, 0.1, 1])
        lo, hi = JOINT_LIMITS_RAD[k]
        body.add_joint(name=f"{prefix}{name}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=_AXIS[AXES[k]],
                       range=[lo, hi], limited=mujoco.mjtLimited.mjLIMITED_TRUE, damping=DAMPING_NMS[k],
                       armature=ARMATURE_KGM2)
        act = spec.add_actuator(name=f"{prefix}{name}", target=f"{prefix}{name}",
                                trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=KP_NM_PER_RAD[k])
        act.ctrlrange = [lo, hi]
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-TORQUE_LIMITS_NM[k], TORQUE_LIMITS_NM[k]]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    # gripper: a palm plate at the flange, two jaws sliding along the flange's y
    flange = body
    flange.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.05, 0.01], pos=[0, 0, 0.07],
                    mass=0.3, rgba=[0.2, 0.2, 0.2, 1], contype=0, conaffinity=0)
    flange.add_site(name=f"{prefix}tcp", pos=[0, 0, TCP_OFFSET_M], size=[0.005, 0, 0])
    for side, sign in (("l", 1.0), ("r", -1.0)):
        f = flange.add_body(name=f"{prefix}finger_{side}", pos=[0, 0, 0])
        f.gravcomp = 1.0
        f.add_joint(name=f"{prefix}finger_{side}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, sign, 0],
                    range=[0.0, GRIPPER_OPEN_M / 2], limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                    damping=FINGER_DAMPING_NS_PER_M, armature=0.01)
        # a finger from the palm plate down to its pad; the pad's inner face is at y = sign·q
        f.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.008, 0.004, 0.03],
                   pos=[0, sign * (PAD_HALF_M[1] + 0.003), 0.09], mass=0.05, contype=0, conaffinity=0,
                   rgba=[0.2, 0.2, 0.2, 1])
        f.add_geom(name=f"{prefix}pad_{side}", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(PAD_HALF_M),
                   pos=[0, sign * PAD_HALF_M[1], TCP_OFFSET_M], mass=0.02, friction=[2.0, 0.01, 0.001],
                   condim=4, rgba=[0.1, 0.1, 0.1, 1], priority=1, solref=list(PAD_SOLREF),
                   solimp=list(PAD_SOLIMP))
        act = spec.add_actuator(name=f"{prefix}finger_{side}", target=f"{prefix}finger_{side}",
                                trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=FINGER_KP_N_PER_M)
        act.ctrlrange = [0.0, GRIPPER_OPEN_M / 2]
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-gripper_force_n, gripper_force_n]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE


def build_arm_kinematics(base_pos_m) -> mujoco.MjModel:
    """The arm alone (no world, no gravity needed): the model the IK solves on."""
    spec = mujoco.MjSpec()
    spec.modelname = "reset_arm"
    add_arm(spec.worldbody, spec, base_pos_m)
    return spec.compile()


class ArmIndex:
    """qpos/qvel/ctrl addresses of the arm in a compiled model that holds it."""

    def __init__(self, m: mujoco.MjModel, prefix: str = PREFIX):
        self.qpos = np.array([m.joint(f"{prefix}{j}").qposadr[0] for j in JOINTS])
        self.dof = np.array([m.joint(f"{prefix}{j}").dofadr[0] for j in JOINTS])
        self.ctrl = np.array([m.actuator(f"{prefix}{j}").id for j in JOINTS])
        self.finger_qpos = np.array([m.joint(f"{prefix}finger_{s}").qposadr[0] for s in "lr"])
        self.finger_ctrl = np.array([m.actuator(f"{prefix}finger_{s}").id for s in "lr"])
        self.tcp = m.site(f"{prefix}tcp").id
