"""MELD's latent model: the ELBO's pieces against hand-computed values, the reward as evidence,
SAC's squashed-Gaussian log-density, per-task replay."""

import math

import numpy as np
import pytest
import torch

from hilstack.learning.meld.model import (
    BeliefFilter,
    LatentConfig,
    LatentModel,
    elbo_terms,
    gaussian_kl,
    gaussian_log_lik,
)
from hilstack.learning.meld.replay import ImageEpisode, TaskReplay
from hilstack.learning.meld.sac import Actor, Sac, SacConfig

TINY = dict(image_hw=(8, 16), action_dim=2, channels=(4, 8), feature_dim=16, latent_dim=4, hidden=8)


def test_gaussian_kl_matches_hand_computed_values():
    # KL(N(1, 2²) ‖ N(0, 1)) = log(1/2) + (4 + 1)/2 − 1/2
    kl = gaussian_kl(torch.tensor([1.0]), torch.tensor([2.0]), torch.tensor([0.0]), torch.tensor([1.0]))
    assert float(kl) == pytest.approx(math.log(0.5) + 2.5 - 0.5, abs=1e-6)  # 1.30685
    # the other direction is a different number: KL(N(0, 1) ‖ N(1, 2²)) = log 2 + (1 + 1)/8 − 1/2
    rev = gaussian_kl(torch.tensor([0.0]), torch.tensor([1.0]), torch.tensor([1.0]), torch.tensor([2.0]))
    assert float(rev) == pytest.approx(math.log(2.0) + 0.25 - 0.5, abs=1e-6)  # 0.44315
    # sums over the latent axis; zero between equal Gaussians
    two = gaussian_kl(torch.tensor([[1.0, 0.0]]), torch.tensor([[2.0, 1.0]]), torch.zeros(1, 2), torch.ones(1, 2))
    assert float(two[0]) == pytest.approx(1.306853, abs=1e-5)
    assert float(gaussian_kl(torch.ones(3), torch.ones(3), torch.ones(3), torch.ones(3))) == 0.0


def test_gaussian_log_lik_matches_hand_computed_values():
    # log N(1; 0, 0.5²) = −½·(1/0.5)² − log 0.5 − ½ log 2π
    one = -2.0 - math.log(0.5) - 0.5 * math.log(2 * math.pi)  # −2.22579
    x = torch.ones(2, 3)
    ll = gaussian_log_lik(x, torch.zeros(2, 3), 0.5, event_dims=1)
    assert ll.shape == (2,)
    assert ll.tolist() == pytest.approx([3 * one, 3 * one], abs=1e-5)
    assert float(gaussian_log_lik(torch.tensor(0.0), torch.tensor(0.0), 1.0, 0)) == pytest.approx(-0.918939, abs=1e-6)


def _batch(b=3, t=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(b, t, 8, 16, 3, generator=g), torch.randn(b, t, generator=g), torch.rand(b, t - 1, 2, generator=g) * 2 - 1)


def test_elbo_is_eq_7_4_assembled_from_its_terms():
    """image log-lik + reward log-lik − KL(posterior ‖ prior), each recomputed here from the
    filter's output with torch.distributions (independent of the module's own formulas)."""
    torch.manual_seed(0)
    m = LatentModel(LatentConfig(**TINY))
    images, rewards, actions = _batch()
    torch.manual_seed(1)
    terms, out = m.elbo(images, rewards, actions)
    b, t, z = out["z"].shape
    zf = out["z"].reshape(b * t, z)
    img_mean = m.decoder(zf).view(images.shape)
    rew_mean = m.reward_head(zf).view(b, t)
    N = torch.distributions.Normal
    image_ll = N(img_mean, m.cfg.image_std).log_prob(images).sum((1, 2, 3, 4))
    reward_ll = N(rew_mean, m.cfg.reward_std).log_prob(rewards).sum(1)
    kl = torch.distributions.kl_divergence(N(out["post_mu"], out["post_std"]), N(out["prior_mu"], out["prior_std"])).sum((1, 2))
    for name, ref in (("image_ll", image_ll), ("reward_ll", reward_ll), ("kl", kl)):
        assert torch.allclose(terms[name], ref, rtol=1e-4, atol=1e-3), name
    assert torch.allclose(terms["elbo"], image_ll + reward_ll - kl, rtol=1e-4, atol=1e-3)
    # the first step's prior is N(0, I); later steps' priors depend on (z_{t-1}, a_{t-1})
    assert torch.equal(out["prior_mu"][:, 0], torch.zeros(b, z)) and torch.equal(out["prior_std"][:, 0], torch.ones(b, z))
    # the KL is the posterior's against the prior, not the reverse (they differ here)
    rev = torch.distributions.kl_divergence(N(out["prior_mu"], out["prior_std"]), N(out["post_mu"], out["post_std"])).sum((1, 2))
    assert not torch.allclose(rev, kl, rtol=1e-2)


def test_elbo_terms_reward_evidence_enters_the_bound():
    """A better reward prediction raises the ELBO by exactly its log-likelihood gain."""
    z = torch.zeros(1, 2, 1)
    base = dict(images=torch.zeros(1, 2, 1, 1, 1), image_mean=torch.zeros(1, 2, 1, 1, 1), post_mu=z, post_std=z + 1,
                prior_mu=z, prior_std=z + 1, image_std=1.0, reward_std=1.0)
    good = elbo_terms(rewards=torch.ones(1, 2), reward_mean=torch.ones(1, 2), **base)
    bad = elbo_terms(rewards=torch.ones(1, 2), reward_mean=torch.zeros(1, 2), **base)
    assert float(good["elbo"] - bad["elbo"]) == pytest.approx(2 * 0.5, abs=1e-6)


@pytest.mark.parametrize("evidence", [True, False])
def test_posterior_sees_the_reward_only_with_reward_evidence(evidence):
    """Same images and actions, different rewards: MELD's belief differs (the reward carries the
    task), SLAC's does not."""
    torch.manual_seed(0)
    m = LatentModel(LatentConfig(**TINY, reward_evidence=evidence))
    images, rewards, actions = _batch(b=1)
    f = BeliefFilter(m)
    b1 = [f.update((images[0, i] * 255).numpy(), float(rewards[0, i])) for i in range(1)]
    f.reset()
    b2 = [f.update((images[0, i] * 255).numpy(), float(rewards[0, i]) + 3.0) for i in range(1)]
    differs = not torch.allclose(b1[-1], b2[-1])
    assert differs == evidence
    # the online filter is the batch filter with the posterior mean passed on
    f.reset()
    for i in range(4):
        bel = f.update((images[0, i] * 255).numpy(), float(rewards[0, i]))
        if i < 3:
            f.act(actions[0, i].numpy())
    assert bel.shape == (2 * TINY["latent_dim"],)


def test_tanh_gaussian_log_density_matches_torch_distributions():
    torch.manual_seed(0)
    actor = Actor(5, 3, 16)
    obs = torch.randn(7, 5)
    torch.manual_seed(1)
    a, logp = actor(obs)
    mu, log_std = actor.net(obs).chunk(2, -1)
    d = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mu, log_std.clamp(-10, 2).exp()), [torch.distributions.TanhTransform()])
    assert torch.allclose(logp, d.log_prob(a.clamp(-1 + 1e-6, 1 - 1e-6)).sum(-1), atol=1e-3)
    assert float(a.detach().abs().max()) < 1.0


def test_sac_entropy_temperature_moves_towards_the_target():
    """With a near-deterministic actor the entropy is below −|A|: α must grow; critic loss falls on a fixed batch."""
    torch.manual_seed(0)
    sac = Sac(4, 2)
    with torch.no_grad():
        sac.actor.net[-1].bias[2:] = -8.0  # log σ = −8: entropy far below the target
        sac.actor.net[-1].weight[2:] = 0.0
    obs, a, r = torch.randn(64, 4), torch.rand(64, 2) * 2 - 1, torch.randn(64)
    alpha0 = sac.alpha.item()
    losses = [sac.update(obs, a, r, obs, torch.zeros(64))["critic_loss"] for _ in range(30)]
    assert sac.alpha.item() > alpha0
    assert losses[-1] < losses[0]


def test_sac_reward_scale_and_entropy_target_are_what_the_config_says():
    """The diagnostics' knobs: the critic's target is ``scale · r + γ (min Q' − α log π')``
    (with done, ``scale · r`` alone), and the temperature's target is the per-dimension value × |A|."""
    torch.manual_seed(0)
    sac = Sac(4, 3, SacConfig(reward_scale=2.5, target_entropy_per_dim=-0.5))
    assert sac.target_entropy == -1.5
    obs, a, r = torch.randn(16, 4), torch.rand(16, 3) * 2 - 1, torch.randn(16)
    with torch.no_grad():
        q1, q2 = sac.critic(obs, a)
    want = ((q1 - 2.5 * r) ** 2).mean() + ((q2 - 2.5 * r) ** 2).mean()  # not_done = 0: the target is scale · r
    assert sac.critic_loss(obs, a, r, obs, torch.zeros(16)).item() == pytest.approx(want.item(), rel=1e-6)


def test_replay_keeps_tasks_apart_and_pads_history():
    rp = TaskReplay()
    for task in (0, 1):
        imgs = np.full((6, 2, 4, 3), task, np.uint8)
        imgs[:, 0, 0, 0] = np.arange(6)  # the step index, to check alignment
        rp.add(ImageEpisode(imgs, np.arange(6, dtype=np.float32) + 10 * task, np.ones((5, 2), np.float32), task))
    assert rp.n_samples == 10 and set(rp.episodes) == {0, 1}
    s = rp.sample(np.random.default_rng(0), 50, 4)
    assert s["images"].shape == (50, 4, 2, 4, 3) and s["actions"].shape == (50, 3, 2)
    for im, rw, task in zip(s["images"], s["rewards"], s["tasks"], strict=True):
        assert np.all(im[:, 1, 1, 0] == task)                  # one task per sequence
        assert np.array_equal(rw - 10 * task, im[:, 0, 0, 0])  # reward t with image t
    p = rp.sample(np.random.default_rng(1), 200, 4, pad_front=3)
    starts = p["images"][:, :, 0, 0, 0]
    assert any(np.array_equal(s_, [0, 0, 0, 0]) for s_ in starts)  # the first frame, repeated
    with pytest.raises(ValueError, match="6 images and rewards"):
        ImageEpisode(np.zeros((5, 2, 4, 3), np.uint8), np.zeros(6), np.zeros((5, 2)), 0)
