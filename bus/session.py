"""Open a Zenoh session from a :class:`configs.BusConfig`.

Without ``bus.access`` every node is a peer (see :func:`zenoh_config`). With it
(bus/access.py) the rig is a star: the driver node (``server=True``) is a Zenoh router
that owns the rig's endpoint, authenticates every session and applies the rig's ACL;
every other node is a client of it with its credentials.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import socket
import time

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
    if bus.router is not None:  # the rig's own router (`hil router`): every node is its client
        c.insert_json5("mode", json.dumps("client"))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints", "[]")
        c.insert_json5("connect/endpoints", json.dumps([bus.router, *bus.connect]))
        c.insert_json5("connect/exit_on_failure", "false")
        c.insert_json5("connect/timeout_ms", "0")
        return c
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
        # a peer that failed to own the rendezvous joins whoever holds it: its Zenoh id says
        # which bus it came for, so the one that joined can tell a stranger (check_rendezvous)
        c.insert_json5("id", json.dumps(bus_id_prefix(bus.endpoint) + secrets.token_hex(12)))
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
    if server and bus.router is None:
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
    # a driver node of a rig with its own router (`hil router`) is a client as a drive user
    user = acc.drive[0] if server and access.USER_ENV not in os.environ else access.user_of(acc)
    if user not in creds:
        raise access.AccessError(f"credentials file {path} has no line for user {user!r} "
                                 f"(bus.access.user or {access.USER_ENV}); it has {sorted(creds)}")
    c.insert_json5("mode", json.dumps("client"))
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([bus.router or bus.endpoint, *bus.connect]))
    c.insert_json5("connect/exit_on_failure", "true")
    c.insert_json5("connect/timeout_ms", "5000")
    c.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    c.insert_json5("transport/auth/usrpwd/password", json.dumps(creds[user]))
    return c


def router_config(bus: BusConfig, rig: str, robots: list[str], tls: dict[str, str] | None = None) -> zenoh.Config:
    """The rig's own Zenoh router (``hil router``): listens on ``bus.router`` (and ``bus.listen``);
    with ``bus.access`` it authenticates every session and applies the rig's ACL, the driver
    nodes being its clients (``access.drive`` users). ``tls``: ``{"cert", "key", "ca"}`` file paths
    for ``tls/...`` endpoints (mutual TLS when ``ca`` is given)."""
    if bus.router is None:
        raise ValueError(f"rig {rig}: bus.router is not set (the endpoint `hil router` listens on)")
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps("router"))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([bus.router, *bus.listen]))
    c.insert_json5("listen/exit_on_failure", "true")
    c.insert_json5("connect/endpoints", "[]")
    if bus.access is not None:
        from hilstack.bus import access

        path = access.credentials_path(bus.access)
        access.read_credentials(path)  # refuses a missing or world-readable file
        c.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(path)))
        c.insert_json5("access_control", json.dumps(access.acl(rig, robots, bus.access, drivers=True)))
    if tls:
        c.insert_json5("transport/link/tls/listen_certificate", json.dumps(tls["cert"]))
        c.insert_json5("transport/link/tls/listen_private_key", json.dumps(tls["key"]))
        if tls.get("ca"):
            c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls["ca"]))
            c.insert_json5("transport/link/tls/enable_mtls", "true")
    return c


def _locator(endpoint: str) -> tuple[str, str, str]:
    """(protocol, address, port) of an endpoint, its host resolved, Zenoh's ``#``/``?`` parts dropped."""
    proto, _, addr = re.split(r"[#?]", endpoint, maxsplit=1)[0].partition("/")
    host, _, port = addr.rpartition(":")
    host = host.strip("[]")
    try:
        host = socket.getaddrinfo(host, None)[0][4][0]
    except (OSError, UnicodeError):
        pass
    return proto, host, port


def bus_id_prefix(endpoint: str) -> str:
    """The first 8 hex digits of the Zenoh id of every peer that came for the bus at ``endpoint``
    (a digest of the endpoint; the rest of the id is random, so ids stay unique)."""
    proto, host, port = _locator(endpoint)
    digest = int(hashlib.sha256(f"{proto}/{host}:{port}".encode()).hexdigest()[:8], 16)
    return f"{digest | 0x10000000:08x}"  # Zenoh refuses an id with a leading 0


def check_rendezvous(session: zenoh.Session, bus: BusConfig) -> None:
    """Refuse a peer session that joined a stranger at the rig's rendezvous endpoint.

    A peer's listen on ``bus.endpoint`` may fail (the port is taken) and is not fatal, since
    the rig's first node holds it and the others connect to it; but the holder may be any Zenoh
    session of this host (another rig's ephemeral listener, a plain ``zenohd``), and joining it
    puts this node on that stranger's bus (its commands, its e-stops, none of its own rig's
    nodes). The link this session opened to the endpoint names the holder's Zenoh id: a peer
    that came for the same bus carries :func:`bus_id_prefix` of the endpoint. One look at the
    session's links, no message exchanged: a holder with another id is :class:`BusUnavailable`
    and the session is closed."""
    want = _locator(bus.endpoint)
    mine = bus_id_prefix(bus.endpoint)
    for link in session.info.links():
        if _locator(str(link.dst)) != want:
            continue
        holder = str(link.zid)
        if not holder.startswith(mine):
            session.close()
            raise BusUnavailable(
                f"the rig's endpoint {bus.endpoint} is held by a Zenoh session that did not come for this bus "
                f"(id {holder}: another rig's or program's on this host); refusing to join it: stop that "
                "process or give the rig a free bus.endpoint")


def rendezvous_listened(bus: BusConfig | None) -> bool:
    """Something listens at the bus's rendezvous (its router, else its endpoint) now (tcp only):
    a session opened next will link to it, not hold it itself."""
    bus = bus or BusConfig()
    proto, host, port = _locator(bus.router or bus.endpoint)
    if proto != "tcp" or not port.isdigit():
        return False
    try:
        with socket.create_connection((host, int(port)), timeout=0.5):
            return True
    except OSError:
        return False


def wait_linked(session: zenoh.Session, bus: BusConfig | None, timeout_s: float = 5.0) -> bool:
    """Wait (bounded) until ``session`` has its link to the bus's rendezvous (a peer's connect
    runs in the background: right after opening, the rig's nodes may not be known yet, and a
    liveliness query then sees none of them). True once linked."""
    bus = bus or BusConfig()
    want = _locator(bus.router or bus.endpoint)
    deadline = time.monotonic() + timeout_s
    while True:
        if any(_locator(str(link.dst)) == want for link in session.info.links()):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)


def _ephemeral(endpoint: str) -> str:
    proto, _, addr = endpoint.partition("/")
    host = addr.rsplit(":", 1)[0] if ":" in addr else addr
    return f"{proto}/{host}:0"


def open_session(bus: BusConfig | None = None, server: bool = False, rig: str | None = None,
                 robots: list[str] | None = None) -> zenoh.Session:
    """A session on the rig's bus. On an access rig a failure to open is :class:`BusUnavailable`
    (one line naming the endpoint and, for a client, the user); so is, for a peer, a rendezvous
    endpoint held by a stranger (:func:`check_rendezvous`)."""
    cfg = zenoh_config(bus, server, rig, robots)
    if bus is None or bus.access is None:
        s = zenoh.open(cfg)
        bus = bus or BusConfig()
        if bus.router is None and bus.mode == "peer":
            check_rendezvous(s, bus)
        return s
    try:
        return zenoh.open(cfg)
    except Exception as e:  # zenoh.ZError; the message ends with a Rust source location
        why = re.split(r"\s+at /", str(e), maxsplit=1)[0].strip()
        if server and bus.router is None:
            raise BusUnavailable(f"rig {rig}: cannot own its endpoint {bus.endpoint} ({why}); another process "
                                 "holds it (another rig on this host? give each rig its own bus.endpoint)") from None
        from hilstack.bus.access import user_of

        raise BusUnavailable(f"cannot join the rig at {bus.endpoint} as user {user_of(bus.access)!r}: no driver "
                             f"node listening there, or it refused these credentials ({why})") from None
