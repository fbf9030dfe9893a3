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
def tmp_out(tmp_path):
    return tmp_path
