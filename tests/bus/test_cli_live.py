"""`hil record` and `hil viz` live against a running rig (all separate processes)."""

from __future__ import annotations

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.recording import summarize
from hilstack.bus.schemas import RobotState
from tests.bus.test_viz_and_bench import _entities


def test_record_and_viz_a_live_rig(bus, spawn, tmp_path):
    ep = bus.endpoint
    up = spawn("up", "pointmass_sim", "--endpoint", ep)
    # record only once the driver node publishes (its start-up, imports included, varies with load)
    with Node("test-wait", "pointmass_sim", bus, handle_signals=False) as n:
        st = n.subscribe(keys.state("pointmass_sim", "pm"), RobotState)
        assert st.wait(60) is not None, "no state from the driver node"
    rec = spawn("record", "--rig", "pointmass_sim", "--seconds", "3", "--out", str(tmp_path / "s.mcap"),
                "--endpoint", ep)
    viz = spawn("viz", "--rig", "pointmass_sim", "--seconds", "3", "--save", str(tmp_path / "s.rrd"),
                "--endpoint", ep)
    assert rec.p.wait(60) == 0, rec.p.stderr.read()
    assert viz.p.wait(60) == 0, viz.p.stderr.read()
    assert up.stop() == 0
    s = summarize(tmp_path / "s.mcap")
    state = s["channels"]["hil/pointmass_sim/pm/state"]
    assert state["count"] >= 30 and 20 < state["rate_hz"] < 80  # 50 Hz driver
    assert "hil/pointmass_sim/pm/spec" in s["channels"]
    assert "/state/pm/x" in _entities(tmp_path / "s.rrd")
