"""Exit with the parent: the one convention of every process a hilstack process starts.

The parent puts its pid in the child's environment (:func:`child_env`, variable
:data:`PARENT_PID_ENV`): a driver's device emulator (drivers/emulator_process.py), a demo's
or `hil mbrl`'s rig process, `hil up`'s per-robot processes. The child calls
:func:`exit_with_parent` once at start: a daemon thread polls ``os.getppid()`` and, once
the parent is gone (killed with SIGKILL, crashed: its cleanup never ran), calls
``on_gone`` (default: SIGTERM to itself, so a driver node stops its robot and exits as on
Ctrl-C, and an emulator ends its loop as on ``EmulatorProcess.stop()``). The variable is
taken out of the environment: a process the child starts is watched only if it sets it
again. Pure standard library: it lives in ``bus/``, the layer every package may import.
"""

from __future__ import annotations

import faulthandler
import io
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable

#: environment variable holding the pid of the process that started this one
PARENT_PID_ENV = "HIL_PARENT_PID"


#: the signal that makes a hilstack process print every thread's Python stack to stderr
DUMP_STACKS_SIGNAL = signal.SIGUSR1


def dump_stacks_on_signal() -> None:
    """`kill -USR1 PID` prints where every thread of this process is (stderr, faulthandler):
    how `hil up` and the tests say where a node that did not stop in time was stuck. Where
    ``sys.stderr`` is no file (a verb run in-process by typer's CliRunner), the process's own."""
    try:
        faulthandler.register(DUMP_STACKS_SIGNAL, all_threads=True)
    except (io.UnsupportedOperation, AttributeError, ValueError):
        faulthandler.register(DUMP_STACKS_SIGNAL, file=sys.__stderr__, all_threads=True)


#: set once SIGINT or SIGTERM reached this process (after :func:`catch_stop_signals`)
_stop_signalled = threading.Event()
#: what a stop signal does: one callback per node that handles signals (:func:`on_stop_signal`)
_on_stop: list[Callable[[], None]] = []
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: the handlers :func:`on_stop_signal` replaced (None: it installed none, or put them back)
_saved: dict[int, object] | None = None


def _stop_handler(signum: int, frame: object) -> None:  # noqa: ARG001
    _stop_signalled.set()
    for cb in list(_on_stop):
        cb()


def catch_stop_signals() -> None:
    """From now on SIGINT and SIGTERM ask this process to stop, whatever it inherited.

    A process started in the background or by a supervisor may inherit SIGTERM (or SIGINT)
    *ignored*, and an ignored disposition survives ``exec``: a stop sent to such a `hil up`
    robot process before its node existed was lost, and the robot ran on until killed (CI stops
    33 and 34; tests/arms/test_rig_up.py). Called first by `hil up`, so a stop that comes while
    it loads is kept (:func:`stop_signalled`) and honoured by the node it then creates (other
    verbs register through :func:`on_stop_signal` when they start driving). Main thread only
    (Python's rule for signal handlers)."""
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            signal.signal(sig, _stop_handler)


class StopRequested(Exception):
    """A stop signal (Ctrl-C, SIGTERM) ended a wait before what it waited for came (a
    controller waiting for its robot's spec, `hil teleop` with no rig up). Not a failure:
    `hil` verbs end with one line and exit 0, as `hil drive` does when stopped early
    (tools/common.py: user_errors)."""


def stop_signalled() -> bool:
    """Whether a stop signal reached this process since :func:`catch_stop_signals`."""
    return _stop_signalled.is_set()


def on_stop_signal(cb: Callable[[], None]) -> Callable[[], None]:
    """Call ``cb`` on SIGINT/SIGTERM, at once if one came already (while the process loaded).
    Every registered callback runs (several nodes in one process all stop). Installs the
    handlers if this process does not catch stop signals yet, and then puts the previous
    ones back once the last callback is forgotten (a library user's Ctrl-C is theirs again;
    a `hil up` that called :func:`catch_stop_signals` keeps catching). Returns the function
    that forgets ``cb``."""
    global _saved
    main = threading.current_thread() is threading.main_thread()
    if main and _saved is None and signal.getsignal(signal.SIGTERM) is not _stop_handler:
        _saved = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
        catch_stop_signals()
    _on_stop.append(cb)
    if _stop_signalled.is_set():
        cb()

    def forget() -> None:
        global _saved
        if cb in _on_stop:
            _on_stop.remove(cb)
        if not _on_stop and _saved is not None and threading.current_thread() is threading.main_thread():
            for sig, h in _saved.items():
                signal.signal(sig, h if h is not None else signal.SIG_DFL)
            _saved = None
            _stop_signalled.clear()  # taken by the callbacks that were running

    return forget


def child_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's environment) with this process as the child's parent."""
    return {**(os.environ if env is None else env), PARENT_PID_ENV: str(os.getpid())}


def _terminate_self() -> None:
    logging.getLogger("hil").warning("the process that started this one is gone: stopping")
    os.kill(os.getpid(), signal.SIGTERM)


def exit_with_parent(on_gone: Callable[[], None] | None = None, poll_s: float = 0.5) -> int | None:
    """Watch the parent named in :data:`PARENT_PID_ENV` (popped from the environment); call
    ``on_gone`` (default: SIGTERM to this process) once it is gone. Returns the parent's pid,
    or None when this process was not started with the variable (nothing is watched)."""
    pid = os.environ.pop(PARENT_PID_ENV, None)
    dump_stacks_on_signal()
    if not pid:
        return None
    parent = int(pid)
    act = on_gone or _terminate_self

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        act()

    threading.Thread(target=watch, daemon=True, name="exit-with-parent").start()
    return parent
