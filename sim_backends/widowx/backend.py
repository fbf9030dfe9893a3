"""WidowX and mechanism MuJoCo backends: the real drivers' code over the in-process
Dynamixel bus (sim_backends/dynamixel/backend.py) on the bench's world.

Robots with the same ``bus_name`` share one world (the arm sees the switch the mechanism
moves). Each robot's ``tick()`` advances that world by its own period.
"""

from __future__ import annotations

from hilstack.configs.schema import RobotConfig, parse_params
from hilstack.drivers.widowx.config import MechanismParams, WidowXParams
from hilstack.drivers.widowx.driver import MechanismDriver, WidowXDriver
from hilstack.sim_backends.dynamixel.backend import DynamixelSim
from hilstack.sim_backends.widowx.world import ArmWorld, shared_world


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
    def from_config(cls, cfg: RobotConfig) -> WidowXSim:
        return cls(parse_params(cfg, WidowXParams), source=cfg.source)

    def _world(self) -> ArmWorld:
        return shared_world(self.params.bus_name, arm_ids=self.ids, start_holding=self.params.sim.get("start_holding"))


class MechanismSim(DynamixelSim, MechanismDriver):
    def __init__(self, params: MechanismParams | None = None, source: str | None = None):
        MechanismDriver.__init__(self, params, backend="sim", source=source)
        self.steps = 0

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> MechanismSim:
        return cls(parse_params(cfg, MechanismParams), source=cfg.source)

    def _world(self) -> ArmWorld:
        return shared_world(self.params.bus_name, mech_ids=self.ids)
