"""`hil calibrate` end to end through typer's CliRunner, and the saved model closes the loop."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from hilstack.calibration import load_model
from hilstack.calibration.synthetic import SynthConfig, generate, write_csv
from hilstack.tools.cli import app

runner = CliRunner()
TRUTH = {"force_offset": {}}


@pytest.fixture(scope="module")
def csv_path(tmp_path_factory):
    eps = generate(SynthConfig(n_episodes=16, duration_s=4.0, seed=5, effects=TRUTH))
    return write_csv(eps, tmp_path_factory.mktemp("cli") / "log.csv")


@pytest.fixture(scope="module")
def cli_run(csv_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("cli_out")
    res = runner.invoke(app, ["calibrate", "--data", str(csv_path), "--model", "axis", "--map",
                              "t=time,u=volts,x=position", "--out", str(out), "--seed", "3", "--json"])
    return res, out


def test_cli_writes_report_and_json_line(cli_run):
    res, out = cli_run
    assert res.exit_code == 0, res.output
    line = json.loads(res.stdout.strip().splitlines()[-1])
    assert line["verdict"] == "found" and line["effects"][0]["name"] in ("force_offset", "slope")
    assert line["after_multi_step_nrmse"] < line["before_multi_step_nrmse"]
    for f in ("report.json", "report.md", "model.json", "residual_before_after.png", "diagnostics.png",
              "candidates.png"):
        assert (out / f).exists(), f
    rep = json.loads((out / "report.json").read_text())
    for key in ("effects", "before", "after", "verdict", "unexplained_structure", "ambiguous", "detection_limit",
                "data", "folds"):
        assert key in rep
    for key in ("name", "params", "interval", "heldout_gain", "p_value"):
        assert key in rep["effects"][0]
    for side in ("before", "after"):
        for kind in ("one_step_nrmse", "multi_step_nrmse"):
            t = rep[side][kind]
            assert set(t["per_channel"]) == {"x", "v"} and t["mean_interval"][0] <= t["mean"] <= t["mean_interval"][1]


def test_cli_summary_text(cli_run, csv_path, tmp_path, monkeypatch):
    """The text summary (no --json) of a real report, and the CLI's defaults for a CSV (column map,
    seed, --quiet = no progress). The calibration itself is cli_run's: running a second one here
    only to print it cost a full calibration of the suite's time."""
    from hilstack import calibration

    _, out = cli_run
    report = json.loads((out / "report.json").read_text())
    calls = []

    def fake_run_calibration(data, **kw):
        calls.append((data, kw))
        return report

    monkeypatch.setattr(calibration, "run_calibration", fake_run_calibration)
    res = runner.invoke(app, ["calibrate", "--data", str(csv_path), "--out", str(tmp_path), "--quiet"])
    assert res.exit_code == 0, res.output
    assert "verdict: found" in res.stdout and "multi-step NRMSE" in res.stdout
    e = report["effects"][0]
    assert f"  {e['name']}: " in res.stdout and f"held-out gain {e['heldout_gain']:.3f}" in res.stdout
    assert f"before {report['before']['multi_step_nrmse']['mean']:.4f}" in res.stdout
    assert f"report: {tmp_path}/report.md" in res.stdout
    (data, kw), = calls
    assert data == csv_path and kw["column_map"] == "t=time,u=volts,x=position" and kw["model"] == "axis"
    assert kw["seed"] == 0 and kw["progress"] is False and kw["out_dir"] == tmp_path


def test_saved_model_simulates_new_data(cli_run):
    """load_model closes the loop: on fresh data with the same physics it beats the nominal."""
    _, out = cli_run
    fitted = load_model(out / "model.json")
    assert "force_offset" in fitted.effects or "slope" in fitted.effects
    fresh = generate(SynthConfig(n_episodes=1, duration_s=4.0, seed=99, effects=TRUTH))[0]
    sim = fitted.simulate(fresh)
    err_aug = np.sqrt(np.mean((sim["x_pred"] - sim["x_true"]) ** 2))
    nominal = load_model(out / "model.json")  # same file, with the report's nominal fit
    nominal.params.effects = []
    nominal.params.coef = json.loads((out / "report.json").read_text())["nominal_params"]
    sim0 = nominal.simulate(fresh)
    err_nom = np.sqrt(np.mean((sim0["x_pred"] - sim0["x_true"]) ** 2))
    assert err_aug < 0.5 * err_nom


def test_cli_missing_column(csv_path, tmp_path):
    res = runner.invoke(app, ["calibrate", "--data", str(csv_path), "--map", "t=time,u=duty,x=position",
                              "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "'duty'" in res.output and str(csv_path) in res.output and "Traceback" not in res.output


def test_cli_nan_in_data(csv_path, tmp_path):
    df = pd.read_csv(csv_path)
    df.loc[123, "volts"] = np.nan
    bad = tmp_path / "bad.csv"
    df.to_csv(bad, index=False)
    res = runner.invoke(app, ["calibrate", "--data", str(bad), "--out", str(tmp_path / "o"), "--quiet"])
    # A NaN row is dropped with a one-line warning (file, row, column); the rest of the data is used.
    assert res.exit_code == 0, res.output
    warn = [ln for ln in res.output.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and str(bad) in warn[0] and "'volts'" in warn[0] and "data row 123" in warn[0]
    assert "Traceback" not in res.output


def test_cli_unknown_model_lists_known(csv_path, tmp_path):
    res = runner.invoke(app, ["calibrate", "--data", str(csv_path), "--model", "nope", "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "axis" in res.output and "velociroach" in res.output


def test_unavailable_backends_raise_clear_errors():
    from hilstack.calibration.models import ModelNotAvailable, get_model

    with pytest.raises(ModelNotAvailable, match="not available|not built"):
        get_model("checkpoint")
    assert get_model("velociroach").name == "velociroach"
