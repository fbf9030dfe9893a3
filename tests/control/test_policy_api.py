"""A policy's optional parts are declared protocols (control/policy_api.py), not attribute probes."""

from __future__ import annotations

import numpy as np

from hilstack.control.planners import RandomShooting
from hilstack.control.policies import BaselinePolicy, MpcPolicy
from hilstack.control.policy_api import (
    DelayAware,
    HasPlanner,
    Observing,
    PlanDetails,
    PlanningPolicy,
    Resettable,
    Shiftable,
)
from hilstack.learning.reach import HeldPolicy

ALL = (PlanningPolicy, PlanDetails, DelayAware, HasPlanner, Resettable, Shiftable)


def test_what_each_policy_declares():
    mpc = MpcPolicy(model=None, planner=RandomShooting(action_dim=2, horizon=3, samples=8), cost=lambda *a: 0.0,
                    delay_steps=1)
    assert all(isinstance(mpc, p) for p in ALL)  # the MPC offers everything the controller node uses
    assert not any(isinstance(lambda x: x, p) for p in ALL)  # a plain function: none of it

    class Stateful:  # a controller with per-episode state only
        def reset(self):
            pass

        def __call__(self, x):
            return x

    assert isinstance(BaselinePolicy(Stateful()), Resettable)
    held = HeldPolicy(mpc, 3, [0, 1])
    assert isinstance(held, PlanningPolicy) and isinstance(held, PlanDetails) and isinstance(held, Resettable)
    assert not isinstance(held, DelayAware) and not isinstance(held, HasPlanner)  # it calls the inner with the state alone
    mpc.last_plan, mpc.last_cost = np.ones((3, 2)), 2.5
    assert held.last_plan is mpc.last_plan and held.last_cost == 2.5  # what the node publishes is the inner MPC's
    assert HeldPolicy(lambda x: x, 3, [0]).last_plan is None


def test_a_cost_that_follows_the_robot_is_observed():
    class PathLike:
        def __call__(self, *a):
            return 0.0

        def observe(self, state):
            pass

    assert isinstance(PathLike(), Observing) and not isinstance(lambda *a: 0.0, Observing)
