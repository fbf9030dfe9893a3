"""A small dilated CNN with a spatial-softmax keypoint head (after KeypointNet, Suwajanakorn
et al. 2018, and the spatial soft-argmax of Levine et al. 2016), one keypoint per ball.

Input: an RGB image (H×W, 280×180 in the thesis), downsampled 2× by area averaging.
Body: a 5×5 stride-2 convolution then three 3×3 convolutions dilated 1, 2, 4 (a receptive
field of ~60 full-resolution pixels, three ball diameters, at one resolution, no pooling), ReLU. Heads: one heatmap per ball whose
spatial softmax gives the expected pixel (sub-cell precision), and a visibility logit per
ball (global max of a second 1×1 map). Output stride 4 w.r.t. the full image; pixels
are returned in full-resolution coordinates (OpenCV's convention: pixel centres at
integers).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

N_KEYPOINTS = 2
#: the network sees the image downsampled by this factor
INPUT_SCALE = 2
#: heatmap cell size in full-resolution pixels
STRIDE = 4


def spatial_soft_argmax(logits: torch.Tensor, stride: int = STRIDE) -> torch.Tensor:
    """(B, K, H, W) heatmap logits → (B, K, 2) expected (u, v) under each map's softmax, in
    full-resolution pixels: cell (i, j) covers pixels [stride·j, stride·(j+1)) and its
    centre is at stride·(j + ½) − ½ (pixel centres at integers)."""
    B, K, H, W = logits.shape
    p = torch.softmax(logits.reshape(B, K, H * W), dim=-1).reshape(B, K, H, W)
    u = (torch.arange(W, dtype=logits.dtype) + 0.5) * stride - 0.5
    v = (torch.arange(H, dtype=logits.dtype) + 0.5) * stride - 0.5
    return torch.stack([(p.sum(2) * u).sum(-1), (p.sum(3) * v).sum(-1)], dim=-1)


class KeypointNet(nn.Module):
    def __init__(self, n_keypoints: int = N_KEYPOINTS, width: int = 12):
        super().__init__()
        c = width
        layers: list[nn.Module] = [nn.Conv2d(3, c, 5, stride=2, padding=2), nn.ReLU()]
        for d in (1, 2, 4):
            layers += [nn.Conv2d(c, c, 3, padding=d, dilation=d), nn.ReLU()]
        self.body = nn.Sequential(*layers)
        self.heat = nn.Conv2d(c, n_keypoints, 1)
        self.vis = nn.Conv2d(c, n_keypoints, 1)
        #: softmax temperature (log), learned
        self.log_temp = nn.Parameter(torch.zeros(()))
        self.n_keypoints = n_keypoints

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x``: (B, 3, h, w) float in [0, 1] at the network's input scale. Returns
        (uv (B, K, 2) in full-resolution pixels, visibility logits (B, K))."""
        f = self.body(x)
        uv = spatial_soft_argmax(self.heat(f) / self.log_temp.exp())
        vis = self.vis(f).amax(dim=(2, 3))
        return uv, vis

    @staticmethod
    def preprocess(images: np.ndarray) -> torch.Tensor:
        """(B, H, W, 3) uint8 → (B, 3, H/2, W/2) float in [0, 1] (2× area downsampling)."""
        x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0
        return nn.functional.avg_pool2d(x, INPUT_SCALE)

    def predict(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(uv (B, K, 2) px, visibility in [0, 1] (B, K)) for (B, H, W, 3) uint8 images."""
        uv, vis = self(self.preprocess(images))
        return uv.numpy().astype(np.float64), torch.sigmoid(vis).numpy().astype(np.float64)


def save_keypoint_net(net: KeypointNet, path: str | Path, meta: dict | None = None) -> Path:
    """Weights in half precision (the shipped file stays well under 1 MB) plus metadata."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.half() if v.is_floating_point() else v for k, v in net.state_dict().items()}
    torch.save({"state_dict": state, "n_keypoints": net.n_keypoints, "width": net.heat.in_channels,
                "meta": meta or {}}, p)
    return p


def load_keypoint_net(path: str | Path) -> KeypointNet:
    p = Path(path)
    try:
        ck = torch.load(p, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ValueError(f"no keypoint-net weights at {p} (make them with tools/train_keypoints.py: see docs/camera.md)") from None
    except Exception as e:  # torch raises several types for a corrupt file
        raise ValueError(f"{p}: not keypoint-net weights ({type(e).__name__}: {e})") from None
    net = KeypointNet(ck["n_keypoints"], ck["width"])
    net.load_state_dict({k: v.float() for k, v in ck["state_dict"].items()})
    net.eval()
    return net
