"""A node's liveliness token goes out once the node is built: a peer that acts on seeing it is heard.

The driver node leaves reset requests to the supervisor once it sees the supervisor's token; a
token declared before the supervisor's subscriptions let a request sent in between go unheard by
both (at start-up, on a loaded machine).
"""

from __future__ import annotations

import threading
import time

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.schemas import ResetEvent, ResetPhase
from hilstack.configs.schema import load_rig
from hilstack.control.reset.config import require_reset
from hilstack.control.reset.supervisor import ResetSupervisor

RIG = "alivetest"


class _SendOnSight:
    """A peer that sends one reset request the moment it sees ``node``'s token appear (its own thread)."""

    def __init__(self, bus, rig: str, node: str):
        self.peer = Node("peer", rig, bus, handle_signals=False)
        self.pub = self.peer.publisher(keys.reset(rig, "request"), ResetEvent, reliable=True)
        self.sent_at = 0.0
        # the product's watch (history: a token that reaches the router before this watch's
        # interest does, on a loaded machine, is still seen), polled every millisecond: the
        # node under test takes 0.5 s between its base and its subscriptions
        self._watch = self.peer.watch_alive(node)
        self._th = threading.Thread(target=self._send, daemon=True)
        self._th.start()

    def _send(self) -> None:
        deadline = time.monotonic() + 30
        while self._watch.alive is not True and time.monotonic() < deadline:
            time.sleep(0.001)
        if self._watch.alive:
            self.sent_at = time.monotonic()  # before the put: the node may have it before put returns
            self.pub.put(ResetEvent(robot="roach", phase=ResetPhase.REQUEST))

    def close(self) -> None:
        self._th.join(5)
        self._watch.close()
        self.peer.close()


class _SlowToSubscribe(Node):
    def __init__(self, bus):
        super().__init__("slow", RIG, bus, handle_signals=False)
        time.sleep(0.5)  # construction work between the base and the subscriptions (a loaded machine)
        self.inbox = self.subscribe(keys.reset(RIG, "request"), ResetEvent, latest=False)


def test_a_node_is_alive_only_once_its_subscriptions_are_declared(bus):
    peer = _SendOnSight(bus, RIG, "slow")
    try:
        time.sleep(0.3)  # the peer's liveliness subscriber is declared on the bus
        with _SlowToSubscribe(bus) as node:
            got = node.inbox.wait(5.0)
            assert peer.sent_at > 0, "the peer never saw the node alive"
            assert got is not None and got.phase == ResetPhase.REQUEST, \
                "a request sent on first sight of the node was lost: its token came before its subscription"
    finally:
        peer.close()


def test_the_reset_supervisor_hears_a_request_sent_the_moment_it_appears(bus):
    cfg = require_reset(load_rig("roach_emulated"), "roach")
    peer = _SendOnSight(bus, "roach_emulated", keys.RESET_SUPERVISOR_NODE)
    try:
        time.sleep(0.3)
        with ResetSupervisor("roach_emulated", cfg, bus, handle_signals=False) as sup:
            deadline = time.monotonic() + 5.0
            while sup.stats["requested"] == 0 and time.monotonic() < deadline:
                sup._take_requests()
                time.sleep(0.05)
            assert peer.sent_at > 0
            assert sup.stats["requested"] == 1
    finally:
        peer.close()


def test_a_node_whose_constructor_fails_is_never_alive(bus):
    class Broken(Node):
        def __init__(self, bus):
            super().__init__("broken", RIG, bus, handle_signals=False)
            self.close()
            raise ValueError("bad config")

    with Node("watcher", RIG, bus, handle_signals=False) as w:
        watch = w.watch_alive("broken")
        try:
            Broken(bus)
        except ValueError:
            pass
        time.sleep(0.5)
        assert watch.alive is None
