"""The two cameras of the WidowX bench rendered from the MuJoCo world: a fixed camera
and a wrist camera, each ``height × height`` pixels, concatenated side by side into one
``height × 2·height`` RGB image (64×128 in the MELD thesis' cable-insertion task).

Rendering goes through :class:`hilstack.sim_backends.rendering.OffscreenRenderer` (offscreen GL,
shadows and reflections off).
"""

from __future__ import annotations

import mujoco
import numpy as np

from hilstack.sim_backends.rendering import OffscreenRenderer

CAMERAS = ("fixed", "wrist")


class BenchCameras:
    def __init__(self, model: mujoco.MjModel, height_px: int = 64):
        self.height_px = height_px
        self._r = OffscreenRenderer(model, height_px, height_px)

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """(height, 2·height, 3) uint8: [fixed | wrist]."""
        return np.concatenate([self._r.render(data, cam) for cam in CAMERAS], axis=1)

    def close(self) -> None:
        self._r.close()
