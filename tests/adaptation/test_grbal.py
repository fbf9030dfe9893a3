"""GrBAL meta-training and run-time adaptation on the toy planar robot (exact, fast)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.learning.adaptation import load_adapter
from hilstack.learning.adaptation.grbal import GrbalAdapter, adapt, evaluate, gradient_norms, segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from tests.adaptation import toy
from tests.adaptation.conftest import K, M


def test_adapted_k_step_error_is_below_unadapted_on_a_heldout_perturbation(meta):
    model, plain, psi, _ = meta
    # outside the training range: gain 0.3 (< 0.5) and turn bias 1.5 (> 1)
    test = segments(toy.episodes(10, 40, seed=99, gain=0.3, turn_bias=1.5), M, K, stride=4)
    e = evaluate(model, model.params(), psi, test)
    assert e["after"] < 0.6 * e["before"]
    # and better than the plain model without adaptation (the MB baseline) on the same windows
    psi0 = {k: torch.zeros_like(v) for k, v in psi.items()}
    assert e["after"] < evaluate(plain, plain.params(), psi0, test)["before"]


def test_meta_training_learns_the_step_size(meta):
    _, _, psi, hist = meta
    assert any(not torch.allclose(v, torch.full_like(v, 0.01)) for v in psi.values())
    assert hist[-1]["after"] < hist[-1]["before"]  # one step helps on the training conditions too


def test_inner_step_is_theta_star_minus_psi_times_gradient(meta):
    model, _, psi, _ = meta
    # a step size of its own (per entry, random): the update must use exactly this one
    gen = torch.Generator().manual_seed(3)
    psi = {k: 0.02 * torch.rand(v.shape, generator=gen) for k, v in psi.items()}
    ad = GrbalAdapter(model, psi, window=M)
    ep = toy.episodes(1, 12, seed=5, gain=0.4)[0]
    for t in range(12):
        ad.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    s, a, n = (torch.as_tensor(x)[-M:] for x in ep.transitions().arrays())
    theta = {k: v.clone().requires_grad_(True) for k, v in model.params().items()}
    g = dict(zip(theta, torch.autograd.grad(model.loss(theta, s, a, n), list(theta.values())), strict=True))
    u = ad.update()
    for k in theta:
        np.testing.assert_allclose(u.tensors[k], (theta[k] - psi[k] * g[k]).detach().numpy(), atol=1e-6)
    u2 = ad.update()  # from θ* again, not from the previous θ'
    for k in theta:
        np.testing.assert_allclose(u2.tensors[k], u.tensors[k], atol=1e-7)
    # the update's model predicts the window better than θ*
    assert model.loss(ad.params_of(u), s, a, n) < model.loss(model.params(), s, a, n)


def test_checkpoint_and_subset_of_parameters(meta, tmp_path):
    model, _, psi, _ = meta
    last = ["4.weight", "4.bias"]
    GrbalAdapter(model, psi, window=M, adapt_params=last).save(tmp_path / "g.pt")
    ad = load_adapter(tmp_path / "g.pt")
    assert isinstance(ad, GrbalAdapter) and ad.adapt_params == last
    for ep in toy.episodes(1, M, seed=6, gain=0.4):
        for t in range(M):
            ad.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    u = ad.update(state_stamp_ns=7)
    assert sorted(u.tensors) == sorted(last) and u.state_stamp_ns == 7
    assert u.nbytes() == sum(model.params()[k].numel() * 4 for k in last)
    s = torch.as_tensor(ep.states[:3])
    out = ad.dynamics(u)(s, torch.zeros(3, 2))
    assert out.shape == (3, 6) and torch.isfinite(out).all()
    # an MB+DE adapter from the same checkpoint (same θ*) for a baseline
    assert load_adapter(tmp_path / "g.pt", method="mb_de").name == "mb_de"
    with pytest.raises(ValueError, match="psi lacks"):
        GrbalAdapter(model, {}, window=M)


def _matmuls(fn) -> int:
    """aten matrix products run by ``fn()`` (forward and backward)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func.overloadpacket in (torch.ops.aten.mm, torch.ops.aten.addmm, torch.ops.aten.bmm):
                Count.n += 1
            return func(*args, **(kwargs or {}))

    with Count():
        fn()
    return Count.n


def test_adapting_a_subset_differentiates_only_that_subset(meta):
    model, _, psi, _ = meta
    last = list(model.params())[-2:]
    full, sub = GrbalAdapter(model, psi, window=M), GrbalAdapter(model, psi, window=M, adapt_params=last)
    ep = toy.episodes(1, M, seed=8, gain=0.4)[0]
    for ad in (full, sub):
        for t in range(M):
            ad.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    n_full, n_sub = _matmuls(full.update), _matmuls(sub.update)
    # 3 layers: forward 3 products; the full backward adds the weight gradients of all 3 and
    # the input gradients of the 2 upper layers; the last layer's: its weight gradient only
    assert n_sub == 3 + 1 < n_full
    # same values as a full-gradient step with ψ = 0 outside the subset
    u = sub.update()
    psi0 = {k: (v if k in last else torch.zeros_like(v)) for k, v in psi.items()}
    ref = GrbalAdapter(model, psi0, window=M)
    for t in range(M):
        ref.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    r = ref.update()
    for k in last:
        np.testing.assert_allclose(u.tensors[k], r.tensors[k], atol=1e-6)


def test_meta_training_a_subset_learns_only_its_step_sizes(meta):
    from hilstack.learning.adaptation.grbal import meta_train
    from tests.adaptation.conftest import train_episodes

    _, plain, _, _ = meta
    model = AdaptiveMLP.from_checkpoint(plain.to_checkpoint())
    last = list(model.params())[-2:]
    first_before = model.params()[list(model.params())[0]].clone()
    psi, hist = meta_train(model, segments(train_episodes(), M, K, stride=4), steps=30, meta_batch=8,
                           psi_init=0.05, psi_lr=1e-2, adapt_params=last)
    assert set(psi) == set(model.params())
    for k, v in psi.items():
        if k in last:
            assert not torch.allclose(v, torch.full_like(v, 0.05))  # learned
        else:
            assert torch.count_nonzero(v) == 0  # not adapted: no step
    # the outer loss still trains every parameter of θ
    assert not torch.allclose(model.params()[list(model.params())[0]], first_before)
    with pytest.raises(ValueError, match="unknown parameters"):
        meta_train(model, segments(train_episodes(), M, K, stride=4), steps=1, adapt_params=["nope"])


def test_clipped_step_caps_the_gradient_norm_and_is_kept_in_the_checkpoint(meta, tmp_path):
    model, _, psi, _ = meta
    last = ["4.weight", "4.bias"]
    one = {k: torch.ones_like(v) for k, v in psi.items()}  # ψ = 1: the step is the (capped) gradient itself
    ep = toy.episodes(1, M, seed=7, gain=0.3, turn_bias=1.5)[0]  # far outside training: a large gradient
    s, a, n = (torch.as_tensor(x) for x in ep.transitions().arrays())
    theta = model.params()
    g_full = {k: theta[k] - v for k, v in adapt(model, theta, one, s, a, n, last).items() if k in last}
    norm = float(torch.sqrt(sum((v * v).sum() for v in g_full.values())))
    cap = 0.25 * norm
    step = {k: theta[k] - v for k, v in adapt(model, theta, one, s, a, n, last, clip=cap).items() if k in last}
    assert float(torch.sqrt(sum((v * v).sum() for v in step.values()))) == pytest.approx(cap, rel=1e-4)
    for k in last:  # the same direction, shortened
        torch.testing.assert_close(step[k], g_full[k] * (cap / norm), atol=1e-6, rtol=1e-4)
    # a cap above the norm changes nothing; the untouched layers stay θ*
    big = adapt(model, theta, one, s, a, n, last, clip=10 * norm)
    for k in theta:
        torch.testing.assert_close(big[k], theta[k] - g_full.get(k, torch.zeros_like(theta[k])), atol=1e-6, rtol=0)
    assert np.median(gradient_norms(model, theta, segments([ep], M // 2, M // 2), last)) > 0
    # the run-time adapter applies the cap its checkpoint names
    GrbalAdapter(model, one, window=M, adapt_params=last, clip=cap).save(tmp_path / "c.pt")
    ad = load_adapter(tmp_path / "c.pt")
    assert ad.clip == cap
    for t in range(M):
        ad.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    u = ad.update()
    for k in last:
        np.testing.assert_allclose(u.tensors[k], (theta[k] - step[k]).numpy(), atol=1e-6)
    with pytest.raises(ValueError, match="clip"):
        GrbalAdapter(model, one, window=M, clip=0.0)
