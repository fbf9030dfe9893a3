"""Batched open-loop rollouts (sim_backends/batch.py, mujoco.rollout): the same states as the
contract loop for the commands the contract applies; bad shapes refused."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.sim_backends.batch import rate_bounded_walk, rollout_held
from hilstack.sim_backends.pointmass import PointMassParams, PointMassSim


def _sim() -> PointMassSim:
    s = PointMassSim(PointMassParams())
    s.configure()
    s.activate()
    return s


def test_batched_rollouts_match_the_contract_loop_state_for_state():
    s = _sim()
    s.reset(x=0.3, y=-0.2)
    sp = s.spec
    cmds = rate_bounded_walk(sp.action.low, sp.action.high, sp.action_rate_per_s * sp.period_s, batch=3, steps=40,
                             rng=np.random.default_rng(0))
    batched = s.rollout_batch(cmds)
    assert batched.shape == (3, 41, 4)
    assert np.ptp(batched[:, -1, 0]) > 0.01  # the three rollouts went different ways
    for b in range(3):
        s.reset(x=0.3, y=-0.2)
        serial = [s.read().state]
        for t in range(40):
            applied = s.write(cmds[b, t])
            assert np.array_equal(applied, cmds[b, t])  # the limiter let the walk through unchanged
            s.tick()
            serial.append(s.read().state)
        np.testing.assert_array_equal(np.array(serial), batched[b])
    # two threads give the same states
    np.testing.assert_array_equal(s.rollout_batch(cmds, threads=2)[:, :, :2], s.rollout_batch(cmds)[:, :, :2])


def test_walk_stays_in_bounds_and_under_the_rate_step():
    lo, hi, step = np.array([-1.0, 0.0]), np.array([1.0, 0.5]), np.array([0.1, 0.2])
    w = rate_bounded_walk(lo, hi, step, batch=4, steps=300, rng=np.random.default_rng(1))
    assert np.all(w >= lo) and np.all(w <= hi)
    d = np.abs(np.diff(np.concatenate([np.zeros((4, 1, 2)), w], axis=1), axis=1))
    assert np.all(d <= step) and d[..., 0].max() > 0.09  # the walk uses its step, and no more
    assert rate_bounded_walk(lo, hi, None, 2, 5, np.random.default_rng(0)).shape == (2, 5, 2)


def test_bad_commands_are_refused():
    s = _sim()
    with pytest.raises(ValueError, match=r"\[B, T, 2\]"):
        s.rollout_batch(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="within"):
        s.rollout_batch(np.full((1, 2, 2), 99.0))
    with pytest.raises(ValueError, match="initial_state"):
        rollout_held(s.model, np.zeros(3), np.zeros((1, 2, 2)), 1)
