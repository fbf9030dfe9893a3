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
The dynamics model normalises its inputs, so the features' scale does not matter.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

__all__ = ["RandomConvEncoder"]


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
