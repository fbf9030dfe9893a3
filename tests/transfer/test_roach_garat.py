"""VelociRoACH GAT/GARAT part: features, the source/target pair, CEM, normalisation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers.velociroach.config import STATE_NAMES
from hilstack.learning.transfer.roach_garat import (
    RoachGaratConfig,
    RoachStep,
    cem,
    episode_return,
    features,
    normalise,
    summarise,
)

IDX = {n: i for i, n in enumerate(STATE_NAMES)}


def _state(yaw: float, v_fwd: float, v_lat: float, crank_l: float, crank_r: float) -> np.ndarray:
    s = np.zeros(len(STATE_NAMES))
    s[IDX["cos_yaw"]], s[IDX["sin_yaw"]] = math.cos(yaw), math.sin(yaw)
    c, si = math.cos(yaw), math.sin(yaw)
    s[IDX["vx"]], s[IDX["vy"]] = c * v_fwd - si * v_lat, si * v_fwd + c * v_lat
    s[IDX["wz"]] = 0.3
    s[IDX["cos_crank_l"]], s[IDX["sin_crank_l"]] = math.cos(crank_l), math.sin(crank_l)
    s[IDX["cos_crank_r"]], s[IDX["sin_crank_r"]] = math.cos(crank_r), math.sin(crank_r)
    s[IDX["crank_vel_l"]], s[IDX["crank_vel_r"]] = 10.0, 9.0
    return s


def test_features_are_body_frame_and_heading_invariant():
    f0 = features(_state(0.0, 0.8, -0.1, 1.0, 1.0 + math.pi))
    f1 = features(_state(2.5, 0.8, -0.1, 1.0, 1.0 + math.pi))
    np.testing.assert_allclose(f0, f1, atol=1e-12)
    np.testing.assert_allclose(f0, [0.8, -0.1, 0.3, 10.0, 9.0, -1.0, 0.0], atol=1e-12)  # anti-phase tripod


def test_missing_leg_target_curves_where_the_source_runs_straighter():
    cfg = RoachGaratConfig(episode_steps=15)
    lat = {}
    for name, leg in (("source", None), ("target", "lm")):
        step = RoachStep(leg, seed=0)
        episode_return(step, np.array([11.0, 11.0]), cfg, np.random.default_rng(0))
        lat[name] = step.progress()[1]
        step.close()
    # equal commands: the target (left middle leg missing) veers left by far more
    assert lat["target"] > 0.2 and lat["target"] > abs(lat["source"]) + 0.15


def test_leg_speed_target_turns_left_and_slows_the_left_cranks():
    cfg = RoachGaratConfig(episode_steps=10)
    assert cfg.leg_speed_scale == (0.6, 1.0) and cfg.missing_leg is None  # the default target
    out = {}
    for name, scale in (("source", None), ("target", (0.6, 1.0))):
        step = RoachStep(None, seed=0, leg_speed_scale=scale)
        rng = np.random.default_rng(0)
        s = step.reset_state(rng)
        for _ in range(cfg.episode_steps):
            s = step(s, np.array([10.0, 10.0]))
        out[name] = (s, step.progress()[1])
        step.close()
    # the left cranks run at 60 % of the command in the target, as commanded in the source
    assert out["target"][0][3] == pytest.approx(6.0, abs=1.0) and out["source"][0][3] == pytest.approx(10.0, abs=1.0)
    assert out["target"][1] > out["source"][1] + 0.1  # veers left
    with pytest.raises(ConfigError, match="leg_speed_scale"):
        RoachStep(None, leg_speed_scale=(0.0, 1.0))


def test_bad_missing_leg_is_refused():
    with pytest.raises(ValueError, match="missing_leg"):
        RoachStep("left_middle")


class _Quadratic:
    """A fake stateful step whose episode return peaks at θ* = (12, 8)."""

    def reset_state(self, rng):
        self.a = None
        return np.zeros(7)

    def __call__(self, s, a):
        self.a = np.asarray(a, float)
        return s

    def progress(self):
        return float(-np.sum((self.a - [12.0, 8.0]) ** 2)), 0.0


def test_cem_finds_the_best_gait_and_uses_the_transform():
    cfg = RoachGaratConfig(episode_steps=2, cem_iterations=10, cem_init_std_rps=(3.0, 3.0))
    np.testing.assert_allclose(cem(_Quadratic(), cfg, seed=0), [12.0, 8.0], atol=0.5)
    # through a transform that adds 2 rev/s on the left, the best command is 2 lower there
    np.testing.assert_allclose(cem(_Quadratic(), cfg, seed=0, transform=lambda s, a: a + [2.0, 0.0]),
                               [10.0, 8.0], atol=0.5)


def test_normalisation_source_zero_target_one_failure_negative():
    n = normalise({"source": -1.0, "target": 1.0, "gat": -2.0, "garat": 0.5})
    assert n == {"source": 0.0, "gat": -0.5, "garat": 0.75}
    assert normalise({"source": 1.0, "target": 0.9, "gat": 2.0, "garat": 2.0})["garat"] is None  # no gap
    rows = [{"seed": 1, "normalised_return": {"source": 0.0, "gat": 0.2, "garat": 0.6}},
            {"seed": 2, "normalised_return": {"source": 0.0, "gat": 0.4, "garat": 1.0}},
            {"seed": 3, "normalised_return": {"source": None, "gat": None, "garat": None}}]
    s = summarise(rows)
    assert s["seeds_with_gap"] == [1, 2]
    assert s["normalised_return"]["garat"] == pytest.approx(0.8)
    assert s["normalised_return_std"]["gat"] == pytest.approx(0.1)
