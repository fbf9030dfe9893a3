"""Protocol 2.0 codec and the X-series control table, checked against dynamixel-sdk's own bytes."""

from __future__ import annotations

import os
import select
import tty

import pytest
from dynamixel_sdk import GroupSyncWrite, PacketHandler, PortHandler
from hypothesis import given, settings
from hypothesis import strategies as st

from hilstack.drivers.dynamixel import protocol as p
from hilstack.drivers.dynamixel.control_table import (
    control_table,
    describe_hardware_error,
    parse_model_file,
    pos_counts,
    pos_rad,
    vel_counts,
    vel_rad_s,
)


@pytest.fixture
def sdk_wire():
    """dynamixel-sdk on one end of a real pty; the test reads what it sends on the other."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    port = PortHandler(os.ttyname(slave))
    assert port.openPort() and port.setBaudRate(1000000)

    def sent() -> bytes:
        out = b""
        while select.select([master], [], [], 0.05)[0]:
            out += os.read(master, 4096)
        return out

    yield port, PacketHandler(2.0), sent
    port.closePort()
    os.close(master)
    os.close(slave)


def test_crc_matches_the_sdk_bytes_and_its_unstuffed_payloads_still_parse(sdk_wire):
    port, ph, sent = sdk_wire
    ph.write4ByteTxOnly(port, 7, 104, 0x12345678)
    assert sent() == p.encode(7, p.WRITE, bytes([104, 0, 0x78, 0x56, 0x34, 0x12]))
    # 0x00FDFFFF puts FF FF FD in the payload. The protocol stuffs an FD after it; the
    # Python SDK (4.1) loses its stuffing (addStuffing rebinds a local list), so it sends
    # the payload as is. The parser must take both.
    ph.write4ByteTxOnly(port, 7, 116, 0x00FDFFFF)
    raw = sent()
    spec = p.encode(7, p.WRITE, bytes([116, 0, 0xFF, 0xFF, 0xFD, 0x00]))
    assert b"\xff\xff\xfd\xfd" in spec[7:] and len(spec) == len(raw) + 1
    for wire in (raw, spec):
        (pkt,) = p.Parser().feed(wire)
        assert (pkt.dxl_id, pkt.instruction, pkt.params) == (7, p.WRITE, bytes([116, 0, 0xFF, 0xFF, 0xFD, 0x00]))


def test_sync_write_bytes_match_the_sdk(sdk_wire):
    port, ph, sent = sdk_wire
    gv = control_table()["Goal Velocity"]
    g = GroupSyncWrite(port, ph, gv.address, gv.size)
    for i, v in [(1, 100), (2, -3)]:
        g.addParam(i, list(gv.encode(v)))
    g.txPacket()
    raw = sent()
    params = bytes([104, 0, 4, 0, 1]) + gv.encode(100) + bytes([2]) + gv.encode(-3)
    assert raw == p.encode(p.BROADCAST_ID, p.SYNC_WRITE, params)


def test_crc_is_the_protocol_crc_on_the_manual_example():
    # e-Manual Protocol 2.0, "Ping" example: instruction packet FF FF FD 00 01 03 00 01 19 4E
    assert p.encode(1, p.PING) == bytes.fromhex("FFFFFD0001030001194E")


def test_parser_skips_garbage_and_drops_bad_crc_split_anywhere():
    good = [p.encode(1, p.READ, bytes([132, 0, 4, 0])), p.encode_status(2, 0, b"\x01\x02")]
    bad = bytearray(p.encode(3, p.PING))
    bad[-1] ^= 0xFF
    stream = b"\x00\xff\x12" + good[0] + bytes(bad) + b"\xff\xff" + good[1]
    for cut in range(len(stream)):
        parser = p.Parser()
        pkts = parser.feed(stream[:cut]) + parser.feed(stream[cut:])
        assert [(q.dxl_id, q.instruction) for q in pkts] == [(1, p.READ), (2, p.STATUS)]
        assert parser.crc_errors == 1
        assert pkts[1].params == b"\x00\x01\x02"


def test_control_table_is_read_from_the_sdk_data_and_matches_the_manual():
    t = control_table("XM430-W350")
    addr = {n: t[n].address for n in ("Operating Mode", "Torque Enable", "Hardware Error Status", "Goal Current",
                                      "Goal Velocity", "Goal Position", "Present Current", "Present Velocity",
                                      "Present Position", "Present Temperature")}
    assert addr == {"Operating Mode": 11, "Torque Enable": 64, "Hardware Error Status": 70, "Goal Current": 102,
                    "Goal Velocity": 104, "Goal Position": 116, "Present Current": 126, "Present Velocity": 128,
                    "Present Position": 132, "Present Temperature": 146}
    assert t.span("Present Current", "Present Temperature") == (126, 21)
    with pytest.raises(KeyError, match="no control-table item"):
        t["Warp Drive"]
    with pytest.raises(ValueError, match="no control table"):
        parse_model_file("[type info]\nname\tvalue\n", "empty")


def test_item_codec_is_signed_where_the_servo_is():
    t = control_table()
    assert t["Present Velocity"].decode(0xFFFFFFFD) == -3  # what the SDK's getData returns
    assert t["Present Current"].decode(bytes([0xFE, 0xFF])) == -2
    assert t["Present Temperature"].decode(bytes([200])) == 200
    assert t["Goal Velocity"].encode(-1) == b"\xff\xff\xff\xff"
    with pytest.raises(ValueError, match="Torque Enable"):
        t["Torque Enable"].encode(256)
    assert pos_rad(pos_counts(1.0)) == pytest.approx(1.0, abs=1e-3)
    assert pos_counts(0.0) == 2048
    assert vel_counts(vel_rad_s(17)) == 17
    assert vel_rad_s(1) == control_table().units["Present Velocity"][0]  # the SDK file's unit
    assert describe_hardware_error(0x24) == "overheating, overload"


# --------------------------------------------------------------------- fuzzing (hypothesis)
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_parser_never_raises_on_noise(data):
    parser = p.Parser()
    for q in parser.feed(data):
        assert 0 <= q.dxl_id <= 0xFF


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 0xFE), st.integers(0, 0xFF), st.binary(max_size=64), st.binary(max_size=20),
       st.integers(1, 40))
def test_encode_parse_round_trip_through_noise_and_chunks(dxl_id, inst, params, noise, chunk):
    raw = noise + p.encode(dxl_id, inst, params)
    parser = p.Parser()
    got = []
    for i in range(0, len(raw), chunk):
        got += parser.feed(raw[i:i + chunk])
    assert got[-1] == p.Packet(dxl_id, inst, params)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 0xFE), st.binary(max_size=32), st.data())
def test_a_flipped_bit_never_yields_a_wrong_packet(dxl_id, params, data):
    raw = bytearray(p.encode(dxl_id, p.WRITE, params))
    bit = data.draw(st.integers(0, len(raw) * 8 - 1))
    raw[bit // 8] ^= 1 << (bit % 8)
    for q in p.Parser().feed(bytes(raw)):
        assert q == p.Packet(dxl_id, p.WRITE, params)  # CRC-16 catches every single-bit error
