"""Stereo calibration on rendered checkerboards (truth: the MuJoCo camera model), the
calibration file, the CLI, and triangulation against truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from hilstack.calibration.camera.stereo import (
    FIXTURE_HAND_FROM_BOARD,
    BoardModel,
    CalibrationError,
    calibrate_stereo,
    compare,
    detect_corners,
    hand_extrinsics,
    random_board_poses,
)
from hilstack.perception.geometry import StereoCalibration, apply, homogeneous, invert, project


@pytest.fixture(scope="module")
def board_views():
    """12 rendered board poses, the fixture view and the truth."""
    from hilstack.sim_backends.shadow_hand.cameras import Checkerboard, HandCameraScene

    cb = Checkerboard()
    scene = HandCameraScene(board=cb)
    scene.set_balls(np.array([[5.0, 5.0, -1.0], [5.0, 6.0, -1.0]]))
    pairs = []
    for pose in random_board_poses(12, seed=3):
        scene.set_board(pose)
        pairs.append(scene.render())
    scene.set_board(FIXTURE_HAND_FROM_BOARD)
    fixture = scene.render()
    truth = scene.truth()
    scene.close()
    return BoardModel(cb.inner, cb.square_m), pairs, fixture, truth


def test_stereo_calibration_recovers_the_rendered_pair(board_views):
    board, pairs, fixture, truth = board_views
    cal = calibrate_stereo(pairs, board, "stereo0")
    hand_extrinsics(cal, fixture[0], board, FIXTURE_HAND_FROM_BOARD)
    err = compare(cal, truth)
    assert cal.report["views_used"] >= 8 and cal.report["rms_px"] < 0.5
    assert err["baseline_error_mm"] < 1.0  # of a 120 mm baseline
    assert err["left_focal_error_px"] < 3 and err["right_focal_error_px"] < 3  # f = 217 px
    assert err["stereo_rotation_error_deg"] < 1.5
    assert err["hand_translation_error_mm"] < 8 and err["hand_rotation_error_deg"] < 2


def test_corners_come_in_the_board_order_whatever_opencv_starts_from(board_views):
    """A board seen upside down (image rotated 180°) gives OpenCV's other numbering;
    detect_corners still orders rows top to bottom, left to right."""
    board, pairs, _, _ = board_views
    img = pairs[0][0]
    a = detect_corners(img, board)
    b = detect_corners(np.ascontiguousarray(img[::-1, ::-1]), board)
    cols, rows = board.inner
    for c in (a, b):
        g = c.reshape(rows, cols, 2)
        assert g[0, :, 1].mean() < g[-1, :, 1].mean() and g[:, 0, 0].mean() < g[:, -1, 0].mean()


def test_too_few_views_is_one_clear_error(board_views):
    board, pairs, _, _ = board_views
    blank = [(np.zeros_like(p[0]), np.zeros_like(p[1])) for p in pairs[:7]]
    with pytest.raises(CalibrationError, match="found in both views of 0 of 7 pairs; need at least 6"):
        calibrate_stereo(blank, board, "x")


def test_calibration_file_is_keyed_by_camera_id_with_a_timestamp(tmp_path, board_views):
    truth = board_views[3]
    p1 = truth.save(tmp_path)
    assert p1.name == "stereo0.json"
    d = json.loads(p1.read_text())
    assert d["camera_id"] == "stereo0" and d["timestamp"].startswith("20")
    again = StereoCalibration.from_dict({**d, "timestamp": "2030-01-01T00:00:00+00:00"})
    again.save(tmp_path)  # the older calibration is kept, renamed by its timestamp
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["stereo0.json", f"stereo0.{d['timestamp'].replace(':', '')}.json"])
    back = StereoCalibration.load(tmp_path, "stereo0")
    assert back.timestamp == "2030-01-01T00:00:00+00:00" and np.allclose(back.K1, truth.K1)
    with pytest.raises(ValueError, match="calibrates camera 'stereo0', not 'other'"):
        StereoCalibration.load(tmp_path / "stereo0.json", "other")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="bad.json: not a camera calibration"):
        StereoCalibration.load(tmp_path / "bad.json")


def test_cli_calibrates_from_image_files_without_prompts(tmp_path, board_views):
    """`hil calibrate-camera --images DIR --fixture F --fixture-pose ...`: the real-rig path
    on the rendered pairs written as PNG files; result file and JSON line."""
    from hilstack.tools.cli import app

    board, pairs, fixture, truth = board_views
    for i, (left, right) in enumerate([*pairs, fixture]):
        name = "fix" if i == len(pairs) else f"{i:02d}"
        cv2.imwrite(str(tmp_path / f"left_{name}.png"), cv2.cvtColor(left, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(tmp_path / f"right_{name}.png"), cv2.cvtColor(right, cv2.COLOR_RGB2BGR))
    rv = cv2.Rodrigues(FIXTURE_HAND_FROM_BOARD[:3, :3])[0].ravel()
    pose = ",".join(f"{v:.9f}" for v in [*FIXTURE_HAND_FROM_BOARD[:3, 3], *rv])
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["calibrate-camera", "--images", str(tmp_path), "--inner", "7x4", "--square-mm", "10",
                                 "--fixture", "fix", "--fixture-pose", pose, "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    line = json.loads(r.output.strip().splitlines()[-1])
    assert line["views_used"] >= 8 and abs(line["baseline_mm"] - 120) < 1.0
    cal = StereoCalibration.load(out, "stereo0")
    assert compare(cal, truth)["hand_translation_error_mm"] < 8
    r = CliRunner().invoke(app, ["calibrate-camera", "--images", str(tmp_path), "--fixture-pose", "1,2"])
    assert r.exit_code == 2 and "--fixture-pose must be six numbers" in r.output


def test_triangulation_inverts_projection_exactly(board_views):
    """Points projected with the truth triangulate back to themselves (hand frame)."""
    truth = board_views[3]
    rng = np.random.default_rng(0)
    pts = np.array([0.0, -0.02, 0.34]) + rng.uniform(-0.04, 0.04, (20, 3))
    left_from_hand = invert(truth.hand_from_left)
    uv_l = project(truth.K1, left_from_hand, pts)
    uv_r = project(truth.K2, homogeneous(truth.R, truth.T) @ left_from_hand, pts)
    back, reproj = truth.triangulate_hand(uv_l, uv_r)
    assert np.allclose(back, pts, atol=1e-9) and np.all(reproj < 1e-6)
    # a 1 px disparity error moves the depth by Z²/(f·B) ≈ 2.4 mm at 25 cm: the error budget
    off, _ = truth.triangulate_hand(uv_l + [0.5, 0.0], uv_r - [0.5, 0.0])
    z_err = np.abs(apply(left_from_hand, off)[:, 2] - apply(left_from_hand, pts)[:, 2])
    assert np.all((z_err > 1e-3) & (z_err < 4e-3))


def test_a_view_that_does_not_fit_is_rejected(board_views):
    """A pair whose right image belongs to another board pose (a mis-paired shot) fits
    badly: it is dropped by its per-view error and the result stays right."""
    board, pairs, fixture, truth = board_views
    bad = [*pairs, (pairs[0][0], pairs[5][1])]
    cal = calibrate_stereo(bad, board, "stereo0")
    assert cal.report["views_rejected"] >= 1
    assert compare(cal, truth)["baseline_error_mm"] < 1.0
