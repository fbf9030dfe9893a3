"""MELD's sequential latent variable model (Zhao, Nagabandi et al. 2020; Nagabandi's thesis ch. 7).

Meta-RL as latent state estimation: one latent ``z_t`` carries both the robot's state and the
task, and its evidence is the image ``x_t`` *and the reward* ``r_t``. The model (SLAC-style,
Lee et al. 2020, with MELD's plain Gaussian latent of 32-unit networks, Table 7.1):

* encoder ``e(x_t)``: a conv net over the (fixed | wrist) image;
* latent dynamics prior ``p(z_1) = N(0, I)``, ``p(z_t | z_{t-1}, a_{t-1})``;
* filtering posterior ``q(z_1 | x_1, r_1)``, ``q(z_t | x_t, r_t, z_{t-1}, a_{t-1})``; with
  ``reward_evidence=False`` the posterior does not see ``r_t`` (SLAC, the no-meta baseline);
* decoders ``p(x_t | z_t)`` (deconv, Gaussian of fixed σ) and ``p(r_t | z_t)`` (Gaussian of fixed σ).

The ELBO (thesis Eq. 7.4), written once in :func:`elbo_terms`::

    E_q [ Σ_t log p(x_t | z_t) + log p(r_t | z_t) − KL( q(z_t | x_t, r_t, z_{t-1}, a_{t-1}) ‖ p(z_t | z_{t-1}, a_{t-1}) ) ]

The belief handed to SAC is the filtering posterior's mean and σ, ``b_t = [μ_t, σ_t]``
(detached: SAC's losses do not train the model, as in SLAC and MELD).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class LatentConfig:
    image_hw: tuple[int, int] = (64, 128)   #: (height, width): two square views side by side
    action_dim: int = 6
    latent_dim: int = 32                    #: MELD Table 7.1: 32-unit latent networks
    hidden: int = 32
    feature_dim: int = 256
    channels: tuple[int, ...] = (16, 32, 64, 128)  #: conv widths; each layer halves the image
    image_std: float = math.sqrt(0.1)       #: σ of the image likelihood (SLAC's value)
    reward_std: float = 0.5                 #: σ of the reward likelihood
    reward_evidence: bool = True            #: False: SLAC's posterior, blind to the reward
    min_std: float = 1e-3

    def __post_init__(self) -> None:
        h, w = self.image_hw
        k = 2 ** len(self.channels)
        if h % k or w % k or h < k or w < k:
            raise ValueError(f"LatentConfig.image_hw {self.image_hw}: both sides must be multiples of {k} "
                             f"(the encoder halves them {len(self.channels)} times)")


# ---------------------------------------------------------------------------- the math, once
def gaussian_kl(mu_q: torch.Tensor, std_q: torch.Tensor, mu_p: torch.Tensor, std_p: torch.Tensor) -> torch.Tensor:
    """KL(N(μ_q, σ_q²) ‖ N(μ_p, σ_p²)) of diagonal Gaussians, summed over the last axis:
    ``Σ log(σ_p/σ_q) + (σ_q² + (μ_q − μ_p)²) / (2σ_p²) − ½``."""
    var_q, var_p = std_q * std_q, std_p * std_p
    return (torch.log(std_p / std_q) + (var_q + (mu_q - mu_p) ** 2) / (2.0 * var_p) - 0.5).sum(-1)


def gaussian_log_lik(x: torch.Tensor, mean: torch.Tensor, std: float, event_dims: int) -> torch.Tensor:
    """log N(x; mean, std²) summed over the last ``event_dims`` axes."""
    ll = -0.5 * ((x - mean) / std) ** 2 - math.log(std) - 0.5 * LOG_2PI
    return ll.flatten(start_dim=ll.dim() - event_dims).sum(-1) if event_dims else ll


def elbo_terms(images: torch.Tensor, rewards: torch.Tensor, image_mean: torch.Tensor, reward_mean: torch.Tensor,
               post_mu: torch.Tensor, post_std: torch.Tensor, prior_mu: torch.Tensor, prior_std: torch.Tensor,
               image_std: float, reward_std: float) -> dict[str, torch.Tensor]:
    """Eq. 7.4 per sequence ``[B]``, summed over time, from the decoders' means at posterior
    samples and the posterior/prior parameters ``[B, T, Z]``. ``elbo = image_ll + reward_ll − kl``."""
    image_ll = gaussian_log_lik(images, image_mean, image_std, event_dims=3).sum(-1)
    reward_ll = gaussian_log_lik(rewards, reward_mean, reward_std, event_dims=0).sum(-1)
    kl = gaussian_kl(post_mu, post_std, prior_mu, prior_std).sum(-1)
    return {"elbo": image_ll + reward_ll - kl, "image_ll": image_ll, "reward_ll": reward_ll, "kl": kl}


# ---------------------------------------------------------------------------- networks
def _mlp(n_in: int, n_hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, n_hidden), nn.LeakyReLU(0.2), nn.Linear(n_hidden, n_hidden),
                         nn.LeakyReLU(0.2), nn.Linear(n_hidden, n_out))


class _GaussianHead(nn.Module):
    def __init__(self, n_in: int, hidden: int, n_out: int, min_std: float):
        super().__init__()
        self.net, self.min_std = _mlp(n_in, hidden, 2 * n_out), min_std

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, s = self.net(x).chunk(2, dim=-1)
        return mu, F.softplus(s) + self.min_std


class Encoder(nn.Module):
    """images ``[N, H, W, C]`` (floats in [0, 1]) → features ``[N, feature_dim]``."""

    def __init__(self, cfg: LatentConfig, in_channels: int = 3):
        super().__init__()
        layers, c_in = [], in_channels
        for c in cfg.channels:
            layers += [nn.Conv2d(c_in, c, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
            c_in = c
        self.conv = nn.Sequential(*layers)
        k = 2 ** len(cfg.channels)
        self.out = nn.Linear(c_in * (cfg.image_hw[0] // k) * (cfg.image_hw[1] // k), cfg.feature_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(self.out(self.conv(x.permute(0, 3, 1, 2)).flatten(1)), 0.2)


class Decoder(nn.Module):
    """``z [N, Z]`` → image mean ``[N, H, W, 3]``."""

    def __init__(self, cfg: LatentConfig):
        super().__init__()
        k = 2 ** len(cfg.channels)
        self.hw0 = (cfg.image_hw[0] // k, cfg.image_hw[1] // k)
        chans = list(reversed(cfg.channels))
        self.inp = nn.Linear(cfg.latent_dim, chans[0] * self.hw0[0] * self.hw0[1])
        layers = []
        for c_in, c_out in zip(chans, chans[1:] + [3], strict=True):
            layers += [nn.ConvTranspose2d(c_in, c_out, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        self.deconv = nn.Sequential(*layers[:-1])  # no activation on the mean
        self.c0 = chans[0]

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = F.leaky_relu(self.inp(z), 0.2).view(-1, self.c0, *self.hw0)
        return self.deconv(h).permute(0, 2, 3, 1)


class LatentModel(nn.Module):
    def __init__(self, cfg: LatentConfig):
        super().__init__()
        self.cfg = cfg
        z, a, h, f = cfg.latent_dim, cfg.action_dim, cfg.hidden, cfg.feature_dim
        r = 1 if cfg.reward_evidence else 0
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)
        self.prior = _GaussianHead(z + a, h, z, cfg.min_std)          # p(z_t | z_{t-1}, a_{t-1})
        self.post_first = _GaussianHead(f + r, h, z, cfg.min_std)     # q(z_1 | x_1, r_1)
        self.post = _GaussianHead(f + r + z + a, h, z, cfg.min_std)   # q(z_t | x_t, r_t, z_{t-1}, a_{t-1})
        self.reward_head = _mlp(z, h, 1)                              # mean of p(r_t | z_t)

    @property
    def belief_dim(self) -> int:
        return 2 * self.cfg.latent_dim

    def _evidence(self, feat: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        return torch.cat([feat, r.unsqueeze(-1)], -1) if self.cfg.reward_evidence else feat

    def posterior_step(self, feat: torch.Tensor, r: torch.Tensor, z_prev: torch.Tensor | None,
                       a_prev: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """One filtering step: (μ, σ) of q(z_t | ·) from the encoded image, reward and last (z, a)."""
        e = self._evidence(feat, r)
        if z_prev is None:
            return self.post_first(e)
        return self.post(torch.cat([e, z_prev, a_prev], -1))

    def prior_step(self, z_prev: torch.Tensor | None, a_prev: torch.Tensor | None,
                   batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        if z_prev is None:
            zeros = torch.zeros(batch, self.cfg.latent_dim)
            return zeros, torch.ones_like(zeros)
        return self.prior(torch.cat([z_prev, a_prev], -1))

    def filter(self, images: torch.Tensor, rewards: torch.Tensor, actions: torch.Tensor) -> dict[str, torch.Tensor]:
        """Run the filter over sequences. ``images [B, T, H, W, 3]`` in [0, 1], ``rewards [B, T]``
        (``r_t`` observed with ``x_t``), ``actions [B, T-1]`` (``a_t`` taken after ``x_t``).
        Returns posterior/prior parameters and reparametrized posterior samples ``[B, T, Z]``."""
        b, t = images.shape[:2]
        feat = self.encoder(images.reshape(b * t, *images.shape[2:])).view(b, t, -1)
        post_mu, post_std, prior_mu, prior_std, zs = [], [], [], [], []
        z = a = None
        for i in range(t):
            if i > 0:
                a = actions[:, i - 1]
            pm, ps = self.prior_step(z, a, b)
            qm, qs = self.posterior_step(feat[:, i], rewards[:, i], z, a)
            z = qm + qs * torch.randn_like(qs)
            post_mu.append(qm), post_std.append(qs), prior_mu.append(pm), prior_std.append(ps), zs.append(z)
        st = lambda xs: torch.stack(xs, 1)  # noqa: E731
        return {"post_mu": st(post_mu), "post_std": st(post_std), "prior_mu": st(prior_mu),
                "prior_std": st(prior_std), "z": st(zs)}

    def elbo(self, images: torch.Tensor, rewards: torch.Tensor, actions: torch.Tensor
             ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """(Eq. 7.4 terms per sequence, the filter's output)."""
        out = self.filter(images, rewards, actions)
        b, t, zd = out["z"].shape
        z = out["z"].reshape(b * t, zd)
        img_mean = self.decoder(z).view(images.shape)
        rew_mean = self.reward_head(z).view(b, t)
        terms = elbo_terms(images, rewards, img_mean, rew_mean, out["post_mu"], out["post_std"], out["prior_mu"],
                           out["prior_std"], self.cfg.image_std, self.cfg.reward_std)
        return terms, out

    @staticmethod
    def belief(post_mu: torch.Tensor, post_std: torch.Tensor) -> torch.Tensor:
        """b_t = [μ_t, σ_t] of the filtering posterior: what SAC acts on."""
        return torch.cat([post_mu, post_std], -1)


class BeliefFilter:
    """The online filter of one episode: feed (image, reward) after each step, read the belief.

    Used by the policy at collection and test time (Algorithm 8): the posterior mean stands in
    for the latent sample passed to the next step, so acting is deterministic given the data."""

    def __init__(self, model: LatentModel):
        self.model = model
        self.reset()

    def reset(self) -> None:
        self.z: torch.Tensor | None = None
        self.a: torch.Tensor | None = None
        self.mu: torch.Tensor | None = None
        self.std: torch.Tensor | None = None

    @torch.no_grad()
    def update(self, image_u8, reward: float) -> torch.Tensor:
        x = torch.as_tensor(image_u8, dtype=torch.float32).unsqueeze(0) / 255.0
        feat = self.model.encoder(x)
        r = torch.tensor([float(reward)])
        self.mu, self.std = self.model.posterior_step(feat, r, self.z, self.a)
        self.z = self.mu
        return self.belief()

    def act(self, action) -> None:
        self.a = torch.as_tensor(action, dtype=torch.float32).view(1, -1)

    def belief(self) -> torch.Tensor:
        return LatentModel.belief(self.mu, self.std)[0]
