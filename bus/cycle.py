"""The one cycle timer that paces every loop (driver ticks, node loops, controllers).

Pure standard library (no Zenoh): it lives in ``bus/`` because that is the bottom
layer every other package may import.

Catch-up rule (the only one in the code base):

* Cycle boundaries lie on a fixed grid ``t0 + k * period_s``; ``t0`` is when the timer
  starts (its first ``wait()`` or ``start()``).
* ``wait()`` sleeps until the next boundary of the grid.
* When the loop body overran and that boundary has already passed, ``wait()`` returns
  at once: the one late cycle starts immediately. Every further boundary that has
  also passed is **skipped**, counted in ``missed``, and never made up: there is no
  burst of catch-up cycles after a stall. The grid (the phase) is kept, so the cycle
  after the late one starts on the next boundary still ahead.

:class:`Rate` applies the same rule to a deadline that a loop polls among others (an
emulator serving telemetry, pose and heartbeat at their own rates, a camera's frames, a
driver's heartbeat): ``due(now)`` is True once per boundary reached, a boundary served
more than a period late skips (and counts) the ones it passed. Loops expose the counts
(``missed``, ``overruns``) in their ``health()`` / summaries.

Section timing: ``with timer.section("plan"): ...`` records how long each named part
of a cycle took; ``summary()`` gives p50/p99/max per section and of the cycle period
itself, plus counts of late cycles and missed periods.

Times are seconds of the injected ``clock`` (default ``time.monotonic``); tests inject
a fake clock and sleep so nothing here depends on wall time.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


def _catch_up(next_s: float, now_s: float, period_s: float) -> tuple[int, float]:
    """The catch-up rule for a boundary ``next_s`` reached at ``now_s``: (boundaries skipped,
    the next boundary). The cycle of ``next_s`` runs now; boundaries also passed are skipped,
    never made up; the grid's phase is kept."""
    missed = int((now_s - next_s) // period_s)
    return missed, next_s + (missed + 1) * period_s


#: samples kept per section for the p50/p99 summary (about 3 min at 50 Hz)
_HISTORY = 10_000


class CycleTimer:
    """Paces a loop at ``period_s`` on a fixed grid; skips (and counts) missed periods.

    ``clock() -> s`` and ``sleep(s)`` are injectable; ``sleep`` may return early
    (e.g. ``threading.Event.wait`` when a stop is requested): ``wait()`` then returns
    early too, and the caller checks its own stop condition.
    """

    def __init__(
        self,
        period_s: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Any] = time.sleep,
    ):
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"cycle period_s must be a positive number of seconds, got {period_s!r}")
        self.period_s = float(period_s)
        self._clock = clock
        self._sleep = sleep
        #: the next boundary wait() aims at [s of clock]; None before start()
        self._next_s: float | None = None
        #: when the current cycle started [s of clock]
        self.cycle_start_s: float | None = None
        self.cycles = 0
        #: cycles that started after their boundary (the body overran)
        self.late = 0
        #: boundaries skipped after an overrun, never made up
        self.missed = 0
        self._samples: dict[str, deque[float]] = {}

    def start(self, at_s: float | None = None) -> float:
        """Start the grid now (or at clock time ``at_s``, e.g. to keep in phase with another
        loop's grid); the first cycle begins then, the next one a period later."""
        now = self._clock() if at_s is None else float(at_s)
        self.cycle_start_s = now
        self._next_s = now + self.period_s
        return now

    def wait(self) -> int:
        """Sleep until the next boundary; returns the periods missed (0 when on time).

        The first call on a timer that was not started starts it and waits a full
        period, so N calls span N periods.
        """
        if self._next_s is None:
            self.start()
        now = self._clock()
        target = self._next_s
        if now < target:
            self._sleep(target - now)
            start = self._clock()
        else:
            # overran: this cycle starts late, right now; boundaries already behind us
            # (beyond the one this cycle belongs to) are skipped, never made up
            self.late += 1
            start = now
        missed, self._next_s = _catch_up(target, max(now, target), self.period_s)
        self.missed += missed
        if self.cycle_start_s is not None:
            self._record("cycle", start - self.cycle_start_s)
        self.cycle_start_s = start
        self.cycles += 1
        return missed

    def deadline_s(self, fraction: float) -> float:
        """Clock time ``fraction`` of a period after the current cycle started."""
        if self.cycle_start_s is None:
            self.start()
        return self.cycle_start_s + fraction * self.period_s

    # ------------------------------------------------------------------ timing
    @contextmanager
    def section(self, name: str) -> Iterator[None]:
        """Time a named part of the cycle (seconds of the timer's clock)."""
        t0 = self._clock()
        try:
            yield
        finally:
            self._record(name, self._clock() - t0)

    def _record(self, name: str, duration_s: float) -> None:
        q = self._samples.get(name)
        if q is None:
            q = self._samples[name] = deque(maxlen=_HISTORY)
        q.append(duration_s)

    def summary(self) -> dict[str, Any]:
        """Counts, and p50/p99/max [s] of the cycle period and of every section."""
        out: dict[str, Any] = {
            "period_s": self.period_s,
            "cycles": self.cycles,
            "late": self.late,
            "missed": self.missed,
        }
        for name, q in self._samples.items():
            s = sorted(q)
            out[name] = {
                "n": len(s),
                "p50_s": _quantile(s, 0.50),
                "p99_s": _quantile(s, 0.99),
                "max_s": s[-1],
            }
        return out

    def format_summary(self) -> str:
        """One line for logs: ``cycles 500 late 2 missed 3 | cycle p50 20.0 ms p99 21.3 ms | ...``."""
        s = self.summary()
        parts = [f"cycles {s['cycles']} late {s['late']} missed {s['missed']}"]
        for name, v in s.items():
            if isinstance(v, dict):
                parts.append(f"{name} p50 {v['p50_s'] * 1e3:.2f} ms p99 {v['p99_s'] * 1e3:.2f} ms")
        return " | ".join(parts)


class Rate:
    """A recurring deadline on a fixed grid, polled by a loop that serves several of them.

    ``due(now_s)`` is True once for each boundary reached (the first at ``first_s``, then
    every ``period_s``) and moves on to the next; after a stall the late boundary fires once
    and every further boundary already passed is skipped, counted in ``missed`` (and the
    firing in ``overruns``), never made up in a burst: the CycleTimer's rule. ``left_s(now)``
    is how long the loop may sleep before this deadline. Times are seconds of the caller's
    clock (``time.monotonic`` in the emulators; tests pass numbers)."""

    def __init__(self, period_s: float, first_s: float):
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"rate period_s must be a positive number of seconds, got {period_s!r}")
        self.period_s = float(period_s)
        #: the next boundary [s]
        self.next_s = float(first_s)
        #: boundaries served
        self.fired = 0
        #: boundaries skipped after a stall, never made up
        self.missed = 0
        #: firings that skipped at least one boundary
        self.overruns = 0

    def due(self, now_s: float) -> bool:
        """True when the next boundary has been reached (then it moves on, by the catch-up rule)."""
        if now_s < self.next_s:
            return False
        missed, self.next_s = _catch_up(self.next_s, now_s, self.period_s)
        self.fired += 1
        if missed:
            self.missed += missed
            self.overruns += 1
        return True

    def left_s(self, now_s: float) -> float:
        """Seconds until the next boundary (0 when it is due)."""
        return max(0.0, self.next_s - now_s)

    def counts(self, prefix: str) -> dict[str, int]:
        """``{prefix_missed, prefix_overruns}`` for a health() or summary dict."""
        return {f"{prefix}_missed": self.missed, f"{prefix}_overruns": self.overruns}


def _quantile(sorted_vals: list[float], q: float) -> float:
    """Nearest-rank quantile of an already sorted, non-empty list."""
    k = max(0, math.ceil(q * len(sorted_vals)) - 1)
    return sorted_vals[k]
