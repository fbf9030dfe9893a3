"""A MuJoCo world whose joints are driven by simulated Dynamixel servos at 1 kHz.

Each servo (:class:`~hilstack.sim_backends.dynamixel.firmware.Servo`, addressed by its
Dynamixel ID as on the wire) drives the model's actuator of its joint's name: every tick
it reads the actuator's length and velocity and sets its torque. A bench (the WidowX arm
and mechanism, the pan unit) builds its model and names its servos; the in-process bus
(:mod:`.backend`) and the bus emulator (:mod:`.emulator`) work on any such world. Time
advances in whole 1 ms servo ticks.
"""

from __future__ import annotations

import mujoco

from hilstack.sim_backends.dynamixel.firmware import TICK_S, Servo, ServoPhysics


class ServoWorld:
    """``servos``: joint name -> (Dynamixel ID, physics, position limits [rad]); the model
    has an actuator of each joint's name (a torque motor on the servo's output shaft)."""

    def __init__(self, model: mujoco.MjModel, servos: dict[str, tuple[int, ServoPhysics, tuple[float, float]]]):
        self.model = model
        self.data = mujoco.MjData(model)
        self.servos: dict[int, Servo] = {}
        self._act: dict[int, int] = {}
        for name, (dxl_id, phys, limits) in servos.items():
            act = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, name)
            if act < 0:
                raise ValueError(f"the model has no actuator {name!r} for servo {dxl_id}")
            self.servos[dxl_id] = Servo(dxl_id, physics=phys, position_limits_rad=limits)
            self._act[dxl_id] = act
        self.reset()

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    def start_pose(self) -> dict[str, float]:
        """Joint angles [rad] the world starts in (joints not named: the model's qpos0)."""
        return {}

    def reset(self) -> None:
        """The start pose at rest, every servo powered on with torque off."""
        mujoco.mj_resetData(self.model, self.data)
        for name, q in self.start_pose().items():
            self.data.joint(name).qpos[0] = q
        mujoco.mj_forward(self.model, self.data)
        for s in self.servos.values():
            s.mem[:] = bytes(len(s.mem))
            s.power_on()
        self._sync_servos()

    def reset_robot(self, names: list[str] | tuple[str, ...], ids: list[int]) -> None:
        """Put some joints back to their start pose at rest and power-cycle their servos,
        leaving the rest of the bench as it is (one robot's reset)."""
        pose = self.start_pose()
        for name in names:
            j = self.data.joint(name)
            j.qpos[0] = pose.get(name, 0.0)
            j.qvel[0] = 0.0
        mujoco.mj_forward(self.model, self.data)
        for dxl_id in ids:
            s = self.servos[dxl_id]
            s.mem[:] = bytes(len(s.mem))
            s.power_on()
            a = self._act[dxl_id]
            s.tick(float(self.data.actuator_length[a]), float(self.data.actuator_velocity[a]), 0.0)

    def _sync_servos(self) -> None:
        """Present registers from the current state (no torque: used after reset)."""
        for i, s in self.servos.items():
            a = self._act[i]
            s.tick(float(self.data.actuator_length[a]), float(self.data.actuator_velocity[a]), 0.0)

    def step(self) -> None:
        """One 1 ms servo tick on every servo, then one MuJoCo step."""
        d = self.data
        for i, s in self.servos.items():
            a = self._act[i]
            d.ctrl[a] = s.tick(float(d.actuator_length[a]), float(d.actuator_velocity[a]), TICK_S)
        mujoco.mj_step(self.model, d)

    def advance(self, duration_s: float) -> None:
        for _ in range(int(round(duration_s / TICK_S))):
            self.step()

    def hold_start_pose(self, ids: list[int] | tuple[int, ...]) -> None:
        """Torque these servos on in position mode, holding where they are (a previous session
        that was not cleanly shut down leaves them so)."""
        for dxl_id in ids:
            s = self.servos[dxl_id]
            s.publish()
            s.set("Goal Position", s.get("Present Position"))
            s.set("Torque Enable", 1)


__all__ = ["ServoWorld"]
