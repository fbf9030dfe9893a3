"""The trackers: triangulation against truth, the spatial softmax, occlusion and loss of a
ball (low confidence → stale in the camera and in the hand backend)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.drivers.camera.config import CameraParams
from hilstack.drivers.camera.pipeline import CameraPipeline, FramePair
from hilstack.perception.keypoint_net import spatial_soft_argmax
from hilstack.perception.tracker import ColorTracker, LearnedTracker, make_tracker

CENTER = np.array([0.0, -0.02, 0.34])  # palm centre, hand frame [m]


def test_spatial_soft_argmax_returns_the_peak_in_full_resolution_pixels():
    h = torch.full((1, 2, 45, 70), -50.0)
    h[0, 0, 10, 30] = 50.0  # row 10, column 30
    h[0, 1, 40, 2] = 50.0
    uv = spatial_soft_argmax(h, stride=4)[0].numpy()
    assert uv[0] == pytest.approx([30 * 4 + 1.5, 10 * 4 + 1.5], abs=1e-4)  # (u, v): column then row
    assert uv[1] == pytest.approx([2 * 4 + 1.5, 40 * 4 + 1.5], abs=1e-4)
    h2 = torch.full((1, 1, 4, 4), -50.0)
    h2[0, 0, 1, 1] = h2[0, 0, 1, 2] = 50.0  # two equal peaks: the mean between them
    assert spatial_soft_argmax(h2, stride=4)[0, 0].numpy() == pytest.approx([7.5, 5.5], abs=1e-4)


def _frames(scene, balls_list, wiggle_rad=0.0):
    out = []
    for k, b in enumerate(balls_list):
        q = scene.hold_q.copy()
        q[2:] += wiggle_rad * np.sin(k + np.arange(q.size - 2))
        scene.set_hand(q)
        scene.set_balls(b)
        out.append(scene.render())
    return out


@pytest.fixture(scope="module")
def motion(scene):
    from hilstack.sim_backends.shadow_hand.cameras import baoding_motion

    balls = baoding_motion(np.arange(0.0, 5.0, 0.5))
    return balls, _frames(scene, balls)


@pytest.mark.parametrize("kind", ["color", "learned"])
def test_tracker_triangulates_the_balls_against_truth(kind, scene, motion):
    tr = make_tracker(kind, scene.truth())
    balls, frames = motion
    err = []
    for b, (left, right) in zip(balls, frames, strict=True):
        r = tr.track(left, right)
        assert np.all(r.confidence > 0.5), r.confidence
        err.append(1e3 * np.linalg.norm(r.positions_m - b, axis=1))
    err = np.array(err)
    bound = {"color": 5.0, "learned": 6.0}[kind]  # mean [mm]; docs/camera.md has the bench figures
    assert err.mean() < bound and err.max() < 3 * bound, err


@pytest.mark.parametrize("kind", ["color", "learned"])
def test_hidden_or_lost_ball_gets_low_confidence(kind, scene):
    tr = make_tracker(kind, scene.truth())
    hidden = np.array([CENTER + [0.02, 0.05, 0.0], CENTER - [0.022, 0.0, 0.0]])  # ball 0 under the palm
    lost = np.array([CENTER - [0.022, 0.0, 0.0], CENTER + [0.5, 0.0, 0.0]])  # ball 1 far out of view
    (l1, r1), (l2, r2) = _frames(scene, [hidden, lost])
    a = tr.track(l1, r1)
    assert a.confidence[0] < 0.3 and a.confidence[1] > 0.5, a.confidence
    b = tr.track(l2, r2)
    assert b.confidence[1] < 0.3 and b.confidence[0] > 0.5, b.confidence


def test_a_hidden_ball_goes_stale_after_the_deadline_and_recovers(scene):
    """The camera pipeline: confident balls refresh ``objects``; hidden for longer than
    ``stale_after_s`` → ``stale_objects`` (the reading stays ok: the frames are fresh);
    the last confident position is kept and its confidence reported as it is."""
    p = CameraParams(stale_after_s=0.15, min_confidence=0.5)
    pipe = CameraPipeline(p, scene.truth())
    pipe.start(0.0)
    seen = np.array([CENTER + [0.022, 0, 0], CENTER - [0.022, 0, 0]])
    hidden = np.array([CENTER + [0.02, 0.05, 0.0], CENTER - [0.022, 0, 0]])
    (ls, rs), (lh, rh) = _frames(scene, [seen, hidden])
    flags = []
    for k, (left, right) in enumerate([(ls, rs), (lh, rh), (lh, rh), (lh, rh), (ls, rs)]):
        t = 0.1 * k
        pipe.feed(FramePair(left, right, t, t))
        obs = pipe.observation(t, k + 1)
        assert obs.ok and not obs.flag("stale_image")
        flags.append(obs.flag("stale_objects"))
        if k == 2:
            assert obs.state[6] < 0.3
            assert np.linalg.norm(obs.state[:3] - seen[0]) < 0.006  # last confident position kept
    assert flags == [False, False, True, True, False]


@pytest.mark.parametrize("kind", ["color", "learned"])
def test_hand_sim_takes_its_balls_from_the_tracker_and_flags_a_lost_ball(kind):
    """The hand rig with ``params.sim.tracker`` (configs/rigs/hand_tracker_sim.yaml): balls_m
    is the tracker's estimate (close to the truth beside it); a ball teleported out of view
    goes stale within the deadline."""
    from hilstack.configs.schema import load_rig, rig_robot_config
    from hilstack.drivers.registry import make_driver

    cfg = rig_robot_config(load_rig("hand_tracker_sim"), "hand")
    assert cfg.params["sim"]["tracker"]["kind"] == "learned"
    d = make_driver(cfg, sim={"tracker": {**cfg.params["sim"]["tracker"], "kind": kind}})
    with d:
        obs = d.read()
        assert not obs.flag("stale_objects") and obs.ok
        err = np.linalg.norm(obs.extras["balls_m"] - obs.extras["balls_true_m"], axis=1)
        assert np.all(err < 0.01), err
        assert obs.extras["image"].shape == (180, 560, 3) and obs.extras["image_encoded"][0] == "jpeg"
        adr = d.hand.ball_qpos_adr[1]
        flags = []
        for _ in range(3):
            d.data.qpos[adr:adr + 3] = (5.0, 5.0, -1.0)
            d.data.qvel[d.hand.ball_dof_adr[1]:d.hand.ball_dof_adr[1] + 6] = 0.0
            d.tick()
            obs = d.read()
            flags.append(obs.flag("stale_objects"))
        assert flags == [False, True, True] and obs.extras["ball_confidence"][1] < 0.3


def test_unknown_tracker_and_bad_weights_are_one_line_errors(tmp_path, scene):
    with pytest.raises(ValueError, match="unknown tracker 'sift': expected 'color' or 'learned'"):
        make_tracker("sift", scene.truth())
    bad = tmp_path / "w.pt"
    bad.write_bytes(b"not torch")
    with pytest.raises(ValueError, match="w.pt: not keypoint-net weights"):
        LearnedTracker(scene.truth(), bad)
    assert isinstance(make_tracker("color", scene.truth()), ColorTracker)


def test_two_estimates_on_one_ball_leave_only_the_more_confident():
    from hilstack.perception.tracker import _exclusive

    pos = np.array([[0.0, 0.0, 0.3], [0.01, 0.0, 0.3]])  # 1 cm apart: one ball, not two
    assert list(_exclusive(pos, np.array([0.9, 0.8]))) == [0.9, 0.0]
    apart = np.array([[0.0, 0.0, 0.3], [0.045, 0.0, 0.3]])
    assert list(_exclusive(apart, np.array([0.9, 0.8]))) == [0.9, 0.8]


def test_a_malformed_frame_pair_is_refused_and_flagged(scene):
    pipe = CameraPipeline(CameraParams(), scene.truth())
    pipe.start(0.0)
    small = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(ValueError, match=r"frame pair of shapes \(10, 10, 3\)/\(10, 10, 3\), expected \(180, 280, 3\)"):
        pipe.feed(FramePair(small, small, 0.0, 0.0))
    obs = pipe.observation(0.0, 1)
    assert not obs.ok and obs.flag("nonfinite_input") and obs.flag("stale_image")
    with pytest.raises(ValueError, match="calibration of stereo0 is for 280x180 images, the cameras give 640x480"):
        CameraPipeline(CameraParams(width_px=640, height_px=480), scene.truth())
