"""`hil up` of a rig with several robots (the WidowX bench: arm + mechanism) starts one
process per robot; stopping it with SIGTERM (as `hil demo arms` and the MBRL loop do)
must stop them all, not leave them running."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[2]


def test_sigterm_to_a_multi_robot_rig_stops_every_robot_process():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    parent = subprocess.Popen([sys.executable, "-m", "hilstack.tools.cli", "up", "arm_widowx_sim", "--endpoint", endpoint],
                              cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    children: list[psutil.Process] = []
    try:
        deadline = time.monotonic() + 60
        while len(children) < 2 and time.monotonic() < deadline:
            children = psutil.Process(parent.pid).children()
            time.sleep(0.2)
        assert len(children) == 2, "the rig should start one process per robot"
        time.sleep(1.0)  # let them install their own signal handlers
        parent.send_signal(signal.SIGTERM)
        parent.wait(30)
        gone, alive = psutil.wait_procs(children, timeout=20)
        assert alive == [], f"robot processes left running: {[p.pid for p in alive]}"
    finally:
        for c in children:
            if c.is_running():
                c.kill()
        if parent.poll() is None:
            parent.kill()
