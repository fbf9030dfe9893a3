"""Parameters and spec of the stereo camera tracker (docs/camera.md explains every field).

State (8 channels): ``ball0_x ball0_y ball0_z ball1_x ball1_y ball1_z`` [m, hand frame]
then ``ball0_conf ball1_conf`` [1, 0..1]. A ball seen with less than ``min_confidence``
keeps its last confident position (0 before any) beside the confidence measured now.
Action: empty (a sensor).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from hilstack.configs.schema import FailAfterS, Params, PeriodS, RateHz, StaleS, finite
from hilstack.drivers.base import RobotSpec, Space

STATE_NAMES = ("ball0_x", "ball0_y", "ball0_z", "ball1_x", "ball1_y", "ball1_z", "ball0_conf", "ball1_conf")


#: left/right pairing tolerance [s]
SkewS = finite(ge=0, le=0.1, source="≤ 0.1 s: frames further apart see a ball moved by centimetres (≤ 0.5 m/s): no pair")


class CameraParams(Params):
    camera_id: str = Field("stereo0", description="the pair's id: names its calibration file")
    period_s: PeriodS = Field(0.05, description="read period (20 Hz)")
    width_px: int = Field(280, gt=0)
    height_px: int = Field(180, gt=0)
    tracker: Literal["color", "learned"] = "learned"
    weights: str | None = Field(None, description="learned: weights file (default: the shipped ones)")
    calibration: str | None = Field(
        None, description="calibration file or directory (<camera_id>.json); sim: None uses the exact one")
    min_confidence: float = Field(0.5, ge=0, le=1, description="below this a ball counts as not seen")
    stale_after_s: StaleS = Field(0.2, description="a frame pair (or a confident ball) older than this is stale")
    fail_after_s: FailAfterS = Field(2.0, description="real: no frame pair for this long takes the error path")
    encoding: Literal["jpeg", "png"] = Field("jpeg", description="how images go on the bus and into recordings")
    jpeg_quality: int = Field(90, ge=1, le=100)
    # real (UVC through OpenCV)
    left_device: int | str = Field(0, description="OpenCV device index, /dev/videoN, or a video file/URL")
    right_device: int | str = 1
    max_skew_s: SkewS = Field(0.01, description="a left/right pair further apart than this is not a pair")
    fps: RateHz = Field(30.0, description="frame rate asked of the cameras")
    sim: dict = Field(default_factory=dict, description="sim backend parameters (palm tilt, motion)")


def camera_spec(p: CameraParams) -> RobotSpec:
    units = ["m"] * 6 + ["1"] * 2
    lo = [-np.inf] * 6 + [0.0, 0.0]
    hi = [np.inf] * 6 + [1.0, 1.0]
    return RobotSpec(
        name="camera",
        state=Space.build([(n, u, a, b) for n, u, a, b in zip(STATE_NAMES, units, lo, hi, strict=True)]),
        action=Space.build([]),
        period_s=p.period_s,
        description=f"stereo pair {p.camera_id} {p.width_px}x{p.height_px}, {p.tracker} ball tracker",
    )
