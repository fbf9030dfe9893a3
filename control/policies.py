"""Policies for the controller node: ``policy(state [S]) -> normalized action [A]``.

* :class:`SafeRandomPolicy`: the MBRL loop's random data collection, with the safety
  override of the thesis (keep the robot in the arena: when it nears the edge heading
  out, turn it back toward the centre).
* :class:`MpcPolicy`: a learned dynamics model + a sampling planner + a cost.
* :class:`BaselinePolicy`: wraps a hand-designed controller (differential drive).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from hilstack.control.costs import state_index
from hilstack.control.policy_api import Observing, Resettable


class SafeRandomPolicy:
    """Random normalized actions, each held for a random number of steps, inside an arena.

    Each held segment (``1..hold_steps`` steps, uniform) is, with probability
    ``1 − forward_fraction``, uniform over the action box (the thesis' random data) and
    otherwise a *forward* command for two-legged-set robots: mean leg command
    ``m ~ U(0, high)`` and difference ``d ~ U(−turn, turn)``, legs ``m ∓ d/2``. Uniform
    independent steps average out to a slow, wobbling gait: the data then barely covers
    the speeds path following asks for (docs/mbrl.md gives the measured coverage).

    Outside ``0.8·arena_radius_m`` while heading away from the centre, a differential
    turn toward the centre replaces the random action (differential-drive robots:
    action = (left, right)).
    """

    def __init__(
        self,
        state_names: Sequence[str],
        action_dim: int,
        arena_radius_m: float = 3.0,
        hold_steps: int = 1,
        low: float = -1.0,
        high: float = 1.0,
        seed: int = 0,
        forward_fraction: float = 0.0,
        turn: float = 0.5,
    ):
        if not 0.0 <= forward_fraction <= 1.0:
            raise ValueError(f"forward_fraction must be in [0, 1], got {forward_fraction}")
        if forward_fraction > 0 and action_dim != 2:
            raise ValueError("forward commands need a two-channel (left, right) action")
        self.ix = state_index(state_names, "x")
        self.iy = state_index(state_names, "y")
        self.ic = state_index(state_names, "cos_yaw")
        self.is_ = state_index(state_names, "sin_yaw")
        self.action_dim = action_dim
        self.arena = arena_radius_m
        self.hold = max(1, hold_steps)
        self.low, self.high = low, high
        self.forward_fraction = float(forward_fraction)
        self.turn = float(turn)
        self.rng = np.random.default_rng(seed)
        self._left = 0
        self._a = np.zeros(action_dim)
        self.overrides = 0

    def _draw(self) -> np.ndarray:
        if self.rng.uniform() < self.forward_fraction:
            m = self.rng.uniform(0.0, self.high)
            d = self.rng.uniform(-self.turn, self.turn)
            return np.clip(np.array([m - d / 2, m + d / 2]), self.low, self.high)
        return self.rng.uniform(self.low, self.high, self.action_dim)

    def __call__(self, state: np.ndarray) -> np.ndarray:
        p = np.array([state[self.ix], state[self.iy]])
        r = float(np.linalg.norm(p))
        heading = np.array([state[self.ic], state[self.is_]])
        if r > 0.8 * self.arena and float(heading @ p) > 0:
            self.overrides += 1
            to_centre = -p / max(r, 1e-9)
            cross = heading[0] * to_centre[1] - heading[1] * to_centre[0]
            turn = 0.6 if cross >= 0 else -0.6  # >0: centre is to the left → right legs faster
            return np.clip(np.array([0.3 - turn, 0.3 + turn]), -1, 1)
        if self._left <= 0:
            self._a = self._draw()
            self._left = int(self.rng.integers(1, self.hold + 1))
        self._left -= 1
        return self._a.copy()


class MpcPolicy:
    """``planner(dynamics, cost, state)`` with a learned model over normalized actions.

    ``model_source`` (online adaptation, learning/adaptation/node.py ``ModelSwap``): called
    at the start of every plan, in the planner's thread; it returns a new dynamics function
    ``(state, action) -> next state`` to plan with from now on, or None to keep the current
    one. The swap happens between plans, never inside one.
    """

    def __init__(self, model: Any, planner: Any, cost: Callable[..., torch.Tensor],
                 model_source: Callable[[], Any] | None = None, delay_steps: int = 0):
        if delay_steps < 0:
            raise ValueError(f"delay_steps must be >= 0, got {delay_steps}")
        #: commands already on their way when a state is measured: on a wall-clock robot
        #: (real, emulated) the command planned from a state is applied at the driver
        #: node's next period, while the one sent before acts (1: the spec's
        #: ``pacing.command_delay_periods``, ``ControllerNode.pacing``). The plan then starts from the state the model predicts
        #: after those (``committed`` of :meth:`__call__`, given by the controller node).
        self.delay_steps = int(delay_steps)
        self.model = model
        #: the dynamics swapped in by ``model_source`` (None: ``model.predict``)
        self.dynamics = None
        self.model_source = model_source
        self.planner = planner
        self.cost = cost
        self.last_plan: np.ndarray | None = None
        self.last_predicted_states: np.ndarray | None = None
        self.last_cost = 0.0

    def reset(self) -> None:
        self.planner.reset()
        if isinstance(self.cost, Resettable):
            self.cost.reset()

    def __call__(self, state: np.ndarray, committed: Sequence[np.ndarray] | None = None) -> np.ndarray:
        """The first action of a plan from ``state``; with ``committed`` (normalized
        actions, oldest first, that act before this plan's first one) from the state the
        model predicts after them."""
        if self.model_source is not None:
            new = self.model_source()
            if new is not None:
                self.dynamics = new
        if isinstance(self.cost, Observing):
            self.cost.observe(state)  # a path cost tracks the robot's place on the path
        dynamics = self.dynamics or self.model.predict
        start = self.predict_after(dynamics, state, committed) if committed is not None and len(committed) else state
        a = self.planner(dynamics, self.cost, start)
        self.last_plan = self.planner.last_plan.numpy()
        pred = self.planner.last_predicted_states
        self.last_predicted_states = None if pred is None else pred.mean(0).numpy()
        costs = self.planner.last_costs
        self.last_cost = float(costs.min()) if costs is not None else 0.0
        return a


    def shift(self, n: int) -> None:
        """The last plan is applied ``n`` periods late: the planner moves along it
        (:meth:`hilstack.control.planners.Planner.shift`)."""
        self.planner.shift(n)

    @staticmethod
    def predict_after(dynamics: Callable[..., torch.Tensor], state: np.ndarray,
                      actions: Sequence[np.ndarray]) -> np.ndarray:
        """``state`` rolled forward through ``actions`` with the model: an ensemble's
        ``[E, B, S]`` by its mean over members, a single model's ``[B, S]`` (the adaptation
        adapters' dynamics) as it is, as the planners' rollout takes both."""
        with torch.inference_mode():
            x = torch.as_tensor(np.asarray(state), dtype=torch.float32).unsqueeze(0)
            for a in actions:
                u = torch.as_tensor(np.asarray(a), dtype=torch.float32).reshape(1, -1)
                nxt = dynamics(x, u)
                x = nxt.mean(0) if nxt.dim() == 3 else nxt
        return x[0].numpy().astype(np.float64)


class BaselinePolicy:
    def __init__(self, controller: Callable[[np.ndarray], np.ndarray]):
        self.controller = controller

    def reset(self) -> None:
        if isinstance(self.controller, Resettable):
            self.controller.reset()

    def __call__(self, state: np.ndarray) -> np.ndarray:
        return np.asarray(self.controller(state), dtype=np.float64)
