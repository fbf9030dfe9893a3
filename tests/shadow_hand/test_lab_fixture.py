"""The hand's lab fixture (drivers/fixture.py, op ``place``): the lab's hands put the Baoding
balls back at rest in the palm, the reset of `hand_emulated` (step `lab_place`, docs/reset.md)."""

from __future__ import annotations

import socket
import time

import numpy as np

from hilstack.drivers.fixture import FixtureClient
from hilstack.drivers.shadow_hand.config import ShadowHandParams
from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim
from hilstack.sim_backends.shadow_hand.emulator import LabFixture


def _reply(client: FixtureClient, fixture: LabFixture) -> dict:
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        fixture.poll()
        r = client.reply()
        if r is not None:
            return r
        time.sleep(0.005)
    raise AssertionError("no reply from the lab fixture")


def test_the_fixture_puts_dropped_balls_back_at_rest_in_the_palm_and_refuses_other_ops():
    sim = ShadowHandSim(ShadowHandParams(objects_in_state=True))
    sim.configure()
    sim.reset()
    rest = sim.balls_m().copy()
    sim.advance(0.5)
    q_hand = sim.joint_state()[0].copy()
    # the balls dropped off the hand
    h = sim.hand
    for adr in h.ball_qpos_adr:
        sim.data.qpos[adr:adr + 3] += (0.0, 0.0, -0.3)
    sim.advance(0.2)
    assert np.all(sim.balls_m()[:, 2] < rest[:, 2] - 0.05)  # on the floor below the hand
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    fixture, client = LabFixture(sim, sock), FixtureClient(sock.getsockname()[1])
    try:
        client.request("right")  # the roach's op: not the hand's
        r = _reply(client, fixture)
        assert not r["ok"] and "unknown op 'right'; known: ['place']" in r["detail"] and fixture.placements == 0
        client.request("place")
        r = _reply(client, fixture)
        assert r["ok"] and r["acted"] and fixture.placements == 1
    finally:
        client.close()
        sock.close()
    # where the reset puts them (the hand is at its hold pose), at rest; the hand not moved
    np.testing.assert_allclose(sim.balls_m(), rest, atol=5e-3)  # in the palm as it is now (the hand settled)
    for da in h.ball_dof_adr:
        assert np.all(sim.data.qvel[da:da + 6] == 0.0)
    np.testing.assert_allclose(sim.joint_state()[0], q_hand, atol=0.05)
    sim.advance(1.0)  # and they stay in the palm
    assert np.all(np.linalg.norm(sim.balls_m() - rest, axis=1) < 0.02)
