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


def test_parts_parse_and_refuse_unknown_names():
    from tools.demo_transfer import PARTS, parse_parts

    assert parse_parts(None) == PARTS and parse_parts("") == PARTS
    assert parse_parts(" sidm ") == ("sidm",)
    with pytest.raises(ValueError, match="HIL_TRANSFER_PARTS"):
        parse_parts("sidm,gart")


@pytest.mark.slow
def test_demo_transfer_sidm_part_only(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_TRANSFER_PRESET", "tiny")
    monkeypatch.setenv("HIL_TRANSFER_PARTS", "sidm")
    r = CliRunner().invoke(app, ["demo", "transfer", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["garat"] is None and rep["skipped"] == ["garat"] and rep["plots"] == ["sidm_validation.png"]
    assert set(rep["checks"]) == {"sidm_multiplier_above_1_on_a_pair"}
    p = rep["sidm"]["pairs"]["similar"]
    assert p["expert_model_on_novice"] > 0 and p["curve"][0]["with_sidm_no_matching"] > 0
    assert len(p["data_multiplier_per_size"]) == len(p["curve"])
    assert "pendulum" not in r.output and "skipped (HIL_TRANSFER_PARTS): garat" in r.output


def test_demo_transfer_unknown_part_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_TRANSFER_PRESET", "tiny")
    monkeypatch.setenv("HIL_TRANSFER_PARTS", "nonsense")
    r = CliRunner().invoke(app, ["demo", "transfer", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "unknown part" in r.output
