"""Load-side backlash (play between motor and measured position) and position-periodic loads (cogging)."""

from __future__ import annotations

import pytest

from hilstack.calibration import axis, run_calibration
from hilstack.calibration.selection import LOSS_CHANNELS
from hilstack.calibration.synthetic import SynthConfig, generate
from tests.calibration.conftest import FAST


def _run(tmp_path, effects: dict, seed: int, **cfg):
    eps = generate(SynthConfig(n_episodes=16, duration_s=6.0, seed=seed, effects=effects, **cfg))
    return run_calibration(eps, out_dir=tmp_path / "out", seed=seed, progress=False, plots=False, config=FAST)


def test_load_backlash_is_found_in_the_multistep_position_error(tmp_path):
    """Play of 1 cm before a 1 mm load encoder: invisible one step ahead (the load stands still in the
    gap, and standstill rows are not regression rows), it shows as a position step at every motion
    reversal in the open-loop windows. Named, its width recovered, the locked-test error falls."""
    r = _run(tmp_path, {"load_backlash": {"halfwidth_x": 0.01}}, seed=1, x_quant=1e-3)
    assert r["verdict"] == "found"
    names = [e["name"] for e in r["effects"]]
    assert names == ["load_backlash"], names
    eff = r["effects"][0]
    assert eff["params"]["halfwidth_x"] == pytest.approx(0.01, rel=0.25)
    assert eff["interval"][0] > 0
    # The evidence is in the open-loop (multi-step) channels, the one-step channels cannot see it.
    cand = next(c for c in r["rounds"][0]["candidates"] if c["name"] == "load_backlash")
    gain = dict(zip(LOSS_CHANNELS, cand["channel_gain"], strict=True))
    assert gain["multi_step_x"] > 0.1 and abs(gain["one_step_x"]) < 0.02
    # Locked-test open-loop x error, measured: 0.00686 -> 0.00552 (x0.80). Before the output-error
    # refinement (round 5) it was 0.0141 -> 0.0065 (x0.46, this bound was 0.8): the refined nominal
    # without play is half as wrong in open loop (it takes part of the play's lag into a and c), so the
    # play's share of what is left is smaller; the play's model itself improved (0.0065 -> 0.0055).
    assert r["after"]["multi_step_nrmse"]["per_channel"]["x"] < 0.9 * r["before"]["multi_step_nrmse"]["per_channel"]["x"]


def test_load_backlash_replay_holds_the_load_in_the_gap():
    """A motor reversing at constant speed: the replayed load stops for 2h/|v| and lags by 2h after."""
    eps = generate(SynthConfig(n_episodes=1, duration_s=3.0, seed=0, x_noise_m=0.0, excitation="sine",
                               effects={"load_backlash": {"halfwidth_x": 0.02}}))
    p = axis.prepare(eps)[0]
    params = axis.fit_axis([p], ["load_backlash"])
    assert params.hyper["halfwidth_x"] == pytest.approx(0.02, rel=0.15)
    with_play = axis.simulate_windows(p, params, 150)
    params.hyper["halfwidth_x"] = 0.0
    without = axis.simulate_windows(p, params, 150)
    err = [float(((s["x_pred"] - s["x_true"]) ** 2).sum()) for s in (with_play, without)]
    assert err[0] < 0.3 * err[1]


def test_cogging_is_named_with_its_period_and_not_taken_for_gravity_or_friction(tmp_path):
    """A rotary joint with 6 detents per revolution, phase near the ±π/2 edge of its representation:
    cogging is named (not gravity, not Coulomb), n = k recovered, the interval excludes zero."""
    cog = {"gc_acc": 2.0, "k_rad_per_x": 6.0, "phase_rad": 1.5}
    r = _run(tmp_path, {"cogging": cog}, seed=2, x_quant=5e-4, u_max=2.0)
    assert r["verdict"] == "found"
    assert [e["name"] for e in r["effects"]] == ["cogging"]
    got = r["effects"][0]["params"]
    assert got["k_rad_per_x"] == pytest.approx(6.0, rel=0.02)
    assert got["gc_acc"] == pytest.approx(2.0, rel=0.1)
    assert r["effects"][0]["interval"][0] > 0
    assert not r["unexplained_structure"]


def test_gravity_load_is_not_taken_for_cogging(tmp_path):
    """One period per revolution is gravity: named as such; cogging (at least two periods over the
    stroke) is not accepted, or the report marks the two ambiguous."""
    r = _run(tmp_path, {"gravity_load": {"gl_acc": 4.0, "q0_rad": 0.0}}, seed=0, x_quant=5e-4, u_max=2.0)
    names = [e["name"] for e in r["effects"]]
    assert names[0] == "gravity_load"
    assert "cogging" not in names or any(set(a["effects"]) == {"cogging", "gravity_load"} for a in r["ambiguous"])


def test_periodic_load_bootstrap_value_does_not_flip_sign_at_the_phase_edge():
    """−A·sin(kx − φ) and A·sin(kx − φ + π) are the same load: measured along the reference phase
    they give the same primary value (a sign flip would put zero inside the bootstrap interval)."""
    ref = axis.AxisParams(effects=["cogging"], coef={"gc_acc": 2.0}, hyper={"cog_k": 6.0, "cog_phase": 1.55})
    flipped = axis.AxisParams(effects=["cogging"], coef={"gc_acc": -2.0}, hyper={"cog_k": 6.0, "cog_phase": 1.55 - 3.14159})
    assert flipped.primary("cogging") < 0 < ref.primary("cogging")
    assert flipped.primary_along("cogging", ref) == pytest.approx(2.0, rel=1e-4)
    assert ref.primary_along("cogging", ref) == pytest.approx(2.0)


def test_cogging_look_alikes_name_the_separating_excitation():
    from hilstack.calibration.effects import is_look_alike, separating_excitation

    for other in ("gravity_load", "coulomb_friction", "force_offset"):
        assert is_look_alike("cogging", other)
    assert "revolution" in separating_excitation("cogging", "gravity_load")
    assert "both directions" in separating_excitation("cogging", "coulomb_friction")
