"""Output-error refinement of the `axis` nominal (issue 28, round 5).

A first-order servo logged through 1 cm odometry: the Savitzky-Golay velocity of the quantised
position is noisy, and the equation-error fit's regressor −c·v_k and target (v_{k+1} − v_k)/Δt share
that noise, which biases a and c upwards (+22 %, +25 % on the gauntlet's servo_vehicle seed 2). The
output-error refinement (open-loop windows from the equation-error start) removes the bias, and with
it the gauntlet's one strong false alarm (actuator_lag absorbing the bias)."""

from __future__ import annotations

import pytest

from hilstack.calibration import axis
from hilstack.calibration.synthetic import SynthConfig, generate

TRUTH = {"a": 4.0, "c_per_s": 4.0}


@pytest.fixture(scope="module")
def odometry_preps():
    eps = generate(SynthConfig(n_episodes=8, duration_s=6.0, seed=2, a=4.0, c_per_s=4.0, u_max=2.0,
                               excitation="drive", x_quant=0.01))
    return axis.prepare(eps)


def _rel_err(params):
    return {k: params.coef[k] / v - 1.0 for k, v in TRUTH.items()}


def test_output_error_removes_the_equation_error_bias(odometry_preps, monkeypatch):
    after = _rel_err(axis.fit_axis(odometry_preps, []))
    monkeypatch.setattr(axis, "OUTPUT_ERROR_REFINE", False)
    before = _rel_err(axis.fit_axis(odometry_preps, []))
    assert min(before.values()) > 0.10, before  # the errors-in-variables bias: the servo 10+ % too fast
    assert max(abs(e) for e in after.values()) < 0.05, (before, after)


def test_output_error_keeps_fold_weights(odometry_preps):
    """Bootstrap counts and folds weight the refinement's episodes as they weight the regression: an
    episode of weight 0 does not move the fit."""
    import numpy as np

    w = np.ones(len(odometry_preps))
    w[0] = 0.0
    p_w = axis.fit_axis(odometry_preps, [], weights=w)
    p_drop = axis.fit_axis(odometry_preps[1:], [])
    for k in TRUTH:
        assert p_w.coef[k] == pytest.approx(p_drop.coef[k], rel=1e-6)


def test_servo_vehicle_seed2_clean_is_no_longer_a_false_alarm(tmp_path):
    from hilstack.tools.bench_calibrate import run_case

    row = run_case("servo_vehicle", 2, False, str(tmp_path))
    assert row["outcome"] == "clean", row


def test_an_episode_shorter_than_the_horizon_is_left_out_not_overrun():
    """The windows are replayed stacked with one horizon (1 s): an episode too short to hold it was
    given its own shorter windows and then indexed with the common horizon (IndexError: the gauntlet's
    rest_mixed_rates seeds 6, 9 and 14 crashed). It is left out of the refinement now (the
    equation-error start still sees it)."""
    import numpy as np

    long_eps = generate(SynthConfig(n_episodes=4, duration_s=6.0, seed=3, a=4.0, c_per_s=4.0, u_max=2.0,
                                    excitation="drive", x_quant=0.01))
    short = generate(SynthConfig(n_episodes=1, duration_s=0.7, seed=4, a=4.0, c_per_s=4.0, u_max=2.0,
                                 excitation="drive", x_quant=0.01))
    preps = axis.prepare(long_eps[:2] + short + long_eps[2:])
    assert preps[2].n - 2 * preps[2].margin - 2 < round(axis.OE_HORIZON_S / preps[0].period_s)
    jobs, _ = axis._oe_jobs(preps, axis.fit_axis(preps, [], refine=False), None)
    assert {j["horizon"] for j in jobs} == {round(axis.OE_HORIZON_S / preps[0].period_s)}
    assert all(j["p"] is not preps[2] for j in jobs)
    params = axis.fit_axis(preps, [])  # raised IndexError before
    assert all(np.isfinite(params.coef[k]) for k in TRUTH)
