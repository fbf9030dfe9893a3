"""Sawyer MuJoCo backend: the contract in-process, in lockstep, on the same vendor
controller the emulator runs (:mod:`.controller`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from hilstack.drivers.base import Health, Observation
from hilstack.drivers.sawyer.config import JOINTS, SawyerParams, sawyer_spec
from hilstack.drivers.sawyer.ros import POSITION_MODE, VELOCITY_MODE
from hilstack.sim_backends.base import LockstepSim
from hilstack.sim_backends.sawyer.controller import SawyerArm


class SawyerSim(LockstepSim):
    """``params.sim.cameras: true`` adds ``extras["image"]``: a fixed camera (metaworld's
    ``corner``) and the wrist camera (``gripperPOV``), ``params.sim.camera_px`` square each,
    side by side (64×128 RGB by default), rendered at every read (shadows off)."""
    params_type = SawyerParams

    CAMERAS = ("corner", "gripperPOV")

    def __init__(self, params: SawyerParams | None = None, source: str | None = None):
        super().__init__()
        self.params = params or SawyerParams()
        #: the controller holds position (after a stop) rather than following a velocity
        self._position_hold = False
        self.source = source
        self.spec = sawyer_spec(self.params)
        self.arm: SawyerArm | None = None
        self._seq = 0
        self._renderer = None

    @property
    def sim_time_s(self) -> float:
        return 0.0 if self.arm is None else self.arm.time_s

    def _on_configure(self) -> None:
        self.arm = SawyerArm()

    def _on_cleanup(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self.arm = None

    def _image(self) -> np.ndarray:
        if self._renderer is None:
            from hilstack.sim_backends.rendering import OffscreenRenderer

            px = int(self.params.sim.get("camera_px", 64))
            self._renderer = OffscreenRenderer(self.arm.model, px, px)
        return np.concatenate([self._renderer.render(self.arm.data, c) for c in self.CAMERAS], axis=1)

    def _advance(self, duration_s: float) -> None:
        self.arm.advance(duration_s)

    def reset(self, **kwargs: Any) -> None:
        self.arm.reset()

    def _read(self) -> Observation:
        a = self.arm
        s = np.concatenate([a.q(), a.qd(), a.effort()])
        finite = bool(np.all(np.isfinite(s)))
        self._seq += 1
        extras: dict[str, Any] = {"ee_pos_m": a.ee_pos().tolist()}
        if self.params.sim.get("cameras"):
            extras["image"] = self._image()
        return Observation(t_s=a.time_s, state=s, seq=self._seq, ok=finite, flags={"stale_telemetry": False,
                           "nonfinite_input": not finite}, extras=extras)

    def _hold_command(self, obs: Observation) -> np.ndarray:
        if self._position_hold:  # after a stop the controller holds position: zero velocity
            return np.zeros(self.spec.action.dim)
        return np.clip(obs.state[7:14], self.spec.action.low, self.spec.action.high)

    def _on_activate(self) -> None:
        self.arm.command(VELOCITY_MODE, list(JOINTS), self._held, self.arm.time_s)

    def _write(self, action: np.ndarray) -> None:
        self.arm.command(VELOCITY_MODE, list(JOINTS), action, self.arm.time_s)
        self._position_hold = False

    def _stop(self) -> None:
        if self.arm is None:
            return
        self.arm.command(VELOCITY_MODE, list(JOINTS), np.zeros(7), self.arm.time_s)
        self.arm.command(POSITION_MODE, list(JOINTS), self.arm.q(), self.arm.time_s)
        self._position_hold = True

    def _health(self) -> Health:
        return Health(ok=self.arm is not None, extra={"backend": "sim", "command_timeouts":
                                                      None if self.arm is None else self.arm.timeouts})
