"""The driver contract, run over every backend of every robot.

Swappable backends are a tested property: each entry of CONTRACT_BACKENDS builds a
driver from config alone (``backend: ...``) and must pass every test here.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from drivers.base import CommandError, Lifecycle, LifecycleError
from drivers.registry import make_driver
from tests.helpers import free_port

# (robot config, backend, param overrides)
CONTRACT_BACKENDS = [
    ("pointmass", "sim", {}),
    ("velociroach", "sim", {}),
    ("velociroach", "emulated", {}),
    ("mocap", "real", {"source": "udp"}),  # the real UDP client, fed by a pose stream below
    # the arm starts held mid-range and moves slowly: 200 periods at the velocity limit must
    # not reach a joint limit, where the driver's joint-limit guard zeroes the command
    ("widowx", "sim", {"max_joint_vel_rad_s": 0.05, "sim": {"start_holding": {"shoulder": -0.5, "elbow": 0.5}}}),
    ("widowx", "emulated", {"max_joint_vel_rad_s": 0.05,
                            "emulator": {"start_holding": {"shoulder": -0.5, "elbow": 0.5}}}),
    ("reset_mechanism", "sim", {}),
    ("reset_mechanism", "emulated", {}),
    ("sawyer", "sim", {}),
    ("sawyer", "emulated", {"joint_states_stale_s": 0.5}),  # 100 Hz stream from a process on a loaded CPU
]


def _pose_stream(port: int, stop: threading.Event) -> None:
    """A mocap system on loopback: a rigid body moving along x, 500 Hz, stamped on its clock."""
    import time

    from drivers.mocap.udp import PoseStreamServer

    t0 = time.monotonic()
    with PoseStreamServer("127.0.0.1", port, body_id=1) as srv:
        while not stop.wait(0.002):
            t = time.monotonic() - t0
            srv.send(t, [0.1 * t, 0.0, 0.05], [1.0, 0.0, 0.0, 0.0])


@pytest.fixture(params=CONTRACT_BACKENDS, ids=lambda p: f"{p[0]}-{p[1]}")
def driver(request):
    robot, backend, params = request.param
    stop = threading.Event()
    if robot == "mocap":
        port = free_port()
        params = {**params, "port": port}
        threading.Thread(target=_pose_stream, args=(port, stop), daemon=True).start()
    d = make_driver(robot, backend=backend, **params)
    yield d
    stop.set()
    d.cleanup()


def test_spec_readable_before_connecting(driver):
    sp = driver.spec
    assert driver.lifecycle is Lifecycle.UNCONFIGURED
    assert sp.state.dim == len(sp.state.names) == len(sp.state.units) > 0
    # sensors (mocap, cameras) have no action channels; actuators have finite limits
    assert np.all(np.isfinite(sp.action.low)) and np.all(np.isfinite(sp.action.high))
    assert sp.period_s > 0


def test_lifecycle_and_refusals(driver):
    with pytest.raises(LifecycleError):
        driver.read()
    with pytest.raises(LifecycleError):
        driver.write(np.zeros(driver.spec.action.dim))
    driver.configure()
    assert driver.lifecycle is Lifecycle.CONFIGURED
    obs = driver.read()
    assert obs.state.shape == (driver.spec.state.dim,)
    assert np.all(np.isfinite(obs.state))
    with pytest.raises(LifecycleError, match="activate"):
        driver.write(np.zeros(driver.spec.action.dim))
    driver.activate()
    assert driver.active
    driver.deactivate()
    assert driver.lifecycle is Lifecycle.CONFIGURED
    driver.cleanup()
    assert driver.lifecycle is Lifecycle.UNCONFIGURED


def test_write_validates_clamps_and_rate_limits(driver):
    sp = driver.spec
    with driver:
        n = sp.action.dim
        with pytest.raises(CommandError, match="shape"):
            driver.write(np.zeros(n + 1))
        if n == 0:  # a sensor: the empty action is the only valid one
            assert driver.write(np.zeros(0)).shape == (0,)
            return
        bad = np.zeros(n)
        bad[0] = np.nan
        with pytest.raises(CommandError, match=sp.action.names[0]):
            driver.write(bad)
        with pytest.raises(CommandError):
            driver.write(["a"] * n)
        # far out of range: clamped to limits and by the rate limit from the held command
        held = driver.held_command
        applied = driver.write(sp.action.high * 100)
        assert np.all(applied <= sp.action.high + 1e-12)
        if sp.action_rate_per_s is not None:
            assert np.all(np.abs(applied - held) <= sp.action_rate_per_s * sp.period_s * 1.0001 + 1e-9)
        # held long enough, a command reaches the limit and no further
        for _ in range(200):
            applied = driver.write(sp.action.high * 100)
            driver.tick()
        np.testing.assert_allclose(applied, sp.action.high)


def test_activation_holds_measured_command(driver):
    with driver:
        assert driver.held_command is not None
        assert np.all(np.isfinite(driver.held_command))


def test_stop_and_context_manager_cleanup(driver):
    with driver:
        driver.write(driver.spec.action.high)  # the limit itself (empty for sensors)
        driver.tick()
        driver.stop()
        if driver.spec.safe_action is not None:
            np.testing.assert_allclose(driver.held_command, driver.spec.safe_action)
    assert driver.lifecycle is Lifecycle.UNCONFIGURED


def test_time_advances_with_tick(driver):
    with driver:
        t0 = driver.read().t_s
        for _ in range(3):
            driver.tick()
        t1 = driver.read().t_s
        assert t1 - t0 >= 2.5 * driver.spec.period_s * 0.9


def test_health(driver):
    with driver:
        for _ in range(20):  # a streamed sensor is healthy once its first samples arrived
            if driver.health().ok:
                break
            driver.tick()
        h = driver.health()
        assert h.ok
        assert h.corrupt_frames == 0
        d = h.to_dict()
        assert "link_quality" in d
