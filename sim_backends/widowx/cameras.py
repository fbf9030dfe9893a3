"""The two cameras of the WidowX bench rendered from the MuJoCo world: a fixed camera
and a wrist camera, each ``height × height`` pixels, concatenated side by side into one
``height × 2·height`` RGB image (64×128 in the MELD thesis' cable-insertion task).

Rendering needs an offscreen OpenGL: set ``MUJOCO_GL=egl`` (or ``osmesa``) before
MuJoCo is imported (shared/PLATFORM_NOTES.md). Shadows and reflections are off: at this
size they cost most of the time and add nothing.
"""

from __future__ import annotations

import mujoco
import numpy as np

CAMERAS = ("fixed", "wrist")


class BenchCameras:
    def __init__(self, model: mujoco.MjModel, height_px: int = 64):
        model.vis.quality.shadowsize = 0
        self.height_px = height_px
        self.renderer = mujoco.Renderer(model, height_px, height_px)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """(height, 2·height, 3) uint8: [fixed | wrist]."""
        views = []
        for cam in CAMERAS:
            self.renderer.update_scene(data, camera=cam)
            views.append(self.renderer.render().copy())
        return np.concatenate(views, axis=1)

    def close(self) -> None:
        self.renderer.close()
