"""What a policy may declare beyond ``policy(state) -> normalized action``.

The controller node and the learning loops call any callable; these protocols name the
optional parts they use, so a policy says what it offers by having them, and callers ask with
``isinstance`` (the protocols are runtime-checkable: an attribute of that name is the claim):

* :class:`Resettable`: ``reset()`` at each episode's start (per-episode state: a planner's warm
  start, a filter, a cost's progress along its path).
* :class:`PlanningPolicy` (``last_plan``), :class:`PlanDetails` (its predicted states and
  cost), :class:`DelayAware` (``delay_steps``), :class:`HasPlanner` (``planner``): an MPC
  behind it; the controller node publishes its plan (``hil.Plan``), runs a late plan shifted,
  answers ``delay_steps`` with the commands already sent, and may refit the planner's samples.
* :class:`Shiftable`: ``shift(n)``, the planner's warm start moved on by ``n`` steps (a late
  plan's first actions are gone).
* :class:`Observing`: a cost's ``observe(state)`` before each plan.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Resettable(Protocol):
    def reset(self) -> None: ...


@runtime_checkable
class PlanningPolicy(Protocol):
    """It plans: ``last_plan`` [H, A] (normalized actions; None before its first plan). The
    controller node publishes it (``hil.Plan``) and runs a late plan's remaining steps."""

    last_plan: np.ndarray | None


@runtime_checkable
class PlanDetails(Protocol):
    """What a published plan carries beside the actions: the predicted states [H, S] (None:
    none) and the plan's cost."""

    last_predicted_states: np.ndarray | None
    last_cost: float


@runtime_checkable
class DelayAware(Protocol):
    """Commands already sent act before the planned one: called as ``policy(state,
    committed=...)`` with the last ``delay_steps`` of them when ``delay_steps`` > 0."""

    delay_steps: int


@runtime_checkable
class HasPlanner(Protocol):
    """Its planner (None: none), whose sample count (``samples``, ``set_samples(n)``) the
    controller node may refit to the load."""

    planner: Any


@runtime_checkable
class Shiftable(Protocol):
    def shift(self, n: int) -> None: ...


@runtime_checkable
class Observing(Protocol):
    """A cost that follows the robot between plans (a path cost's place on its path):
    ``observe(state)`` with each state the policy plans from."""

    def observe(self, state: np.ndarray) -> None: ...
