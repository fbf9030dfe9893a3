"""The whole MBRL loop on the simulated VelociRoACH, tiny: every node on the bus, report files."""

from __future__ import annotations

import json

from tools.demo import run_demo


def test_tiny_demo_writes_a_complete_report(tmp_path):
    r = run_demo(
        tmp_path,
        quick=True,
        random_rollouts=6,
        rollout_steps=20,
        epochs=3,
        retrain_epochs=1,
        eval_steps=8,
        samples=64,
        paths=("straight", "left"),
        data_sizes=(3,),
        progress=False,
    )
    rep = json.loads((tmp_path / "report.json").read_text())
    for speed in ("low_speed", "high_speed"):
        assert set(rep[speed]["paths"]) == {"straight", "left"}
        costs = [rep[speed]["paths"][p]["mpc"]["cost"] for p in ("straight", "left")]
        assert rep[speed]["mpc_cost"] == sum(costs) / 2
        assert isinstance(rep[speed]["differential_drive_cost"], float)
    assert rep["training"][0]["episodes"] == 6
    assert rep["training"][1]["episodes"] > 6  # aggregated on-policy data
    assert rep["data_size_curve"][0]["random_rollouts"] == 3
    for f in ("report.md", "costs.png", "trajectories_high_speed.png", "demo.rrd", "model.pt"):
        assert (tmp_path / f).is_file(), f
    assert "MPC vs differential drive" in (tmp_path / "report.md").read_text()
    assert r["wall_s"] > 0


def test_a_rig_that_never_comes_up_is_a_clear_error(tmp_path):
    import pytest

    from learning.mbrl import RigError

    rig = tmp_path / "broken.yaml"
    rig.write_text(
        "name: broken\nrobots:\n  roach:\n    config: velociroach\n    backend: real\n"
        "    params: {port: /dev/hilstack-no-such-port}\npace: realtime\n"
    )
    with pytest.raises(RigError, match="driver log") as e:
        # operator resets: this rig is about the driver never coming up, not about resets
        run_demo(tmp_path / "out", quick=True, rig=str(rig), rig_timeout_s=4.0, progress=False, operator_resets=True)
    log = (tmp_path / "out" / "logs" / "driver.log").read_text()
    assert "hilstack-no-such-port" in log  # the driver said what was wrong
    assert "no spec" in str(e.value)
