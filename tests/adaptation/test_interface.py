"""The adapter interface: checkpoints, updates, dynamics, MB and MB+DE math, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.learning.adaptation import load_adapter
from hilstack.learning.adaptation.base import ModelUpdate
from hilstack.learning.adaptation.baselines import MbAdapter, MbDeAdapter
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.training import fit_plain
from tests.adaptation import toy


@pytest.fixture(scope="module")
def trained() -> AdaptiveMLP:
    m = AdaptiveMLP(toy.NAMES, 2, hidden=(32, 32), seed=0)
    hist = fit_plain(m, toy.episodes(20, 30, seed=0), epochs=15, batch_size=64)
    assert hist[-1] < 0.5 * hist[0]  # it learned
    return m


def test_checkpoint_round_trip_builds_the_named_method(trained, tmp_path):
    MbDeAdapter(trained, window=8, lr=0.02).save(tmp_path / "de.pt")
    a = load_adapter(tmp_path / "de.pt")
    assert isinstance(a, MbDeAdapter) and a.window == 8 and a.lr == 0.02
    assert isinstance(load_adapter(tmp_path / "de.pt", method="mb"), MbAdapter)
    s = torch.as_tensor(np.stack([e.states[0] for e in toy.episodes(5, 1, seed=3)]))
    act = torch.zeros(5, 2)
    u = a.update()
    np.testing.assert_allclose(a.dynamics(u)(s, act).numpy(), trained.step(trained.params(), s, act).detach().numpy(),
                               atol=1e-6)


def test_mb_publishes_nothing_and_counts(trained):
    a = MbAdapter(trained, window=4)
    ep = toy.episodes(1, 3, seed=1)[0]
    for t in range(3):
        a.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    u1, u2 = a.update(state_stamp_ns=123), a.update()
    assert (u1.method, u1.seq, u1.state_stamp_ns, u1.tensors, u1.info["window"]) == ("mb", 1, 123, {}, 3)
    assert u2.seq == 2


def test_mb_de_is_one_sgd_step_per_update_continuing(trained):
    lr = 0.05
    a = MbDeAdapter(trained, window=16, lr=lr)
    ep = toy.episodes(1, 20, seed=2, gain=0.4)[0]  # a perturbed robot
    for t in range(20):
        a.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    s, act, n = (torch.as_tensor(x) for x in ep.transitions().arrays())
    s, act, n = s[-16:], act[-16:], n[-16:]  # the window keeps the last M
    theta = {k: v.clone().requires_grad_(True) for k, v in trained.params().items()}
    g = torch.autograd.grad(trained.loss(theta, s, act, n), list(theta.values()))
    expect1 = {k: (v - lr * gi).detach() for (k, v), gi in zip(theta.items(), g, strict=True)}
    u1 = a.update()
    for k in expect1:
        np.testing.assert_allclose(u1.tensors[k], expect1[k].numpy(), atol=1e-6)
    # the second step starts from the first step's parameters, not θ*
    p1 = {k: v.clone().requires_grad_(True) for k, v in expect1.items()}
    g2 = torch.autograd.grad(trained.loss(p1, s, act, n), list(p1.values()))
    u2 = a.update()
    k0 = next(iter(expect1))
    np.testing.assert_allclose(u2.tensors[k0], (expect1[k0] - lr * g2[0]).numpy(), atol=1e-6)
    # and the loss on the window falls
    assert trained.loss(a.params_of(u2), s, act, n) < trained.loss(trained.params(), s, act, n)
    a.reset()
    assert all(torch.equal(a.current[k], trained.params()[k]) for k in a.current)


def test_bad_input_is_one_line_and_refused(trained, tmp_path):
    a = MbDeAdapter(trained, window=4)
    s = np.zeros(6, np.float32)
    s[4] = 1.0
    with pytest.raises(ValueError, match="non-finite action"):
        a.observe(s, np.array([np.nan, 0.0]), s)
    with pytest.raises(ValueError, match="expected state \\[6\\]"):
        a.observe(s[:5], np.zeros(2), s)
    assert a.update().info["window"] == 0  # nothing bad entered the window
    with pytest.raises(ValueError, match="method 'grbal'"):
        a.dynamics(ModelUpdate("grbal", 1))
    with pytest.raises(KeyError, match="unknown parameter"):
        a.dynamics(ModelUpdate("mb_de", 1, tensors={"nope": np.zeros(1)}))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_adapter(tmp_path / "missing.pt")
    torch.save({"format": "other"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an adaptation checkpoint"):
        load_adapter(tmp_path / "other.pt")
    a.save(tmp_path / "a.pt")
    with pytest.raises(ValueError, match="unknown adaptation method"):
        load_adapter(tmp_path / "a.pt", method="magic")


def test_open_loop_rollout_stays_close_to_the_truth(trained):
    # regression: constant input channels (body-frame x, y, cos yaw of the state itself) were
    # normalized by a 1e-6 std, so a predicted state slightly off the unit circle blew up
    # the next prediction and planner rollouts diverged
    ep = toy.episodes(1, 8, seed=11)[0]
    s = torch.as_tensor(ep.states[:1])
    with torch.no_grad():
        for t in range(8):
            s = trained.step(trained.params(), s, torch.as_tensor(ep.actions[t:t + 1]))
    assert float(np.abs(s[0, :2].numpy() - ep.states[8, :2]).max()) < 0.2
