"""`hil bench calibrate`: a one-seed version of the realistic-data gauntlet (the full one is a benchmark)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from tools.bench_calibrate import CASES, format_table
from tools.cli import app

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
