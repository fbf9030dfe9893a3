"""WidowX and mechanism MuJoCo backends: the real drivers' code over the in-process
Dynamixel bus (sim_backends/dynamixel/backend.py) on the bench's world.

Robots with the same ``bus_name`` share one world (the arm sees the switch the mechanism
moves). Each robot's ``tick()`` advances that world by its own period.
"""

from __future__ import annotations

from typing import Any

from hilstack.drivers.widowx.config import MechanismParams, WidowXParams
from hilstack.drivers.widowx.driver import MechanismDriver, WidowXDriver
from hilstack.sim_backends.dynamixel.backend import DynamixelSim
from hilstack.sim_backends.widowx.world import ArmWorld, shared_world

#: a mid-range pose of the arm (rad), away from the limits: calibration excitations move about it
MID_POSE_RAD = {"waist": 0.0, "shoulder": -0.3, "elbow": 0.3, "forearm_roll": 0.0, "wrist_angle": 0.4,
                "wrist_rotate": 0.0}


class WidowXSim(DynamixelSim, WidowXDriver):
    """``params.sim.cameras: true`` adds ``extras["image"]``: the fixed and wrist cameras,
    64×128 RGB (``params.sim.camera_px`` per view), rendered at every read."""

    def __init__(self, params: WidowXParams | None = None, source: str | None = None):
        WidowXDriver.__init__(self, params, backend="sim", source=source)
        self.steps = 0
        self._cameras = None

    def _read(self):
        obs = super()._read()
        if self.params.sim.get("cameras") and self.world is not None:
            if self._cameras is None:
                from hilstack.sim_backends.widowx.cameras import BenchCameras

                self._cameras = BenchCameras(self.world.model, int(self.params.sim.get("camera_px", 64)))
            obs.extras["image"] = self._cameras.render(self.world.data)
        return obs

    def _close_bus(self) -> None:
        if self._cameras is not None:
            self._cameras.close()
            self._cameras = None
        super()._close_bus()

    @classmethod
    def calibration_bench(cls, params: WidowXParams | None = None) -> dict[str, Any]:
        """What `hil calibrate --model <widowx config>` needs to replay a recording through the
        bench's MuJoCo model (hilstack.calibration.mjcf_robot): the bench's MjSpec (``params.sim.mjcf``
        if set, else the built one), how each arm joint is driven (velocity-mode PI loop: P on
        velocity error [N·m·s/rad], I [N·m/rad], torque limit [N·m], torque constant [N·m/A]),
        which state columns hold position, velocity and current, and that actions are goal
        velocities [rad/s] of the joints in that order."""
        import mujoco

        from hilstack.drivers.dynamixel.control_table import RAD_S_PER_COUNT
        from hilstack.drivers.widowx.config import JOINTS
        from hilstack.sim_backends.dynamixel.firmware import ServoPhysics
        from hilstack.sim_backends.widowx.model import build_spec

        params = params or WidowXParams()
        torques = {n: t for n, _, _, t in JOINTS}
        mjcf = params.sim.get("mjcf")
        spec = mujoco.MjSpec.from_file(str(mjcf)) if mjcf else build_spec(torques)
        names = [n for n, _, _, _ in JOINTS]
        loops = {}
        for n in names:
            ph = ServoPhysics(stall_torque_nm=torques[n])
            loops[n] = {"mode": "velocity", "kp_nm_s": ph.vel_kp_nm_s, "ki_nm": ph.vel_ki_nm,
                        "tau_max_nm": ph.stall_torque_nm, "kt_nm_per_a": ph.kt_nm_per_a}
        k = len(names)
        # an excitation (hilstack.calibration.robot_rig): effects go to the sim world or the bus emulator;
        # the bench starts holding the mid pose; a bus of its own; joint velocities track the multi-sine
        excite = {"place": {"sim": "sim", "emulated": "emulator"}, "bench": {"start_holding": dict(MID_POSE_RAD)},
                  "driver": {"bus_name": "excite-{seed}-{uid}", "telemetry_stale_s": 0.25},
                  "mid": [MID_POSE_RAD[n] for n in names], "command": "velocity", "amplitude": 0.35}
        # the driver writes each goal rounded to a Goal Velocity count (RAD_S_PER_COUNT = 0.024 rad/s): the
        # replay rounds the recorded goals alike (on a lockstep clean recording the open-loop error
        # fell from 0.013 to 0.005); the goal written after sample k acts from sample k on (goal_lag 1)
        return {"spec": spec, "joints": names, "loops": loops, "q": list(range(0, k)), "qd": list(range(k, 2 * k)),
                "current": list(range(2 * k, 3 * k)), "action": "goal_velocity", "excite": excite,
                "goal_step": RAD_S_PER_COUNT, "goal_lag": 1}

    def _world(self) -> ArmWorld:
        return shared_world(self.params.bus_name, arm_ids=self.ids, start_holding=self.params.sim.get("start_holding"),
                            effects=self.params.sim.get("effects"), mjcf=self.params.sim.get("mjcf"))


class MechanismSim(DynamixelSim, MechanismDriver):
    def __init__(self, params: MechanismParams | None = None, source: str | None = None):
        MechanismDriver.__init__(self, params, backend="sim", source=source)
        self.steps = 0

    def _world(self) -> ArmWorld:
        return shared_world(self.params.bus_name, mech_ids=self.ids)
