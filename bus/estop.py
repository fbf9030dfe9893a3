"""The rig's e-stop: the latch every node holds, acknowledgements, and the operator's command.

What "engaged" means: every driver node of the rig holds its robot in the safe state
(``stop()``), deactivates the driver and refuses commands until an explicit release.

Who holds the latch: every node on the bus (:class:`hilstack.bus.node.Node` creates an
:class:`EStopLatch`). It keeps the last e-stop command it heard and answers queries
for it on ``hil/<rig>/estop/latch/<node>``. The ``hil estop`` process is short-lived,
so the rig's memory of an e-stop is the set of running nodes: a driver node that
starts late (or restarts) asks them during its start-up window and starts stopped
when ANY of them says engaged (disagreement errs on the safe side). When no node of
the rig is running, nothing remembers the e-stop; a driver then starts as always,
holding the safe action until the first command.

Who releases: a release is only taken from ``hil/<rig>/estop/release/<user>``
(``EStop.sender`` is set from that key); a release on the engage key (an old client, a
replayed recording) is refused and counted. On a rig with access control the ACL lets
only the ``release`` users' credentials publish there, each on its own key, and every
authenticated session may engage (bus/access.py).

Acknowledgements: a driver node answers each e-stop command on
``hil/<rig>/estop/ack`` with an :class:`~hilstack.bus.schemas.EStopAck` quoting the command's
id and the state it is now in. :func:`command_estop` repeats the command until every
driver node alive on the rig (liveliness tokens ``hil/<rig>/alive/driver-*``) has
acknowledged it, or the timeout passes. An engage counts as done for a node only when
its ack also says ``device_confirmed`` (the device itself confirmed the stop); nodes that
acknowledged without it are listed in ``EStopResult.unconfirmed``.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import zenoh

from hilstack.bus import keys
from hilstack.bus.cycle import Rate
from hilstack.bus.schemas import EStop, EStopAck, MalformedMessage, decode, encode
from hilstack.bus.wake import is_wake

if TYPE_CHECKING:
    from hilstack.bus.node import Node


class EStopLatch:
    """The e-stop state of the rig as one node last heard it.

    Subscribes ``hil/<rig>/estop`` and serves the queryable
    ``hil/<rig>/estop/latch/<node>``. The Zenoh callbacks only decode the tiny
    ``EStop`` payload (so a malformed one can never replace a good latch) and store
    it; the owner's thread takes the commands with :meth:`take`.
    """

    def __init__(self, session: zenoh.Session, rig: str, node: str, releasers: list[str] | None = None):
        self.rig = rig
        self.node = node
        #: on a rig with access control: the users that may release (the ACL already holds the
        #: others back; this is the same rule checked again where the release takes effect)
        self.releasers = None if releasers is None else set(releasers)
        self._session = session
        self._lock = threading.Lock()
        self._latched: EStop | None = None
        self._pending: deque[EStop] = deque(maxlen=256)
        #: releases not taken, with why (a release on the engage key, from a user not allowed...)
        self._refused: deque[tuple[EStop, str]] = deque(maxlen=256)
        self.refused_releases = 0
        self.malformed = 0
        self._sub = session.declare_subscriber(keys.estop(rig), self._on_sample)
        self._release_sub = session.declare_subscriber(keys.estop_release_all(rig), self._on_release)
        self._queryable = session.declare_queryable(keys.estop_latch(rig, node), self._on_query)

    # ------------------------------------------------------------------ callbacks
    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.attachment is not None and is_wake(sample):
            return  # a timed wait's wake-up in this process (bus/node.py), not a message
        try:
            msg = decode(sample.payload.to_bytes(), EStop)
        except MalformedMessage:
            self.malformed += 1
            return
        if not msg.engaged:
            # a release must come on the sender's release key (it names who releases); one on
            # the engage key is an old client or a replayed recording: never taken
            self._refuse(msg, "a release on the engage key (not on hil/<rig>/estop/release/<user>)")
            return
        self._take(msg)

    def _on_release(self, sample: zenoh.Sample) -> None:
        if sample.attachment is not None and is_wake(sample):
            return
        try:
            msg = decode(sample.payload.to_bytes(), EStop)
        except MalformedMessage:
            self.malformed += 1
            return
        user = str(sample.key_expr).rsplit("/", 1)[-1]
        claimed, msg.sender = msg.sender, user  # the key names the sender (bound to its credentials by the ACL)
        if msg.engaged:
            self._refuse(msg, "an engage on a release key")
        elif self.releasers is not None and user not in self.releasers:
            self._refuse(msg, f"user {user!r} may not release (bus.access.release: {sorted(self.releasers)})")
        elif claimed and claimed != user:
            self._refuse(msg, f"sender {claimed!r} released on {user!r}'s key")
        else:
            self._take(msg)

    def _take(self, msg: EStop) -> None:
        with self._lock:
            self._latched = msg
            self._pending.append(msg)

    def _refuse(self, msg: EStop, why: str) -> None:
        with self._lock:
            self.refused_releases += 1
            self._refused.append((msg, why))

    def _on_query(self, query: zenoh.Query) -> None:
        with self._lock:
            msg = self._latched
        # always answer (empty: no e-stop heard), so a starting driver knows who replied
        query.reply(keys.estop_latch(self.rig, self.node), b"" if msg is None else encode(msg))

    # ------------------------------------------------------------------ owner side
    @property
    def latched(self) -> EStop | None:
        """The last e-stop command heard (engaged or released), or None."""
        with self._lock:
            return self._latched

    @property
    def engaged(self) -> bool:
        m = self.latched
        return m is not None and m.engaged

    def take(self) -> list[EStop]:
        """E-stop commands heard since the last call, in arrival order."""
        with self._lock:
            out = list(self._pending)
            self._pending.clear()
        return out

    def take_refused(self) -> list[tuple[EStop, str]]:
        """Releases refused since the last call, with why (the driver node logs them)."""
        with self._lock:
            out = list(self._refused)
            self._refused.clear()
        return out

    def sync_from_peers(self, window_s: float, min_window_s: float = 0.2, query_timeout_s: float = 0.25) -> EStop | None:
        """Ask every node of the rig for its latch; return the first engaged one, or None.

        An engaged latch found is adopted, so this node answers engaged too. Asks for
        at least ``min_window_s`` (a fresh session meets its peers within milliseconds
        on one host, a little later across hosts) and at most ``window_s`` seconds; in
        between it stops as soon as every node alive on the rig has answered.
        """
        from hilstack.bus.node import alive_nodes

        t0 = time.monotonic()
        while True:
            left = t0 + window_s - time.monotonic()
            latches = query_latches(self._session, self.rig, max(0.05, min(query_timeout_s, left)))
            latches.pop(self.node, None)
            engaged = next((m for m in latches.values() if m is not None and m.engaged), None)
            if engaged is not None:
                with self._lock:
                    if self._latched is None or not self._latched.engaged:
                        self._latched = engaged
                return engaged
            if self.engaged:  # heard a live engage meanwhile
                return self.latched
            elapsed = time.monotonic() - t0
            if elapsed >= window_s:
                return None
            if elapsed >= min_window_s:
                alive = set(alive_nodes(self._session, self.rig, timeout_s=0.2)) - {self.node}
                if alive <= set(latches):
                    return None
            time.sleep(0.02)

    def close(self) -> None:
        self._queryable.undeclare()
        self._release_sub.undeclare()
        self._sub.undeclare()


def query_latches(session: zenoh.Session, rig: str, timeout_s: float = 0.5) -> dict[str, EStop | None]:
    """Node name → the last e-stop command that node heard (None: it heard none)."""
    out: dict[str, EStop | None] = {}
    for reply in session.get(keys.estop_latch_all(rig), timeout=timeout_s):
        if reply.ok is None:
            continue
        name = str(reply.ok.key_expr).rsplit("/", 1)[-1]
        data = reply.ok.payload.to_bytes()
        try:
            out[name] = decode(data, EStop) if data else None
        except MalformedMessage:
            continue
    return out


@dataclass
class EStopResult:
    """What :func:`command_estop` saw: driver nodes alive, and who acknowledged what."""

    rig: str
    engaged: bool
    estop_id: str
    drivers: set[str] = field(default_factory=set)
    #: driver node → the state it acknowledged
    acked: dict[str, bool] = field(default_factory=dict)
    #: driver node → whether its device confirmed the stop (its newest ack)
    device_confirmed: dict[str, bool] = field(default_factory=dict)
    #: what driver nodes said beside the state ("driver-pm: release refused: ...")
    details: list[str] = field(default_factory=list)

    @property
    def confirmed(self) -> list[str]:
        return sorted(n for n, e in self.acked.items() if e == self.engaged)

    @property
    def missing(self) -> list[str]:
        return sorted(self.drivers - set(self.confirmed))

    @property
    def unconfirmed(self) -> list[str]:
        """Engage: driver nodes that acknowledged but whose device did not confirm the stop."""
        return [n for n in self.confirmed if not self.device_confirmed.get(n, False)] if self.engaged else []

    @property
    def ok(self) -> bool:
        """At least one driver node, and every driver node seen alive, confirmed (an
        engage: with its device's confirmation)."""
        return bool(self.confirmed) and not self.missing and not self.unconfirmed


def command_estop(
    node: Node,
    engaged: bool = True,
    reason: str = "operator",
    timeout_s: float = 2.0,
    settle_s: float = 0.5,
    repeat_s: float = 0.05,
) -> EStopResult:
    """Engage (or release) the rig's e-stop and wait for the driver nodes' acknowledgements.

    The command is repeated every ``repeat_s`` (a node still connecting gets a later
    copy; repeats share one id) until every driver node seen alive on the rig has
    acknowledged the requested state, at least ``settle_s`` has passed (time to
    discover the rig's nodes) and at most ``timeout_s`` in all.
    """
    rig = node.rig
    acks = node.subscribe(keys.estop_ack(rig), EStopAck, latest=False, capacity=1024)
    # a release goes on the sender's own release key: it names who released (bus/access.py)
    pub = node.publisher(keys.estop(rig) if engaged else keys.estop_release(rig, node.user), EStop)
    res = EStopResult(rig=rig, engaged=engaged, estop_id=uuid.uuid4().hex)
    msg = EStop(engaged=engaged, reason=reason, source=node.name, id=res.estop_id, sender=node.user)
    t0 = time.monotonic()
    # the one scheduler (bus/cycle.py): repeats and liveliness queries on their own grids,
    # a late one skips what it missed (no burst of repeats after a slow query)
    repeat, alive = Rate(repeat_s, t0), Rate(0.2, t0)
    while True:
        now = time.monotonic()
        if repeat.due(now):
            pub.put(msg)
        if alive.due(now):
            res.drivers |= _driver_nodes(node, min(0.2, max(0.05, t0 + timeout_s - now)))
        for _, payload in acks.drain():
            try:
                ack = decode(payload, EStopAck)
            except MalformedMessage:
                continue
            if ack.estop_id == res.estop_id:
                res.acked[ack.node] = ack.engaged
                res.device_confirmed[ack.node] = ack.device_confirmed
                note = f"{ack.node}: {ack.detail}"
                if ack.detail and note not in res.details:
                    res.details.append(note)
                res.drivers.add(ack.node)
        elapsed = time.monotonic() - t0
        if (res.ok and elapsed >= settle_s) or elapsed >= timeout_s:
            return res
        acks.wait_queued(min(repeat.left_s(time.monotonic()), alive.left_s(time.monotonic())))


def _driver_nodes(node: Node, timeout_s: float) -> set[str]:
    from hilstack.bus.node import alive_nodes

    return {n for n in alive_nodes(node.session, node.rig, timeout_s) if n.startswith(keys.DRIVER_NODE_PREFIX)}
