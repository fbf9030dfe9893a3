"""Shared pieces of MuJoCo sim backends: lockstep time."""

from __future__ import annotations

from typing import Any

from drivers.base import Driver


class LockstepSim(Driver):
    """A simulated backend whose clock advances only in ``tick()``.

    Subclasses implement ``_advance(duration_s)`` to integrate physics with the held
    command and ``sim_time_s``.
    """

    backend = "sim"

    def __init__(self) -> None:
        super().__init__()
        self.steps = 0

    def now(self) -> float:
        return self.sim_time_s

    @property
    def sim_time_s(self) -> float:
        raise NotImplementedError

    def tick(self) -> None:
        self._advance(self.spec.period_s)
        self.steps += 1

    def _advance(self, duration_s: float) -> None:
        raise NotImplementedError

    def reset(self, **kwargs: Any) -> None:
        """Put the simulated robot back to its initial state (sim-only convenience)."""
        raise NotImplementedError
