"""InvertedPendulum source/target pair: the heavier pole is in the model, stepping from a state is exact."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.learning.transfer.pendulum import StepFrom, make_env


def test_target_has_the_heavier_pole_and_behaves_differently(tmp_path):
    src, tgt = make_env(None, tmp_path), make_env(15.0, tmp_path)
    pole = src.unwrapped.model.body("pole").id
    assert src.unwrapped.model.body_mass[pole] == pytest.approx(5.0186, rel=1e-3)
    assert tgt.unwrapped.model.body_mass[pole] == pytest.approx(15.0)
    s = np.array([0.0, 0.1, 0.0, 0.0])
    a = np.array([1.0])
    d_src, d_tgt = StepFrom(src)(s, a) - s, StepFrom(tgt)(s, a) - s
    assert abs(d_src[3] - d_tgt[3]) > 0.05  # the pole's rate responds differently


def test_step_from_matches_the_env_own_step(tmp_path):
    env = make_env(None, tmp_path)
    obs, _ = env.reset(seed=3)
    nxt, *_ = env.step(np.array([0.7], np.float32))
    np.testing.assert_allclose(StepFrom(make_env(None, tmp_path))(obs.astype(float), np.array([0.7])), nxt,
                               rtol=1e-6, atol=1e-9)


def test_bad_pole_mass_is_refused(tmp_path):
    with pytest.raises(ValueError, match="pole mass"):
        make_env(float("nan"), tmp_path)


def test_floor_is_below_none_and_gat_on_the_pendulum(tmp_path):
    from hilstack.learning.transfer.grounding import Gat, floor_error, transition_error
    from hilstack.learning.transfer.pendulum import collect

    src, tgt = StepFrom(make_env(None, tmp_path)), StepFrom(make_env(15.0, tmp_path))

    def agent(s, rng):  # a stabilising PD law with exploration noise (no PPO: seconds, not minutes)
        return np.clip(np.array([2.0 * s[1] + 0.5 * s[3] + 0.2 * s[0]]) + rng.normal(0, 0.5, 1), -3, 3)

    target, source, val = collect(tgt, agent, 300, 200, 1), collect(src, agent, 300, 200, 3), collect(tgt, agent, 30, 200, 2)
    low, high = np.array([-3.0]), np.array([3.0])
    gat = Gat(source, target, low, high, steps=100)
    floor, none = floor_error(src, val, low, high), transition_error(src, val)
    assert 0 < floor < none and floor <= transition_error(src, val, gat)
    # break-it: the coarse grid alone must not beat the refined search
    assert floor_error(src, val, low, high, grid=4, iters=0) > floor


def test_the_agent_collects_the_rollout_length_it_is_given(tmp_path):
    """PPO collects whole rollouts: with SB3's default 2048 steps a 64-step budget would still
    collect (and train on) 2048, so a preset's ``agent_n_steps`` is what bounds its cost."""
    from hilstack.learning.transfer.pendulum import train_agent

    model = train_agent(make_env(None, tmp_path), 64, seed=0, n_steps=64)
    assert model.n_steps == 64 and model.num_timesteps == 64


def test_every_preset_agent_rollout_fits_its_timesteps():
    """A rollout longer than the budget would be collected whole (the tiny preset paid 2048 steps for 256)."""
    from hilstack.tools.demo_transfer import TransferDemoConfig

    for name, preset in TransferDemoConfig.PRESETS.items():
        p = preset["pendulum"]
        assert p.agent_n_steps <= p.agent_timesteps, name
