"""`hil up` of a rig with several robots (the WidowX bench: arm + mechanism) starts one
process per robot; stopping it with SIGTERM (as `hil demo arms` and the MBRL loop do)
must stop them all, not leave them running, also when the signal comes while they load and
`hil up` inherited SIGTERM ignored (a supervisor's or CI runner's disposition: CI stops 33 and
34 lost the stop sent to a robot process that had no node yet, and the robot ran on)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from tests.helpers import free_port

ROOT = Path(__file__).resolve().parents[2]


def _ignore_sigterm() -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


@pytest.mark.parametrize(("inherited", "after_s"), [("default", 1.0), ("ignored", 0.0), ("ignored", 0.4)],
                         ids=["loaded", "while-loading-sigterm-ignored", "soon-sigterm-ignored"])
def test_sigterm_to_a_multi_robot_rig_stops_every_robot_process(tmp_path, inherited, after_s):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    log = tmp_path / "up.log"
    with log.open("w") as err:
        parent = subprocess.Popen([sys.executable, "-m", "hilstack.tools.cli", "up", "arm_widowx_sim", "--endpoint",
                                   endpoint], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err,
                                  preexec_fn=_ignore_sigterm if inherited == "ignored" else None)
    children: list[psutil.Process] = []
    try:
        deadline = time.monotonic() + 60
        while len(children) < 2 and time.monotonic() < deadline:
            children = psutil.Process(parent.pid).children()
            time.sleep(0.05)
        assert len(children) == 2, "the rig should start one process per robot"
        time.sleep(after_s)  # 1 s: they have their nodes; 0: they are still loading
        parent.send_signal(signal.SIGTERM)
        # a node stuck past `hil up`'s grace is dumped and killed: exit 1 and its stacks in the log
        code = parent.wait(60)
        gone, alive = psutil.wait_procs(children, timeout=20)
        assert alive == [], f"robot processes left running: {[p.pid for p in alive]}"
        assert code == 0, log.read_text()
    finally:
        for c in children:
            if c.is_running():
                c.kill()
        if parent.poll() is None:
            parent.kill()
