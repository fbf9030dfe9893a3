"""The planning benchmark runs and reports the documented fields (never asserts speed)."""

import math

import numpy as np
import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from hilstack.control.planners import BAODING_PDDM
from hilstack.learning.dynamics import EnsembleDynamics
from hilstack.tools.bench_plan import WORKLOADS, PlainEnsemble, _make_planner, plan_flops, run_bench_plan


def _finite_pos(x):
    return x is not None and math.isfinite(x) and x > 0


def test_run_bench_plan_reports_all_workloads_and_levers():
    out = run_bench_plan(calls=2, warmup=1, quality_seeds=1)
    for name in WORKLOADS:
        r = out[name]
        for key in ("p50_ms", "p99_ms", "peer_p50_ms", "peer_p99_ms", "peer_plain_model_p50_ms",
                    "gflops", "matmul_gflops", "gflop_per_plan"):
            assert _finite_pos(r[key]), (name, key, r[key])
        assert r["p99_ms"] >= r["p50_ms"]
        assert r["dtype"] in ("float32", "bfloat16")
        # achieved rate is the FLOP count over our p50 (not a copy of the matmul rate)
        assert r["gflops"] == pytest.approx(r["gflop_per_plan"] / (r["p50_ms"] / 1e3))
    assert out["B"]["ensemble"] == 3 and out["B"]["samples"] == 700 and out["B"]["horizon"] == 7
    assert out["A"]["state_dim"] == 24 and out["A"]["samples"] == 500 and out["A"]["horizon"] == 4
    b = out["baoding"]
    assert (b["state_dim"], b["action_dim"], b["ensemble"], b["samples"], b["horizon"]) == (36, 20, 3, 700, 7)
    assert b["gflop_per_plan"] == pytest.approx(plan_flops(3, 700, 7, [56, 500, 500, 36]) / 1e9)
    assert b["p99_within_budget"] == (b["p99_ms"] < 100.0)
    assert b["within_half_plain_peer"] == (b["p50_ms"] <= 0.5 * b["peer_plain_model_p50_ms"])
    lev = b["levers"]
    assert _finite_pos(lev["samples_350"]["p50_ms"]) and _finite_pos(lev["hidden_2x250"]["p99_ms"])
    assert _finite_pos(lev["samples_350"]["plan_cost_ratio"])
    assert lev["hidden_2x250"]["plan_cost_ratio"] is None  # another model: not comparable
    assert lev["tuned_chunks"]["chunks"] in (1, 2, 4) and lev["tuned_chunks"]["default_chunks"] == 4
    for name in ("samples_350", "tuned_chunks", "hidden_2x250"):
        r = lev[name]
        assert r["ratio_p50_vs_plain_model"] == pytest.approx(r["p50_ms"] / lev["peer_plain_model_p50_ms"])
        assert r["ratio_p50_vs_configured"] == pytest.approx(r["p50_ms"] / lev["configured_p50_ms"])
    assert ("skipped" in lev["bf16"]) == (out["env"]["cpu_bf16"] is None)
    env = out["env"]
    assert env["calls"] == 2 and len(env["loadavg"]) == 3 and len(env["loadavg_start"]) == 3


def test_plan_flops_formula_on_a_tiny_case():
    # by hand: layers 8->7->5 are 56 + 35 = 91 multiply-adds per input; 2 members x 64
    # samples x 4 steps x 2 FLOP
    assert plan_flops(2, 64, 4, [8, 7, 5]) == 2 * 2 * 64 * 4 * 91 == 93184
    # and torch's own FLOP counter agrees on a real rollout of both models
    m = EnsembleDynamics(5, 3, ensemble=2, hidden=(7,), seed=0).eval()
    for predict in (m._predict_diff, PlainEnsemble(m)):
        with torch.inference_mode(), FlopCounterMode(display=False) as fc:
            s = torch.randn(64, 5)
            for _ in range(4):
                s = predict(s, torch.randn(64, 3))
        assert fc.get_total_flops() == plan_flops(2, 64, 4, [8, 7, 5])


def test_plain_sequential_ensemble_is_the_same_function():
    """The plain-model peer must time the same network, or the comparison means nothing."""
    m = EnsembleDynamics(6, 2, ensemble=3, hidden=(16, 16), seed=1).eval()
    rng = np.random.default_rng(0)
    with torch.no_grad():  # non-trivial normalization so it is exercised too
        m.input_mean.copy_(torch.from_numpy(rng.normal(size=8).astype(np.float32)))
        m.input_std.copy_(torch.from_numpy(rng.uniform(0.5, 2, size=8).astype(np.float32)))
        m.delta_mean.copy_(torch.from_numpy(rng.normal(size=6).astype(np.float32)))
        m.delta_std.copy_(torch.from_numpy(rng.uniform(0.5, 2, size=6).astype(np.float32)))
    plain = PlainEnsemble(m)
    s, a = torch.randn(3, 40, 6), torch.randn(40, 2)
    with torch.inference_mode():
        torch.testing.assert_close(plain(s, a), m.predict(s, a), rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(plain(s[0], a), m.predict(s[0], a), rtol=1e-4, atol=1e-5)


def test_baoding_workload_is_the_one_baoding_config():
    w = WORKLOADS["baoding"]
    assert _make_planner(w).config() == BAODING_PDDM.planner(seed=0).config()
    assert {k: w[k] for k in ("state_dim", "action_dim", "ensemble", "hidden")} == BAODING_PDDM.model_kwargs()
    assert (w["samples"], w["horizon"]) == (BAODING_PDDM.samples, BAODING_PDDM.horizon)
    c = BAODING_PDDM
    assert (c.horizon, c.samples, c.gamma, c.beta, c.ensemble, c.hidden) == (7, 700, 20.0, 0.6, 3, (500, 500))
    # the reference code's sampler (google-research/pddm mppi.py, config/baoding.txt)
    assert (c.sigma, c.filter, c.low_noise_fraction) == (0.9, "actions", 0.1)


def test_tune_inference_pins_a_measured_chunk_count_without_changing_the_function():
    m = EnsembleDynamics(6, 2, ensemble=3, hidden=(32, 32), seed=0).eval()
    s, a = torch.randn(3, 256, 6), torch.randn(256, 2)
    assert EnsembleDynamics._chunks_for(256) == 4
    with torch.inference_mode():
        ref = m.predict(s, a)  # default split
    # candidates without the default, so predict can only use k if it honours the pin
    k = m.tune_inference(256, candidates=(1, 2, 3), reps=2)
    assert k in (1, 2)  # 3 does not divide 256
    used = []
    orig = m._chunk_weights
    m._chunk_weights = lambda n: used.append(n) or orig(n)
    with torch.inference_mode():
        out = m.predict(s, a)
        m.predict(s[:, :60], a[:60])  # another batch size keeps the default split
    assert used == [k, EnsembleDynamics._chunks_for(60)]
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
    for forced in (1, 2, 4):  # whatever tuning picks, the function is the same
        m._chunks_pinned[256] = forced
        with torch.inference_mode():
            torch.testing.assert_close(m.predict(s, a), ref, rtol=1e-5, atol=1e-5)
    m.set_inference_dtype("fp32")  # a new precision forgets measurements of the old one
    assert m._chunks_pinned == {}
    with pytest.raises(ValueError, match="divides batch=256"):
        m.tune_inference(256, candidates=(3, 7))


def test_plan_cost_measure_ranks_a_planned_sequence_above_random_ones():
    """The quality measure of the levers: a PDDM plan must score better than random plans."""
    from dataclasses import replace

    from hilstack.tools.bench_plan import _cost_for, _plan_cost

    cfg = replace(BAODING_PDDM, hidden=(32, 32), samples=200)
    model = EnsembleDynamics(**cfg.model_kwargs(), seed=0).eval()
    cost = _cost_for("baoding", cfg.state_dim)
    s0 = torch.from_numpy(np.random.default_rng(0).normal(size=cfg.state_dim).astype(np.float32))
    planner, evaluator = cfg.planner(0), cfg.planner(0)
    for _ in range(3):  # a few warm-started iterations from the same state
        planner(model, cost, s0)
    planned = _plan_cost(evaluator, model, cost, s0, planner.last_plan)
    g = torch.Generator().manual_seed(1)
    random = [_plan_cost(evaluator, model, cost, s0, torch.rand(cfg.horizon, cfg.action_dim, generator=g) * 2 - 1)
              for _ in range(20)]
    assert planned < float(np.mean(random))
