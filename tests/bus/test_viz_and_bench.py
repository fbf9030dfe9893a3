"""rerun logging (read back from the .rrd) and the bus benchmark's output shape."""

from __future__ import annotations

import json
import os

from hilstack.bus import keys
from hilstack.bus.recording import McapLog
from hilstack.bus.schemas import Command, Image, Plan, RobotState, SpecMsg
from tests.helpers import spec_dict


def _entities(rrd) -> set[str]:
    import rerun as rr

    return {str(c.entity_path) for c in rr.chunk.RrdReader(str(rrd)).stream().to_chunks()}


def test_viz_recording_to_rrd_with_layout(tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    mc = tmp_path / "a.mcap"
    spec = spec_dict("pm", ["x", "y", "vx", "vy"], ["fx", "fy"])
    with McapLog(mc) as log:
        log.write(keys.spec("r", "pm"), SpecMsg(robot="pm", spec=spec))
        for i in range(20):
            log.write(keys.state("r", "pm"), RobotState(robot="pm", t_s=i * 0.1, state=[i * 0.1, 0.0, 1.0, 0.0]))
            log.write(keys.cmd("r", "pm"), Command(robot="pm", action=[1.0, 0.0]))
        log.write(keys.plan("r"), Plan(robot="pm", actions=[[1.0, 0.0]], states=[[0, 0, 0, 0], [0.1, 0, 0, 0]]))
        log.write(keys.image("r", "cam"), Image(camera="cam", t_s=0.0, width=2, height=2, data=bytes(12)))
    rrd = tmp_path / "a.rrd"
    r = CliRunner().invoke(app, ["viz", "--recording", str(mc), "--save", str(rrd)])
    assert r.exit_code == 0, r.output
    ents = _entities(rrd)
    for e in ("/state/pm/x", "/cmd/pm/fx", "/world/pm/path", "/world/pm/plan", "/camera/cam"):
        assert e in ents, (e, ents)


def test_bench_bus_prints_json_with_ratio():
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    # --pin where there are 2 CPUs to pin to (the ping side and the pong processes on one each)
    pin = hasattr(os, "sched_getaffinity") and len(os.sched_getaffinity(0)) >= 2
    before = os.sched_getaffinity(0) if pin else None
    r = CliRunner().invoke(app, ["bench", "bus", "--n", "100", "--via-router", "--json"] + (["--pin"] if pin else []))
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["pinned"] is pin
    if pin:
        assert os.sched_getaffinity(0) == before  # the test process is given back all its CPUs
    for size in ("64B", "4096B"):
        row = out[size]
        assert row["raw"]["p50_us"] > 0 and row["node"]["p99_us"] >= row["node"]["p50_us"]
        assert row["ratio_p50"] == row["node"]["p50_us"] / row["raw"]["p50_us"]
        assert row["ratio_p99"] == row["node"]["p99_us"] / row["raw"]["p99_us"]
        assert row["raw_over_tcp_p50"] == row["raw"]["p50_us"] / row["tcp"]["p50_us"] and row["tcp"]["p50_us"] > 0
        # the reference stacks between raw and node: the node's channel, then typed messages
        for a, b in (("ring", "raw"), ("ring_typed", "ring"), ("node", "ring_typed")):
            assert row[f"{a}_over_{b}_p50"] == row[a]["p50_us"] / row[b]["p50_us"] > 0
        # --via-router: the extra hop through a router process, beside the direct peer hop
        assert row["router_over_raw_p50"] == row["router"]["p50_us"] / row["raw"]["p50_us"] > 0
    assert "ratio_p50" in out and "ratio_p99" in out and out["loadavg_1min"] >= 0
