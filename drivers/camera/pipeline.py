"""Frames → tracker → observation: the part every camera backend shares.

Freshness (hilstack.drivers.base): the frame pair is the input ``image`` (``stale_image``; stale
makes ``ok`` False; past ``fail_after_s`` the real backend takes the error path); the
balls are ``objects`` (``stale_objects``: refreshed only by a pair in which both balls
have at least ``min_confidence``), a flag that leaves the reading ``ok``, as the hand's
own ball inputs do.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hilstack.drivers.base import Flag, Freshness, Inputs, Observation
from hilstack.drivers.camera.config import CameraParams
from hilstack.perception.geometry import StereoCalibration
from hilstack.perception.tracker import TrackResult, make_tracker


@dataclass
class FramePair:
    """Two RGB images (H, W, 3) uint8 and their capture times [s, backend clock]."""

    left: np.ndarray
    right: np.ndarray
    t_left_s: float
    t_right_s: float

    @property
    def t_s(self) -> float:
        return max(self.t_left_s, self.t_right_s)


def encode_image(img_rgb: np.ndarray, encoding: str, jpeg_quality: int = 90) -> bytes:
    """JPEG or PNG bytes of an RGB image (OpenCV's codecs)."""
    ext, args = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]) if encoding == "jpeg" else (".png", [])
    ok, buf = cv2.imencode(ext, cv2.cvtColor(img_rgb, cv2.COLOR_RGB2BGR), args)
    if not ok:
        raise ValueError(f"OpenCV could not encode a {img_rgb.shape} image as {encoding}")
    return buf.tobytes()


class CameraPipeline:
    def __init__(self, params: CameraParams, calibration: StereoCalibration):
        self.params = p = params
        if (calibration.width_px, calibration.height_px) != (p.width_px, p.height_px):
            raise ValueError(f"calibration of {calibration.camera_id} is for {calibration.width_px}x"
                             f"{calibration.height_px} images, the cameras give {p.width_px}x{p.height_px}")
        self.cal = calibration
        self.tracker = make_tracker(p.tracker, calibration, p.weights)
        self.inputs = Inputs(Freshness("image", p.stale_after_s, Flag.STALE_IMAGE, p.fail_after_s))
        self.objects = Freshness("objects", p.stale_after_s, Flag.STALE_OBJECTS)
        self.last: TrackResult | None = None
        self._pair: FramePair | None = None
        self._positions = np.zeros((2, 3))
        self._conf = np.zeros(2)
        self.pairs = 0

    def start(self, now_s: float) -> None:
        self.inputs.start(now_s)
        self.objects.start(now_s)
        self._pair, self.last = None, None
        self._positions, self._conf = np.zeros((2, 3)), np.zeros(2)

    def feed(self, pair: FramePair) -> TrackResult:
        """Track one new pair (time is the pair's capture time)."""
        well_formed = pair.left.shape == pair.right.shape == (self.params.height_px, self.params.width_px, 3)
        # a malformed pair is not used (counted like a non-finite sample) and refreshes nothing
        self.inputs["image"].update(pair.t_s, well_formed)
        if not well_formed:
            raise ValueError(f"frame pair of shapes {pair.left.shape}/{pair.right.shape}, expected "
                             f"({self.params.height_px}, {self.params.width_px}, 3)")
        r = self.tracker.track(pair.left, pair.right)
        good = (r.confidence >= self.params.min_confidence) & np.isfinite(r.positions_m).all(axis=1)
        self._positions[good] = r.positions_m[good]
        self._conf = np.where(np.isfinite(r.confidence), r.confidence, 0.0)
        if good.all():
            self.objects.update(pair.t_s)
        self._pair, self.last = pair, r
        self.pairs += 1
        return r

    def observation(self, now_s: float, seq: int) -> Observation:
        ok, flags = self.inputs.assess(now_s, report=True)
        flags[Flag.STALE_OBJECTS.value] = self.objects.stale(now_s)
        state = np.concatenate([self._positions.ravel(), self._conf])
        extras: dict = {"objects_age_s": self.objects.age_s(now_s)}
        t_s = now_s
        pr = self._pair
        if pr is not None:
            t_s = pr.t_s
            both = np.concatenate([pr.left, pr.right], axis=1)
            extras["image"] = both
            extras["image_encoded"] = (self.params.encoding,
                                       encode_image(both, self.params.encoding, self.params.jpeg_quality))
            extras["skew_s"] = abs(pr.t_left_s - pr.t_right_s)
            if self.last is not None:
                extras["uv_left"], extras["uv_right"] = self.last.uv_left, self.last.uv_right
                extras["inference_s"] = self.last.inference_s
        return Observation(t_s, state, seq, ok=ok, flags=flags, extras=extras)

    def ages(self, now_s: float) -> dict:
        return {**self.inputs.ages(now_s), "objects_age_s": self.objects.age_s(now_s)}
