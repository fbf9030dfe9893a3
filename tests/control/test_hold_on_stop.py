"""A position-controlled robot's stop holds its last target: no jump to a measured pose."""

from __future__ import annotations

import numpy as np

from hilstack.drivers.shadow_hand.config import ACT_INDEX, ShadowHandParams, to_action
from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim


def test_hand_stop_keeps_the_firmware_target_it_was_sent():
    """The hand sim (its firmware at 1 kHz): after a rate-limited move, ``stop()`` leaves the
    firmware's targets where the last command put them. It used to replace them with the
    measured angles at once, a jump of the tracking error (0.2 rad here, and all of the way
    back to a stale pose on a link whose telemetry stopped) with no rate limit."""
    sim = ShadowHandSim(ShadowHandParams())
    try:
        with sim:
            for _ in range(3):
                sim.tick()
            target = sim.held_command.copy()
            target[[3, 12]] = 1.0  # FFJ2 and LFJ3 curl as far as they go
            for _ in range(3):
                applied = sim.write(target)
                sim.tick()
            fw_before = sim.firmware.target_rad.copy()
            measured = to_action(sim.read().state[ACT_INDEX])
            assert np.abs(measured - applied).max() > 0.05  # the stop has something to jump over
            sim.stop()
            np.testing.assert_allclose(sim.held_command, applied, atol=1e-12)
            np.testing.assert_allclose(sim.firmware.target_rad, fw_before, atol=1e-9)
            # the rate limit restarts from the held target
            back = sim.write(-np.ones_like(applied))
            assert np.abs(back - applied).max() <= 4.0 * 0.1 + 1e-9
    finally:
        sim.cleanup()
