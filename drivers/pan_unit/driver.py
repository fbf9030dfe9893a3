"""The pan unit's driver: the contract over a Dynamixel bus, its servo in position mode.

backend "real": ``params.port``; "emulated": the bus emulator with the pan unit's world
(``python -m hilstack.sim_backends.pan_unit.emulator``, started by the driver); the sim
backend (sim_backends/pan_unit/backend.py) runs this code over an in-process bus.
"""

from __future__ import annotations

from hilstack.drivers.dynamixel.position import PositionRobot
from hilstack.drivers.pan_unit.config import PanUnitParams, pan_unit_spec


class PanUnitDriver(PositionRobot):
    params_type = PanUnitParams
    EMULATOR = "pan_unit"
    BUS_NAME = "pan_unit"

    def __init__(self, params: PanUnitParams | None = None, backend: str = "real", source: str | None = None):
        params = params or PanUnitParams()
        self.ids = dict(params.ids)
        self.spec = pan_unit_spec(params)
        super().__init__(params, backend, source)

    def _emulator_config(self) -> dict:
        return {"pan_id": self.ids["pan"]}
