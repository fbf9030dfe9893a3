"""The simulated bench: WidowX + mechanism + switch in MuJoCo, each joint driven by a
:class:`~hilstack.sim_backends.dynamixel.firmware.Servo` at 1 kHz (a
:class:`~hilstack.sim_backends.dynamixel.world.ServoWorld`).

Used by the sim backends in-process (lockstep) and by the bus emulator process (real
time). Servos are addressed by Dynamixel ID, as on the wire.

Several robots built in one process with the same bus name share one world (as they
share one bus on the bench): ``shared_world(name, ...)`` hands out the same object while
any robot holds it. Time advances in whole 1 ms servo ticks.
"""

from __future__ import annotations

import weakref

import mujoco
import numpy as np

from hilstack.drivers.widowx.config import JOINTS, MECH_DEFAULT_IDS
from hilstack.sim_backends.dynamixel.firmware import ServoPhysics, effect_fields
from hilstack.sim_backends.dynamixel.world import ServoWorld
from hilstack.sim_backends.widowx.model import WX250S_LINKS, MechanismGeometry, build_spec

#: Interbotix' sleep pose: shoulder and elbow on their limits, so gravity keeps it there
SLEEP_POSE_RAD = {"shoulder": -1.88, "elbow": 1.60, "wrist_angle": -1.74}
#: MJCF custom numeric: the servos' goal delay [s] (hilstack.calibration.mjcf_robot writes it)
DELAY_NUMERIC = "hilstack_input_delay_s"
#: a robot's world stays shared while one of its robots lives (bus name -> world)
_WORLDS: weakref.WeakValueDictionary[str, ArmWorld] = weakref.WeakValueDictionary()


class ArmWorld(ServoWorld):
    def __init__(self, arm_ids: dict[str, int] | None = None, mech_ids: dict[str, int] | None = None,
                 mech: MechanismGeometry | None = None, start_holding: dict[str, float] | None = None,
                 effects: dict[str, float] | None = None, mjcf: str | None = None):
        """``start_holding``: start with the arm torqued and holding these joint angles
        [rad] in position mode, as a previous session that was not cleanly shut down
        leaves it (default: the sleep pose with torque off, as after power-on).
        ``effects``: what the arm's servos have that the MuJoCo model lacks
        (:data:`~hilstack.sim_backends.dynamixel.firmware.EFFECTS`: gearbox friction, damping,
        an input delay), for calibration tests. ``mjcf``: load the bench from this MJCF file
        (e.g. one ``hil calibrate`` wrote) instead of building it; it must have the same
        joints and actuators; its ``hilstack_input_delay_s`` numeric becomes the servos' delay."""
        self.start_holding = dict(start_holding) if start_holding else None
        self.arm_ids = arm_ids or {n: i for n, i, _, _ in JOINTS}
        self.mech_ids = mech_ids or dict(MECH_DEFAULT_IDS)
        self.mech = mech or MechanismGeometry()
        torques = {n: t for n, _, _, t in JOINTS}
        model = build_spec(torques, self.mech).compile() if mjcf is None else load_bench_mjcf(mjcf)
        effects = dict(effects or {})
        nid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, DELAY_NUMERIC)
        if nid >= 0 and "input_delay_s" not in effects:  # a calibrated MJCF's identified goal delay
            effects["input_delay_s"] = float(model.numeric_data[model.numeric_adr[nid]])
        arm = effect_fields(effects)
        limits = {name: rng for name, _, _, rng, *_ in WX250S_LINKS}
        r = self.mech.rail_pinion_radius_m
        limits["mech_rotate"] = (-self.mech.rotate_half_range_rad, self.mech.rotate_half_range_rad)
        limits["mech_rail"] = (-self.mech.rail_half_travel_m / r, self.mech.rail_half_travel_m / r)
        torques.update({"mech_rotate": 4.1, "mech_rail": 4.1})
        super().__init__(model, {name: (dxl_id, ServoPhysics(stall_torque_nm=torques[name],
                                                             **(arm if name in self.arm_ids else {})), limits[name])
                                 for name, dxl_id in {**self.arm_ids, **self.mech_ids}.items()})

    def start_pose(self) -> dict[str, float]:
        """Arm in its sleep pose, resting on the shoulder and elbow limits (where a real
        WidowX rests with torque off), or the ``start_holding`` pose."""
        return self.start_holding if self.start_holding is not None else SLEEP_POSE_RAD

    def reset(self) -> None:
        """The start pose, servos powered on with torque off (holding, torqued, with
        ``start_holding``)."""
        super().reset()
        if self.start_holding is not None:
            self.hold_start_pose(list(self.arm_ids.values()))

    # ------------------------------------------------------------------ readouts
    def ee_pos(self) -> np.ndarray:
        return self.data.site("ee").xpos.copy()

    def port_pose(self) -> tuple[np.ndarray, float]:
        """Switch port position [m] in the world and housing yaw [rad]."""
        return self.data.site("port").xpos.copy(), float(self.data.joint("mech_rotate").qpos[0])


def load_bench_mjcf(path: str) -> mujoco.MjModel:
    """The bench model from an MJCF file; a one-line ValueError if it is unreadable or lacks a
    joint or actuator the servos drive."""
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except (ValueError, OSError) as e:
        raise ValueError(f"mjcf {path}: {str(e).splitlines()[0]}") from None
    need = [n for n, _, _, _ in JOINTS] + ["mech_rail", "mech_rotate"]
    for name in need:
        for kind in (mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_ACTUATOR):
            if mujoco.mj_name2id(model, kind, name) < 0:
                raise ValueError(f"mjcf {path}: no {kind.name[6:].lower()} named {name!r} (the bench's joints "
                                 f"and actuators: {need})")
    return model


def shared_world(bus_name: str, arm_ids: dict[str, int] | None = None,
                 mech_ids: dict[str, int] | None = None, start_holding: dict[str, float] | None = None,
                 effects: dict[str, float] | None = None, mjcf: str | None = None) -> ArmWorld:
    """The world of a bus: created by the first robot that asks, shared with the rest."""
    w = _WORLDS.get(bus_name)
    if w is None:
        w = ArmWorld(arm_ids, mech_ids, start_holding=start_holding, effects=effects, mjcf=mjcf)
        _WORLDS[bus_name] = w
    else:
        for name, ids in (("arm", arm_ids), ("mechanism", mech_ids)):
            have = w.arm_ids if name == "arm" else w.mech_ids
            if ids is not None and ids != have:
                raise ValueError(f"bus {bus_name!r} already has {name} IDs {have}, config asks for {ids}")
    return w


def kinematics_model():
    """The arm's world as a MuJoCo model for kinematics above the drivers (the reach task's
    end effector and the mechanism's port): the ``widowx.kinematics`` skill (pyproject.toml)."""
    return ArmWorld().model
