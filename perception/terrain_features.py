"""Image features for the image-conditioned terrain model (thesis ch. 3.3): a fixed random
conv net and a fixed random projection, no downloaded and no trained weights.

The thesis passes the robot's camera image through the convolutional layers of an AlexNet
pretrained on ImageNet and projects the result to a low dimension with a fixed random matrix;
the dynamics model takes that vector beside the state and the action. ImageNet weights cannot
be downloaded here, so the conv layers are random instead, drawn once from a seed (Kaiming-
normal, as a network is initialised) and never trained:

* why random and not trained on the sim's renders: a net trained on our own renders of the
  very terrains it is then asked to tell apart would be a terrain classifier fitted to the
  test set, and any gain would be partly its training; fixed random filters learn nothing
  about the terrains, like the thesis' ImageNet filters, which never saw the robot's floors;
* random conv filters with a rectifier and pooling keep colour and texture statistics of an
  image (Jarrett et al., ICCV 2009; Saxe et al., "On random weights and unsupervised feature
  learning", ICML 2011), which is what tells the terrains apart;
* they are deterministic from the seed, cost ~1 ms per 64×64 image on one CPU thread, and
  need no file.

Layout: RGB in [0, 1] minus 0.5 → conv 5×5 stride 2 (16) → ReLU → conv 3×3 stride 2 (32) →
ReLU → conv 3×3 stride 2 (64) → ReLU → mean over the image (64 numbers, invariant to where on
the image a patch is) → a fixed Gaussian projection to ``out_dim`` (entries N(0, 1/64)).
The dynamics model normalises each input channel, but that does not make the 16 features 16
inputs' worth of information: the mean activations of random filters move together, and on the
roach's four terrains three principal directions carry > 99 % of the features' variance (66, 26,
6 %; docs/mbrl.md). :class:`FeatureWhitening`, fitted on the training data, turns them into the
few decorrelated unit-variance inputs they are.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

__all__ = ["FeatureWhitening", "RandomConvEncoder"]


class RandomConvEncoder:
    """``encode(images) -> [N, out_dim]`` float32 features of ``[N, H, W, 3]`` uint8 images
    (or one ``[H, W, 3]`` image → ``[out_dim]``). Same seed, same features."""

    def __init__(self, out_dim: int = 16, seed: int = 0, channels: tuple[int, ...] = (16, 32, 64)):
        if out_dim < 1:
            raise ValueError(f"out_dim must be >= 1, got {out_dim}")
        self.out_dim, self.seed, self.channels = int(out_dim), int(seed), tuple(int(c) for c in channels)
        gen = torch.Generator().manual_seed(self.seed)
        layers: list[nn.Module] = []
        c_in = 3
        for i, c in enumerate(self.channels):
            k = 5 if i == 0 else 3
            conv = nn.Conv2d(c_in, c, k, stride=2, padding=k // 2)
            with torch.no_grad():
                conv.weight.normal_(0.0, (2.0 / (c_in * k * k)) ** 0.5, generator=gen)  # Kaiming normal
                conv.bias.zero_()
            layers += [conv, nn.ReLU()]
            c_in = c
        self.net = nn.Sequential(*layers).eval().requires_grad_(False)
        self.projection = torch.randn(c_in, self.out_dim, generator=gen) / c_in**0.5

    @property
    def names(self) -> list[str]:
        """Channel names of the features (``img_0`` ...), as they join the state."""
        return [f"img_{i}" for i in range(self.out_dim)]

    def encode(self, images: np.ndarray, batch: int = 256) -> np.ndarray:
        x = np.asarray(images)
        single = x.ndim == 3
        if single:
            x = x[None]
        if x.ndim != 4 or x.shape[-1] != 3:
            raise ValueError(f"images must be [N, H, W, 3] (or one [H, W, 3]), got shape {x.shape}")
        out = []
        with torch.inference_mode():
            for i in range(0, len(x), batch):
                t = torch.from_numpy(np.ascontiguousarray(x[i:i + batch])).permute(0, 3, 1, 2).float() / 255.0 - 0.5
                h = self.net(t).mean(dim=(2, 3))
                out.append((h @ self.projection).numpy())
        f = np.concatenate(out).astype(np.float32) if out else np.zeros((0, self.out_dim), np.float32)
        return f[0] if single else f


class FeatureWhitening:
    """PCA whitening of image features, fitted on training features: ``f ↦ (f − μ) V_k / σ_k``
    with the principal directions ``V_k`` that carry at least ``min_share`` of the variance each.

    Why: per-channel normalisation of near-collinear features (a random projection of mean
    activations that move together) hands the network ``F`` copies of a few signals, so at the
    first layer they weigh like ``F`` inputs against each state channel's one; whitened, each
    independent direction is one unit-variance input, the scale of a normalised state channel.
    """

    def __init__(self, features: np.ndarray, min_share: float = 0.01):
        f = np.asarray(features, dtype=np.float64)
        if f.ndim != 2 or len(f) < 2:
            raise ValueError(f"features must be [N >= 2, F], got shape {f.shape}")
        if not 0.0 < min_share < 1.0:
            raise ValueError(f"min_share must be in (0, 1), got {min_share}")
        self.mean = f.mean(0)
        _, sv, vt = np.linalg.svd(f - self.mean, full_matrices=False)
        var = sv**2 / len(f)
        share = var / max(var.sum(), 1e-30)
        k = max(1, int((share >= min_share).sum()))
        #: the variance share of every principal direction (descending), for the report
        self.shares = share.tolist()
        self.projection = (vt[:k].T / np.sqrt(np.maximum(var[:k], 1e-30))).astype(np.float32)

    @property
    def out_dim(self) -> int:
        return int(self.projection.shape[1])

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return ((np.asarray(features, dtype=np.float32) - self.mean.astype(np.float32)) @ self.projection).astype(
            np.float32)
