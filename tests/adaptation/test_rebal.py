"""ReBAL: the GRU's hidden state adapts the model to a held-out condition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.learning.adaptation import load_adapter
from hilstack.learning.adaptation.grbal import segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.rebal import ContextEncoder, RebalAdapter, evaluate, meta_train
from hilstack.learning.adaptation.training import fit_plain
from tests.adaptation import toy
from tests.adaptation.conftest import K, M, train_episodes


@pytest.fixture(scope="module")
def rebal():
    torch.manual_seed(0)
    eps = train_episodes()
    model = AdaptiveMLP(toy.NAMES, 2, hidden=(64, 64), seed=0, context_dim=8)
    enc = ContextEncoder(model, 8)
    # normalization from the data; the zero context is what an MB model without context sees
    fit_plain(model, eps, epochs=0)
    meta_train(model, enc, segments(eps, M, K, stride=4), steps=200, batch=32, lr=3e-3)
    return model, enc


def test_context_lowers_the_error_on_a_heldout_condition(rebal):
    model, enc = rebal
    test = segments(toy.episodes(10, 40, seed=99, gain=0.4, turn_bias=1.2), M, K, stride=4)
    e = evaluate(model, enc, test)
    assert e["after"] < 0.7 * e["before"]


def test_update_is_the_gru_state_of_the_window_and_round_trips(rebal, tmp_path):
    model, enc = rebal
    RebalAdapter(model, enc, window=M).save(tmp_path / "r.pt")
    ad = load_adapter(tmp_path / "r.pt")
    assert isinstance(ad, RebalAdapter)
    ep = toy.episodes(1, 12, seed=4, gain=0.4)[0]
    for t in range(12):
        ad.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    u = ad.update()
    assert list(u.tensors) == ["h"] and u.tensors["h"].shape == (8,) and u.nbytes() == 32
    s = torch.as_tensor(ep.states[4:12])
    a = torch.as_tensor(ep.actions[4:12])
    with torch.no_grad():
        h = enc(model, s[None], a[None], torch.as_tensor(ep.states[5:13])[None])[0]
    np.testing.assert_allclose(u.tensors["h"], h.numpy(), atol=1e-6)  # the last M only
    pred = ad.dynamics(u)(s, a)
    assert pred.shape == (8, 6)
    # the adapted context predicts this robot's next states better than a zero context
    err = lambda p: float(((p - torch.as_tensor(ep.states[5:13])) ** 2).sum())  # noqa: E731
    assert err(pred) < err(ad.dynamics(None)(s, a))
    with pytest.raises(ValueError, match="shape"):
        ad.dynamics(type(u)("rebal", 1, tensors={"h": np.zeros(3, np.float32)}))
