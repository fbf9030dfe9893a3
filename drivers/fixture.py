"""The lab fixture: what puts a robot that lies on its back back onto its legs.

On a real VelociRoACH rig that is a person (or a mechanical fixture); the robot cannot
right itself from its back (docs/reset.md, "Measured on this rig"). The firmware
emulator stands in for it with a small **lab-fixture service** beside the robot: a
separate system, like the mocap stream, not the robot's radio protocol. The reset
supervisor calls it from its ``lab_fixture`` step only when its own ``self_right`` step
failed, and counts each use (``resets.fixture_recoveries`` in a demo's report.json:
every one is an operator intervention on a real rig).

Wire format: one JSON object per UDP datagram on loopback (the emulator's port is in its
ready line and in the emulated driver's health, ``lab_fixture_port``):

- request ``{"op": "right", "id": N}``: put the robot upright where it lies (same x, y and
  heading), at rest, standing on its legs;
- reply ``{"id": N, "ok": true, "acted": bool, "detail": "..."}``: ``acted`` is false when
  the robot already stood upright (nothing was touched);
- request ``{"op": "place", "id": N}`` (the Shadow Hand's emulator): put the objects back in
  place, the Baoding balls at rest in the palm (the hand is not touched); ``acted`` true.

A bad request is answered ``{"ok": false, "detail": "<what is wrong>"}``.
"""

from __future__ import annotations

import json
import socket
from typing import Any

#: the largest datagram either side sends or accepts [bytes]
MAX_DATAGRAM = 512
#: the fixture's operations: right a robot (the roach), put the objects back (the hand's balls)
OPS = ("right", "place")


def encode(msg: dict[str, Any]) -> bytes:
    return json.dumps(msg, separators=(",", ":")).encode()


def decode_request(data: bytes, ops: tuple[str, ...] = OPS) -> tuple[dict[str, Any] | None, str]:
    """(request, '') or (None, why it is not a valid request); ``ops``: the operations this
    fixture serves (the roach's rights a robot, the hand's places the balls: neither does the other's)."""
    try:
        m = json.loads(data.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        return None, f"not JSON: {e}"
    if not isinstance(m, dict):
        return None, "not a JSON object"
    if m.get("op") not in ops:
        return None, f"unknown op {m.get('op')!r}; known: {list(ops)}"
    if not isinstance(m.get("id", 0), int):
        return None, f"id must be an integer, got {m.get('id')!r}"
    return m, ""


def refusal(data: bytes, why: str) -> dict[str, Any]:
    """The answer to a bad request; it carries the request's id when it had one, so a
    :class:`FixtureClient` that asked for an operation this fixture does not serve hears why."""
    out: dict[str, Any] = {"ok": False, "detail": f"bad lab-fixture request: {why}"}
    try:
        m = json.loads(data.decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        return out
    if isinstance(m, dict) and isinstance(m.get("id"), int):
        out["id"] = m["id"]
    return out


def service_socket(port: int) -> tuple[Any, int]:
    """A non-blocking UDP socket on loopback for a fixture service, and the port it got (0: any)."""
    import socket

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.setblocking(False)
    return sock, sock.getsockname()[1]


class FixtureService:
    """The service side, on an emulator's simulated world: :meth:`poll` (non-blocking, from
    the emulator's loop) answers every pending request on ``sock``; a subclass names its
    ``ops`` and does the work in :meth:`act`. ``sock`` None: the placing code without a service."""

    ops: tuple[str, ...] = ()

    def __init__(self, sock: Any):
        self.sock = sock
        self.requests = 0
        self.bad_requests = 0

    def act(self, op: str) -> tuple[bool, str]:
        """Do ``op``; (whether anything was touched, what was done)."""
        raise NotImplementedError

    def poll(self) -> None:
        while True:
            try:
                data, addr = self.sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionResetError:
                continue
            self.requests += 1
            req, why = decode_request(data, ops=self.ops)
            if req is None:
                self.bad_requests += 1
                reply = refusal(data, why)
            else:
                acted, detail = self.act(req["op"])
                reply = {"id": req.get("id", 0), "ok": True, "acted": acted, "detail": detail}
            self.sock.sendto(encode(reply), addr)


class FixtureClient:
    """Asks a lab-fixture service (UDP, loopback) to right the robot. Non-blocking:
    :meth:`request` sends, :meth:`reply` returns the answer to the last request once it
    came (the reset step polls it on every robot state)."""

    def __init__(self, port: int, host: str = "127.0.0.1"):
        self.address = (host, int(port))
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._id = 0

    def request(self, op: str = "right") -> int:
        """Send a request; returns its id. Datagrams can be lost: call again to resend."""
        self._id += 1
        self._sock.sendto(encode({"op": op, "id": self._id}), self.address)
        return self._id

    def reply(self) -> dict[str, Any] | None:
        """The reply to the latest request (older replies are dropped), or None yet."""
        while True:
            try:
                data = self._sock.recv(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return None
            except ConnectionRefusedError:  # loopback ICMP: nothing listens on the port
                return {"ok": False, "detail": f"no lab fixture listening on udp port {self.address[1]}"}
            try:
                m = json.loads(data.decode())
            except (UnicodeDecodeError, json.JSONDecodeError):
                continue
            if isinstance(m, dict) and m.get("id") == self._id:
                return m

    def close(self) -> None:
        self._sock.close()
