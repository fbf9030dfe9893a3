"""`hil adapt` beside `hil mpc --adapt` on the simulated VelociRoACH rig (three processes on
real Zenoh), and their one-line errors."""

from __future__ import annotations

import json

import torch

from hilstack.bus.node import Node, alive_nodes
from hilstack.configs.schema import load_rig, rig_robot_config
from hilstack.drivers.registry import make_driver
from hilstack.learning.adaptation.baselines import MbDeAdapter
from hilstack.learning.adaptation.model import AdaptiveMLP
from tests.helpers import wait_for


def roach_checkpoint(path):
    spec = make_driver(rig_robot_config(load_rig("roach_sim"), "roach")).spec
    torch.manual_seed(0)
    MbDeAdapter(AdaptiveMLP(list(spec.state.names), len(spec.action.names), hidden=(16,)), window=8).save(path)
    return path


def test_adapt_node_feeds_the_mpc_on_the_roach_sim_rig(bus, spawn, tmp_path):
    ck = str(roach_checkpoint(tmp_path / "mbde.pt"))
    spawn("up", "roach_sim", "--endpoint", bus.endpoint)
    node = spawn("adapt", "roach_sim", "--checkpoint", ck, "--max-updates", "12", "--idle-timeout", "20",
                 "--send", "last_layer", "--json", "--endpoint", bus.endpoint)
    # the node declares its liveliness token once warmed up (its first gradient takes seconds)
    with Node("probe", "roach_sim", bus, handle_signals=False) as probe:
        wait_for(lambda: "adaptation" in alive_nodes(probe.session, "roach_sim", timeout_s=0.2), 120, "the node")
    mpc = spawn("mpc", "roach_sim", "--adapt", ck, "--steps", "25", "--planner", "random_shooting", "--json",
                "--endpoint", bus.endpoint)
    out, err = mpc.p.communicate(timeout=240)
    assert mpc.p.returncode == 0, err[-2000:]
    m = json.loads(out.strip().splitlines()[-1])["model_updates"]
    assert m["applied"] >= 1 and m["rejected"] == 0 and m["malformed"] == 0
    assert m["delay_ms_p50"] > 0
    nout, nerr = node.p.communicate(timeout=60)
    assert node.p.returncode == 0, nerr[-2000:]
    s = json.loads(nout.strip().splitlines()[-1])
    assert s["window_clears"] >= 1  # the MPC reset the robot to the path start: a new episode
    # each update follows new transitions or a window clear (which publishes θ*); how the
    # states batch into steps depends on the load, so count, do not assume one clear
    assert s["updates"] == 12 and s["transitions"] >= 1
    assert s["updates"] <= s["transitions"] + s["window_clears"]
    assert s["rejected"] == 0 and s["nonfinite_updates"] == 0


def test_cli_errors_are_one_line(tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    ck = str(roach_checkpoint(tmp_path / "mbde.pt"))
    for args, why in [
        (["adapt", "roach_sim", "--checkpoint", str(bad)], "not a readable torch checkpoint"),
        (["adapt", "roach_sim", "--checkpoint", ck, "--send", "7.weight"], "--send '7.weight'"),
        (["adapt", "roach_sim", "--checkpoint", ck, "--method", "nope"], "unknown adaptation method 'nope'"),
        (["mpc", "roach_sim", "--adapt", ck, "--model", ck], "exactly one of --model"),
        (["mpc", "roach_sim"], "exactly one of --model"),
    ]:
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 2 and why in r.output, (args, r.output)
        assert r.output.strip().count("\n") == 0 and "Traceback" not in r.output


def test_bench_adaptation_measures_the_delay_against_raw_zenoh():
    from hilstack.tools.bench_adaptation import run_bench_adaptation

    r = run_bench_adaptation(rig="pointmass_sim", updates=3, hidden=(16,), payloads=("last_layer",), peer_n=20)
    row = r["last_layer"]
    assert row["received"] == 3 and row["rejected"] == 0
    assert row["bytes"] == 4 * (16 * 4 + 4)  # the output layer of a 16-wide net onto 4 states
    assert 0 < row["delay_ms"]["p50"] <= row["delay_ms"]["p99"]
    assert row["raw_oneway_ms_p50"] > 0 and row["ratio_p50"] > 0
    assert row["node"]["transitions"] >= 3 and r["period_ms"] == 20.0
    assert 0 < row["node_update_cpu_ms"]["p50"] <= row["node_update_cpu_ms"]["p99"]
    assert r["choice"] in ("last_layer", None) and r["choice"] == ("last_layer" if row["within_period"] else None)


def test_mpc_refuses_a_checkpoint_of_another_robot(bus, spawn, tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    ck = str(roach_checkpoint(tmp_path / "mbde.pt"))
    spawn("up", "pointmass_lockstep", "--endpoint", bus.endpoint)
    r = CliRunner().invoke(app, ["mpc", "pointmass_lockstep", "--adapt", ck, "--endpoint", bus.endpoint])
    assert r.exit_code == 2 and "robot pm has ['x', 'y', 'vx', 'vy']" in r.output, r.output
