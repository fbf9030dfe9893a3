"""The one cycle timer: its catch-up rule and timing summary, on an injected clock."""

from __future__ import annotations

import pytest

from hilstack.bus.cycle import CycleTimer, Rate


class FakeClock:
    """A clock that moves only when slept on or told to (the loop body's work)."""

    def __init__(self) -> None:
        self.t = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.sleeps.append(dt)
        self.t += dt

    def work(self, dt: float) -> None:
        self.t += dt


def _timer(period_s: float = 0.1) -> tuple[CycleTimer, FakeClock]:
    c = FakeClock()
    return CycleTimer(period_s, clock=c, sleep=c.sleep), c


def test_on_time_cycles_sit_on_the_grid():
    timer, c = _timer()
    t0 = timer.start()
    starts = []
    for _ in range(5):
        c.work(0.03)
        assert timer.wait() == 0
        starts.append(timer.cycle_start_s)
    assert starts == pytest.approx([t0 + 0.1 * k for k in range(1, 6)])
    assert timer.late == 0 and timer.missed == 0 and timer.cycles == 5


def test_first_wait_without_start_waits_a_full_period():
    timer, c = _timer()
    t0 = c.t
    timer.wait()
    timer.wait()
    assert c.t == pytest.approx(t0 + 0.2)  # N waits span N periods


def test_stall_skips_missed_periods_without_a_burst_and_keeps_the_phase():
    timer, c = _timer()
    t0 = timer.start()
    c.work(0.35)  # the body stalls for 3.5 periods
    missed = timer.wait()
    # boundary 1 is served late, right away; boundaries 2 and 3 are skipped and counted
    assert missed == 2 and timer.missed == 2 and timer.late == 1
    assert c.sleeps == []  # the late cycle starts at once
    assert timer.cycle_start_s == pytest.approx(t0 + 0.35)
    # no burst: the next cycle waits for boundary 4 (the grid is kept), then on time again
    starts = []
    for _ in range(3):
        c.work(0.01)
        assert timer.wait() == 0
        starts.append(timer.cycle_start_s)
    assert starts == pytest.approx([t0 + 0.4, t0 + 0.5, t0 + 0.6])
    assert timer.cycles == 4 and timer.missed == 2 and timer.late == 1


def test_small_overrun_is_late_but_misses_nothing():
    timer, c = _timer()
    t0 = timer.start()
    c.work(0.12)
    assert timer.wait() == 0
    assert timer.late == 1 and timer.missed == 0
    c.work(0.01)
    timer.wait()
    assert timer.cycle_start_s == pytest.approx(t0 + 0.2)


def test_section_summary_p50_p99_and_cycle_periods():
    timer, c = _timer()
    timer.start()
    for k in range(100):
        with timer.section("plan"):
            c.work(0.001 * (k + 1))  # 1 ms ... 100 ms
        timer.wait()
    s = timer.summary()
    assert s["plan"]["n"] == 100
    assert s["plan"]["p50_s"] == pytest.approx(0.050)
    assert s["plan"]["p99_s"] == pytest.approx(0.099)
    assert s["plan"]["max_s"] == pytest.approx(0.100)
    # the 100 ms body overran once (exactly on the boundary: late, nothing missed)
    assert s["cycle"]["p50_s"] == pytest.approx(0.1)
    assert "plan p50 50.00 ms p99 99.00 ms" in timer.format_summary()


def test_early_wakeup_from_a_stop_request_returns_early():
    c = FakeClock()
    timer = CycleTimer(0.1, clock=c, sleep=lambda dt: c.work(dt / 2))  # interrupted halfway
    timer.start()
    assert timer.wait() == 0
    assert c.t == pytest.approx(100.05)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_period_is_refused(bad):
    with pytest.raises(ValueError, match="period_s"):
        CycleTimer(bad)


def test_driver_tick_follows_the_catch_up_rule(monkeypatch):
    """Driver.tick is paced by the same timer: a stall is not made up in a burst."""
    from tests.test_driver_base import Fake

    c = FakeClock()

    def timer_on_fake_clock(period_s):
        return CycleTimer(period_s, clock=c, sleep=c.sleep)

    monkeypatch.setattr("hilstack.drivers.base.CycleTimer", timer_on_fake_clock)
    d = Fake()
    t0 = c.t
    super(Fake, d).tick()  # the wall-clock tick of the base class (Fake overrides it)
    assert c.t == pytest.approx(t0 + 0.1)
    c.work(0.35)
    super(Fake, d).tick()  # late: returns at once, 2 periods skipped
    assert c.t == pytest.approx(t0 + 0.45) and d._cycle.missed == 2
    super(Fake, d).tick()
    assert c.t == pytest.approx(t0 + 0.5)  # back on the grid


def test_node_run_is_paced_and_timed(bus):
    from hilstack.bus.node import Node

    with Node("t", "cyc", bus, handle_signals=False) as n:
        calls = []
        assert n.run(lambda: calls.append(1), 0.001, max_steps=3) == 3
        assert n.cycle.summary()["step"]["n"] == 3 and n.cycle.cycles == 2


# -- Rate: the same rule for a deadline a loop polls among others -------------------------------
def _firings(rate: Rate, times: list[float]) -> list[float]:
    return [t for t in times if rate.due(t)]


def test_rate_fires_once_per_boundary_on_the_grid():
    r = Rate(0.1, first_s=10.0)
    # polled every 10 ms for half a second: one firing per boundary, at the first poll past it
    polls = [10.0 + 0.01 * k for k in range(51)]
    fired = _firings(r, polls)
    assert fired == pytest.approx([10.0 + 0.1 * k for k in range(6)])
    assert r.fired == 6 and r.missed == 0 and r.overruns == 0
    assert r.left_s(10.52) == pytest.approx(0.08)


def test_rate_after_a_stall_fires_once_skips_the_rest_and_keeps_the_phase():
    r = Rate(0.1, first_s=0.0)
    assert r.due(0.0)
    # the loop stalls until 0.47: boundaries 0.1 .. 0.4 passed; one firing, three skipped
    polls = [0.47, 0.47, 0.48, 0.49, 0.5, 0.51, 0.6]
    fired = _firings(r, polls)
    assert fired == pytest.approx([0.47, 0.5, 0.6])  # no burst: the next one waits for 0.5
    assert r.missed == 3 and r.overruns == 1 and r.fired == 4
    assert r.counts("telemetry") == {"telemetry_missed": 3, "telemetry_overruns": 1}


@pytest.mark.parametrize("bad", [0.0, -1.0, float("inf"), float("nan")])
def test_rate_bad_period_is_refused(bad):
    with pytest.raises(ValueError, match="period_s"):
        Rate(bad, 0.0)
