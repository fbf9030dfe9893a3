"""GAT and GARAT on a known linear system: the target's actuator is twice as strong."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from hilstack.learning.datasets import Transitions
from hilstack.learning.transfer.grounding import (
    Discriminator,
    GaratConfig,
    Gat,
    discriminator_update,
    fit_mlp,
    train_garat,
    transition_error,
)

A = np.array([[1.0, 0.1], [0.0, 0.95]])
B = np.array([0.0, 0.1])
LOW, HIGH = np.array([-3.0]), np.array([3.0])


def source(s, a):
    return A @ s + B * a[0]


def target(s, a):
    return A @ s + 2.0 * B * a[0]


def reset_state(rng):
    return rng.normal(0, 0.5, 2)


def agent(s, rng):
    return np.clip(np.array([-1.0 * s[0] - 1.0 * s[1]]) + rng.normal(0, 0.5, 1), LOW, HIGH)


def done(s):
    return bool(np.abs(s).max() > 5)


def rollouts(step, n, seed):
    rng = np.random.default_rng(seed)
    S, Acts, S1 = [], [], []
    s = reset_state(rng)
    for t in range(n):
        a = agent(s, rng)
        s1 = step(s, a)
        S.append(s), Acts.append(a), S1.append(s1)
        s = reset_state(rng) if done(s1) or t % 50 == 49 else s1
    return Transitions(np.array(S), np.array(Acts), np.array(S1))


def test_gat_transformed_action_reproduces_the_target_transition():
    tgt, src, val = rollouts(target, 800, 0), rollouts(source, 800, 1), rollouts(target, 200, 2)
    gat = Gat(src, tgt, LOW, HIGH, steps=800)
    # the exact answer is ã = 2a (inside the limits here)
    inside = np.abs(val.actions[:, 0]) < 1.0
    np.testing.assert_allclose(gat(val.states[inside], val.actions[inside])[:, 0], 2 * val.actions[inside, 0], atol=0.15)
    none, grounded = transition_error(source, val), transition_error(source, val, gat)
    assert grounded < 0.15 * none


def test_discriminator_separates_source_from_target_transitions():
    torch.manual_seed(0)
    tgt, src = rollouts(target, 1000, 0), rollouts(source, 1000, 1)
    d = Discriminator(tgt, 32)
    opt = torch.optim.Adam(d.parameters(), lr=3e-3)
    discriminator_update(d, opt, src, tgt, steps=300, rng=np.random.default_rng(0))
    with torch.no_grad():
        p_src = torch.sigmoid(d(torch.as_tensor(d.inputs(src)))).numpy()
        p_tgt = torch.sigmoid(d(torch.as_tensor(d.inputs(tgt)))).numpy()
    assert ((p_src > 0.5).mean() + (p_tgt < 0.5).mean()) / 2 > 0.85
    # the GARAT reward −log D is higher on target-like transitions
    assert d.reward(tgt).mean() > d.reward(src).mean() + 0.5


@pytest.mark.slow
def test_garat_grounds_the_source_towards_the_target():
    tgt, val = rollouts(target, 2000, 0), rollouts(target, 200, 2)
    cfg = GaratConfig(total_timesteps=6144, n_steps=512, batch_size=128, n_epochs=5, log_std_init=-1.0,
                      disc_steps=50, width=32, seed=0)
    g = train_garat(source, tgt, reset_state, agent, done, LOW, HIGH, max_steps=50, cfg=cfg)
    assert g.disc_updates == 12  # once per PPO update
    none, grounded = transition_error(source, val), transition_error(source, val, g)
    assert grounded < 0.5 * none


def test_bad_transitions_are_refused():
    """A NaN in the recorded target data (a dropped sensor sample) is refused in one line
    naming where, before any model is fitted on it."""
    good = Transitions(np.zeros((8, 1)), np.zeros((8, 1)), np.zeros((8, 1)))
    bad = Transitions(np.zeros((8, 1)), np.zeros((8, 1)), np.where(np.arange(8)[:, None] == 5, np.nan, 0.0))
    with pytest.raises(ValueError, match=r"NaN or inf in next_states \(row 5 and 0 more\)"):
        Gat(good, bad, LOW, HIGH, steps=1)
    with pytest.raises(ValueError, match="NaN or inf in next_states"):
        train_garat(lambda s, a: s, bad, None, None, None, LOW, HIGH, max_steps=1, cfg=GaratConfig())


def test_gat_smoothing_alpha_blends_with_the_identity():
    tgt, src, val = rollouts(target, 400, 0), rollouts(source, 400, 1), rollouts(target, 50, 2)
    full = Gat(src, tgt, LOW, HIGH, steps=100)
    half, zero = copy.copy(full), copy.copy(full)
    half.alpha, zero.alpha = 0.5, 0.0
    s, a = val.states[:10], np.clip(val.actions[:10], -1, 1)
    assert np.abs(full(s, a) - a).max() > 0.1  # the fitted transform is not the identity
    np.testing.assert_allclose(half(s, a), np.clip(0.5 * full(s, a) + 0.5 * a, LOW, HIGH), atol=1e-6)
    np.testing.assert_allclose(zero(s, a), a, atol=1e-12)
    with pytest.raises(ValueError, match="alpha"):
        Gat(src, tgt, LOW, HIGH, steps=10, alpha=1.5)


def test_fit_mlp_early_stopping_keeps_the_best_held_out_weights():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(60, 3))
    y = x[:, :1] + rng.normal(0, 1.0, (60, 1))  # few noisy samples: a wide net overfits with many steps
    xv = rng.normal(size=(500, 3))
    err = {}
    for vf in (0.0, 0.3):
        m = fit_mlp(x, y, width=64, layers=2, steps=300, lr=1e-2, val_frac=vf)
        err[vf] = float(np.mean((m(xv) - xv[:, :1]) ** 2))
    assert err[0.3] < 0.7 * err[0.0]
    with pytest.raises(ValueError, match="val_frac"):
        fit_mlp(x, y, steps=1, val_frac=1.0)


def test_floor_is_zero_where_an_exact_mapping_exists_and_below_none_and_gat():
    from hilstack.learning.transfer.grounding import floor_error

    tgt, src, val = rollouts(target, 300, 0), rollouts(source, 300, 1), rollouts(target, 40, 2)
    inside = Transitions(*(v[np.abs(val.actions[:, 0]) < 1.4] for v in (val.states, val.actions, val.next_states)))
    assert len(inside) > 20
    # the exact mapping ã = 2a reproduces every target transition whose 2a is inside the limits
    exact = transition_error(source, inside, lambda s, a: np.clip(2 * a, LOW, HIGH))
    floor = floor_error(source, inside, LOW, HIGH)
    assert exact < 1e-9 and floor < 1e-6
    # on all transitions (some need |ã| > 3) the floor is > 0 but below no grounding and GAT
    gat = Gat(src, tgt, LOW, HIGH, steps=100)
    f_all = floor_error(source, val, LOW, HIGH)
    assert f_all <= transition_error(source, val) and f_all <= transition_error(source, val, gat)
    # break-it: a coarse grid without the bounded-Brent refinement must not beat the fine search
    assert floor_error(source, val, LOW, HIGH, grid=4, iters=0) > f_all + 1e-4


def test_best_action_finds_the_minimiser_of_a_known_curve():
    from hilstack.learning.transfer.grounding import best_action

    # the error |step(s, ã) − s'| of the source is |0.1·(ã − 1.234)|: minimiser 1.234 between grid points
    s = np.zeros(2)
    x, e = best_action(source, s, source(s, np.array([1.234])), -3.0, 3.0, grid=7)
    assert abs(x - 1.234) < 1e-5 and e < 1e-6
    with pytest.raises(ValueError, match="grid"):
        best_action(source, s, s, -3.0, 3.0, grid=1)


def test_discriminator_label_smoothing_bounds_its_confidence_and_bad_values_are_refused():
    tgt, src = rollouts(target, 400, 0), rollouts(source, 400, 1)
    probs = {}
    for ls in (0.0, 0.2):
        torch.manual_seed(0)
        d = Discriminator(tgt, 32)
        opt = torch.optim.Adam(d.parameters(), lr=3e-3)
        discriminator_update(d, opt, src, tgt, steps=150, rng=np.random.default_rng(0), label_smoothing=ls,
                             grad_penalty=0.1)
        with torch.no_grad():
            probs[ls] = torch.sigmoid(d(torch.as_tensor(d.inputs(src)))).numpy().max()
    assert probs[0.2] < 0.9 < probs[0.0]  # smoothed labels 0.8: D no longer pushes towards 1
    d = Discriminator(tgt, 8)
    opt = torch.optim.Adam(d.parameters())
    with pytest.raises(ValueError, match="label_smoothing"):
        discriminator_update(d, opt, src, tgt, 1, np.random.default_rng(0), label_smoothing=0.5)
    with pytest.raises(ValueError, match="grad_penalty"):
        discriminator_update(d, opt, src, tgt, 1, np.random.default_rng(0), grad_penalty=-1.0)


def test_garat_checkpoint_selection_keeps_the_best_held_out_policy():
    tgt = rollouts(target, 500, 0)
    cfg = GaratConfig(total_timesteps=512, n_steps=128, batch_size=64, n_epochs=2, disc_steps=5, width=16,
                      select_frac=0.2, select_every=2, log_std_init=-0.5)
    g = train_garat(source, tgt, reset_state, agent, done, LOW, HIGH, max_steps=50, cfg=cfg)
    assert g.disc_updates == 4
    assert [n for n, _ in g.select_errors] == [0, 2, 4]
    best_n, best_e = min(g.select_errors, key=lambda r: r[1])
    assert g.selected_update == best_n
    # the returned π_g is that checkpoint: its error on the held-out 20 % (same draw) is the best one
    idx = np.random.default_rng(cfg.seed + 7919).permutation(len(tgt))[:100]
    held = Transitions(tgt.states[idx], tgt.actions[idx], tgt.next_states[idx])
    assert transition_error(source, held, g) == pytest.approx(best_e, abs=1e-9)
    with pytest.raises(ValueError, match="select_frac"):
        train_garat(source, tgt, reset_state, agent, done, LOW, HIGH, 50, GaratConfig(select_frac=1.0))
