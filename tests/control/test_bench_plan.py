"""The planning benchmark runs and reports the documented fields (never asserts speed)."""

import math

from tools.bench_plan import WORKLOADS, run_bench_plan


def test_run_bench_plan_reports_both_workloads():
    out = run_bench_plan(calls=2, warmup=1)
    for name in WORKLOADS:
        r = out[name]
        assert r["planner"] in ("random_shooting", "pddm")
        for key in ("p50_ms", "p99_ms", "peer_p50_ms", "peer_p99_ms"):
            assert r[key] is not None and math.isfinite(r[key]) and r[key] > 0
        assert r["p99_ms"] >= r["p50_ms"]
        assert r["dtype"] in ("float32", "bfloat16")
    assert out["B"]["ensemble"] == 3 and out["B"]["samples"] == 700 and out["B"]["horizon"] == 7
    assert out["A"]["state_dim"] == 24 and out["A"]["samples"] == 500 and out["A"]["horizon"] == 4
    assert out["env"]["calls"] == 2
