"""A tiny UDP pose stream: one datagram per rigid-body sample.

Wire format: little-endian, no padding, 52 bytes, ``struct`` format ``<4sIdI3f4fI``
(:data:`PACKET`):

====== ======= ==========================================================
offset type    field
====== ======= ==========================================================
0      4s      magic ``b"HPOS"``
4      uint32  seq (increments per sample sent by one server; wraps)
8      float64 t_s: sample time [s] (sender clock: mocap or sim time)
16     uint32  rigid-body id
20     float32 x, y, z [m], world frame, z up
32     float32 qw, qx, qy, qz (body → world)
48     uint32  CRC32 of bytes 0..47 (zlib.crc32)
====== ======= ==========================================================

Packets with a wrong size, magic or CRC are counted as corrupt and dropped. Gaps in
``seq`` are counted as dropped packets (the stream is lossy by design: a late pose is
worth nothing, so there is no retransmission). Reordered packets older than the newest
one received are ignored (counted in ``stale``).

:class:`PoseStreamServer` sends (the emulator / a mocap bridge uses it);
:class:`UdpPoseClient` receives on a background thread and keeps only the latest sample.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
import zlib

import numpy as np

from hilstack.drivers.mocap.base import PoseSample

MAGIC = b"HPOS"
_BODY = struct.Struct("<4sIdI3f4f")
PACKET = struct.Struct("<4sIdI3f4fI")
PACKET_SIZE = PACKET.size  # 52


def encode_pose(seq: int, t_s: float, body_id: int, position_m, quaternion_wxyz) -> bytes:
    """One datagram (see the module docstring for the layout)."""
    p = [float(v) for v in position_m]
    q = [float(v) for v in quaternion_wxyz]
    body = _BODY.pack(MAGIC, seq & 0xFFFFFFFF, float(t_s), int(body_id), *p, *q)
    return body + struct.pack("<I", zlib.crc32(body))


def decode_pose(data: bytes) -> tuple[int, PoseSample] | None:
    """(seq, sample) from a datagram, or None if it is not a valid pose packet."""
    if len(data) != PACKET_SIZE:
        return None
    magic, seq, t_s, body_id, x, y, z, qw, qx, qy, qz, crc = PACKET.unpack(data)
    if magic != MAGIC or zlib.crc32(data[: _BODY.size]) != crc:
        return None
    return seq, PoseSample(
        t_s=t_s,
        position_m=np.array([x, y, z]),
        quaternion_wxyz=np.array([qw, qx, qy, qz]),
        frame_id=str(body_id),
        seq=seq,
    )


class PoseStreamServer:
    """Sends pose datagrams to one receiver at (host, port). Loopback in tests."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, body_id: int = 1):
        self.address = (host, int(port))
        self.body_id = body_id
        self.seq = 0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(self, t_s: float, position_m, quaternion_wxyz, body_id: int | None = None) -> int:
        """Send one sample; returns the sequence number used."""
        seq = self.seq
        self._sock.sendto(
            encode_pose(seq, t_s, self.body_id if body_id is None else body_id, position_m, quaternion_wxyz),
            self.address,
        )
        self.seq = (seq + 1) & 0xFFFFFFFF
        return seq

    def skip(self, n: int = 1) -> None:
        """Consume sequence numbers without sending (a dropout the receiver will count)."""
        self.seq = (self.seq + n) & 0xFFFFFFFF

    def send_raw(self, data: bytes) -> None:
        """Send arbitrary bytes (fault injection in tests)."""
        self._sock.sendto(data, self.address)

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> PoseStreamServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class UdpPoseClient:
    """Receives the pose stream on a background thread; ``latest()`` returns the newest sample.

    ``port=0`` binds an ephemeral port (read it back from ``.port``). ``body_id`` filters
    one rigid body (None: accept all). Counters: ``received``, ``corrupt``, ``dropped``
    (sequence gaps), ``stale`` (older than the newest).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, body_id: int | None = None):
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, int(port)))
        self._sock.settimeout(0.05)  # lets the thread notice close() promptly
        self.host, self.port = self._sock.getsockname()
        self.body_id = body_id
        self.received = self.corrupt = self.dropped = self.stale = 0
        self._latest: PoseSample | None = None
        self._last_seq: int | None = None
        self._lock = threading.Lock()
        self._new = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"udp-pose:{self.port}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, _ = self._sock.recvfrom(2048)
            except TimeoutError:
                continue
            except OSError:
                return  # socket closed
            self._handle(data, time.monotonic())

    def _handle(self, data: bytes, now_s: float) -> None:
        with self._lock:
            self._handle_locked(data, now_s)
            self._new.notify_all()

    def _handle_locked(self, data: bytes, now_s: float) -> None:
        dec = decode_pose(data)
        if dec is None:
            self.corrupt += 1
            return
        seq, s = dec
        if self.body_id is not None and s.frame_id != str(self.body_id):
            return
        if self._last_seq is not None:
            gap = (seq - self._last_seq) & 0xFFFFFFFF
            if gap == 0 or gap > 0x7FFFFFFF:
                self.stale += 1
                return
            self.dropped += gap - 1
        self._last_seq = seq
        self.received += 1
        self._latest = PoseSample(s.t_s, s.position_m, s.quaternion_wxyz, s.frame_id, seq, now_s)

    def latest(self) -> PoseSample | None:
        with self._lock:
            return self._latest

    def wait_for(self, seq: int, timeout_s: float = 1.0) -> PoseSample | None:
        """Block until a sample with sequence ≥ ``seq`` arrived (tests, start-up); None on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._latest is None or ((self._latest.seq - seq) & 0xFFFFFFFF) > 0x7FFFFFFF:
                left = deadline - time.monotonic()
                if left <= 0 or not self._new.wait(left):
                    return None
            return self._latest

    def wait_counts(self, total: int, timeout_s: float = 1.0) -> bool:
        """Block until received + corrupt + stale ≥ ``total`` packets were handled."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self.received + self.corrupt + self.stale < total:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._new.wait(left)
            return True

    def stats(self) -> dict[str, int]:
        with self._lock:
            return {"received": self.received, "corrupt": self.corrupt, "dropped": self.dropped, "stale": self.stale}

    def close(self) -> None:
        self._stop.set()
        self._sock.close()
        self._thread.join(timeout=1.0)

    def __enter__(self) -> UdpPoseClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
