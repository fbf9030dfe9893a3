"""Dynamixel bus emulator: a process that behaves like the servos of one bench.

It owns the device end of a serial link (a pty it creates with ``--print-pty``) and
answers Protocol 2.0 instruction packets for every servo of the simulated bench:
PING, READ, WRITE, REBOOT, SYNC_READ, SYNC_WRITE, each servo with its own control table
(:mod:`.firmware`), on the bench's MuJoCo world (a :class:`.world.ServoWorld`) advanced in
real time in 1 ms servo ticks. A bench's emulator module builds its world and calls
:func:`main` (sim_backends/widowx/emulator.py, sim_backends/pan_unit/emulator.py).

It must be a separate process: dynamixel-sdk busy-polls the port and starves any thread
of its own process (docs/arms.md).

On start it prints one JSON line ``{"pty": ..., "pid": ...}`` on stdout; logs go to
stderr. It stops on SIGTERM, on SIGINT unless a parent started it (bus/lifetime.py: Ctrl-C
in the driver's terminal must not cut the bus before the driver's stop), or when the parent dies.

Fault injection (config keys): ``missing_ids`` (these IDs never answer, as an unplugged
servo), ``hardware_errors`` ({id: bits}: latched at power-on, cleared by a reboot
unless ``persistent_errors``), ``corrupt_every`` (every N-th status packet gets a bad
CRC), ``garbage_every`` (noise bytes before every N-th status packet).

Host death (tests): ``state_file`` (a path) gets one JSON line every ``state_every_s``
wall-clock seconds: ``{"t": monotonic [s], "sim_t": [s], "servos": {id: [position
rad, velocity rad/s, Bus Watchdog]}}``, read without sending the servos a packet (a
read over the bus would feed their watchdog). ``linger_s``: when the parent process
dies, go on simulating the servos this long before exiting, as a real bench stays
powered after its host died (default 0: exit at once).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import sys
import threading
import time
import tty
from collections.abc import Callable
from typing import Any

from hilstack.bus.cycle import Rate
from hilstack.bus.lifetime import exit_with_parent
from hilstack.drivers.dynamixel import protocol as p
from hilstack.sim_backends.base import RealtimePacer
from hilstack.sim_backends.dynamixel.firmware import TICK_S
from hilstack.sim_backends.dynamixel.world import ServoWorld

#: never integrate more than this per loop: if the CPU falls behind, sim time slips
MAX_CATCHUP_S = 0.05


def log(msg: str) -> None:
    print(f"[dynamixel-emulator {os.getpid()}] {msg}", file=sys.stderr, flush=True)


class BusEmulator:
    """The servos of one bus answering instruction packets. No I/O: bytes in, bytes out."""

    def __init__(self, world: ServoWorld, *, missing_ids: list[int] | tuple[int, ...] = (),
                 hardware_errors: dict[int, int] | None = None, persistent_errors: bool = False,
                 corrupt_every: int = 0, garbage_every: int = 0):
        self.world = world
        self.missing = set(missing_ids)
        self.corrupt_every = int(corrupt_every)
        self.garbage_every = int(garbage_every)
        self.parser = p.Parser()
        self.status_sent = 0
        self.instructions = 0
        self.injected_corrupt = 0
        self.realtime_slip_s = 0.0  # sim time given up because the CPU fell behind
        for dxl_id, bits in (hardware_errors or {}).items():
            self.world.servos[int(dxl_id)].inject_hardware_error(int(bits), persistent=persistent_errors)

    def _status(self, dxl_id: int, error: int, data: bytes = b"") -> bytes:
        raw = bytearray(p.encode_status(dxl_id, error, data))
        self.status_sent += 1
        if self.corrupt_every and self.status_sent % self.corrupt_every == 0:
            raw[-1] ^= 0xA5  # bad CRC: the driver must count it and go on
            self.injected_corrupt += 1
        if self.garbage_every and self.status_sent % self.garbage_every == 0:
            raw = bytearray(b"\x00\x13\xff\x37") + raw
        return bytes(raw)

    def _servo(self, dxl_id: int):
        if dxl_id in self.missing:
            return None
        return self.world.servos.get(dxl_id)

    def feed(self, data: bytes) -> bytes:
        """Bytes from the bus -> the bytes all servos put on the bus in answer."""
        out = bytearray()
        for pkt in self.parser.feed(data):
            self.instructions += 1
            out += self.handle(pkt)
        return bytes(out)

    def handle(self, pkt: p.Packet) -> bytes:
        inst, prm = pkt.instruction, pkt.params
        if inst == p.SYNC_WRITE:
            if len(prm) < 4:
                return b""
            addr, n = prm[0] | prm[1] << 8, prm[2] | prm[3] << 8
            body = prm[4:]
            for k in range(0, len(body) - n, n + 1) if n else ():
                s = self._servo(body[k])
                if s is not None:
                    s.heard()
                    s.write(addr, bytes(body[k + 1:k + 1 + n]))  # no status for sync write
            return b""
        if inst == p.SYNC_READ:
            if len(prm) < 4:
                return b""
            addr, n = prm[0] | prm[1] << 8, prm[2] | prm[3] << 8
            out = bytearray()
            for dxl_id in prm[4:]:  # each servo answers in the order asked
                s = self._servo(dxl_id)
                if s is not None:
                    s.heard()
                    err, data = s.read(addr, n)
                    out += self._status(dxl_id, err | s.status_error(), data)
            return bytes(out)
        ids = list(self.world.servos) if pkt.dxl_id == p.BROADCAST_ID else [pkt.dxl_id]
        out = bytearray()
        for dxl_id in ids:
            s = self._servo(dxl_id)
            if s is None:
                continue
            s.heard()
            reply = pkt.dxl_id != p.BROADCAST_ID or inst == p.PING
            if inst == p.PING:
                data = s.table["Model Number"].encode(s.get("Model Number")) + bytes([s.get("Firmware Version")])
                out += self._status(dxl_id, s.status_error(), data)
            elif inst == p.READ and len(prm) == 4:
                err, data = s.read(prm[0] | prm[1] << 8, prm[2] | prm[3] << 8)
                out += self._status(dxl_id, err | s.status_error(), data)
            elif inst == p.WRITE and len(prm) >= 3:
                err = s.write(prm[0] | prm[1] << 8, bytes(prm[2:]))
                if reply:
                    out += self._status(dxl_id, err | s.status_error())
            elif inst == p.REBOOT:
                if reply:
                    out += self._status(dxl_id, 0)
                s.power_on()
            elif reply:
                out += self._status(dxl_id, p.ERR_INSTRUCTION | s.status_error())
        return bytes(out)

    def summary(self) -> dict[str, Any]:
        return {"instructions": self.instructions, "status_sent": self.status_sent,
                "rx_crc_errors": self.parser.crc_errors, "rx_garbage_bytes": self.parser.garbage_bytes,
                "injected_corrupt": self.injected_corrupt, "sim_time_s": round(self.world.time_s, 3)}


def servo_states(world: ServoWorld) -> dict[str, list[float]]:
    """ID -> [position rad, velocity rad/s, Bus Watchdog] of the last servo tick."""
    out = {}
    for i, s in world.servos.items():
        q, qd, _ = s._present
        out[str(i)] = [round(q, 5), round(qd, 5), s.get("Bus Watchdog")]
    return out


def run(bus: BusEmulator, fd: int, parent_gone: threading.Event, running: list[bool], rtf: float = 1.0,
        state_file: str | None = None, state_every_s: float = 0.02, linger_s: float = 0.0) -> None:
    """Serve the pty until stopped (``running[0]`` False), or ``linger_s`` after ``parent_gone``
    is set (bus/lifetime.py)."""
    pacer = RealtimePacer(bus.world.time_s, TICK_S, MAX_CATCHUP_S, rtf, now_s=time.monotonic())
    states = open(state_file, "a", buffering=1) if state_file else None  # noqa: SIM115 - closed below
    try:
        _loop(bus, fd, parent_gone, running, pacer, states, state_every_s, linger_s)
    finally:
        if states is not None:
            states.close()


def _loop(bus, fd, parent_gone, running, pacer, states, state_every_s, linger_s) -> None:
    world = bus.world
    state_rate = Rate(state_every_s, time.monotonic())  # the state file's lines (bus/cycle.py)
    exit_at: float | None = None
    while running[0]:
        now = time.monotonic()
        wait = max(0.0, min(TICK_S, world.time_s + TICK_S - pacer.target_s(now)))
        r, _, _ = select.select([fd], [], [], wait)
        if r:
            try:
                data = os.read(fd, 4096)
            except OSError as e:
                log(f"port gone: {e}")
                return
            reply = bus.feed(data)
            if reply:
                os.write(fd, reply)
        now = time.monotonic()
        # step one tick at a time, checking the port between ticks: answers stay prompt
        if pacer.due(now, world.time_s) >= 1:
            world.step()
        bus.realtime_slip_s = pacer.slip_s
        if states is not None and state_rate.due(now):
            states.write(json.dumps({"t": now, "sim_t": round(world.time_s, 4), "servos": servo_states(world)}) + "\n")
        if exit_at is not None and now >= exit_at:
            log("lingered after the parent: exiting")
            return
        if exit_at is None and parent_gone.is_set():
            if linger_s <= 0:
                log("parent process is gone: exiting")
                return
            log(f"parent process is gone: the servos run on for {linger_s:g} s")
            exit_at = now + linger_s


def main(argv: list[str] | None, make_world: Callable[[dict[str, Any]], ServoWorld], prog: str) -> int:
    """Serve the bench ``make_world(config)`` builds (its keys beside the fault keys above)."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    ap.add_argument("--print-pty", action="store_true", required=True, help="create a pty and print its path")
    ap.add_argument("--config", default="{}", help="JSON: the bench's keys, missing_ids, hardware_errors, ...")
    args = ap.parse_args(argv)
    cfg = json.loads(args.config)
    try:
        world = make_world(cfg)
    except ValueError as e:  # a bad bench key (effects, mjcf, ...): one line, exit 2
        print(f"error: --config {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    bus = BusEmulator(world, missing_ids=[int(i) for i in cfg.get("missing_ids", [])],
                      hardware_errors={int(k): int(v) for k, v in cfg.get("hardware_errors", {}).items()},
                      persistent_errors=bool(cfg.get("persistent_errors", False)),
                      corrupt_every=int(cfg.get("corrupt_every", 0)), garbage_every=int(cfg.get("garbage_every", 0)))
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    path = os.ttyname(slave)
    running = [True]

    def _stop(signum, frame):  # noqa: ARG001
        running[0] = False

    parent_gone = threading.Event()
    parent = exit_with_parent(parent_gone.set)
    signal.signal(signal.SIGTERM, _stop)
    # started by a driver (bus/lifetime.py): Ctrl-C in its terminal reaches us too, but the
    # driver must still send its stop over the bus; it ends us (SIGTERM) when it is done
    signal.signal(signal.SIGINT, signal.SIG_IGN if parent is not None else _stop)
    print(json.dumps({"pty": path, "pid": os.getpid()}), flush=True)
    log(f"serving {path}: IDs {sorted(world.servos)}, missing {sorted(bus.missing)}")
    try:
        run(bus, master, parent_gone, running, float(cfg.get("realtime_factor", 1.0)),
            state_file=cfg.get("state_file"), state_every_s=float(cfg.get("state_every_s", 0.02)),
            linger_s=float(cfg.get("linger_s", 0.0)))
    finally:
        log(f"summary {json.dumps({**bus.summary(), 'realtime_slip_s': round(bus.realtime_slip_s, 4)})}")
        os.close(master)
        os.close(slave)
    return 0

