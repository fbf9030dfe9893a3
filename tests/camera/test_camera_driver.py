"""The stereo camera behind the contract: sim backend, real backend (OpenCV VideoCapture on
video files: the same code a UVC device runs), pairing, images on the bus and in MCAP."""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from hilstack.bus import keys
from hilstack.bus.recording import McapLog, foxglove_image_topic, read_messages
from hilstack.bus.schemas import Image
from hilstack.drivers.base import CommandError, LinkError
from hilstack.drivers.camera.config import STATE_NAMES
from hilstack.drivers.camera.pipeline import encode_image
from hilstack.drivers.camera.uvc import Frame, pair_frames
from hilstack.drivers.registry import make_driver


def test_sim_camera_is_a_sensor_that_tracks_the_balls():
    d = make_driver("camera", backend="sim")
    assert d.spec.action.dim == 0 and d.spec.state.names == STATE_NAMES
    with d:
        for _ in range(3):
            obs = d.read()
            d.tick()
        assert obs.ok and not obs.flag("stale_image") and not obs.flag("stale_objects")
        err_mm = 1000 * np.linalg.norm(obs.state[:6].reshape(2, 3) - obs.extras["balls_true_m"], axis=1)
        assert np.all(err_mm < 10), err_mm
        assert np.all(obs.state[6:] > 0.5)
        img = obs.extras["image"]
        assert img.shape == (180, 560, 3) and img.dtype == np.uint8
        enc, data = obs.extras["image_encoded"]
        assert enc == "jpeg" and data[:2] == b"\xff\xd8"  # a JPEG file
        assert d.write([]).shape == (0,)
        with pytest.raises(CommandError):
            d.write([0.0])


def test_pairing_takes_the_newest_left_and_refuses_skew():
    img = np.zeros((1, 1, 3), np.uint8)
    left = [Frame(1.00, 1, img), Frame(1.033, 2, img)]
    right = [Frame(0.99, 7, img), Frame(1.031, 8, img), Frame(1.06, 9, img)]
    a, b = pair_frames(left, right, max_skew_s=0.005)
    assert (a.seq, b.seq) == (2, 8)
    assert pair_frames(left, [Frame(1.02, 1, img)], max_skew_s=0.005) is None
    assert pair_frames([], right, 0.1) is None


def _video(path, frames, fps=30.0):
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()


def test_real_backend_reads_two_streams_through_opencv(tmp_path, scene):
    """The real backend on two video files (cv2.VideoCapture, the UVC code path): the pair
    is tracked with the calibration file; a missing device is a one-line LinkError."""
    from hilstack.sim_backends.shadow_hand.cameras import baoding_motion

    lefts, rights = [], []
    for b in baoding_motion(np.arange(0, 1.5, 1 / 30)):
        scene.set_balls(b)
        left, right = scene.render()
        lefts.append(left)
        rights.append(right)
    _video(tmp_path / "l.avi", lefts)
    _video(tmp_path / "r.avi", rights)
    scene.truth().save(tmp_path / "cal")
    d = make_driver("camera", backend="real", left_device=str(tmp_path / "l.avi"),
                    right_device=str(tmp_path / "r.avi"), calibration=str(tmp_path / "cal"), max_skew_s=0.02)
    with d:
        obs = None
        for _ in range(200):
            obs = d.read()
            if obs.ok:
                break
            d.tick()
        assert obs is not None and obs.ok, obs.flags
        # somewhere on the circle about the palm centre (MJPG costs a little accuracy)
        pos = obs.state[:6].reshape(2, 3)
        c = np.array([0.0, -0.02, 0.34])
        assert np.all(np.abs(np.linalg.norm((pos - c)[:, [0, 2]], axis=1) - 0.025) < 0.006), pos
        assert obs.extras["skew_s"] <= 0.02
        assert d.health().frames_received > 0

    # a device that exists but does not open is a link error (exit 1); one that does not exist is
    # a config error naming the field (exit 2), as a missing serial port on every robot
    (tmp_path / "junk.avi").write_bytes(b"not a video")
    bad = make_driver("camera", backend="real", left_device=str(tmp_path / "junk.avi"),
                      right_device=str(tmp_path / "r.avi"), calibration=str(tmp_path / "cal"))
    with pytest.raises(LinkError, match="camera left: cannot open device .*junk.avi") as e:
        bad.configure()
    assert "\n" not in str(e.value)
    from hilstack.configs.schema import ConfigError

    gone = make_driver("camera", backend="real", left_device=str(tmp_path / "nope.avi"),
                       right_device=str(tmp_path / "r.avi"), calibration=str(tmp_path / "cal"))
    with pytest.raises(ConfigError, match="params.left_device: .*nope.avi does not exist"):
        gone.configure()


def test_real_backend_without_calibration_is_a_config_error():
    from hilstack.configs.schema import ConfigError

    d = make_driver("camera", backend="real")
    with pytest.raises(ConfigError, match="params.calibration"):
        d.configure()


def test_images_are_recorded_as_foxglove_compressed_images(tmp_path, scene):
    """JPEG/PNG hil.Image → a foxglove.CompressedImage channel (protobuf, decoded with the
    schema stored in the file), the bytes unchanged; rerun's MCAP importer reads it as an
    EncodedImage and its checker passes; our reader still gets the hil.Image back."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    left, right = scene.render()
    both = np.concatenate([left, right], axis=1)
    png = encode_image(both, "png")
    path = tmp_path / "cam.mcap"
    topic = keys.image("rig", "camera")
    with McapLog(path) as log:
        for i in range(3):
            log.write(topic, Image(camera="camera", t_s=0.1 * i, width=560, height=180, encoding="png", data=png,
                                   seq=i + 1, stamp_s=1000.0 + 0.1 * i))
    got = []
    with open(path, "rb") as f:
        dec = DecoderFactory()
        for schema, channel, message in make_reader(f).iter_messages():
            if schema.name == "foxglove.CompressedImage":
                assert channel.topic == foxglove_image_topic("rig", "camera")
                got.append(dec.decoder_for(channel.message_encoding, schema)(message.data))
    assert len(got) == 3 and got[0].format == "png" and got[0].frame_id == "camera"
    back = cv2.cvtColor(cv2.imdecode(np.frombuffer(got[0].data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(back, both)  # PNG: lossless, nothing re-encoded on the way
    assert [m.msg.data for m in read_messages(path).messages] == [png] * 3

    import rerun as rr

    comps = set()
    for c in rr.chunk.McapReader(str(path)).stream().to_chunks():
        if "foxglove/camera/image" in str(c.entity_path):
            comps |= set(c.to_record_batch().schema.names)
    assert "EncodedImage:blob" in comps and "EncodedImage:media_type" in comps
    p = subprocess.run([sys.executable, "-m", "rerun", "mcap", "check", "--full", str(path)], capture_output=True,
                       text=True, timeout=120, env={**os.environ, "RERUN_ANALYTICS": "off"})
    assert p.returncode == 0 and "foxglove/camera/image" in p.stdout, p.stdout + p.stderr
    lines = [ln for ln in p.stdout.splitlines() if "/hil/" in ln]
    assert lines and all(ln.split()[0] == "ok" for ln in lines), p.stdout


def test_stereo_uvc_hands_out_each_pair_once_and_counts_unpaired_left_frames_once():
    from types import SimpleNamespace

    from hilstack.drivers.camera.uvc import StereoUvc

    img = np.zeros((1, 1, 3), np.uint8)
    s = StereoUvc.__new__(StereoUvc)  # the pairing state only; grabbers stand in below
    s.max_skew_s, s.skewed, s._refused, s._last = 0.005, 0, None, None
    left = [Frame(1.0, 1, img)]
    right = [Frame(1.001, 1, img)]
    s.left = SimpleNamespace(error=None, frames=lambda: list(left))
    s.right = SimpleNamespace(error=None, frames=lambda: list(right))
    assert s.latest_pair() is not None and s.latest_pair() is None  # nothing new: no repeat
    left.append(Frame(1.1, 2, img))  # its partner has not come yet (or never will)
    assert s.latest_pair() is None and s.latest_pair() is None
    assert s.skewed == 1
    s.right.error = "camera right: stream from 1 ended"
    with pytest.raises(LinkError, match="stream from 1 ended"):
        s.latest_pair()


def test_a_stream_that_ends_takes_the_error_path_with_one_line(tmp_path, scene):
    scene.set_balls(np.array([[0.022, -0.02, 0.34], [-0.022, -0.02, 0.34]]))
    left, right = scene.render()
    _video(tmp_path / "l.avi", [left] * 3)
    _video(tmp_path / "r.avi", [right] * 3)
    scene.truth().save(tmp_path / "cal")
    d = make_driver("camera", backend="real", left_device=str(tmp_path / "l.avi"),
                    right_device=str(tmp_path / "r.avi"), calibration=str(tmp_path / "cal"), max_skew_s=0.05)
    d.configure()
    with pytest.raises(LinkError, match=r"camera (left|right): stream from .* ended") as e:
        for _ in range(400):  # 3 frames at 30 fps, then the file ends
            d.read()
            d.tick()
    assert "\n" not in str(e.value)
    assert d.lifecycle.value == "unconfigured" and d.last_error  # the error path ran
