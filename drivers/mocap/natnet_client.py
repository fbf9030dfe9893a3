"""OptiTrack NatNet client behind the :class:`~hilstack.drivers.mocap.base.PoseSource` protocol.

Uses the PyPI ``natnet`` package (>= 0.3, pure Python: ``natnet.NatNetClient``), which
speaks NatNet over UDP: a command socket to Motive's command port (1510: connect /
server info / model definitions / keep-alive) and a data socket on the data port (1511,
multicast 239.255.42.99 by default, or unicast) carrying ``NAT_FRAMEOFDATA`` packets.
Each frame's ``rigid_bodies`` hold ``id_num``, ``pos`` (x, y, z [m]) and ``rot`` as
(qx, qy, qz, qw); ``suffix.timestamp`` is Motive's clock [s].

Frames: Motive streams y-up by default; ``up_axis="y"`` converts to the z-up world
frame the rest of the stack uses (x stays, y_world = -z_motive, z_world = y_motive),
``up_axis="z"`` passes poses through (Motive's streaming "Up Axis: Z" setting).

Untested against real hardware here (no Motive server in CI); the conversion and the
callback path are unit-tested by feeding ``_on_frame`` synthetic frames.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Literal

import numpy as np

from hilstack.drivers.mocap.base import PoseSample

# y-up (Motive default) → z-up: a +90° rotation about x
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_Q_Y_UP_TO_Z_UP = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0])  # wxyz


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def natnet_to_world(pos_xyz, rot_xyzw, up_axis: Literal["y", "z"] = "y") -> tuple[np.ndarray, np.ndarray]:
    """NatNet position/quaternion (x, y, z, w order) → world position [m], quaternion wxyz."""
    p = np.asarray(pos_xyz, dtype=float)
    qx, qy, qz, qw = (float(v) for v in rot_xyzw)
    q = np.array([qw, qx, qy, qz])
    if up_axis == "y":
        p = _Y_UP_TO_Z_UP @ p
        q = _qmul(_Q_Y_UP_TO_Z_UP, q)
    # not normalized: a rotation keeps the norm, so a broken quaternion from the wire (zero,
    # garbage) stays visibly broken and the driver rejects it (drivers/mocap/driver.py)
    return p, q


class NatNetPoseSource:
    """Latest pose of one rigid body from a Motive (OptiTrack) server.

    ``NatNetPoseSource(server_ip, local_ip, rigid_body_id=1)``; ``connect()`` waits for
    the server info (raises TimeoutError), then frames arrive on the package's threads;
    ``latest()`` returns the newest pose of ``rigid_body_id`` with tracking valid.
    """

    def __init__(
        self,
        server_ip: str = "127.0.0.1",
        local_ip: str = "127.0.0.1",
        rigid_body_id: int = 1,
        multicast_address: str = "239.255.42.99",
        command_port: int = 1510,
        data_port: int = 1511,
        use_multicast: bool = True,
        up_axis: Literal["y", "z"] = "y",
    ):
        self.rigid_body_id = rigid_body_id
        self.up_axis = up_axis
        self._kw = dict(
            server_ip_address=server_ip,
            local_ip_address=local_ip,
            multicast_address=multicast_address,
            command_port=command_port,
            data_port=data_port,
            use_multicast=use_multicast,
        )
        self._client: Any = None
        self._lock = threading.Lock()
        self._latest: PoseSample | None = None
        self.frames = 0
        self.untracked = 0
        self.dropped = 0
        self._last_frame: int | None = None

    def connect(self, timeout_s: float = 5.0) -> None:
        from hilstack.configs.extras import require

        natnet = require("natnet", "the NatNet mocap source")  # imported here: only this backend needs it

        self._client = natnet.NatNetClient(**self._kw)
        self._client.on_data_frame_received_event.handlers.append(self._on_frame)
        self._client.connect(timeout=timeout_s)
        self._client.run_async()

    def _on_frame(self, frame: Any) -> None:
        """Called on the package's data thread: only copy the pose out (no work here)."""
        now = time.monotonic()
        fn = getattr(getattr(frame, "prefix", None), "frame_number", None)
        t_s = float(getattr(getattr(frame, "suffix", None), "timestamp", 0.0) or 0.0)
        for rb in frame.rigid_bodies or ():
            if rb.id_num != self.rigid_body_id:
                continue
            with self._lock:
                self.frames += 1
                if fn is not None and self._last_frame is not None and fn > self._last_frame + 1:
                    self.dropped += fn - self._last_frame - 1
                self._last_frame = fn
                if rb.tracking_valid is False:
                    self.untracked += 1
                    return
                p, q = natnet_to_world(rb.pos, rb.rot, self.up_axis)
                self._latest = PoseSample(t_s, p, q, str(rb.id_num), int(fn or 0), now)
            return

    #: NatNet's ports are the server's (command_port, data_port): none of its own to report
    port = None

    def latest(self) -> PoseSample | None:
        with self._lock:
            return self._latest

    def stats(self) -> dict[str, int]:
        """Frames of the tracked body received, and frames missed by the frame number (NatNet
        frames are parsed by the natnet package: no corrupt count here)."""
        with self._lock:
            return {"received": self.frames, "corrupt": 0, "dropped": self.dropped}

    def close(self) -> None:
        if self._client is not None:
            self._client.shutdown()
            self._client = None

    def __enter__(self) -> NatNetPoseSource:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
