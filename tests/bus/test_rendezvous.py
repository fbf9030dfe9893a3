"""A peer whose rendezvous endpoint is held by a stranger refuses to join it (bus/session.py)."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from hilstack.bus.node import Node
from hilstack.bus.session import BusUnavailable, bus_id_prefix, open_session
from hilstack.configs.schema import BusConfig
from tests.helpers import free_port


def _plain_peer(endpoint: str) -> zenoh.Session:
    """A Zenoh session of another program holding ``endpoint`` (as a `zenohd` or another tool would)."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    return zenoh.open(c)


def _wait(cond, timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_a_stranger_holding_the_endpoint_is_refused_in_one_line(bus):
    stranger = _plain_peer(bus.endpoint)
    try:
        with pytest.raises(BusUnavailable) as e:
            open_session(bus)
        msg = str(e.value)
        assert "\n" not in msg and bus.endpoint in msg and str(stranger.info.zid()) in msg
        assert "did not come for this bus" in msg
        # the refused session is closed: the stranger is left with no peer
        assert _wait(lambda: not list(stranger.info.peers_zid()))
        # so is a node of the rig (hil up, hil mpc...: every node opens its session this way)
        with pytest.raises(BusUnavailable, match="did not come for this bus"):
            Node("mpc", "rig_a", bus=bus, handle_signals=False)
    finally:
        stranger.close()


def test_another_rigs_node_on_the_port_is_a_stranger_too(bus):
    """Another rig's node whose own listener took this rig's port (the hazard on a busy host)."""
    other = BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}", listen=[bus.endpoint])
    s_other = open_session(other)
    try:
        with pytest.raises(BusUnavailable, match="did not come for this bus"):
            open_session(bus)
    finally:
        s_other.close()


def test_peers_of_the_same_bus_join_the_first_and_hear_it(bus):
    first = open_session(bus)
    second = open_session(bus)  # its listen on the endpoint fails: it joins the first, as designed
    try:
        assert str(first.info.zid()).startswith(bus_id_prefix(bus.endpoint))
        assert [str(z) for z in second.info.peers_zid()] == [str(first.info.zid())]
        got: list[bytes] = []
        sub = second.declare_subscriber("hil/t/x", lambda s: got.append(s.payload.to_bytes()))
        assert _wait(lambda: (first.put("hil/t/x", b"hi"), bool(got))[1], 5.0)
        sub.undeclare()
    finally:
        second.close()
        first.close()
    # the same endpoint spelt with a host name is the same bus; another port is another
    port = bus.endpoint.rsplit(":", 1)[1]
    assert bus_id_prefix(f"tcp/localhost:{port}") == bus_id_prefix(bus.endpoint)
    assert bus_id_prefix(f"tcp/127.0.0.1:{int(port) + 1}") != bus_id_prefix(bus.endpoint)


def test_a_session_can_wait_for_its_link_to_a_listening_rig():
    """What replay's live-driver check relies on (bus/recording.py): it knows a rig listens at
    the endpoint before it opens its session, and waits for the link before it asks the rig
    which driver nodes are alive (a background connect may take longer than the check)."""
    from hilstack.bus.session import rendezvous_listened, wait_linked

    bus = BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}")
    assert not rendezvous_listened(bus)  # nothing there: a session opened next holds it itself
    holder = open_session(bus)
    try:
        assert rendezvous_listened(bus)
        s = open_session(bus)
        try:
            assert wait_linked(s, bus, 10.0)
        finally:
            s.close()
        assert not wait_linked(holder, bus, 0.1)  # the holder has no link to its own endpoint
    finally:
        holder.close()


def test_a_node_that_asks_to_join_is_linked_to_the_rig_when_constructed():
    """A recorder or viewer (`join_wait_s`) starts its `--seconds` only once linked to a rig that
    listens at the endpoint."""
    from hilstack.bus.session import wait_linked

    bus = BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}")
    holder = Node("driver-x", "join_rig", bus, handle_signals=False)
    try:
        n = Node("viewer", "join_rig", bus, handle_signals=False, join_wait_s=10.0)
        try:
            assert wait_linked(n.session, bus, 0.0)  # linked already, no further wait
        finally:
            n.close()
    finally:
        holder.close()
