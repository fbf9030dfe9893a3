"""Negative control: nothing hidden, nothing found (and the false-detection rate is low)."""

from __future__ import annotations

import pytest

from hilstack.calibration.models import AxisModel
from hilstack.calibration.selection import SelectionConfig, select_effects
from hilstack.calibration.synthetic import SynthConfig, generate


def test_nothing_found_in_clean_data(report_for):
    r = report_for()
    assert r["verdict"] == "none" and r["effects"] == []
    assert r["unexplained_structure"] is False
    # Before and after are the same model.
    assert r["after"]["multi_step_nrmse"]["mean"] == r["before"]["multi_step_nrmse"]["mean"]
    # A detection limit is reported for the testable effects.
    lim = r["detection_limit"]["per_effect"]
    for name in ("coulomb_friction", "force_offset", "delay", "deadband"):
        assert lim[name]["value"] is not None and lim[name]["value"] > 0


def test_detection_limit_uses_the_acceptance_threshold(report_for):
    """The limit is computed at the level an effect must reach to enter the model: "moderate" (a 95 %
    interval excluding no effect), with 80 % power (issue 28: no correction towards zero)."""
    from scipy.stats import norm

    r = report_for()
    assert r["detection_limit"]["z"] == pytest.approx(norm.ppf(0.975) + norm.ppf(0.8))
    assert r["data"]["resolution"]["can_accept"] is True


def test_detection_limit_is_meaningful(report_for):
    """An offset well above the reported limit is found (the limit is not vacuous)."""
    lim = report_for()["detection_limit"]["per_effect"]["force_offset"]["value"]
    assert lim < 1.0  # the offset hidden in test_single_effect_recovered is 1.0 m/s² and is found


def test_false_detection_rate_over_seeds():
    """30 seeds of clean data with a cheap configuration: at most 1 false detection (≈ < 5 %), and at
    most 1 run in which any candidate reaches "strong" evidence (issue 28's goal: ≤ 5 % at strong).
    Measured with the current rule: 0 of 30 at strong or moderate (docs/calibration.md)."""
    cfg = SelectionConfig(n_boot=15, max_rounds=1, horizon_s=0.5)
    model = AxisModel()
    detections, strong = [], []
    for seed in range(30):
        eps = generate(SynthConfig(n_episodes=12, duration_s=3.0, seed=100 + seed))
        res = select_effects(model, model.prepare(eps), cfg, seed=seed)
        if res.accepted:
            detections.append((seed, [a.name for a in res.accepted]))
        levels = [c["evidence"]["level"] for c in res.rounds[0]["candidates"]]
        if "strong" in levels:
            strong.append(seed)
    assert len(detections) <= 1, detections
    assert len(strong) <= 1, strong
