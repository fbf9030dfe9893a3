"""Soft actor-critic (Haarnoja et al. 2018) on a feature vector: MELD's belief, or a baseline's
encoded history. 2×256 tanh-Gaussian actor, twin Q critics with Polyak targets, entropy
temperature tuned towards ``−action_dim`` (MELD Table 7.1: lr 3e-4 for actor and critic).

Actions are normalized to [−1, 1]; the environment scales them.
"""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F


@dataclass(frozen=True)
class SacConfig:
    hidden: int = 256
    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005
    init_alpha: float = 0.1
    target_entropy_per_dim: float = -1.0  #: the temperature's target entropy per action dimension
    reward_scale: float = 1.0             #: rewards are multiplied by this in the critic's target


def mlp2(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, n_out))


class Actor(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int, hidden: int):
        super().__init__()
        self.net = mlp2(obs_dim, hidden, 2 * action_dim)

    def forward(self, obs: torch.Tensor, deterministic: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(action in [−1, 1], log π(action))."""
        mu, log_std = self.net(obs).chunk(2, -1)
        std = log_std.clamp(-10.0, 2.0).exp()
        u = mu if deterministic else mu + std * torch.randn_like(mu)
        a = torch.tanh(u)
        # log-density of the tanh-squashed Gaussian (the change of variables' Jacobian)
        logp = (-0.5 * ((u - mu) / std) ** 2 - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        logp = logp - (2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))).sum(-1)
        return a, logp


class TwinQ(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int, hidden: int):
        super().__init__()
        self.q1, self.q2 = mlp2(obs_dim + action_dim, hidden, 1), mlp2(obs_dim + action_dim, hidden, 1)

    def forward(self, obs: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([obs, a], -1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


class Sac(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int, cfg: SacConfig | None = None):
        super().__init__()
        self.cfg = cfg or SacConfig()
        self.action_dim = action_dim
        self.actor = Actor(obs_dim, action_dim, self.cfg.hidden)
        self.critic = TwinQ(obs_dim, action_dim, self.cfg.hidden)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(self.cfg.init_alpha)))
        self.target_entropy = self.cfg.target_entropy_per_dim * float(action_dim)

    # Optimizers are made on the first update: the first one a process makes imports
    # torch._dynamo (seconds; 12 s at load 39 on 2 cores), which a policy that only acts (a
    # controller node, a meta-test) never needs.
    @functools.cached_property
    def opt_actor(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.actor.parameters(), lr=self.cfg.lr)

    @functools.cached_property
    def opt_critic(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.critic.parameters(), lr=self.cfg.lr)

    @functools.cached_property
    def opt_alpha(self) -> torch.optim.Optimizer:
        return torch.optim.Adam([self.log_alpha], lr=self.cfg.lr)

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    def critic_loss(self, obs, a, r, next_obs, not_done) -> torch.Tensor:
        with torch.no_grad():
            a2, logp2 = self.actor(next_obs)
            q1t, q2t = self.critic_target(next_obs, a2)
            target = self.cfg.reward_scale * r + self.cfg.gamma * not_done * (torch.min(q1t, q2t) - self.alpha * logp2)
        q1, q2 = self.critic(obs, a)
        return F.mse_loss(q1, target) + F.mse_loss(q2, target)

    def update(self, obs, a, r, next_obs, not_done, critic_obs=None, critic_next_obs=None,
               extra_critic_opt: torch.optim.Optimizer | None = None) -> dict[str, float]:
        """One SAC step on a batch of transitions. ``critic_obs`` (default ``obs``) may carry
        gradients into an encoder whose optimizer is ``extra_critic_opt`` (the history baseline)."""
        co = obs if critic_obs is None else critic_obs
        cn = next_obs if critic_next_obs is None else critic_next_obs
        lc = self.critic_loss(co, a, r, cn, not_done)
        self.opt_critic.zero_grad()
        if extra_critic_opt is not None:
            extra_critic_opt.zero_grad()
        lc.backward()
        self.opt_critic.step()
        if extra_critic_opt is not None:
            extra_critic_opt.step()
        obs = obs.detach()
        a_pi, logp = self.actor(obs)
        q1, q2 = self.critic(obs, a_pi)
        la = (self.alpha.detach() * logp - torch.min(q1, q2)).mean()
        self.opt_actor.zero_grad()
        la.backward()
        self.opt_actor.step()
        lalpha = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        self.opt_alpha.zero_grad()
        lalpha.backward()
        self.opt_alpha.step()
        with torch.no_grad():
            for p, pt in zip(self.critic.parameters(), self.critic_target.parameters(), strict=True):
                pt.lerp_(p, self.cfg.tau)
        return {"critic_loss": lc.item(), "actor_loss": la.item(), "alpha": self.alpha.item(),
                "entropy": float(-logp.detach().mean())}

    @torch.no_grad()
    def act(self, obs: torch.Tensor, deterministic: bool = False):
        a, _ = self.actor(obs.unsqueeze(0), deterministic=deterministic)
        return a[0].numpy()
