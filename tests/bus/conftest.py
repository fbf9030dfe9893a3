import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from configs.schema import BusConfig

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def bus() -> BusConfig:
    return BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}")


class Proc:
    def __init__(self, args: list[str]):
        self.p = subprocess.Popen(
            [sys.executable, "-m", "tools.cli", *args],
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


@pytest.fixture
def spawn():
    procs: list[Proc] = []

    def _spawn(*args: str) -> Proc:
        pr = Proc(list(args))
        procs.append(pr)
        return pr

    yield _spawn
    for pr in procs:
        if pr.p.poll() is None:
            pr.p.kill()
            pr.p.wait()


def wait_for(cond, timeout_s: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")
