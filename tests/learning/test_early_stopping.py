"""The one early-stopping helper (learning/early_stopping.py): patience, best-state restore, cadence."""

from __future__ import annotations

import math

import pytest
import torch

from hilstack.learning.early_stopping import EarlyStopping, due


def _losses_run(losses, **kw):
    """Feed ``losses`` to a helper watching one linear layer whose weight is set to the
    evaluation's number before each update; returns (helper, evaluations run, weight after restore)."""
    net = torch.nn.Linear(1, 1, bias=False)
    psi = {"p": torch.zeros(2)}
    es = EarlyStopping(net, psi, **kw)
    run = 0
    for i, v in enumerate(losses, start=1):
        with torch.no_grad():
            net.weight.fill_(i)
            psi["p"].fill_(-i)
        run = i
        if es.update(v):
            break
    es.restore()
    return es, run, net.weight.item(), psi["p"][0].item()


def test_stops_after_patience_evaluations_without_a_new_best_and_restores_the_best():
    es, run, w, p = _losses_run([5.0, 3.0, 4.0, 3.5, 3.2, 1.0], patience=3)
    assert run == 5  # evaluations 3, 4, 5 did not beat evaluation 2
    assert (es.best_index, es.best, es.stale) == (2, 3.0, 3)
    assert (w, p) == (2.0, -2.0)  # module and tensor mapping both back to evaluation 2


def test_no_patience_keeps_the_best_and_never_stops():
    es, run, w, _ = _losses_run([5.0, 3.0, 4.0, 3.5, 3.2, 2.5, 9.0], patience=None)
    assert run == 7 and es.best_index == 6 and w == 6.0


def test_min_delta_counts_a_tiny_gain_as_no_gain():
    es, run, w, _ = _losses_run([1.0, 1.0 - 1e-9, 1.0 - 2e-9], patience=2, min_delta=1e-6)
    assert run == 3 and es.best_index == 1 and w == 1.0


def test_keep_initial_restores_the_start_when_nothing_improves():
    net = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        net.weight.fill_(7.0)
    es = EarlyStopping(net, patience=2, keep_initial=True)
    with torch.no_grad():
        net.weight.fill_(1.0)
    assert not es.update(math.nan) and es.update(math.nan)  # NaN is never a best
    assert es.restore() and net.weight.item() == 7.0
    assert not EarlyStopping(net, patience=2).restore()  # nothing kept, nothing written


def test_restore_writes_into_the_same_tensors_an_optimizer_holds():
    net = torch.nn.Linear(2, 1)
    params = dict(net.named_parameters())
    ids = {k: id(v) for k, v in params.items()}
    es = EarlyStopping(params, patience=1)
    es.update(1.0)
    with torch.no_grad():
        net.weight.add_(1.0)
    es.restore()
    assert {k: id(v) for k, v in net.named_parameters()} == ids
    assert torch.equal(net.weight, params["weight"])


def test_cadence_and_bad_settings():
    assert [s for s in range(25) if due(s, 25, 10)] == [9, 19, 24]
    with pytest.raises(ValueError, match="patience"):
        EarlyStopping(torch.nn.Linear(1, 1), patience=0)
    with pytest.raises(ValueError, match="min_delta"):
        EarlyStopping(torch.nn.Linear(1, 1), min_delta=-1.0)
    with pytest.raises(ValueError, match="at least one"):
        EarlyStopping(patience=1)
