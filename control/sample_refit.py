"""The planner's sample count on the wall clock, refitted from measured plan times.

:func:`refit_samples` is the rule (one implementation): ``hil demo`` (``MbrlRun.run_paths``,
after every MPC episode) and the controller node (:class:`SampleRefit`, every few seconds of
one long realtime episode: ``hil mpc``) both call it. The first fit, before any plan ran, is
``hilstack.learning.mbrl.fit_samples_to_budget``. Lockstep rigs have no deadline and never refit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def refit_samples(samples: int, plan_times_s, late_plans: int, steps: int, *, max_samples: int,
                  min_samples: int, budget_s: float, deadline_s: float, max_late_share: float = 0.05,
                  max_growth: float = 2.0, min_change: float = 0.1) -> tuple[int, dict[str, Any]]:
    """The planner's sample count refitted from one episode on the wall clock: the plan
    times it measured (``plan_times_s``, seconds) and its late-plan share (``late_plans``
    of ``steps`` commands sent the shifted last plan: ``EpisodeLog.late_plans``).

    :func:`fit_samples_to_budget` fits the count once, at the start; the load of a shared
    machine changes within minutes (issue 29: a run that kept N = 500 from a 29 ms plan at
    a quiet moment then planned 274-542 ms median against the 80 ms deadline). The count is
    scaled by the smallest of ``budget_s / p50`` (the median plan within the budget, as the
    first fit) and ``deadline_s / p_tail``, the plan-time quantile ``1 - max_late_share``
    within the deadline (plan time taken as proportional to the samples: with a fixed
    overhead a cut falls short and the next episode cuts again). A late share above
    ``max_late_share`` cuts by at least a quarter (cycles were late for reasons the plan
    times alone do not show: the planner's thread waiting for the core) and never grows.
    Growth is at most ``max_growth`` times per refit; the result stays within
    [``min_samples``, ``max_samples``] (the configured count), and a growth under
    ``min_change`` of the count is not made (no churn on noise); a plan over the budget or
    the deadline is always cut.

    Returns the new count and a record: ``from``, ``to``, ``plan_ms_p50``, ``plan_ms_tail``,
    ``late_share``, ``reason``."""
    n = int(samples)
    t = np.asarray(list(plan_times_s), dtype=float)
    late_share = float(late_plans) / steps if steps > 0 else 0.0
    rec: dict[str, Any] = {"from": n, "to": n, "plans": int(t.size), "late_share": late_share,
                           "plan_ms_p50": None, "plan_ms_tail": None, "reason": "no plans measured"}
    if t.size == 0:
        return n, rec
    p50 = float(np.median(t))
    tail = float(np.quantile(t, 1.0 - max_late_share))
    rec.update(plan_ms_p50=p50 * 1e3, plan_ms_tail=tail * 1e3)
    r_med = budget_s / max(p50, 1e-9)
    r_tail = deadline_s / max(tail, 1e-9)
    r = min(r_med, r_tail)
    reason = "median over the budget" if r_med <= r_tail else f"p{100 * (1 - max_late_share):.0f} over the deadline"
    if late_share > max_late_share:
        r = min(r, 0.75)
        reason = f"late share {late_share:.0%} over {max_late_share:.0%}"
    elif r > 1.0:
        r = min(r, max_growth)
        reason = "plans within budget and deadline: room to grow"
    else:
        reason = reason if r < 1.0 else "plans at the budget"
    target = int(min(max_samples, max(min_samples, math.floor(n * r))))
    if n < target < (1.0 + min_change) * n and target != max_samples:
        rec["reason"] = f"{reason} (growth under {min_change:.0%}: kept)"
        return n, rec
    rec.update(to=target, reason=reason)
    return target, rec


@dataclass
class SampleRefit:
    """Periodic :func:`refit_samples` within one realtime episode (``hil mpc`` may run one
    long episode while the machine's load changes): every ``every_steps`` commands sent,
    once at least ``min_plans`` plans came back in that window (a planner much slower than
    the period widens the window instead of refitting from nothing), the count is refitted
    from that window's plan times and late plans. The controller node applies the new count
    between two plans (``planner.set_samples``), never during one. ``refits`` lists the changes
    (:func:`refit_samples`' records, with ``at_step``); ``samples`` is the count now."""

    max_samples: int
    min_samples: int
    budget_s: float
    deadline_s: float
    max_late_share: float = 0.05
    every_steps: int = 50
    min_plans: int = 5
    samples: int | None = None
    refits: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.every_steps < 1 or self.min_plans < 1 or self.min_samples < 1 or self.max_samples < self.min_samples:
            raise ValueError(f"SampleRefit: every_steps, min_plans >= 1 and 1 <= min_samples <= max_samples, got "
                             f"{self.every_steps}, {self.min_plans}, {self.min_samples}, {self.max_samples}")
        if not (0 < self.budget_s <= self.deadline_s and math.isfinite(self.deadline_s)):
            raise ValueError(f"SampleRefit: need 0 < budget_s <= deadline_s (finite), got {self.budget_s}, {self.deadline_s}")
        self._mark = (0, 0, 0)  # (commands, plans, late plans) of the log when the window started

    def start(self, samples: int) -> None:
        """A new episode with ``samples`` in the planner: the window starts empty."""
        self.samples = int(samples)
        self._mark = (0, 0, 0)

    def update(self, log: Any, samples: int) -> int:
        """The count for the next plan, given the episode's log so far (``actions``,
        ``plan_times_s``, ``late_plans``: :class:`hilstack.control.controller_node.EpisodeLog`)
        and the planner's count now. Refits when the window is full, else returns it as is."""
        steps0, plans0, late0 = self._mark
        steps, plans = len(log.actions) - steps0, len(log.plan_times_s) - plans0
        if steps < self.every_steps or plans < self.min_plans:
            return samples
        n, rec = refit_samples(samples, log.plan_times_s[plans0:], log.late_plans - late0, steps,
                               max_samples=self.max_samples, min_samples=self.min_samples, budget_s=self.budget_s,
                               deadline_s=self.deadline_s, max_late_share=self.max_late_share)
        self._mark = (len(log.actions), len(log.plan_times_s), log.late_plans)
        if n != samples:
            rec["at_step"] = len(log.actions)
            self.refits.append(rec)
        self.samples = n
        return n
