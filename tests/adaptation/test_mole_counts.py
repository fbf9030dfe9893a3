"""MOLe's CRP counts are the soft counts of the thesis: the sum of every step's posterior."""

from __future__ import annotations

import numpy as np

from hilstack.learning.adaptation.mole import MoleAdapter
from tests.adaptation.test_mole import A, B, _run


def test_counts_are_the_sum_of_the_posteriors_and_follow_the_active_task(meta):
    model, _, psi, _ = meta
    ad = MoleAdapter(model, psi, window=8, lr=0.01, alpha=1.0)
    segs = _run(ad, [A, B], steps=30)
    ups = [u for seg in segs for u in seg]
    n_tasks = len(ad.tasks)
    total = np.zeros(n_tasks)
    for u in ups:
        p = np.asarray(u.info["posterior"])
        total[: len(p)] += p
    np.testing.assert_allclose(ad.counts.numpy(), total, atol=1e-9)
    # the task active through most of a segment gathers most of that segment's count
    task_a, task_b = segs[0][-1].info["task"], segs[1][-1].info["task"]
    assert task_a != task_b
    assert ad.counts[task_a] > 20 and ad.counts[task_b] > 10
    assert abs(float(ad.counts.sum()) - len(ups)) < 1e-9  # one unit of count per step
