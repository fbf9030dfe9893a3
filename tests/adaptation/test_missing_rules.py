"""Rules no earlier test pinned down (issue 24, item 6): each test fails on the wrong code.

* MOLe's CRP concentration α enters the prior and the adapter's posterior (every other
  test uses α = 1, where a hard-coded 1 passes);
* MOLe creates a task only when the new candidate's posterior beats *every* existing
  task's ("any" would create a task whenever one stale task explains the data worse);
* GrBAL meta-trains on the *next* K transitions after adapting on the *past* M (scoring
  the adapted model on the past M it was adapted on is the overfitting objective).
"""

from __future__ import annotations

import numpy as np
import torch

from hilstack.learning.adaptation.grbal import adapt, evaluate, segments, task_losses
from hilstack.learning.adaptation.mole import MoleAdapter, crp_log_prior, task_posterior
from tests.adaptation import toy
from tests.adaptation.conftest import K, M


def test_crp_prior_uses_alpha():
    counts = torch.tensor([3.0, 1.0])
    for alpha in (0.25, 4.0):
        np.testing.assert_allclose(crp_log_prior(counts, alpha).exp().numpy(),
                                   [3 / (4 + alpha), 1 / (4 + alpha), alpha / (4 + alpha)], rtol=1e-12)
    ll = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    p = task_posterior(ll, counts, 4.0).numpy()
    ref = np.exp(ll.numpy()) * np.array([3, 1, 4.0])
    np.testing.assert_allclose(p, ref / ref.sum(), rtol=1e-12)


def _window(ad, seed=1, gain=0.4, steps=None):
    ep = toy.episodes(1, steps or ad.window, seed=seed, gain=gain, turn_bias=0.8)[0]
    for t in range(len(ep)):
        ad.observe(ep.states[t], ep.actions[t], ep.states[t + 1])
    return ad.window_tensors()


def test_mole_adapter_posterior_uses_its_alpha(meta):
    """The adapter's reported posterior is the CRP posterior with *its* α, computed by hand."""
    model, _, psi, _ = meta
    for alpha in (0.05, 20.0):
        ad = MoleAdapter(model, psi, window=8, alpha=alpha)
        th = model.params()
        bad = {k: v + 0.05 * torch.randn_like(v, generator=torch.Generator().manual_seed(1)) for k, v in th.items()}
        ad.tasks, ad.counts = [dict(th), bad], torch.tensor([2.0, 1.0], dtype=torch.float64)
        s, a, n = _window(ad)
        cand = adapt(model, th, psi, s[:4], a[:4], n[:4])
        ll = torch.tensor([ad._log_lik(p, s[4:], a[4:], n[4:]) for p in (th, bad, cand)], dtype=torch.float64)
        ref = task_posterior(ll, torch.tensor([2.0, 1.0]), alpha)
        u = ad.update()
        if ref[2] > ref[:2].max():
            expect = ref.numpy()
        else:
            expect = (ref[:2] / ref[:2].sum()).numpy()
        np.testing.assert_allclose(u.info["posterior"], expect, rtol=1e-9)
    # α changes the outcome: the two runs above disagree on the new task's share
    small = task_posterior(ll, torch.tensor([2.0, 1.0]), 0.05)[2]
    large = task_posterior(ll, torch.tensor([2.0, 1.0]), 20.0)[2]
    assert large > 10 * small


def _three_models(model, psi, s, a, n):
    """(good, candidate, stale): log-likelihoods on the scored half in that order."""
    th = model.params()
    cand = {k: v.detach() for k, v in adapt(model, th, psi, s[:4], a[:4], n[:4]).items()}
    good = {k: v.clone().requires_grad_(True) for k, v in cand.items()}
    opt = torch.optim.Adam(list(good.values()), lr=1e-3)
    for _ in range(200):  # fits the whole window, the scored half included
        opt.zero_grad()
        model.loss(good, s, a, n).backward()
        opt.step()
    good = {k: v.detach() for k, v in good.items()}
    gen = torch.Generator().manual_seed(2)
    stale = {k: v + 0.3 * torch.randn(v.shape, generator=gen) for k, v in th.items()}
    return good, cand, stale


def test_mole_creates_a_task_only_when_the_candidate_beats_every_task(meta):
    model, _, psi, _ = meta
    ad = MoleAdapter(model, psi, window=8, alpha=1.0)
    s, a, n = _window(ad)
    good, cand, stale = _three_models(model, psi, s, a, n)
    ll = [ad._log_lik(p, s[4:], a[4:], n[4:]) for p in (good, cand, stale)]
    assert ll[0] > ll[1] > ll[2], ll  # the set-up: the candidate beats the stale task only

    # one good task and one stale one: the candidate beats "any" but not "every" -> no task
    ad.tasks, ad.counts = [good, stale], torch.tensor([1.0, 1.0], dtype=torch.float64)
    u = ad.update()
    assert u.info["tasks_created"] == 2 and len(u.info["posterior"]) == 2
    assert u.info["task"] == 0
    # two stale tasks: the candidate beats every one -> a third task
    ad.tasks, ad.counts = [stale, dict(stale)], torch.tensor([1.0, 1.0], dtype=torch.float64)
    u = ad.update()
    assert u.info["tasks_created"] == 3 and u.info["task"] == 2


def test_segments_split_past_m_and_next_k():
    ep = toy.episodes(1, M + K, seed=3)[0]
    seg = segments([ep], M, K)
    sp, ap, np_ = seg.past([0])
    sf, af, nf = seg.future([0])
    np.testing.assert_array_equal(sp[0].numpy(), ep.states[:M])
    np.testing.assert_array_equal(np_[0].numpy(), ep.states[1:M + 1])
    np.testing.assert_array_equal(ap[0].numpy(), ep.actions[:M])
    np.testing.assert_array_equal(sf[0].numpy(), ep.states[M:M + K])
    np.testing.assert_array_equal(nf[0].numpy(), ep.states[M + 1:M + K + 1])
    np.testing.assert_array_equal(af[0].numpy(), ep.actions[M:M + K])


def test_meta_objective_adapts_on_past_m_and_scores_the_next_k(meta):
    """The outer loss of meta-training, by hand: adapt on the past M, score on the next K.

    The segment switches condition at M (gain 1 before, 0.3 after), so the loss on the next
    K and the loss on the past M differ by far more than the tolerance."""
    model, _, psi, _ = meta
    past = toy.episodes(1, M, seed=4, gain=1.0)[0]
    s = past.states[-1]
    rng = np.random.default_rng(4)
    st, ac = list(past.states), list(past.actions)
    for _ in range(K):
        a = rng.uniform(-1, 1, 2).astype(np.float32)
        s = toy.step(s, a, 0.3, 1.5)
        st.append(s)
        ac.append(a)
    from hilstack.learning.datasets import Episode
    seg = segments([Episode(np.array(st), np.array(ac))], M, K)
    th = model.params()
    after, before = task_losses(model, th, psi, seg, torch.tensor([0]))
    S, A, N = (torch.as_tensor(x) for x in (np.array(st[:-1]), np.array(ac), np.array(st[1:])))
    adapted = adapt(model, th, psi, S[:M], A[:M], N[:M])
    on_next_k = float(model.loss(adapted, S[M:], A[M:], N[M:]))
    on_past_m = float(model.loss(adapted, S[:M], A[:M], N[:M]))
    assert abs(on_next_k - on_past_m) > 0.1 * on_next_k  # the two objectives are distinguishable here
    np.testing.assert_allclose(float(after[0]), on_next_k, rtol=1e-5)
    np.testing.assert_allclose(float(before[0]), float(model.loss(th, S[M:], A[M:], N[M:])), rtol=1e-5)
    # and the adapted model is the one adapted on the past M (not on the next K)
    wrong = adapt(model, th, psi, S[M:], A[M:], N[M:])
    assert abs(float(model.loss(wrong, S[M:], A[M:], N[M:])) - on_next_k) > 1e-4
    assert evaluate(model, th, psi, seg)["after"] == float(after.mean())
