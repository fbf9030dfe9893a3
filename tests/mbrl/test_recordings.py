"""Episodes from MCAP recordings: transitions, normalization, resets, bad readings."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.bus import keys
from hilstack.bus.recording import McapLog
from hilstack.bus.schemas import RobotState, SpecMsg
from hilstack.learning.recordings import episodes_from_mcap
from tests.helpers import spec_dict

SPEC = spec_dict("bot", ["x", "v"], ["u"], -2.0, 2.0)


def _write(path, states):
    with McapLog(path) as log:
        log.write(keys.spec("r", "bot"), SpecMsg(robot="bot", spec=SPEC))
        for i, (ep, x, a, ok) in enumerate(states):
            log.write(keys.state("r", "bot"),
                      RobotState(robot="bot", t_s=0.1 * i, state=[x, 0.0], action=[a], episode=ep, ok=ok, seq=i + 1))


def test_transitions_episodes_and_normalized_actions(tmp_path):
    rows = [(1, float(i), 1.0 * (i > 0), True) for i in range(6)] + [(2, 10.0 + i, -2.0, True) for i in range(4)]
    _write(tmp_path / "a.mcap", rows)
    eps = episodes_from_mcap(tmp_path / "a.mcap")
    assert [len(e) for e in eps] == [5, 3]
    np.testing.assert_allclose(eps[0].states[:, 0], np.arange(6))
    np.testing.assert_allclose(eps[0].actions[:, 0], 0.5)  # 1.0 of ±2 → 0.5
    np.testing.assert_allclose(eps[1].actions[:, 0], -1.0)
    raw = episodes_from_mcap(tmp_path / "a.mcap", normalize=False)
    np.testing.assert_allclose(raw[1].actions[:, 0], -2.0)
    assert eps[0].meta["state_names"] == ["x", "v"]


def test_bad_readings_split_the_episode(tmp_path):
    rows = [(0, float(i), 1.0, i != 4) for i in range(10)]
    _write(tmp_path / "b.mcap", rows)
    eps = episodes_from_mcap(tmp_path / "b.mcap")
    assert [e.states[0, 0] for e in eps] == [0.0, 5.0]
    assert [len(e) for e in eps] == [3, 4]


def test_unknown_robot_is_a_clear_error(tmp_path):
    _write(tmp_path / "c.mcap", [(0, 0.0, 0.0, True), (0, 1.0, 0.0, True)])
    with pytest.raises(ValueError, match="no states of robot 'other'"):
        episodes_from_mcap(tmp_path / "c.mcap", "other")


class _Recorder:
    """Writes a recording in order: the spec, then states and the supervisor's transitions."""

    def __init__(self, log: McapLog):
        self.log, self._t = log, iter(range(1, 1000))
        log.write(keys.spec("r", "bot"), SpecMsg(robot="bot", spec=SPEC), log_time_ns=next(self._t))

    def state(self, i: int, ep: int, x: float) -> None:
        self.log.write(keys.state("r", "bot"), RobotState(robot="bot", t_s=0.1 * i, state=[x, 0.0], action=[1.0],
                                                          episode=ep, seq=i + 1), log_time_ns=next(self._t))

    def transitions(self, *path: str) -> None:
        """``transitions("a", "b", "c")``: a → b, then b → c."""
        from hilstack.bus.schemas import ResetTransition

        for src, dst in zip(path[:-1], path[1:], strict=True):
            self.log.write(keys.reset_transition("r"), ResetTransition(robot="bot", trigger="t", source=src, dest=dst),
                           log_time_ns=next(self._t))


def test_a_reset_recorded_under_the_ended_episode_is_left_out(tmp_path):
    """The driver bumps the episode when the reset is done: the reset's motion (here a
    teleport-like jump) is recorded under episode 0, between the supervisor's transitions."""
    with McapLog(tmp_path / "r.mcap") as log:
        rec = _Recorder(log)
        for i in range(5):
            rec.state(i, 0, float(i))
        rec.transitions("running", "episode_end")
        for i, x in [(5, 4.5), (6, 50.0), (7, 0.0)]:  # the reset drives back, then jumps home
            rec.state(i, 0, x)
        rec.transitions("episode_end", "paused", "resetting", "verifying", "resumed", "running")
        for i in range(8, 12):
            rec.state(i, 1, float(i - 8))
    eps = episodes_from_mcap(tmp_path / "r.mcap")
    np.testing.assert_allclose(eps[0].states[:, 0], [0, 1, 2, 3, 4])
    np.testing.assert_allclose(eps[1].states[:, 0], [0, 1, 2, 3])
    assert max(np.abs(np.diff(e.states[:, 0])).max() for e in eps) == 1.0


def test_a_recording_that_starts_during_a_reset_leaves_that_reset_out(tmp_path):
    """A demo phase's recording starts while the supervisor still handles the previous
    phase's last episode (it ended on a detector, e.g. the robot tipped): the states before
    the robot is back to ``running`` are the reset's (a robot on its back, its self-right
    kicks, the lab fixture), not an episode's. The 'running → episode_end' transition that
    opens the reset is in the previous file. (Measured: the emulated quick demo's on-policy
    data held 6.7 s of a robot on its back as a transition sequence of episode 60.)"""
    with McapLog(tmp_path / "r.mcap") as log:
        rec = _Recorder(log)
        for i, x in [(0, 7.0), (1, 7.0), (2, 7.0)]:  # lying where it tipped, episode 0 ended already
            rec.state(i, 0, x)
        rec.transitions("episode_end", "paused", "resetting")
        for i, x in [(3, 9.0), (4, 30.0), (5, 0.0)]:  # kicks, the fixture, the drive back
            rec.state(i, 0, x)
        rec.transitions("resetting", "verifying", "resumed", "running")
        for i in range(6, 10):
            rec.state(i, 1, float(i - 6))
    eps = episodes_from_mcap(tmp_path / "r.mcap")
    assert [e.meta["episode"] for e in eps] == [1]
    np.testing.assert_allclose(eps[0].states[:, 0], [0, 1, 2, 3])

    # a recording that starts inside a running episode keeps the states before its first transition
    with McapLog(tmp_path / "s.mcap") as log:
        rec = _Recorder(log)
        for i in range(4):
            rec.state(i, 3, float(i))
        rec.transitions("running", "episode_end")
    eps = episodes_from_mcap(tmp_path / "s.mcap")
    np.testing.assert_allclose(eps[0].states[:, 0], [0, 1, 2, 3])
