"""The learners compared in ``hil demo meld``, behind one interface:

* :class:`MeldAgent`: the latent model with reward evidence + SAC on its belief (MELD);
* ``MeldAgent(reward_evidence=False)``: the same without the reward in the posterior (SLAC, the
  thesis' no-meta-learning baseline);
* :class:`HistorySacAgent`: SAC on the last ``k`` images and rewards (the thesis' SAC baseline),
  its conv encoder trained by the critic's loss.

Interface: ``reset()`` at an episode start, ``observe(image_u8, reward)`` after each image,
``act(deterministic) -> action`` (normalized, [−1, 1]), ``train_step(replay, rng) -> dict``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from hilstack.learning.meld.model import BeliefFilter, Encoder, LatentConfig, LatentModel
from hilstack.learning.meld.replay import TaskReplay
from hilstack.learning.meld.sac import Sac, SacConfig


@dataclass(frozen=True)
class AgentConfig:
    latent: LatentConfig = field(default_factory=LatentConfig)
    sac: SacConfig = field(default_factory=SacConfig)
    model_lr: float = 1e-4          #: MELD Table 7.1
    batch: int = 32                 #: sequences per step (Table 7.1: 512 transitions on a GPU)
    seq_len: int = 8                #: images per sequence (SLAC's 8)
    history: int = 4                #: frames of the history baseline


def _to_t(batch: dict[str, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (torch.as_tensor(batch["images"], dtype=torch.float32) / 255.0, torch.as_tensor(batch["rewards"]),
            torch.as_tensor(batch["actions"]))


class MeldAgent:
    name = "meld"

    def __init__(self, cfg: AgentConfig, reward_evidence: bool = True):
        self.cfg = replace(cfg, latent=replace(cfg.latent, reward_evidence=reward_evidence))
        self.name = "meld" if reward_evidence else "slac"
        self.model = LatentModel(self.cfg.latent)
        self.sac = Sac(self.model.belief_dim, self.cfg.latent.action_dim, self.cfg.sac)
        self.filter = BeliefFilter(self.model)
        self.beliefs: list[np.ndarray] = []

    @functools.cached_property
    def opt_model(self) -> torch.optim.Optimizer:
        """Made on the first train step (see :class:`~.sac.Sac`: an acting-only agent needs none)."""
        return torch.optim.Adam(self.model.parameters(), lr=self.cfg.model_lr)

    def reset(self) -> None:
        self.filter.reset()
        self.beliefs = []

    def observe(self, image_u8: np.ndarray, reward: float) -> None:
        self.beliefs.append(self.filter.update(image_u8, reward).numpy())

    def act(self, deterministic: bool = False) -> np.ndarray:
        a = self.sac.act(self.filter.belief(), deterministic)
        self.filter.act(a)
        return a

    def task_features(self) -> np.ndarray:
        """The belief's mean over the episode so far ``[t, Z]`` (what the task probe reads)."""
        return np.stack(self.beliefs)[:, : self.cfg.latent.latent_dim]

    def train_step(self, replay: TaskReplay, rng: np.random.Generator) -> dict[str, float]:
        """One model step on the ELBO and one SAC step on the beliefs of the same sequences."""
        images, rewards, actions = _to_t(replay.sample(rng, self.cfg.batch, self.cfg.seq_len))
        terms, out = self.model.elbo(images, rewards, actions)
        loss = -terms["elbo"].mean() / images.shape[1]
        self.opt_model.zero_grad()
        loss.backward()
        self.opt_model.step()
        b = LatentModel.belief(out["post_mu"], out["post_std"]).detach()
        zd = b.shape[-1]
        obs, nxt = b[:, :-1].reshape(-1, zd), b[:, 1:].reshape(-1, zd)
        stats = self.sac.update(obs, actions.reshape(-1, actions.shape[-1]), rewards[:, 1:].reshape(-1), nxt,
                                torch.ones(obs.shape[0]))
        return {"elbo": terms["elbo"].mean().item(), "kl": terms["kl"].mean().item(),
                "reward_ll": terms["reward_ll"].mean().item(), **stats}


class HistoryEncoder(torch.nn.Module):
    """The last ``k`` images stacked on channels, plus the last ``k`` rewards → features."""

    def __init__(self, latent: LatentConfig, k: int):
        super().__init__()
        self.k = k
        self.conv = Encoder(latent, in_channels=3 * k)
        self.dim = latent.feature_dim + k

    def forward(self, images: torch.Tensor, rewards: torch.Tensor) -> torch.Tensor:
        """``images [N, k, H, W, 3]``, ``rewards [N, k]``."""
        n, k, h, w, c = images.shape
        stacked = images.permute(0, 2, 3, 1, 4).reshape(n, h, w, k * c)
        return torch.cat([self.conv(stacked), rewards], -1)


class HistorySacAgent:
    name = "sac_history"

    def __init__(self, cfg: AgentConfig):
        self.cfg = cfg
        self.k = cfg.history
        self.encoder = HistoryEncoder(cfg.latent, self.k)
        self.sac = Sac(self.encoder.dim, cfg.latent.action_dim, cfg.sac)
        self.reset()

    @functools.cached_property
    def opt_encoder(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.encoder.parameters(), lr=self.cfg.sac.lr)

    def reset(self) -> None:
        self.images: list[np.ndarray] = []
        self.rewards: list[float] = []

    def observe(self, image_u8: np.ndarray, reward: float) -> None:
        if not self.images:  # pad the start with the first frame, as the replay does
            self.images, self.rewards = [image_u8] * (self.k - 1), [float(reward)] * (self.k - 1)
        self.images.append(image_u8)
        self.rewards.append(float(reward))

    @torch.no_grad()
    def _features(self) -> torch.Tensor:
        im = torch.as_tensor(np.stack(self.images[-self.k:]), dtype=torch.float32).unsqueeze(0) / 255.0
        r = torch.tensor([self.rewards[-self.k:]], dtype=torch.float32)
        return self.encoder(im, r)[0]

    def act(self, deterministic: bool = False) -> np.ndarray:
        return self.sac.act(self._features(), deterministic)

    def train_step(self, replay: TaskReplay, rng: np.random.Generator) -> dict[str, float]:
        k = self.k
        images, rewards, actions = _to_t(replay.sample(rng, self.cfg.batch, k + 1, pad_front=k - 1))
        feat = self.encoder(torch.cat([images[:, :k], images[:, 1:]]), torch.cat([rewards[:, :k], rewards[:, 1:]]))
        obs, nxt = feat.chunk(2)
        return self.sac.update(obs.detach(), actions[:, -1], rewards[:, -1], nxt.detach(),
                               torch.ones(obs.shape[0]), critic_obs=obs, critic_next_obs=nxt.detach(),
                               extra_critic_opt=self.opt_encoder)


AGENTS = {"meld": lambda cfg: MeldAgent(cfg), "slac": lambda cfg: MeldAgent(cfg, reward_evidence=False),
          "sac_history": HistorySacAgent}
