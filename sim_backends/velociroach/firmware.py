"""The VelociRoACH on-board firmware behaviour, shared by the sim backend and the emulator.

What the dsPIC board does every 1 ms tick (after the Biomimetic Millisystems Lab
firmware the VelociRoACH runs, as described by Haldane et al. 2013 and Nagabandi's
thesis): read the crank encoders, run one PID per side on leg (crank) velocity, or pass
a PWM duty through, saturate the duty, and stop the motors when commands stop coming.

Pure Python, no I/O, no clock of its own: the caller passes ``now_s`` (sim time in the
sim backend, wall time in the emulator) and calls :meth:`Firmware.tick` at 1 kHz.
Scalar float arithmetic on purpose: this runs 1000 times per simulated second and
numpy's per-call overhead would dominate (see ``tools/bench_sim.py``).

Units: leg velocity in rev/s of the crank (positive drives the robot forward), crank
angle in rad, duty in [-1, 1] (sign = motor direction), voltages in V, currents in A.

PID (per side): error e = ω_ref − ω [rev/s]; the integral is of e over time, i.e. the
crank *angle* error in rev, so the integral term also holds the phase between the two
sides (the alternating tripod) while both track the same speed:

    duty = ff·ω_ref/vbat + kp·e + ki·∫e dt + kd·de/dt

``ff`` [V per rev/s] is a back-EMF feed-forward (k_e·G·2π for the nominal motor).
The integral is clamped so that its term stays within ±``i_limit_duty`` (anti-windup).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hilstack.drivers.velociroach.mavlink import mav

TICK_S = 0.001
TICK_HZ = 1000

#: fault bits reported in telemetry: the dialect XML's ROACH_FAULT enum is their one definition
FAULT_WATCHDOG = mav.ROACH_FAULT_WATCHDOG
FAULT_LOW_BATTERY = mav.ROACH_FAULT_LOW_BATTERY
FAULT_MOTOR = mav.ROACH_FAULT_MOTOR  # stall or over-current


@dataclass
class FirmwareConfig:
    """Firmware settings (units in names)."""

    kp_duty_per_rps: float = 0.05
    ki_duty_per_rev: float = 1.5
    kd_duty_per_rps2: float = 0.0
    ff_v_per_rps: float = 0.2
    i_limit_duty: float = 0.8
    max_duty: float = 1.0
    watchdog_s: float = 0.5
    low_battery_v: float = 3.4
    overcurrent_a: float = 1.5


class Firmware:
    """One board: two PID loops (left, right), PWM pass-through, watchdog, fault flags."""

    def __init__(self, config: FirmwareConfig | None = None):
        self.config = config or FirmwareConfig()
        self.reset()

    # ------------------------------------------------------------------ commands
    def reset(self) -> None:
        """Power-on state: clock at 0, motors off, no command received yet."""
        self.t_fw_ms = 0
        self.mode = "leg_velocity"  # or "pwm"
        self.setpoint_l = 0.0  # rev/s (velocity mode) or duty (pwm mode)
        self.setpoint_r = 0.0
        self.duty_l = 0.0
        self.duty_r = 0.0
        self._int_l = 0.0  # rev
        self._int_r = 0.0
        self._prev_e_l = 0.0
        self._prev_e_r = 0.0
        self.last_cmd_s: float | None = None
        self.watchdog_tripped = False
        self.faults = 0
        self.commands_received = 0

    def set_leg_velocity(self, left_rps: float, right_rps: float, now_s: float) -> None:
        """Leg-velocity mode with setpoints in rev/s; feeds the watchdog."""
        if self.mode != "leg_velocity":
            self._int_l = self._int_r = 0.0
        self.mode = "leg_velocity"
        self.setpoint_l, self.setpoint_r = float(left_rps), float(right_rps)
        self._fed(now_s)

    def set_pwm(self, left_duty: float, right_duty: float, now_s: float) -> None:
        """PWM pass-through mode, duty in [-1, 1] (saturated to ``max_duty``); feeds the watchdog."""
        self.mode = "pwm"
        self.setpoint_l, self.setpoint_r = float(left_duty), float(right_duty)
        self._fed(now_s)

    def set_gains(self, kp: float, ki: float, kd: float) -> None:
        """PID gains: kp [duty per rev/s], ki [duty per rev], kd [duty per rev/s²]."""
        c = self.config
        c.kp_duty_per_rps, c.ki_duty_per_rev, c.kd_duty_per_rps2 = float(kp), float(ki), float(kd)

    def stop(self, now_s: float) -> None:
        """Zero leg velocity (the PID holds the legs where they are)."""
        self.set_leg_velocity(0.0, 0.0, now_s)

    def _fed(self, now_s: float) -> None:
        if self.watchdog_tripped:
            # re-arm from rest: the integral from before the trip is stale
            self._int_l = self._int_r = 0.0
        self.last_cmd_s = float(now_s)
        self.watchdog_tripped = False
        self.commands_received += 1

    # ------------------------------------------------------------------ 1 kHz loop
    def tick(
        self, now_s: float, vel_l_rps: float, vel_r_rps: float, vbat_v: float, current_l_a: float, current_r_a: float
    ) -> tuple[float, float]:
        """One 1 ms control step from the measured crank velocities; returns (duty_l, duty_r)."""
        c = self.config
        self.t_fw_ms += 1
        faults = 0
        if self.last_cmd_s is not None and not self.watchdog_tripped and now_s - self.last_cmd_s > c.watchdog_s:
            self.watchdog_tripped = True
            self.setpoint_l = self.setpoint_r = 0.0
            self._int_l = self._int_r = 0.0
        if self.watchdog_tripped or self.last_cmd_s is None:
            # motors off (terminals shorted: the back-EMF brakes the legs)
            dl = dr = 0.0
            if self.watchdog_tripped:
                faults |= FAULT_WATCHDOG
        elif self.mode == "pwm":
            dl, dr = self.setpoint_l, self.setpoint_r
        else:
            vb = vbat_v if vbat_v > 1.0 else 1.0
            ff = c.ff_v_per_rps / vb
            el = self.setpoint_l - vel_l_rps
            er = self.setpoint_r - vel_r_rps
            ki = c.ki_duty_per_rev
            if ki > 0.0:
                lim = c.i_limit_duty / ki
                il = self._int_l + el * TICK_S
                ir = self._int_r + er * TICK_S
                self._int_l = lim if il > lim else (-lim if il < -lim else il)
                self._int_r = lim if ir > lim else (-lim if ir < -lim else ir)
            kd = c.kd_duty_per_rps2 * TICK_HZ
            dl = ff * self.setpoint_l + c.kp_duty_per_rps * el + ki * self._int_l + kd * (el - self._prev_e_l)
            dr = ff * self.setpoint_r + c.kp_duty_per_rps * er + ki * self._int_r + kd * (er - self._prev_e_r)
            self._prev_e_l, self._prev_e_r = el, er
        m = c.max_duty
        self.duty_l = m if dl > m else (-m if dl < -m else dl)
        self.duty_r = m if dr > m else (-m if dr < -m else dr)
        if vbat_v < c.low_battery_v:
            faults |= FAULT_LOW_BATTERY
        if abs(current_l_a) > c.overcurrent_a or abs(current_r_a) > c.overcurrent_a:
            faults |= FAULT_MOTOR
        self.faults = faults
        return self.duty_l, self.duty_r

    def snapshot(self) -> dict:
        """The firmware-owned part of a telemetry packet."""
        return {
            "t_fw_ms": int(self.t_fw_ms),
            "mode": self.mode,
            "setpoint": (self.setpoint_l, self.setpoint_r),
            "duty": (self.duty_l, self.duty_r),
            "faults": int(self.faults),
        }


def default_ff_v_per_rps(k_e_v_s_per_rad: float, gear_ratio: float) -> float:
    """Back-EMF feed-forward [V per crank rev/s] for a motor constant and gear ratio."""
    return k_e_v_s_per_rad * gear_ratio * 2.0 * math.pi
