"""The fit caches per-episode regression statistics: repeated fits reuse them and match a fresh fit."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.calibration import axis
from hilstack.calibration.synthetic import SynthConfig, generate


def _preps():
    return axis.prepare(generate(SynthConfig(n_episodes=4, duration_s=3.0, seed=3, effects={"deadband": {}})))


def test_repeated_fit_reuses_episode_statistics(monkeypatch):
    preps = _preps()
    first = axis.fit_axis(preps, ["deadband"], refine=False)
    calls = []
    real_design = axis.design
    monkeypatch.setattr(axis, "design", lambda p, params: calls.append(1) or real_design(p, params))
    # The same fit again: no new design matrix at all.
    axis.fit_axis(preps, ["deadband"], refine=False)
    assert calls == []
    # A bootstrap replicate (other weights): the grid is reused; only its refined (off-grid) point is new.
    axis.fit_axis(preps, ["deadband"], weights=np.array([2.0, 0.0, 1.0, 1.0]), refine=False)
    assert len(calls) <= len(preps)
    # The cached statistics give the same fit as fresh episodes without a cache.
    fresh = axis.fit_axis(_preps(), ["deadband"], refine=False)
    assert first.hyper == fresh.hyper
    assert first.coef == fresh.coef


def test_cache_is_keyed_on_what_the_design_reads():
    preps = _preps()
    params = axis.fit_axis(preps, ["deadband"], refine=False)
    s1 = axis.episode_stats(preps[:1], params)[0]
    params.hyper["width_u"] = params.hyper["width_u"] + 0.1
    s2 = axis.episode_stats(preps[:1], params)[0]
    assert not np.allclose(s1.xty, s2.xty)


def test_exact_signed_rank_matches_scipy_without_its_permutation_test(monkeypatch):
    """Small held-out sets with zeros or ties: the enumerated exact p equals scipy's permutation p."""
    from scipy import stats as st

    from hilstack.calibration import selection

    rng = np.random.default_rng(5)
    cases = []
    for n in (6, 9, 13):
        for _ in range(3):
            d = rng.normal(0.4, 1.0, n)
            d[rng.integers(0, n, 2)] = 0.0
            d[1] = -d[2]  # a tie in |d|
            cases.append(d)
    expected = [st.wilcoxon(d, alternative="greater", zero_method="zsplit").pvalue for d in cases]

    def no_permutation(*a, **k):
        raise AssertionError("scipy permutation test called")

    monkeypatch.setattr(st, "permutation_test", no_permutation)
    for d, want in zip(cases, expected, strict=True):
        base = np.abs(d) + 1.0
        assert selection.paired_p(base, base - d) == pytest.approx(want, abs=1e-12)


def test_batched_replay_equals_one_replay_per_episode():
    """Open-loop windows of many (episode, parameters) pairs replayed in one batch are exactly the
    per-episode replays: each window keeps its own coefficients (friction, gravity, cogging, play)."""
    preps = axis.prepare(generate(SynthConfig(n_episodes=3, duration_s=2.0, seed=4,
                                              effects={"coulomb_friction": {}})))
    plain = axis.fit_axis(preps, [], refine=False)
    fric = axis.fit_axis(preps, ["coulomb_friction"], refine=False)
    rich = axis.fit_axis(preps, ["coulomb_friction"], refine=False)
    rich.effects = rich.effects + ["stribeck_friction", "gravity_load", "cogging", "load_backlash", "back_emf"]
    rich.coef.update(fs_extra_acc=0.7, gl_acc=1.5, gc_acc=0.4, fa_acc=0.3, kemf=0.5)
    rich.hyper.update(vs=0.05, q0_rad=0.2, cog_k=5.0, cog_phase=0.3, halfwidth_x=0.004)
    jobs = [(p, prm, None, None) for prm in (plain, fric, rich) for p in preps]
    jobs.append((preps[1], plain, np.array([preps[1].margin, preps[1].margin + 7]), np.array([0.0, 0.01])))
    batched = axis.simulate_many(jobs, 60)
    for (p, prm, starts, play), b in zip(jobs, batched, strict=True):
        one = axis.simulate_many([(p, prm, starts, play)], 60)[0]
        for key in ("x_pred", "v_pred", "x_true", "k"):
            np.testing.assert_array_equal(b[key], one[key])
    # the mix matters: the rich parameters move the replay, so a batch that shared one window's
    # coefficients with the others would fail above
    assert not np.allclose(batched[0]["x_pred"], batched[2 * len(preps)]["x_pred"])


def test_bench_speed_mode_runs_batched_and_peer_with_identical_reports(tmp_path, monkeypatch):
    """`hil bench calibrate --speed`: both runs happen, their reports agree, the peer really replays
    one episode at a time (no timing is asserted)."""
    from hilstack.calibration.synthetic import write_csv
    from hilstack.tools import bench_calibrate as bc

    def small(out):
        out.mkdir(parents=True, exist_ok=True)
        eps = generate(SynthConfig(n_episodes=6, duration_s=2.0, seed=2, effects={"coulomb_friction": {}}))
        return write_csv(eps, out / "speed.csv"), "t=time,u=volts,x=position", "small synthetic", None

    sizes = []
    real_group = axis._replay_group
    monkeypatch.setattr(bc, "speed_recording", small)
    monkeypatch.setattr(axis, "_replay_group", lambda built, h, dt: sizes.append((axis.REPLAY_BATCH_JOBS,
                                                                                   len(built))) or real_group(built, h, dt))
    res = bc.run_speed(tmp_path, log=lambda s: None)
    assert res["identical"] and res["verdict"] == "found" and "coulomb_friction" in res["effects"]
    assert res["cpu_s_ratio_peer_over_batched"] > 0 and "peer / batched" in bc.format_speed(res)
    assert max(n for b, n in sizes if b is None) > 1  # batched: many jobs per replay
    assert {n for b, n in sizes if b == 1} == {1}  # the peer: one job per replay
    assert axis.REPLAY_BATCH_JOBS is None  # restored
