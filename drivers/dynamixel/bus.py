"""A Dynamixel Protocol 2.0 bus through dynamixel-sdk, with the statistics a driver needs.

``DynamixelBus`` wraps the SDK's ``PortHandler``/``PacketHandler``: typed reads and
writes by control-table item name, sync read of a block of items from many IDs (each
answer is dispatched by ID, so a missing servo costs one timeout and does not hide the
others), sync write, ping, reboot. Every call is counted: instructions sent, status
packets received, CRC errors (``COMM_RX_CORRUPT``), missing status packets
(``COMM_RX_TIMEOUT``), the last round-trip time.

Robots on one bus (the arm and the mechanism share an adapter) share one object:
``acquire_bus(key, opener)`` hands out a reference-counted instance per port; the lock
makes each transaction atomic between them. Only one process may own a port: it is
opened exclusively (pyserial ``exclusive=True``, an ``flock`` on the device), so a
second process that opens it gets a one-line :class:`LinkError` instead of colliding
packets on the wire (``hil up`` runs the robots of one bus in one process).

Time bounds: every transaction waits for its status packets at most the SDK's transfer
time plus a margin; ``sync_read`` takes a tighter margin from its caller (the robots
pass a fraction of their control period), so a device that stops answering costs a
read at most about one period. Writes to the port time out after ``WRITE_TIMEOUT_S``
(a device that stopped reading cannot block the driver).
"""

from __future__ import annotations

import json
import os
import signal
import termios
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import serial
from dynamixel_sdk import COMM_RX_CORRUPT, COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler, PortHandler
from serial import SerialException

from hilstack.drivers.base import LinkError
from hilstack.drivers.dynamixel.control_table import ControlTable, control_table, describe_status_error
from hilstack.drivers.emulator_process import EmulatorProcess, emulator_module
from hilstack.drivers.fdio import write_all

EMULATOR_START_TIMEOUT_S = 30.0
# dynamixel-sdk packet layout offsets (status packet: ... INST ERROR PARAMS)
_PKT_ID, _PKT_ERROR, _PKT_PARAM = 4, 8, 9


class ServoError(RuntimeError):
    """A servo answered with an error in its status packet."""


#: dynamixel-sdk's own status timeout: 2 × its 16 ms latency-timer assumption + 2 ms
SDK_TIMEOUT_MARGIN_MS = 34.0
#: a write to the port that cannot complete within this fails (the device stopped reading)
WRITE_TIMEOUT_S = 0.1


class _Port(PortHandler):
    """The SDK's port with a configurable status timeout margin (the SDK hard-codes
    34 ms for a 16 ms USB latency timer; an emulator on a loaded CPU needs more, an
    adapter set to 1 ms needs less)."""

    timeout_margin_ms = SDK_TIMEOUT_MARGIN_MS

    def setPacketTimeout(self, packet_length):  # noqa: N802 - the SDK's name
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.timeout_margin_ms

    def writePort(self, packet):  # noqa: N802 - the SDK's name
        # not pyserial's write: a complete write counts as done however late (drivers/fdio.py)
        return write_all(self.ser.fileno(), bytes(packet), WRITE_TIMEOUT_S, f"Dynamixel port {self.port_name}")

    def setupPort(self, cflag_baud):  # noqa: N802 - the SDK's name
        """The SDK's setup, but the port is locked for this process (``exclusive``) and
        writes time out."""
        if self.is_open:
            self.closePort()
        self.ser = serial.Serial(port=self.port_name, baudrate=self.baudrate, bytesize=serial.EIGHTBITS,
                                 timeout=0, write_timeout=WRITE_TIMEOUT_S, exclusive=True)
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True


class DynamixelBus:
    def __init__(self, port_name: str, baudrate: int, table: ControlTable | None = None,
                 timeout_margin_ms: float = SDK_TIMEOUT_MARGIN_MS):
        self.port_name = port_name
        self.baudrate = baudrate
        self.table = table or control_table()
        self.port = _Port(port_name)
        self.port.timeout_margin_ms = float(timeout_margin_ms)
        self.ph = PacketHandler(2.0)
        self.lock = threading.RLock()
        self.stats = {"instructions": 0, "status_ok": 0, "crc_errors": 0, "missing_status": 0,
                      "tx_errors": 0, "servo_errors": 0}
        self.last_rtt_s: float | None = None
        self.last_error: str | None = None
        self.emulator: EmulatorProcess | None = None
        self._refs = 0
        self._closed = True

    # ------------------------------------------------------------------ open / close
    def open(self) -> None:
        try:
            ok = self.port.setBaudRate(self.baudrate)
        except Exception as e:  # pyserial's SerialException: port missing, busy, no permission
            if "exclusively lock" in str(e):
                raise LinkError(f"Dynamixel port {self.port_name} is in use by another process (one process "
                                "owns a bus: run the robots of one bus in one `hil up`)") from None
            raise LinkError(f"cannot open Dynamixel port {self.port_name}: {e}") from None
        if not ok:
            raise LinkError(f"cannot open Dynamixel port {self.port_name} at {self.baudrate} baud")
        self._closed = False

    def close(self) -> None:
        if not self._closed:
            try:
                self.port.closePort()
            except Exception:
                pass
            self._closed = True
        if self.emulator is not None:
            if self.emulator.alive:  # a frozen (SIGSTOPped) emulator must run to take its SIGTERM
                os.kill(self.emulator.proc.pid, signal.SIGCONT)
            self.emulator.stop()
            self.emulator = None

    @property
    def closed(self) -> bool:
        return self._closed

    def emulator_tail(self, n: int = 10) -> str:
        return "(no emulator)" if self.emulator is None else self.emulator.tail(n)

    # ------------------------------------------------------------------ bookkeeping
    def _count(self, result: int, error: int = 0) -> None:
        if result == COMM_SUCCESS:
            self.stats["status_ok"] += 1
            if error & 0x7F:
                self.stats["servo_errors"] += 1
        elif result == COMM_RX_CORRUPT:
            self.stats["crc_errors"] += 1
        elif result == COMM_RX_TIMEOUT:
            self.stats["missing_status"] += 1
        else:
            self.stats["tx_errors"] += 1

    def _check(self, what: str, dxl_id: int, result: int, error: int) -> None:
        self._count(result, error)
        if result != COMM_SUCCESS:
            msg = f"{what} ID {dxl_id}: {self.ph.getTxRxResult(result)}"
            self.last_error = msg
            raise LinkError(msg)
        if error & 0x7F:
            msg = f"{what} ID {dxl_id}: servo answered {describe_status_error(error)}"
            self.last_error = msg
            raise ServoError(msg)

    def _require_open(self) -> None:
        if self._closed:
            raise LinkError(f"Dynamixel port {self.port_name} is closed")

    def _io(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Call the SDK; a failing port (adapter unplugged: EIO) becomes a LinkError,
        and the SDK's busy flag is cleared so the stop that follows can still try."""
        try:
            return fn(*args)
        except (OSError, SerialException, termios.error) as e:
            self.port.is_using = False
            self.stats["tx_errors"] += 1
            self.last_error = f"Dynamixel port {self.port_name} failed: {e}"
            raise LinkError(self.last_error) from None

    # ------------------------------------------------------------------ single servo
    def ping(self, dxl_id: int) -> tuple[int, int]:
        """(model number, status error byte) of a servo; LinkError if it does not answer."""
        with self.lock:
            self._require_open()
            self.stats["instructions"] += 1
            model, result, error = self._io(self.ph.ping, self.port, dxl_id)
            self._count(result, error)
            if result != COMM_SUCCESS:
                msg = f"ping ID {dxl_id}: {self.ph.getTxRxResult(result)}"
                self.last_error = msg
                raise LinkError(msg)
            return model, error

    def read(self, dxl_id: int, item: str) -> int:
        it = self.table[item]
        with self.lock:
            self._require_open()
            self.stats["instructions"] += 1
            data, result, error = self._io(self.ph.readTxRx, self.port, dxl_id, it.address, it.size)
            self._check(f"read {item}", dxl_id, result, error)
            return it.decode(bytes(data))

    def write(self, dxl_id: int, item: str, value: int) -> None:
        it = self.table[item]
        with self.lock:
            self._require_open()
            self.stats["instructions"] += 1
            result, error = self._io(self.ph.writeTxRx, self.port, dxl_id, it.address, it.size,
                                     list(it.encode(value)))
            self._check(f"write {item}={value}", dxl_id, result, error)

    def reboot(self, dxl_id: int) -> None:
        with self.lock:
            self._require_open()
            self.stats["instructions"] += 1
            result, error = self._io(self.ph.reboot, self.port, dxl_id)
            self._check("reboot", dxl_id, result, error)

    # ------------------------------------------------------------------ groups
    def sync_write(self, item: str, values: dict[int, int]) -> None:
        """One SYNC_WRITE of ``item`` to several IDs (no status packets come back)."""
        it = self.table[item]
        param: list[int] = []
        for dxl_id, v in values.items():
            param += [dxl_id, *it.encode(v)]
        with self.lock:
            self._require_open()
            self.stats["instructions"] += 1
            result = self._io(self.ph.syncWriteTxOnly, self.port, it.address, it.size, param, len(param))
            if result != COMM_SUCCESS:
                self._count(result)
                msg = f"sync write {item}: {self.ph.getTxRxResult(result)}"
                self.last_error = msg
                raise LinkError(msg)

    def sync_read(self, ids: Iterable[int], first: str, last: str,
                  timeout_margin_ms: float | None = None) -> tuple[dict[int, bytes], dict[int, int]]:
        """SYNC_READ of the block ``first..last`` from ``ids``, waiting for the answers at
        most their transfer time plus ``timeout_margin_ms`` (default: the bus's margin).

        Returns ``(data, errors)``: the raw block of every servo that answered, and the
        status error byte of every answer that had one. IDs that did not answer (or
        whose answer was corrupt) are absent from ``data``."""
        ids = list(ids)
        addr, n = self.table.span(first, last)
        data: dict[int, bytes] = {}
        errors: dict[int, int] = {}
        with self.lock:
            self._require_open()
            self.stats["instructions"] += 1
            t0 = time.monotonic()
            margin = self.port.timeout_margin_ms
            if timeout_margin_ms is not None:
                self.port.timeout_margin_ms = min(margin, float(timeout_margin_ms))
            try:
                result = self._io(self.ph.syncReadTx, self.port, addr, n, ids, len(ids), False)
            finally:
                self.port.timeout_margin_ms = margin
            if result != COMM_SUCCESS:
                self._count(result)
                self.last_error = f"sync read: {self.ph.getTxRxResult(result)}"
                raise LinkError(self.last_error)
            pending = set(ids)
            corrupt = 0
            while pending:
                pkt, result = self._io(self.ph.rxPacket, self.port, False)
                if result == COMM_RX_TIMEOUT:
                    break  # counted below, per ID that did not answer
                self._count(result, pkt[_PKT_ERROR] if result == COMM_SUCCESS else 0)
                if result != COMM_SUCCESS:
                    if result == COMM_RX_CORRUPT:
                        self.last_error = "sync read: a status packet failed its CRC"
                        corrupt += 1
                        if len(data) + corrupt >= len(ids):
                            break  # every servo answered once: waiting on would only time out
                        continue
                    break
                dxl_id = pkt[_PKT_ID]
                if dxl_id in pending:
                    pending.discard(dxl_id)
                    data[dxl_id] = bytes(pkt[_PKT_PARAM:_PKT_PARAM + n])
                    if pkt[_PKT_ERROR]:
                        errors[dxl_id] = pkt[_PKT_ERROR]
            # IDs that sent nothing at all (a corrupt answer is counted as a CRC error only)
            missing = pending - set(data)
            n_missing = max(0, len(missing) - corrupt)
            self.stats["missing_status"] += n_missing
            if missing:
                self.last_error = f"sync read: no status packet from ID(s) {sorted(missing)}"
            self.last_rtt_s = time.monotonic() - t0
        return data, errors

    def decode(self, raw: bytes, first: str, item: str) -> int:
        """An item's value out of a block read starting at item ``first``."""
        it = self.table[item]
        off = it.address - self.table[first].address
        return it.decode(raw[off:off + it.size])


# ---------------------------------------------------------------------- sharing and emulator
_BUSES: dict[str, DynamixelBus] = {}
_BUSES_LOCK = threading.Lock()


def acquire_bus(key: str, opener: Callable[[], DynamixelBus]) -> DynamixelBus:
    """The open bus for ``key`` (a port, or an emulated bus name), opened on first use."""
    with _BUSES_LOCK:
        bus = _BUSES.get(key)
        if bus is None or bus.closed:
            bus = opener()
            _BUSES[key] = bus
        bus._refs += 1
        return bus


def release_bus(key: str, bus: DynamixelBus) -> None:
    with _BUSES_LOCK:
        bus._refs -= 1
        if bus._refs <= 0:
            bus.close()
            if _BUSES.get(key) is bus:
                del _BUSES[key]


#: the emulator shares loaded cores with the driver (a load of 7 on 2 cores here made
#: 150 ms too short once in a few runs): give its answers more time
EMULATED_TIMEOUT_MARGIN_MS = 400.0


def start_emulator(config: dict[str, Any], baudrate: int, start_timeout_s: float = EMULATOR_START_TIMEOUT_S,
                   module: str | None = None,
                   timeout_margin_ms: float = EMULATED_TIMEOUT_MARGIN_MS, keep_log: bool = False) -> DynamixelBus:
    """Start the bus emulator process on a pty and open a bus on it."""
    emu = EmulatorProcess(module or emulator_module("widowx"), ["--print-pty", "--config", json.dumps(config)], start_timeout_s=start_timeout_s,
                          keep_log=keep_log)
    info = emu.start()
    bus = DynamixelBus(info["pty"], baudrate, timeout_margin_ms=timeout_margin_ms)
    bus.emulator = emu
    try:
        bus.open()
    except Exception:
        bus.close()
        raise
    return bus
