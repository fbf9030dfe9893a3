import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

# Tests share 2 cores with each other and with emulator processes.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    pass

# Credentials of the access-controlled rigs (configs/rigs/*: ~/.config/hilstack/<rig>.credentials,
# created by `hil up` when missing) go to a private HOME of this test session, never the user's:
# every test process, and every `hil` process a test starts, sees it. Caches stay where they were.
os.environ.setdefault("XDG_CACHE_HOME", str(Path.home() / ".cache"))
os.environ.pop("HIL_CREDENTIALS", None)
os.environ.pop("HIL_BUS_USER", None)
TEST_HOME = tempfile.mkdtemp(prefix="hil-test-home-")
os.environ["HOME"] = TEST_HOME
atexit.register(shutil.rmtree, TEST_HOME, ignore_errors=True)

# Parallel runs (pytest-xdist): a worker's processes draw their rig ports from the worker's own
# quarter of the range below the ephemeral ports (bus/ports.py), the tests' endpoints and the
# ports its demos, `hil` subprocesses and Ray tasks draw alike: two workers never draw one port.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:]
os.environ["HIL_PORT_SLOT"] = f"{int(_WORKER) % 4 if _WORKER.isdigit() else 0}/4"
# Ray (the sweep tests' local runtimes) joins a cluster it finds on the host when not told an
# address (RAY_ADDRESS, or the last `ray start` recorded in /tmp/ray): a test's never does, and
# keeps its session files in this process's own directory.
os.environ.pop("RAY_ADDRESS", None)
os.environ["RAY_TMPDIR"] = TEST_HOME


@pytest.fixture
def bus():
    """A private Zenoh rendezvous endpoint per test: tests never hear each other."""
    from hilstack.configs.schema import BusConfig
    from tests.helpers import free_port

    return BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}")


@pytest.fixture
def spawn():
    """Start `hil ...` subprocesses; killed at teardown if still running."""
    from tests.helpers import Proc

    procs = []

    def _spawn(*args: str):
        pr = Proc(list(args))
        procs.append(pr)
        return pr

    yield _spawn
    for pr in procs:
        if pr.p.poll() is None:
            pr.p.kill()
            pr.p.wait()


@pytest.fixture
def rig_bus():
    """``rig_bus("roach_emulated")``: that rig's bus (access control included) on a private
    endpoint, its credentials created in the session's HOME (tests/helpers.py: private_rig_bus)."""
    from tests.helpers import private_rig_bus

    return private_rig_bus
