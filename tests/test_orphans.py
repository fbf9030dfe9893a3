"""A rig started by a `hil` process stops when that process dies without stopping it
(SIGKILL, a crash), and so does a device emulator a driver started: bus/lifetime.py,
exit_with_parent (the one convention)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

from hilstack.bus.node import Node, alive_nodes
from tests.helpers import wait_for

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not reaped: its parent is gone and init reaps it soon) is not alive
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split(")")[-1].split()[0] != "Z"


def test_a_killed_demo_does_not_leave_its_rig_running(bus, tmp_path):
    code = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from hilstack.configs.schema import BusConfig
        from hilstack.learning.mbrl import rig_processes
        with rig_processes("roach_sim", BusConfig(endpoint={bus.endpoint!r}), Path({str(tmp_path)!r})) as p:
            print(p.pid, flush=True)
            time.sleep(600)
    """)
    parent = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        rig_pid = int(parent.stdout.readline())
        log = tmp_path / "driver.log"
        with Node("probe", "roach_sim", bus, handle_signals=False) as probe:
            wait_for(lambda: alive_nodes(probe.session, "roach_sim", timeout_s=0.2), 60, "the rig's driver node")
        assert _alive(rig_pid)
        parent.send_signal(signal.SIGKILL)  # no cleanup runs in the parent
        parent.wait(10)
        wait_for(lambda: not _alive(rig_pid), 20, "the orphaned rig to stop")
        assert "is gone: stopping" in log.read_text()
    finally:
        if parent.poll() is None:
            parent.kill()


def test_a_device_emulator_exits_when_its_driver_process_is_killed(tmp_path):
    """The same convention for the emulator a driver starts (drivers/emulator_process.py)."""
    code = textwrap.dedent("""
        import time
        from hilstack.drivers.emulator_process import EmulatorProcess, emulator_module
        emu = EmulatorProcess(emulator_module("velociroach"), ["--print-pty"], keep_log=True)
        emu.start()
        print(emu.proc.pid, emu.log_path, flush=True)
        time.sleep(600)
    """)
    parent = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    emu_pid = None
    try:
        pid, log = parent.stdout.readline().split()
        emu_pid = int(pid)
        assert _alive(emu_pid)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        wait_for(lambda: not _alive(emu_pid), 20, "the orphaned emulator to exit")
        assert "parent process is gone: exiting" in open(log).read()
        os.unlink(log)
    finally:
        if parent.poll() is None:
            parent.kill()
        if emu_pid is not None and _alive(emu_pid):
            os.kill(emu_pid, signal.SIGKILL)
