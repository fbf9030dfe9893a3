"""The pan unit's sim backend: its real driver over the in-process Dynamixel bus, in lockstep."""

from __future__ import annotations

import math

from hilstack.drivers.pan_unit.config import PanUnitParams
from hilstack.drivers.pan_unit.driver import PanUnitDriver
from hilstack.sim_backends.dynamixel.backend import DynamixelSim
from hilstack.sim_backends.pan_unit.world import PanWorld, shared_world


class PanUnitSim(DynamixelSim, PanUnitDriver):
    def __init__(self, params: PanUnitParams | None = None, source: str | None = None):
        PanUnitDriver.__init__(self, params, backend="sim", source=source)
        self.steps = 0

    def _world(self) -> PanWorld:
        return shared_world(self.params.bus_name, self.ids["pan"], math.radians(self.params.pan_half_range_deg))
