"""The hand's CAN protocol (DBC via cantools), the telemetry assembler, the bus-load
arithmetic, the action mapping, and a little fuzzing of the decode paths (hypothesis)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilstack.drivers.shadow_hand.config import (
    ACT_INDEX,
    ACTUATED_JOINTS,
    JOINT_HIGH_RAD,
    JOINT_LOW_RAD,
    JOINT_NAMES,
    ShadowHandParams,
    joint_tracking_error,
    to_action,
    to_joint_rad,
)
from hilstack.drivers.shadow_hand.protocol import (
    CYCLE_IDS,
    ID_POS,
    ID_TARGET,
    ProtocolError,
    TelemetryAssembler,
    bus_load,
    database,
    decode,
    decode_targets,
    encode_targets,
    encode_telemetry,
    frame_bits_worst_case,
)
from hilstack.sim_backends.shadow_hand.emulator import SlcanDevice


def _cycle(cycle: int, q=None, qd=None, eff=None, **kw):
    q = np.linspace(-0.3, 1.2, 24) if q is None else q
    qd = np.linspace(-3, 3, 24) if qd is None else qd
    eff = np.linspace(-0.5, 0.5, 20) if eff is None else eff
    args = {"mode": 2, "faults": 0, "motor_fault_mask": 0, "rx_error_count": 0, "t_fw_ms": 1234, **kw}
    return encode_telemetry(q, qd, eff, cycle=cycle, **args)


def test_dbc_has_every_message_with_units_and_scaled_integers():
    db = database()
    names = {m.name for m in db.messages}
    assert {"HAND_ESTOP", "HOST_HEARTBEAT", "HAND_STATUS"} <= names
    assert {f"HAND_TARGET_{k}" for k in range(5)} <= names
    targets = [s for k in range(5) for s in db.get_message_by_name(f"HAND_TARGET_{k}").signals]
    assert [s.name for s in targets] == [f"target_{j}" for j in ACTUATED_JOINTS]
    assert all(s.unit == "rad" and s.length == 16 and s.is_signed and s.scale == 1e-4 for s in targets)
    pos = [s for m in ID_POS for s in db.get_message_by_frame_id(m).signals]
    assert [s.name for s in pos] == [f"pos_{j}" for j in JOINT_NAMES]
    assert all(m.length <= 8 for m in db.messages)  # classic CAN
    # e-stop outranks everything on the bus (lowest id wins arbitration)
    assert db.get_message_by_name("HAND_ESTOP").frame_id == min(m.frame_id for m in db.messages)


def test_targets_round_trip_to_the_dbc_resolution():
    t = to_joint_rad(np.linspace(-1, 1, 20))
    frames = encode_targets(t)
    assert [mid for mid, _ in frames] == list(ID_TARGET)
    got = np.zeros(20)
    for mid, data in frames:
        first, vals = decode_targets(mid, data)
        got[first:first + len(vals)] = vals
    np.testing.assert_allclose(got, t, atol=0.5e-4 + 1e-12)


def test_encode_refuses_non_finite_and_out_of_range():
    with pytest.raises(ProtocolError, match="not finite"):
        encode_targets(np.full(20, np.nan))
    with pytest.raises(ProtocolError, match="HAND_TARGET_0"):
        encode_targets(np.full(20, 5.0))  # beyond the int16 signal range: never wrapped
    with pytest.raises(ProtocolError, match="shape"):
        encode_targets(np.zeros(24))


def test_decode_names_what_is_wrong():
    with pytest.raises(ProtocolError, match="unknown CAN id 0x7FF"):
        decode(0x7FF, b"\0" * 8)
    with pytest.raises(ProtocolError, match=r"HAND_POS_0 \(0x200\) has 7 data bytes, the DBC says 8"):
        decode(0x200, b"\0" * 7)


def test_telemetry_saturates_spikes_but_refuses_nan():
    frames = _cycle(0, qd=np.full(24, 100.0))  # 100 rad/s is past the ±32.767 signal range
    asm = TelemetryAssembler()
    tel = None
    for mid, data in frames:
        tel = asm.feed(mid, decode(mid, data)[1]) or tel
    np.testing.assert_allclose(tel.qd_rad_s, 32.767)
    with pytest.raises(ProtocolError, match="not finite"):
        _cycle(0, q=np.full(24, np.nan))


def test_assembler_returns_complete_cycles_and_counts_drops():
    asm = TelemetryAssembler()
    q = np.linspace(-0.3, 1.2, 24)
    for mid, data in _cycle(7, q=q):
        tel = asm.feed(mid, decode(mid, data)[1])
    assert tel is not None and tel.cycle == 7 and tel.mode == 2 and tel.t_fw_ms == 1234
    np.testing.assert_allclose(tel.q_rad, q, atol=0.5e-4)
    # cycle 8 loses two frames: not used, two drops counted
    frames = [f for f in _cycle(8) if f[0] not in (ID_POS[1], ID_POS[3])]
    out = [asm.feed(mid, decode(mid, data)[1]) for mid, data in frames]
    assert out[-1] is None and asm.incomplete_cycles == 1 and asm.dropped_frames == 2
    # cycles 9 and 10 never arrive: 11 is complete, 2 whole cycles counted as dropped
    for mid, data in _cycle(11):
        tel = asm.feed(mid, decode(mid, data)[1])
    assert tel.cycle == 11 and asm.cycles == 2
    assert asm.dropped_frames == 2 + 2 * len(CYCLE_IDS)
    # the 8-bit counter wraps without counting drops
    for c in (255, 0):
        for mid, data in _cycle(c):
            asm.feed(mid, decode(mid, data)[1])
    assert asm.dropped_frames == 2 + 2 * len(CYCLE_IDS) + (255 - 11 - 1) * len(CYCLE_IDS)


def test_bus_load_budget():
    # 8 data bytes, 11-bit id: 111 bits + 24 worst-case stuff bits (incl. 3-bit IFS) = 135
    assert frame_bits_worst_case(8) == 135
    assert frame_bits_worst_case(0) == 55
    load = bus_load(telemetry_hz=100, command_hz=10, heartbeat_hz=10)
    # 17 eight-byte telemetry frames + the status frame per cycle at 100 Hz
    assert load["telemetry"] == pytest.approx(18 * 135 * 100 / 1e6)
    assert load["total"] < 0.3  # the budget in docs/shadow_hand.md: under half the bus
    assert bus_load(telemetry_hz=1000, command_hz=10, heartbeat_hz=10)["total"] > 1.0  # 1 kHz would not fit


def test_action_mapping_inverse_and_limits():
    lo, hi = JOINT_LOW_RAD[ACT_INDEX], JOINT_HIGH_RAD[ACT_INDEX]
    np.testing.assert_allclose(to_joint_rad(-np.ones(20)), lo)
    np.testing.assert_allclose(to_joint_rad(np.ones(20)), hi)
    a = np.linspace(-0.9, 0.9, 20)
    np.testing.assert_allclose(to_action(to_joint_rad(a)), a)
    assert np.all(to_action(hi + 1.0) == 1.0)  # a reading past a limit maps to the limit
    state = np.zeros(48)
    state[ACT_INDEX] = to_joint_rad(a)
    state[ACT_INDEX[3]] += 0.02
    te = joint_tracking_error(state, a)
    assert te["worst_joint"] == ACTUATED_JOINTS[3] and te["max_rad"] == pytest.approx(0.02)


# ---------------------------------------------------------------------- fuzzing
@settings(max_examples=300, deadline=None)
@given(mid=st.integers(0, 0x7FF), data=st.binary(max_size=8))
def test_fuzz_decode_only_raises_protocol_error(mid, data):
    try:
        name, vals = decode(mid, data)
    except ProtocolError:
        return
    assert all(np.isfinite(v) for v in vals.values())


@settings(max_examples=300, deadline=None)
@given(targets=st.lists(st.floats(-3.2768, 3.2767), min_size=20, max_size=20))
def test_fuzz_target_round_trip(targets):
    got = np.zeros(20)
    for mid, data in encode_targets(np.array(targets)):
        first, vals = decode_targets(mid, data)
        got[first:first + len(vals)] = vals
    np.testing.assert_allclose(got, targets, atol=0.5e-4 + 1e-9)


@settings(max_examples=300, deadline=None)
@given(line=st.text(alphabet="tTCOSsVF0123456789ABCDEFabcdefZ \x07", max_size=24))
def test_fuzz_slcan_device_parser(line):
    """The emulator's adapter side never crashes on a garbled line from the host."""
    import os

    r, w = os.pipe()
    try:
        dev = SlcanDevice(w)
        dev.open = True
        frame = dev._command(line)
        os.set_blocking(r, False)
        answer = os.read(r, 4096) if line else b""
    finally:
        os.close(r)
        os.close(w)
    if frame is not None:
        mid, data = frame
        assert line[0] == "t" and 0 <= mid <= 0x7FF and len(line) == 5 + 2 * len(data)
        assert answer == b"z\r"
    elif line:
        assert answer in (b"\r", b"\a", b"V1013\r", b"F00\r")


# ---------------------------------------------------------------------- the driver's SLCAN receive path
@pytest.fixture(scope="module")
def loop_bus():
    """python-can's real slcan interface on pyserial's loop:// (what is written is read back)."""
    import can

    bus = can.Bus(interface="slcan", channel="loop://", bitrate=1_000_000, sleep_after_open=0, timeout=0.001)
    yield bus
    bus.shutdown()


def _drain(drv, bus) -> list:
    got = []
    for _ in range(64):
        msg = drv._recv_one(bus, timeout_s=0.001)
        if msg is None and not bus.serialPortOrig.in_waiting:
            break
        if msg is not None:
            got.append(msg)
    return got


def test_garbled_slcan_lines_are_corrupt_frames_not_a_dead_link(loop_bus):
    """Regression: a short line (IndexError in python-can) or non-ASCII bytes (left in
    python-can's buffer, failing every later read) took the whole link down."""
    from hilstack.drivers.shadow_hand.driver import ShadowHandDriver

    drv = ShadowHandDriver(ShadowHandParams())
    loop_bus.serialPortOrig.reset_input_buffer()
    for junk in (b"t12\r", b"T1\r", b"t2008ZZ\r", b"\xff\xfe\r"):
        loop_bus.serialPortOrig.write(junk)
        _drain(drv, loop_bus)
    assert drv.corrupt_frames == 4
    mid, data = encode_targets(np.zeros(20))[0]
    loop_bus.serialPortOrig.write(f"t{mid:03X}8{data.hex().upper()}\r".encode())
    got = _drain(drv, loop_bus)  # the link still works after all that
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(mid, data)]


@settings(max_examples=200, deadline=None)
@given(junk=st.binary(max_size=30))
def test_fuzz_driver_slcan_receive(loop_bus, junk):
    from hilstack.drivers.shadow_hand.driver import ShadowHandDriver

    drv = ShadowHandDriver(ShadowHandParams())
    loop_bus.flush()
    loop_bus.serialPortOrig.write(junk + b"\r")
    for m in _drain(drv, loop_bus):  # whatever comes out goes through the frame handler too
        drv._handle(m, 0.0)
    mid, data = encode_targets(np.zeros(20))[1]
    loop_bus.serialPortOrig.write(f"t{mid:03X}8{data.hex().upper()}\r".encode())
    assert (mid, data) in [(m.arbitration_id, bytes(m.data)) for m in _drain(drv, loop_bus)]


def test_frame_handler_sorts_own_foreign_error_and_corrupt_frames():
    import can

    from hilstack.drivers.shadow_hand.driver import ShadowHandDriver

    drv = ShadowHandDriver(ShadowHandParams())
    mid, data = encode_targets(np.zeros(20))[0]
    drv._handle(can.Message(arbitration_id=mid, data=data, is_extended_id=False), 0.0)  # our own, echoed
    drv._handle(can.Message(arbitration_id=0x7E0, data=b"\0" * 8, is_extended_id=False), 0.0)  # another node
    drv._handle(can.Message(arbitration_id=0x200, data=b"\0" * 3, is_extended_id=False), 0.0)  # short POS frame
    drv._handle(can.Message(arbitration_id=0x4, is_error_frame=True), 0.0)
    h = drv.health()  # unconfigured: counters only
    assert (drv.frames_received, drv.foreign_frames, drv.corrupt_frames, drv.bus_error_frames) == (0, 1, 1, 1)
    assert "HAND_POS_0" in drv.last_corrupt and not h.ok
