"""Unit tests of the contract's own logic on a trivial in-memory driver (no I/O)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.base import Driver, Lifecycle, Observation, RobotSpec, Space


class Fake(Driver):
    backend = "sim"

    def __init__(self, fail_read=False):
        super().__init__()
        self.spec = RobotSpec(
            name="fake",
            state=Space.build([("q", "rad", -1, 1)]),
            action=Space.build([("q_cmd", "rad", -1, 1)]),
            period_s=0.1,
            action_rate_per_s=np.array([1.0]),
        )
        self.q = 0.3
        self.sent = []
        self.stopped = 0
        self.t = 0.0
        self.fail_read = fail_read

    def now(self):
        return self.t

    def tick(self):
        self.t += 0.1

    def _read(self):
        if self.fail_read:
            raise OSError("port vanished")
        return Observation(self.t, np.array([self.q]), 0)

    def _write(self, a):
        self.sent.append(a.copy())

    def _stop(self):
        self.stopped += 1

    def _hold_command(self, obs):
        return obs.state  # position robot: hold where it is


def test_activation_holds_measured_state_and_rate_limits_from_there():
    d = Fake()
    with d:
        assert d.held_command == pytest.approx([0.3])
        a = d.write([1.0])  # 1 rad/s * 0.1 s from 0.3
        assert a == pytest.approx([0.4])
        d.tick()
        assert d.write([-1.0]) == pytest.approx([0.3])
    assert d.lifecycle is Lifecycle.UNCONFIGURED and d.stopped >= 1


def test_nothing_reaches_the_wire_on_bad_input():
    d = Fake()
    with d:
        for bad in ([np.inf], [np.nan], [1.0, 2.0], "x", None):
            with pytest.raises(ValueError):
                d.write(bad)
        assert d.sent == []


def test_error_path_stops_and_goes_unconfigured():
    d = Fake(fail_read=True)
    d.configure()
    with pytest.raises(OSError):
        d.activate()
    assert d.lifecycle is Lifecycle.UNCONFIGURED
    assert d.stopped == 1 and "port vanished" in d.health().last_error


def test_space_checks():
    with pytest.raises(ValueError, match="low > high"):
        Space.build([("a", "m", 1, 0)])
    s = Space.build([("a", "m", 0, 1), ("b", "m", 0, 1)])
    assert s.index("b") == 1
    with pytest.raises(KeyError, match="channels are"):
        s.index("c")
