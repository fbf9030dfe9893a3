"""The WidowX 250 6DOF arm, the task-reset mechanism and its switch, built with MjSpec.

Kinematics (joint origins and axes), link masses, centres of mass and inertias are the
published values of Trossen Robotics' description ``interbotix_xsarm_descriptions``
(``urdf/wx250s.urdf.xacro``, as expanded in Stillrainy/wx250s_simulation
``assets/wx250s.urdf``); see docs/arms.md. Geometry is a set of capsules for looks
(the published meshes are not needed for dynamics); the arm does not collide.

Frames: world z up, the arm's base at the origin facing +x. Joint angles 0 are the
description's zero pose (arm stretched forward, "L" shape folded at 0 = upright upper arm).

The mechanism (two servos on the same bus): a carriage on a linear rail along world y,
driven by a pinion of radius ``rail_pinion_radius_m`` (servo angle = y / r), carrying a
housing that a second servo turns about z. The switch's port (goal site ``port``) sits on
the housing. Each servo drives its MuJoCo actuator in its own units (N·m on its shaft):
the rail actuator has gear 1/r so its "length" is the servo angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from hilstack.drivers.widowx.description import WX250S_LINKS

#: base link (fixed): mass and CoM of wx250s/base_link
BASE_MASS_KG = 0.538736
#: gripper_link origin -> ee_gripper_link: ee_arm 0.043 + fingers 0.023 + ee_gripper 0.027575 [m]
EE_OFFSET_M = 0.043 + 0.023 + 0.027575
#: reflected rotor inertia of an X-series servo at its output [kg·m²] (stabilizes 1 kHz stepping)
SERVO_ARMATURE_KGM2 = 0.01
JOINT_DAMPING_NMS = 0.1      # the description's <dynamics damping>
JOINT_FRICTION_NM = 0.1      # and friction


@dataclass(frozen=True)
class MechanismGeometry:
    base_xyz_m: tuple[float, float, float] = (0.32, 0.0, 0.0)
    rail_half_travel_m: float = 0.01
    rotate_half_range_rad: float = math.radians(8.0)
    rail_pinion_radius_m: float = 0.01
    housing_mass_kg: float = 0.25
    port_offset_m: tuple[float, float, float] = (-0.03, 0.0, 0.12)


def _inertia_in_body(inertia: tuple, yaw_rad: float) -> list[float]:
    ixx, iyy, izz, ixy, ixz, iyz = inertia
    m = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    mb = r @ m @ r.T
    return [mb[0, 0], mb[1, 1], mb[2, 2], mb[0, 1], mb[0, 2], mb[1, 2]]


def build_spec(stall_torques_nm: dict[str, float], mech: MechanismGeometry | None = None,
               mech_stall_torque_nm: float = 4.1, timestep_s: float = 0.001) -> mujoco.MjSpec:
    """Arm (actuators named after joints) + mechanism (``mech_rail``, ``mech_rotate``)."""
    mech = mech or MechanismGeometry()
    spec = mujoco.MjSpec()
    spec.modelname = "widowx250s_reset_mechanism"
    spec.compiler.degree = False  # every angle here is in rad
    spec.option.timestep = timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    wb = spec.worldbody
    wb.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[1, 1, 0.01], rgba=[0.8, 0.8, 0.8, 1])
    wb.add_light(pos=[0, 0, 2], dir=[0, 0, -1])
    wb.add_camera(name="fixed", pos=[0.75, -0.55, 0.55], xyaxes=[0.6, 0.8, 0, -0.35, 0.26, 0.9])
    base = wb.add_body(name="base_link", pos=[0, 0, 0])
    base.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.05, 0.036, 0], pos=[0, 0, 0.036],
                  mass=BASE_MASS_KG, contype=0, conaffinity=0, rgba=[0.1, 0.1, 0.1, 1])
    parent = base
    for name, off, axis, (lo, hi), mass, com, inertia, yaw in WX250S_LINKS:
        body = parent.add_body(name=f"{name}_link", pos=list(off))
        body.mass = mass
        body.ipos = list(com)
        body.fullinertia = _inertia_in_body(inertia, yaw)
        body.explicitinertial = True
        body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=list(axis), range=[lo, hi],
                       limited=mujoco.mjtLimited.mjLIMITED_TRUE, damping=JOINT_DAMPING_NMS,
                       frictionloss=JOINT_FRICTION_NM, armature=SERVO_ARMATURE_KGM2)
        seg = np.array(com) * 2.0
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, *seg.tolist()], size=[0.018, 0, 0],
                      contype=0, conaffinity=0, mass=0, rgba=[0.15, 0.15, 0.15, 1])
        t = stall_torques_nm[name]
        spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT, gear=[1, 0, 0, 0, 0, 0],
                          ctrlrange=[-t, t], ctrllimited=mujoco.mjtLimited.mjLIMITED_TRUE)
        parent = body
    parent.add_site(name="ee", pos=[EE_OFFSET_M, 0, 0], size=[0.008, 0, 0], rgba=[1, 0.2, 0.2, 1])
    # above the gripper, looking forward and 17° down (camera -z = (0.95, 0, -0.3))
    parent.add_camera(name="wrist", pos=[0.0, 0, 0.05], xyaxes=[0, -1, 0, 0.3, 0, 0.95], fovy=70)

    # --- the task-reset mechanism and the switch
    r = mech.rail_pinion_radius_m
    carriage = wb.add_body(name="mech_carriage", pos=list(mech.base_xyz_m))
    carriage.add_joint(name="mech_rail", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 1, 0],
                       range=[-mech.rail_half_travel_m, mech.rail_half_travel_m],
                       limited=mujoco.mjtLimited.mjLIMITED_TRUE, damping=2.0,
                       armature=SERVO_ARMATURE_KGM2 / (r * r))
    carriage.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.05, 0.04, 0.01], pos=[0, 0, 0.01], mass=0.2,
                      contype=0, conaffinity=0, rgba=[0.5, 0.5, 0.6, 1])
    housing = carriage.add_body(name="switch_housing", pos=[0, 0, 0.02])
    housing.add_joint(name="mech_rotate", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1],
                      range=[-mech.rotate_half_range_rad, mech.rotate_half_range_rad],
                      limited=mujoco.mjtLimited.mjLIMITED_TRUE, damping=0.05, armature=SERVO_ARMATURE_KGM2)
    housing.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.08, 0.06], pos=[0, 0, 0.06],
                     mass=mech.housing_mass_kg, contype=0, conaffinity=0, rgba=[0.9, 0.9, 0.85, 1])
    housing.add_site(name="port", pos=list(mech.port_offset_m), size=[0.006, 0, 0], rgba=[0.1, 0.8, 0.1, 1])
    t = mech_stall_torque_nm
    spec.add_actuator(name="mech_rail", target="mech_rail", trntype=mujoco.mjtTrn.mjTRN_JOINT,
                      gear=[1.0 / r, 0, 0, 0, 0, 0], ctrlrange=[-t, t], ctrllimited=mujoco.mjtLimited.mjLIMITED_TRUE)
    spec.add_actuator(name="mech_rotate", target="mech_rotate", trntype=mujoco.mjtTrn.mjTRN_JOINT,
                      gear=[1, 0, 0, 0, 0, 0], ctrlrange=[-t, t], ctrllimited=mujoco.mjtLimited.mjLIMITED_TRUE)
    return spec
