"""A Dynamixel robot whose servos run their position loops: the action is the target pose.

The state is the pose and its rates, each channel a servo's shaft angle divided by its
``_scale`` (1 for a joint in rad; 1/radius for a rail in m). Activation and ``stop()`` hold
the measured pose (the spec's ``safe_action`` is None), read back (``stop_confirmed``).
The WidowX bench's task-reset mechanism and the pan unit are such robots.
"""

from __future__ import annotations

import numpy as np

from hilstack.drivers.base import Observation
from hilstack.drivers.dynamixel.control_table import OPERATING_MODES, pos_counts
from hilstack.drivers.dynamixel.robot import DynamixelRobot


class PositionRobot(DynamixelRobot):
    """A subclass sets ``ids`` and ``spec`` (action: one target per servo, in ``ids`` order)
    before ``super().__init__``, and ``_scale`` after it when a channel is not a shaft angle."""

    def __init__(self, params, backend: str, source: str | None):
        super().__init__(params, backend, source)
        #: servo shaft angle per unit of each action channel (rad per unit)
        self._scale = np.ones(len(self.ids))

    def _read(self) -> Observation:
        self._read_bus()
        pose = self._q / self._scale
        state = np.concatenate([pose, self._qd / self._scale])
        return self._observation(state, {"temperatures_c": self._temp_c.tolist()})

    def _hold_command(self, obs: Observation) -> np.ndarray:
        return np.clip(obs.state[: len(self.ids)], self.spec.action.low, self.spec.action.high)

    def _on_activate(self) -> None:
        self._send_pose(self._held)

    def _write(self, action: np.ndarray) -> None:
        self._send_pose(action)

    def _send_pose(self, pose: np.ndarray) -> dict[int, int]:
        goal = {i: self.clamp_goal_position(i, pos_counts(float(x * s), self.bus.table.zero_count))
                for i, x, s in zip(self.ids.values(), pose, self._scale, strict=True)}
        self._stop_confirmed = False
        if self._mode != OPERATING_MODES["position"]:
            self._send(self.set_mode, "position", {i: ("Goal Position", c) for i, c in goal.items()})
        else:
            self._send(self.bus.sync_write, "Goal Position", goal)
        return goal

    def _hold_target(self, target: np.ndarray) -> None:
        """The stop at the held target (``Driver.stop``), read back (``stop_confirmed``)."""
        goal = self._send_pose(target)
        self._stop_confirmed = self._confirm_hold(goal)

    def _stop(self) -> np.ndarray | None:
        """Hold the measured pose, read back (``stop_confirmed``); returns it (the held
        command and the rate limit restart there)."""
        self._stop_confirmed = False
        if self.bus is None or self.bus.closed:
            return None
        self._sync_read()
        pose = self._q / self._scale
        if not np.all(np.isfinite(pose)):
            return None
        goal = self._send_pose(pose)
        self._stop_confirmed = self._confirm_hold(goal)
        return np.clip(pose, self.spec.action.low, self.spec.action.high)
