"""WidowX 250 and task-reset mechanism drivers: the contract over a Dynamixel bus.

backend "real": ``params.port`` (a U2D2 or other USB-serial adapter, docs/arms.md).
backend "emulated": the same code against the bus emulator process
(``python -m hilstack.sim_backends.widowx.emulator``) on a pty it creates.
The sim backend (sim_backends/widowx/backend.py) runs this same code over an in-process
bus on the MuJoCo world, in lockstep.

WidowX: joint velocity commands to the servos' velocity loops (Operating Mode 1).
``limit()`` adds to the contract's clamps a joint-limit guard: a joint within
``limit_margin_rad`` of a limit may only move away from it (the servo ignores its
position limits in velocity mode). ``stop()``: zero velocity to every joint, then
position hold at the measured pose (Operating Mode 3), read back (``stop_confirmed``);
the next ``write()`` returns to velocity mode. After a Bus Watchdog trip (the servos
stopped themselves) the rate limit restarts from zero velocity, as the joints are.

Mechanism: target rotation [rad] and rail offset [m] to the servos' position loops; stop
holds the measured pose.
"""

from __future__ import annotations

import math

import numpy as np

from hilstack.drivers.base import Observation
from hilstack.drivers.dynamixel.control_table import OPERATING_MODES, pos_counts, vel_counts
from hilstack.drivers.dynamixel.position import PositionRobot
from hilstack.drivers.dynamixel.robot import DynamixelRobot
from hilstack.drivers.widowx.config import (
    JOINT_NAMES,
    MECH_JOINTS,
    MechanismParams,
    WidowXParams,
    joint_limits,
    mechanism_spec,
    widowx_spec,
)

VELOCITY = OPERATING_MODES["velocity"]


class WidowXDriver(DynamixelRobot):
    params_type = WidowXParams

    def __init__(self, params: WidowXParams | None = None, backend: str = "real", source: str | None = None):
        params = params or WidowXParams()
        self.ids = {n: params.ids[n] for n in JOINT_NAMES}
        self.spec = widowx_spec(params)
        super().__init__(params, backend, source)
        lim = joint_limits(params)
        self._lo = np.array([lim[n][0] for n in JOINT_NAMES])
        self._hi = np.array([lim[n][1] for n in JOINT_NAMES])
        self._vel_limit_counts: dict[int, int] = {}

    def _emulator_config(self) -> dict:
        return {"arm_ids": self.ids}

    def _on_bus_ready(self) -> None:
        self._vel_limit_counts = {i: self.bus.read(i, "Velocity Limit") for i in self.ids.values()}

    # ------------------------------------------------------------------ contract
    def _read(self) -> Observation:
        self._read_bus()
        state = np.concatenate([self._q, self._qd, self._cur])
        return self._observation(state, {"temperatures_c": self._temp_c.tolist()})

    def _hold_command(self, obs: Observation) -> np.ndarray:
        # what the servos run: in position mode (after a stop) they hold still, zero velocity;
        # in velocity mode what the joints do now (≈ 0 at rest) is what keeps them there
        if self._mode != VELOCITY:
            return np.zeros(self.spec.action.dim)
        return np.clip(obs.state[6:12], self.spec.action.low, self.spec.action.high)

    def _on_activate(self) -> None:
        self._send_velocity(self._held)

    def limit(self, a: np.ndarray, now_s: float) -> np.ndarray:
        if self.watchdog_tripped:  # the servos stopped themselves: ramp up again from rest
            self._anchor(self.spec.safe_action, now_s)
        a = super().limit(a, now_s)
        p = self.spec.period_s
        if self.telemetry_age_s() > p and self.now() - self._t_read_try > p:
            # the guard needs the pose now, not the one of the last read(); at most one read
            # per period (a silent device must not cost every write a read timeout)
            self._read_bus()
        m = self.params.limit_margin_rad
        q = self._q
        # towards a limit inside the margin: not allowed (finite q only: NaN compares False)
        a = np.where((q >= self._hi - m) & (a > 0), 0.0, a)
        a = np.where((q <= self._lo + m) & (a < 0), 0.0, a)
        return a

    def _write(self, action: np.ndarray) -> None:
        self._send_velocity(action)

    def _send_velocity(self, v_rad_s: np.ndarray) -> None:
        goal = {}
        for (_, dxl_id), v in zip(self.ids.items(), v_rad_s, strict=True):
            lim = self._vel_limit_counts.get(dxl_id, 0)
            goal[dxl_id] = max(-lim, min(lim, vel_counts(float(v))))
        self._stop_confirmed = False
        if self._mode != VELOCITY:
            self._send(self.set_mode, "velocity", {i: ("Goal Velocity", c) for i, c in goal.items()})
        else:
            self._send(self.bus.sync_write, "Goal Velocity", goal)

    def _stop(self) -> None:
        self._stop_confirmed = False
        if self.bus is None or self.bus.closed:
            return
        ids = list(self.ids.values())
        if self._mode == VELOCITY:
            self.bus.sync_write("Goal Velocity", {i: 0 for i in ids})  # first: stop moving
        try:
            self._sync_read()
        finally:
            hold = {i: ("Goal Position", self.clamp_goal_position(i, pos_counts(float(q), self.bus.table.zero_count)))
                    for i, q in zip(ids, self._q, strict=True) if math.isfinite(q)}
            if len(hold) == len(ids):
                self.set_mode("position", hold)
                self._stop_confirmed = self._confirm_hold({i: c for i, (_, c) in hold.items()})


class MechanismDriver(PositionRobot):
    params_type = MechanismParams

    def __init__(self, params: MechanismParams | None = None, backend: str = "real", source: str | None = None):
        params = params or MechanismParams()
        self.ids = {n: params.ids[n] for n in MECH_JOINTS}
        self.spec = mechanism_spec(params)
        super().__init__(params, backend, source)
        #: servo shaft angle per unit of each action channel (rad per rad, rad per m)
        self._scale = np.array([1.0, 1.0 / params.rail_pinion_radius_m])

    def _emulator_config(self) -> dict:
        return {"mech_ids": self.ids}

    def pose(self) -> tuple[float, float]:
        """(rotation [rad], offset [m]) as last measured."""
        r, o = self._q / self._scale
        return float(r), float(o)
