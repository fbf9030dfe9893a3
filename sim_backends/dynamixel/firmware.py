"""One Dynamixel X-series servo as its firmware behaves, shared by the sim backend and
the bus emulator: a control table in bytes, the 1 kHz control loop, errors.

Pure Python, no I/O, no clock: the caller runs :meth:`Servo.tick` every ``TICK_S`` with
the joint's measured position [rad] and velocity [rad/s] and applies the returned torque
[N·m] (for a servo on a rail, the joint is the servo's output shaft, see model.py).

What is modelled (XM430-W350 e-Manual, "Control Table" and "Operating Mode"):
* Operating Mode (velocity 1, position 3; others refused with a data range error) and
  the rule that EEPROM items (address < 64) are writable only with torque off (access
  error otherwise); read-only items refuse writes (access error).
* Goal Velocity beyond Velocity Limit and Goal Position outside the position limits are
  refused with a data limit error, as the servo does.
* velocity mode: a PI loop on velocity; position mode: a PID on position; both saturate
  at the stall torque (the current limit).
* Hardware Error Status: overload (saturated longer than ``overload_s``), overheating
  (a first-order thermal model crosses the temperature limit) or injected bits. Any
  error turns the torque off and sets the alert bit of every status packet; Torque
  Enable = 1 is then refused until a reboot clears the error.
* Present Current from the torque (torque constant ``kt``), Present Temperature, Present
  Input Voltage, Moving, and Realtime Tick (120): the servo's clock in ms (simulated time: the
  ticks run, wrapping after 32,767) at the tick whose present values a read returns.
* Bus Watchdog (98), as the e-Manual describes it: 1..127 arms it (unit 20 ms); with
  torque on, no instruction packet for longer than that stops the servo (velocity mode:
  Goal Velocity becomes 0; position mode: the servo stops its profile where it is, and
  this model has no profile, so it keeps holding its Goal Position),
  the register reads -1, and writes to Goal PWM/Current/Velocity/Position are refused
  with a data range error until 0 is written (0 disarms and clears the trip). The caller
  reports every instruction packet that reaches the servo (:meth:`Servo.heard`); the time
  since the last one is counted in servo ticks (simulated time). Which packets count is a
  modelling choice: those addressed to the servo (its ID, broadcast, or a sync
  instruction naming it); a value other than 0 while tripped is refused (data range).

The gains are in SI units, not the servo's raw gain registers: the emulator's job is the
wire protocol and a plausible closed loop, not a bit-exact copy of ROBOTIS' controller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hilstack.drivers.dynamixel import protocol as p
from hilstack.drivers.dynamixel.control_table import (
    AMP_PER_COUNT,
    BUS_WATCHDOG_MAX_UNITS,
    BUS_WATCHDOG_TRIPPED,
    BUS_WATCHDOG_UNIT_S,
    GOAL_ITEMS,
    OPERATING_MODES,
    RAD_PER_COUNT,
    REALTIME_TICK_MODULUS,
    REALTIME_TICK_S,
    ControlTable,
    control_table,
)
from hilstack.sim_backends.effects import FRICTION_V_EPS_RAD_S, validate_effects

TICK_S = 0.001
MODEL_NUMBERS = {"XM430-W350": 1020, "XM540-W270": 1120, "XL430-W250": 1060}
#: the first RAM address: below it is EEPROM (writable only with torque off)
EEPROM_END = 64
READ_ONLY = frozenset({"Model Number", "Model Information", "Firmware Version", "Registered Instruction",
                       "Hardware Error Status", "Realtime Tick", "Moving", "Moving Status", "Present PWM",
                       "Present Current", "Present Load", "Present Velocity", "Present Position",
                       "Velocity Trajectory", "Position Trajectory", "Present Input Voltage",
                       "Present Temperature"})
VELOCITY_MODE = OPERATING_MODES["velocity"]
HW_OVERHEATING = 1 << 2
HW_OVERLOAD = 1 << 5


@dataclass
class ServoPhysics:
    """SI parameters of one servo as mounted (units in names)."""

    stall_torque_nm: float = 4.1        # XM430-W350 at 12 V (e-Manual)
    kt_nm_per_a: float = 1.78           # 4.1 N·m / 2.3 A stall current
    vel_kp_nm_s: float = 2.0            # velocity loop
    vel_ki_nm: float = 120.0          # high enough that a held arm sags < 1° when the loop starts
    pos_kp_nm_per_rad: float = 30.0     # position loop
    pos_ki_nm_per_rad_s: float = 30.0
    pos_kd_nm_s: float = 1.5
    overload_s: float = 3.0             # saturated this long -> overload error
    ambient_c: float = 25.0
    thermal_tau_s: float = 600.0        # winding to ambient
    thermal_c_per_a2: float = 15.0      # steady-state rise per A² of current
    supply_v: float = 12.0
    # effects the sim's MuJoCo model lacks (the emulator's ``effects`` option; 0 = absent):
    #: Coulomb friction in the gearbox [N·m], opposing the output shaft's motion
    friction_nm: float = 0.0
    #: viscous friction in the gearbox [N·m·s/rad]
    damping_nm_s: float = 0.0
    #: a goal (velocity/position) takes effect this long after it was written [s]
    input_delay_s: float = 0.0


#: ``effects`` keys -> (ServoPhysics field, upper bound): what the emulator can add to the sim
EFFECTS = {"joint_friction_nm": ("friction_nm", 2.0), "joint_damping_nm_s": ("damping_nm_s", 5.0),
           "input_delay_s": ("input_delay_s", 0.5)}


def effect_fields(effects: dict | None) -> dict[str, float]:
    """Validate an ``effects`` mapping into ServoPhysics fields (a ValueError names the bad key or value)."""
    return validate_effects(effects, EFFECTS)


class Servo:
    """Control table + firmware of one servo."""

    def __init__(self, dxl_id: int, model: str = "XM430-W350", physics: ServoPhysics | None = None,
                 position_limits_rad: tuple[float, float] | None = None, velocity_limit_rad_s: float = 4.8):
        self.table: ControlTable = control_table(model)
        self.model = model
        self.phys = physics or ServoPhysics()
        self.mem = bytearray(self.table.size)
        self.injected_error = 0
        self._defaults = (dxl_id, position_limits_rad, velocity_limit_rad_s)
        self.power_on()

    # ------------------------------------------------------------------ table
    def get(self, name: str) -> int:
        it = self.table[name]
        return it.decode(bytes(self.mem[it.address:it.address + it.size]))

    def set(self, name: str, value: int) -> None:
        """Firmware-side write (no access rules)."""
        it = self.table[name]
        self.mem[it.address:it.address + it.size] = it.encode(value)
        if not name.startswith("Present") and name != "Moving" and hasattr(self, "_dirty"):
            self._refresh()

    def power_on(self) -> None:
        """Power-on / reboot: RAM back to defaults, EEPROM kept, errors cleared."""
        dxl_id, limits, vlim = self._defaults
        first = not any(self.mem)
        if first:
            self.set("Model Number", MODEL_NUMBERS.get(self.model, 0))
            self.set("Firmware Version", 48)
            self.set("ID", dxl_id)
            self.set("Baud Rate", 3)  # 1 Mbps
            self.set("Operating Mode", OPERATING_MODES["position"])
            self.set("Temperature Limit", 80)
            self.set("Moving Threshold", 10)
            self.set("Max Voltage Limit", 160)
            self.set("Min Voltage Limit", 95)
            self.set("Current Limit", int(self.phys.stall_torque_nm / self.phys.kt_nm_per_a / AMP_PER_COUNT))
            self.set("Velocity Limit", int(vlim / self.table.units.get("Goal Velocity", (0.0239691227, ""))[0]))
            lo, hi = limits if limits is not None else (-math.pi, math.pi)
            self.set("Min Position Limit", self._pos_counts(lo))
            self.set("Max Position Limit", self._pos_counts(hi))
            self.set("Present Temperature", int(self.phys.ambient_c))
            self.temperature_c = self.phys.ambient_c
        ram = self.table["Torque Enable"].address
        self.mem[ram:] = bytes(len(self.mem) - ram)
        self.set("Status Return Level", 2)
        self.set("Present Input Voltage", int(round(self.phys.supply_v * 10)))
        self.set("Present Temperature", int(round(self.temperature_c)))
        self.set("Hardware Error Status", self.injected_error)
        self._integral = 0.0
        self._saturated_s = 0.0
        self._idle_s = 0.0  # since the last instruction packet (Bus Watchdog)
        self._present = (0.0, 0.0, 0.0)  # q [rad], qd [rad/s], current [A] of the last tick
        self._dirty = False
        self._clock_s = 0.0  # servo time [s] (ticks), for the input delay
        #: (due [s], the goals the loop keeps using until then) of delayed goal writes
        self._pending: list[tuple[float, dict[str, float]]] = []
        self._refresh()

    def _refresh(self) -> None:
        """Cache what the 1 kHz loop needs (the table is the truth; this is a copy)."""
        self._torque_on = self.get("Torque Enable") == 1
        self._mode = self.get("Operating Mode")
        self._goal_vel_rad_s = self.get("Goal Velocity") * self.vel_scale
        self._goal_pos_rad = self._pos_rad(self.get("Goal Position"))
        self._tau_max = min(self.phys.stall_torque_nm, self.get("Current Limit") * AMP_PER_COUNT
                            * self.phys.kt_nm_per_a)
        self._hw_error = self.get("Hardware Error Status")
        self._temp_limit_c = self.get("Temperature Limit")
        self._moving_threshold_rad_s = self.get("Moving Threshold") * self.vel_scale
        self._watchdog = self.get("Bus Watchdog")

    # ------------------------------------------------------------------ bus watchdog
    def heard(self) -> None:
        """An instruction packet reached this servo: the Bus Watchdog starts counting anew."""
        self._idle_s = 0.0

    @property
    def watchdog_tripped(self) -> bool:
        return self._watchdog == BUS_WATCHDOG_TRIPPED

    def _trip_watchdog(self) -> None:
        """No instruction for the set time: stop (velocity 0; position mode holds its goal,
        the end of a profile this model does not have), refuse goals."""
        if self._mode == VELOCITY_MODE:
            self.set("Goal Velocity", 0)
        self.set("Bus Watchdog", BUS_WATCHDOG_TRIPPED)

    def publish(self) -> None:
        """Write the present values of the last tick into the table (before a read)."""
        if not self._dirty:
            return
        q, qd, cur = self._present
        self.set("Present Position", self._pos_counts(q))
        self.set("Present Velocity", int(round(qd / self.vel_scale)))
        self.set("Present Current", int(round(cur / AMP_PER_COUNT)))
        self.set("Present Temperature", int(round(self.temperature_c)))
        self.set("Moving", int(abs(qd) > self._moving_threshold_rad_s))
        # the servo's clock at that tick (ms, wraps after 32,767): the time of the present values
        self.set("Realtime Tick", int(round(self._clock_s / REALTIME_TICK_S)) % REALTIME_TICK_MODULUS)
        self._dirty = False

    def _pos_counts(self, rad: float) -> int:
        return int(round(rad / RAD_PER_COUNT)) + self.table.zero_count

    def _pos_rad(self, counts: int) -> float:
        return (counts - self.table.zero_count) * RAD_PER_COUNT

    @property
    def vel_scale(self) -> float:
        return self.table.units.get("Goal Velocity", (0.0239691227, ""))[0]

    @property
    def hardware_error(self) -> int:
        return self._hw_error

    @property
    def torque_on(self) -> bool:
        return self._torque_on

    def status_error(self) -> int:
        """The alert bit every status packet carries while a hardware error is latched."""
        return p.ERR_ALERT if self.hardware_error else 0

    def inject_hardware_error(self, bits: int, persistent: bool = False) -> None:
        """A hardware fault: latched until reboot (``persistent``: it survives reboots too)."""
        self.set("Hardware Error Status", self.hardware_error | bits)
        self.set("Torque Enable", 0)
        if persistent:
            self.injected_error |= bits

    # ------------------------------------------------------------------ wire access
    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """(error code, data) of a READ; data is empty on error."""
        if length <= 0 or address < 0 or address + length > len(self.mem):
            return p.ERR_DATA_RANGE, b""
        self.publish()
        return 0, bytes(self.mem[address:address + length])

    def write(self, address: int, data: bytes) -> int:
        """A WRITE from the bus; returns the status error code (0: done)."""
        if not data or address < 0 or address + len(data) > len(self.mem):
            return p.ERR_DATA_RANGE
        touched = [it for it in self.table.items.values()
                   if it.address < address + len(data) and address < it.address + it.size
                   and not it.name.startswith("Indirect")]
        if not touched or any(it.address < address or it.address + it.size > address + len(data) for it in touched):
            return p.ERR_DATA_LENGTH  # partial items are not writable
        if any(it.name in READ_ONLY for it in touched):
            return p.ERR_ACCESS
        if address < EEPROM_END and self.torque_on:
            return p.ERR_ACCESS
        new = {it.name: it.decode(data[it.address - address:it.address - address + it.size]) for it in touched}
        err = self._check(new)
        if err:
            return err
        if new.get("Torque Enable") == 1 and not self.torque_on:
            self._integral = 0.0
        if "Operating Mode" in new:
            self._integral = 0.0
        if self.phys.input_delay_s > 0 and any(n in GOAL_ITEMS for n in new):
            # the register reads back at once; the loop sees the goal input_delay_s later
            self._pending.append((self._clock_s + self.phys.input_delay_s, dict(self._goals())))
        self.mem[address:address + len(data)] = data
        self._refresh()
        return 0

    def _goals(self) -> dict[str, float]:
        return {"vel": self._goal_vel_rad_s, "pos": self._goal_pos_rad}

    def _check(self, new: dict[str, int]) -> int:
        if "Bus Watchdog" in new:
            wd = new["Bus Watchdog"]
            if not 0 <= wd <= BUS_WATCHDOG_MAX_UNITS or (self.watchdog_tripped and wd != 0):
                return p.ERR_DATA_RANGE
        elif self.watchdog_tripped and any(g in new for g in GOAL_ITEMS):
            return p.ERR_DATA_RANGE  # goals are read-only until the trip is cleared
        if "Operating Mode" in new and new["Operating Mode"] not in (OPERATING_MODES["velocity"],
                                                                     OPERATING_MODES["position"]):
            return p.ERR_DATA_RANGE
        if "Torque Enable" in new:
            if new["Torque Enable"] not in (0, 1):
                return p.ERR_DATA_RANGE
            if new["Torque Enable"] == 1 and self.hardware_error:
                return p.ERR_RESULT_FAIL  # torque stays off until a reboot clears the error
        if "Goal Velocity" in new and abs(new["Goal Velocity"]) > self.get("Velocity Limit"):
            return p.ERR_DATA_LIMIT
        if "Goal Position" in new and not (self.get("Min Position Limit") <= new["Goal Position"]
                                           <= self.get("Max Position Limit")):
            return p.ERR_DATA_LIMIT
        return 0

    # ------------------------------------------------------------------ 1 kHz loop
    def tick(self, q_rad: float, qd_rad_s: float, dt_s: float = TICK_S) -> float:
        """One control step from the measured joint state; returns the torque [N·m]."""
        ph = self.phys
        tau = 0.0
        self._clock_s += dt_s
        goal_vel, goal_pos = self._goal_vel_rad_s, self._goal_pos_rad
        if self._pending:
            while self._pending and self._pending[0][0] <= self._clock_s + 1e-12:
                self._pending.pop(0)
            if self._pending:  # a goal written less than input_delay_s ago: the older one still acts
                goal_vel, goal_pos = self._pending[0][1]["vel"], self._pending[0][1]["pos"]
        if self._torque_on and self._watchdog > 0:
            self._idle_s += dt_s
            if self._idle_s > self._watchdog * BUS_WATCHDOG_UNIT_S + 1e-9:
                self._trip_watchdog()
        if self._torque_on and not self._hw_error:
            if self._mode == VELOCITY_MODE:
                e = goal_vel - qd_rad_s
                tau_p = ph.vel_kp_nm_s * e
                gain_i = ph.vel_ki_nm
            else:
                e = goal_pos - q_rad
                tau_p = ph.pos_kp_nm_per_rad * e - ph.pos_kd_nm_s * qd_rad_s
                gain_i = ph.pos_ki_nm_per_rad_s
            tau_max = self._tau_max
            # anti-windup: integrate only while the output is not saturated by it
            trial = self._integral + e * dt_s
            if abs(tau_p + gain_i * trial) < tau_max:
                self._integral = trial
            tau = tau_p + gain_i * self._integral
            saturated = abs(tau) >= tau_max
            tau = tau_max if tau > tau_max else (-tau_max if tau < -tau_max else tau)
            self._saturated_s = self._saturated_s + dt_s if saturated else 0.0
            if self._saturated_s > ph.overload_s:
                self.inject_hardware_error(HW_OVERLOAD)
                tau = 0.0
        current_a = tau / ph.kt_nm_per_a
        if ph.friction_nm or ph.damping_nm_s:  # losses between the motor and the output shaft
            tau -= ph.friction_nm * max(-1.0, min(1.0, qd_rad_s / FRICTION_V_EPS_RAD_S)) + ph.damping_nm_s * qd_rad_s
        # thermal model: dT/dt = (ambient + k·I² − T) / tau
        self.temperature_c += dt_s * (ph.ambient_c + ph.thermal_c_per_a2 * current_a * current_a
                                      - self.temperature_c) / ph.thermal_tau_s
        if self.temperature_c >= self._temp_limit_c and not self._hw_error & HW_OVERHEATING:
            self.inject_hardware_error(HW_OVERHEATING)
        self._present = (q_rad, qd_rad_s, current_a)
        self._dirty = True
        return tau
