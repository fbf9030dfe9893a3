"""Episode-end detectors: pluggable checks the reset supervisor runs on every state.

A detector sees each :class:`~hilstack.bus.schemas.RobotState` of the running episode (with the
robot's state-channel names) and returns why the episode ended, or ``None``. The
supervisor calls :meth:`EpisodeEndDetector.start` when a new episode begins.

- :class:`TimeoutDetector`: the episode lasted ``max_s`` seconds of robot time
  (the thesis ends a Baoding episode after 10 s).
- :class:`ArenaDetector`: the robot left a circle in the world plane (VelociRoACH: mocap
  x, y).
- :class:`TippedDetector`: the robot is on its side or back (roll or pitch).
- :class:`DropDetector`: an object fell; the hand implements it on its state or the
  camera tracker's ball heights. The generic rule here watches named height channels.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence

from hilstack.bus.schemas import RobotState
from hilstack.control.reset.config import DetectorConfig


class EpisodeEndDetector(ABC):
    """``detector(state) -> reason | None``. One instance per supervisor."""

    name: str = "detector"
    #: the robot whose state this detector sees (None: the reset robot's); set from the config
    robot: str | None = None

    def bind(self, state_names: Sequence[str]) -> None:  # noqa: B027 - optional hook
        """Called once with the robot's state channel names (from its spec)."""

    def start(self, first: RobotState) -> None:  # noqa: B027 - optional hook
        """A new episode begins with ``first``."""

    @abstractmethod
    def __call__(self, state: RobotState) -> str | None:
        """Why the episode is over (one line), or None while it runs."""


class TimeoutDetector(EpisodeEndDetector):
    name = "timeout"

    def __init__(self, max_s: float):
        self.max_s = float(max_s)
        self._t0_s: float | None = None

    def start(self, first: RobotState) -> None:
        self._t0_s = first.t_s

    def __call__(self, state: RobotState) -> str | None:
        if self._t0_s is None:
            self._t0_s = state.t_s
        if state.t_s - self._t0_s >= self.max_s:
            return f"timeout: episode ran {state.t_s - self._t0_s:.1f} s (max {self.max_s:g} s)"
        return None


class ArenaDetector(EpisodeEndDetector):
    """The robot's (x, y) [m, world frame] is farther than ``radius_m`` from the centre."""

    name = "arena"

    def __init__(self, radius_m: float, center_xy_m: tuple[float, float] = (0.0, 0.0), x: str = "x", y: str = "y"):
        self.radius_m = float(radius_m)
        self.cx, self.cy = map(float, center_xy_m)
        self._names = (x, y)
        self._ix = self._iy = -1

    def bind(self, state_names: Sequence[str]) -> None:
        self._ix, self._iy = (list(state_names).index(n) for n in self._names)

    def __call__(self, state: RobotState) -> str | None:
        r = math.hypot(state.state[self._ix] - self.cx, state.state[self._iy] - self.cy)
        if r > self.radius_m:  # NaN compares False: a bad reading does not end the episode
            return f"arena: robot {r:.2f} m from the centre (radius {self.radius_m:g} m)"
        return None


class DropDetector(EpisodeEndDetector):
    """An object dropped: any of ``channels`` (heights [m]) below ``min_height_m``.

    The interface the Shadow Hand implements: subclass and override ``__call__`` for a
    drop seen in the hand state or the camera tracker's ball positions.
    """

    name = "drop"

    def __init__(self, channels: Sequence[str], min_height_m: float):
        self.channels = list(channels)
        self.min_height_m = float(min_height_m)
        self._idx: list[int] = []

    def bind(self, state_names: Sequence[str]) -> None:
        missing = [c for c in self.channels if c not in state_names]
        if missing:
            raise ValueError(f"drop detector: state has no channel {missing}; has {list(state_names)}")
        self._idx = [list(state_names).index(c) for c in self.channels]

    def __call__(self, state: RobotState) -> str | None:
        for c, i in zip(self.channels, self._idx, strict=True):
            if state.state[i] < self.min_height_m:
                return f"drop: {c} = {state.state[i]:.3f} m (below {self.min_height_m:g} m)"
        return None


class TippedDetector(EpisodeEndDetector):
    """The robot tipped over: ``cos_roll`` or ``cos_pitch`` below ``min_cos`` (data
    after a flip is not the task's; a ``self_right`` reset step can recover it)."""

    name = "tipped"

    def __init__(self, min_cos: float = 0.5):
        self.min_cos = float(min_cos)
        self._idx: list[tuple[str, int]] = []

    def bind(self, state_names: Sequence[str]) -> None:
        self._idx = [(c, list(state_names).index(c)) for c in ("cos_roll", "cos_pitch") if c in state_names]
        if not self._idx:
            raise ValueError(f"tipped detector: state has neither cos_roll nor cos_pitch; has {list(state_names)}")

    def __call__(self, state: RobotState) -> str | None:
        for c, i in self._idx:
            if state.state[i] < self.min_cos:
                return f"tipped: {c} = {state.state[i]:.2f} (below {self.min_cos:g})"
        return None


def make_detector(cfg: DetectorConfig) -> EpisodeEndDetector:
    if cfg.kind == "timeout":
        d: EpisodeEndDetector = TimeoutDetector(cfg.max_s)
    elif cfg.kind == "arena":
        d = ArenaDetector(cfg.radius_m, cfg.center_xy_m)
    elif cfg.kind == "tipped":
        d = TippedDetector(cfg.min_cos)
    else:
        d = DropDetector(cfg.channels, cfg.min_height_m)
    #: None: the reset robot's state; a name: that robot's (the supervisor feeds it)
    d.robot = cfg.robot
    return d
