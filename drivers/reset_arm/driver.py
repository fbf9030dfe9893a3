"""The reset arm's driver over its controller's UDP link (drivers/reset_arm/protocol.py).

backend "emulated": the controller is the reset station inside the Shadow Hand's firmware
emulator (sim_backends/reset_arm/server.py), started by the hand's driver with
``params.emulator.arm_port``; this driver connects to that port. backend "real": the same
code against the station's arm controller at ``params.host:params.port``.

``read()`` drains the socket and keeps the newest valid state; a state older than
``state_deadline_s`` is stale (``ok`` False, ``stale_telemetry``), frames that are not
states are counted and dropped (they never refresh the input); no valid state for
``link_timeout_periods`` control periods (the controller frozen or dead, the link down)
takes the error path (the contract's rule, drivers/base.py). ``stop()`` holds the measured joints and keeps the jaws'
target (a held ball is not dropped). The controller itself holds when commands stop.
"""

from __future__ import annotations

import socket
import time

import numpy as np

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import Driver, Flag, Freshness, Health, Inputs, LinkError, Observation
from hilstack.drivers.reset_arm.config import ResetArmParams, reset_arm_spec
from hilstack.drivers.reset_arm.protocol import QUERY, ProtocolError, decode_state, encode_command


class ResetArmDriver(Driver):
    params_type = ResetArmParams

    def __init__(self, params: ResetArmParams | None = None, backend: str = "real", source: str | None = None):
        super().__init__()
        self.params = params or ResetArmParams()
        self.backend = backend
        self.source = source
        self.spec = reset_arm_spec(self.params)
        self._sock: socket.socket | None = None
        self._state = np.full(21, np.nan)
        self._t_s: float | None = None
        self._seq = 0
        self._cmd_seq = 0
        self.bad_frames = 0
        self.received = 0
        self.sent = 0
        self.inputs = Inputs(Freshness.fail_after_periods("state", self.params.state_deadline_s, Flag.STALE_TELEMETRY,
                                                          self.params.link_timeout_periods, self.params.period_s))

    def now(self) -> float:
        return time.monotonic()

    @property
    def _addr(self) -> tuple[str, int]:
        return (self.params.host, int(self.params.port))

    def _on_configure(self) -> None:
        p = self.params
        if p.port is None:
            raise ConfigError(self.source, [("params.port", "the arm controller's UDP port is required for the "
                                             f"{self.backend} backend (emulated: the hand's params.emulator.arm_port)")])
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self.inputs.start(self.now())
        deadline = time.monotonic() + p.connect_timeout_s
        while self._t_s is None:
            self._sock.sendto(QUERY, self._addr)
            time.sleep(0.05)
            self._drain()
            if time.monotonic() > deadline:
                raise LinkError(f"reset arm: no state from the arm controller at {p.host}:{p.port} within "
                                f"{p.connect_timeout_s:g} s; is the hand's emulator up with emulator.arm_port "
                                f"{p.port} and the reset station (params.sim.reset_station)?")

    def _on_cleanup(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _drain(self) -> None:
        while True:
            try:
                raw = self._sock.recv(512)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # ICMP port unreachable: the controller is not there (yet)
                if self._t_s is None:
                    return
                self.fail_link(f"reset arm: link to {self.params.host}:{self.params.port} failed: {e}")
            try:
                _, t, s = decode_state(raw)
            except ProtocolError:
                self.bad_frames += 1  # counted (health corrupt_frames); it does not refresh the state
                continue
            self.received += 1
            finite = bool(np.all(np.isfinite(s)))
            self.inputs["state"].update(self.now(), finite)
            if finite:
                self._state, self._t_s = s, t

    def _refresh_inputs(self) -> None:
        self._drain()

    def _read(self) -> Observation:
        self._drain()
        ok, flags = self.inputs.assess(self.now(), report=True)
        self._seq += 1
        return Observation(t_s=self.now(), state=self._state.copy(), seq=self._seq, ok=ok, flags=flags,
                           extras={"controller_t_s": self._t_s})

    def _hold_command(self, obs: Observation) -> np.ndarray:
        s = obs.state
        if not np.all(np.isfinite(s[:15])):
            raise LinkError("reset arm: no valid state to hold")
        return np.clip(s[list(range(7)) + [14]], self.spec.action.low, self.spec.action.high)

    def _send(self, action: np.ndarray) -> None:
        if self._sock is None:
            raise LinkError("reset arm: not connected")
        self._cmd_seq += 1
        self._sock.sendto(encode_command(self._cmd_seq, action), self._addr)
        self.sent += 1

    def _write(self, action: np.ndarray) -> None:
        self._send(action)

    def _stop(self) -> np.ndarray | None:
        """Hold the measured joints; the jaws keep the last commanded opening."""
        if self._sock is None or not np.all(np.isfinite(self._state[:7])):
            return None
        grip = self.held_command[7] if self.held_command is not None else self._state[14]
        a = np.concatenate([self._state[:7], [grip]])
        self._send(a)
        return a

    def _health(self) -> Health:
        age = self.inputs["state"].age_s(self.now())
        fresh = age is not None and age <= self.params.state_deadline_s
        return Health(ok=self._sock is not None and fresh, link_quality=1.0 if fresh else 0.0,
                      frames_sent=self.sent, frames_received=self.received, corrupt_frames=self.bad_frames,
                      extra={"backend": self.backend, **self.inputs.ages(self.now())})
