"""drivers/fdio.write_all: a device write is done once the kernel took every byte, however late
the writer was scheduled (pyserial 3.5 raised "Write timeout" then: a loaded machine failed a
healthy Dynamixel link); a device that takes nothing times out."""

from __future__ import annotations

import os
import tty

import pytest

from hilstack.drivers import fdio


def _pty() -> tuple[int, int]:
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave


def test_a_complete_write_is_done_even_when_the_writer_was_descheduled(monkeypatch):
    master, slave = _pty()
    try:
        clock = iter([0.0] + [100.0] * 100)  # the first reading, then 100 s later (a starved process)
        monkeypatch.setattr(fdio.time, "monotonic", lambda: next(clock))
        assert fdio.write_all(master, b"\xff\xff\xfd\x00\x01", 0.1, "test port") == 5
        assert os.read(slave, 16) == b"\xff\xff\xfd\x00\x01"
    finally:
        os.close(master)
        os.close(slave)


def test_a_device_that_takes_nothing_times_out_in_one_line():
    master, slave = _pty()  # nobody reads the slave end: its buffer fills
    try:
        with pytest.raises(TimeoutError, match=r"test port: write timed out \(\d+ of 1000000 bytes not taken"):
            fdio.write_all(master, b"x" * 1_000_000, 0.2, "test port")
    finally:
        os.close(master)
        os.close(slave)
