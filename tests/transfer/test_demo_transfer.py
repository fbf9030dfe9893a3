"""`hil demo transfer` end to end on the seconds-long preset: report keys and plots."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from tools.cli import app


@pytest.mark.slow
def test_demo_transfer_writes_the_report_and_plots(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_TRANSFER_PRESET", "tiny")
    r = CliRunner().invoke(app, ["demo", "transfer", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "report.json").read_text())
    for pair in ("similar", "dissimilar"):
        p = rep["sidm"]["pairs"][pair]
        assert [row["minutes"] for row in p["curve"]] == [0.05, 0.1]
        assert all(row["with_sidm"] > 0 and row["without_sidm"] > 0 for row in p["curve"])
        assert "data_multiplier" in p
    ge = rep["garat"]["pendulum"]["grounding_error"]
    assert set(ge) == {"none", "gat", "garat"} and all(v > 0 for v in ge.values())
    assert set(rep["garat"]["roach"]["normalised_return"]) == {"source", "gat", "garat"}
    for f in rep["plots"]:
        assert (tmp_path / f).read_bytes()[:4] == b"\x89PNG"
    assert "sidm similar: data multiplier" in r.output and "pendulum grounding error" in r.output


def test_unknown_demo_is_a_one_line_error():
    r = CliRunner().invoke(app, ["demo", "nonsense"])
    assert r.exit_code == 2 and "unknown demo 'nonsense'" in r.output
