"""`hil bench tracker --json`: one JSON line with the figures per tracker and the ratios."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner


def test_bench_tracker_prints_one_json_line_with_errors_latencies_and_ratios():
    from hilstack.tools.cli import app

    r = CliRunner().invoke(app, ["bench", "tracker", "--seconds", "0.3", "--json"])
    assert r.exit_code == 0, r.output
    lines = r.stdout.strip().splitlines()
    out = json.loads(lines[-1])
    assert out["frames"] == 3
    for k in ("color", "learned"):
        t = out[k]
        assert 0 < t["mean_error_mm"] < 30 and t["p95_error_mm"] >= 0 and t["detected"] > 0.5
        assert 0 < t["latency_ms_p50"] <= t["latency_ms_p99"]
        assert t["capture_inference_ms_p50"] > t["latency_ms_p50"]  # capture adds a render
    ratio = out["learned_vs_color"]
    assert ratio["mean_error_ratio"] == pytest.approx(out["learned"]["mean_error_mm"] / out["color"]["mean_error_mm"])
    assert ratio["latency_p50_ratio"] == pytest.approx(out["learned"]["latency_ms_p50"] / out["color"]["latency_ms_p50"])
    assert out["goals"]["thesis_error_mm"] == 5.0 and out["goals"]["thesis_latency_ms"] == 20.0
    assert out["goals"]["learned_error_met"] == (out["learned"]["mean_error_mm"] <= 5.0)


def test_closed_loop_runs_the_same_controller_on_truth_and_on_the_tracker():
    import math

    from hilstack.tools.bench_tracker import closed_loop

    r = closed_loop(0.3, trackers=("color",))
    assert r["truth"]["estimate_error_mm_mean"] == 0.0  # truth fed back: no estimate error
    assert 0.0 < r["color"]["estimate_error_mm_mean"] < 10.0  # the tracker's balls, not the truth
    assert all(math.isfinite(r[k]["return"]) and r[k]["return"] < 0 for k in ("truth", "color"))
