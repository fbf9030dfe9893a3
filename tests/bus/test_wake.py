"""Latest-value subscriptions block in Zenoh's ring channel; a timed wait ends by a session-local
wake-up sample (bus/node.py: ``_WakeTimer``, bus/wake.py). These tests pin what that design
must keep: timeouts without polling, stale wake-ups never taken for a timeout nor eating a
message, wake-ups never seen by a recorder or by another process, close() ending a wait."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from hilstack.bus import keys
from hilstack.bus import node as node_mod
from hilstack.bus.node import Node
from hilstack.bus.schemas import Command, decode, encode
from hilstack.bus.wake import is_wake, wake_key

RIG = "waketest"
KEY = keys.cmd(RIG, "pm")


def _in_thread(fn, timeout_s: float = 10.0):
    """Run ``fn`` in a thread; fail (instead of hanging the suite) if it does not return in time."""
    out: dict = {}
    th = threading.Thread(target=lambda: out.setdefault("r", fn()), daemon=True)
    th.start()
    th.join(timeout_s)
    assert not th.is_alive(), f"still blocked after {timeout_s} s"
    return out["r"]


def _cmd(x: float) -> bytes:
    return encode(Command(robot="pm", action=[x]))


def test_timed_wait_times_out_then_takes_a_message_sent_mid_wait(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node:
        sub = node.subscribe(KEY, Command)
        fired = node_mod._TIMER.fired
        t0 = time.monotonic()
        assert _in_thread(lambda: sub.wait(0.3)) is None
        took = time.monotonic() - t0
        assert took >= 0.29, f"returned after {took:.3f} s, before its 0.3 s timeout"
        assert node_mod._TIMER.fired == fired + 1  # ended by the timer's wake-up, not by polling
        # a message sent in the middle of a long wait ends it at once
        threading.Timer(0.2, lambda: node.session.put(KEY, _cmd(2.5))).start()
        t0 = time.monotonic()
        got = _in_thread(lambda: sub.wait(30.0))
        assert got is not None and got.action == [2.5]
        assert time.monotonic() - t0 < 20.0
        assert node_mod._TIMER.fired == fired + 1  # no wake-up for a wait a message ended


def test_a_stale_wake_is_neither_a_timeout_nor_eats_a_message(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node:
        sub = node.subscribe(KEY, Command)
        node.session.put(KEY, _cmd(1.0))
        assert sub.wait(5.0).action == [1.0]
        # the wake-up of a wait that already returned (the timer read the wait just before the
        # message ended it), in both orders around a message
        for order in ("wake first", "message first"):
            stale = sub._token
            if order == "wake first":
                sub._put_wake(stale)
                node.session.put(KEY, _cmd(2.0))
            else:
                node.session.put(KEY, _cmd(2.0))
                sub._put_wake(stale)
            assert sub.wait(5.0).action == [2.0], order
        # a stale wake-up queued before a wait does not end that wait early
        sub._put_wake(sub._token)
        sub._put_wake(sub._token - 1)
        t0 = time.monotonic()
        assert _in_thread(lambda: sub.wait(0.3)) is None
        assert time.monotonic() - t0 >= 0.29
        # nor one that comes while the wait is blocked in Zenoh's channel (the race itself)
        blocked = sub._token + 1  # the token the next wait takes
        threading.Timer(0.1, lambda: sub._put_wake(blocked - 1)).start()
        t0 = time.monotonic()
        assert _in_thread(lambda: sub.wait(0.4)) is None
        assert time.monotonic() - t0 >= 0.39 and sub._token == blocked
        threading.Timer(0.1, lambda: sub._put_wake(blocked)).start()  # stale for the next wait
        threading.Timer(0.2, lambda: node.session.put(KEY, _cmd(2.5))).start()
        assert _in_thread(lambda: sub.wait(10.0)).action == [2.5]
        # nor pushes a message out of the ring: a message, then the ring's size less one of wake-ups
        node.session.put(KEY, _cmd(3.0))
        for _ in range(sub.LATEST_RING - 1):
            sub._put_wake(sub._token)
        assert sub.poll().action == [3.0]
        # nor does a wait_queued() take it for a message
        for _ in range(2):
            sub._put_wake(sub._token)
        assert sub.wait_queued(0.2) is False
        node.session.put(KEY, _cmd(4.0))
        assert sub.wait_queued(5.0) is True and sub.poll().action == [4.0] and sub.poll() is None


def test_wait_takes_the_newest_queued_at_once_and_waits_on_past_a_malformed_one(bus):
    """wait() blocks in Zenoh's channel without looking first (`hil bench bus`): what is queued
    comes back at once, the newest of it, whatever the timeout; a malformed message does not
    end a wait, a valid one after it does."""
    with Node("sub", RIG, bus, handle_signals=False) as node:
        sub = node.subscribe(KEY, Command)
        fired = node_mod._TIMER.fired
        for timeout in (None, 30.0, 0.0, -1.0):
            for x in (1.0, 2.0, 3.0):
                node.session.put(KEY, _cmd(x))
            t0 = time.monotonic()
            assert _in_thread(lambda t=timeout: sub.wait(t)).action == [3.0], timeout
            assert time.monotonic() - t0 < 5.0 and sub.poll() is None
        # a stale wake-up and garbage ahead of the message: skipped, the message returned
        sub._put_wake(sub._token)
        node.session.put(KEY, b"\x00garbage")
        node.session.put(KEY, _cmd(4.0))
        assert _in_thread(lambda: sub.wait(0.0)).action == [4.0]
        # what wait_queued() took is what the next wait returns, at once
        node.session.put(KEY, _cmd(5.0))
        assert sub.wait_queued(0.0) is True and _in_thread(lambda: sub.wait(30.0)).action == [5.0]
        assert sub.wait(0.0) is None and sub.wait(-1.0) is None  # nothing queued: no block
        # only garbage: a timed wait waits on to its timeout, not to the garbage
        malformed = sub.malformed
        threading.Timer(0.1, lambda: node.session.put(KEY, b"\x00garbage")).start()
        t0 = time.monotonic()
        assert _in_thread(lambda: sub.wait(0.5)) is None
        assert time.monotonic() - t0 >= 0.49 and sub.malformed == malformed + 1
        # garbage, then a message: one wait returns the message
        threading.Timer(0.1, lambda: node.session.put(KEY, b"\x00garbage")).start()
        threading.Timer(0.3, lambda: node.session.put(KEY, _cmd(6.0))).start()
        assert _in_thread(lambda: sub.wait(30.0)).action == [6.0]
        assert sub.malformed == malformed + 2 and "not a valid Command" in sub.last_error
        assert node_mod._TIMER.fired == fired + 1  # only the wait that timed out was woken


def test_wake_ups_reach_no_recorder_no_latch_and_no_other_process(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node, Node("far", RIG, bus, handle_signals=False) as far:
        rec = node.subscribe(keys.all_of(RIG), Command, latest=False, capacity=64)  # a recorder, same session
        far_rec = far.subscribe(keys.all_of(RIG), Command, latest=False, capacity=64)
        far_raw = far.session.declare_subscriber(keys.all_of(RIG), zenoh.handlers.FifoChannel(256))  # unfiltered
        sub = node.subscribe(KEY, Command)
        est = node.subscribe(keys.estop(RIG), Command)  # a wait on the e-stop key: wakes the latch's key
        wild = node.subscribe(f"hil/{RIG}/*/pm", Command)  # a wildcard key: a wake on a key it matches
        # both ways linked first (discovery takes a moment), so a wake-up that left would arrive
        pub, far_pub = node.publisher(KEY, Command), far.publisher(KEY, Command)
        far_got: list = []
        deadline = time.monotonic() + 10
        while (not far_got or not rec._inbox._q) and time.monotonic() < deadline:
            pub.put(Command(robot="pm", action=[7.0]))
            far_pub.put(Command(robot="pm", action=[7.0]))
            time.sleep(0.05)
            while (smp := far_raw.try_recv()) is not None:
                far_got.append(smp)
        assert far_got and rec._inbox._q, "the two sessions did not link"
        # a message carries no attachment (what tells it from a wake-up)
        assert all(x.attachment is None and not is_wake(x) for x in far_got)
        time.sleep(0.2)
        rec.drain(), far_rec.drain(), sub.poll(), wild.poll()
        while far_raw.try_recv() is not None:
            pass
        fired = node_mod._TIMER.fired
        for s in (sub, est, wild):
            assert _in_thread(lambda s=s: s.wait(0.2)) is None
        assert node_mod._TIMER.fired == fired + 3
        far_pub.put(Command(robot="pm", action=[8.0]))  # one message after the wake-ups
        deadline = time.monotonic() + 10
        while not rec._inbox._q and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)
        got = rec.drain()
        assert [decode(p, Command).action for _, p in got] == [[8.0]], "the recorder recorded a wake-up"
        assert [decode(p, Command).action for _, p in far_rec.drain()] == [[8.0]]
        far_got = []
        while (smp := far_raw.try_recv()) is not None:
            far_got.append(smp)
        assert [x.attachment for x in far_got] == [None], "a wake-up left the process"
        assert node.estop.malformed == 0 and far.estop.malformed == 0


def test_close_ends_a_blocked_wait_and_wait_queued(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node:
        sub = node.subscribe(KEY, Command)
        other = node.subscribe(KEY, Command)
        got: dict = {}

        def waiter(s, name, untimed):
            got[name] = s.wait(None if untimed else 60.0) if name != "queued" else s.wait_queued(60.0)

        ths = [threading.Thread(target=waiter, args=(sub, "timed", False), daemon=True),
               threading.Thread(target=waiter, args=(other, "queued", False), daemon=True)]
        for th in ths:
            th.start()
        time.sleep(0.3)  # let them block in Zenoh's channel
        sub.close()
        other.close()
        for th in ths:
            th.join(10.0)
            assert not th.is_alive(), "close() did not end a wait blocked in Zenoh's channel"
        assert got == {"timed": None, "queued": False}


def test_a_steady_stream_costs_no_timer_wake_up_per_message(bus, monkeypatch):
    with Node("sub", RIG, bus, handle_signals=False) as node:
        sub = node.subscribe(KEY, Command)
        scheduled = []
        schedule = node_mod._TIMER.schedule
        monkeypatch.setattr(node_mod._TIMER, "schedule", lambda s, d: (scheduled.append(d), schedule(s, d)))
        stop = threading.Event()

        def send():
            for i in range(300):
                if stop.is_set():
                    return
                node.session.put(KEY, _cmd(float(i)))
                time.sleep(0.002)

        th = threading.Thread(target=send, daemon=True)
        th.start()
        for _ in range(50):
            assert sub.wait(10.0) is not None
        stop.set()
        th.join(10)
        # the first wait records its deadline; later ones (later deadlines) leave it: the timer
        # re-reads the current deadline when the recorded one comes, not once per message
        assert len(scheduled) == 1, f"{len(scheduled)} timer calls for 50 waits"


@pytest.mark.parametrize("key", ["hil/r/cmd/pm", "hil/r/*/pm", "hil/**", "hil/r/**/pm", "hil/r/a$*/x", "**"])
def test_wake_key_is_a_concrete_key_the_subscription_matches(key):
    w = wake_key(key)
    assert "*" not in w and zenoh.KeyExpr(key).includes(zenoh.KeyExpr(w))
