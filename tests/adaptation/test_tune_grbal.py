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
from hilstack.learning.adaptation.tune_grbal import check_training_only, tune_grbal
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


@pytest.mark.parametrize("errors, choice, edges, says", [
    ((0.30, 0.31, 0.32, 0.33, 0.20, 0.34, 0.35, 0.36, 0.37), (0.5, 3e-4), (None, None), []),
    ((0.10, 0.31, 0.32, 0.33, 0.20, 0.34, 0.35, 0.36, 0.37), (0.25, 1e-4), ("lower", "lower"),
     ["0.25 is the grid's lower edge", "0.0001 is the grid's lower edge", "below"]),
    ((0.30, 0.31, 0.32, 0.33, 0.20, 0.34, 0.35, 0.36, 0.10), (None, 1e-3), ("upper", "upper"),
     ["no cap chosen", "0.001 is the grid's upper edge", "above"]),
])
def test_a_choice_on_the_grids_edge_is_flagged(monkeypatch, errors, choice, edges, says):
    """The criterion replaced by a fixed error per grid point (in grid order: quantile, then rate);
    each point is still meta-trained (one step)."""
    calls = iter(errors)
    monkeypatch.setattr(ex, "online_error", lambda *a, **k: next(calls))
    cfg = AdaptationConfig.from_preset("tiny", rate_grid=(1.0,), tune_rollouts=1, val_fraction=0.2, meta_steps=1)
    r = tune_grbal(cfg, _training_rollouts(), toy.NAMES, 0, P, quantiles=(0.25, 0.5, None),
                   meta_lrs=(1e-4, 3e-4, 1e-3), log=lambda _: None)
    assert (r["choice"]["clip_quantile"], r["choice"]["meta_lr"]) == choice
    assert (r["edge"]["clip_quantile"], r["edge"]["meta_lr"]) == edges
    text = " ".join(r["warnings"])
    assert bool(r["warnings"]) == bool(says) and all(s in text for s in says)
    assert r["spread"] == pytest.approx((max(errors) - min(errors)) / min(errors))
