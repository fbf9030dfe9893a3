"""The Dynamixel bus emulator (a separate process on a pty) through the real dynamixel-sdk."""

from __future__ import annotations

import time

import pytest

from hilstack.drivers.base import LinkError
from hilstack.drivers.dynamixel.bus import ServoError, start_emulator
from hilstack.drivers.dynamixel.control_table import OPERATING_MODES, control_table, vel_rad_s
from hilstack.sim_backends.dynamixel.firmware import Servo

ARM = [1, 2, 4, 6, 7, 8]


@pytest.fixture(scope="module")
def bus():
    b = start_emulator({"missing_ids": [7], "hardware_errors": {"10": 0x20}}, 1_000_000)
    yield b
    b.close()


def test_ping_and_missing_id(bus):
    assert bus.ping(1)[0] == 1020  # XM430-W350's model number
    before = bus.stats["missing_status"]
    with pytest.raises(LinkError, match="no status packet"):
        bus.ping(7)
    assert bus.stats["missing_status"] == before + 1


def test_sync_read_answers_by_id_around_a_missing_servo(bus):
    before = bus.stats["missing_status"]
    data, errors = bus.sync_read(ARM, "Present Current", "Present Temperature")
    assert sorted(data) == [1, 2, 4, 6, 8]  # 7 is unplugged; those after it still count
    assert bus.stats["missing_status"] == before + 1
    assert "7" in bus.last_error
    # torque is off at power-on: the folded arm settles under gravity, within its limits
    shoulder = bus.decode(data[2], "Present Current", "Present Position")
    assert bus.read(2, "Min Position Limit") <= shoulder <= bus.read(2, "Max Position Limit")
    assert 20 <= bus.decode(data[1], "Present Current", "Present Temperature") <= 30
    assert errors == {}


def test_hardware_error_latches_until_reboot(bus):
    assert bus.read(10, "Hardware Error Status") == 0x20
    _, err = bus.ping(10)
    assert err & 0x80  # the alert bit rides on every status packet
    with pytest.raises(ServoError, match="result fail"):
        bus.write(10, "Torque Enable", 1)
    bus.reboot(10)
    assert bus.read(10, "Hardware Error Status") == 0
    bus.write(10, "Torque Enable", 1)
    bus.write(10, "Torque Enable", 0)


def test_control_table_access_rules(bus):
    bus.write(1, "Torque Enable", 0)
    bus.write(1, "Operating Mode", OPERATING_MODES["velocity"])
    bus.write(1, "Torque Enable", 1)
    with pytest.raises(ServoError, match="access error"):  # EEPROM with torque on
        bus.write(1, "Operating Mode", OPERATING_MODES["position"])
    with pytest.raises(ServoError, match="access error"):  # read-only
        bus.write(1, "Present Position", 0)
    with pytest.raises(ServoError, match="data limit"):
        bus.write(1, "Goal Velocity", bus.read(1, "Velocity Limit") + 1)
    with pytest.raises(ServoError, match="data range"):
        bus.write(2, "Operating Mode", 7)


def test_velocity_mode_moves_the_simulated_joint(bus):
    bus.write(1, "Torque Enable", 0)
    bus.write(1, "Operating Mode", OPERATING_MODES["velocity"])
    bus.write(1, "Torque Enable", 1)
    p0 = bus.read(1, "Present Position")
    bus.sync_write("Goal Velocity", {1: 21})  # 0.5 rad/s
    time.sleep(0.4)
    v = vel_rad_s(bus.read(1, "Present Velocity"))
    p1 = bus.read(1, "Present Position")
    bus.sync_write("Goal Velocity", {1: 0})
    assert v == pytest.approx(0.5, rel=0.1)
    assert p1 - p0 > 20  # counts: it moved the right way


def test_corrupt_status_packets_are_counted_not_fatal():
    # a generous status timeout: this is about corrupt vs missing, and a starved emulator
    # process on a loaded CPU must not turn a late answer into a missing one
    b = start_emulator({"corrupt_every": 3, "garbage_every": 4}, 1_000_000, timeout_margin_ms=2000.0)
    try:
        got, receives, rx = 0, [], b.ph.rxPacket
        b.ph.rxPacket = lambda *a: receives.append(1) or rx(*a)
        for _ in range(10):
            data, _ = b.sync_read([1, 2, 4], "Present Current", "Present Position")
            got += len(data)
        assert b.stats["crc_errors"] == 10  # 30 status packets, every 3rd corrupt
        assert got == 20
        assert b.stats["missing_status"] == 0  # a corrupt answer is not a missing one
        # each read ends once every servo answered, corrupt or not: no wait for a fourth
        # packet that cannot come (it cost the whole timeout margin, 2 s a read)
        assert len(receives) == 30
    finally:
        b.close()


def test_servo_model_unit():
    s = Servo(3, position_limits_rad=(-1.0, 1.0))
    t = control_table()
    # a position goal beyond the limit is refused, inside it is applied
    assert s.write(t["Goal Position"].address, t["Goal Position"].encode(4000)) == 6
    assert s.write(t["Torque Enable"].address, b"\x01") == 0
    assert s.write(t["Goal Position"].address, t["Goal Position"].encode(2100)) == 0
    tau = s.tick(0.0, 0.0)
    assert tau > 0  # pushes towards the goal
    s.inject_hardware_error(0x04)
    assert s.tick(0.0, 0.0) == 0.0 and not s.torque_on
    s.power_on()
    assert s.hardware_error == 0
