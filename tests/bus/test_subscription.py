"""Subscriptions: typed latest-value and FIFO queues; ``wait`` blocks instead of polling."""

from __future__ import annotations

import sys
import threading
import time

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.schemas import Command, encode

RIG = "subtest"


def _calls_made_by(fn):
    """Run ``fn`` in this thread and count the Python and C calls it makes (sys.setprofile).

    A blocking wait makes a handful of calls whatever its duration; a busy-poll makes
    calls on every iteration, so the count grows with the time it waits.
    """
    n = 0

    def prof(frame, event, arg):
        nonlocal n
        if event in ("call", "c_call"):
            n += 1

    sys.setprofile(prof)
    try:
        result = fn()
    finally:
        sys.setprofile(None)
    return result, n


def test_wait_blocks_without_polling_then_times_out(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node:
        sub = node.subscribe(keys.cmd(RIG, "pm"), Command)
        got, calls = _calls_made_by(lambda: sub.wait(1.0))
    assert got is None
    # the busy-poll version made thousands of calls in 1 s (one sleep(0.2 ms) per loop)
    assert calls < 200, f"wait made {calls} calls while idle: it polls"


def test_wait_wakes_on_a_message_from_another_session(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node, Node("pub", RIG, bus, handle_signals=False) as other:
        sub = node.subscribe(keys.cmd(RIG, "pm"), Command)
        pub = other.publisher(keys.cmd(RIG, "pm"), Command)
        stop = threading.Event()

        def send():
            # keep sending until the waiter has it (discovery takes a moment)
            while not stop.is_set():
                pub.put(Command(robot="pm", action=[1.5]))
                stop.wait(0.05)

        th = threading.Thread(target=send)
        th.start()
        try:
            got, calls = _calls_made_by(lambda: sub.wait(20.0))
        finally:
            stop.set()
            th.join()
    assert got is not None and got.action == [1.5] and got.robot == "pm"
    assert calls < 400


def test_latest_keeps_the_newest_fifo_keeps_all_and_malformed_are_counted(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node:
        latest = node.subscribe(keys.cmd(RIG, "pm"), Command)
        fifo = node.subscribe(keys.cmd(RIG, "pm"), Command, latest=False, capacity=3)
        key = keys.cmd(RIG, "pm")
        node.session.put(key, b"\x00garbage")
        for i in range(5):
            node.session.put(key, encode(Command(robot="pm", action=[float(i)])))
        deadline = time.monotonic() + 5
        # the FIFO's callback runs on a thread of its own: wait until it saw all 6 (a latest
        # subscription's ring channel has them as soon as a put in this session returns)
        while fifo.dropped < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert latest.poll().action == [4.0] and latest.poll() is None
        assert latest.dropped == 5  # superseded: the garbage and 4 older values
        assert len(fifo.drain()) == 3 and fifo.dropped == 3  # 6 sent, capacity 3: the oldest 3 dropped
        node.session.put(key, b"\x00garbage")
        while latest.malformed == 0 and time.monotonic() < deadline + 5:
            assert latest.poll() is None
            time.sleep(0.01)
        assert latest.malformed == 1 and "not a valid Command" in latest.last_error


def test_close_wakes_a_waiter_and_negative_timeouts_do_not_block(bus):
    with Node("sub", RIG, bus, handle_signals=False) as node:
        sub = node.subscribe(keys.cmd(RIG, "pm"), Command)
        fifo = node.subscribe(keys.cmd(RIG, "pm"), Command, latest=False, capacity=4)
        assert sub.wait(-1.0) is None and fifo.wait_queued(-1.0) is False
        got: dict = {}
        started = threading.Event()

        def waiter():
            started.set()
            got["msg"] = sub.wait(60.0)
            got["queued"] = fifo.wait_queued(60.0)

        th = threading.Thread(target=waiter, daemon=True)
        th.start()
        assert started.wait(10)
        time.sleep(0.2)  # let it block (a close before the wait must return at once too)
        sub.close()
        fifo.close()
        # before close() rang the doorbell the waiter slept its whole 60 s timeout
        th.join(20.0)
        assert not th.is_alive(), "close() did not wake the thread blocked in wait()"
        assert got == {"msg": None, "queued": False}
        # closed: an untimed wait cannot hang; a timed one sleeps out its timeout (no spinning
        # in a caller's loop until its deadline)
        assert sub.wait(None) is None
        t0 = time.monotonic()
        got, calls = _calls_made_by(lambda: sub.wait(0.3))
        assert got is None and time.monotonic() - t0 >= 0.25 and calls < 200
