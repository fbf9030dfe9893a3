import os

import pytest

# Tests share 2 cores with each other and with emulator processes.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    pass


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
