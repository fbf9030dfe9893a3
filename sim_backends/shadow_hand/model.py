"""The Shadow Dexterous Hand scene with two Baoding balls, built with ``mujoco.MjSpec``.

The hand is the MJCF that gymnasium-robotics ships inside its wheel
(``gymnasium_robotics/envs/assets/hand/manipulate_egg.xml``, Shadow Robot's E-series hand
as modelled by OpenAI): 24 hinge joints, 20 position actuators. Only its asset files are
used (its ``gym.make`` environments fail on MuJoCo >= 3.12). MjSpec edits:

* the bodies ``object`` and ``target`` (the egg) are deleted;
* two free-joint spheres (radius 0.02 m, 0.05 kg) are added above the palm (the PDDM
  reference code's are larger, 0.028 m and 0.043 kg: docs/baoding.md, "The reference's balls are larger");
* the 20 position servos become torque motors (``set_to_motor``, ctrl range = the servo's
  force range): the position loop runs in the firmware model at 1 kHz
  (:mod:`hilstack.sim_backends.shadow_hand.firmware`), as on the real hand's motor boards;
* the physics step becomes 1 ms (the firmware's tick) instead of 2 ms.

Frames: world z up. The hand's mount is rotated so that the palm faces up (+z) with the
fingers pointing along world -y; ball positions are reported in the world frame [m].
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from hilstack.drivers.shadow_hand.config import ACTUATED_JOINTS, JOINT_NAMES
from hilstack.sim_backends.reset_arm.model import DEFAULT_GRIPPER_FORCE_N
from hilstack.sim_backends.shadow_hand.station import StationGeometry, add_station

BALL_RADIUS_M = 0.02
BALL_MASS_KG = 0.05
PHYSICS_DT_S = 0.001


def hand_asset_path() -> Path:
    """Path of gymnasium-robotics' ``manipulate_egg.xml`` (found without importing the
    package: its import pulls gymnasium and is not needed for the assets)."""
    spec = importlib.util.find_spec("gymnasium_robotics")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            "the Shadow Hand model comes from the gymnasium-robotics wheel: pip install gymnasium-robotics")
    path = Path(next(iter(spec.submodule_search_locations))) / "envs" / "assets" / "hand" / "manipulate_egg.xml"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing from the gymnasium-robotics wheel")
    return path


@dataclass(frozen=True)
class HandModel:
    """A compiled scene plus the index maps every user of it needs."""

    model: mujoco.MjModel
    qpos_adr: np.ndarray  # (24,) qpos index of each joint in JOINT_NAMES
    dof_adr: np.ndarray  # (24,) qvel index of each joint
    act_joint: np.ndarray  # (20,) index into JOINT_NAMES of each actuated joint
    joint_low: np.ndarray  # (24,) joint range [rad]
    joint_high: np.ndarray
    torque_limit_nm: np.ndarray  # (20,) per motor
    ball_qpos_adr: tuple[int, int]  # first qpos index of each ball's free joint
    ball_dof_adr: tuple[int, int]
    ball_body: tuple[int, int]
    #: the reset station (ramp + arm), when the scene has one (sim_backends/shadow_hand/station.py)
    station: StationGeometry | None = None


def build_scene(palm_tilt_rad: float = 0.0, station: StationGeometry | None = None,
                gripper_force_n: float = DEFAULT_GRIPPER_FORCE_N,
                edit: Callable[[mujoco.MjSpec], None] | None = None) -> HandModel:
    """The hand, palm up, with two balls; ``palm_tilt_rad`` tilts the mount about world x.
    ``station``: add the reset station (ramp, pick-up spot, reset arm) beside the hand;
    its actuators come after the hand's 20. ``edit`` adds to the spec before it is
    compiled (the stereo cameras and the calibration board of
    :mod:`hilstack.sim_backends.shadow_hand.cameras`)."""
    return index_scene(scene_spec(palm_tilt_rad, station, gripper_force_n, edit), station)


def scene_spec(palm_tilt_rad: float = 0.0, station: StationGeometry | None = None,
               gripper_force_n: float = DEFAULT_GRIPPER_FORCE_N,
               edit: Callable[[mujoco.MjSpec], None] | None = None) -> mujoco.MjSpec:
    """The scene of :func:`build_scene` as an ``MjSpec``, not compiled (calibration edits it)."""
    spec = mujoco.MjSpec.from_file(str(hand_asset_path()))
    for name in ("object", "target"):
        spec.delete(spec.body(name))
    spec.option.timestep = PHYSICS_DT_S
    # palm up: palm axes in the world x_p = -x, y_p = -z (the back of the hand down),
    # z_p = -y (fingers along -y); then tilted about world x (+ lowers the fingertips: at 0.15 rad
    # the fingers slope 8.6° down from the wrist, docs/baoding.md, "Where the balls sit")
    up = np.array([0.0, 0.0, np.sqrt(0.5), -np.sqrt(0.5)])
    tilt = np.array([np.cos(palm_tilt_rad / 2), np.sin(palm_tilt_rad / 2), 0.0, 0.0])
    q = np.zeros(4)
    mujoco.mju_mulQuat(q, tilt, up)
    mount = spec.body("robot0:hand mount")
    mount.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    mount.quat = q
    mount.pos = np.array([1.0, 1.25, 0.15])
    for act in spec.actuators:
        lo, hi = float(act.forcerange[0]), float(act.forcerange[1])
        act.set_to_motor()
        act.ctrlrange = np.array([lo, hi])
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    spec.visual.quality.shadowsize = 0
    for i, rgba in enumerate(((0.8, 0.2, 0.2, 1.0), (0.2, 0.3, 0.8, 1.0))):
        b = spec.worldbody.add_body(name=f"ball{i}", pos=[1.0, 1.0, 0.3 + 0.05 * i])
        b.add_freejoint(name=f"ball{i}:joint")
        b.add_geom(name=f"ball{i}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[BALL_RADIUS_M, 0, 0],
                   mass=BALL_MASS_KG, rgba=rgba, condim=4, friction=[1.0, 0.005, 0.0001])
    if station is not None:
        add_station(spec, station, gripper_force_n)
    if edit is not None:
        edit(spec)
    return spec


def index_scene(spec: mujoco.MjSpec, station: StationGeometry | None = None) -> HandModel:
    """Compile a scene spec (:func:`scene_spec`, or one calibrated from it) with its index maps."""
    m = spec.compile()
    qadr = np.array([m.joint(f"robot0:{j}").qposadr[0] for j in JOINT_NAMES])
    dadr = np.array([m.joint(f"robot0:{j}").dofadr[0] for j in JOINT_NAMES])
    act_joint = []
    for i in range(len(ACTUATED_JOINTS)):
        jid = m.actuator_trnid[i, 0]
        act_joint.append(JOINT_NAMES.index(m.joint(jid).name.removeprefix("robot0:")))
    if tuple(JOINT_NAMES[k] for k in act_joint) != ACTUATED_JOINTS:
        raise RuntimeError("actuator order of the shipped MJCF changed; update ACTUATED_JOINTS")
    jids = [m.joint(f"robot0:{j}").id for j in JOINT_NAMES]
    return HandModel(
        model=m,
        qpos_adr=qadr,
        dof_adr=dadr,
        act_joint=np.array(act_joint),
        joint_low=m.jnt_range[jids, 0].copy(),
        joint_high=m.jnt_range[jids, 1].copy(),
        torque_limit_nm=m.actuator_ctrlrange[:len(ACTUATED_JOINTS), 1].copy(),
        ball_qpos_adr=(m.joint("ball0:joint").qposadr[0], m.joint("ball1:joint").qposadr[0]),
        ball_dof_adr=(m.joint("ball0:joint").dofadr[0], m.joint("ball1:joint").dofadr[0]),
        ball_body=(m.body("ball0").id, m.body("ball1").id),
        station=station,
    )
