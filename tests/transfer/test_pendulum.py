"""InvertedPendulum source/target pair: the heavier pole is in the model, stepping from a state is exact."""

from __future__ import annotations

import numpy as np
import pytest

from learning.transfer.pendulum import StepFrom, make_env


def test_target_has_the_heavier_pole_and_behaves_differently(tmp_path):
    src, tgt = make_env(None, tmp_path), make_env(15.0, tmp_path)
    pole = src.unwrapped.model.body("pole").id
    assert src.unwrapped.model.body_mass[pole] == pytest.approx(5.0186, rel=1e-3)
    assert tgt.unwrapped.model.body_mass[pole] == pytest.approx(15.0)
    s = np.array([0.0, 0.1, 0.0, 0.0])
    a = np.array([1.0])
    d_src, d_tgt = StepFrom(src)(s, a) - s, StepFrom(tgt)(s, a) - s
    assert abs(d_src[3] - d_tgt[3]) > 0.05  # the pole's rate responds differently


def test_step_from_matches_the_env_own_step(tmp_path):
    env = make_env(None, tmp_path)
    obs, _ = env.reset(seed=3)
    nxt, *_ = env.step(np.array([0.7], np.float32))
    np.testing.assert_allclose(StepFrom(make_env(None, tmp_path))(obs.astype(float), np.array([0.7])), nxt,
                               rtol=1e-6, atol=1e-9)


def test_bad_pole_mass_is_refused(tmp_path):
    with pytest.raises(ValueError, match="pole mass"):
        make_env(float("nan"), tmp_path)
