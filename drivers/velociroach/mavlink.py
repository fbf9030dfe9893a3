"""The VelociRoACH MAVLink v2 dialect: generated from ``dialect/velociroach.xml`` at import.

The XML is the single definition of the wire messages. The Python module is generated
with pymavlink's mavgen into a cache directory keyed by the hash of the XML (plus the
included ``minimal.xml`` and the pymavlink version), so a fresh clone needs no network and
no generated file in git. The module is registered as ``pymavlink.dialects.v20.velociroach``
in this process (``sys.modules``), so ``mavutil.mavlink_connection(..., dialect="velociroach")``
works after ``import hilstack.drivers.velociroach.mavlink``. Stock tools started on their own
(``mavlogdump.py --dialect velociroach``) cannot find it: mavutil imports dialects only
from the ``pymavlink.dialects.v20`` package directory, and ``MAVLINK_DIALECT`` only picks
a name there. Decode a ``.tlog`` with the wrapper, which loads the dialect and then runs
pymavlink's own mavlogdump with any of its options (see docs/velociroach.md)::

    python -m hilstack.drivers.velociroach.mavlink dump --types ROACH_TELEMETRY runs/roach.tlog

Also here: encoders with a last range check (nothing non-finite or out of range is ever
packed), and :class:`MavDecoder` which decodes one frame at a time and counts sequence gaps.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import math
import os
import shutil
import sys
import tempfile
import threading
from pathlib import Path
from types import ModuleType

# must be set before pymavlink's mavutil is imported anywhere: it picks v1/v2 at import
os.environ["MAVLINK20"] = "1"

import pymavlink  # noqa: E402

DIALECT_NAME = "velociroach"
DIALECT_XML = Path(__file__).resolve().parent / "dialect" / "velociroach.xml"
MODULE_NAME = f"pymavlink.dialects.v20.{DIALECT_NAME}"

#: system/component ids on the radio network
BASE_SYSID, BASE_COMPID = 255, 190  # a ground station, as MAVLink tools expect
ROBOT_SYSID, ROBOT_COMPID = 1, 1

#: an XBee 802.15.4 frame carries at most this many payload bytes
XBEE_MAX_PAYLOAD_B = 100


class EncodeError(ValueError):
    """A value that must not go on the wire (NaN, inf, out of range). Nothing was packed."""


def cache_root() -> Path:
    env = os.environ.get("HILSTACK_CACHE")
    if env:
        return Path(env) / "mavlink"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hilstack" / "mavlink"


def _minimal_xml() -> Path:
    p = Path(pymavlink.__file__).resolve().parent / "dialects" / "v20" / "minimal.xml"
    if not p.is_file():
        raise RuntimeError(f"pymavlink {pymavlink.__version__} does not ship {p}; reinstall pymavlink")
    return p


def _dialect_key() -> str:
    h = hashlib.sha256()
    h.update(DIALECT_XML.read_bytes())
    h.update(_minimal_xml().read_bytes())
    h.update(str(getattr(pymavlink, "__version__", "?")).encode())
    return h.hexdigest()[:16]


def _generate(out_dir: Path) -> Path:
    """Run mavgen into ``out_dir`` (atomically: two processes may race on a fresh cache)."""
    from pymavlink.generator import mavgen, mavparse

    target = out_dir / f"{DIALECT_NAME}.py"
    if target.is_file():
        return target
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".gen-", dir=out_dir.parent))
    try:
        # mavgen resolves <include> relative to the including file
        shutil.copy(DIALECT_XML, tmp / DIALECT_XML.name)
        shutil.copy(_minimal_xml(), tmp / "minimal.xml")
        opts = mavgen.Opts(
            str(tmp / DIALECT_NAME), wire_protocol=mavparse.PROTOCOL_2_0, language="Python3", validate=True
        )
        try:
            # mavgen prints progress on stdout; the emulator's stdout is its handshake channel
            with contextlib.redirect_stdout(io.StringIO()) as out:
                ok = mavgen.mavgen(opts, [str(tmp / DIALECT_XML.name)])
            if ok is False:
                raise RuntimeError(f"mavgen failed on {DIALECT_XML}:\n{out.getvalue()}")
        except SystemExit as e:  # mavgen calls exit(1) on an invalid XML
            raise RuntimeError(f"mavgen rejected {DIALECT_XML} (exit {e.code}); see its output above") from None
        gen = tmp / f"{DIALECT_NAME}.py"
        if not gen.is_file():
            raise RuntimeError(f"mavgen produced no {gen.name} from {DIALECT_XML}")
        out_dir.mkdir(parents=True, exist_ok=True)
        os.replace(gen, target)  # atomic: a concurrent reader sees all or nothing
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def load_dialect() -> ModuleType:
    """The generated dialect module (generating it on first use)."""
    mod = sys.modules.get(MODULE_NAME)
    if mod is not None:
        return mod
    key = _dialect_key()
    try:
        path = _generate(cache_root() / key)
    except OSError:
        # read-only home (CI sandbox...): a per-user temp dir still works
        path = _generate(Path(tempfile.gettempdir()) / f"hilstack-mavlink-{os.getuid()}" / key)
    spec = importlib.util.spec_from_file_location(MODULE_NAME, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[MODULE_NAME] = mod
    try:
        spec.loader.exec_module(mod)
    except Exception:
        del sys.modules[MODULE_NAME]
        raise
    import pymavlink.dialects.v20 as v20

    setattr(v20, DIALECT_NAME, mod)
    return mod


mav = load_dialect()
MAVError = mav.MAVError


# --------------------------------------------------------------------------- encoding
def _check(name: str, value: float, limit: float) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise EncodeError(f"{name}={value!r} is not finite: not sent")
    if abs(v) > limit:
        raise EncodeError(f"{name}={v} outside ±{limit}: not sent")
    return v


class MavEncoder:
    """Packs messages from one endpoint (its own sequence counter).

    Thread-safe: the driver packs commands on the control thread and heartbeats on its
    reader thread; packing and bumping the 8-bit sequence number happen under one lock,
    so no two frames share a sequence number.
    """

    def __init__(self, sysid: int, compid: int):
        self._mav = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._lock = threading.Lock()

    def pack(self, msg) -> bytes:
        with self._lock:
            buf = bytes(msg.pack(self._mav))
            self._mav.seq = (self._mav.seq + 1) % 256
        if len(buf) > XBEE_MAX_PAYLOAD_B:
            raise EncodeError(f"{msg.get_type()} is {len(buf)} bytes, more than one XBee frame ({XBEE_MAX_PAYLOAD_B})")
        return buf

    # base station -> robot
    def leg_velocity(self, cmd_seq: int, left_rps: float, right_rps: float, max_rps: float) -> bytes:
        """The last check before the wire: finite and within ±max_rps, else EncodeError."""
        left = _check("left_rps", left_rps, max_rps)
        right = _check("right_rps", right_rps, max_rps)
        return self.pack(mav.MAVLink_roach_leg_velocity_cmd_message(
            ROBOT_SYSID, ROBOT_COMPID, cmd_seq & 0xFFFFFFFF, left, right))

    def pwm(self, cmd_seq: int, duty_left: float, duty_right: float) -> bytes:
        dl = _check("duty_left", duty_left, 1.0)
        dr = _check("duty_right", duty_right, 1.0)
        return self.pack(mav.MAVLink_roach_pwm_cmd_message(ROBOT_SYSID, ROBOT_COMPID, cmd_seq & 0xFFFFFFFF, dl, dr))

    def heartbeat(self, *, robot: bool = False, faults: int = 0) -> bytes:
        if robot:
            return self.pack(mav.MAVLink_heartbeat_message(
                mav.MAV_TYPE_GROUND_ROVER, mav.MAV_AUTOPILOT_GENERIC, 0, faults & 0xFFFFFFFF,
                mav.MAV_STATE_ACTIVE, 3))
        return self.pack(mav.MAVLink_heartbeat_message(
            mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE, 3))

    def pid_set(self, request_id: int, kp: float, ki: float, kd: float) -> bytes:
        vals = [_check(n, v, 1e6) for n, v in (("kp", kp), ("ki", ki), ("kd", kd))]
        return self.pack(mav.MAVLink_roach_pid_gains_set_message(
            ROBOT_SYSID, ROBOT_COMPID, request_id & 0xFFFF, *vals))

    def pid_get(self, request_id: int) -> bytes:
        return self.pack(mav.MAVLink_roach_pid_gains_get_message(ROBOT_SYSID, ROBOT_COMPID, request_id & 0xFFFF))

    # robot -> base station
    def telemetry(self, t: dict, *, last_cmd_seq: int, rx_good: int, rx_corrupt: int) -> bytes:
        def vec(key: str, n: int) -> list[float]:
            v = [float(x) for x in t[key]]
            if len(v) != n:
                raise EncodeError(f"telemetry {key} has {len(v)} values, expected {n}")
            return v

        return self.pack(mav.MAVLink_roach_telemetry_message(
            int(t["t_fw_ms"]) & 0xFFFFFFFF, vec("gyro_rps", 3), vec("accel_mps2", 3),
            vec("crank_angle_rad", 2), vec("crank_vel_rps", 2), vec("bemf_v", 2), float(t["vbat_v"]),
            vec("duty", 2), int(t["faults"]) & 0xFFFFFFFF, last_cmd_seq & 0xFFFFFFFF,
            rx_good & 0xFFFFFFFF, rx_corrupt & 0xFFFFFFFF))

    def pid_gains(self, request_id: int, kp: float, ki: float, kd: float, result: int) -> bytes:
        return self.pack(mav.MAVLink_roach_pid_gains_message(request_id & 0xFFFF, kp, ki, kd, result))

    def status_text(self, severity: int, faults: int, text: str) -> bytes:
        raw = text.encode("ascii", "replace")[:50]
        return self.pack(mav.MAVLink_roach_status_text_message(severity, faults & 0xFFFFFFFF, raw))


# --------------------------------------------------------------------------- decoding
class MavDecoder:
    """Decodes whole MAVLink frames (one per XBee payload) and tracks sequence gaps.

    ``decode`` returns the message, or None after counting the frame as corrupt (bad
    CRC, bad length, unknown id). Gaps in a sender's 8-bit sequence count as dropped,
    except the frames already counted as corrupt: a frame that arrived broken still
    used a sequence number, and it must not be counted twice (corrupt and dropped).
    Frames destroyed below MAVLink (bad XBee checksum, truncation) are reported with
    :meth:`note_lost`. Invariant for one sender: ``received + dropped`` plus the frames
    counted corrupt (here or through ``note_lost``) is the number of frames it sent, up
    to the frames after the last one received (a gap shows only when the next arrives).
    """

    def __init__(self) -> None:
        self._mav = mav.MAVLink(None)
        self._last_seq: dict[tuple[int, int], int] = {}
        self.corrupt = 0
        self.dropped = 0
        self.received = 0
        self.last_error: str | None = None
        #: frames counted as corrupt that the next sequence gap has not explained yet
        self._unexplained_lost = 0

    def note_lost(self, n: int = 1) -> None:
        """``n`` frames were destroyed before reaching MAVLink (already counted as corrupt there)."""
        self._unexplained_lost += n

    def decode(self, frame: bytes):
        try:
            m = self._mav.decode(bytearray(frame))
        except MAVError as e:
            self._fail(f"bad MAVLink frame: {e}")
            return None
        except Exception as e:  # e.g. struct errors on a frame that passed the CRC by chance
            self._fail(f"undecodable MAVLink frame: {type(e).__name__}: {e}")
            return None
        if isinstance(m, mav.MAVLink_unknown):
            self._fail(f"unknown MAVLink message id {m.get_msgId()}")
            return None
        key = (m.get_srcSystem(), m.get_srcComponent())
        seq = m.get_seq()
        last = self._last_seq.get(key)
        if last is not None:
            gap = (seq - last - 1) % 256
            # a huge "gap" is more likely the sender restarting than 128+ lost frames
            if gap < 128:
                explained = min(gap, self._unexplained_lost)
                self._unexplained_lost -= explained
                self.dropped += gap - explained
            else:
                self._unexplained_lost = 0
        self._last_seq[key] = seq
        self.received += 1
        return m

    def _fail(self, why: str) -> None:
        self.corrupt += 1
        self._unexplained_lost += 1
        self.last_error = why


def main(argv: list[str] | None = None) -> int:
    """Usage:
    python -m hilstack.drivers.velociroach.mavlink dump [mavlogdump options] LOG.tlog
        decode a .tlog with pymavlink's mavlogdump, this dialect loaded (``mavlogdump``
        is accepted as an alias of ``dump``; ``dump --help`` lists mavlogdump's options)
    python -m hilstack.drivers.velociroach.mavlink path
        print where the generated dialect module lives"""
    import argparse

    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(prog="python -m hilstack.drivers.velociroach.mavlink",
                                 description="The VelociRoACH MAVLink dialect's tools.",
                                 epilog="dump [mavlogdump options] LOG.tlog: decode a .tlog with pymavlink's "
                                        "mavlogdump, this dialect loaded (mavlogdump is an alias; dump --help lists "
                                        "its options). path: where the generated dialect module lives.")
    ap.add_argument("command", choices=["dump", "mavlogdump", "mavlogdump.py", "path"])
    # everything after the command is mavlogdump's (its own --help included)
    a = ap.parse_args(argv[:1])
    if a.command == "path":
        if argv[1:]:
            ap.error(f"path takes no arguments, got {argv[1:]}")
        print(mav.__file__)
        return 0
    if a.command in ("dump", "mavlogdump", "mavlogdump.py"):
        import runpy

        rest = argv[1:]
        if "-h" not in rest and "--help" not in rest:
            if not rest or rest[-1].startswith("-"):
                print("error: dump needs a .tlog file as its last argument", file=sys.stderr)
                return 2
            if not Path(rest[-1]).is_file():
                print(f"error: no such log file: {rest[-1]}", file=sys.stderr)
                return 2
        if "--dialect" not in rest:
            rest = ["--dialect", DIALECT_NAME, *rest]
        sys.argv = ["mavlogdump.py", *rest]
        try:
            runpy.run_module("pymavlink.tools.mavlogdump", run_name="__main__", alter_sys=True)
        except SystemExit as e:
            return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
