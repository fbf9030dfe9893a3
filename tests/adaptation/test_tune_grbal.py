"""GrBAL's cap quantile and θ's meta learning rate chosen on training conditions only (issue 24).

* the tuning refuses any rollout of a test condition or of the held-out terrain, so the
  choice cannot see one; training-range rollouts pass;
* the choice is the grid point with the lowest online error, each point meta-trained for real,
  and a choice on a grid's edge is flagged, as ``tune_rates`` flags a step size.
"""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.learning.adaptation import experiment as ex
from hilstack.learning.adaptation.experiment import AdaptationConfig
from hilstack.learning.adaptation.tune_grbal import check_training_only, grid_points, tune_grbal
from hilstack.tasks.perturbations import PerturbationSettings, load_presets
from tests.adaptation import toy

P = load_presets("velociroach")
CFG = AdaptationConfig.from_preset("tiny", rate_grid=(0.0, 1.0), tune_rollouts=2, val_fraction=0.2,
                                   meta_steps=4, meta_eval_every=2)


def _training_rollouts(n: int = 10) -> list:
    """Toy rollouts named and labelled as the demo's training data: terrain-c<i>#0, unperturbed or in range."""
    rng = np.random.default_rng(0)
    eps = []
    for i in range(n):
        (e,) = toy.episodes(1, 16, seed=i, gain=rng.uniform(0.6, 1.4), turn_bias=rng.uniform(-0.5, 0.5))
        terrain = P.training_terrains[i % len(P.training_terrains)]
        cond = (PerturbationSettings() if i % 2 == 0 else
                PerturbationSettings(missing_leg=["lf"], slope_deg=3.0, payload_kg=0.01, heading_offset_deg=-9.0))
        e.name = f"{terrain}-c{i}#0"
        e.meta = {"condition": {**cond.model_dump(), "leg_speed_scale": [0.8, 1.2]}}
        eps.append(e)
    return eps


@pytest.mark.parametrize("poison, says", [(name, "not a training condition") for name in P.tests] + [
    ("heldout_terrain", "not a training terrain")])
def test_the_tuning_refuses_a_rollout_of_a_test_condition(poison, says):
    eps = _training_rollouts()
    check_training_only(eps, P)  # the training range passes
    bad = eps[3]
    if poison == "heldout_terrain":
        bad.name = f"terrain_{P.heldout_terrain}#0"
        bad.meta = {"condition": PerturbationSettings().model_dump()}
    else:
        bad.meta = {"condition": P.tests[poison].model_dump()}
    with pytest.raises(ValueError, match=says) as e:
        tune_grbal(CFG, eps, toy.NAMES, 0, P, quantiles=(0.5,), meta_lrs=(1e-3,), log=lambda _: None)
    assert bad.name in str(e.value) and "\n" not in str(e.value)


def test_the_choice_is_the_lowest_online_error_of_the_grid_each_point_meta_trained():
    """Real meta-training per grid point on the toy: the chosen point has the lowest error
    reported, the cap differs per quantile (none for None) and the held-out rollouts are the
    demo's split (training conditions)."""
    eps = _training_rollouts()
    logs = []
    r = tune_grbal(CFG, eps, toy.NAMES, 0, P, quantiles=(0.25, None), meta_lrs=(1e-4, 1e-2), log=logs.append)
    assert [(g["clip_quantile"], g["meta_lr"]) for g in r["grid"]] == [(0.25, 1e-4), (0.25, 1e-2),
                                                                      (None, 1e-4), (None, 1e-2)]
    best = min(r["grid"], key=lambda g: g["error"])
    assert r["choice"] == {"clip_quantile": best["clip_quantile"], "meta_lr": best["meta_lr"]}
    for g in r["grid"]:
        assert set(g["errors"]) == {0.0, 1.0} and g["error"] == min(g["errors"].values())
        assert (g["clip"] is None) == (g["clip_quantile"] is None)
    # θ's rate changes θ*: the two rates give different errors at x1
    assert r["grid"][0]["error_x1"] != r["grid"][1]["error_x1"]
    assert len(r["held_out_rollouts"]) == 2 and all("-c" in n for n in r["held_out_rollouts"])
    assert r["current"] == {"clip_quantile": CFG.grbal_clip_quantile, "meta_lr": CFG.meta_lr}


Q, LR = (0.25, 0.5, None), (1e-4, 3e-4, 1e-3)


@pytest.mark.parametrize("low, choice, edges, says", [
    ({(0.5, 3e-4): 0.20}, (0.5, 3e-4), (None, None), []),
    ({(0.5, 3e-4): 0.20, (0.25, 1e-4): 0.10}, (0.25, 1e-4), ("lower", "lower"),
     ["0.25 is the grid's lower edge", "0.0001 is the grid's lower edge", "below"]),
    ({(0.5, 3e-4): 0.20, (None, 1e-3): 0.10}, (None, 1e-3), ("upper", "upper"),
     ["no cap chosen", "0.001 is the grid's upper edge", "above"]),
])
def test_a_choice_on_the_grids_edge_is_flagged(monkeypatch, low, choice, edges, says):
    """The criterion replaced by a fixed error per grid point (0.3 and up, ``low`` where given);
    each point is still meta-trained (one step)."""
    cfg = AdaptationConfig.from_preset("tiny", rate_grid=(1.0,), tune_rollouts=1, val_fraction=0.2, meta_steps=1)
    current = {"clip_quantile": cfg.grbal_clip_quantile, "meta_lr": cfg.meta_lr}
    order = grid_points(Q, LR, current)
    assert sorted(order, key=str) == sorted([(q, lr) for q in Q for lr in LR], key=str)  # every point once
    assert order[0] == (0.5, 1e-3)  # the presets' point first
    errors = [low.get(p, 0.3 + 0.01 * i) for i, p in enumerate(order)]
    calls = iter(errors)
    monkeypatch.setattr(ex, "online_error", lambda *a, **k: next(calls))
    r = tune_grbal(cfg, _training_rollouts(), toy.NAMES, 0, P, quantiles=Q, meta_lrs=LR, log=lambda _: None)
    assert [(g["clip_quantile"], g["meta_lr"]) for g in r["grid"]] == order
    assert (r["choice"]["clip_quantile"], r["choice"]["meta_lr"]) == choice
    assert (r["edge"]["clip_quantile"], r["edge"]["meta_lr"]) == edges
    text = " ".join(r["warnings"])
    assert bool(r["warnings"]) == bool(says) and all(s in text for s in says)
    assert r["spread"] == pytest.approx((max(errors) - min(errors)) / min(errors))


def _seed_result(seed: int, errors: dict) -> dict:
    return {"seed": seed, "current": {"clip_quantile": 0.5, "meta_lr": 1e-4},
            "grid": [{"clip_quantile": q, "meta_lr": lr, "error": e, "rate": 0.25} for (q, lr), e in errors.items()]}


@pytest.mark.parametrize("other, verdict", [
    ((0.20, 0.21, 0.22), "adopt cap quantile None, θ lr 0.001"),   # below the presets on every seed
    ((0.10, 0.35, 0.22), "flat"),                                  # a lower mean, but not on every seed
    ((0.30, 0.31, 0.32), "keep it"),                               # the presets have the lowest mean
])
def test_the_summary_adopts_a_point_only_if_it_is_below_the_presets_on_every_seed(other, verdict):
    from hilstack.learning.adaptation.tune_grbal import summarize

    cur = (0.25, 0.26, 0.27)
    results = [_seed_result(s, {(0.5, 1e-4): cur[s], (None, 1e-3): other[s]}) for s in range(3)]
    text = summarize(results)
    assert verdict in text.splitlines()[-1]
    assert "| 0.5 (presets) | 0.0001 | 0.2500 (x0.25)" in text
