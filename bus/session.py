"""Open a Zenoh session from a :class:`configs.BusConfig`."""

from __future__ import annotations

import json

import zenoh

from hilstack.configs.schema import BusConfig


def zenoh_config(bus: BusConfig | None = None) -> zenoh.Config:
    bus = bus or BusConfig()
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(bus.mode))
    c.insert_json5("scouting/multicast/enabled", json.dumps(bus.multicast_scouting))
    c.insert_json5("scouting/gossip/enabled", json.dumps(bus.gossip))
    listen = list(bus.listen)
    connect = list(bus.connect)
    if bus.mode == "peer":
        # The first node owns the rendezvous port; the others connect to it. Every node
        # also listens on an ephemeral port of the same host, so that peers that learn
        # of each other by gossip can link directly (peers do not route for others).
        listen = [bus.endpoint, _ephemeral(bus.endpoint), *listen]
        connect = [bus.endpoint, *connect]
        c.insert_json5("listen/exit_on_failure", "false")
    elif not connect:
        connect = [bus.endpoint]
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    # never block start-up on an absent peer/router: connect in the background
    c.insert_json5("connect/exit_on_failure", "false")
    c.insert_json5("connect/timeout_ms", "0")
    return c


def _ephemeral(endpoint: str) -> str:
    proto, _, addr = endpoint.partition("/")
    host = addr.rsplit(":", 1)[0] if ":" in addr else addr
    return f"{proto}/{host}:0"


def open_session(bus: BusConfig | None = None) -> zenoh.Session:
    return zenoh.open(zenoh_config(bus))
