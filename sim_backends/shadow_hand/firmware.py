"""The Shadow Hand's motor-board firmware behaviour, shared by the sim backend and the emulator.

Every 1 ms tick it runs one joint position loop per actuated joint (20), with the
measured joint angle and velocity:

    e = target − q
    effort = clip(kp·e + ki·∫e dt − kd·q̇, −torque_limit, +torque_limit)   [N·m]

The integral removes the steady-state error a P loop leaves under gravity (the wrist
sags ~0.1 rad with P alone), which matters because "stop" holds the *measured*
position: with a P loop every hold would sag a little further. Anti-windup: the
integral term is clamped to ±torque_limit.

Commands arrive as joint position targets [rad]; the firmware never trusts them: a
non-finite target is refused, a target outside the joint's range is clamped to it.

Safety, all on the firmware's own clock (``now_s``, passed by the caller: sim time in
the sim backend, the emulator's clock in the emulator):

* **watchdog**: no command (targets or host heartbeat) for ``watchdog_s`` → targets
  become the measured position (hold where it is), mode HOLD, fault bit WATCHDOG. A new
  target frame re-arms it.
* **e-stop**: latched; targets become the measured position, mode ESTOP; target frames
  are ignored until the host releases it.
* **motor fault** (injected): a faulted motor's effort is 0 (limp); the bit stays set.

Effects the hand's MuJoCo model lacks (``FirmwareConfig``'s ``friction_nm``, ``damping_nm_s``,
``input_delay_s``; the sim's and the emulator's ``params.sim.effects``, for calibration:
docs/calibration.md): Coulomb and viscous losses in the tendon drive between the motor, whose
effort is reported, and the joint, and a delay before a target frame takes effect.

Pure Python/numpy, no I/O, no threads (the caller owns the clock and the loop).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilstack.drivers.shadow_hand.protocol import (  # noqa: F401 - re-exported for the emulator and tests
    FAULT_BUS_OFF,
    FAULT_ESTOP,
    FAULT_MOTOR,
    FAULT_RX_ERROR,
    FAULT_WATCHDOG,
    MODE_ESTOP,
    MODE_HOLD,
    MODE_POSITION,
)
from hilstack.sim_backends.effects import FRICTION_V_EPS_RAD_S, validate_effects

TICK_S = 0.001

# modes and fault bits are the wire protocol's (drivers/shadow_hand/protocol.py)


@dataclass
class FirmwareConfig:
    """Gains and limits per actuated joint (arrays of 20), units in names."""

    kp_nm_per_rad: np.ndarray
    kd_nms_per_rad: np.ndarray
    ki_nm_per_rad_s: np.ndarray
    torque_limit_nm: np.ndarray
    joint_low_rad: np.ndarray
    joint_high_rad: np.ndarray
    watchdog_s: float = 0.5
    #: Coulomb friction in each joint's drive [N·m], opposing the joint's motion (0: absent)
    friction_nm: float = 0.0
    #: viscous friction in each joint's drive [N·m·s/rad]
    damping_nm_s: float = 0.0
    #: a target frame takes effect this long after it arrived [s]
    input_delay_s: float = 0.0


#: ``effects`` keys -> (FirmwareConfig field, upper bound): what the sim/emulator can add to the hand
EFFECTS = {"joint_friction_nm": ("friction_nm", 0.5), "joint_damping_nm_s": ("damping_nm_s", 2.0),
           "input_delay_s": ("input_delay_s", 0.5)}


def effect_fields(effects: dict | None) -> dict[str, float]:
    """Validate an ``effects`` mapping into FirmwareConfig fields (a ValueError names the bad key or value)."""
    return validate_effects(effects, EFFECTS)


class HandFirmware:
    """The motor boards of one hand (20 position loops, watchdog, e-stop, faults)."""

    def __init__(self, config: FirmwareConfig):
        self.config = config
        self.n = len(config.kp_nm_per_rad)
        self.reset()

    def reset(self, q_rad: np.ndarray | None = None) -> None:
        """Power-on: hold ``q_rad`` (the measured position), no command received yet."""
        self.t_fw_ms = 0
        self.mode = MODE_HOLD
        self.target_rad = np.zeros(self.n) if q_rad is None else np.array(q_rad, dtype=np.float64)
        self.effort_nm = np.zeros(self.n)
        self.integral_rad_s = np.zeros(self.n)
        self.last_cmd_s: float | None = None
        self.watchdog_tripped = False
        self.estop = False
        self.motor_fault_mask = 0
        self.rx_error = False
        self.bus_off_event = False
        self.commands_received = 0
        self.commands_refused = 0
        self._q = self.target_rad.copy()
        #: (due [s], the targets the loops keep using until then) of delayed target frames
        self._pending: list[tuple[float, np.ndarray]] = []

    def preload(self, effort_nm: np.ndarray) -> None:
        """Start as if the hand had been holding its pose: the integral term carries
        ``effort_nm`` (e.g. the static gravity load at a sim reset), so nothing sags."""
        ki = self.config.ki_nm_per_rad_s
        self.integral_rad_s = np.divide(np.asarray(effort_nm, dtype=np.float64), ki,
                                        out=np.zeros(self.n), where=ki > 0)

    # ------------------------------------------------------------------ commands
    def set_targets(self, first: int, targets_rad: np.ndarray, now_s: float) -> bool:
        """Targets for joints ``first .. first+len-1`` (actuator order). Returns False
        (and flags RX_ERROR) when refused: non-finite values, or an e-stop is latched."""
        t = np.asarray(targets_rad, dtype=np.float64)
        if self.estop or not np.all(np.isfinite(t)) or first < 0 or first + t.size > self.n:
            self.commands_refused += 1
            if not self.estop:
                self.rx_error = True
            return False
        c = self.config
        sl = slice(first, first + t.size)
        if c.input_delay_s > 0:  # the loops see this frame input_delay_s later
            self._pending.append((float(now_s) + c.input_delay_s, self.target_rad.copy()))
        self.target_rad[sl] = np.clip(t, c.joint_low_rad[sl], c.joint_high_rad[sl])
        self.mode = MODE_POSITION
        self._fed(now_s)
        return True

    def heartbeat(self, now_s: float) -> None:
        """The host is alive: feeds the watchdog (targets unchanged)."""
        if self.mode == MODE_POSITION:
            self._fed(now_s)

    def set_estop(self, engaged: bool) -> None:
        """Engage (latched hold at the measured position) or release (hold, wait for targets)."""
        if engaged and not self.estop:
            self._pending.clear()  # an e-stop acts at once, whatever the drive's delay
            self.target_rad = self._q.copy()
            self.mode = MODE_ESTOP
        elif not engaged and self.estop:
            self.mode = MODE_HOLD
            self.last_cmd_s = None
        self.estop = bool(engaged)

    def inject_motor_fault(self, index: int) -> None:
        self.motor_fault_mask |= 1 << int(index)

    def _fed(self, now_s: float) -> None:
        self.last_cmd_s = float(now_s)
        self.watchdog_tripped = False
        self.commands_received += 1

    # ------------------------------------------------------------------ 1 kHz loop
    def tick(self, now_s: float, q_rad: np.ndarray, qd_rad_s: np.ndarray) -> np.ndarray:
        """One 1 ms step from the measured actuated-joint angles/velocities; returns the
        motor efforts [N·m] (actuator order)."""
        c = self.config
        self.t_fw_ms += 1
        self._q = q_rad
        if (self.mode == MODE_POSITION and self.last_cmd_s is not None
                and now_s - self.last_cmd_s > c.watchdog_s):
            # the host went quiet: hold where the hand is now, not at a stale target
            self.watchdog_tripped = True
            self.mode = MODE_HOLD
            self.target_rad = np.array(q_rad, dtype=np.float64)
            self._pending.clear()
        target = self.target_rad
        if self._pending:
            while self._pending and self._pending[0][0] <= now_s + 1e-12:
                self._pending.pop(0)
            if self._pending:  # a frame that arrived less than input_delay_s ago: the older targets act
                target = self._pending[0][1]
        err = target - q_rad
        ki = c.ki_nm_per_rad_s
        lim_i = np.divide(c.torque_limit_nm, ki, out=np.zeros(self.n), where=ki > 0)
        self.integral_rad_s = np.clip(self.integral_rad_s + err * TICK_S, -lim_i, lim_i)
        e = c.kp_nm_per_rad * err + ki * self.integral_rad_s - c.kd_nms_per_rad * qd_rad_s
        np.clip(e, -c.torque_limit_nm, c.torque_limit_nm, out=e)
        if self.motor_fault_mask:
            for i in range(self.n):
                if self.motor_fault_mask >> i & 1:
                    e[i] = 0.0
        self.effort_nm = e
        if c.friction_nm or c.damping_nm_s:  # losses between the motor (its effort is reported) and the joint
            qd = np.asarray(qd_rad_s, dtype=np.float64)
            return e - c.friction_nm * np.clip(qd / FRICTION_V_EPS_RAD_S, -1.0, 1.0) - c.damping_nm_s * qd
        return e

    @property
    def faults(self) -> int:
        f = 0
        if self.watchdog_tripped:
            f |= FAULT_WATCHDOG
        if self.estop:
            f |= FAULT_ESTOP
        if self.motor_fault_mask:
            f |= FAULT_MOTOR
        if self.rx_error:
            f |= FAULT_RX_ERROR
        if self.bus_off_event:
            f |= FAULT_BUS_OFF
        return f
