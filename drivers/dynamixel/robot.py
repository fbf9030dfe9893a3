"""A robot made of Dynamixel X-series servos on one Protocol 2.0 bus: the shared part of
the WidowX arm and the task-reset mechanism drivers.

What it does for a subclass (which names its joints/IDs and maps servo units to its
state and action):

* opens the bus (``real``: ``params.port``; ``emulated``: starts the bus emulator
  process; ``sim``: an in-process bus on the MuJoCo world, see
  sim_backends/widowx/backend.py), shared with the other robots of the same bus;
* at configure: pings every ID (a missing servo is a one-line error naming joint, ID and
  port), checks Hardware Error Status (reboots only if the config allows it), reads the
  limits, does a first sync read;
* ``read()``: one SYNC_READ of Present Current .. Present Temperature from every ID;
  a joint that did not answer keeps its last value, and the reading is ``ok=False`` with
  ``flags["stale_telemetry"]`` once the oldest joint value is older than ``telemetry_stale_s``;
  a hardware alert in any status packet reads the error, takes the error path (stop the
  others, go UNCONFIGURED) and raises with the decoded error;
* ``health()``: link counters of the bus, the round-trip time of the last sync read,
  telemetry age, servo temperatures and input voltage, latched hardware errors.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import Driver, Health, Lifecycle, LinkError, Observation
from hilstack.drivers.dynamixel.bus import DynamixelBus, ServoError, acquire_bus, release_bus, start_emulator
from hilstack.drivers.dynamixel.control_table import (
    AMP_PER_COUNT,
    OPERATING_MODES,
    STATUS_ALERT_BIT,
    VOLT_PER_COUNT,
    describe_hardware_error,
    pos_rad,
    vel_rad_s,
)

BLOCK = ("Present Current", "Present Temperature")
#: wait after a REBOOT before the servo answers again (e-Manual: about 0.5 s on XM)
REBOOT_WAIT_S = 0.5


class DynamixelRobot(Driver):
    #: joint name -> Dynamixel ID, set by the subclass
    ids: dict[str, int]

    def __init__(self, params: Any, backend: str, source: str | None):
        super().__init__()
        self.params = params
        self.backend = backend
        self.source = source
        self.bus: Any = None
        self._bus_key: str | None = None
        n = len(self.ids)
        self._q = np.full(n, np.nan)       # servo shaft angle [rad]
        self._qd = np.full(n, np.nan)      # [rad/s]
        self._cur = np.full(n, np.nan)     # [A]
        self._temp_c = np.full(n, np.nan)
        self._volt = np.full(n, np.nan)
        self._t_joint = np.full(n, -np.inf)  # when each joint last answered (self.now())
        self._hw_errors: dict[str, str] = {}
        self._mode: int | None = None
        self._seq = 0

    # ------------------------------------------------------------------ bus
    def _emulator_config(self) -> dict[str, Any]:
        raise NotImplementedError

    def _open_bus(self) -> tuple[str, Any]:
        p = self.params
        if self.backend == "emulated":
            key = f"emulated:{p.bus_name}"
            e = p.emulator
            cfg = {**self._emulator_config(), **e.model_dump(exclude={"start_timeout_s", "keep_log"})}
            return key, acquire_bus(key, lambda: start_emulator(cfg, p.baudrate, start_timeout_s=e.start_timeout_s,
                                                                keep_log=e.keep_log))
        if not p.port:
            raise ConfigError(self.source, [("params.port", "no serial port: set params.port (e.g. /dev/ttyUSB0) "
                                                            "or pass --port; see docs/arms.md")])

        def opener() -> DynamixelBus:
            b = DynamixelBus(p.port, p.baudrate, timeout_margin_ms=2.0 * p.latency_timer_ms + 2.0)
            b.open()
            return b

        return p.port, acquire_bus(p.port, opener)

    def _close_bus(self) -> None:
        if self.bus is not None and self._bus_key is not None:
            release_bus(self._bus_key, self.bus)
        self.bus = None
        self._bus_key = None

    @property
    def where(self) -> str:
        return "the emulator" if self.backend == "emulated" else ("the sim bus" if self.backend == "sim"
                                                                   else str(self.params.port))

    # ------------------------------------------------------------------ lifecycle
    def _on_configure(self) -> None:
        self._bus_key, self.bus = self._open_bus()
        for name, dxl_id in self.ids.items():
            try:
                _, err = self.bus.ping(dxl_id)
            except LinkError:
                raise LinkError(f"{self.spec.name}: joint {name!r} (ID {dxl_id}) does not answer on {self.where}: "
                                f"check its cable, power (12 V) and ID/baud ({self.params.baudrate})") from None
            hw = self.bus.read(dxl_id, "Hardware Error Status") if err & STATUS_ALERT_BIT else 0
            if hw:
                what = describe_hardware_error(hw)
                if not self.params.reboot_on_hardware_error:
                    raise LinkError(f"{self.spec.name}: joint {name!r} (ID {dxl_id}) has a latched hardware error "
                                    f"({what}); find the cause, then reboot it (params.reboot_on_hardware_error) "
                                    "or power-cycle")
                self.bus.reboot(dxl_id)
                self._wait_reboot(dxl_id, name, what)
        self._mode = None
        self._on_bus_ready()
        self._sync_read()
        missing = [n for n, t in zip(self.ids, self._t_joint, strict=True) if not math.isfinite(t)]
        if missing:
            raise LinkError(f"{self.spec.name}: no state from joints {missing} on {self.where}")

    def _wait_reboot(self, dxl_id: int, name: str, what: str) -> None:
        deadline = time.monotonic() + 3.0
        while True:
            self._sleep(REBOOT_WAIT_S / 5)
            try:
                if self.bus.read(dxl_id, "Hardware Error Status") == 0:
                    return
            except LinkError:
                pass
            if time.monotonic() > deadline:
                raise LinkError(f"{self.spec.name}: joint {name!r} (ID {dxl_id}) still reports {what} after a reboot")

    def _sleep(self, s: float) -> None:
        time.sleep(s)

    def _on_bus_ready(self) -> None:  # noqa: B027 - optional hook
        """Read limits etc. once the servos answered."""

    def _on_cleanup(self) -> None:
        self._close_bus()

    # ------------------------------------------------------------------ servo helpers
    def set_mode(self, mode: str, goal: dict[int, tuple[str, int]] | None = None) -> None:
        """Operating mode for every joint: torque off, mode, goal, torque on.

        X-series servos accept a mode change only with torque off (EEPROM area), so the
        joints are limp for the time of three sync writes (~1 ms at 1 Mbps)."""
        m = OPERATING_MODES[mode]
        ids = list(self.ids.values())
        self.bus.sync_write("Torque Enable", {i: 0 for i in ids})
        self.bus.sync_write("Operating Mode", {i: m for i in ids})
        if goal:
            item = next(iter(goal.values()))[0]
            self.bus.sync_write(item, {i: v for i, (_, v) in goal.items()})
        self.bus.sync_write("Torque Enable", {i: 1 for i in ids})
        self._mode = m

    def _sync_read(self) -> None:
        data, errors = self.bus.sync_read(self.ids.values(), *BLOCK)
        now = self.now()
        dec = self.bus.decode
        for k, (name, dxl_id) in enumerate(self.ids.items()):
            raw = data.get(dxl_id)
            if raw is None:
                continue
            self._q[k] = pos_rad(dec(raw, BLOCK[0], "Present Position"), self.bus.table.zero_count)
            self._qd[k] = vel_rad_s(dec(raw, BLOCK[0], "Present Velocity"))
            self._cur[k] = dec(raw, BLOCK[0], "Present Current") * AMP_PER_COUNT
            self._temp_c[k] = dec(raw, BLOCK[0], "Present Temperature")
            self._volt[k] = dec(raw, BLOCK[0], "Present Input Voltage") * VOLT_PER_COUNT
            self._t_joint[k] = now
            if errors.get(dxl_id, 0) & STATUS_ALERT_BIT and name not in self._hw_errors:
                try:
                    bits = self.bus.read(dxl_id, "Hardware Error Status")
                except (LinkError, ServoError) as e:
                    bits, self._hw_errors[name] = 0, f"alert, status unreadable: {e}"
                if bits:
                    self._hw_errors[name] = describe_hardware_error(bits)

    def _check_hw(self) -> None:
        if self._hw_errors and self.lifecycle is not Lifecycle.UNCONFIGURED and not self._failing:
            self.fail_link(f"{self.spec.name}: hardware error, " + "; ".join(
                f"{n} (ID {self.ids[n]}): {w}" for n, w in self._hw_errors.items()) +
                " — its torque is off; the others were stopped")

    def telemetry_age_s(self) -> float:
        return float(self.now() - np.min(self._t_joint))

    def _observation(self, state: np.ndarray, extras: dict[str, Any]) -> Observation:
        age = self.telemetry_age_s()
        stale = not age < self.params.telemetry_stale_s
        finite = bool(np.all(np.isfinite(state)))
        self._seq += 1
        return Observation(t_s=self.now(), state=state, seq=self._seq, ok=not stale and finite,
                           flags={"stale_telemetry": stale, "nonfinite_input": not finite, "hardware_error": bool(self._hw_errors)},
                           extras={"telemetry_age_s": age, **extras})

    def _read_bus(self) -> None:
        if self.bus is None or self.bus.closed:
            raise LinkError(f"{self.spec.name}: bus closed ({self.last_error or 'not configured'})")
        try:
            self._sync_read()
        except LinkError as e:
            # the port itself failed (unplugged adapter): the error path, then say so
            if self._failing:
                raise
            self.fail_link(e)
        self._check_hw()

    # ------------------------------------------------------------------ health
    def _health(self) -> Health:
        b = self.bus
        if b is None:
            return Health(ok=False, link_quality=0.0, last_error=self.last_error)
        st = dict(b.stats)
        answered = st["status_ok"] + st["crc_errors"] + st["missing_status"]
        age = self.telemetry_age_s()
        fresh = age < self.params.telemetry_stale_s
        return Health(
            ok=bool(fresh and not self._hw_errors and self.lifecycle is not Lifecycle.UNCONFIGURED),
            link_quality=1.0 if answered == 0 else st["status_ok"] / answered,
            frames_sent=st["instructions"], frames_received=st["status_ok"],
            corrupt_frames=st["crc_errors"], dropped_frames=st["missing_status"],
            latency_s=b.last_rtt_s, last_error=b.last_error or self.last_error,
            extra={"backend": self.backend, "telemetry_age_s": age, "servo_errors": st["servo_errors"],
                   "temperatures_c": {n: float(t) for n, t in zip(self.ids, self._temp_c, strict=True)},
                   "input_voltage_v": float(np.nanmin(self._volt)) if np.any(np.isfinite(self._volt)) else None,
                   "hardware_errors": dict(self._hw_errors), "ids": dict(self.ids)},
        )
