"""Baoding-ball trackers behind one interface: a stereo pair in, 3-D ball positions in
the hand frame and a confidence per ball out.

* :class:`ColorTracker` (classical baseline): HSV colour segmentation (OpenCV) of each
  ball in each view, the centroid of its largest blob, stereo triangulation.
* :class:`LearnedTracker`: a small dilated CNN (after KeypointNet) with a spatial-softmax
  keypoint head per ball, run on each view, then the same triangulation (the pair's
  disparity gives the depth). Trained on rendered images with domain randomisation
  (:mod:`hilstack.tools.train_keypoints`); weights in ``perception/weights/``.

Confidence (both trackers) is in [0, 1]: how much of the ball each view sees (the blob
area, or the network's visibility head) times how well the two views agree (the
reprojection error of the triangulated point); of two estimates closer than the balls can
be (1.5 radii), the less confident one gets 0. A ball hidden by a finger or out of view
gets a low confidence; its position is NaN when no view saw it at all. Consumers compare
``confidence`` with a threshold (the hand backend's ``min_confidence``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from hilstack.perception.geometry import StereoCalibration, apply, invert

#: ball radius [m] (the thesis' Baoding balls; sim_backends/shadow_hand/model.py builds the same)
BALL_RADIUS_M = 0.02
N_BALLS = 2
WEIGHTS_DIR = Path(__file__).parent / "weights"


@dataclass
class TrackResult:
    """One stereo pair's answer. Positions [m] in the hand frame (NaN: not seen)."""

    positions_m: np.ndarray  # (2, 3)
    confidence: np.ndarray  # (2,) in [0, 1]
    uv_left: np.ndarray  # (2, 2) pixels (NaN: not seen)
    uv_right: np.ndarray
    #: time spent in ``track`` [s]
    inference_s: float = 0.0
    extra: dict = field(default_factory=dict)


@runtime_checkable
class Tracker(Protocol):
    name: str

    def track(self, left: np.ndarray, right: np.ndarray) -> TrackResult:
        """``left``, ``right``: (H, W, 3) uint8 RGB of the calibrated pair."""
        ...


def _fuse(cal: StereoCalibration, uv_l: np.ndarray, uv_r: np.ndarray, seen: np.ndarray,
          reproj_sigma_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate the balls seen in both views: (positions (2, 3), agreement (2,), depth (2,))."""
    pos = np.full((N_BALLS, 3), np.nan)
    agree = np.zeros(N_BALLS)
    depth = np.full(N_BALLS, np.nan)
    both = np.flatnonzero(seen)
    if both.size:
        X, err = cal.triangulate_hand(uv_l[both], uv_r[both])
        z = apply(invert(cal.hand_from_left), X)[:, 2]
        ok = np.isfinite(X).all(axis=1) & (z > 0)
        pos[both[ok]] = X[ok]
        depth[both[ok]] = z[ok]
        agree[both[ok]] = np.exp(-0.5 * (err[ok] / reproj_sigma_px) ** 2)
    return pos, agree, depth


def _exclusive(pos: np.ndarray, conf: np.ndarray, min_separation_m: float = 1.5 * BALL_RADIUS_M) -> np.ndarray:
    """Two rigid balls cannot overlap (centres ≥ 2 radii apart): when both estimates land on
    one ball (a keypoint for a missing ball latching onto the other one), the less
    confident of the two is not a ball. Returns the corrected confidences."""
    conf = conf.copy()
    if np.isfinite(pos).all() and np.linalg.norm(pos[0] - pos[1]) < min_separation_m:
        conf[int(np.argmin(conf))] = 0.0
    return conf


class ColorTracker:
    """HSV thresholds per ball (OpenCV hue 0-180): ball 0 red, ball 1 blue, as rendered.

    ``min_area_px``: smaller blobs are noise (the ball is not seen). ``reproj_sigma_px``:
    the scale of the stereo-agreement term of the confidence."""

    name = "color"

    #: (lower, upper) HSV bounds per ball; red wraps around hue 0, hence two ranges
    HSV_RANGES: tuple[tuple[tuple[tuple[int, int, int], tuple[int, int, int]], ...], ...] = (
        (((0, 120, 60), (10, 255, 255)), ((170, 120, 60), (180, 255, 255))),
        (((100, 120, 60), (130, 255, 255)),),
    )

    def __init__(self, calibration: StereoCalibration, min_area_px: int = 12, reproj_sigma_px: float = 2.0):
        self.cal = calibration
        self.min_area_px = min_area_px
        self.reproj_sigma_px = reproj_sigma_px

    def _blobs(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(centroids (2, 2) px, areas (2,) px) of each ball's largest blob in one view."""
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)
        uv = np.full((N_BALLS, 2), np.nan)
        area = np.zeros(N_BALLS)
        for i, ranges in enumerate(self.HSV_RANGES):
            mask = np.zeros(img.shape[:2], np.uint8)
            for lo, hi in ranges:
                mask |= cv2.inRange(hsv, np.array(lo, np.uint8), np.array(hi, np.uint8))
            # the outer contour's filled area: the specular highlight (unsaturated, so not in
            # the mask) would otherwise pull the centroid away from the ball's centre
            contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            if not contours:
                continue
            c = max(contours, key=cv2.contourArea)
            m = cv2.moments(c)
            if m["m00"] >= self.min_area_px:
                uv[i], area[i] = (m["m10"] / m["m00"], m["m01"] / m["m00"]), m["m00"]
        return uv, area

    def track(self, left: np.ndarray, right: np.ndarray) -> TrackResult:
        t0 = time.perf_counter()
        uv_l, a_l = self._blobs(left)
        uv_r, a_r = self._blobs(right)
        seen = (a_l > 0) & (a_r > 0)
        pos, agree, depth = _fuse(self.cal, uv_l, uv_r, seen, self.reproj_sigma_px)
        # the area a whole ball would cover at the triangulated depth
        f = self.cal.K1[0, 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            full = np.pi * (f * BALL_RADIUS_M / depth) ** 2
            vis = np.where(np.isfinite(full), np.minimum(1.0, np.minimum(a_l, a_r) / full), 0.0)
        conf = _exclusive(pos, np.clip(vis * agree, 0.0, 1.0))
        return TrackResult(pos, conf, uv_l, uv_r, time.perf_counter() - t0,
                           extra={"area_px": np.stack([a_l, a_r], axis=1)})


class LearnedTracker:
    """The CNN keypoint tracker (:class:`hilstack.perception.keypoint_net.KeypointNet`) on both views,
    then stereo triangulation. ``weights``: a ``.pt`` file written by
    ``python -m hilstack.tools.train_keypoints`` (default: the shipped ``perception/weights/keypoint_net.pt``).
    """

    name = "learned"

    def __init__(self, calibration: StereoCalibration, weights: str | Path | None = None,
                 reproj_sigma_px: float = 2.0):
        import torch

        from hilstack.perception.keypoint_net import load_keypoint_net

        self.cal = calibration
        self.reproj_sigma_px = reproj_sigma_px
        path = Path(weights) if weights is not None else WEIGHTS_DIR / "keypoint_net.pt"
        self.net = load_keypoint_net(path)
        self._torch = torch

    def keypoints(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(uv (2 views, 2 balls, 2) px at full resolution, visibility (2 views, 2 balls))."""
        with self._torch.inference_mode():
            uv, vis = self.net.predict(np.stack([left, right]))
        return uv, vis

    def track(self, left: np.ndarray, right: np.ndarray) -> TrackResult:
        t0 = time.perf_counter()
        uv, vis = self.keypoints(left, right)
        seen = (vis[0] > 0.1) & (vis[1] > 0.1)
        pos, agree, _ = _fuse(self.cal, uv[0], uv[1], seen, self.reproj_sigma_px)
        conf = _exclusive(pos, np.clip(np.minimum(vis[0], vis[1]) * agree, 0.0, 1.0))
        uv_l = np.where(seen[:, None], uv[0], np.nan)
        uv_r = np.where(seen[:, None], uv[1], np.nan)
        return TrackResult(pos, conf, uv_l, uv_r, time.perf_counter() - t0, extra={"visibility": vis})


def make_tracker(kind: str, calibration: StereoCalibration, weights: str | Path | None = None) -> Tracker:
    """``kind``: ``color`` or ``learned``; a wrong kind raises ValueError naming the choices."""
    if kind == "color":
        return ColorTracker(calibration)
    if kind == "learned":
        return LearnedTracker(calibration, weights)
    raise ValueError(f"unknown tracker {kind!r}: expected 'color' or 'learned'")
