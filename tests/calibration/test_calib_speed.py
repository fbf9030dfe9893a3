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


def test_feature_cache_follows_every_input_side_hyper_parameter():
    """The cached command-chain columns are keyed on every hyper-parameter the chain reads: a design
    built through the cache equals one built on fresh episodes, whichever of them changed."""
    preps = _preps()
    params = axis.fit_axis(preps, ["deadband", "delay", "backlash", "actuator_lag", "saturation",
                                   "force_offset"], refine=False)
    axis.design(preps[0], params)  # fill the cache
    for h, dv in (("width_u", 0.05), ("delay_s", 0.013), ("halfwidth_u", 0.04), ("tau_s", 0.02),
                  ("limit_u", -0.2)):
        new = params.hyper[h] + dv if np.isfinite(params.hyper[h]) else 0.5
        changed = axis.AxisParams(**{**params.__dict__, "hyper": {**params.hyper, h: new}})
        X, _, _ = axis.design(preps[0], changed)
        X_fresh, _, _ = axis.design(_preps()[0], changed)
        np.testing.assert_array_equal(X, X_fresh, err_msg=h)


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
    monkeypatch.setattr(axis, "_replay_group", lambda built, h, dt: sizes.append(
        (axis.REPLAY_BATCH_JOBS, len(built), axis.USE_COMPILED)) or real_group(built, h, dt))
    res = bc.run_speed(tmp_path, log=lambda s: None)
    assert res["identical"] and res["verdict"] == "found" and "coulomb_friction" in res["effects"]
    assert res["cpu_s_ratio_peer_over_batched"] > 0 and "peer / batched" in bc.format_speed(res)
    assert max(n for b, n, c in sizes if b is None) > 1  # batched: many jobs per replay
    assert {n for b, n, c in sizes if b == 1} == {1}  # the peer: one job per replay
    assert {c for b, n, c in sizes if b == 1} == {False}  # ... through the numpy replay
    assert {c for b, n, c in sizes if b is None} == {True, False}  # the replay as it runs, and numpy's
    assert res["cpu_s_ratio_numpy_over_batched"] > 0 and "numpy / batched" in bc.format_speed(res)
    assert axis.REPLAY_BATCH_JOBS is None and axis.USE_COMPILED is True  # restored


def _rich_jobs():
    preps = axis.prepare(generate(SynthConfig(n_episodes=3, duration_s=2.0, seed=4,
                                              effects={"coulomb_friction": {}})))
    plain = axis.fit_axis(preps, [], refine=False)
    rich = axis.fit_axis(preps, ["coulomb_friction"], refine=False)
    rich.effects = rich.effects + ["stribeck_friction", "gravity_load", "cogging", "load_backlash", "back_emf",
                                   "force_offset", "slope"]
    rich.coef.update(fs_extra_acc=0.7, gl_acc=1.5, gc_acc=0.4, fa_acc=0.3, kemf=0.5, offset_acc=0.2,
                     gravity_acc=-0.1)
    rich.hyper.update(vs=0.05, q0_rad=0.2, cog_k=5.0, cog_phase=0.3, halfwidth_x=0.004)
    neg = axis.fit_axis(preps, ["coulomb_friction"], refine=False)
    neg.coef["fc_acc"] = -0.5  # a negative fitted friction is applied explicitly, not as a stick
    return [(p, prm, None, None) for prm in (plain, rich, neg) for p in preps]


def test_compiled_replay_equals_the_numpy_replay(monkeypatch):
    """The numba replay (speed extra) is the numpy replay: same windows, same sticking, same play."""
    if axis.compiled.replay is None:
        pytest.skip("numba (hilstack[speed]) is not installed: the numpy replay runs")
    jobs = _rich_jobs()
    monkeypatch.setattr(axis, "USE_COMPILED", False)
    ref = axis.simulate_many(jobs, 80)
    monkeypatch.setattr(axis, "USE_COMPILED", True)
    got = axis.simulate_many(jobs, 80)
    for r, g in zip(ref, got, strict=True):
        # sin and exp may differ in the last bit between numpy's and LLVM's libraries
        np.testing.assert_allclose(g["x_pred"], r["x_pred"], rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(g["v_pred"], r["v_pred"], rtol=1e-11, atol=1e-12)
        np.testing.assert_array_equal(g["v_pred"] == 0, r["v_pred"] == 0)  # the same samples stick
    u = np.sin(np.linspace(0, 20, 500)) + 0.05 * np.random.default_rng(0).normal(size=500)
    compiled_play = axis.backlash_play(u, 0.3)
    monkeypatch.setattr(axis, "USE_COMPILED", False)
    np.testing.assert_array_equal(compiled_play, axis.backlash_play(u, 0.3))


def test_refinement_with_stacked_windows_equals_a_replay_per_job(monkeypatch):
    """The output-error refinement replays its windows stacked once; its residual is that of replaying
    each job on its own with the same coefficients, each job weighted by the square root of its
    episode weight (a Gaussian likelihood with the fold/bootstrap counts as weights)."""
    import scipy.optimize

    preps = axis.prepare(generate(SynthConfig(n_episodes=4, duration_s=3.0, seed=6,
                                              effects={"coulomb_friction": {}, "force_offset": {}})))
    fit = axis.fit_axis(preps, ["coulomb_friction", "force_offset"], refine=False)
    w = np.array([1.0, 3.0, 0.0, 1.0])
    jobs, wts = axis._oe_jobs(preps, fit, w)
    sims = axis._replay_built(jobs)
    ex = np.concatenate([np.sqrt(wi) * (s["x_pred"] - s["x_true"]).ravel() for wi, s in zip(wts, sims, strict=True)])
    ev = np.concatenate([np.sqrt(wi) * (s["v_pred"] - s["v_true"]).ravel() for wi, s in zip(wts, sims, strict=True)])
    want = np.concatenate([ex / np.sqrt(np.mean(ex**2)), ev / np.sqrt(np.mean(ev**2))])
    seen = []
    real = scipy.optimize.least_squares

    def spy(fun, x0, **kw):
        seen.append(fun(np.array(x0, float)))
        return real(fun, x0, **kw)

    monkeypatch.setattr(scipy.optimize, "least_squares", spy)
    axis.refine_output_error(preps, axis.AxisParams(**{**fit.__dict__, "coef": dict(fit.coef)}), w)
    np.testing.assert_allclose(seen[0], want, rtol=1e-10, atol=1e-12)
