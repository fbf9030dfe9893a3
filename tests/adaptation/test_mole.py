"""MOLe: CRP posterior math, new tasks on new conditions, recall of old ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hilstack.learning.adaptation import load_adapter
from hilstack.learning.adaptation.grbal import GrbalAdapter
from hilstack.learning.adaptation.mole import MoleAdapter, crp_log_prior, task_posterior
from tests.adaptation import toy

A, B = (1.0, 0.0), (0.3, 1.5)  # normal; slow and turning (outside the meta-training range)


def test_crp_prior_and_posterior_by_hand():
    counts = torch.tensor([3.0, 1.0])
    np.testing.assert_allclose(crp_log_prior(counts, 1.0).exp().numpy(), [3 / 5, 1 / 5, 1 / 5])
    np.testing.assert_allclose(crp_log_prior(torch.zeros(0), 1.0).exp().numpy(), [1.0])
    post = task_posterior(torch.tensor([0.0, math.log(2), math.log(4)]), counts, 1.0)
    np.testing.assert_allclose(post.numpy(), [1 / 3, 2 / 9, 4 / 9], atol=1e-12)


def _run(ad: MoleAdapter, conds, steps=40, seed=0):
    rng = np.random.default_rng(seed)
    s = toy.episodes(1, 1, seed=0)[0].states[0]
    out = []
    for g, b in conds:
        seg = []
        for _ in range(steps):
            a = rng.uniform(-1, 1, 2).astype(np.float32)
            n = toy.step(s, a, g, b)
            ad.observe(s, a, n)
            s = n
            seg.append(ad.update())
        out.append(seg)
    return out


def test_new_task_on_a_new_condition_and_recall_on_switching_back(meta):
    model, _, psi, _ = meta
    ad = MoleAdapter(model, psi, window=8, lr=0.01, alpha=1.0)
    segs = _run(ad, [A, B, A, B])
    created = [s[-1].info["tasks_created"] for s in segs]
    assert created[0] == 1                      # one condition, one task
    assert created[1] > created[0]              # a genuinely new condition: a new task
    assert created[3] == created[2] == created[1]  # switching back creates nothing...
    task_a, task_b = segs[0][-1].info["task"], segs[1][-1].info["task"]
    assert task_a != task_b
    assert segs[2][-1].info["task"] == task_a   # ...it recalls the old tasks
    assert segs[3][-1].info["task"] == task_b
    for u in segs[3]:
        p = u.info["posterior"]
        assert len(p) == u.info["tasks_created"] and abs(sum(p) - 1) < 1e-9
        assert u.info["task"] == int(np.argmax(p))
    # the published parameters are the active task's
    for k, v in ad.tasks[task_b].items():
        np.testing.assert_array_equal(segs[3][-1].tensors[k], v.numpy())


def test_builds_from_a_grbal_checkpoint_and_refuses_a_plain_one(meta, tmp_path):
    model, _, psi, _ = meta
    GrbalAdapter(model, psi, window=8).save(tmp_path / "g.pt")
    ad = load_adapter(tmp_path / "g.pt", method="mole")
    assert isinstance(ad, MoleAdapter) and ad.window == 8 and ad.score == 4
    ad.save(tmp_path / "m.pt")
    assert isinstance(load_adapter(tmp_path / "m.pt"), MoleAdapter)
    from hilstack.learning.adaptation.baselines import MbAdapter
    MbAdapter(model, window=8).save(tmp_path / "mb.pt")
    with pytest.raises(ValueError, match="no step size psi"):
        load_adapter(tmp_path / "mb.pt", method="mole")
    ad.reset()
    assert ad.update().info == {"window": 0, "posterior": [], "task": -1, "tasks_created": 0}
