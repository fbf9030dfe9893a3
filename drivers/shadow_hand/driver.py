"""Shadow Hand driver: the driver contract over the hand's CAN bus (python-can + the DBC).

Transports, chosen by ``params.transport`` (python-can interfaces):

* ``socketcan``: a CAN adapter the kernel knows (``channel: can0``); real rigs.
* ``slcan``: a USB-serial CAN adapter in SLCAN mode (``channel: /dev/ttyACM0``).
* ``udp_multicast``: CAN frames over UDP multicast (``channel``: an IPv4 group). Used by
  the emulated backend; the bus echoes our own frames, which are filtered out by id.

backend "emulated" starts the firmware emulator (``python -m hilstack.sim_backends.shadow_hand.
emulator``) as its own process, on a pty it creates (slcan; also when the config
says socketcan, which needs a kernel CAN interface) or on a free UDP port
(udp_multicast), unless ``params.emulator.spawn`` is false (then ``channel`` names an
emulator that is already running).

Threads: a reader thread drains the bus, assembles telemetry cycles, sends the host
heartbeat (feeding the firmware watchdog) and runs the driver-side watchdog; ``read()``
only copies the newest telemetry under a lock. ``write()`` sends the five target frames
from the caller's thread (sends are serialized by a lock).

Safety: the firmware holds position when heartbeats stop (host or link dead); the driver
sends stop (hold the measured position) when the caller has not written for
``driver_watchdog_s``; telemetry older than ``telemetry_deadline_s`` makes a reading
``ok=False`` with ``flags["stale_telemetry"]``; no complete telemetry cycle for
``link_timeout_periods`` control periods (a frozen or dead hand, the link open or not)
takes the error path on the next ``read()`` or ``write()`` (the contract's rule,
drivers/base.py); any link failure goes through ``fail()``, which tries to send the stop
while the port is still open.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from typing import Any

import numpy as np

from hilstack.bus.cycle import Rate
from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import (
    Driver,
    Flag,
    Freshness,
    Health,
    Inputs,
    LinkError,
    Observation,
    require_device,
)
from hilstack.drivers.emulator_process import EmulatorProcess, emulator_module
from hilstack.drivers.shadow_hand.config import (
    ACT_INDEX,
    ShadowHandParams,
    joint_tracking_error,
    shadow_hand_spec,
    to_action,
    to_joint_rad,
)
from hilstack.drivers.shadow_hand.protocol import (
    FAULT_ESTOP,
    FAULT_MOTOR,
    FAULT_WATCHDOG,
    FW_TICK_S,
    HAND_IDS,
    HOST_IDS,
    HOST_MODE_POSITION,
    ProtocolError,
    Telemetry,
    TelemetryAssembler,
    decode,
    encode,
    encode_targets,
    unwrap_fw_clock,
)

DEFAULT_UDP_GROUP = "239.74.163.2"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


class ShadowHandDriver(Driver):
    params_type = ShadowHandParams

    def __init__(self, params: ShadowHandParams | None = None, backend: str = "real", source: str | None = None):
        super().__init__()
        params = params or ShadowHandParams()
        if backend == "emulated" and params.transport == "socketcan":
            # no kernel CAN here (no vcan): the emulator stands in for the adapter over SLCAN
            params = params.model_copy(update={"transport": "slcan"})
        self.params = params
        self.backend = backend
        self.source = source
        self.spec = shadow_hand_spec(self.params)
        self.bus: Any = None
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._hb_rate: Rate | None = None  # the heartbeat's deadline (reader thread)
        self._emu: EmulatorProcess | None = None
        #: UDP port of the emulator's lab fixture (params.emulator.lab_fixture; drivers/fixture.py)
        self._fixture_port: int | None = None
        self._balls: list[Any] = []  # UdpPoseClient per ball, when a tracker streams them
        self._asm = TelemetryAssembler()
        self._tel: Telemetry | None = None
        self._tel_t: float | None = None
        #: the hand's own clock (HAND_STATUS.t_fw_ms): the last raw count and its unwrapped total [ticks]
        self._fw_raw: int | None = None
        self._fw_total = 0
        #: the hand's telemetry: stale after telemetry_deadline_s, the error path after
        #: link_timeout_periods control periods without a complete cycle (a frozen or dead hand)
        self.inputs = Inputs(Freshness.fail_after_periods(
            "telemetry", params.telemetry_deadline_s, Flag.STALE_TELEMETRY, params.link_timeout_periods,
            params.period_s))
        self._reader_error: str | None = None
        self._seq = 0
        self._hb_counter = 0
        self._estop_counter = 0
        self._last_cmd_t: float | None = None
        self._wd_fired = False
        self.frames_sent = 0
        self.frames_received = 0
        self.corrupt_frames = 0
        self.foreign_frames = 0
        self.bus_error_frames = 0
        self.driver_watchdog_trips = 0
        self.last_corrupt: str | None = None

    #: measured − commanded actuated joint angles (used by `hil drive`)
    tracking_error = staticmethod(joint_tracking_error)

    # ------------------------------------------------------------------ lifecycle
    def _on_configure(self) -> None:
        p = self.params
        spawn = self.backend == "emulated" and p.emulator.spawn
        if not spawn and not p.channel:
            raise ConfigError(self.source, [("params.channel", f"no CAN channel for transport {p.transport}: "
                                             "e.g. can0 (socketcan), /dev/ttyACM0 (slcan)")])
        channel, udp_port = p.channel, p.emulator.udp_port
        self._open_ball_tracker(spawn)
        if spawn:
            channel, udp_port = self._start_emulator()
        self.bus = self._open_bus(channel, udp_port)
        with self._lock:
            self._tel = self._tel_t = None
            self._fw_raw, self._fw_total = None, 0
            self.inputs.start(time.monotonic())
        self._stop_evt.clear()
        self._reader_error = None
        self._thread = threading.Thread(target=self._reader, name="shadow-hand-can", daemon=True)
        self._thread.start()
        self._wait_first_telemetry()

    def _open_ball_tracker(self, spawn: bool) -> None:
        """Ball positions come from a tracker, not from the hand: one UDP pose stream per
        ball (``hilstack.drivers.mocap.udp``). The emulator streams its sim's balls to ports we pick."""
        from hilstack.drivers.mocap.udp import UdpPoseClient

        p = self.params
        if spawn and p.emulator.balls:
            self._balls = [UdpPoseClient("127.0.0.1", 0) for _ in range(2)]
        elif p.ball_tracker_ports:
            if len(p.ball_tracker_ports) != 2:
                raise ConfigError(self.source, [("params.ball_tracker_ports", "expected two ports (ball 0, ball 1), "
                                                 f"got {p.ball_tracker_ports}")])
            self._balls = [UdpPoseClient("0.0.0.0", port) for port in p.ball_tracker_ports]
        if p.objects_in_state and not self._balls:
            raise ConfigError(self.source, [("params.objects_in_state", "needs ball positions: set "
                                             "params.ball_tracker_ports (or emulator.balls: true)")])

    def _open_bus(self, channel: str, udp_port: int | None) -> Any:
        import can

        p = self.params
        if p.transport == "slcan":
            require_device(channel, self.source, "params.channel", "the SLCAN adapter")
        try:
            if p.transport == "socketcan":
                return can.Bus(interface="socketcan", channel=channel)
            if p.transport == "slcan":
                # serial read timeout: python-can's 1 ms default wakes the reader 1000 times a
                # second when the bus is idle; 10 ms is well inside the telemetry deadline.
                # A pty needs no settling after open (a USB adapter may reset: keep python-can's)
                extra = {"sleep_after_open": 0.0} if self.backend == "emulated" else {}
                return can.Bus(interface="slcan", channel=channel, bitrate=p.bitrate, timeout=0.01, **extra)
            return can.Bus(interface="udp_multicast", channel=channel or DEFAULT_UDP_GROUP,
                           port=int(udp_port or 43113), fd=False)
        except (can.CanError, OSError, ValueError) as e:
            raise LinkError(f"cannot open {p.transport} channel {channel}: {e}") from None

    def _start_emulator(self) -> tuple[str, int | None]:
        p = self.params
        args = ["--transport", p.transport, "--config", json.dumps(p.model_dump(mode="json"))]
        if self._balls:
            args += ["--ball-ports", ",".join(str(c.port) for c in self._balls)]
        if p.emulator.lab_fixture:
            args += ["--fixture-port", "0"]
        if p.transport == "slcan":
            args.append("--print-pty")
        else:
            args += ["--channel", p.channel or DEFAULT_UDP_GROUP,
                     "--udp-port", str(p.emulator.udp_port or free_udp_port())]
        self._emu = EmulatorProcess(emulator_module("shadow_hand"), args,
                                    start_timeout_s=p.emulator.start_timeout_s,
                                    keep_log=p.emulator.keep_log)
        info = self._emu.start()
        # the lab fixture is beside the hand, not on its CAN bus: the reset step finds it in the health
        self._fixture_port = info.get("fixture_port")
        return info["channel"], info.get("port")

    def _emu_tail(self, n: int = 15) -> str:
        return "(no emulator)" if self._emu is None else self._emu.tail(n)

    def _wait_first_telemetry(self) -> None:
        timeout_s = self.params.emulator.connect_timeout_s if self.backend == "emulated" else 3.0
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if self._reader_error:
                    raise LinkError(self._reader_error)
                if self._tel is not None:
                    return
            time.sleep(0.01)
        hint = (f"emulator log:\n{self._emu_tail()}" if self.backend == "emulated" else
                f"is the hand powered, the adapter on {self.params.channel} up at {self.params.bitrate} bit/s "
                "and the bus terminated (120 Ω at both ends)?")
        raise LinkError(f"no complete telemetry cycle from the hand within {timeout_s:.0f} s "
                        f"({self.frames_received} frames, {self.corrupt_frames} corrupt); {hint}")

    def _on_activate(self) -> None:
        # the firmware leaves its boot hold and tracks the measured position: nothing jumps
        self._send_targets(self._held)
        self._last_cmd_t = time.monotonic()
        self._wd_fired = False

    def _on_cleanup(self) -> None:
        self._stop_evt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception:
                pass  # already gone with its port
            self.bus = None
        if self._emu is not None:
            self._emu.stop()
            self._emu = None
        for c in self._balls:
            c.close()
        self._balls = []

    # ------------------------------------------------------------------ reader thread
    def _reader(self) -> None:
        import can

        bus = self.bus
        # the host heartbeat: one scheduler (bus/cycle.py), a late one skips and counts
        self._hb_rate = hb = Rate(1.0 / self.params.heartbeat_hz, time.monotonic())
        while not self._stop_evt.is_set():
            try:
                msg = self._recv_one(bus, timeout_s=0.005)
                now = time.monotonic()
                if msg is not None:
                    self._handle(msg, now)
                if hb.due(now):
                    self._heartbeat()
                self._driver_watchdog(now)
            except (can.CanError, OSError) as e:
                err = f"CAN link lost ({self.params.transport}): {e}"
                with self._lock:
                    self._reader_error = err if self._emu is None else self._emu.failure(err)
                return
            except Exception as e:  # a bug here must show up in health, not kill the link silently
                with self._lock:
                    self._reader_error = f"CAN reader crashed: {type(e).__name__}: {e}"
                return

    def _recv_one(self, bus: Any, timeout_s: float) -> Any:
        """One frame from the bus, or None. A garbled SLCAN line is a corrupt frame, not a
        dead link: python-can's slcan parser raises ValueError (bad hex, bad digit) or
        IndexError (a short line) on it, and a CanOperationError caused by a
        UnicodeDecodeError on non-ASCII bytes, which it also leaves in its line buffer:
        ``flush()`` clears that buffer, or every later read would fail the same way.
        Anything else from the bus (the port vanished) is a link failure and propagates."""
        import can

        try:
            return bus.recv(timeout=timeout_s)
        except (ValueError, IndexError) as e:
            self._count_corrupt(f"unparsable frame from the adapter: {type(e).__name__}: {e}")
        except can.CanOperationError as e:
            if not isinstance(e.__cause__, UnicodeDecodeError):
                raise
            self._count_corrupt(f"non-ASCII bytes from the adapter: {e.__cause__}")
            bus.flush()
        return None

    def _count_corrupt(self, why: str) -> None:
        with self._lock:
            self.corrupt_frames += 1
            self.last_corrupt = why

    def _handle(self, msg: Any, now: float) -> None:
        if msg.is_error_frame:
            with self._lock:
                self.bus_error_frames += 1  # the controller saw a bus error (socketcan)
            return
        mid = msg.arbitration_id
        if mid in HOST_IDS:
            return  # our own frame echoed by a multicast bus
        if mid not in HAND_IDS or msg.is_extended_id or msg.is_remote_frame:
            with self._lock:
                self.foreign_frames += 1  # another node on a shared bus: not ours, not corrupt
            return
        try:
            _, vals = decode(mid, bytes(msg.data))
        except ProtocolError as e:
            self._count_corrupt(str(e))
            return
        with self._lock:
            self.frames_received += 1
            tel = self._asm.feed(mid, vals)
            if tel is not None:
                # every complete cycle advances the hand's clock (the reader sees them all, 20 ms apart)
                self._fw_total = unwrap_fw_clock(self._fw_raw, tel.t_fw_ms, self._fw_total)
                self._fw_raw = tel.t_fw_ms
                self._tel, self._tel_t = tel, now
                self.inputs["telemetry"].update(now)

    def _send(self, mid: int, data: bytes) -> None:
        import can

        bus = self.bus
        if bus is None:
            raise LinkError("CAN bus not open")
        with self._send_lock:
            try:
                bus.send(can.Message(arbitration_id=mid, data=data, is_extended_id=False))
            except (can.CanError, OSError) as e:
                raise LinkError(f"CAN send failed ({self.params.transport}): {e}") from None
            self.frames_sent += 1

    def _heartbeat(self) -> None:
        self._hb_counter = (self._hb_counter + 1) % 256
        self._send(*encode("HOST_HEARTBEAT", {"counter": self._hb_counter, "host_mode": HOST_MODE_POSITION}))

    def _driver_watchdog(self, now: float) -> None:
        """The caller went quiet while active: hold the measured position, once."""
        if not self.active or self._last_cmd_t is None or self._wd_fired:
            return
        if now - self._last_cmd_t > self.params.driver_watchdog_s:
            held = self._hold_measured()
            if held is not None:  # the next write ramps from what the hand now holds
                self._anchor(held, self.now())
            # flag after the hold is sent: whoever sees the flag sees the new held command
            self.driver_watchdog_trips += 1
            self._wd_fired = True

    def _send_targets(self, action: np.ndarray) -> None:
        try:
            frames = encode_targets(to_joint_rad(action))
        except ProtocolError as e:
            # the base class validated already; reaching this is a bug upstream, never a send
            raise LinkError(f"refused to send bad targets: {e}") from None
        for mid, data in frames:
            self._send(mid, data)

    def _hold_measured(self) -> np.ndarray | None:
        """Send the measured joint angles as targets; returns that action (None: no telemetry)."""
        with self._lock:
            tel = self._tel
        if tel is None:
            return None
        a = to_action(tel.q_rad[ACT_INDEX])
        self._send_targets(a)
        return a

    # ------------------------------------------------------------------ contract hooks
    def _check_link(self) -> None:
        emu = self._emu
        if emu is not None and emu.proc is not None and not emu.alive:
            # over UDP a dead emulator is only silence: say what happened instead of going stale
            with self._lock:
                self._reader_error = self._reader_error or emu.failure(
                    f"the emulator exited with code {emu.proc.returncode}")
        with self._lock:
            err = self._reader_error
        if err:
            self.fail_link(err)  # tries the stop while the port is open, then closes

    def _read(self) -> Observation:
        self._check_link()
        now = time.monotonic()
        with self._lock:
            tel, tel_t = self._tel, self._tel_t
            dev_t = self._fw_total * FW_TICK_S
            ok, flags = self.inputs.assess(now, report=True)
        age = now - tel_t
        state = np.concatenate([tel.q_rad, tel.qd_rad_s])
        flags = {
            **flags,  # stale_telemetry, nonfinite_input, invalid_input
            "watchdog": bool(tel.faults & FAULT_WATCHDOG),
            "estop": bool(tel.faults & FAULT_ESTOP),
            "motor_fault": bool(tel.faults & FAULT_MOTOR),
            "driver_watchdog": self._wd_fired,
        }
        extras = {"effort_nm": tel.effort_nm.copy(), "mode": tel.mode, "faults": tel.faults,
                  "motor_fault_mask": tel.motor_fault_mask, "telemetry_age_s": age, "t_fw_ms": tel.t_fw_ms}
        if self._balls:
            samples = [c.latest() for c in self._balls]
            have = all(smp is not None for smp in samples)
            extras["balls_m"] = np.stack([smp.position_m for smp in samples]) if have else None
            ages = [now - smp.received_s for smp in samples] if have else None
            extras["balls_age_s"] = None if ages is None else max(ages)
            # a separate sensor: stale balls are flagged, the hand's own reading stays valid
            flags["stale_objects"] = not (have and max(ages) <= self.params.telemetry_deadline_s)
        if self.params.objects_in_state:
            # no ball reading yet: NaN makes the reading not ok (drivers/base.py), never a made-up pose
            balls = extras.get("balls_m")
            state = np.concatenate([state, np.full(6, np.nan) if balls is None else np.asarray(balls).reshape(-1)])
        self._seq += 1
        return Observation(
            t_s=tel_t, state=state, seq=self._seq,
            ok=ok,  # device faults are flags; the reading stays valid data (docs/platform.md)
            flags=flags, extras=extras,
            # the hand's own clock when the cycle was sampled [s since the first cycle of this
            # configure]: t_s is the host's, stamped when the reader assembled the cycle
            device_t_s=dev_t,
        )

    def _hold_command(self, obs: Observation) -> np.ndarray:
        return to_action(obs.state[ACT_INDEX])

    def _write(self, action: np.ndarray) -> None:
        self._check_link()
        self._send_targets(action)
        self._last_cmd_t = time.monotonic()
        self._wd_fired = False

    def _stop(self) -> np.ndarray | None:
        """Hold the measured position (stop for a hand: nothing moves, nothing drops)."""
        if self.bus is None:
            return None
        return self._hold_measured()

    def estop(self, engage: bool = True) -> None:
        """Send the e-stop frame (highest-priority id); the firmware latches a hold."""
        self._estop_counter = (self._estop_counter + 1) % 256
        self._send(*encode("HAND_ESTOP", {"engage": int(engage), "counter": self._estop_counter}))

    def _health(self) -> Health:
        now = time.monotonic()
        with self._lock:
            err = self._reader_error
            tel, tel_t = self._tel, self._tel_t
            asm = self._asm
            counters = (self.frames_received, self.corrupt_frames, asm.dropped_frames, asm.cycles,
                        asm.incomplete_cycles, self.foreign_frames, self.last_corrupt)
        rx, corrupt, dropped, cycles, incomplete, foreign, last_corrupt = counters
        if self.bus is None:
            return Health(ok=False, link_quality=0.0, last_error=self.last_error or err)
        age = None if tel_t is None else now - tel_t
        fresh = age is not None and age <= self.params.telemetry_deadline_s
        expected = rx + dropped + corrupt
        return Health(
            ok=bool(fresh and err is None),
            link_quality=1.0 if expected == 0 else rx / expected,
            frames_sent=self.frames_sent,
            frames_received=rx,
            corrupt_frames=corrupt,
            dropped_frames=dropped,
            latency_s=None,
            last_error=err or self.last_error,
            extra={
                "backend": self.backend,
                "transport": self.params.transport,
                **({"lab_fixture_port": self._fixture_port} if self._fixture_port else {}),
                **(self._hb_rate.counts("heartbeat") if self._hb_rate else {}),
                "telemetry_age_s": age,
                "telemetry_cycles": cycles,
                "incomplete_cycles": incomplete,
                "foreign_frames": foreign,
                "bus_error_frames": self.bus_error_frames,
                "last_corrupt": last_corrupt,
                "hand_faults": None if tel is None else tel.faults,
                "hand_mode": None if tel is None else tel.mode,
                "hand_rx_errors": None if tel is None else tel.rx_error_count,
                "motor_fault_mask": None if tel is None else tel.motor_fault_mask,
                "driver_watchdog_trips": self.driver_watchdog_trips,
                **{k: v for k, v in self.inputs.ages(now).items() if k != "telemetry_age_s"},
            },
        )

    @property
    def emulator(self) -> EmulatorProcess | None:
        """The emulator process (emulated backend), for its log and for tests."""
        return self._emu
