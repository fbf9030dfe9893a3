"""The radio link: XBee 802.15.4 API frames carrying one MAVLink v2 frame each.

Layers, bottom up:

* a byte port: pyserial (a real ``/dev/ttyUSB0``, a pty, ``loop://``) or :class:`FdPort`
  (the emulator's pty master);
* :class:`XBeeDeframer`: byte stream -> XBee API frames (API mode 1, no escaping). It
  resynchronises on the 0x7E start delimiter and counts, then skips, bad checksums,
  truncated frames, impossible lengths and garbage between frames;
* :class:`~hilstack.drivers.velociroach.mavlink.MavDecoder`: XBee payload -> MAVLink message, counts
  bad CRCs and sequence gaps (dropped frames);
* :class:`RadioLink`: both directions for one endpoint (``role="base"``: the PC behind the
  base-station XBee sends TX64 requests and receives RX64 frames; ``role="robot"``: the
  emulator, which sees the PC's TX64 requests and answers with RX64 frames), with link
  statistics and an optional ``.tlog`` of every MAVLink frame.

Every port error (device unplugged, pty closed, write stuck) becomes
:class:`hilstack.drivers.base.LinkError` with the port name in the message; nothing blocks longer
than the port's timeouts.
"""

from __future__ import annotations

import errno
import os
import select
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

from digi.xbee.exception import InvalidPacketException
from digi.xbee.models.address import XBee64BitAddress
from digi.xbee.models.mode import OperatingMode
from digi.xbee.packets import factory
from digi.xbee.packets.raw import RX64Packet, TX64Packet

from hilstack.drivers.base import LinkError
from hilstack.drivers.fdio import write_all
from hilstack.drivers.velociroach.mavlink import MavDecoder

START = 0x7E
FRAME_TX64 = 0x00
FRAME_RX64 = 0x80
FRAME_TX_STATUS = 0x89
#: API id + frame id/rssi + 8-byte address + options + 100 payload bytes, with margin
MAX_FRAME_LEN = 120
#: a partial frame with no new byte for this long is declared truncated
STALE_PARTIAL_S = 0.2


def addr64(hex16: str) -> XBee64BitAddress:
    return XBee64BitAddress.from_hex_string(hex16)


def xbee_tx64(dest: XBee64BitAddress, payload: bytes, frame_id: int = 0) -> bytes:
    """A TX (64-bit address) request, PC -> XBee. frame_id 0: the module sends no TX status."""
    return bytes(TX64Packet(frame_id, dest, 0, bytearray(payload)).output())


def xbee_rx64(src: XBee64BitAddress, payload: bytes, rssi_dbm: int = 40) -> bytes:
    """An RX (64-bit address) frame, XBee -> PC. ``rssi_dbm`` is -dBm as the module reports it."""
    return bytes(RX64Packet(src, rssi_dbm, 0, bytearray(payload)).output())


def xbee_checksum_ok(frame: bytes) -> bool:
    return (sum(frame[3:]) & 0xFF) == 0xFF


@dataclass
class XBeeFrame:
    frame_type: int
    #: the 64-bit address of the other end (RX64: source, TX64: destination)
    addr64: str
    payload: bytes
    rssi_dbm: int | None = None


class XBeeDeframer:
    """Byte stream in, checked XBee API frames out; corrupt input counted and skipped.

    On any bad frame only its start byte is dropped and the scan resumes, so a good frame
    that began inside the bad one's claimed length is still found.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._last_byte_t: float | None = None
        self.frames = 0
        self.corrupt = 0
        self.bad_checksum = 0
        self.truncated = 0
        self.garbage = 0
        self.bad_length = 0
        self.last_error: str | None = None
        #: the next bytes are the body of a broken frame already counted: a 0x7E in there
        #: starts no new corrupt event (only a good frame is taken from inside it)
        self._quiet_b = 0
        #: the non-frame bytes being skipped continue a corrupt run already counted
        #: (a garbage run going on in the next read, the bytes after an impossible length)
        self._resync = False

    @property
    def lost_frames(self) -> int:
        """Corrupt events that destroyed a frame (all but garbage between frames)."""
        return self.bad_checksum + self.truncated + self.bad_length

    def feed(self, data: bytes, now_s: float | None = None) -> list[XBeeFrame]:
        """Bytes in (any split), complete checked frames out. ``now_s``: monotonic clock [s].

        Each corrupt event is counted once, however the reads split it: a garbage run, or a
        broken frame including its body (a start delimiter inside a broken frame's claimed
        length begins nothing new unless it begins a good frame). A pause longer than
        :data:`STALE_PARTIAL_S` ends a run; a frame left unfinished by it is truncated.
        """
        now_s = time.monotonic() if now_s is None else now_s
        buf = self._buf
        if self._last_byte_t is not None and now_s - self._last_byte_t > STALE_PARTIAL_S:
            if buf:
                if not self._quiet_b:
                    self._bad("truncated", "truncated XBee frame (stream stopped mid-frame)")
                buf.clear()
            self._quiet_b, self._resync = 0, False
        if data:
            buf += data
            self._last_byte_t = now_s
        out: list[XBeeFrame] = []
        while buf:
            if buf[0] != START:
                i = buf.find(START)
                n = len(buf) if i < 0 else i
                excess = n - self._quiet_b  # bytes beyond the body of a broken frame
                self._consume(n)
                if excess > 0:
                    if not self._resync:
                        self._bad("garbage", f"{excess} garbage byte(s) between frames")
                    self._resync = i < 0  # no start delimiter ended it: it goes on in the next read
                continue
            self._resync = False
            quiet = self._quiet_b > 0  # inside a broken frame: already counted
            if len(buf) < 3:
                break
            length = (buf[1] << 8) | buf[2]
            if length == 0 or length > MAX_FRAME_LEN:
                self._consume(1)
                if not quiet:
                    self._bad("bad_length", f"impossible XBee frame length {length}")
                    self._resync = True
                continue
            total = length + 4
            if len(buf) < total:
                # incomplete: either more bytes are coming, or it was truncated and a later
                # frame already started; a valid frame further on proves truncation
                j = self._next_valid_frame(1)
                if j is None:
                    break
                self._consume(j)
                if not quiet:
                    self._bad("truncated", "truncated XBee frame")
                continue
            frame = bytes(buf[:total])
            if not xbee_checksum_ok(frame):
                j = self._next_valid_frame(1)
                # a "bad checksum" that swallowed the start of a valid frame was a truncation
                truncated = j is not None and j < total
                self._consume(1)
                if not quiet:
                    kind = "truncated" if truncated else "bad_checksum"
                    self._bad(kind, f"XBee {kind.replace('_', ' ')} (frame type 0x{frame[3]:02X})")
                    self._quiet_b = (j if truncated and j is not None else total) - 1
                continue
            self._consume(total)
            self._quiet_b = 0  # a good frame: whatever was broken before it has ended
            f = self._parse(frame)
            if f is not None:
                self.frames += 1
                out.append(f)
        return out

    def _consume(self, n: int) -> None:
        """Drop ``n`` bytes from the buffer (and from a broken frame's body, if in one)."""
        del self._buf[:n]
        self._quiet_b = max(0, self._quiet_b - n)

    def _next_valid_frame(self, start: int) -> int | None:
        buf = self._buf
        j = buf.find(START, start)
        while j >= 0:
            if len(buf) >= j + 3:
                length = (buf[j + 1] << 8) | buf[j + 2]
                if 0 < length <= MAX_FRAME_LEN and len(buf) >= j + length + 4:
                    if xbee_checksum_ok(bytes(buf[j : j + length + 4])):
                        return j
            j = buf.find(START, j + 1)
        return None

    def _parse(self, frame: bytes) -> XBeeFrame | None:
        ftype = frame[3]
        try:
            if ftype == FRAME_RX64:
                p = factory.build_frame(bytearray(frame), OperatingMode.API_MODE)
                return XBeeFrame(ftype, str(p.x64bit_source_addr), bytes(p.rf_data or b""), p.rssi)
            if ftype == FRAME_TX64:
                p = TX64Packet.create_packet(bytearray(frame), OperatingMode.API_MODE)
                return XBeeFrame(ftype, str(p.x64bit_dest_addr), bytes(p.rf_data or b""))
        except (InvalidPacketException, ValueError, IndexError) as e:
            self._bad("bad_checksum", f"XBee frame rejected by digi-xbee: {e}")
            return None
        # TX status, modem status, AT responses: valid frames, no MAVLink in them
        return XBeeFrame(ftype, "", b"")

    def _bad(self, kind: str, why: str) -> None:
        self.corrupt += 1
        setattr(self, kind, getattr(self, kind) + 1)
        self.last_error = why


class BytePort(Protocol):
    def read(self, size: int = 1) -> bytes: ...
    def write(self, data: bytes) -> int | None: ...
    def close(self) -> None: ...


class FdPort:
    """A raw file descriptor (the emulator's pty master) with a pyserial-like read/write."""

    def __init__(self, fd: int, name: str = "pty", timeout_s: float = 0.01, write_timeout_s: float = 0.5):
        self.fd = fd
        self.name = name
        self.timeout = timeout_s
        self.write_timeout = write_timeout_s
        os.set_blocking(fd, False)

    def read(self, size: int = 4096) -> bytes:
        r, _, _ = select.select([self.fd], [], [], self.timeout)
        if not r:
            return b""
        try:
            return os.read(self.fd, max(size, 4096))
        except BlockingIOError:
            return b""
        except OSError as e:
            if e.errno == errno.EIO:  # pty master: no process holds the other end open
                return b""
            raise

    def write(self, data: bytes) -> int:
        return write_all(self.fd, data, self.write_timeout, self.name)

    def close(self) -> None:
        try:
            os.close(self.fd)
        except OSError:
            pass


class TlogWriter:
    """``.tlog``: each MAVLink frame as ``>Q`` microseconds since the epoch + the raw frame.

    pymavlink reads it back: ``mavutil.mavlink_connection(path, dialect="velociroach")``.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "ab")  # noqa: SIM115 - lives as long as the link
        self._lock = threading.Lock()

    def write(self, frame: bytes, t_unix_s: float | None = None) -> None:
        usec = int((time.time() if t_unix_s is None else t_unix_s) * 1e6)
        with self._lock:
            self._f.write(struct.pack(">Q", usec) + frame)

    def close(self) -> None:
        with self._lock:
            if not self._f.closed:
                self._f.flush()
                self._f.close()


def open_serial(url: str, baudrate: int, timeout_s: float = 0.01, write_timeout_s: float = 0.5):
    """Open a pyserial port by device path or URL (``loop://``...). LinkError if impossible."""
    import serial

    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s, write_timeout=write_timeout_s)
    except (serial.SerialException, OSError, ValueError) as e:
        hint = "" if Path(url).exists() or "://" in url else " (no such device; `hil find-port` lists candidates)"
        raise LinkError(f"cannot open serial port {url!r}: {e}{hint}") from None


class RadioLink:
    """One endpoint of the radio link over a byte port.

    ``send(frame)`` wraps a packed MAVLink frame in an XBee frame and writes it;
    ``receive(timeout_s)`` reads what the port has (waiting at most ``timeout_s``) and
    returns the decoded MAVLink messages. Each method is called from one thread (the driver
    reads in its reader thread and writes from the control thread; pyserial allows that).
    """

    def __init__(
        self,
        port: Any,
        *,
        role: Literal["base", "robot"] = "base",
        robot_addr64: str = "0013A20040A1B2C3",
        tlog: str | Path | None = None,
        name: str | None = None,
    ):
        self.port = port
        self.role = role
        self.name = name or getattr(port, "name", None) or getattr(port, "port", None) or "port"
        self.robot_addr = addr64(robot_addr64)
        self._robot_addr_str = str(self.robot_addr)
        self.deframer = XBeeDeframer()
        self.decoder = MavDecoder()
        self.tlog = TlogWriter(tlog) if tlog else None
        self._wlock = threading.Lock()
        self.frames_sent = 0
        self.bytes_sent = 0
        self.bytes_received = 0
        self.foreign_frames = 0
        self.last_rx_s: float | None = None
        self.last_error: str | None = None
        self.closed = False
        self.dead: str | None = None
        #: receive times of good frames in the last second, for link quality
        self._rx_times: deque[float] = deque()
        self._bad_times: deque[float] = deque()
        self._last_bad_count = 0

    @classmethod
    def open(cls, url: str, baudrate: int = 230400, write_timeout_s: float = 0.5, **kw: Any) -> RadioLink:
        return cls(open_serial(url, baudrate, write_timeout_s=write_timeout_s), name=url, **kw)

    # ------------------------------------------------------------------ I/O
    def send(self, mav_frame: bytes) -> None:
        if self.dead:
            raise LinkError(self.dead)
        if self.role == "base":
            raw = xbee_tx64(self.robot_addr, mav_frame)
        else:
            raw = xbee_rx64(self.robot_addr, mav_frame)
        if self.tlog:
            # logged before the write: the reply can arrive (and be logged by the reader
            # thread) before a write call returns, and the log must keep cause before effect
            self.tlog.write(mav_frame)
        self.send_raw(raw)

    def send_raw(self, raw: bytes) -> None:
        """Write bytes as they are (fault injection uses this to send broken frames)."""
        with self._wlock:
            try:
                self.port.write(raw)
                flush = getattr(self.port, "flush", None)
                if flush is not None and not isinstance(self.port, FdPort):
                    flush()
            except Exception as e:  # SerialException, OSError, SerialTimeoutException, TimeoutError
                self._die(f"serial port {self.name}: write failed ({type(e).__name__}: {e}); "
                          "device unplugged or the other end closed?")
            self.frames_sent += 1
            self.bytes_sent += len(raw)

    def receive(self, timeout_s: float | None = None) -> list[Any]:
        """Messages decoded from the bytes available now (waits up to the port timeout)."""
        if self.dead:
            raise LinkError(self.dead)
        try:
            if timeout_s is not None and hasattr(self.port, "timeout"):
                self.port.timeout = timeout_s
            waiting = getattr(self.port, "in_waiting", 0) or 0
            data = self.port.read(max(int(waiting), 1) if not isinstance(self.port, FdPort) else 4096)
        except Exception as e:
            self._die(f"serial port {self.name}: read failed ({type(e).__name__}: {e}); "
                      "device unplugged or the other end closed?")
        return self.feed(data)

    def feed(self, data: bytes, now_s: float | None = None) -> list[Any]:
        """Decode bytes (from ``receive`` or a test). Returns good MAVLink messages."""
        now = time.monotonic() if now_s is None else now_s
        self.bytes_received += len(data)
        msgs = []
        want = FRAME_RX64 if self.role == "base" else FRAME_TX64
        lost_before = self.deframer.lost_frames
        frames = self.deframer.feed(data, now)
        # frames broken at the XBee layer used a MAVLink sequence number too
        self.decoder.note_lost(self.deframer.lost_frames - lost_before)
        for f in frames:
            if f.frame_type != want:
                continue  # TX status and friends
            if f.addr64 != self._robot_addr_str:
                self.foreign_frames += 1  # another robot on the same channel
                continue
            m = self.decoder.decode(f.payload)
            if m is None:
                continue
            if self.tlog:
                self.tlog.write(f.payload)
            msgs.append(m)
            self._rx_times.append(now)
        if msgs:
            self.last_rx_s = now
        bad = self.corrupt_frames
        for _ in range(bad - self._last_bad_count):
            self._bad_times.append(now)
        self._last_bad_count = bad
        return msgs

    def _die(self, why: str) -> None:
        self.dead = why
        self.last_error = why
        raise LinkError(why)

    # ------------------------------------------------------------------ health
    @property
    def corrupt_frames(self) -> int:
        return self.deframer.corrupt + self.decoder.corrupt

    @property
    def frames_received(self) -> int:
        return self.decoder.received

    @property
    def dropped_frames(self) -> int:
        return self.decoder.dropped

    def quality(self, expected_hz: float, now_s: float | None = None, window_s: float = 1.0) -> float:
        """Good frames in the last ``window_s`` over what ``expected_hz`` promises, reduced by
        the share of corrupt frames; 0 when silent."""
        now = time.monotonic() if now_s is None else now_s
        for q in (self._rx_times, self._bad_times):
            while q and now - q[0] > window_s:
                q.popleft()
        good, bad = len(self._rx_times), len(self._bad_times)
        if good == 0:
            return 0.0
        rate = min(1.0, good / max(expected_hz * window_s, 1.0))
        return rate * good / (good + bad)

    def stats(self) -> dict[str, Any]:
        d = self.deframer
        return {
            "frames_sent": self.frames_sent,
            "frames_received": self.frames_received,
            "corrupt_frames": self.corrupt_frames,
            "dropped_frames": self.dropped_frames,
            "bad_xbee_checksum": d.bad_checksum,
            "truncated_frames": d.truncated,
            "garbage_runs": d.garbage,
            "bad_length": d.bad_length,
            "bad_mavlink": self.decoder.corrupt,
            "foreign_frames": self.foreign_frames,
            "bytes_sent": self.bytes_sent,
            "bytes_received": self.bytes_received,
            "last_corrupt_reason": self.decoder.last_error if self.decoder.corrupt else d.last_error,
        }

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.port.close()
        except Exception:
            pass
        if self.tlog:
            self.tlog.close()
