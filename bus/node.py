"""Node base: a Zenoh session, a liveliness token, typed publishers and subscribers.

No work runs in Zenoh's threads: a latest-value subscription's node thread blocks in the
subscriber's Zenoh ring channel (timed waits end by a session-local wake-up sample,
:class:`_WakeTimer`); a FIFO subscription's callback only queues the sample in a bounded
deque and wakes the node's thread. Payloads are decoded in the node's thread when it asks
for them, and malformed ones are counted and dropped without disturbing the node.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import os
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
from hilstack.bus.schemas import DECODE_ERRORS, Msg, decoder, encode, malformed
from hilstack.bus.session import open_session, rendezvous_listened, wait_linked
from hilstack.bus.wake import WAKE_PREFIX, is_wake, wake_key
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
        self._put = self._pub.put
        self.seq = 0

    def put(self, msg: T) -> T:
        # the hot path of every node: no call of ours below this one (`hil bench bus`)
        self.seq += 1
        msg.seq = self.seq
        msg.stamp_s = time.time()
        self._put(encode(msg))
        return msg

    def resend(self, msg: T) -> T:
        """Put ``msg`` again as it was (same sequence number and stamp): a receiver that has it
        sees nothing new, one that missed it gets it."""
        self._put(encode(msg))
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
        if sample.attachment is not None and is_wake(sample):
            return  # a timed wait's wake-up in this process (Subscription), not a message
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


class _WakeTimer:
    """One thread per process that ends timed waits: when a wait's deadline passes it puts a
    wake-up sample, session-locally (``Locality.SESSION_LOCAL``: it never leaves the process),
    on the subscription's key with the wait's token in the attachment; the waiter, blocked in
    Zenoh's channel, takes it and returns.

    Cheap on the hot path: a subscription records one deadline here at a time
    (``_timer_at``); when it comes the timer re-reads the subscription's current wait
    (``_wait``: token and deadline, or None between waits) and sleeps again if the deadline
    moved later, so a node that waits with a fixed timeout and gets its messages in time
    causes one timer wake-up per timeout, not per message. A wait calls :meth:`schedule` only
    when its deadline is earlier than the recorded one (or none is recorded).

    Ordering (no lost wake-up without a lock on the hot path): the waiter stores ``_wait``
    before it reads ``_timer_at``; the timer clears ``_timer_at`` before it reads ``_wait``.
    So either the waiter sees no recorded deadline and schedules, or the timer sees the wait.
    """

    def __init__(self) -> None:
        self._cv = threading.Condition(threading.Lock())
        self._heap: list[tuple[float, int, Subscription]] = []
        self._n = 0
        self._thread: threading.Thread | None = None
        #: wake-ups sent (tests; a steady node sends none)
        self.fired = 0
        #: times the thread woke up (tests: not one per message)
        self.rounds = 0

    def schedule(self, sub: Subscription, deadline: float) -> None:
        with self._cv:
            self._n += 1
            sub._timer_entry = self._n  # older entries of this subscription are void
            sub._timer_at = deadline
            heapq.heappush(self._heap, (deadline, self._n, sub))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="hil-wake-timer", daemon=True)
                self._thread.start()
            elif self._heap[0][1] == self._n:
                self._cv.notify()  # earlier than the thread's planned wake-up

    def _run(self) -> None:
        heap = self._heap
        while True:
            due: list[tuple[Subscription, int]] = []
            with self._cv:
                self.rounds += 1
                now = time.monotonic()
                while heap and heap[0][0] <= now:
                    _, n, sub = heapq.heappop(heap)
                    if sub._timer_entry != n:
                        continue  # replaced by a later schedule()
                    sub._timer_at = _NEVER  # before reading _wait (see the class docstring)
                    sub._timer_entry = 0
                    w = sub._wait
                    if w is None or sub._closed:
                        continue  # not waiting: its next wait schedules again
                    token, deadline = w
                    if deadline > now:
                        self._n += 1
                        sub._timer_entry = self._n
                        sub._timer_at = deadline
                        heapq.heappush(heap, (deadline, self._n, sub))
                    elif sub._woken != token:
                        sub._woken = token
                        due.append((sub, token))
                if not due:
                    self._cv.wait(heap[0][0] - now if heap else None)
                    continue
            for sub, token in due:
                self.fired += 1
                sub._put_wake(token)


_NEVER = float("inf")
_TIMER = _WakeTimer()
_SUB_IDS = itertools.count(1)


def _new_timer_after_fork() -> None:
    # a forked child has no timer thread (only the forking thread survives a fork)
    global _TIMER
    _TIMER = _WakeTimer()


os.register_at_fork(after_in_child=_new_timer_after_fork)


class Subscription(Generic[T]):
    """Typed subscription.

    ``latest=True`` (default): a latest-value queue; ``poll()`` returns the newest
    unseen message or None, ``wait(timeout_s)`` blocks (no polling) for a new one.
    ``latest=False``: a FIFO of ``capacity`` messages, drained with ``drain()``
    (recorders, logs); when it overflows the oldest are dropped and counted in
    ``dropped``. One consumer thread per subscription.

    Latest mode hands samples over without a Python thread in between: the subscriber has a
    Zenoh ring channel (``RingChannel(LATEST_RING)``) and the node's thread blocks in its
    ``recv()`` (Zenoh releases the GIL), as raw zenoh-python does. zenoh-python has no receive
    with a timeout, so a timed wait is ended by a wake-up sample the process's
    :class:`_WakeTimer` puts session-locally on the subscription's key; a wake-up of an earlier
    wait (it returned meanwhile) is recognised by its token and skipped. FIFO mode keeps a
    Python callback into a bounded deque (:class:`_Inbox`: it counts overflow; Zenoh's
    FifoChannel would block the network thread when full).
    """

    #: ring size of a latest-value subscription: a wake-up takes a place in it, so more than
    #: one, so a stale wake-up never pushes out a message (see docs/platform.md, `hil bench bus`)
    LATEST_RING = 8

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
        self.latest = latest
        self._session = session
        self._closed = False
        self._superseded = 0
        if latest:
            self._inbox = None
            self._wake_key = wake_key(key)
            self._wake_id = WAKE_PREFIX + next(_SUB_IDS).to_bytes(8, "little")
            self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(self.LATEST_RING))
            # the handler, not the subscriber: undeclaring while a thread is in the subscriber's
            # recv() raises "Already borrowed"; the handler's recv() raises ZError instead (close())
            handler = self._sub.handler
            self._recv, self._try_recv = handler.recv, handler.try_recv
            self._held: zenoh.Sample | None = None  # taken by wait_queued(), not yet by poll()
            self._token = 0
            #: (token, deadline) of the timed wait in progress, else None (read by the timer)
            self._wait: tuple[int, float] | None = None
            self._timer_at = _NEVER
            self._timer_entry = 0
            self._woken = 0
        else:
            self._inbox = _Inbox(capacity)
            # Zenoh runs the callback on its own Python thread (indirect callback), so the
            # network threads never wait for the GIL; the callback only queues the sample
            self._sub = session.declare_subscriber(key, self._inbox.push)
        self._decode_bytes = decoder(typ)
        self.last: T | None = None
        #: monotonic time at which ``last`` was taken from the queue
        self.last_rx_s: float | None = None
        self.malformed = 0
        self.last_error: str | None = None

    @property
    def dropped(self) -> int:
        """FIFO mode: samples lost because the queue was full. Latest mode: values superseded by
        a newer one when taken (a burst longer than ``LATEST_RING`` loses the older ones in
        Zenoh's ring, uncounted)."""
        return self._superseded if self._inbox is None else self._inbox.overflow

    def _decode(self, sample: zenoh.Sample) -> T | None:
        try:
            msg = self._decode_bytes(sample.payload.to_bytes())
        except DECODE_ERRORS as e:
            self._malformed(sample, e)
            return None
        self.last = msg
        self.last_rx_s = time.monotonic()
        return msg

    def _malformed(self, sample: zenoh.Sample, error: Exception) -> None:
        self.malformed += 1
        self.last_error = f"{sample.key_expr}: {malformed(self.type, error)}"

    def _take_all(self) -> list[zenoh.Sample]:
        """Latest mode: every message queued now (wake-ups left out), oldest first."""
        out: list[zenoh.Sample] = []
        if self._held is not None:
            out.append(self._held)
            self._held = None
        try_recv = self._try_recv
        try:
            while (smp := try_recv()) is not None:
                if smp.attachment is None or not is_wake(smp):
                    out.append(smp)
        except zenoh.ZError:
            pass  # closed: the ring is gone
        return out

    def _newest(self, samples: list[zenoh.Sample]) -> T | None:
        """The newest valid message of ``samples``: decoded newest first, the older ones are
        superseded (not decoded, as a latest-value queue overwrote them before)."""
        for i in range(len(samples) - 1, -1, -1):
            m = self._decode(samples[i])
            if m is not None:
                self._superseded += i
                return m
        return None

    def poll(self) -> T | None:
        """Newest message not seen yet, or None (never blocks)."""
        if self._inbox is None:
            return self._newest(self._take_all())
        newest = None
        while (smp := self._inbox.pop()) is not None:
            m = self._decode(smp)
            if m is not None:
                newest = m
        return newest

    def _put_wake(self, token: int) -> None:
        """(timer thread) End the wait ``token``: a wake-up sample into this process only."""
        try:
            self._session.put(self._wake_key, b"", attachment=self._wake_id + token.to_bytes(8, "little", signed=True),
                              allowed_destination=zenoh.Locality.SESSION_LOCAL)
        except Exception:  # the session closed meanwhile: nobody waits any more
            pass

    def _recv_message(self, deadline: float | None) -> zenoh.Sample | None:
        """Latest mode: block in Zenoh's channel for the next message (wake-ups skipped), or
        None once ``deadline`` (monotonic; None: never) passed or the subscription closed.
        A message already queued returns at once: the caller need not look first."""
        if self._closed:
            if deadline is not None:
                time.sleep(max(0.0, deadline - time.monotonic()))  # a caller looping until a deadline must not spin
            return None
        if deadline is None:
            token = -1  # no deadline: no wake-up of this wait exists
        else:
            self._token = token = self._token + 1
            self._wait = (token, deadline)  # before reading _timer_at (see _WakeTimer)
            if deadline < self._timer_at:
                _TIMER.schedule(self, deadline)
        try:
            while True:
                try:
                    smp = self._recv()
                except zenoh.ZError:
                    return None  # close() undeclared the subscriber
                a = smp.attachment
                if a is None:
                    return smp
                b = a.to_bytes()
                if not b.startswith(WAKE_PREFIX):
                    return smp  # someone else's attachment: a message all the same
                if b == self._wake_id + token.to_bytes(8, "little", signed=True):
                    return None  # this wait's deadline passed
                # a wake-up of an earlier wait, or of another subscription on this key: skip
        finally:
            self._wait = None

    def wait(self, timeout_s: float | None = None) -> T | None:
        """Block until a new valid message arrives or ``timeout_s`` passes (None: forever)
        or the subscription is closed (None).

        Latest mode: blocks in Zenoh's channel; FIFO mode: sleeps on a doorbell the Zenoh
        callback rings. No polling in either.
        """
        if self._inbox is not None:
            return self._wait_fifo(timeout_s)
        # The hot path of every node (`hil bench bus`). Cold after a blocking receive, each
        # bytecode costs: one receive, which returns at once when a message is queued, then one
        # look for newer ones, with the usual case written out here (not _try_recv_message, _decode)
        if timeout_s is None:
            deadline = None
        elif timeout_s > 0:
            deadline = time.monotonic() + timeout_s
        else:
            return self.poll()  # no wait: the newest of what is queued
        while True:
            smp = self._held
            if smp is None:
                smp = self._recv_message(deadline)
                if smp is None:
                    return None
            else:
                self._held = None
            try:
                nxt = self._try_recv()
            except zenoh.ZError:
                nxt = None  # closed meanwhile
            if nxt is None:
                try:
                    m = self._decode_bytes(smp.payload.to_bytes())
                except DECODE_ERRORS as e:
                    self._malformed(smp, e)
                else:
                    self.last = m
                    self.last_rx_s = time.monotonic()
                    return m
            elif (m := self._newest([smp, *([] if is_wake(nxt) else [nxt]), *self._take_all()])) is not None:
                return m
            # malformed: wait on for a valid one until the deadline
            if deadline is not None and deadline <= time.monotonic():
                return None

    def _wait_fifo(self, timeout_s: float | None) -> T | None:
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
        t = None if timeout_s is None else max(0.0, timeout_s)
        if self._inbox is not None:
            return self._inbox.wait(t)
        if self._held is not None:
            return True
        smp = self._try_recv_message()
        if smp is None and (t is None or t > 0):
            smp = self._recv_message(None if t is None else time.monotonic() + t)
        self._held = smp
        return smp is not None

    def _try_recv_message(self) -> zenoh.Sample | None:
        try:
            while (smp := self._try_recv()) is not None:
                if smp.attachment is None or not is_wake(smp):
                    return smp
        except zenoh.ZError:
            pass
        return None

    def drain(self, max_items: int | None = None) -> list[tuple[str, bytes]]:
        """FIFO mode: raw (key, payload) pairs, undecoded (for recorders); latest mode: all
        that Zenoh's ring holds (at most ``LATEST_RING``; ``max_items`` does not apply: the rest
        could not be put back)."""
        if self._inbox is None:
            return [(str(s.key_expr), s.payload.to_bytes()) for s in self._take_all()]
        out: list[tuple[str, bytes]] = []
        while (max_items is None or len(out) < max_items) and (smp := self._inbox.pop()) is not None:
            out.append((str(smp.key_expr), smp.payload.to_bytes()))
        return out

    def age_s(self) -> float:
        return float("inf") if self.last_rx_s is None else time.monotonic() - self.last_rx_s

    def close(self) -> None:
        """Stop listening; a thread blocked in :meth:`wait` returns None at once (latest mode:
        undeclaring ends its ``recv()`` with ZError; FIFO mode: see :class:`_Inbox`)."""
        self._closed = True
        try:
            self._sub.undeclare()
        finally:
            if self._inbox is not None:
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


class _AliveOnceBuilt(type):
    """Node's metaclass: the liveliness token goes out when the whole constructor has run, the
    subclass's subscriptions included. Peers act on a node's token (a driver node leaves reset
    requests to the supervisor once it sees the supervisor alive); a token declared before the
    subscriptions let a request sent in between go unheard, at start-up, by everyone."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        node = super().__call__(*args, **kwargs)
        node._declare_alive()
        return node


class Node(metaclass=_AliveOnceBuilt):
    """Base of every process on the bus.

    Declares the liveliness token ``hil/<rig>/alive/<name>`` once constructed (subscribe in
    ``__init__``: what a node subscribes to later can miss what a peer sends on seeing it alive) and holds the rig's
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
        self._token: Any = None  # declared by _declare_alive once the constructor has run
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

    def _declare_alive(self) -> None:
        if self._token is None and not self._closed:
            self._token = self.session.liveliness().declare_token(keys.alive(self.rig, self.name))

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
        if self._token is not None:
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
