"""`hil demo transfer` end to end on the seconds-long preset: report keys and plots."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from hilstack.tools.cli import app


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
    assert set(ge) == {"none", "gat", "garat", "floor"} and all(v > 0 for v in ge.values())
    assert ge["floor"] <= min(ge["none"], ge["gat"], ge["garat"])  # no transform beats the floor
    roach = rep["garat"]["roach"]
    assert set(roach["normalised_return"]) == {"source", "gat", "garat"}
    assert roach["seeds"] == [0] and len(roach["per_seed"]) == 1
    row = roach["per_seed"][0]
    assert set(row["target_return_m"]) == {"source", "target", "gat", "garat"}
    assert row["garat_disc_updates"] == 2  # 128 PPO steps / 64 per update: one D update per π_g update
    assert rep["garat"]["pendulum"]["seeds"] == [0]
    for f in rep["plots"]:
        assert (tmp_path / f).read_bytes()[:4] == b"\x89PNG"
    assert "sidm similar with_sidm: data multiplier per size" in r.output and "pendulum grounding error" in r.output


def test_part_runs_only_that_half(tmp_path, monkeypatch):
    import hilstack.learning.transfer.roach_pairs as rp
    import hilstack.tools.demo_transfer as dt

    calls = []
    monkeypatch.setattr(rp, "run_sidm", lambda *a: calls.append("sidm") or {"pairs": {}})
    monkeypatch.setattr(dt, "_pendulum_over_seeds", lambda *a: calls.append("pendulum") or {})
    monkeypatch.setattr(dt, "_roach_over_seeds", lambda *a: calls.append("roach") or {})
    monkeypatch.setattr(dt, "_plots", lambda *a: [])
    rep = dt.run_transfer_demo(tmp_path, preset="tiny", part="sidm", log=lambda m: None)
    assert calls == ["sidm"] and "garat" not in rep and "sidm" in rep
    with pytest.raises(ValueError, match="unknown part"):
        dt.run_transfer_demo(tmp_path, preset="tiny", part="both")
    r = CliRunner().invoke(app, ["demo", "arms", "--part", "garat"])
    assert r.exit_code != 0 and "--part is for the transfer demo only" in r.output


def test_unknown_demo_is_a_one_line_error():
    r = CliRunner().invoke(app, ["demo", "nonsense"])
    assert r.exit_code == 2 and "unknown demo 'nonsense'" in r.output


@pytest.mark.slow
def test_demo_transfer_sidm_part_on_the_wheeled_setting(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_TRANSFER_PRESET", "tiny")
    r = CliRunner().invoke(app, ["demo", "transfer", "--part", "sidm", "--setting", "wheeled", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "report.json").read_text())
    assert "garat" not in rep and rep["part"] == "sidm" and rep["setting"] == "wheeled"
    assert rep["plots"] == ["sidm_validation.png"]
    assert set(rep["checks"]) == {"sidm_multiplier_above_1_on_a_pair"}
    assert rep["sidm"]["variants"] == ["with_sidm", "without_sidm", "sidm_paper", "finetune"]
    p = rep["sidm"]["pairs"]["dissimilar"]
    assert p["overrides"]["stiffness_n_per_m"] == 400.0 * 667  # the paper's pair, not the roach's
    assert p["expert_model_on_novice"] > 0
    for row in p["curve"]:
        assert all(row[k] > 0 for k in rep["sidm"]["variants"])
    for tag in ("", "_sidm_paper", "_finetune"):
        per = p["data_multiplier_per_size" + tag]
        assert len(per) == len(p["curve"]) and {e["where"] for e in per} <= {"interpolated", "beyond", "below"}
    assert "sidm similar sidm_paper: data multiplier per size" in r.output and "pendulum" not in r.output
    r = CliRunner().invoke(app, ["demo", "transfer", "--setting", "wheeled", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "--setting is for `hil demo transfer --part sidm` only" in r.output


def test_demo_transfer_unknown_part_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("HIL_TRANSFER_PRESET", "tiny")
    r = CliRunner().invoke(app, ["demo", "transfer", "--part", "nonsense", "--out", str(tmp_path)])
    assert r.exit_code != 0 and "part" in r.output and "Traceback" not in r.output
