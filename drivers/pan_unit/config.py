"""The pan unit: one Dynamixel XM430-W350 turning a camera or sensor about a vertical axis.

State (2): pan angle [rad], pan rate [rad/s]. Action (1): target pan angle [rad] to the
servo's position loop, rate limited. Stop holds the measured angle (``safe_action`` None).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from hilstack.configs.schema import PeriodS, StaleS, finite
from hilstack.drivers.base import RobotSpec, Space
from hilstack.drivers.dynamixel.params import BusParams, check_watchdog

#: the pan range each way [deg]
PanHalfRangeDeg = finite(ge=5.0, le=170.0, source=(
    "≥ 5°: a range the servo's 0.088° resolution holds; ≤ 170°: the cable to the sensor winds less than a turn"))
#: rate limit of the pan target [rad/s]
PanRateRadS = finite(gt=0, le=4.8, source="XM430-W350 no-load speed at 12 V: 46 rev/min = 4.8 rad/s (ROBOTIS e-Manual)")


class PanUnitParams(BusParams):
    ids: dict[str, int] = Field(default_factory=lambda: {"pan": 1})
    bus_name: str = "pan_unit"
    period_s: PeriodS = Field(0.02, description="driver control period")
    telemetry_stale_s: StaleS = Field(0.1, description="a reading older than this is not ok")
    pan_half_range_deg: PanHalfRangeDeg = 90.0
    pan_rate_rad_s: PanRateRadS = Field(2.0, description="rate limit of the pan target")

    @field_validator("ids")
    @classmethod
    def _ids(cls, v: dict[str, int]) -> dict[str, int]:
        if set(v) != {"pan"} or not 0 <= v["pan"] <= 252:
            raise ValueError(f"ids must be {{pan: 0..252}}, got {v}")
        return v

    @field_validator("period_s")
    @classmethod
    def _watchdog_vs_period(cls, v: float, info: ValidationInfo) -> float:
        return check_watchdog(v, info)


def pan_unit_spec(p: PanUnitParams) -> RobotSpec:
    r = math.radians(p.pan_half_range_deg)
    return RobotSpec(name="pan_unit", state=Space.build([("pan", "rad", -r, r), ("pan_vel", "rad/s", -math.inf, math.inf)]),
                     action=Space.build([("pan", "rad", -r, r)]), period_s=p.period_s,
                     action_rate_per_s=np.array([p.pan_rate_rad_s]),
                     description="pan unit: one Dynamixel XM430-W350 in position mode")
