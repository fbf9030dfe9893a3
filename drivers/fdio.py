"""Bounded writes to a non-blocking device file descriptor (serial port, pty).

A write is done once every byte is in the kernel's buffer, however long the process waited
to be scheduled: pyserial 3.5's ``Serial.write`` with a ``write_timeout`` raises
"Write timeout" when the timeout has passed by the time ``os.write`` returns, even when that
call wrote everything (pyserial issue #281), which on a loaded machine failed a healthy
Dynamixel link. Here only a device that stops taking bytes for ``timeout_s`` times out.
"""

from __future__ import annotations

import os
import select
import time


def write_all(fd: int, data: bytes, timeout_s: float, what: str = "device") -> int:
    """Write all of ``data`` to non-blocking ``fd``; TimeoutError when the device takes no
    byte for ``timeout_s`` (nobody reading the pty, a stalled adapter). Returns ``len(data)``."""
    view = memoryview(data)
    deadline = time.monotonic() + timeout_s
    while view:
        try:
            n = os.write(fd, view)
        except BlockingIOError:
            n = 0
        if n:
            view = view[n:]
            deadline = time.monotonic() + timeout_s  # it takes bytes: the bound is per stall
            continue
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"{what}: write timed out ({len(view)} of {len(data)} bytes not taken in "
                               f"{timeout_s:g} s; nobody reading?)")
        select.select([], [fd], [], left)
    return len(data)
