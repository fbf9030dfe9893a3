"""Loopback ports for a rig's own bus endpoint (a demo's rig, a test's, a sweep worker's).

A port from ``bind(0)`` comes from the OS's ephemeral range (Linux default 32768-60999), the
range every outgoing connection and every ``:0`` listener draws from. Between choosing it and
the rig's first node listening on it, any other Zenoh session on the host (its ephemeral
listener, an outgoing link) may take it; the rig's peers, whose rendezvous listen then fails,
would join that stranger's session instead of their own (bus/session.py: peers connect to
whoever holds the rendezvous endpoint). So a rig's port is chosen below the ephemeral range,
where the OS never hands one out by itself, checked free by binding it, and handed out in turn
from a per-process start. Processes started together have pids a few apart: their starts are
spread over the range by a multiplicative hash of the pid (pid mod span put them a few ports
apart, so each walked onto the ports the next one had taken: parallel test runs collided on
their rigs' endpoints, NodeConflict). ``HIL_PORT_SLOT=k/n`` confines a process and every
process it starts to part k of n of the range: parallel test workers set it (tests/conftest.py),
so the ports their demos, `hil` subprocesses and Ray tasks draw never meet another worker's.
Pure standard library.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

_next: dict[tuple[int, int], int] = {}

#: ``k/n``: draw from part k of n of the range, unless a caller names its own part
SLOT_ENV = "HIL_PORT_SLOT"


def _unassigned_range() -> tuple[int, int]:
    """[lo, hi): ports the OS does not assign by itself (below its ephemeral range)."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    return max(1024, low - 12768), low


def _spread(pid: int, span: int) -> int:
    """A start in [0, span) for process ``pid``: Fibonacci hashing, so pids a few apart start
    far apart (consecutive ones about 0.38·span)."""
    return ((pid * 0x9E3779B97F4A7C15) & (2**64 - 1)) * span >> 64


def _env_slot() -> tuple[int, int]:
    """(slot, slots) from ``$HIL_PORT_SLOT`` (``k/n``); (0, 1), the whole range, without it."""
    v = os.environ.get(SLOT_ENV, "").strip()
    if not v:
        return 0, 1
    try:
        k, n = (int(x) for x in v.split("/"))
    except ValueError:
        k = n = -1
    if not (1 <= n <= 64 and 0 <= k < n):
        raise ValueError(f"{SLOT_ENV}={v!r}: expected k/n with 0 <= k < n <= 64, e.g. 1/4")
    return k, n


def free_port(host: str = "127.0.0.1", slot: int | None = None, slots: int | None = None) -> int:
    """A port free on ``host`` now, below the ephemeral range. ``slots`` > 1 splits the range
    into that many parts and draws from part ``slot`` (parallel test workers: one part each);
    neither given: the part ``$HIL_PORT_SLOT`` names, else the whole range."""
    if slot is None and slots is None:
        slot, slots = _env_slot()
    slot, slots = slot or 0, slots or 1
    if not (1 <= slots <= 64 and 0 <= slot < slots):
        raise ValueError(f"slot {slot} of {slots}: expected 0 <= slot < slots <= 64")
    lo, hi = _unassigned_range()
    span = (hi - lo) // slots
    base = lo + slot * span
    nxt = _next.get((slot, slots), base + _spread(os.getpid(), span))
    for _ in range(span):
        port, nxt = nxt, base + (nxt - base + 1) % span
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
        _next[(slot, slots)] = nxt
        return port
    raise RuntimeError(f"no free port on {host} in {base}-{base + span - 1}")


def free_endpoint(host: str = "127.0.0.1") -> str:
    """``tcp/HOST:PORT`` with :func:`free_port`: a rig endpoint of its own on this host."""
    return f"tcp/{host}:{free_port(host)}"
