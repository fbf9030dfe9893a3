"""Test helpers: free ports, `hil` subprocesses, waiting on conditions."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A port below the OS's ephemeral range (hilstack.bus.ports), each pytest-xdist worker
    drawing from its own quarter of it (``HIL_PORT_SLOT``, set by tests/conftest.py)."""
    from hilstack.bus.ports import free_port as _free_port

    return _free_port()


class Proc:
    def __init__(self, args: list[str]):
        self.p = subprocess.Popen(
            [sys.executable, "-m", "hilstack.tools.cli", *args],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )

    def stop(self, timeout: float = 10.0) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
        try:
            return self.p.wait(timeout)
        except subprocess.TimeoutExpired:
            self.p.kill()
            raise


def wait_or_dump(p: subprocess.Popen, timeout_s: float, what: str = "the process") -> int:
    """``p.wait(timeout_s)``; past it, every process of ``p``'s tree prints its stacks
    (SIGUSR1: bus/lifetime.dump_stacks_on_signal) before it is killed, and the test fails with
    ``p``'s stderr (where a stop hung, instead of a bare timeout). ``p`` has stderr=PIPE."""
    import psutil
    import pytest

    try:
        return p.wait(timeout_s)
    except subprocess.TimeoutExpired:
        tree = [p.pid] + [c.pid for c in psutil.Process(p.pid).children(recursive=True)]
        for pid in tree:
            try:
                os.kill(pid, signal.SIGUSR1)
            except ProcessLookupError:
                pass
        time.sleep(1.0)
        for pid in reversed(tree):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        _, err = p.communicate(timeout=30)
        pytest.fail(f"{what} still running {timeout_s:g} s after the signal; stderr with its stacks:\n{err[-8000:]}")


def wait_for(cond, timeout_s: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


def _readline_within(p: subprocess.Popen, timeout_s: float) -> str:
    """One line of ``p``'s stdout, or "" at EOF or after ``timeout_s``."""
    import selectors

    with selectors.DefaultSelector() as sel:
        sel.register(p.stdout, selectors.EVENT_READ)
        if not sel.select(timeout_s):
            return ""
    return p.stdout.readline()


def hil_drive_with_device_signal(robot: str, emulator_module: str, sig: int, timeout_s: float = 120.0,
                                 settle_s: float = 1.5) -> subprocess.CompletedProcess:
    """``hil drive ROBOT --backend emulated`` for long; once the driver is active and driving
    (its "driving for" line on stdout), then ``settle_s`` more, its emulator process gets
    ``sig`` (SIGSTOP: frozen; SIGKILL: dead). Returns the finished ``hil drive``.
    A frozen emulator is continued and killed afterwards if it is still there.

    The driver's own line is the readiness signal: activity of the emulator process (bytes
    it reads) also counts its imports, so a freeze could land before it serves the link."""
    p = subprocess.Popen([sys.executable, "-m", "hilstack.tools.cli", "drive", robot, "--backend", "emulated",
                          "--seconds", "600"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    emu = None
    try:
        def child() -> int | None:
            kids = Path(f"/proc/{p.pid}/task/{p.pid}/children").read_text().split()
            for k in kids:
                if emulator_module in Path(f"/proc/{k}/cmdline").read_bytes().decode(errors="replace"):
                    return int(k)
            return None

        # blocks until the line (or EOF: hil drive failed before driving); `timeout_s` bounds it
        line = _readline_within(p, timeout_s)
        assert "driving for" in line, (line, p.poll(), p.poll() is not None and p.communicate())
        emu = child()
        assert emu is not None, f"{robot}'s emulator process is not a child of hil drive"
        time.sleep(settle_s)
        assert p.poll() is None, p.communicate()
        os.kill(emu, sig)
        out, err = p.communicate(timeout=timeout_s)
        return subprocess.CompletedProcess(p.args, p.returncode, out, err)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        if emu is not None:
            for s in (signal.SIGCONT, signal.SIGKILL):
                try:
                    os.kill(emu, s)
                except ProcessLookupError:
                    break


def private_rig_bus(rig: str):
    """A rig config's bus (its access control included) on a private endpoint, with the rig's
    credentials created when missing, as `hil up` does (in the test session's HOME:
    tests/conftest.py). Nodes built in-process on an emulated rig use this, not a plain BusConfig."""
    from hilstack.tools.common import provision_credentials, rig_bus

    name, bus, cfg = rig_bus(rig, f"tcp/127.0.0.1:{free_port()}", need_config=True)
    provision_credentials(name, bus, cfg)
    return bus


def wait_rig_router(bus, timeout_s: float = 90.0) -> None:
    """On an access rig: until its driver node (the rig's router) admits this process's credentials.
    A client on an access rig needs the router up when it opens (bus/session.py)."""
    if bus.access is None:
        return
    from hilstack.bus.session import BusUnavailable, open_session

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            open_session(bus).close()
            return
        except BusUnavailable:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def spec_dict(name: str, state: list[str], action: list[str], low: float | list[float] = -1.0,
              high: float | list[float] = 1.0, period_s: float = 0.1, **kw) -> dict:
    """A complete robot spec as it crosses the bus (``RobotSpec.to_dict()``), for tests that
    write or publish one by hand: unbounded states, actions in ``[low, high]``."""
    import numpy as np

    from hilstack.drivers.base import RobotSpec, Space

    n = len(action)
    lo, hi = np.broadcast_to(np.asarray(low, float), (n,)), np.broadcast_to(np.asarray(high, float), (n,))
    return RobotSpec(name, Space.build([(s, "", -np.inf, np.inf) for s in state]),
                     Space.build([(a, "", lo[i], hi[i]) for i, a in enumerate(action)]), period_s, **kw).to_dict()


def rig_pacing(rig_name, robot):
    """The pacing a rig's driver node runs ``robot`` in (and publishes in its spec)."""
    from hilstack.configs.schema import load_rig, rig_robot_config
    from hilstack.drivers.base import Pacing

    rig = load_rig(rig_name)
    return Pacing.of_backend(rig_robot_config(rig, robot).backend, rig.pace)
