"""A replay never releases an e-stop (issue 22, item 10).

Review: `hil replay --include-commands --force` re-sent a recorded release while the rig was
e-stopped, and the recorded commands then drove the robot. Here the whole story runs through
the CLI against a driver node process: record a session in which the operator releases and
drives, engage the e-stop, replay the recording with --include-commands --force: the robot
stays stopped, the e-stop engaged, and the replay says it left the release out.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time

from hilstack.bus import keys
from hilstack.bus.node import Node, alive_nodes
from hilstack.bus.schemas import Command, RobotState, decode
from hilstack.configs.schema import BusConfig
from tests.helpers import ROOT, free_port, wait_for

RIG = "pointmass_sim"


def _hil(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hilstack.tools.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=180)


def test_replay_with_commands_and_force_never_releases_the_estop(tmp_path, spawn):
    ep = f"tcp/127.0.0.1:{free_port()}"
    bus = BusConfig(endpoint=ep)
    up = spawn("up", RIG, "--endpoint", ep)
    ctl = Node("test-ctl", RIG, bus, handle_signals=False)
    got: list[RobotState] = []
    sub = ctl.subscribe(keys.state(RIG, "pm"), RobotState, latest=False)

    def new() -> list[RobotState]:
        out = [decode(p, RobotState) for _, p in sub.drain()]
        got.extend(out)
        return out

    rec_path = tmp_path / "session.mcap"
    try:
        wait_for(lambda: new(), 60, "the driver node's first state")
        rec = spawn("record", "--rig", RIG, "--endpoint", ep, "--out", str(rec_path))
        wait_for(lambda: "recorder" in alive_nodes(ctl.session, RIG, 0.5), 60, "the recorder")
        # the recorded session: the operator engages, releases, drives
        assert _hil("estop", RIG, "--endpoint", ep, "--timeout-s", "5").returncode == 0
        r = _hil("estop", RIG, "--endpoint", ep, "--release", "--timeout-s", "5")
        assert r.returncode == 0, r.stderr
        cmd = ctl.publisher(keys.cmd(RIG, "pm"), Command)
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:
            cmd.put(Command(robot="pm", action=[2.0, 0.0]))
            time.sleep(0.05)
        assert any(s.action and s.action[0] > 0.5 for s in new())  # it drove
        time.sleep(0.6)  # the recorder's flush period
        assert rec.stop(60) == 0

        # the operator's e-stop, then the replay of that session onto the live rig
        assert _hil("estop", RIG, "--endpoint", ep, "--timeout-s", "5").returncode == 0
        wait_for(lambda: any(s.stopped_reason == "estop" for s in new()), 30, "the e-stop")
        t_engaged = time.time()
        r = _hil("replay", str(rec_path), "--include-commands", "--force", "--speed", "1", "--endpoint", ep)
        assert r.returncode == 0, r.stderr
        t_mark = time.time()
        wait_for(lambda: any(s.stamp_s > t_mark + 0.5 for s in new()), 30, "states after the replay")
        after = [s for s in got if s.stamp_s > t_engaged]
        assert after and all(s.stopped_reason == "estop" and not s.active for s in after), \
            "the replay released the e-stop"
        assert all(all(abs(a) < 1e-9 for a in s.action) for s in after), "a replayed command drove the robot"
        r2 = _hil("nodes", RIG, "--endpoint", ep, "--json")
        row = next(x for x in json.loads(r2.stdout) if x["node"] == "driver-pm")
        assert row["estop"] == "engaged"
        assert re.search(r"never replayed: \d+ e-stop releases on hil/pointmass_sim/estop/release/", r.stderr)
    finally:
        ctl.close()
        assert up.stop(60) == 0
