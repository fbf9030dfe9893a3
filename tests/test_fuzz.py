"""Short fuzzing of every parser of untrusted bytes (the long runs: `hil bench fuzz`).

The harnesses and their invariants live in tools/fuzz.py; here hypothesis drives them
with a few hundred inputs per parser (random bytes and mutated valid frames), and a short
atheris run checks the runner, including that it reports a crash.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hilstack.bus import schemas
from hilstack.tools import fuzz

SETTINGS = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


def mutated(seeds: list[bytes]) -> st.SearchStrategy[bytes]:
    """A valid input with a few bytes replaced, inserted or cut: deeper than random bytes."""

    def mutate(seed: bytes, edits: list[tuple[int, int, int]], cut: int) -> bytes:
        b = bytearray(seed)
        for kind, pos, val in edits:
            i = pos % (len(b) + 1)
            if kind == 0 and i < len(b):
                b[i] = val
            elif kind == 1:
                b.insert(i, val)
            elif i < len(b):
                del b[i]
        return bytes(b[: len(b) - cut % 8]) if cut % 3 == 0 else bytes(b)

    edit = st.tuples(st.integers(0, 2), st.integers(0, 1023), st.integers(0, 255))
    return st.builds(mutate, st.sampled_from(seeds), st.lists(edit, max_size=6), st.integers(0, 255))


def inputs(target: str) -> st.SearchStrategy[bytes]:
    _, seeds, _ = fuzz.TARGETS[target]
    return st.one_of(st.binary(max_size=300), mutated(seeds()))


@pytest.mark.parametrize("target", sorted(fuzz.TARGETS))
def test_the_seeds_are_valid_input(target):
    harness, seeds, _ = fuzz.TARGETS[target]
    for s in seeds():
        harness(s)


def test_seeds_reach_past_the_checks():
    """The seeds decode to real frames and messages, so mutations start deep in the parser."""
    from hilstack.drivers.velociroach.link import XBeeDeframer
    from hilstack.drivers.velociroach.mavlink import MavDecoder

    d = XBeeDeframer()
    assert sum(len(d.feed(s[2:], now_s=0.0)) for s in fuzz.seeds_xbee()) >= 20
    dec = MavDecoder()
    assert all(dec.decode(s[2:]) is not None for s in fuzz.seeds_mavlink()[:-1])
    for s in fuzz.seeds_bus():
        schemas.decode(s[1:], fuzz._bus_types()[s[0]])


@SETTINGS
@given(inputs("xbee"))
def test_fuzz_xbee_deframer(data):
    fuzz.fuzz_xbee(data)


@SETTINGS
@given(inputs("mavlink"))
def test_fuzz_mavlink_decoder(data):
    fuzz.fuzz_mavlink(data)


@SETTINGS
@given(inputs("bus"))
def test_fuzz_bus_decoders(data):
    fuzz.fuzz_bus(data)


def test_a_non_utf8_string_is_a_malformed_message():
    """Found by `hil bench fuzz`: msgspec let UnicodeDecodeError out of hilstack.bus.schemas.decode."""
    raw = bytes.fromhex("84a474797065aa68696c2e50696e0884a47479672f31")  # a Ping with a broken tag
    with pytest.raises(schemas.MalformedMessage):
        schemas.decode(raw, schemas.Ping)
    good = schemas.encode(schemas.Command(robot="roach", action=[0.0, 0.0]))
    bad = good.replace(b"roach", b"ro\xffch")
    with pytest.raises(schemas.MalformedMessage, match="Command"):
        schemas.decode(bad, schemas.Command)


def test_the_mavlink_crc_fixer_makes_a_flipped_frame_decode():
    from hilstack.drivers.velociroach.mavlink import MavDecoder

    frame = bytearray(fuzz._mav_seed_frames()[4])
    frame[14] ^= 0x10  # a payload bit: the CRC no longer matches
    dec = MavDecoder()
    assert dec.decode(bytes(frame)) is None and dec.corrupt == 1
    assert dec.decode(fuzz.fix_mavlink_crc(bytes(frame))) is not None


def test_a_broken_counter_is_caught_by_the_harness(monkeypatch):
    """Break the deframer's bookkeeping on purpose: the harness must call it a crash."""
    from hilstack.drivers.velociroach.link import XBeeDeframer

    def bad_without_kind(self, kind, why):  # counts the total but forgets the kind
        self.corrupt += 1
        self.last_error = why

    seed = fuzz.seeds_xbee()[1]  # starts with garbage
    fuzz.fuzz_xbee(seed)
    monkeypatch.setattr(XBeeDeframer, "_bad", bad_without_kind)
    with pytest.raises(fuzz.InvariantBroken, match="kinds add up"):
        fuzz.fuzz_xbee(seed)


def test_a_decoder_that_loses_count_is_caught(monkeypatch):
    from hilstack.drivers.velociroach.mavlink import MavDecoder

    monkeypatch.setattr(MavDecoder, "_fail", lambda self, why: None)
    with pytest.raises(fuzz.InvariantBroken, match="frames decoded"):
        fuzz.fuzz_mavlink(b"\x00\x10" + b"\xfd" * 40)


def planted_bug(data: bytes) -> None:
    """A parser with a crash the fuzzer must find (used by the runner test below)."""
    if len(data) >= 2 and data[0] == 0x7E:
        raise IndexError("planted bug")


def test_the_atheris_runner_counts_inputs_and_reports_a_crash():
    clean = fuzz.run_target("bus", 3000)
    assert clean["crashes"] == 0 and clean["inputs"] == 3000 and "crash" not in clean
    found = fuzz.run_target("tests.test_fuzz:planted_bug", 200_000)
    assert found["crashes"] == 1
    assert found["crash"]["exception"][0] == "IndexError: planted bug"
    assert found["crash"]["input_hex"].startswith("7e")


def test_unknown_target_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown fuzz target 'nope'"):
        fuzz.resolve("nope")
