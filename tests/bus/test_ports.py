"""A rig's own port (bus/ports.py): below the ephemeral range, and processes started together
(pids a few apart: parallel test runs, a sweep's workers) draw different ports."""

from __future__ import annotations

import itertools

import pytest

from hilstack.bus import ports


class _AlwaysFree:
    """A socket whose bind always succeeds: which ports a process would draw, whatever this host runs."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def bind(self, addr):
        pass


@pytest.mark.parametrize("slots", [1, 4])
def test_processes_started_together_draw_disjoint_ports(monkeypatch, slots):
    monkeypatch.setattr(ports.socket, "socket", _AlwaysFree)
    lo, hi = ports._unassigned_range()
    drawn = {}
    for pid in range(4000, 4008):  # eight processes started one after another
        monkeypatch.setattr(ports.os, "getpid", lambda pid=pid: pid)
        monkeypatch.setattr(ports, "_next", {})
        drawn[pid] = [ports.free_port(slot=slots - 1, slots=slots) for _ in range(50)]  # a test file's rigs
    for a, b in itertools.combinations(drawn, 2):
        assert not set(drawn[a]) & set(drawn[b]), (a, b)
    span = (hi - lo) // slots
    base = lo + (slots - 1) * span
    assert all(base <= p < base + span for ps in drawn.values() for p in ps)
    assert all(len(set(ps)) == len(ps) for ps in drawn.values())  # a process never repeats itself


def test_hil_port_slot_confines_every_draw_without_a_part_of_its_own(monkeypatch):
    """A test worker's demos, `hil` subprocesses and Ray tasks call free_port() without a part:
    $HIL_PORT_SLOT (set per pytest-xdist worker by tests/conftest.py) keeps them in the worker's."""
    monkeypatch.setattr(ports.socket, "socket", _AlwaysFree)
    monkeypatch.setattr(ports, "_next", {})
    lo, hi = ports._unassigned_range()
    span = (hi - lo) // 4
    monkeypatch.setenv("HIL_PORT_SLOT", "2/4")
    assert all(lo + 2 * span <= ports.free_port() < lo + 3 * span for _ in range(50))
    assert lo <= ports.free_port(slot=0, slots=4) < lo + span  # a caller's own part wins
    monkeypatch.delenv("HIL_PORT_SLOT")
    assert all(lo <= ports.free_port() < hi for _ in range(50))  # without it: the whole range
    for bad in ("4/4", "1", "a/b", "0/0"):
        monkeypatch.setenv("HIL_PORT_SLOT", bad)
        with pytest.raises(ValueError, match="HIL_PORT_SLOT"):
            ports.free_port()
