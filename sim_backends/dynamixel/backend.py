"""The sim backend of a Dynamixel robot: the real driver's code over an in-process bus.

``SimBus`` offers what :class:`hilstack.drivers.dynamixel.bus.DynamixelBus` offers (ping, read,
write, reboot, sync read/write, counters) by calling the simulated servos' control
tables directly, without packets or a port. The drivers' logic (modes, limits, hold,
stop, health) is therefore the same code on every backend; only the clock differs:
``tick()`` advances the world by one control period (1 kHz servo ticks).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import Any

import numpy as np

from hilstack.drivers.base import Lifecycle, LinkError
from hilstack.drivers.dynamixel.bus import ServoError
from hilstack.drivers.dynamixel.control_table import control_table, describe_status_error
from hilstack.sim_backends.base import LockstepSim
from hilstack.sim_backends.dynamixel.world import ServoWorld


class SimBus:
    """The bus API on the world's servos, in-process."""

    def __init__(self, world: ServoWorld):
        self.world = world
        self.table = control_table()
        self.lock = threading.RLock()
        self.stats = {"instructions": 0, "status_ok": 0, "crc_errors": 0, "missing_status": 0,
                      "tx_errors": 0, "servo_errors": 0}
        self.last_rtt_s: float | None = 0.0
        self.last_error: str | None = None
        self.closed = False

    def _servo(self, dxl_id: int):
        self.stats["instructions"] += 1
        s = self.world.servos.get(dxl_id)
        if s is None:
            self.stats["missing_status"] += 1
            self.last_error = f"ID {dxl_id}: There is no status packet!"
            raise LinkError(self.last_error)
        self.stats["status_ok"] += 1
        s.heard()  # an instruction reached it: its Bus Watchdog counts anew
        return s

    def _err(self, what: str, dxl_id: int, err: int) -> None:
        if err:
            self.stats["servo_errors"] += 1
            self.last_error = f"{what} ID {dxl_id}: servo answered {describe_status_error(err)}"
            raise ServoError(self.last_error)

    def ping(self, dxl_id: int) -> tuple[int, int]:
        s = self._servo(dxl_id)
        return s.get("Model Number"), s.status_error()

    def read(self, dxl_id: int, item: str) -> int:
        it = self.table[item]
        err, data = self._servo(dxl_id).read(it.address, it.size)
        self._err(f"read {item}", dxl_id, err)
        return it.decode(data)

    def write(self, dxl_id: int, item: str, value: int) -> None:
        it = self.table[item]
        self._err(f"write {item}={value}", dxl_id, self._servo(dxl_id).write(it.address, it.encode(value)))

    def reboot(self, dxl_id: int) -> None:
        self._servo(dxl_id).power_on()

    def sync_write(self, item: str, values: dict[int, int]) -> None:
        it = self.table[item]
        self.stats["instructions"] += 1
        for dxl_id, v in values.items():
            s = self.world.servos.get(dxl_id)
            if s is not None:
                s.heard()
                s.write(it.address, it.encode(v))

    def sync_read(self, ids: Iterable[int], first: str, last: str,
                  timeout_margin_ms: float | None = None) -> tuple[dict[int, bytes], dict[int, int]]:
        addr, n = self.table.span(first, last)
        self.stats["instructions"] += 1
        data, errors = {}, {}
        for dxl_id in ids:
            s = self.world.servos.get(dxl_id)
            if s is None:
                self.stats["missing_status"] += 1
                continue
            self.stats["status_ok"] += 1
            s.heard()
            err, raw = s.read(addr, n)
            data[dxl_id] = raw
            if err | s.status_error():
                errors[dxl_id] = err | s.status_error()
        return data, errors

    def decode(self, raw: bytes, first: str, item: str) -> int:
        it = self.table[item]
        off = it.address - self.table[first].address
        return it.decode(raw[off:off + it.size])

    def close(self) -> None:
        self.closed = True


class DynamixelSim(LockstepSim):
    """Lockstep time and the in-process bus for a DynamixelRobot: the sim backend of a
    Dynamixel robot is ``class MySim(DynamixelSim, MyDriver)`` with :meth:`_world`."""

    backend = "sim"
    world: ServoWorld | None = None

    @property
    def sim_time_s(self) -> float:
        return 0.0 if self.world is None else self.world.time_s

    def _world(self) -> ServoWorld:
        """The bench's world for ``params.bus_name`` (robots of one bus share it)."""
        raise NotImplementedError

    def _open_bus(self) -> tuple[str, Any]:
        self.world = self._world()
        return f"sim:{self.params.bus_name}", SimBus(self.world)

    def _close_bus(self) -> None:
        if self.bus is not None:
            self.bus.close()
        self.bus = None
        self.world = None  # the world lives while another robot of the bus holds it

    def _sleep(self, s: float) -> None:
        if self.world is not None:
            self.world.advance(s)

    def _advance(self, duration_s: float) -> None:
        if self.world is None:
            raise LinkError(f"{self.spec.name}: tick() needs configure() first")
        self.world.advance(duration_s)

    def reset(self, **kwargs: Any) -> None:
        """This robot's joints back to their start pose, its servos power-cycled, and the
        driver through configure (and activate) again; the other robots of the bench stay."""
        if kwargs:
            raise TypeError(f"{self.spec.name} reset takes no pose, got {sorted(kwargs)}")
        active = self.active
        w = self.world
        if w is None:
            raise LinkError(f"{self.spec.name}: reset() needs configure() first")
        self.stop()
        w.reset_robot(list(self.ids), list(self.ids.values()))
        self._q[:] = np.nan
        self._t_joint[:] = -np.inf
        self._mode = None
        self._lifecycle = Lifecycle.UNCONFIGURED  # reconfigure on the same (kept) bus
        self._close_bus()
        self.configure()
        if active:
            self.activate()
