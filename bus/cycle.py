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
        missed = 0
        if now < target:
            self._sleep(target - now)
            start = self._clock()
        else:
            # overran: this cycle starts late, right now; boundaries already behind us
            # (beyond the one this cycle belongs to) are skipped, never made up
            self.late += 1
            missed = int((now - target) // self.period_s)
            target += missed * self.period_s
            start = now
        self.missed += missed
        self._next_s = target + self.period_s
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


def _quantile(sorted_vals: list[float], q: float) -> float:
    """Nearest-rank quantile of an already sorted, non-empty list."""
    k = max(0, math.ceil(q * len(sorted_vals)) - 1)
    return sorted_vals[k]
