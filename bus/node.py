"""Node base: a Zenoh session, a liveliness token, typed publishers and subscribers.

No work runs in Zenoh callbacks: a subscription's callback only queues the sample
(latest value, or a bounded FIFO) and wakes the node's thread; payloads are decoded
in the node's thread when it asks for them, and malformed ones are counted and
dropped without disturbing the node.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh

from hilstack.bus import keys
from hilstack.bus.access import identity
from hilstack.bus.cycle import CycleTimer
from hilstack.bus.estop import EStopLatch
from hilstack.bus.lifetime import on_stop_signal
from hilstack.bus.schemas import MalformedMessage, Msg, decode, encode
from hilstack.bus.session import open_session, rendezvous_listened, wait_linked
from hilstack.configs.schema import BusConfig

log = logging.getLogger("hil")

#: nodes not closed yet: closed when the interpreter exits, *before* it joins non-daemon
#: threads (zenoh's callback threads are such threads: a process that ended with a node still
#: open waited for them forever instead of exiting)
_open_nodes: weakref.WeakSet[Node] = weakref.WeakSet()


def _close_open_nodes() -> None:
    for node in list(_open_nodes):
        node.close()


threading._register_atexit(_close_open_nodes)  # noqa: SLF001 - the hook concurrent.futures uses for the same reason

T = TypeVar("T", bound=Msg)


class Publisher(Generic[T]):
    """Stamps (wall clock) and numbers each message, encodes, puts.

    ``reliable``: a message that must arrive (a reset handshake, a lockstep state or
    command) waits for room in Zenoh's send queue (``CongestionControl.BLOCK``) instead of
    being dropped when the queue stays full for 1 ms, Zenoh's default for data: on a loaded
    2-core machine a starved send thread lost a reset answer and the rig stopped.
    """

    def __init__(self, session: zenoh.Session, key: str, typ: type[T], express: bool = True, reliable: bool = False):
        self.key = key
        self.type = typ
        cc = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        self._pub = session.declare_publisher(key, express=express, congestion_control=cc)
        self.seq = 0

    def put(self, msg: T) -> T:
        self.seq += 1
        msg.seq = self.seq
        msg.stamp_s = time.time()
        return self.resend(msg)

    def resend(self, msg: T) -> T:
        """Put ``msg`` again as it was (same sequence number and stamp): a receiver that has it
        sees nothing new, one that missed it gets it."""
        self._pub.put(encode(msg))
        return msg

    def close(self) -> None:
        self._pub.undeclare()


class _Inbox:
    """Hands samples from Zenoh's callback thread to the node's thread.

    The callback only appends to a bounded deque (when full the oldest sample is
    dropped and counted in ``overflow``) and, when the node's thread is blocked in
    :meth:`wait`, rings a doorbell (a ``queue.SimpleQueue``) that wakes it. No
    decoding and no Python-level locking run in the callback: both calls are atomic
    C operations. :meth:`close` rings too, so a thread blocked in :meth:`wait` returns at
    once; later timed waits on a closed inbox sleep out their timeout (a caller looping
    until a deadline must not spin) and an untimed one returns False at once.

    The node-thread side avoids exceptions on its hot path (an empty deque or bell is
    tested, not caught): each wait and each take is a few C calls (``hil bench bus``).
    """

    def __init__(self, capacity: int):
        self._q: deque[zenoh.Sample] = deque(maxlen=capacity)
        self._bell: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._waiting = False
        self.closed = False
        self.overflow = 0

    def push(self, sample: zenoh.Sample) -> None:
        if len(self._q) == self._q.maxlen:
            self.overflow += 1
        self._q.append(sample)
        if self._waiting:
            self._bell.put(None)

    def pop(self) -> zenoh.Sample | None:
        # one consumer thread: a non-empty deque stays non-empty until it pops
        return self._q.popleft() if self._q else None

    def wait(self, timeout_s: float | None) -> bool:
        """Block until something is queued (True) or ``timeout_s`` passes or the inbox closes (False)."""
        # announce the wait before looking, so a push after the look rings the bell
        self._waiting = True
        try:
            if self._q:
                return True
            if self.closed and timeout_s is None:
                return False  # nothing can arrive: waiting forever would hang
            try:
                self._bell.get(timeout=timeout_s)
            except queue.Empty:
                pass
            return bool(self._q)
        finally:
            self._waiting = False
            bell = self._bell
            while not bell.empty():  # rings that came after we woke: drop them (no spurious wakeups later)
                bell.get_nowait()

    def close(self) -> None:
        self.closed = True
        self._bell.put(None)


class Subscription(Generic[T]):
    """Typed subscription.

    ``latest=True`` (default): a latest-value queue; ``poll()`` returns the newest
    unseen message or None, ``wait(timeout_s)`` blocks (no polling) for a new one.
    ``latest=False``: a FIFO of ``capacity`` messages, drained with ``drain()``
    (recorders, logs); when it overflows the oldest are dropped and counted in
    ``dropped``. One consumer thread per subscription.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        typ: Any,
        latest: bool = True,
        capacity: int = 4096,
    ):
        self.key = key
        self.type = typ
        self._inbox = _Inbox(1 if latest else capacity)
        # Zenoh runs the callback on its own Python thread (indirect callback), so the
        # network threads never wait for the GIL; the callback only queues the sample
        self._sub = session.declare_subscriber(key, self._inbox.push)
        self.last: T | None = None
        self._last_key_expr: zenoh.KeyExpr | None = None
        #: monotonic time at which ``last`` was taken from the queue
        self.last_rx_s: float | None = None
        self.received = 0
        self.malformed = 0
        self.last_error: str | None = None

    @property
    def last_key(self) -> str | None:
        """Key of ``last`` (turned into a string when asked, not per message)."""
        return None if self._last_key_expr is None else str(self._last_key_expr)

    @property
    def dropped(self) -> int:
        """FIFO mode: samples lost because the queue was full (latest mode: superseded values)."""
        return self._inbox.overflow

    def _decode(self, sample: zenoh.Sample) -> T | None:
        try:
            msg = decode(sample.payload.to_bytes(), self.type)
        except MalformedMessage as e:
            self.malformed += 1
            self.last_error = f"{sample.key_expr}: {e}"
            return None
        self.received += 1
        self.last = msg
        self._last_key_expr = sample.key_expr
        self.last_rx_s = time.monotonic()
        return msg

    def poll(self) -> T | None:
        """Newest message not seen yet, or None (never blocks)."""
        newest = None
        while (smp := self._inbox.pop()) is not None:
            m = self._decode(smp)
            if m is not None:
                newest = m
        return newest

    def wait(self, timeout_s: float | None = None) -> T | None:
        """Block until a new valid message arrives or ``timeout_s`` passes (None: forever)
        or the subscription is closed (None).

        Sleeps on a doorbell the Zenoh callback rings: no polling.
        """
        m = self.poll()
        if m is not None:
            return m
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        left = None if timeout_s is None else max(0.0, timeout_s)
        while True:
            if not self._inbox.wait(left):
                return None
            m = self.poll()
            if m is not None:
                return m
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None

    def wait_queued(self, timeout_s: float | None) -> bool:
        """Block until a sample is queued, without taking it (True), or ``timeout_s`` passes."""
        return self._inbox.wait(None if timeout_s is None else max(0.0, timeout_s))

    def drain(self, max_items: int | None = None) -> list[tuple[str, bytes]]:
        """FIFO mode: raw (key, payload) pairs, undecoded (for recorders)."""
        out: list[tuple[str, bytes]] = []
        while (max_items is None or len(out) < max_items) and (smp := self._inbox.pop()) is not None:
            out.append((str(smp.key_expr), smp.payload.to_bytes()))
        return out

    def age_s(self) -> float:
        return float("inf") if self.last_rx_s is None else time.monotonic() - self.last_rx_s

    def close(self) -> None:
        """Stop listening; a thread blocked in :meth:`wait` returns None at once (see :class:`_Inbox`)."""
        try:
            self._sub.undeclare()
        finally:
            self._inbox.close()


class AliveWatch:
    """Whether one named node of the rig is alive (its liveliness token), kept by a Zenoh
    callback: ``alive`` is None until the node was seen, then True, and False once its token
    is gone (it exited, was killed, or lost its link)."""

    def __init__(self, session: zenoh.Session, rig: str, name: str):
        self.name = name
        self.alive: bool | None = None
        self._sub = session.liveliness().declare_subscriber(keys.alive(rig, name), self._on, history=True)

    def _on(self, sample: zenoh.Sample) -> None:  # Zenoh callback: one attribute store, no work
        self.alive = sample.kind == zenoh.SampleKind.PUT

    @property
    def gone(self) -> bool:
        """Seen alive, and gone since."""
        return self.alive is False

    def close(self) -> None:
        self._sub.undeclare()


class NodeConflict(ValueError):
    """A node that must be alone on its rig (a driver node) found its name already alive."""


class Node:
    """Base of every process on the bus.

    Declares the liveliness token ``hil/<rig>/alive/<name>`` and holds the rig's
    e-stop latch (``self.estop``, :class:`hilstack.bus.estop.EStopLatch`: every node remembers
    the last e-stop command and tells late driver nodes); SIGINT/SIGTERM set
    ``stop_event`` (when created in the main thread) so ``run()`` loops end cleanly
    and ``close()`` runs.
    """

    def __init__(
        self,
        name: str,
        rig: str,
        bus: BusConfig | None = None,
        session: zenoh.Session | None = None,
        handle_signals: bool = True,
        server: bool = False,
        robots: list[str] | None = None,
        unique: bool = False,
        join_wait_s: float = 0.0,
    ):
        self.name = name
        self.rig = rig
        #: who this process is on the bus (bus/access.py: identity); releases are sent in its name
        self.user = identity(bus)
        self._own_session = session is None
        # ``server`` (a driver node on a rig with access control): the rig's router, ACL for ``robots``
        # ``join_wait_s`` > 0 (a recorder, a viewer: whose ``--seconds`` count from here): when a rig
        # listens at the endpoint, wait (bounded) for this session's link to it, so that its first
        # messages are not lost to the background connect (a 1-s viewer logged nothing under load)
        rig_up = session is None and join_wait_s > 0 and rendezvous_listened(bus)
        self.session = session if session is not None else open_session(bus, server=server, rig=rig, robots=robots)
        if rig_up and not wait_linked(self.session, bus, join_wait_s):
            log.warning("%s: no link to the rig listening at %s within %.0f s; going on", name,
                        (bus or BusConfig()).router or (bus or BusConfig()).endpoint, join_wait_s)
        self.stop_event = threading.Event()
        if unique:
            # a driver node is one per robot and rig: a second one on the same endpoint is another
            # process (another user's rig of the same name on this host?) and both would command it
            others = alive_nodes(self.session, rig, timeout_s=0.2, window_s=0.3)
            if name in others:
                if self._own_session:
                    self.session.close()
                where = bus.endpoint if bus is not None else "this bus"
                raise NodeConflict(f"a node {name} is already alive on rig {rig} at {where}: another process "
                                   "(another user's rig of the same name?) drives it; give each rig its own "
                                   "bus.endpoint")
        self._token = self.session.liveliness().declare_token(keys.alive(rig, name))
        self._closeables: list[Any] = []
        self._closed = False
        self.estop = EStopLatch(self.session, rig, name,
                                releasers=None if bus is None or bus.access is None else list(bus.access.release))
        self._closeables.append(self.estop)
        #: the timer of the last ``run()`` (timing summary)
        self.cycle: CycleTimer | None = None
        # Ctrl-C/SIGTERM stop this node, also one that came while the process loaded
        # (bus/lifetime.py: a supervisor's SIGTERM may arrive before the node exists)
        self._forget_signals = (on_stop_signal(self.stop_event.set)
                                if handle_signals and threading.current_thread() is threading.main_thread() else None)
        _open_nodes.add(self)

    # -------------------------------------------------------------- pub/sub
    def publisher(self, key: str, typ: type[T], reliable: bool = False) -> Publisher[T]:
        """``reliable``: never dropped on a full send queue (see :class:`Publisher`)."""
        p = Publisher(self.session, key, typ, reliable=reliable)
        self._closeables.append(p)
        return p

    def subscribe(self, key: str, typ: Any, latest: bool = True, capacity: int = 4096) -> Subscription:
        s = Subscription(self.session, key, typ, latest=latest, capacity=capacity)
        self._closeables.append(s)
        return s

    def watch_alive(self, name: str) -> AliveWatch:
        """Track whether node ``name`` of this rig is alive (:class:`AliveWatch`)."""
        w = AliveWatch(self.session, self.rig, name)
        self._closeables.append(w)
        return w

    def malformed_count(self) -> int:
        return sum(s.malformed for s in self._closeables if isinstance(s, Subscription))

    # -------------------------------------------------------------- loop
    def run(self, step: Callable[[], None], period_s: float, max_steps: int | None = None) -> int:
        """Call ``step`` every ``period_s`` (wall clock) until stopped; returns steps run.

        Paced by :class:`hilstack.bus.cycle.CycleTimer` (``self.cycle`` after the call: its
        catch-up rule, late/missed counts and the p50/p99 of ``step``); a stop request
        interrupts the sleep between steps.
        """
        timer = self.cycle = CycleTimer(period_s, sleep=self.stop_event.wait)
        timer.start()
        n = 0
        while not self.stop_event.is_set() and (max_steps is None or n < max_steps):
            with timer.section("step"):
                step()
            n += 1
            if max_steps is not None and n >= max_steps:
                break
            timer.wait()
        return n

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.stop_event.set()
        if self._forget_signals is not None:
            self._forget_signals()
        for c in reversed(self._closeables):
            try:
                c.close()
            except Exception:
                pass
        try:
            self._token.undeclare()
        except Exception:
            pass
        if self._own_session:
            self.session.close()

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def alive_nodes(session: zenoh.Session, rig: str, timeout_s: float = 1.0, window_s: float = 0.0) -> list[str]:
    """Names of nodes whose liveliness token is present on the rig.

    ``window_s`` > 0: keep asking for that long and return every name seen (a session
    opened a moment ago may not have found its peers yet).
    """
    deadline = time.monotonic() + window_s
    out: set[str] = set()
    while True:
        for r in session.liveliness().get(keys.alive_all(rig), timeout=timeout_s):
            if r.ok is not None:
                out.add(str(r.ok.key_expr).rsplit("/", 1)[-1])
        left = deadline - time.monotonic()
        if left <= 0:
            return sorted(out)
        time.sleep(min(0.1, left))
