"""WidowX and mechanism MuJoCo backends: the real drivers' code over an in-process bus.

``SimBus`` offers what :class:`hilstack.drivers.dynamixel.bus.DynamixelBus` offers (ping, read,
write, reboot, sync read/write, counters) by calling the simulated servos' control
tables directly, without packets or a port. The drivers' logic (modes, limits, hold,
stop, health) is therefore the same code on every backend; only the clock differs:
``tick()`` advances the shared world by one control period (1 kHz servo ticks).

Robots with the same ``bus_name`` share one world (the arm sees the switch the mechanism
moves). Each robot's ``tick()`` advances that world by its own period.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import Any

import numpy as np

from hilstack.configs.schema import RobotConfig, parse_params
from hilstack.drivers.base import Lifecycle, LinkError
from hilstack.drivers.dynamixel.bus import ServoError
from hilstack.drivers.dynamixel.control_table import control_table, describe_status_error
from hilstack.drivers.widowx.config import MechanismParams, WidowXParams
from hilstack.drivers.widowx.driver import MechanismDriver, WidowXDriver
from hilstack.sim_backends.base import LockstepSim
from hilstack.sim_backends.widowx.world import ArmWorld, shared_world


class SimBus:
    """The bus API on the world's servos, in-process."""

    def __init__(self, world: ArmWorld):
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


class _SimMixin(LockstepSim):
    """Lockstep time and the in-process bus for a DynamixelRobot."""

    backend = "sim"
    world: ArmWorld | None = None

    @property
    def sim_time_s(self) -> float:
        return 0.0 if self.world is None else self.world.time_s

    def _layout(self) -> dict[str, Any]:
        raise NotImplementedError

    def _open_bus(self) -> tuple[str, Any]:
        self.world = shared_world(self.params.bus_name, **self._layout())
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


class WidowXSim(_SimMixin, WidowXDriver):
    """``params.sim.cameras: true`` adds ``extras["image"]``: the fixed and wrist cameras,
    64×128 RGB (``params.sim.camera_px`` per view), rendered at every read."""

    def __init__(self, params: WidowXParams | None = None, source: str | None = None):
        WidowXDriver.__init__(self, params, backend="sim", source=source)
        self.steps = 0
        self._cameras = None

    def _read(self):
        obs = super()._read()
        if self.params.sim.get("cameras") and self.world is not None:
            if self._cameras is None:
                from hilstack.sim_backends.widowx.cameras import BenchCameras

                self._cameras = BenchCameras(self.world.model, int(self.params.sim.get("camera_px", 64)))
            obs.extras["image"] = self._cameras.render(self.world.data)
        return obs

    def _close_bus(self) -> None:
        if self._cameras is not None:
            self._cameras.close()
            self._cameras = None
        super()._close_bus()

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> WidowXSim:
        return cls(parse_params(cfg, WidowXParams), source=cfg.source)

    @classmethod
    def calibration_bench(cls, params: WidowXParams | None = None) -> dict[str, Any]:
        """What `hil calibrate --model <widowx config>` needs to replay a recording through the
        bench's MuJoCo model (hilstack.calibration.mjcf_robot): the bench's MjSpec (``params.sim.mjcf``
        if set, else the built one), how each arm joint is driven (velocity-mode PI loop: P on
        velocity error [N·m·s/rad], I [N·m/rad], torque limit [N·m], torque constant [N·m/A]),
        which state columns hold position, velocity and current, and that actions are goal
        velocities [rad/s] of the joints in that order."""
        import mujoco

        from hilstack.drivers.widowx.config import JOINTS
        from hilstack.sim_backends.widowx.firmware import ServoPhysics
        from hilstack.sim_backends.widowx.model import build_spec

        params = params or WidowXParams()
        torques = {n: t for n, _, _, t in JOINTS}
        mjcf = params.sim.get("mjcf")
        spec = mujoco.MjSpec.from_file(str(mjcf)) if mjcf else build_spec(torques)
        names = [n for n, _, _, _ in JOINTS]
        loops = {}
        for n in names:
            ph = ServoPhysics(stall_torque_nm=torques[n])
            loops[n] = {"mode": "velocity", "kp_nm_s": ph.vel_kp_nm_s, "ki_nm": ph.vel_ki_nm,
                        "tau_max_nm": ph.stall_torque_nm, "kt_nm_per_a": ph.kt_nm_per_a}
        k = len(names)
        return {"spec": spec, "joints": names, "loops": loops, "q": list(range(0, k)), "qd": list(range(k, 2 * k)),
                "current": list(range(2 * k, 3 * k)), "action": "goal_velocity",
                "hold_pose": params.sim.get("start_holding")}

    def _layout(self) -> dict[str, Any]:
        return {"arm_ids": self.ids, "start_holding": self.params.sim.get("start_holding"),
                "effects": self.params.sim.get("effects"), "mjcf": self.params.sim.get("mjcf")}


class MechanismSim(_SimMixin, MechanismDriver):
    def __init__(self, params: MechanismParams | None = None, source: str | None = None):
        MechanismDriver.__init__(self, params, backend="sim", source=source)
        self.steps = 0

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> MechanismSim:
        return cls(parse_params(cfg, MechanismParams), source=cfg.source)

    def _layout(self) -> dict[str, Any]:
        return {"mech_ids": self.ids}
