"""Held-out split and early stopping of MB, GrBAL's meta-training and ReBAL; the saved training data (tiny sizes)."""

from __future__ import annotations

import pytest
import torch

from hilstack.learning.adaptation import grbal, rebal
from hilstack.learning.adaptation.grbal import segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.rebal import ContextEncoder
from hilstack.learning.adaptation.training import fit_plain
from hilstack.learning.datasets import Transitions, split_episodes
from tests.adaptation import toy


def test_split_holds_out_whole_rollouts():
    eps = toy.episodes(20, 5, seed=0)
    tr, va = split_episodes(eps, 0.25, 1)
    assert len(va) == 5 and len(tr) == 15
    assert {e.name for e in tr}.isdisjoint({e.name for e in va})
    assert split_episodes(eps, 0.25, 1)[1][0].name == va[0].name  # deterministic per seed
    assert len(split_episodes(eps[:2], 0.01, 0)[1]) == 1  # at least one held out
    assert split_episodes(eps, 0.0, 0)[1] == []
    with pytest.raises(ValueError, match="val_fraction"):
        split_episodes(eps, 1.0, 0)


def test_fit_plain_stops_early_and_keeps_the_best_held_out_epoch():
    # held-out rollouts of another robot (a fifth of the speed): fitting the training data
    # better eventually makes the held-out loss worse, so training must stop and roll back
    train = toy.episodes(20, 20, seed=0)
    val = toy.episodes(6, 20, seed=1, gain=0.2, turn_bias=1.0)
    m = AdaptiveMLP(toy.NAMES, 2, hidden=(32, 32), seed=0)
    h: dict = {}
    hist = fit_plain(m, train, epochs=60, batch_size=64, lr=3e-3, val=val, patience=3, history=h)
    assert len(hist) == h["epochs_run"] == len(h["val"])
    assert h["epochs_run"] < 60 and h["epochs_run"] - h["best_epoch"] == 3
    with torch.no_grad():
        now = float(m.loss(m.params(), *(torch.as_tensor(x) for x in Transitions.from_episodes(val).arrays())))
    assert now == pytest.approx(min(h["val"]), rel=1e-5)
    assert now < h["val"][-1]  # the weights are the best epoch's, not the last


def test_meta_training_stops_early_and_returns_the_best_theta_and_psi():
    M = K = 4
    train = segments(toy.episodes(30, 12, seed=0, turn_bias=0.5), M, K, stride=2)
    val = segments(toy.episodes(6, 12, seed=1, gain=0.3, turn_bias=-1.5), M, K, stride=2)
    m = AdaptiveMLP(toy.NAMES, 2, hidden=(32, 32), seed=0)
    fit_plain(m, toy.episodes(30, 12, seed=0, turn_bias=0.5), epochs=0)
    psi, hist = grbal.meta_train(m, train, steps=400, meta_batch=8, lr=3e-3, val=val, eval_every=10, patience=3)
    best = hist[-1]
    assert "best_step" in best and hist[-2]["step"] < 400  # stopped
    ev = grbal.evaluate(m, m.params(), psi, val)
    assert ev["after"] == pytest.approx(best["after"], rel=1e-5)
    assert best["after"] == min(h["after"] for h in hist[:-1])


def test_rebal_stops_early_and_keeps_the_best_weights():
    M = K = 4
    train = segments(toy.episodes(30, 12, seed=0, turn_bias=0.5), M, K, stride=2)
    val = segments(toy.episodes(6, 12, seed=1, gain=0.3, turn_bias=-1.5), M, K, stride=2)
    m = AdaptiveMLP(toy.NAMES, 2, hidden=(32, 32), seed=0, context_dim=4)
    fit_plain(m, toy.episodes(30, 12, seed=0), epochs=0)
    enc = ContextEncoder(m, 4)
    hist = rebal.meta_train(m, enc, train, steps=400, batch=16, lr=3e-3, val=val, eval_every=10, patience=3)
    assert "best_step" in hist[-1] and hist[-2]["step"] < 400
    assert rebal.evaluate(m, enc, val)["after"] == pytest.approx(min(h["val_loss"] for h in hist[:-1]), rel=1e-5)


def test_training_rollouts_are_saved_and_load_back(tmp_path):
    from hilstack.learning.adaptation.experiment import load_episodes, save_episodes

    eps = toy.episodes(3, 7, seed=2)
    for i, e in enumerate(eps):
        e.meta["condition"] = {"payload_kg": 0.01 * i}
    save_episodes(tmp_path / "d" / "x.npz", eps)
    back = load_episodes(tmp_path / "d" / "x.npz")
    assert [e.name for e in back] == [e.name for e in eps]
    for a, b in zip(eps, back, strict=True):
        assert (a.states == b.states).all() and (a.actions == b.actions).all()
        assert b.meta["condition"] == a.meta["condition"]


def test_unperturbed_conditions_are_the_first_and_a_spread_fraction():
    from hilstack.learning.adaptation.experiment import AdaptationConfig, unperturbed_conditions

    assert unperturbed_conditions(AdaptationConfig(conditions_per_terrain=12, unperturbed_fraction=0.0)) == {0}
    assert unperturbed_conditions(AdaptationConfig(conditions_per_terrain=12, unperturbed_fraction=0.5)) == \
        {0, 2, 4, 6, 8, 10}
    assert unperturbed_conditions(AdaptationConfig(conditions_per_terrain=3, unperturbed_fraction=1.0)) == {0, 1, 2}
    with pytest.raises(ValueError, match="unperturbed_fraction"):
        unperturbed_conditions(AdaptationConfig(unperturbed_fraction=1.5))
