"""`hil bench calibrate`: a one-seed version of the realistic-data gauntlet (the full one is a benchmark)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from hilstack.tools.bench_calibrate import CASES, format_table
from hilstack.tools.cli import app

runner = CliRunner()


def test_gauntlet_one_seed_mixed_rates_rest_and_nan(tmp_path):
    """Mixed 50/100 Hz episodes, episodes at rest and NaN rows, through CSV and the CLI verb: the
    hidden delay is named, the clean version raises no alarm, nothing crashes."""
    res = runner.invoke(app, ["bench", "calibrate", "--seeds", "1", "--cases", "rest_mixed_rates", "--out",
                              str(tmp_path), "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout.strip().splitlines()[-1])
    case = out["cases"]["rest_mixed_rates"]
    assert case["crashes"] == 0 and case["data_errors"] == 0
    assert case["hits"] == 1 and case["false_alarms"] == 0
    assert "hit rate 100%" in format_table({**out, "rows": []})


def test_gauntlet_unknown_case_is_a_one_line_error(tmp_path):
    res = runner.invoke(app, ["bench", "calibrate", "--seeds", "1", "--cases", "nope", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "unknown case" in res.output and all(c in res.output for c in CASES)


def test_gauntlet_runs_seed_major_and_logs_every_row(tmp_path, monkeypatch):
    """A run stopped early leaves equal seeds per case: jobs go seed by seed, each row is appended to
    rows.jsonl as it finishes, and `summarize` tabulates such a partial log."""
    import hilstack.tools.bench_calibrate as bc

    def fake(case, seed, hidden, root, n_boot):
        hit = not (case == "gravity_arm" and seed == 1)
        return {"case": case, "seed": seed, "hidden": hidden, "truth": bc.CASES[case].truth if hidden else None,
                "outcome": ("hit" if hit else "miss") if hidden else "clean", "verdict": "found" if hidden else "none",
                "effects": [bc.CASES[case].truth] if hidden else [], "cpu_s": 1.0 + seed, "elapsed_s": 2.0}

    monkeypatch.setattr(bc, "run_case", fake)
    bc.run_bench_calibrate(seeds=2, cases=["gravity_arm", "servo_vehicle"], out_dir=tmp_path)
    rows = [json.loads(line) for line in (tmp_path / "rows.jsonl").read_text().splitlines()]
    assert [(r["seed"], r["case"]) for r in rows[:4]] == [(0, "gravity_arm")] * 2 + [(0, "servo_vehicle")] * 2
    partial = bc.summarize(rows[:6])  # stopped during seed 1
    assert partial["totals"]["seeds_per_case"] == {"gravity_arm": 2, "servo_vehicle": 1}
    assert partial["cases"]["gravity_arm"]["misses"] == 1 and partial["cases"]["gravity_arm"]["hits"] == 1
    assert partial["cases"]["servo_vehicle"]["cpu_s"]["p50"] == 1.0
    assert "1.0/1.0" in format_table(partial)
