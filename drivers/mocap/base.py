"""The mocap contract: anything that yields the latest rigid-body pose.

Frames: positions [m] in the mocap world frame (z up, as the VelociRoACH arena is set
up; NatNet's default y-up must be converted by the source), quaternions (w, x, y, z)
rotating body to world. ``t_s`` is the source's timestamp of the sample [s] (mocap
clock or sim time), not the arrival time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class PoseSample:
    """One rigid-body pose. ``frame_id`` names the rigid body (e.g. its mocap id)."""

    t_s: float
    position_m: np.ndarray
    quaternion_wxyz: np.ndarray
    frame_id: str = "0"
    seq: int = 0
    #: receive time on the local monotonic clock [s] (None for in-process sources)
    received_s: float | None = field(default=None, compare=False)

    @property
    def position(self) -> np.ndarray:
        return self.position_m

    @property
    def quaternion(self) -> np.ndarray:
        return self.quaternion_wxyz


@runtime_checkable
class PoseSource(Protocol):
    """A latest-value pose source. ``latest()`` never blocks; None when nothing arrived yet.
    ``stats()``: its counters (``received``, ``corrupt``, ``dropped`` frames; the driver's health).
    ``port``: the local UDP port it listens on, when it has one of its own (None otherwise)."""

    port: int | None

    def latest(self) -> PoseSample | None: ...

    def stats(self) -> dict[str, int]: ...

    def close(self) -> None: ...
