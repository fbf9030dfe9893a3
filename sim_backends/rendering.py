"""Offscreen MuJoCo rendering shared by every simulated camera (WidowX bench, hand stereo pair).

Rendering needs an offscreen OpenGL: set ``MUJOCO_GL=egl`` (or ``osmesa``) before MuJoCo is
imported (shared/PLATFORM_NOTES.md). Shadows and reflections are off: at 280×180 they cost
most of the time (~14 fps with them, ~200-500 fps without, measured in PLATFORM_NOTES) and
add nothing a tracker needs.
"""

from __future__ import annotations

import mujoco
import numpy as np


class OffscreenRenderer:
    """``height_px × width_px`` RGB renders of named model cameras, shadows and reflections off."""

    def __init__(self, model: mujoco.MjModel, height_px: int, width_px: int):
        model.vis.quality.shadowsize = 0
        self.height_px, self.width_px = height_px, width_px
        try:
            self.renderer = mujoco.Renderer(model, height_px, width_px)
        except mujoco.FatalError as e:
            raise RuntimeError("offscreen rendering needs an OpenGL platform: set MUJOCO_GL=egl (or osmesa) "
                               f"before MuJoCo is imported ({str(e).splitlines()[0]})") from None
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False

    def render(self, data: mujoco.MjData, camera: str | int) -> np.ndarray:
        """(height, width, 3) uint8 RGB of ``camera`` (name or id) at ``data``'s state."""
        self.renderer.update_scene(data, camera=camera)
        return self.renderer.render().copy()

    def close(self) -> None:
        # OSMesa needs the context released before the interpreter exits (PLATFORM_NOTES)
        self.renderer.close()
