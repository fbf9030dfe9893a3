"""Pinhole stereo geometry: intrinsics, frames, projection, triangulation, the calibration record.

Conventions (OpenCV's throughout):

* camera frame: x right, y down, z forward (optical axis) [m]; pixel (u, v) with the
  centre of the top-left pixel at (0, 0);
* ``K`` is the 3×3 intrinsic matrix [px]; ``dist`` OpenCV's distortion vector (k1 k2 p1 p2 k3);
* the stereo extrinsics ``R``, ``T`` map left-camera coordinates to right-camera ones,
  ``x_right = R·x_left + T`` [m] (what ``cv2.stereoCalibrate`` returns);
* ``hand_from_left`` is the 4×4 homogeneous transform from the left camera frame to the
  hand frame (the hand's mount/base, fixed to the rig) [m].

MuJoCo cameras look along their −z with y up; :func:`cv_from_mujoco_cam` converts.
OpenCV (``cv2.triangulatePoints``, ``cv2.undistortPoints``) does the numerics.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

#: MuJoCo camera axes (x right, y up, z back) → OpenCV camera axes (x right, y down, z forward)
MJ_TO_CV = np.diag([1.0, -1.0, -1.0])


def intrinsics_from_fovy(fovy_deg: float, width_px: int, height_px: int) -> np.ndarray:
    """K of an ideal pinhole with vertical field of view ``fovy_deg`` (MuJoCo's camera
    model: square pixels, principal point at the image centre)."""
    f = 0.5 * height_px / math.tan(math.radians(fovy_deg) / 2)
    return np.array([[f, 0.0, (width_px - 1) / 2], [0.0, f, (height_px - 1) / 2], [0.0, 0.0, 1.0]])


def homogeneous(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return homogeneous(R.T, -R.T @ t)


def apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Transform (N, 3) points [m] by the 4×4 ``T``."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    return p @ T[:3, :3].T + T[:3, 3]


def cv_from_mujoco_cam(cam_xpos: np.ndarray, cam_xmat: np.ndarray) -> np.ndarray:
    """4×4 world_from_cv of a MuJoCo camera (``data.cam_xpos[i]``, ``data.cam_xmat[i]``)."""
    return homogeneous(np.asarray(cam_xmat, dtype=np.float64).reshape(3, 3) @ MJ_TO_CV, cam_xpos)


def project(K: np.ndarray, cam_from_x: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(N, 2) pixel coordinates of (N, 3) points given in frame x (no distortion)."""
    pc = apply(cam_from_x, pts)
    uv = pc @ K.T
    return uv[:, :2] / uv[:, 2:3]


def triangulate(P1: np.ndarray, P2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """(N, 3) points from matched undistorted pixels (N, 2) in two views with 3×4
    projection matrices (DLT, ``cv2.triangulatePoints``), in the frame of the matrices."""
    a = np.asarray(uv1, dtype=np.float64).reshape(-1, 2).T
    b = np.asarray(uv2, dtype=np.float64).reshape(-1, 2).T
    X = cv2.triangulatePoints(P1, P2, a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (X[:3] / X[3]).T


@dataclass
class StereoCalibration:
    """A calibrated stereo pair and its place on the hand (see the module's conventions).

    Written by ``hil calibrate camera`` (calibration/camera) as ``<camera_id>.json``."""

    camera_id: str
    width_px: int
    height_px: int
    K1: np.ndarray
    dist1: np.ndarray
    K2: np.ndarray
    dist2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    hand_from_left: np.ndarray = field(default_factory=lambda: np.eye(4))
    #: ISO 8601 UTC time of the calibration
    timestamp: str = ""
    #: RMS reprojection error of the stereo fit [px], and anything else the procedure reports
    report: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("K1", "dist1", "K2", "dist2", "R", "T", "hand_from_left"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        self.T = self.T.reshape(3)
        if not self.timestamp:
            self.timestamp = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T))

    @property
    def P1(self) -> np.ndarray:
        """Left projection matrix, left camera frame."""
        return self.K1 @ np.hstack([np.eye(3), np.zeros((3, 1))])

    @property
    def P2(self) -> np.ndarray:
        """Right projection matrix, left camera frame."""
        return self.K2 @ np.hstack([self.R, self.T.reshape(3, 1)])

    def undistort(self, uv: np.ndarray, right: bool = False) -> np.ndarray:
        """Pixels (N, 2) with the lens distortion removed (still in pixels of K)."""
        K, d = (self.K2, self.dist2) if right else (self.K1, self.dist1)
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if not np.any(d):
            return uv.reshape(-1, 2)
        return cv2.undistortPoints(uv, K, d, P=K).reshape(-1, 2)

    def triangulate_hand(self, uv_left: np.ndarray, uv_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points in the hand frame (N, 3) [m], reprojection error (N,) [px]) from matched
        raw pixels of the two views."""
        a, b = self.undistort(uv_left), self.undistort(uv_right, right=True)
        X = triangulate(self.P1, self.P2, a, b)
        e1 = np.linalg.norm(project(self.K1, np.eye(4), X) - a, axis=1)
        e2 = np.linalg.norm(project(self.K2, homogeneous(self.R, self.T), X) - b, axis=1)
        return apply(self.hand_from_left, X), np.maximum(e1, e2)

    def to_dict(self) -> dict[str, Any]:
        return {
            "camera_id": self.camera_id, "timestamp": self.timestamp,
            "width_px": self.width_px, "height_px": self.height_px,
            "K1": self.K1.tolist(), "dist1": self.dist1.ravel().tolist(),
            "K2": self.K2.tolist(), "dist2": self.dist2.ravel().tolist(),
            "R": self.R.tolist(), "T_m": self.T.tolist(), "baseline_m": self.baseline_m,
            "hand_from_left": self.hand_from_left.tolist(), "report": self.report,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StereoCalibration:
        return cls(camera_id=d["camera_id"], width_px=int(d["width_px"]), height_px=int(d["height_px"]),
                   K1=d["K1"], dist1=d["dist1"], K2=d["K2"], dist2=d["dist2"], R=d["R"], T=d["T_m"],
                   hand_from_left=d["hand_from_left"], timestamp=d["timestamp"], report=d.get("report", {}))

    def save(self, directory: str | Path) -> Path:
        """Write ``<directory>/<camera_id>.json`` (an older file of the same camera is kept
        as ``<camera_id>.<its timestamp>.json``). Returns the path."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        path = d / f"{self.camera_id}.json"
        if path.exists():
            try:
                old = json.loads(path.read_text()).get("timestamp", "old").replace(":", "")
            except (json.JSONDecodeError, AttributeError):
                old = "unreadable"
            path.rename(d / f"{self.camera_id}.{old}.json")
        path.write_text(json.dumps(self.to_dict(), indent=2))
        return path

    @classmethod
    def load(cls, path: str | Path, camera_id: str | None = None) -> StereoCalibration:
        """From a file, or from a directory plus ``camera_id``. A missing or malformed file
        raises ValueError naming it."""
        p = Path(path)
        if p.is_dir():
            if camera_id is None:
                raise ValueError(f"{p} is a directory: name the camera id to load")
            p = p / f"{camera_id}.json"
        try:
            d = json.loads(p.read_text())
            cal = cls.from_dict(d)
        except FileNotFoundError:
            raise ValueError(f"no camera calibration at {p} (run `hil calibrate camera`)") from None
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{p}: not a camera calibration ({type(e).__name__}: {e})") from None
        if camera_id is not None and cal.camera_id != camera_id:
            raise ValueError(f"{p} calibrates camera {cal.camera_id!r}, not {camera_id!r}")
        return cal
