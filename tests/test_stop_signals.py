"""bus/lifetime.py's stop signals, in a child process of its own (signal handlers are the
process's): every signal-handling node stops; the process's own handlers come back when its
last node closes; and in a process that catches stop signals from its start (`hil up`), a node
created after the signal (it came while the drivers loaded) starts stopped, also where SIGTERM
was inherited ignored."""

from __future__ import annotations

import subprocess
import sys

from tests.helpers import ROOT, free_port

CHILD = """
import os, signal
signal.signal(signal.SIGTERM, signal.SIG_IGN)  # as inherited from a supervisor
from hilstack.bus.lifetime import catch_stop_signals
from hilstack.bus.node import Node
from hilstack.bus.session import BusConfig
bus = BusConfig(endpoint="tcp/127.0.0.1:{port}")
a = Node("a", "t", bus)
b = Node("b", "t", bus)
os.kill(os.getpid(), signal.SIGTERM)
print("both stopped", a.stop_event.wait(5) and b.stop_event.wait(5))
a.close(); b.close()
print("handler given back", signal.getsignal(signal.SIGTERM) is signal.SIG_IGN)
catch_stop_signals()  # as `hil up` does first
os.kill(os.getpid(), signal.SIGTERM)  # while it loads: no node yet
c = Node("c", "t", bus)  # made after the signal: starts stopped
print("late stopped", c.stop_event.is_set())
quiet = Node("q", "t", bus, handle_signals=False)
print("quiet stopped", quiet.stop_event.is_set())
c.close(); quiet.close()
"""


def test_a_stop_signal_stops_every_node_and_the_nodes_made_after_it():
    out = subprocess.run([sys.executable, "-c", CHILD.format(port=free_port())], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:4] == ["both stopped True", "handler given back True", "late stopped True",
                                           "quiet stopped False"], out.stdout


def test_a_process_that_ends_with_a_node_open_exits():
    """zenoh's callback threads are non-daemon: a node left open held the interpreter's exit forever."""
    child = ("from hilstack.bus.node import Node\nfrom hilstack.bus.session import BusConfig\n"
             f"n = Node('left-open', 't', BusConfig(endpoint='tcp/127.0.0.1:{free_port()}'))\n"
             "n.subscribe('hil/t/x', bytes)\nprint('made')\n")
    out = subprocess.run([sys.executable, "-c", child], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert (out.returncode, out.stdout.strip()) == (0, "made"), out.stderr
