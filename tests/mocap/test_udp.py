"""The UDP pose stream on loopback: round trip, corrupt packets, dropouts; NatNet conversion."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hilstack.drivers.mocap.base import PoseSource
from hilstack.drivers.mocap.natnet_client import NatNetPoseSource, natnet_to_world
from hilstack.drivers.mocap.udp import PACKET_SIZE, PoseStreamServer, UdpPoseClient, decode_pose, encode_pose


@pytest.fixture
def link():
    client = UdpPoseClient("127.0.0.1", 0)
    server = PoseStreamServer("127.0.0.1", client.port, body_id=3)
    yield server, client
    server.close()
    client.close()


def test_encode_decode_round_trip():
    data = encode_pose(7, 12.5, 3, (1.0, -2.0, 0.03), (1.0, 0.0, 0.0, 0.0))
    assert len(data) == PACKET_SIZE == 52
    seq, s = decode_pose(data)
    assert seq == 7 and s.t_s == 12.5 and s.frame_id == "3"
    np.testing.assert_allclose(s.position_m, (1.0, -2.0, 0.03), atol=1e-6)
    np.testing.assert_allclose(s.quaternion_wxyz, (1, 0, 0, 0))
    flipped = bytearray(data)
    flipped[20] ^= 0x01  # one bit of x: the CRC catches it
    assert decode_pose(bytes(flipped)) is None
    assert decode_pose(data[:-1]) is None
    assert decode_pose(b"XXXX" + data[4:]) is None


def test_udp_round_trip(link):
    server, client = link
    assert isinstance(client, PoseSource)
    assert client.latest() is None
    q = np.array([np.cos(0.3), 0.0, 0.0, np.sin(0.3)])
    for k in range(5):
        server.send(0.1 * k, (0.1 * k, 0.2, 0.03), q)
    s = client.wait_for(4, timeout_s=2.0)
    assert s is not None and s.seq == 4
    np.testing.assert_allclose(s.position_m, (0.4, 0.2, 0.03), atol=1e-6)
    np.testing.assert_allclose(s.quaternion_wxyz, q, atol=1e-6)
    assert s.frame_id == "3" and s.t_s == pytest.approx(0.4)
    assert client.stats() == {"received": 5, "corrupt": 0, "dropped": 0, "stale": 0}


def test_corrupt_packet_counted_and_ignored(link):
    server, client = link
    server.send(1.0, (1, 2, 3), (1, 0, 0, 0))
    assert client.wait_for(0)
    server.send_raw(b"garbage")
    good = bytearray(encode_pose(1, 2.0, 3, (9, 9, 9), (1, 0, 0, 0)))
    good[-1] ^= 0xFF  # bad CRC
    server.send_raw(bytes(good))
    assert client.wait_counts(3, timeout_s=2.0)
    assert client.corrupt == 2
    np.testing.assert_allclose(client.latest().position_m, (1, 2, 3))


def test_dropout_counted_as_sequence_gap(link):
    server, client = link
    server.send(0.0, (0, 0, 0), (1, 0, 0, 0))
    server.skip(3)  # three samples lost on the way
    server.send(0.4, (0.4, 0, 0), (1, 0, 0, 0))
    s = client.wait_for(4, timeout_s=2.0)
    assert s is not None and s.t_s == pytest.approx(0.4)
    assert client.dropped == 3 and client.received == 2
    # a late, reordered packet is not taken as the latest pose
    server.send_raw(encode_pose(2, 0.2, 3, (0.2, 0, 0), (1, 0, 0, 0)))
    assert client.wait_counts(3, timeout_s=2.0)
    assert client.stale == 1 and client.latest().t_s == pytest.approx(0.4)


def test_natnet_y_up_conversion_and_frame_callback():
    # a body 1 m "up" in Motive's y-up frame is 1 m up (z) in the world frame
    p, q = natnet_to_world((0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0), up_axis="y")
    np.testing.assert_allclose(p, (0, 0, 1), atol=1e-12)
    # identity orientation in y-up: the body's y axis (Motive up) maps to world z
    import mujoco

    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, q)
    np.testing.assert_allclose(mat.reshape(3, 3) @ (0, 1, 0), (0, 0, 1), atol=1e-12)
    p, q = natnet_to_world((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), up_axis="z")
    np.testing.assert_allclose(p, (1, 2, 3))
    np.testing.assert_allclose(q, (1, 0, 0, 0))

    src = NatNetPoseSource(rigid_body_id=2, up_axis="z")
    rb = SimpleNamespace(id_num=2, pos=(0.5, 0.0, 0.02), rot=(0.0, 0.0, 0.0, 1.0), tracking_valid=True)
    frame = lambda n, rbs: SimpleNamespace(  # noqa: E731
        prefix=SimpleNamespace(frame_number=n), suffix=SimpleNamespace(timestamp=n / 120), rigid_bodies=rbs
    )
    src._on_frame(frame(10, [SimpleNamespace(id_num=1, pos=(9, 9, 9), rot=(0, 0, 0, 1), tracking_valid=True), rb]))
    s = src.latest()
    assert s.frame_id == "2" and s.t_s == pytest.approx(10 / 120)
    np.testing.assert_allclose(s.position_m, (0.5, 0.0, 0.02))
    src._on_frame(frame(13, [SimpleNamespace(**{**rb.__dict__, "tracking_valid": False})]))
    assert src.dropped == 2 and src.untracked == 1 and src.latest().t_s == pytest.approx(10 / 120)
