"""The driver contract, run over every backend of every robot.

Swappable backends are a tested property: each entry of CONTRACT_BACKENDS builds a
driver from config alone (``backend: ...``) and must pass every test here.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.base import CommandError, Lifecycle, LifecycleError
from drivers.registry import make_driver

# (robot config, backend, param overrides)
CONTRACT_BACKENDS = [
    ("pointmass", "sim", {}),
    ("velociroach", "sim", {}),
    ("velociroach", "emulated", {}),
]


@pytest.fixture(params=CONTRACT_BACKENDS, ids=lambda p: f"{p[0]}-{p[1]}")
def driver(request):
    robot, backend, params = request.param
    d = make_driver(robot, backend=backend, **params)
    yield d
    d.cleanup()


def test_spec_readable_before_connecting(driver):
    sp = driver.spec
    assert driver.lifecycle is Lifecycle.UNCONFIGURED
    assert sp.state.dim == len(sp.state.names) == len(sp.state.units) > 0
    assert sp.action.dim > 0 and np.all(np.isfinite(sp.action.low)) and np.all(np.isfinite(sp.action.high))
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
        driver.write(driver.spec.action.high)
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
        h = driver.health()
        assert h.ok
        assert h.corrupt_frames == 0
        d = h.to_dict()
        assert "link_quality" in d
