"""Radio link unit tests: MAVLink codec, XBee deframer, tlog, command checks, vanished port.

No sleeps and no physics here; the pty tests wait on conditions with short timeouts.
"""

from __future__ import annotations

import math
import os
import threading
import time
import tty

import numpy as np
import pytest

from hilstack.drivers.base import CommandError, LinkError
from hilstack.drivers.velociroach import mavlink as vm
from hilstack.drivers.velociroach.config import VelociRoachParams
from hilstack.drivers.velociroach.link import (
    FdPort,
    RadioLink,
    XBeeDeframer,
    addr64,
    open_serial,
    xbee_rx64,
    xbee_tx64,
)

ADDR = "0013A20040A1B2C3"
TEL = {
    "t_fw_ms": 123456, "gyro_rps": [0.1, -0.2, 0.3], "accel_mps2": [0.0, 0.5, 9.81],
    "crank_angle_rad": [1.0, 4.0], "crank_vel_rps": [5.5, -5.5], "bemf_v": [1.25, -1.25], "vbat_v": 3.9,
    "duty": [0.5, -0.5], "faults": 3,
}


def robot_frames() -> list[bytes]:
    """One MAVLink frame of every robot -> base message."""
    e = vm.MavEncoder(vm.ROBOT_SYSID, vm.ROBOT_COMPID)
    return [
        e.heartbeat(robot=True, faults=1),
        e.telemetry(TEL, last_cmd_seq=7, rx_good=100, rx_corrupt=2),
        e.pid_gains(9, 0.05, 1.5, 0.0, vm.mav.ROACH_RESULT_ACCEPTED),
        e.status_text(vm.mav.ROACH_SEVERITY_WARNING, 1, "watchdog: no command for 0.50s"),
    ]


def wrap_rx(frames: list[bytes]) -> bytes:
    return b"".join(xbee_rx64(addr64(ADDR), f) for f in frames)


# --------------------------------------------------------------------------- codec
def test_every_message_round_trips_through_xbee_and_mavlink():
    base = vm.MavEncoder(vm.BASE_SYSID, vm.BASE_COMPID)
    to_robot = [
        (base.leg_velocity(41, 3.5, -2.25, 15.0), {"cmd_seq": 41, "left_rps": 3.5, "right_rps": -2.25}),
        (base.pwm(42, 0.5, -1.0), {"cmd_seq": 42, "duty_left": 0.5, "duty_right": -1.0}),
        (base.heartbeat(), {"type": vm.mav.MAV_TYPE_GCS}),
        (base.pid_set(3, 0.1, 2.0, 0.01), {"request_id": 3, "kp": 0.1, "ki": 2.0, "kd": 0.01}),
        (base.pid_get(4), {"request_id": 4}),
    ]
    robot = RadioLink(None, role="robot", robot_addr64=ADDR)
    got = robot.feed(b"".join(xbee_tx64(addr64(ADDR), f) for f, _ in to_robot))
    assert len(got) == len(to_robot)
    for m, (_, want) in zip(got, to_robot, strict=True):
        for k, v in want.items():
            assert getattr(m, k) == pytest.approx(v, rel=1e-6), (m.get_type(), k)

    link = RadioLink(None, role="base", robot_addr64=ADDR)
    hb, tel, gains, text = link.feed(wrap_rx(robot_frames()))
    assert hb.get_type() == "HEARTBEAT" and hb.custom_mode == 1 and hb.get_srcSystem() == vm.ROBOT_SYSID
    assert tel.time_fw_ms == 123456 and tel.last_cmd_seq == 7 and tel.rx_good == 100 and tel.rx_corrupt == 2
    np.testing.assert_allclose(tel.gyro, TEL["gyro_rps"], rtol=1e-6)
    np.testing.assert_allclose(tel.accel, TEL["accel_mps2"], rtol=1e-6)
    np.testing.assert_allclose(tel.crank_angle, TEL["crank_angle_rad"], rtol=1e-6)
    np.testing.assert_allclose(tel.crank_vel, TEL["crank_vel_rps"], rtol=1e-6)
    np.testing.assert_allclose(tel.bemf, TEL["bemf_v"], rtol=1e-6)
    np.testing.assert_allclose(tel.duty, TEL["duty"], rtol=1e-6)
    assert tel.vbat == pytest.approx(3.9) and tel.faults == 3
    assert (gains.request_id, gains.kp, gains.ki, gains.result) == (9, pytest.approx(0.05), 1.5, 0)
    assert text.text == "watchdog: no command for 0.50s" and text.faults == 1
    assert link.corrupt_frames == 0 and link.dropped_frames == 0 and link.frames_received == 4


def test_every_frame_fits_one_xbee_payload():
    for f in robot_frames():
        assert len(f) <= vm.XBEE_MAX_PAYLOAD_B


# --------------------------------------------------------------------------- deframer
def test_deframer_skips_bad_checksum_truncation_garbage_and_bad_crc():
    frames = robot_frames()
    good = [xbee_rx64(addr64(ADDR), f) for f in frames]
    bad_sum = bytearray(good[1])
    bad_sum[-1] ^= 0xFF
    truncated = good[1][: len(good[1]) // 2]
    bad_crc_payload = bytearray(frames[1])
    bad_crc_payload[20] ^= 0x01
    bad_crc = xbee_rx64(addr64(ADDR), bytes(bad_crc_payload))
    stream = (b"\x00\x13garbage" + good[0] + bytes(bad_sum) + good[1] + truncated + good[2]
              + b"\xff\xfe" + bad_crc + good[3])
    link = RadioLink(None, role="base", robot_addr64=ADDR)
    msgs = link.feed(stream)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "ROACH_TELEMETRY", "ROACH_PID_GAINS", "ROACH_STATUS_TEXT"]
    s = link.stats()
    assert s["garbage_runs"] == 2
    assert s["bad_xbee_checksum"] == 1
    assert s["truncated_frames"] == 1
    assert s["bad_mavlink"] == 1
    assert link.corrupt_frames == 5


def test_deframer_byte_at_a_time_and_split_frames():
    raw = wrap_rx(robot_frames())
    d = XBeeDeframer()
    out = []
    for i in range(len(raw)):
        out += d.feed(raw[i : i + 1], now_s=0.0)
    assert len(out) == 4 and d.corrupt == 0


def test_truncated_frame_at_end_of_stream_is_dropped_when_stale():
    raw = xbee_rx64(addr64(ADDR), robot_frames()[0])
    d = XBeeDeframer()
    assert d.feed(raw[:10], now_s=0.0) == []
    assert d.feed(b"", now_s=1.0) == [] and d.truncated == 1
    assert len(d.feed(raw, now_s=1.1)) == 1


def test_a_corrupt_run_split_over_reads_counts_once():
    """39 injected runs once became 66: each read that saw part of a run counted it again."""
    frames = robot_frames()
    good = [xbee_rx64(addr64(ADDR), f) for f in frames]
    bad_sum = bytearray(good[1])
    bad_sum[-1] ^= 0x5A
    noise = bytes(range(1, 40))  # no 0x7E in it
    stream = good[0] + noise + good[1] + bytes(bad_sum) + good[2] + noise + good[3] + noise + good[0]
    for chunk in (1, 3, 7, len(stream)):
        d = XBeeDeframer()
        out = []
        for i in range(0, len(stream), chunk):
            out += d.feed(stream[i : i + chunk], now_s=0.0)
        assert len(out) == 5, chunk
        assert (d.garbage, d.bad_checksum, d.truncated, d.bad_length) == (3, 1, 0, 0), chunk
        assert d.corrupt == 4, chunk


@pytest.mark.parametrize("inner", [
    b"\x7e\x00\x05\x01\x02\x03\x04\x05\x06",  # a plausible frame start inside the body
    b"\x7e\x7e\xff",  # an impossible length inside the body
])
@pytest.mark.parametrize("chunk", [1, 5, 1000])
def test_a_start_byte_inside_a_broken_frame_is_not_a_second_error(inner, chunk):
    """A broken frame counts once, whatever 0x7E bytes its body holds."""
    good = xbee_rx64(addr64(ADDR), robot_frames()[0])
    broken = bytearray(xbee_rx64(addr64(ADDR), b"\x01\x02" + inner + b"\x03" * 20))
    broken[-1] ^= 0x5A
    for tail_is_start in (False, True):
        if tail_is_start:
            broken[-1] = 0x7E  # the broken checksum byte itself looks like a frame start
        stream = good + bytes(broken) + good + good
        d = XBeeDeframer()
        out = []
        for i in range(0, len(stream), chunk):
            out += d.feed(stream[i : i + chunk], now_s=0.0)
        assert len(out) == 3
        assert (d.corrupt, d.bad_checksum, d.bad_length, d.truncated, d.garbage) == (1, 1, 0, 0, 0)


def test_a_pause_ends_a_garbage_run():
    d = XBeeDeframer()
    d.feed(b"\x01\x02", now_s=0.0)
    d.feed(b"\x03", now_s=0.05)  # the same run
    assert d.garbage == 1
    d.feed(b"\x04", now_s=1.0)  # a new burst after a silence
    assert d.garbage == 2


def test_corrupt_frames_are_not_counted_again_as_dropped():
    e = vm.MavEncoder(vm.ROBOT_SYSID, vm.ROBOT_COMPID)
    frames = [e.heartbeat(robot=True) for _ in range(12)]
    raws = [xbee_rx64(addr64(ADDR), f) for f in frames]
    bad_sum = bytearray(raws[3])
    bad_sum[-1] ^= 0x5A  # XBee layer: bad checksum
    bad_crc = bytearray(frames[6])
    bad_crc[-3] ^= 0x01  # MAVLink layer: bad CRC in a valid XBee frame
    stream = (b"".join(raws[:3]) + bytes(bad_sum) + b"".join(raws[4:6]) + xbee_rx64(addr64(ADDR), bytes(bad_crc))
              + raws[7] + raws[9] + raws[10] + raws[11])  # frame 8 really lost on the air
    link = RadioLink(None, role="base", robot_addr64=ADDR)
    assert len(link.feed(stream)) == 9
    assert link.corrupt_frames == 2 and link.dropped_frames == 1 and link.frames_received == 9
    # the invariant: every frame sent is accounted for exactly once
    assert link.frames_received + link.corrupt_frames + link.dropped_frames == len(frames)


def test_corrupt_frame_fed_in_a_later_read_than_its_gap():
    """The gap and the corrupt frame that explains it may be seen in either order."""
    e = vm.MavEncoder(vm.ROBOT_SYSID, vm.ROBOT_COMPID)
    frames = [e.heartbeat(robot=True) for _ in range(4)]
    bad_crc = bytearray(frames[2])
    bad_crc[-3] ^= 0x01
    link = RadioLink(None, role="base", robot_addr64=ADDR)
    link.feed(wrap_rx([frames[0], frames[1]]))
    link.feed(wrap_rx([bytes(bad_crc), frames[3]]))
    assert (link.frames_received, link.corrupt_frames, link.dropped_frames) == (3, 1, 0)


def test_encoder_sequence_numbers_are_unique_across_threads():
    """The driver packs commands and heartbeats on two threads; no sequence number twice."""
    import sys
    from collections import Counter

    enc = vm.MavEncoder(vm.BASE_SYSID, vm.BASE_COMPID)
    per_thread = 1024
    out: list[list[bytes]] = [[], []]

    def work(k: int) -> None:
        for _ in range(per_thread):
            out[k].append(enc.heartbeat())

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible to provoke the race
    try:
        ts = [threading.Thread(target=work, args=(k,)) for k in range(2)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
    finally:
        sys.setswitchinterval(old)
    seqs = Counter(f[4] for f in out[0] + out[1])  # MAVLink v2: the sequence is byte 4
    assert set(seqs.values()) == {2 * per_thread // 256}, seqs.most_common(3)


def test_counts_are_exact_over_a_real_pty():
    """39 injected runs must read as 39 whatever the pty's reads do; no corrupt frame as a drop."""
    import random

    rng = random.Random(3)
    enc = vm.MavEncoder(vm.ROBOT_SYSID, vm.ROBOT_COMPID)
    stream, n_frames, n_garbage, n_bad = [], 300, 0, 0
    for i in range(n_frames):
        raw = bytearray(xbee_rx64(addr64(ADDR), enc.heartbeat(robot=True)))
        if i % 7 == 3:
            stream.append(bytes(rng.choice([b for b in range(256) if b != 0x7E]) for _ in range(rng.randint(1, 40))))
            n_garbage += 1
        if i % 11 == 5:
            raw[-1] ^= 0x5A  # bad XBee checksum
            n_bad += 1
        stream.append(bytes(raw))
    data = b"".join(stream)

    master, slave = os.openpty()
    tty.setraw(slave)
    link = RadioLink.open(os.ttyname(slave), 230400, role="base", robot_addr64=ADDR)
    os.close(slave)

    def write():  # odd-sized writes so frames and runs straddle the reader's reads
        i = 0
        while i < len(data):
            n = rng.randint(1, 97)
            os.write(master, data[i : i + n])
            i += n

    w = threading.Thread(target=write)
    w.start()
    got = 0
    deadline = time.monotonic() + 10.0
    while got < n_frames - n_bad and time.monotonic() < deadline:
        got += len(link.receive(timeout_s=0.02))
    w.join()
    link.close()
    os.close(master)
    s = link.stats()
    assert got == n_frames - n_bad
    assert (s["garbage_runs"], s["bad_xbee_checksum"], s["truncated_frames"]) == (n_garbage, n_bad, 0)
    assert link.dropped_frames == 0 and link.corrupt_frames == n_garbage + n_bad, str(s)


def test_sequence_gaps_count_as_dropped():
    e = vm.MavEncoder(vm.ROBOT_SYSID, vm.ROBOT_COMPID)
    frames = [e.heartbeat(robot=True) for _ in range(6)]
    link = RadioLink(None, role="base", robot_addr64=ADDR)
    link.feed(wrap_rx([frames[0], frames[1], frames[4], frames[5]]))
    assert link.dropped_frames == 2 and link.frames_received == 4


def test_frames_for_another_robot_are_ignored():
    other = xbee_rx64(addr64("0013A20040FFFFFF"), robot_frames()[0])
    link = RadioLink(None, role="base", robot_addr64=ADDR)
    assert link.feed(other) == [] and link.foreign_frames == 1 and link.corrupt_frames == 0


# --------------------------------------------------------------------------- tlog
def test_tlog_is_read_back_by_pymavlink(tmp_path):
    from pymavlink import mavutil

    path = tmp_path / "run.tlog"
    link = RadioLink(open_serial("loop://", 230400), role="base", robot_addr64=ADDR, tlog=path)
    enc = vm.MavEncoder(vm.BASE_SYSID, vm.BASE_COMPID)
    link.send(enc.leg_velocity(1, 2.0, 2.0, 15.0))
    link.feed(wrap_rx(robot_frames()))
    link.close()
    mlog = mavutil.mavlink_connection(str(path), dialect="velociroach")
    types = []
    while (m := mlog.recv_match()) is not None:
        types.append(m.get_type())
        if m.get_type() == "ROACH_TELEMETRY":
            assert m.time_fw_ms == 123456 and abs(m._timestamp - time.time()) < 60
    assert types == ["ROACH_LEG_VELOCITY_CMD", "HEARTBEAT", "ROACH_TELEMETRY", "ROACH_PID_GAINS", "ROACH_STATUS_TEXT"]


# --------------------------------------------------------------------------- commands
@pytest.mark.parametrize("left,right", [(math.nan, 0.0), (0.0, math.inf), (15.01, 0.0), (0.0, -100.0)])
def test_bad_commands_never_reach_the_wire(left, right):
    port = open_serial("loop://", 230400)
    link = RadioLink(port, role="base", robot_addr64=ADDR)
    enc = vm.MavEncoder(vm.BASE_SYSID, vm.BASE_COMPID)
    bad_writes = [
        lambda: link.send(enc.leg_velocity(1, left, right, 15.0)),
        lambda: link.send(enc.pwm(2, left / 15.0, right / 15.0) if math.isfinite(left + right)
                          else enc.pwm(2, left, right)),
    ]
    for bad in bad_writes:
        sent, waiting = link.frames_sent, port.in_waiting
        with pytest.raises(vm.EncodeError):
            bad()
        assert (link.frames_sent, port.in_waiting) == (sent, waiting)  # this write sent nothing
    sent = link.frames_sent
    link.send(enc.leg_velocity(3, 15.0, -15.0, 15.0))  # the limit itself is fine
    assert link.frames_sent == sent + 1 and port.in_waiting > 0


class FakeRobot:
    """The robot end of a pty: heartbeat + telemetry at 50 Hz, records every command."""

    def __init__(self, master_fd: int):
        self.port = FdPort(master_fd, name="fake-robot")
        self.link = RadioLink(self.port, role="robot", robot_addr64=ADDR)
        self.enc = vm.MavEncoder(vm.ROBOT_SYSID, vm.ROBOT_COMPID)
        self.commands: list = []
        self.stop = threading.Event()
        self.t = threading.Thread(target=self.run, daemon=True)
        self.t.start()

    def run(self):
        next_tel = 0.0
        try:
            while not self.stop.is_set():
                for m in self.link.receive(timeout_s=0.005):
                    if m.get_type() in ("ROACH_LEG_VELOCITY_CMD", "ROACH_PWM_CMD"):
                        self.commands.append(m)
                now = time.monotonic()
                if now >= next_tel:
                    next_tel = now + 0.02
                    self.link.send(self.enc.heartbeat(robot=True))
                    self.link.send(self.enc.telemetry(TEL, last_cmd_seq=0, rx_good=0, rx_corrupt=0))
        except LinkError:
            pass


def test_driver_never_sends_nan_or_out_of_range(tmp_path):
    """Real driver on a pty with a fake robot: every command on the wire is finite and in range."""
    from hilstack.drivers.velociroach.driver import VelociRoachDriver

    master, slave = os.openpty()
    tty.setraw(slave)
    robot = FakeRobot(master)
    drv = VelociRoachDriver(VelociRoachParams(port=os.ttyname(slave), max_leg_vel_rps=10.0), backend="real")
    try:
        with drv:
            # every MAVLink frame the driver hands to the link, decoded: the reader thread
            # sends heartbeats meanwhile, so count the command frames, not all frames
            sent_types: list[str] = []
            spy = vm.MavDecoder()
            send = drv.link.send

            def recording_send(frame: bytes) -> None:
                sent_types.append(spy.decode(frame).get_type())
                send(frame)

            drv.link.send = recording_send

            def commands_sent() -> int:
                return sum(t in ("ROACH_LEG_VELOCITY_CMD", "ROACH_PWM_CMD") for t in list(sent_types))

            bad_writes = [
                (CommandError, None, lambda: drv.write([math.nan, 0.0])),
                (CommandError, None, lambda: drv.write([0.0, math.inf])),
                # bypassing the contract: the encoder refuses
                (LinkError, "not finite", lambda: drv._write(np.array([math.nan, 1.0]))),
                (LinkError, "outside", lambda: drv._write(np.array([50.0, 1.0]))),
            ]
            for exc, match, bad in bad_writes:
                n = commands_sent()
                with pytest.raises(exc, match=match):
                    bad()
                assert commands_sent() == n  # this bad write put no command on the wire
            for i in range(5):
                n = commands_sent()
                drv.write([1e9, -1e9])  # clamped by the contract
                assert commands_sent() == n + 1, i
            deadline = time.monotonic() + 2.0
            while len(robot.commands) < 5 and time.monotonic() < deadline:
                time.sleep(0.005)
    finally:
        robot.stop.set()
        robot.t.join(2.0)
        os.close(slave)
        robot.port.close()
    vals = [(c.left_rps, c.right_rps) for c in robot.commands]
    assert len(vals) >= 5
    assert all(math.isfinite(a) and math.isfinite(b) and abs(a) <= 10.0 and abs(b) <= 10.0 for a, b in vals)
    assert vals[-1] == (0.0, 0.0)  # stop() on exit


# --------------------------------------------------------------------------- port loss
def test_vanished_port_raises_link_error_quickly():
    master, slave = os.openpty()
    tty.setraw(slave)
    link = RadioLink.open(os.ttyname(slave), 230400, role="base", robot_addr64=ADDR)
    os.close(slave)  # only the link holds the device now
    os.write(master, wrap_rx(robot_frames()[:1]))
    got = []
    deadline = time.monotonic() + 2.0
    while not got and time.monotonic() < deadline:
        got = link.receive(timeout_s=0.05)
    assert got
    os.close(master)  # the device is gone (USB unplugged)
    t0 = time.monotonic()
    with pytest.raises(LinkError, match="unplugged"):
        for _ in range(100):
            link.receive(timeout_s=0.05)
    assert time.monotonic() - t0 < 1.0
    with pytest.raises(LinkError):  # and it stays dead, for writers too
        link.send(vm.MavEncoder(255, 190).heartbeat())
    link.close()


def test_missing_port_is_a_clear_error():
    with pytest.raises(LinkError, match="find-port"):
        open_serial("/dev/ttyNOPE_hilstack", 230400)
