import pytest


@pytest.fixture(scope="module")
def scene():
    """One rendered hand scene with the stereo pair, shared by a module's tests."""
    from hilstack.sim_backends.shadow_hand.cameras import HandCameraScene

    s = HandCameraScene()
    yield s
    s.close()
