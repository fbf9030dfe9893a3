"""The hand's CAN protocol, driven by the CAN database ``shadow_hand.dbc`` (cantools).

Every frame is encoded and decoded through the DBC: scaled integer signals with units
(targets and angles in 0.1 mrad, velocities in mrad/s, efforts in mN·m). This module has
no I/O: it turns values into ``(arbitration_id, data)`` pairs and back, and assembles
the telemetry frames of one cycle into one :class:`Telemetry`.

Telemetry cycle (hand → host, at ``telemetry_hz``): HAND_POS_0..5, HAND_VEL_0..5,
HAND_EFFORT_0..4, then HAND_STATUS, which closes the cycle and carries an 8-bit cycle
counter. A cycle whose frames did not all arrive is not used (its missing frames are
counted as dropped); a gap in the cycle counter counts the whole missed cycles.

HAND_STATUS also carries ``t_fw_ms``, the motor boards' free-running firmware clock (one count
per 1 ms control tick, 16 bits: it wraps to 0 after 65,535) at the tick whose values the cycle
carries. :func:`unwrap_fw_clock` continues it across the wrap; the driver reports it as
``Observation.device_t_s`` (the hand's own sample time, free of the host's latency).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cantools
import numpy as np

from hilstack.drivers.shadow_hand.config import ACTUATED_JOINTS, JOINT_NAMES

#: modes (``HAND_STATUS.mode`` in the DBC)
MODE_HOLD = 1  # holding the measured position (boot, watchdog)
MODE_POSITION = 2  # tracking the host's targets
MODE_ESTOP = 3  # latched hold until the host releases it

#: fault bits (``HAND_STATUS.faults`` in the DBC)
FAULT_WATCHDOG = 1
FAULT_ESTOP = 2
FAULT_MOTOR = 4  # at least one motor faulted: see motor_fault_mask
FAULT_RX_ERROR = 8  # a frame was refused (bad target, wrong length)
FAULT_BUS_OFF = 16  # the CAN controller went bus-off since the last status

DBC_PATH = Path(__file__).with_name("shadow_hand.dbc")
JOINTS_PER_FRAME = 4
ID_ESTOP = 0x010
ID_HOST_HEARTBEAT = 0x080
ID_TARGET = tuple(range(0x100, 0x105))
ID_STATUS = 0x180
ID_POS = tuple(range(0x200, 0x206))
ID_VEL = tuple(range(0x210, 0x216))
ID_EFFORT = tuple(range(0x220, 0x225))
#: frames the host sends / the hand sends (a bus shared by both also carries the other's)
HOST_IDS = frozenset((ID_ESTOP, ID_HOST_HEARTBEAT, *ID_TARGET))
HAND_IDS = frozenset((ID_STATUS, *ID_POS, *ID_VEL, *ID_EFFORT))
#: telemetry frames in one cycle, in send order (HAND_STATUS last)
CYCLE_IDS = (*ID_POS, *ID_VEL, *ID_EFFORT, ID_STATUS)

#: HAND_STATUS.t_fw_ms: the firmware clock's period [s] and its counter's modulus (16 bits)
FW_TICK_S = 0.001
FW_CLOCK_MODULUS = 1 << 16


def unwrap_fw_clock(last_raw: int | None, raw: int, total: int) -> int:
    """The firmware clock in ticks since the first cycle seen, continued across the 65,535 -> 0 wrap.

    ``total`` is the unwrapped count at ``last_raw`` (None: ``raw`` is the first cycle; 0 is
    returned). Cycles must arrive less than 65.536 s apart: the driver's link deadline (1 s by
    default) ends a link long before; a board reset (the clock restarts at 0) reads as one step forward.
    """
    if last_raw is None:
        return 0
    return total + (int(raw) - int(last_raw)) % FW_CLOCK_MODULUS

HOST_MODE_IDLE = 0
HOST_MODE_POSITION = 2


class ProtocolError(ValueError):
    """A frame that cannot be decoded (unknown id, wrong length, bad signal)."""


@functools.cache
def database() -> cantools.database.can.Database:
    return cantools.database.load_file(str(DBC_PATH), database_format="dbc")


def _frame_of(mid: int) -> cantools.database.can.Message:
    return database().get_message_by_frame_id(mid)


def encode(name: str, values: dict[str, float]) -> tuple[int, bytes]:
    """Encode one message by name; values in physical units. Out-of-range or non-finite
    values raise ProtocolError (cantools' strict range check) rather than wrapping."""
    msg = database().get_message_by_name(name)
    for k, v in values.items():
        if not np.isfinite(v):
            raise ProtocolError(f"{name}.{k} is not finite: {v}")
    try:
        return msg.frame_id, bytes(msg.encode(values, scaling=True, strict=True))
    except Exception as e:
        raise ProtocolError(f"cannot encode {name}: {e}") from None


def decode(mid: int, data: bytes) -> tuple[str, dict[str, float]]:
    """Decode one frame. Raises ProtocolError naming what is wrong."""
    try:
        msg = _frame_of(mid)
    except KeyError:
        raise ProtocolError(f"unknown CAN id 0x{mid:03X}") from None
    if len(data) != msg.length:
        raise ProtocolError(f"{msg.name} (0x{mid:03X}) has {len(data)} data bytes, the DBC says {msg.length}")
    try:
        vals = msg.decode(bytes(data), decode_choices=False, scaling=True)
    except Exception as e:
        raise ProtocolError(f"{msg.name} (0x{mid:03X}) does not decode: {e}") from None
    return msg.name, {k: float(v) for k, v in vals.items()}


def encode_targets(targets_rad: np.ndarray) -> list[tuple[int, bytes]]:
    """Position targets [rad] of the 20 actuated joints -> 5 HAND_TARGET frames."""
    t = np.asarray(targets_rad, dtype=np.float64).reshape(-1)
    if t.shape != (len(ACTUATED_JOINTS),):
        raise ProtocolError(f"targets have shape {t.shape}, expected ({len(ACTUATED_JOINTS)},)")
    out = []
    for k in range(len(ID_TARGET)):
        names = ACTUATED_JOINTS[JOINTS_PER_FRAME * k:JOINTS_PER_FRAME * (k + 1)]
        vals = {f"target_{j}": float(t[JOINTS_PER_FRAME * k + i]) for i, j in enumerate(names)}
        out.append(encode(f"HAND_TARGET_{k}", vals))
    return out


def decode_targets(mid: int, data: bytes) -> tuple[int, np.ndarray]:
    """A HAND_TARGET frame -> (first actuator index, targets [rad])."""
    name, vals = decode(mid, data)
    if not name.startswith("HAND_TARGET_"):
        raise ProtocolError(f"{name} is not a target frame")
    k = int(name.rsplit("_", 1)[1])
    names = ACTUATED_JOINTS[JOINTS_PER_FRAME * k:JOINTS_PER_FRAME * (k + 1)]
    return JOINTS_PER_FRAME * k, np.array([vals[f"target_{j}"] for j in names])


def encode_telemetry(q_rad: np.ndarray, qd_rad_s: np.ndarray, effort_nm: np.ndarray, *, mode: int, faults: int,
                     motor_fault_mask: int, cycle: int, rx_error_count: int, t_fw_ms: int) -> list[tuple[int, bytes]]:
    """One telemetry cycle (CYCLE_IDS order). Values outside a signal's range saturate at
    it (a velocity spike must not stop telemetry); NaN raises ProtocolError."""
    db = database()
    out = []
    for ids, prefix, names, vec in ((ID_POS, "pos", JOINT_NAMES, q_rad), (ID_VEL, "vel", JOINT_NAMES, qd_rad_s),
                                    (ID_EFFORT, "effort", ACTUATED_JOINTS, effort_nm)):
        vec = np.asarray(vec, dtype=np.float64)
        for k, mid in enumerate(ids):
            msg = db.get_message_by_frame_id(mid)
            vals = {}
            for i, j in enumerate(names[JOINTS_PER_FRAME * k:JOINTS_PER_FRAME * (k + 1)]):
                sig = msg.get_signal_by_name(f"{prefix}_{j}")
                v = float(vec[JOINTS_PER_FRAME * k + i])
                if not np.isfinite(v):
                    raise ProtocolError(f"{msg.name}.{sig.name} is not finite: {v}")
                vals[sig.name] = min(max(v, sig.minimum), sig.maximum)
            out.append(encode(msg.name, vals))
    out.append(encode("HAND_STATUS", {"mode": mode, "faults": faults & 0xFF, "motor_fault_mask": motor_fault_mask,
                                      "cycle": cycle & 0xFF, "rx_error_count": rx_error_count & 0xFF,
                                      "t_fw_ms": t_fw_ms & 0xFFFF}))
    return out


@dataclass
class Telemetry:
    """One complete telemetry cycle, SI units, JOINT_NAMES / ACTUATED_JOINTS order."""

    q_rad: np.ndarray
    qd_rad_s: np.ndarray
    effort_nm: np.ndarray
    mode: int
    faults: int
    motor_fault_mask: int
    cycle: int
    rx_error_count: int
    t_fw_ms: int


class TelemetryAssembler:
    """Collects the frames of a cycle; HAND_STATUS closes it.

    ``feed`` returns a :class:`Telemetry` when a complete cycle closed, else None.
    Counters: ``cycles`` (complete), ``dropped_frames`` (missing frames of incomplete
    cycles plus whole cycles skipped by the counter)."""

    def __init__(self) -> None:
        self._vals: dict[int, dict[str, float]] = {}
        self._last_cycle: int | None = None
        self.cycles = 0
        self.incomplete_cycles = 0
        self.dropped_frames = 0

    def feed(self, mid: int, vals: dict[str, float]) -> Telemetry | None:
        if mid != ID_STATUS:
            self._vals[mid] = vals
            return None
        cycle = int(vals["cycle"])
        if self._last_cycle is not None:
            skipped = (cycle - self._last_cycle - 1) % 256
            self.dropped_frames += skipped * len(CYCLE_IDS)
        self._last_cycle = cycle
        got, self._vals = self._vals, {}
        missing = [m for m in CYCLE_IDS[:-1] if m not in got]
        if missing:
            self.incomplete_cycles += 1
            self.dropped_frames += len(missing)
            return None
        self.cycles += 1
        pos = {k: v for m in ID_POS for k, v in got[m].items()}
        vel = {k: v for m in ID_VEL for k, v in got[m].items()}
        eff = {k: v for m in ID_EFFORT for k, v in got[m].items()}
        return Telemetry(
            q_rad=np.array([pos[f"pos_{j}"] for j in JOINT_NAMES]),
            qd_rad_s=np.array([vel[f"vel_{j}"] for j in JOINT_NAMES]),
            effort_nm=np.array([eff[f"effort_{j}"] for j in ACTUATED_JOINTS]),
            mode=int(vals["mode"]), faults=int(vals["faults"]), motor_fault_mask=int(vals["motor_fault_mask"]),
            cycle=cycle, rx_error_count=int(vals["rx_error_count"]), t_fw_ms=int(vals["t_fw_ms"]),
        )


# ---------------------------------------------------------------------- bus load
def frame_bits_worst_case(data_bytes: int) -> int:
    """Bits on the wire of one classic CAN frame with an 11-bit id, worst-case bit
    stuffing, including the 3-bit interframe space: 8n + 47 + floor((34 + 8n − 1)/4)
    (Davis et al., "Controller Area Network (CAN) schedulability analysis", 2007)."""
    n = int(data_bytes)
    return 8 * n + 47 + (34 + 8 * n - 1) // 4


def bus_load(telemetry_hz: float, command_hz: float, heartbeat_hz: float, bitrate: int = 1_000_000) -> dict:
    """Worst-case bus load of this protocol [fraction of the bit rate], per stream."""
    db = database()

    def bits(ids):
        return sum(frame_bits_worst_case(db.get_message_by_frame_id(m).length) for m in ids)

    streams = {
        "telemetry": bits(CYCLE_IDS) * telemetry_hz,
        "targets": bits(ID_TARGET) * command_hz,
        "heartbeat": bits([ID_HOST_HEARTBEAT]) * heartbeat_hz,
    }
    out = {k: v / bitrate for k, v in streams.items()}
    out["total"] = sum(out.values())
    return out
