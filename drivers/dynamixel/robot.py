"""A robot made of Dynamixel X-series servos on one Protocol 2.0 bus: the shared part of
the WidowX arm and the task-reset mechanism drivers.

What it does for a subclass (which names its joints/IDs and maps servo units to its
state and action):

* opens the bus (``real``: ``params.port``; ``emulated``: starts the bus emulator
  process, the robot's ``EMULATOR``; ``sim``: an in-process bus on the MuJoCo world, see
  sim_backends/dynamixel/backend.py), shared with the other robots of the same bus;
* at configure: pings every ID (a missing servo is a one-line error naming joint, ID and
  port), checks Hardware Error Status (reboots only if the config allows it), reads the
  limits, does a first sync read (waiting for it as long as for the pings);
* ``read()``: one SYNC_READ of Bus Watchdog .. Present Temperature from every ID,
  waiting for the answers at most ``READ_TIMEOUT_PERIODS`` of a control period (so a
  device that stopped answering costs a read about one period, not the SDK's timeout);
  a joint that did not answer keeps its last value, and the reading is ``ok=False`` with
  ``flags["stale_telemetry"]`` once the oldest joint value is older than ``telemetry_stale_s``;
  no answer from every servo for ``link_timeout_periods`` periods (the contract's
  ``Freshness(fail_after_s=...)``: a frozen, unpowered or unplugged device) takes the
  error path (stop sent, UNCONFIGURED, ``last_error``) and raises ``LinkError``;
  a hardware alert in any status packet reads the error, takes the error path (stop the
  others, go UNCONFIGURED) and raises with the decoded error;
* the servos' own Bus Watchdog (``bus_watchdog_s``): armed whenever the driver turns the
  torque on, so the servos stop by themselves when the host stops talking (its process
  died); a servo that tripped (the register reads -1) is reported as ``flags["watchdog"]``
  and re-armed before the next goal (goals are refused while it is tripped);
* ``stop()`` writes its hold first, then reads the servos back: :meth:`stop_confirmed` is
  True only when every servo answered after the stop and reports the goal the stop wrote. A
  read-back whose answers come late (a loaded machine) is retried, each read at most
  ``READ_TIMEOUT_PERIODS`` of a period, for ``stop_confirm_timeout_s`` in all;
* ``health()``: link counters of the bus, the round-trip time of the last sync read,
  telemetry age, servo temperatures and input voltage, latched hardware errors.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import (
    Driver,
    Flag,
    Freshness,
    Health,
    Inputs,
    Lifecycle,
    LinkError,
    Observation,
    require_device,
)
from hilstack.drivers.dynamixel.bus import DynamixelBus, ServoError, acquire_bus, release_bus, start_emulator
from hilstack.drivers.dynamixel.control_table import (
    AMP_PER_COUNT,
    BUS_WATCHDOG_MIN_FIRMWARE,
    BUS_WATCHDOG_TRIPPED,
    BUS_WATCHDOG_UNIT_S,
    OPERATING_MODES,
    REALTIME_TICK_S,
    STATUS_ALERT_BIT,
    VOLT_PER_COUNT,
    describe_hardware_error,
    pos_rad,
    unwrap_tick,
    vel_rad_s,
)
from hilstack.drivers.emulator_process import emulator_module

BLOCK = ("Bus Watchdog", "Present Temperature")
#: a read waits for the servos' answers at most this fraction of a control period
READ_TIMEOUT_PERIODS = 0.8
#: wait after a REBOOT before the servo answers again (e-Manual: about 0.5 s on XM)
REBOOT_WAIT_S = 0.5


class DynamixelRobot(Driver):
    #: joint name -> Dynamixel ID, set by the subclass
    ids: dict[str, int]
    #: the device emulator of this robot's bench (entry points ``hilstack.emulators``): the
    #: Dynamixel bus emulator (sim_backends/dynamixel/emulator.py) on the bench's MuJoCo world
    EMULATOR = "widowx"
    #: the default ``params.bus_name`` of the robot's params (robots of one bus share it)
    BUS_NAME = "widowx"

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
        # each servo's Realtime Tick: the last raw value and the unwrapped count since the first read
        self._tick_raw: list[int | None] = [None] * n
        self._tick_total = np.zeros(n, dtype=np.int64)
        self._hw_errors: dict[str, str] = {}
        self._mode: int | None = None
        self._seq = 0
        self._wd = np.zeros(n, dtype=int)  # Bus Watchdog register as last read (-1: tripped)
        self._goal_pos = np.zeros(n, dtype=int)  # Goal Position register as last read [counts]
        self.watchdog_trips = 0
        self._stop_confirmed = False
        self._pos_limits: dict[int, tuple[int, int]] = {}  # ID -> (Min, Max Position Limit) [counts]
        self._t_read_try = -np.inf  # when the last sync read was sent (self.now())
        self._answers = np.zeros(n, dtype=np.int64)  # status packets each joint answered a read with
        self.inputs = Inputs(Freshness("telemetry", params.telemetry_stale_s, Flag.STALE_TELEMETRY,
                                       fail_after_s=params.link_timeout_periods * params.period_s))

    # ------------------------------------------------------------------ bus
    @classmethod
    def shared_bus_key(cls, cfg: Any) -> str | None:
        """Robots with the same key share one port and must run in one process (``hil up``
        groups them): the adapter for ``real``, the emulator for ``emulated``; None for
        sim (each process has its own world)."""
        p = cfg.params or {}
        if cfg.backend == "real":
            return f"dynamixel:{p.get('port')}"
        if cfg.backend == "emulated":
            return f"dynamixel-emulated:{p.get('bus_name', cls.BUS_NAME)}"
        return None

    def _emulator_config(self) -> dict[str, Any]:
        raise NotImplementedError

    def _open_bus(self) -> tuple[str, Any]:
        p = self.params
        if self.backend == "emulated":
            key = f"emulated:{p.bus_name}"
            e = p.emulator
            cfg = {**self._emulator_config(), **e.model_dump(exclude={"start_timeout_s", "keep_log"})}
            module = emulator_module(self.EMULATOR)
            return key, acquire_bus(key, lambda: start_emulator(cfg, p.baudrate, start_timeout_s=e.start_timeout_s,
                                                                module=module, keep_log=e.keep_log))
        if not p.port:
            raise ConfigError(self.source, [("params.port", "no serial port: set params.port (e.g. /dev/ttyUSB0) "
                                                            "or pass --port; see docs/arms.md")])
        require_device(p.port, self.source, "params.port", "the U2D2 / USB-serial adapter")

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
        self.inputs.start(self.now())
        self._stop_confirmed = False
        self._pos_limits = {}
        for name, dxl_id in self.ids.items():
            try:
                _, err = self.bus.ping(dxl_id)
            except LinkError:
                raise LinkError(f"{self.spec.name}: joint {name!r} (ID {dxl_id}) does not answer on {self.where}: "
                                f"check its cable, power (12 V) and ID/baud ({self.params.baudrate})") from None
            fw = self.bus.read(dxl_id, "Firmware Version")
            if fw < BUS_WATCHDOG_MIN_FIRMWARE:
                raise LinkError(f"{self.spec.name}: joint {name!r} (ID {dxl_id}) has firmware v{fw}, without the "
                                f"Bus Watchdog (needs v{BUS_WATCHDOG_MIN_FIRMWARE}+): update it with DYNAMIXEL "
                                "Wizard; without it the servos would not stop when the host dies")
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
        # a position goal outside these is refused by the servo (data limit error; a sync
        # write gets no answer): every hold the driver sends is clamped into them
        self._pos_limits = {i: (self.bus.read(i, "Min Position Limit"), self.bus.read(i, "Max Position Limit"))
                            for i in self.ids.values()}
        self._on_bus_ready()
        self._sync_read(within_period=False)
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
        self.bus.sync_write("Bus Watchdog", {i: 0 for i in ids})  # clears a trip: goals are accepted again
        self.bus.sync_write("Operating Mode", {i: m for i in ids})
        if goal:
            item = next(iter(goal.values()))[0]
            self.bus.sync_write(item, {i: v for i, (_, v) in goal.items()})
        self.bus.sync_write("Torque Enable", {i: 1 for i in ids})
        self.bus.sync_write("Bus Watchdog", {i: self.watchdog_units for i in ids})
        self._wd[:] = self.watchdog_units
        self._mode = m

    def clamp_goal_position(self, dxl_id: int, counts: int) -> int:
        """A Goal Position the servo accepts: within its position limits (a joint resting on
        its end stop may read a few counts beyond them; that hold would be refused and the
        servo would go on to its previous goal)."""
        lo, hi = self._pos_limits.get(dxl_id, (counts, counts))
        return max(lo, min(hi, counts))

    @property
    def watchdog_units(self) -> int:
        """``bus_watchdog_s`` in the register's 20 ms units, rounded up."""
        return max(1, math.ceil(self.params.bus_watchdog_s / BUS_WATCHDOG_UNIT_S - 1e-9))

    @property
    def watchdog_tripped(self) -> bool:
        return bool(np.any(self._wd == BUS_WATCHDOG_TRIPPED))

    def rearm_watchdog(self) -> None:
        """After a trip (the host stalled longer than ``bus_watchdog_s`` and the servos
        stopped): clear it (0) and arm it again, so goals are accepted."""
        ids = list(self.ids.values())
        self.bus.sync_write("Bus Watchdog", {i: 0 for i in ids})
        self.bus.sync_write("Bus Watchdog", {i: self.watchdog_units for i in ids})
        self._wd[:] = self.watchdog_units

    def _confirm_hold(self, goal: dict[int, int]) -> bool:
        """Read the servos back after a stop's hold was written: True once every servo answered a
        read sent after it with the Goal Position ``goal`` (its ID's; a servo not in ``goal``:
        any). Reads are retried until ``params.stop_confirm_timeout_s`` has passed in all (one
        read waits at most ``READ_TIMEOUT_PERIODS`` of a period: at a load of 15 its answers
        came late and a held stop was reported not confirmed); a failing port is False at once.
        A device already silent when the stop began (its telemetry stale) is read back once, as
        before: retried, every stop of a frozen bus held the driver node's loop that long, and
        an e-stop's acknowledgement missed ``hil estop``'s wait (1.5 s) after an unhealthy stop."""
        retry = self.telemetry_age_s() < self.params.telemetry_stale_s
        deadline = time.monotonic() + self.params.stop_confirm_timeout_s
        ids = list(self.ids.values())
        confirmed: set[int] = set()
        while True:
            seen = self._answers.copy()
            try:
                self._sync_read(max_wait_s=deadline - time.monotonic() if retry else None)
            except LinkError:
                return False
            for k, dxl_id in enumerate(ids):
                if self._answers[k] > seen[k] and self._goal_pos[k] == goal.get(dxl_id, self._goal_pos[k]):
                    confirmed.add(dxl_id)
            if len(confirmed) == len(ids):
                return True
            if not retry or time.monotonic() >= deadline:
                return False

    def stop_confirmed(self) -> bool:
        """True when the servos read back the hold of the last ``stop()`` (see the module)."""
        return self._stop_confirmed and self.lifecycle is not Lifecycle.UNCONFIGURED

    def _sync_read(self, within_period: bool = True, max_wait_s: float | None = None) -> None:
        """Read every joint's block. ``within_period``: wait for the answers at most
        READ_TIMEOUT_PERIODS of a period (the control loop), and at most ``max_wait_s`` when
        given (≥ 0); otherwise as long as the bus waits for any answer (configure's first reading,
        beside the pings: on an emulator starved by a loaded CPU the period's bound lost all six
        answers and configure failed)."""
        self._t_read_try = self.now()
        bound_ms = READ_TIMEOUT_PERIODS * self.spec.period_s * 1000.0 if within_period else None
        if bound_ms is not None and max_wait_s is not None:
            bound_ms = min(bound_ms, max(0.0, max_wait_s) * 1000.0)
        data, errors = self.bus.sync_read(self.ids.values(), *BLOCK, timeout_margin_ms=bound_ms)
        now = self.now()
        dec = self.bus.decode
        if len(data) == len(self.ids):
            self.inputs["telemetry"].update(now)
        for k, (name, dxl_id) in enumerate(self.ids.items()):
            raw = data.get(dxl_id)
            if raw is None:
                continue
            wd = dec(raw, BLOCK[0], "Bus Watchdog")
            if wd == BUS_WATCHDOG_TRIPPED and self._wd[k] != BUS_WATCHDOG_TRIPPED:
                self.watchdog_trips += 1
            self._wd[k] = wd
            self._goal_pos[k] = dec(raw, BLOCK[0], "Goal Position")
            self._answers[k] += 1
            self._q[k] = pos_rad(dec(raw, BLOCK[0], "Present Position"), self.bus.table.zero_count)
            self._qd[k] = vel_rad_s(dec(raw, BLOCK[0], "Present Velocity"))
            self._cur[k] = dec(raw, BLOCK[0], "Present Current") * AMP_PER_COUNT
            self._temp_c[k] = dec(raw, BLOCK[0], "Present Temperature")
            self._volt[k] = dec(raw, BLOCK[0], "Present Input Voltage") * VOLT_PER_COUNT
            self._t_joint[k] = now
            tick = dec(raw, BLOCK[0], "Realtime Tick")
            self._tick_total[k] = unwrap_tick(self._tick_raw[k], tick, int(self._tick_total[k]))
            self._tick_raw[k] = tick
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
                           flags={"stale_telemetry": stale, "nonfinite_input": not finite,
                                  "hardware_error": bool(self._hw_errors), "watchdog": self.watchdog_tripped},
                           extras={"telemetry_age_s": age, **extras}, device_t_s=self.device_t_s())

    def device_t_s(self) -> float | None:
        """The first joint's servo clock at its last reading [s since that servo's first reading].

        Every servo keeps its own Realtime Tick (ms, wrapping after 32,767), and their origins
        differ on a real bus, so one servo (the first joint) is the clock of the sample: the
        present values of one sync read are sampled within a fraction of a millisecond of each
        other. None before that servo answered.
        """
        return None if self._tick_raw[0] is None else float(self._tick_total[0]) * REALTIME_TICK_S

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
        self._check_alive()

    def _check_alive(self) -> None:
        """The contract's frozen-device rule: no status from every servo for
        ``link_timeout_periods`` control periods with the port open takes the error path."""
        now = self.now()
        gone = self.inputs.expired(now)
        if gone is None or self._failing or self.lifecycle is Lifecycle.UNCONFIGURED:
            return
        age = gone.age_s(now)
        since = "since configure" if age is None else f"for {age:.2f} s"
        silent = [n for n, t in zip(self.ids, self._t_joint, strict=True) if not now - t <= gone.fail_after_s]
        self.fail_link(f"{self.spec.name}: no usable telemetry (no status from joints {silent}) on {self.where} {since} (limit: "
                       f"{self.params.link_timeout_periods} control periods of {self.spec.period_s:g} s): "
                       "servos frozen, unpowered or unplugged")

    def _refresh_inputs(self) -> None:
        """Before a write: a driver written to without reads for a period asks the servos first,
        so the contract's frozen-device rule judges a recent answer, not the last read()."""
        if self.bus is not None and not self.bus.closed and self.now() - self._t_read_try >= self.spec.period_s:
            self._read_bus()

    def _send(self, fn, *args) -> None:
        """A goal write: re-arms a tripped watchdog first; a failing port takes the error path."""
        try:
            if self.watchdog_tripped:
                self.rearm_watchdog()
            fn(*args)
        except LinkError as e:
            if self._failing:
                raise
            self.fail_link(e)

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
                   "bus_watchdog_s": self.watchdog_units * BUS_WATCHDOG_UNIT_S, "watchdog_trips": self.watchdog_trips,
                   **self.inputs.ages(self.now()),
                   "temperatures_c": {n: float(t) for n, t in zip(self.ids, self._temp_c, strict=True)},
                   "input_voltage_v": float(np.nanmin(self._volt)) if np.any(np.isfinite(self._volt)) else None,
                   "hardware_errors": dict(self._hw_errors), "ids": dict(self.ids)},
        )
