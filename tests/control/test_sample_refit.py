"""The planner's sample count refitted within one realtime episode (SampleRefit), from
measured plan times given as inputs (no wall clock)."""

from __future__ import annotations

import pytest

from hilstack.control.controller_node import EpisodeLog
from hilstack.control.planners import CEM
from hilstack.control.sample_refit import SampleRefit

KW = dict(max_samples=500, min_samples=50, budget_s=0.04, deadline_s=0.08, max_late_share=0.05)


def _run(refit: SampleRefit, load_of_step, steps: int, n0: int = 500, per_sample_s=1e-4, plans_every=1):
    """Drive ``refit`` as the controller node does: before each plan it asks for the count; a
    plan takes ``load`` x samples x per_sample_s (late when over the 80 ms deadline)."""
    log, n, seen = EpisodeLog(), n0, []
    refit.start(n)
    for i in range(steps):
        n = refit.update(log, n)
        seen.append(n)
        log.actions.append(0.0)
        if i % plans_every == 0:
            t = load_of_step(i) * n * per_sample_s
            log.plan_times_s.append(t)
            log.late_plans += int(t > 0.08)
    return seen, log


def test_the_count_follows_the_load_within_one_long_episode():
    """Quiet (20 ms at 500: within budget) for 100 steps, then 4x the load (80 ms at 500:
    over the budget) for 200 steps, then quiet again: kept, cut, grown back, within bounds,
    and only at window ends (every 50 commands)."""
    refit = SampleRefit(**KW, every_steps=50)
    seen, _ = _run(refit, lambda i: 0.4 if i < 100 or i >= 300 else 1.6, 500)
    assert seen[:101] == [500] * 101  # quiet: nothing to cut (growth is capped at the configured count)
    loaded = seen[150:300]
    assert max(loaded) <= 250 and min(loaded) >= 50  # cut to the budget: 40 ms / (1.6 x 0.1 ms) = 250
    assert seen[-1] > max(loaded)  # the load fell: grown back
    changes = [i for i in range(1, len(seen)) if seen[i] != seen[i - 1]]
    assert changes and all(c % 50 == 0 for c in changes)
    assert [r["at_step"] for r in refit.refits] == changes and refit.samples == seen[-1]
    assert all(50 <= r["to"] <= 500 for r in refit.refits) and refit.refits[0]["from"] == 500


def test_a_planner_slower_than_the_window_widens_it_instead_of_refitting_from_nothing():
    """A plan back every 20th command only: the window waits for min_plans (5) plans."""
    refit = SampleRefit(**KW, every_steps=10, min_plans=5)
    seen, log = _run(refit, lambda i: 4.0, 120, plans_every=20)  # 200 ms plans at 500 samples
    first = next(i for i in range(len(seen)) if seen[i] != 500)
    assert first == 81  # plans at steps 0, 20, ..., 80: the fifth comes back at step 80
    assert refit.refits[0]["plans"] == 5 and refit.refits[0]["to"] < 500


def test_a_window_with_late_plans_cuts_even_when_the_times_look_fine():
    refit = SampleRefit(**KW, every_steps=20)
    log = EpisodeLog(actions=[0.0] * 20, plan_times_s=[0.01] * 20, late_plans=5)  # 25 % late
    refit.start(400)
    assert refit.update(log, 400) == 300 and refit.refits[-1]["late_share"] == 0.25
    log.actions += [0.0] * 19
    assert refit.update(log, 300) == 300  # the window restarted: 19 commands are not yet one


def test_bad_refit_settings_are_refused_naming_them():
    with pytest.raises(ValueError, match="every_steps"):
        SampleRefit(**KW, every_steps=0)
    with pytest.raises(ValueError, match="budget_s"):
        SampleRefit(**{**KW, "budget_s": 0.1})  # over the deadline


def test_cem_keeps_its_elite_share_when_resized():
    cem = CEM(horizon=3, samples=500, elites=50, action_dim=2)
    cem.set_samples(120)
    assert cem.samples == 120 and cem.elites == 12
    cem.set_samples(500)
    assert cem.elites == 50
    cem.set_samples(3)
    assert 1 <= cem.elites <= 3
    with pytest.raises(ValueError, match="samples"):
        cem.set_samples(0)
