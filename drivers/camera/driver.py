"""The stereo camera tracker's real backend: two UVC cameras (OpenCV), a tracker, the contract.

``read()`` takes the newest left/right pair (paired by arrival time within
``max_skew_s``, :mod:`hilstack.drivers.camera.uvc`), tracks the balls, and returns the state of
:mod:`hilstack.drivers.camera.config` with ``extras["image"]`` (left | right, RGB) and
``extras["image_encoded"]`` (``params.encoding`` bytes, what the bus and recordings
carry). It never blocks: with no new pair it reports the last one and its age
(``stale_image`` past ``stale_after_s``; past ``fail_after_s`` the error path). The
calibration file is required (``params.calibration``): a real pair has no truth.
"""

from __future__ import annotations

import time

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import Driver, Health, LinkError, Observation, require_device
from hilstack.drivers.camera.config import CameraParams, camera_spec
from hilstack.drivers.camera.pipeline import CameraPipeline, FramePair
from hilstack.perception.geometry import StereoCalibration


class StereoCameraDriver(Driver):
    params_type = CameraParams

    def __init__(self, params: CameraParams | None = None, backend: str = "real", source: str | None = None):
        super().__init__()
        self.params = params or CameraParams()
        self.backend = backend
        self.source = source
        self.spec = camera_spec(self.params)
        self.pipeline: CameraPipeline | None = None
        self.uvc = None
        self._seq = 0

    def _on_configure(self) -> None:
        from hilstack.drivers.camera.uvc import StereoUvc

        p = self.params
        for fld in ("left_device", "right_device"):
            dev = getattr(p, fld)
            if isinstance(dev, str):
                require_device(dev, self.source, f"params.{fld}", "the camera")
        if p.calibration is None:
            raise ConfigError(self.source, [("params.calibration", "a real stereo pair needs its calibration file "
                                                                   "(hil calibrate camera)")])
        try:
            cal = StereoCalibration.load(p.calibration, p.camera_id)
            self.pipeline = CameraPipeline(p, cal)
        except ValueError as e:
            raise ConfigError(self.source, [("params.calibration", str(e))]) from None
        self.pipeline.start(time.monotonic())
        self.uvc = StereoUvc(p.left_device, p.right_device, p.width_px, p.height_px, p.fps, p.max_skew_s)

    def _on_cleanup(self) -> None:
        if self.uvc is not None:
            self.uvc.close()
            self.uvc = None

    def _poll(self) -> float:
        try:
            pr = self.uvc.latest_pair()
        except LinkError as e:  # a stream ended or a camera vanished: the error path, then raise
            self.fail_link(e)
        if pr is not None:
            a, b = pr
            self.pipeline.feed(FramePair(a.image, b.image, a.t_s, b.t_s))
        now = time.monotonic()
        gone = self.pipeline.inputs.expired(now)
        if gone is not None:
            self.fail_link(f"camera {self.params.camera_id}: no frame pair for more than {gone.fail_after_s} s "
                           f"(max skew {self.params.max_skew_s} s; {self.uvc.skewed} pairs refused as skewed)")
        return now

    def _read(self) -> Observation:
        self._seq += 1
        now = self._poll()
        return self.pipeline.observation(now, self._seq)

    def _write(self, action) -> None:
        pass  # a sensor: the base class already refused anything but the empty action

    def _stop(self) -> None:
        pass

    def _health(self) -> Health:
        now = time.monotonic()
        ok = self.pipeline is not None and not self.pipeline.inputs["image"].stale(now)
        u = self.uvc
        return Health(
            ok=ok,
            frames_received=0 if u is None else u.left.received + u.right.received,
            corrupt_frames=0 if u is None else u.left.bad_frames + u.right.bad_frames,
            dropped_frames=0 if u is None else u.skewed,
            latency_s=None if self.pipeline is None else self.pipeline.inputs["image"].age_s(now),
            last_error=self.last_error,
            extra={**({} if self.pipeline is None else self.pipeline.ages(now)),
                   **({} if u is None else {"missed_frames": u.left.missed_frames + u.right.missed_frames})},
        )
