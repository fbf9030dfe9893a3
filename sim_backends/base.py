"""Shared pieces of MuJoCo sim backends: lockstep time, and real-time pacing for emulators."""

from __future__ import annotations

import time
from typing import Any

from hilstack.drivers.base import Driver


class LockstepSim(Driver):
    """A simulated backend whose clock advances only in ``tick()``.

    Subclasses implement ``_advance(duration_s)`` to integrate physics with the held
    command; the clock is ``self.data.time`` unless they override ``sim_time_s``.
    """

    backend = "sim"

    def __init__(self) -> None:
        super().__init__()
        self.steps = 0

    def now(self) -> float:
        return self.sim_time_s

    #: the MuJoCo data of a backend that integrates one model itself (None until configured);
    #: a backend whose clock lives elsewhere (a servo world, a scene) overrides ``sim_time_s``
    data: Any = None

    @property
    def sim_time_s(self) -> float:
        return 0.0 if self.data is None else float(self.data.time)

    def tick(self) -> None:
        self._advance(self.spec.period_s)
        self.steps += 1

    def _advance(self, duration_s: float) -> None:
        raise NotImplementedError

    def reset(self, **kwargs: Any) -> None:
        """Put the simulated robot back to its initial state (sim-only convenience)."""
        raise NotImplementedError


class RealtimePacer:
    """Keeps a device emulator's simulation on the wall clock, in whole firmware ticks.

    :meth:`due` says how many ticks of ``tick_s`` to integrate now so that sim time follows
    ``realtime_factor`` × wall time since construction. When the loop falls more than
    ``max_catchup_s`` behind (a loaded CPU), that time is given up and counted in
    ``slip_s`` instead of integrated in one burst: the robot's world slows down rather than
    jumping."""

    def __init__(self, sim_time_s: float, tick_s: float, max_catchup_s: float = 0.05,
                 realtime_factor: float = 1.0, now_s: float | None = None):
        self.t0_s = time.monotonic() if now_s is None else now_s
        self.sim_t0_s = sim_time_s
        self.tick_s = tick_s
        self.max_catchup_s = max_catchup_s
        self.realtime_factor = realtime_factor
        self.slip_s = 0.0

    def target_s(self, now_s: float) -> float:
        """The sim time the wall clock asks for at ``now_s``."""
        return self.sim_t0_s + (now_s - self.t0_s) * self.realtime_factor

    def due(self, now_s: float, sim_time_s: float) -> int:
        """Whole ticks to integrate at ``now_s`` (0 when the sim is ahead)."""
        lag = self.target_s(now_s) - sim_time_s
        if lag > self.max_catchup_s:
            slip = lag - self.max_catchup_s
            self.sim_t0_s -= slip
            self.slip_s += slip
            lag = self.max_catchup_s
        return max(0, int(lag / self.tick_s + 1e-9))
