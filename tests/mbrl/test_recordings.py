"""Episodes from MCAP recordings: transitions, normalization, resets, bad readings."""

from __future__ import annotations

import numpy as np
import pytest

from bus import keys
from bus.recording import McapLog
from bus.schemas import RobotState, SpecMsg
from learning.recordings import episodes_from_mcap

SPEC = {"state": {"names": ["x", "v"]}, "action": {"names": ["u"], "low": [-2.0], "high": [2.0]}}


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
