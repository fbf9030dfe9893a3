"""Open a Zenoh session from a :class:`configs.BusConfig`.

Without ``bus.access`` every node is a peer (see :func:`zenoh_config`). With it
(bus/access.py) the rig is a star: the driver node (``server=True``) is a Zenoh router
that owns the rig's endpoint, authenticates every session and applies the rig's ACL;
every other node is a client of it with its credentials.
"""

from __future__ import annotations

import json
import re

import zenoh

from hilstack.configs.schema import BusConfig


class BusUnavailable(RuntimeError):
    """The session cannot open (endpoint taken, router absent, credentials refused): one line."""


def zenoh_config(bus: BusConfig | None = None, server: bool = False, rig: str | None = None,
                 robots: list[str] | None = None) -> zenoh.Config:
    """``server`` (access rigs only): the rig's router; needs ``rig`` and its ``robots`` for the ACL."""
    bus = bus or BusConfig()
    if bus.access is not None:
        return _access_config(bus, server, rig, robots or [])
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


def _access_config(bus: BusConfig, server: bool, rig: str | None, robots: list[str]) -> zenoh.Config:
    from hilstack.bus import access

    acc = bus.access
    assert acc is not None
    path = access.credentials_path(acc)
    creds = access.read_credentials(path)  # refuses a missing or world-readable file
    c = zenoh.Config()
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    if server:
        if rig is None:
            raise ValueError("the rig's router needs the rig name")
        c.insert_json5("mode", json.dumps("router"))
        # owns the endpoint or fails: a node that joined someone else's listener could not
        # tell who sends it commands (Zenoh authenticates the side that connects)
        c.insert_json5("listen/endpoints", json.dumps([bus.endpoint, *bus.listen]))
        c.insert_json5("listen/exit_on_failure", "true")
        c.insert_json5("connect/endpoints", "[]")
        c.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(path)))
        c.insert_json5("access_control", json.dumps(access.acl(rig, robots, acc)))
        return c
    user = access.user_of(acc)
    if user not in creds:
        raise access.AccessError(f"credentials file {path} has no line for user {user!r} "
                                 f"(bus.access.user or {access.USER_ENV}); it has {sorted(creds)}")
    c.insert_json5("mode", json.dumps("client"))
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([bus.endpoint, *bus.connect]))
    c.insert_json5("connect/exit_on_failure", "true")
    c.insert_json5("connect/timeout_ms", "5000")
    c.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    c.insert_json5("transport/auth/usrpwd/password", json.dumps(creds[user]))
    return c


def _ephemeral(endpoint: str) -> str:
    proto, _, addr = endpoint.partition("/")
    host = addr.rsplit(":", 1)[0] if ":" in addr else addr
    return f"{proto}/{host}:0"


def open_session(bus: BusConfig | None = None, server: bool = False, rig: str | None = None,
                 robots: list[str] | None = None) -> zenoh.Session:
    """A session on the rig's bus. On an access rig a failure to open is :class:`BusUnavailable`
    (one line naming the endpoint and, for a client, the user)."""
    cfg = zenoh_config(bus, server, rig, robots)
    if bus is None or bus.access is None:
        return zenoh.open(cfg)
    try:
        return zenoh.open(cfg)
    except Exception as e:  # zenoh.ZError; the message ends with a Rust source location
        why = re.split(r"\s+at /", str(e), maxsplit=1)[0].strip()
        if server:
            raise BusUnavailable(f"rig {rig}: cannot own its endpoint {bus.endpoint} ({why}); another process "
                                 "holds it (another rig on this host? give each rig its own bus.endpoint)") from None
        from hilstack.bus.access import user_of

        raise BusUnavailable(f"cannot join the rig at {bus.endpoint} as user {user_of(bus.access)!r}: no driver "
                             f"node listening there, or it refused these credentials ({why})") from None
