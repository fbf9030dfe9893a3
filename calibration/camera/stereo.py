"""Checkerboard stereo calibration with OpenCV.

* Corners: ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` on each view. OpenCV may
  number a board's corners from any corner; :func:`detect_corners` orders them rows top to
  bottom, each left to right (the board is held upright, its x axis to the cameras'
  right and y down, as the fixture and the views here have it), so both cameras and the
  board model agree.
* Intrinsics per camera (``cv2.calibrateCamera``), then ``cv2.stereoCalibrate`` refining
  them with the left→right ``R``, ``T`` (OpenCV's ``x_right = R·x_left + T``).
* Hand extrinsics: ``cv2.solvePnP`` of the left view of the board in a known fixture pose
  on the hand (``hand_from_board``): ``hand_from_left = hand_from_board · board_from_left``.

Units: metres, pixels, radians unless a name says otherwise.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from hilstack.perception.geometry import StereoCalibration, homogeneous, invert


class CalibrationError(ValueError):
    """Not enough usable views, unreadable images, a board not found: one line saying which."""


@dataclass(frozen=True)
class BoardModel:
    """Inner corners (columns, rows) and square size [m] (the printed board's geometry)."""

    inner: tuple[int, int]
    square_m: float

    def object_points(self) -> np.ndarray:
        """(N, 3) corners in the board frame, centred, row by row along +x (float32)."""
        cols, rows = self.inner
        i, j = np.meshgrid(np.arange(cols), np.arange(rows))
        x = (i.ravel() - (cols - 1) / 2) * self.square_m
        y = (j.ravel() - (rows - 1) / 2) * self.square_m
        return np.stack([x, y, np.zeros_like(x)], axis=1).astype(np.float32)


_SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)


def detect_corners(img_rgb: np.ndarray, board: BoardModel) -> np.ndarray | None:
    """(N, 2) float32 sub-pixel corners in the board's order, or None if not found."""
    gray = cv2.cvtColor(img_rgb, cv2.COLOR_RGB2GRAY)
    found, c = cv2.findChessboardCorners(gray, board.inner,
                                         flags=cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    c = cv2.cornerSubPix(gray, c, (3, 3), (-1, -1), _SUBPIX).reshape(-1, 2)
    cols, rows = board.inner
    g = c.reshape(rows, cols, 2)
    if g[0, :, 1].mean() > g[-1, :, 1].mean():
        g = g[::-1]  # OpenCV started at the bottom: rows run down the image here
    if g[:, 0, 0].mean() > g[:, -1, 0].mean():
        g = g[:, ::-1]  # and rows run left to right
    return np.ascontiguousarray(g.reshape(-1, 2))


def calibrate_stereo(pairs: list[tuple[np.ndarray, np.ndarray]], board: BoardModel, camera_id: str,
                     min_views: int = 6) -> StereoCalibration:
    """Intrinsics and extrinsics from (left, right) RGB views of the board; views where
    either camera misses the board are skipped (counted in the report)."""
    if not pairs:
        raise CalibrationError("no image pairs to calibrate from")
    h, w = pairs[0][0].shape[:2]
    obj, pl, pr = [], [], []
    for left, right in pairs:
        if left.shape[:2] != (h, w) or right.shape[:2] != (h, w):
            raise CalibrationError(f"image pairs differ in size: {left.shape[:2]}/{right.shape[:2]} vs {(h, w)}")
        a, b = detect_corners(left, board), detect_corners(right, board)
        if a is not None and b is not None:
            obj.append(board.object_points())
            pl.append(a)
            pr.append(b)
    if len(obj) < min_views:
        raise CalibrationError(f"the board ({board.inner[0]}x{board.inner[1]} inner corners) was found in both "
                               f"views of {len(obj)} of {len(pairs)} pairs; need at least {min_views}")
    # rendered or lab cameras of this size: k3 and tangential terms are not identifiable from
    # a few views of a small board; fixing them keeps the fit well posed
    flags = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    # a view that does not fit the others (a board found shifted by a square, a mis-paired
    # shot) is dropped by its stereo per-view error (> 3x the median, at least 1 px), and
    # the fit repeated
    given = len(obj)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-9)
    while True:
        if len(obj) < min_views:
            raise CalibrationError(f"only {len(obj)} of {given} board views fit consistently; need at least "
                                   f"{min_views}")
        _, K1, d1, _, _ = cv2.calibrateCamera(obj, pl, (w, h), None, None, flags=flags)
        _, K2, d2, _, _ = cv2.calibrateCamera(obj, pr, (w, h), None, None, flags=flags)
        rms, K1, d1, K2, d2, R, T, _, _, _, _, per_view = cv2.stereoCalibrateExtended(
            obj, pl, pr, K1, d1, K2, d2, (w, h), np.eye(3), np.zeros((3, 1)),
            flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)
        worst = np.asarray(per_view).reshape(len(obj), -1).max(axis=1)
        keep = worst <= max(1.0, 3 * float(np.median(worst)))
        if keep.all():
            break
        obj, pl, pr = ([x for x, k in zip(v, keep, strict=True) if k] for v in (obj, pl, pr))
    return StereoCalibration(camera_id=camera_id, width_px=w, height_px=h, K1=K1, dist1=d1.ravel(), K2=K2,
                             dist2=d2.ravel(), R=R, T=T.ravel(),
                             report={"rms_px": float(rms), "views_used": len(obj), "views_given": len(pairs),
                                     "views_rejected": given - len(obj),
                                     "board_inner": list(board.inner), "square_m": board.square_m})


def hand_extrinsics(cal: StereoCalibration, left_view: np.ndarray, board: BoardModel,
                    hand_from_board: np.ndarray) -> StereoCalibration:
    """Set ``cal.hand_from_left`` from the left view of the board held in a known pose on
    the hand (``hand_from_board``, 4×4 [m])."""
    c = detect_corners(left_view, board)
    if c is None:
        raise CalibrationError("the board in its fixture pose was not found in the left view")
    ok, rvec, tvec = cv2.solvePnP(board.object_points(), c, cal.K1, cal.dist1, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("solvePnP failed on the fixture view")
    left_from_board = homogeneous(cv2.Rodrigues(rvec)[0], tvec.ravel())
    cal.hand_from_left = np.asarray(hand_from_board, dtype=np.float64) @ invert(left_from_board)
    cal.report["fixture_reprojection_px"] = float(np.sqrt(np.mean(np.sum(
        (cv2.projectPoints(board.object_points(), rvec, tvec, cal.K1, cal.dist1)[0].reshape(-1, 2) - c) ** 2,
        axis=1))))
    return cal


def _rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def compare(est: StereoCalibration, truth: StereoCalibration) -> dict[str, float]:
    """Errors of a calibration against the truth: intrinsics [px], baseline [mm], stereo
    rotation [deg], hand extrinsics translation [mm] and rotation [deg]."""
    out = {}
    for k, (a, b) in {"left": (est.K1, truth.K1), "right": (est.K2, truth.K2)}.items():
        out[f"{k}_focal_error_px"] = float(max(abs(a[0, 0] - b[0, 0]), abs(a[1, 1] - b[1, 1])))
        out[f"{k}_principal_point_error_px"] = float(np.hypot(a[0, 2] - b[0, 2], a[1, 2] - b[1, 2]))
    out["baseline_error_mm"] = 1000 * abs(est.baseline_m - truth.baseline_m)
    out["translation_error_mm"] = 1000 * float(np.linalg.norm(est.T - truth.T))
    out["stereo_rotation_error_deg"] = _rot_deg(est.R @ truth.R.T)
    d = invert(truth.hand_from_left) @ est.hand_from_left
    out["hand_translation_error_mm"] = 1000 * float(np.linalg.norm(d[:3, 3]))
    out["hand_rotation_error_deg"] = _rot_deg(d[:3, :3])
    return out


#: board axes in the hand frame (columns) when it faces the pair upright: x = image right
#: (hand −x), y = image down (hand +z), z = away from the cameras (hand +y)
BOARD_FACING_CAMERAS = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


def random_board_poses(n: int, seed: int, center_in_hand_m=(0.0, -0.02, 0.34)) -> list[np.ndarray]:
    """``n`` board poses (hand_from_board) in front of the pair: printed face towards the
    cameras (board z = hand +y, into the board), x along the image's right (hand −x), centre 3-7 cm above
    the palm centre, tilted up to ±30° about its x and y and ±15° about z."""
    rng = np.random.default_rng(seed)
    base = BOARD_FACING_CAMERAS
    out = []
    for _ in range(n):
        rv = np.radians(rng.uniform([-30, -30, -15], [30, 30, 15]))
        R = base @ cv2.Rodrigues(rv)[0]
        # hand −y is towards the cameras: the board is held 3-8 cm above the palm centre
        c = np.asarray(center_in_hand_m) + rng.uniform([-0.01, -0.07, -0.01], [0.01, -0.03, 0.01])
        out.append(homogeneous(R, c))
    return out


#: the fixture: the board flat 4 cm above the palm centre (clear of the fingers), facing the pair
FIXTURE_HAND_FROM_BOARD = homogeneous(BOARD_FACING_CAMERAS, (0.0, -0.06, 0.34))


def calibrate_rendered(views: int = 15, seed: int = 0, camera_id: str = "stereo0") -> tuple[StereoCalibration,
                                                                                              dict[str, Any]]:
    """The whole procedure on MuJoCo renders of the board (random poses, then the fixture
    pose); returns the calibration and its errors against the exact camera model."""
    from hilstack.sim_backends.shadow_hand.cameras import Checkerboard, HandCameraScene

    cb = Checkerboard()
    board = BoardModel(cb.inner, cb.square_m)
    scene = HandCameraScene(board=cb)
    try:
        scene.set_balls(np.array([[5.0, 5.0, -1.0], [5.0, 6.0, -1.0]]))  # out of the way
        pairs = []
        for pose in random_board_poses(views, seed):
            scene.set_board(pose)
            pairs.append(scene.render())
        cal = calibrate_stereo(pairs, board, camera_id)
        scene.set_board(FIXTURE_HAND_FROM_BOARD)
        hand_extrinsics(cal, scene.render()[0], board, FIXTURE_HAND_FROM_BOARD)
        errors = compare(cal, scene.truth(camera_id))
    finally:
        scene.close()
    cal.report["error_vs_truth"] = errors
    cal.report["source"] = f"{views} rendered board views (seed {seed}) + fixture view"
    return cal, errors


def _read_rgb(path: str) -> np.ndarray:
    bgr = cv2.imread(path, cv2.IMREAD_COLOR)
    if bgr is None:
        raise CalibrationError(f"cannot read image {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def calibrate_from_images(directory: str | Path, board: BoardModel, camera_id: str,
                          fixture: str | None = None, hand_from_board: np.ndarray | None = None) -> StereoCalibration:
    """Real pairs: ``left_*.png`` / ``right_*.png`` (matching suffixes) in ``directory``;
    ``fixture``: the suffix of the pair taken with the board in the fixture pose
    ``hand_from_board`` (without it, ``hand_from_left`` stays the identity)."""
    d = Path(directory)
    lefts = sorted(glob.glob(str(d / "left_*.png")))
    if not lefts:
        raise CalibrationError(f"no left_*.png images in {d}")
    pairs, fixture_pair = [], None
    for lp in lefts:
        suffix = Path(lp).name.removeprefix("left_")
        rp = d / f"right_{suffix}"
        if not rp.exists():
            raise CalibrationError(f"{lp} has no partner {rp}")
        pair = (_read_rgb(lp), _read_rgb(str(rp)))
        if fixture is not None and suffix.removesuffix(".png") == fixture:
            fixture_pair = pair
        else:
            pairs.append(pair)
    cal = calibrate_stereo(pairs, board, camera_id)
    if fixture is not None:
        if fixture_pair is None or hand_from_board is None:
            raise CalibrationError(f"fixture pair left_{fixture}.png and its pose are both needed")
        hand_extrinsics(cal, fixture_pair[0], board, hand_from_board)
    return cal
