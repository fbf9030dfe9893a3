"""The whole MBRL loop on the simulated VelociRoACH, tiny: every node on the bus, report files."""

from __future__ import annotations

import json

import numpy as np

from hilstack.tools.demo import run_demo


def test_tiny_demo_writes_a_complete_report(tmp_path):
    r = run_demo(
        tmp_path,
        quick=True,
        random_rollouts=6,
        rollout_steps=20,
        epochs=3,
        retrain_epochs=1,
        samples=64,
        paths=("straight", "left"),
        path_scale=0.25,
        time_limit_speed_mps=0.4,
        tune_paths=("right",),
        tune_path_scale=0.25,
        baseline_candidates=3,
        progress=False,
    )
    rep = json.loads((tmp_path / "report.json").read_text())
    for speed in ("low_speed", "high_speed"):
        v = rep[speed]
        assert set(v["paths"]) == {"straight", "left"}
        costs = [v["paths"][p]["mpc"]["cost"] for p in ("straight", "left")]
        assert v["mpc_cost"] == sum(costs) / 2
        assert isinstance(v["differential_drive_cost"], float)
        for who in ("mpc", "differential_drive"):
            done = [v["paths"][p][who]["completed"] for p in ("straight", "left")]
            assert v[f"{who}_completed"] == sum(done)
            per = [v["paths"][p][who] for p in ("straight", "left")]
            assert v[f"{who}_cost_per_m"] == sum(m["cost"] for m in per) / max(sum(m["progress_m"] for m in per), 0.01)
            for m in per:
                assert set(m) >= {"cost", "completed", "progress_m", "cost_per_m", "time_s"}
                assert m["time_s"] <= m["time_limit_s"] + 0.1 + 1e-9
    bt = rep["baseline_tuning"]
    assert bt["candidates"] == 3 and set(bt["best_params"]) == {"low_speed", "high_speed"}
    assert set(bt["best_params"]["low_speed"]) == {"omega_nom", "k_heading", "k_perp", "d_max"}
    assert len(bt["per_speed"]["high_speed"]["candidates"]) == 3
    assert rep["training"][0]["episodes"] == 6
    assert rep["training"][1]["episodes"] > 6  # aggregated on-policy data
    assert "data_size_curve" not in rep  # one seed, no statistics: the full run's Table 3.1 replaces it
    for f in ("report.md", "costs.png", "trajectories_high_speed.png", "demo.rrd", "model.pt"):
        assert (tmp_path / f).is_file(), f
    assert "MPC vs tuned differential drive" in (tmp_path / "report.md").read_text()
    assert r["wall_s"] > 0

    # the trained model drives `hil mpc` on a fresh rig, scored with the same metrics
    from typer.testing import CliRunner

    from hilstack.configs.schema import BusConfig
    from hilstack.learning.mbrl import rig_processes
    from hilstack.tools.cli import app
    from hilstack.tools.demo import free_endpoint

    bus = BusConfig(endpoint=free_endpoint())
    with rig_processes("roach_sim", bus, tmp_path / "mpc_logs"):
        out = CliRunner().invoke(app, ["mpc", "roach_sim", "--model", str(tmp_path / "model.pt"), "--path", "left",
                                       "--path-scale", "0.25", "--steps", "15", "--json", "--endpoint", bus.endpoint])
    assert out.exit_code == 0, out.output
    m = json.loads(out.output)
    assert {"completed", "progress_m", "cost_per_m", "time_s"} <= set(m) and 0 < m["steps"] <= 15


def test_a_rig_that_never_comes_up_is_a_clear_error(tmp_path):
    import pytest

    from hilstack.bus.access import generate
    from hilstack.learning.mbrl import RigError

    rig = tmp_path / "broken.yaml"
    cred = tmp_path / "broken.credentials"  # a real robot's rig has access control (docs/platform.md)
    generate(cred, ["operator"])
    rig.write_text(
        "name: broken\nrobots:\n  roach:\n    config: velociroach\n    backend: real\n"
        "    params: {port: /dev/hilstack-no-such-port}\npace: realtime\n"
        f"bus:\n  access:\n    credentials: {cred}\n"
    )
    with pytest.raises(RigError, match="driver log") as e:
        # operator resets: this rig is about the driver never coming up, not about resets
        run_demo(tmp_path / "out", quick=True, rig=str(rig), rig_timeout_s=120.0, progress=False,
                 operator_resets=True)
    log = (tmp_path / "out" / "logs" / "driver.log").read_text()
    assert "hilstack-no-such-port" in log  # the driver said what was wrong
    # and the demo said it as soon as the rig's process exited (not at the 120 s timeout),
    # with the driver's reason, on one line
    msg = str(e.value)
    assert "exited (code " in msg and "hilstack-no-such-port" in msg and "\n" not in msg


def test_tiny_full_run_writes_the_thesis_tables_with_statistics(tmp_path):
    """`hil demo --full` on a tiny configuration: Table 3.1, the speed sweep and Table 3.2
    over two seeds, with mean ± std, per-seed values and error-bar plots."""
    rep = run_demo(
        # one speed and no main-run iteration: the tables below use the high speed only, and the
        # main run's on-policy iteration is test_tiny_demo_writes_a_complete_report's
        tmp_path, full=True, random_rollouts=3, rollout_steps=30, epochs=2, retrain_epochs=1, samples=64,
        paths=("straight",), path_scale=0.2, time_limit_speed_mps=0.4, tune_paths=("right",),
        tune_path_scale=0.2, baseline_candidates=2, seeds=(0, 1), table_sizes=(2,), table_paths=("straight",),
        sweep_speeds=(1.0,), terrain_rollouts=2, speeds={"high_speed": 1.0}, iterations=0, progress=False,
    )
    t31 = rep["table_3_1"]
    assert list(t31["rows"]) == ["2", "2+on-policy"] and t31["seeds"] == [0, 1]
    cell = t31["rows"]["2"]["paths"]["straight"]["cost"]
    assert cell["n"] == 2 and cell["mean"] == sum(cell["values"]) / 2
    assert cell["std"] == float(np.std(cell["values"], ddof=1))
    sw = rep["speed_sweep"]["rows"]
    assert [r["speed"] for r in sw] == [1.0] and sw[0]["mpc"]["cost_per_m"]["n"] == 2
    t32 = rep["table_3_2"]
    assert t32["terrains"] == ["carpet", "styrofoam"]
    assert set(t32["matrix"]) == {"mpc trained on carpet", "mpc trained on styrofoam", "mpc trained on both",
                                  "differential drive (tuned per terrain)"}
    for row in t32["matrix"].values():
        assert set(row) == {"carpet", "styrofoam"}
    # the styrofoam rig really is another terrain
    assert "styrofoam" in (tmp_path / "rigs" / "roach_sim_styrofoam.yaml").read_text()
    md = (tmp_path / "report.md").read_text()
    for title in ("Table 3.1", "Fig. 3.8", "Table 3.2"):
        assert title in md
    assert " ± " in md
    for f in ("table_3_1.png", "speed_sweep.png", "table_3_2.png"):
        assert (tmp_path / f).is_file(), f
    # every experiment episode is recorded
    for f in ("recordings/312-eval-seed1.mcap", "recordings/330-sweep-1.00.mcap",
              "terrain_styrofoam/recordings/322-eval-styrofoam.mcap"):
        assert (tmp_path / f).is_file() and str(tmp_path / f) in rep["recordings"], f
