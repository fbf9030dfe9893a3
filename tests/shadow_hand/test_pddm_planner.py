"""PDDM as Baoding uses it (issue 30): the first mean (``init_mean``), the reference code's
action filter anchored at the action executed last, the low-noise share of the samples,
and the per-plan weighting diagnostics (effective sample size, the mean's shift)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.control.planners import PDDM, PddmConfig


def still(s, a):  # a dynamics that never moves: every candidate scores the same
    return s.clone()


def flat(states, actions):
    return torch.zeros(states.shape[0], states.shape[1])


def test_the_first_plan_is_centred_on_init_mean():
    """With equal rewards the weighted mean is the samples' mean: the first action is the
    first mean (init_mean) up to the noise's average; not the middle of the bounds."""
    init = np.linspace(-0.6, 0.6, 5)
    for filt in ("noise", "actions"):
        p = PDDM(-1.0, 1.0, horizon=4, samples=4000, gamma=20.0, beta=0.7, sigma=0.05, action_dim=5, seed=0,
                 init_mean=init, filter=filt)
        a = p(still, flat, np.zeros(3))
        np.testing.assert_allclose(a, init, atol=0.01)
        p.reset()  # reset goes back to init_mean, not to what was planned
        np.testing.assert_allclose(p.mean.numpy(), np.tile(init, (4, 1)), atol=1e-6)


def test_the_action_filter_smooths_actions_from_the_one_executed_last():
    """filter="actions" (google-research/pddm mppi.py): a_t = β(μ_t + u_t) + (1-β) a_{t-1},
    a_{-1} = the previously executed action. With σ = 0 the samples are that recursion of the
    mean exactly; the noise filter would return the mean itself."""
    beta, H = 0.6, 5
    p = PDDM(-5.0, 5.0, horizon=H, samples=3, gamma=20.0, beta=beta, sigma=0.0, action_dim=1, seed=0,
             init_mean=[0.0], filter="actions")
    mean = torch.ones(H, 1)
    got = p.sample(mean)[0, :, 0].numpy()
    want, prev = [], 0.0  # anchored at the init mean (nothing executed yet)
    for _ in range(H):
        prev = beta * 1.0 + (1 - beta) * prev
        want.append(prev)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # the anchor is the action returned by the last plan
    p.previous = torch.tensor([2.0])
    got = p.sample(mean)[0, 0, 0].item()
    assert got == pytest.approx(beta * 1.0 + (1 - beta) * 2.0)
    # and a plan sets it
    a = p(still, flat, np.zeros(2))
    assert p.previous.item() == pytest.approx(float(a[0]))


def test_the_action_filter_noise_statistics():
    """u ~ N(0, σ²): Var a_0 = β²σ² about β μ_0 + (1-β) a_prev, and the next step correlates
    with it through (1-β)."""
    beta, sigma = 0.6, 0.5
    p = PDDM(-100.0, 100.0, horizon=3, samples=40000, beta=beta, sigma=sigma, action_dim=1, seed=3,
             filter="actions")
    a = p.sample(torch.zeros(3, 1))[:, :, 0].numpy()
    assert a[:, 0].std() == pytest.approx(beta * sigma, rel=0.03)
    var1 = (beta * sigma) ** 2 * (1 + (1 - beta) ** 2)
    assert a[:, 1].std() == pytest.approx(np.sqrt(var1), rel=0.03)
    cov = np.mean(a[:, 0] * a[:, 1])
    assert cov == pytest.approx((1 - beta) * (beta * sigma) ** 2, rel=0.1)


def test_low_noise_share_of_the_samples():
    p = PDDM(-100.0, 100.0, horizon=2, samples=10000, beta=1.0, sigma=0.9, action_dim=1, seed=4,
             low_noise_fraction=0.1, low_noise_scale=0.3, filter="actions")
    a = p.sample(torch.zeros(2, 1))[:, :, 0].numpy()
    assert a[:9000].std() == pytest.approx(0.9, rel=0.05)
    assert a[9000:].std() == pytest.approx(0.27, rel=0.08)


def test_plan_diagnostics_effective_sample_size_and_shift():
    p = PDDM(-1.0, 1.0, horizon=3, samples=200, gamma=20.0, beta=0.7, sigma=0.3, action_dim=2, seed=5)
    p(still, flat, np.zeros(2))  # equal rewards: every weight 1
    assert p.last_ess == pytest.approx(200.0, rel=1e-5) and p.last_shift < 0.05

    def prefers_high(states, actions):  # cost -100·a: γ·ΔR in the hundreds, one sample wins
        return -100.0 * actions.sum((-1, -2)).expand(states.shape[0], -1)

    p.reset()
    p(still, prefers_high, np.zeros(2))
    assert p.last_ess < 1.5 and p.last_shift > 0.1
    assert len(p.history) == 1


def test_pddm_config_carries_the_filter_and_the_low_noise_share():
    c = PddmConfig(horizon=7, samples=10, gamma=20.0, beta=0.6, ensemble=1, hidden=(4,), state_dim=3,
                   action_dim=2, sigma=0.9, filter="actions", low_noise_fraction=0.1)
    cfg = c.planner().config()
    assert (cfg["filter"], cfg["low_noise_fraction"], cfg["sigma"]) == ("actions", 0.1, pytest.approx([0.9, 0.9]))
    with pytest.raises(ValueError, match="filter"):
        PDDM(-1.0, 1.0, action_dim=1, filter="wrong")


def test_a_reachable_set_bounds_every_sampled_step_from_the_action_executed_last():
    """``reachable`` (the actuator's rate limit): each candidate's first step lies within the
    set of the action executed last, each later step within the set of the step before, and
    the plan (a weighted mean of reachable sequences) is reachable too; without it the same
    sampler jumps further."""
    r = 0.1

    def reach(prev):
        return (prev - r).clamp(min=-1.0), (prev + r).clamp(max=1.0)

    def prefers_high(states, actions):  # a cost that pulls the first action up
        return -actions[:, 0, 0].expand(states.shape[0], -1)

    for filt in ("noise", "actions"):
        p = PDDM(-1.0, 1.0, horizon=5, samples=300, gamma=20.0, beta=0.6, sigma=0.9, action_dim=3, seed=0,
                 init_mean=[0.2, 0.0, -0.2], filter=filt, reachable=reach)
        free = PDDM(-1.0, 1.0, horizon=5, samples=300, gamma=20.0, beta=0.6, sigma=0.9, action_dim=3, seed=0,
                    init_mean=[0.2, 0.0, -0.2], filter=filt)
        prev = p.previous.clone()
        a = p.sample(p.mean.clone())
        steps = torch.cat([(a[:, :1] - prev).abs(), (a[:, 1:] - a[:, :-1]).abs()], 1)
        assert float(steps.max()) <= r + 1e-6
        b = free.sample(free.mean.clone())
        assert float(torch.cat([(b[:, :1] - prev).abs(), (b[:, 1:] - b[:, :-1]).abs()], 1).max()) > 3 * r
        for _ in range(3):
            prev = p.previous.clone()
            act = p(still, prefers_high, np.zeros(2))
            assert np.all(np.abs(act - prev.numpy()) <= r + 1e-6)
            np.testing.assert_allclose(p.previous.numpy(), act, atol=1e-6)
        assert act[0] > 0.2 + 2 * r  # it moved up, a step of r at most per plan
