"""`hil doctor` and `hil find-port` on a fake sysfs tree (tools/doctor.py), and on this machine."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from hilstack.tools import doctor
from hilstack.tools.cli import app


def _usb_tty(root: Path, tty: str, vid: int, pid: int, product: str, latency: int | None = None) -> None:
    """A USB serial device as Linux shows it: the tty's ``device`` link into the USB tree."""
    usb = root / "sys" / "devices" / "pci0000:00" / "usb1" / f"1-{tty}"
    iface = usb / f"1-{tty}:1.0" / tty
    iface.mkdir(parents=True)
    (usb / "idVendor").write_text(f"{vid:04x}\n")
    (usb / "idProduct").write_text(f"{pid:04x}\n")
    (usb / "product").write_text(product + "\n")
    cls = root / "sys" / "class" / "tty" / tty
    cls.mkdir(parents=True)
    (cls / "device").symlink_to(iface)
    (root / "dev").mkdir(exist_ok=True)
    (root / "dev" / tty).write_text("")
    if latency is not None:
        d = root / "sys" / "bus" / "usb-serial" / "devices" / tty
        d.mkdir(parents=True)
        (d / "latency_timer").write_text(f"{latency}\n")


@pytest.fixture
def sysfs(tmp_path: Path) -> Path:
    _usb_tty(tmp_path, "ttyUSB0", 0x0403, 0x6014, "USB <-> Serial Converter", latency=16)  # a U2D2
    _usb_tty(tmp_path, "ttyUSB1", 0x0403, 0x6001, "FT232R USB UART", latency=1)  # an XBee board
    _usb_tty(tmp_path, "ttyACM0", 0x16D0, 0x117E, "CANable")
    (tmp_path / "sys" / "class" / "tty" / "ttyS0").mkdir()  # a platform UART: not listed
    return tmp_path


def test_find_port_names_devices_by_vid_pid(sysfs):
    ports = {p["device"]: p for p in doctor.serial_ports(sysfs)}
    assert set(ports) == {"/dev/ttyUSB0", "/dev/ttyUSB1", "/dev/ttyACM0"}
    assert ports["/dev/ttyUSB0"]["role"] == "dynamixel" and "U2D2" in ports["/dev/ttyUSB0"]["known_as"]
    assert ports["/dev/ttyUSB1"]["role"] == "xbee"
    assert ports["/dev/ttyACM0"]["role"] == "slcan" and ports["/dev/ttyACM0"]["latency_timer_ms"] is None
    assert ports["/dev/ttyUSB0"]["latency_timer_ms"] == 16


def test_serial_checks_device_kind_and_latency(sysfs):
    by = {i.what.split(": ")[1]: i for i in doctor.check_serial("roach", "/dev/ttyUSB0", "xbee", sysfs)}
    assert by["serial port"].ok is True
    assert by["USB device"].ok is False and "U2D2" in by["USB device"].detail  # a U2D2 is no XBee
    assert by["FTDI latency timer"].ok is False and "latency_timer" in by["FTDI latency timer"].fix
    items = doctor.check_serial("roach", "/dev/ttyUSB1", "xbee", sysfs)
    assert [i.ok for i in items] == [True, True, True]
    missing = doctor.check_serial("arm", "/dev/ttyUSB7", "dynamixel", sysfs)
    assert len(missing) == 1 and missing[0].ok is False and "U2D2" in missing[0].fix
    assert doctor.check_serial("arm", None, "dynamixel", sysfs)[0].ok is False


def test_can_checks_type_state_and_bitrate(tmp_path):
    net = tmp_path / "sys" / "class" / "net" / "can0"
    net.mkdir(parents=True)
    (net / "type").write_text("280\n")
    (net / "flags").write_text("0x80\n")  # down
    items = doctor.check_can("hand", "can0", 1_000_000, tmp_path, read_bitrate=lambda _: 500_000)
    assert [i.ok for i in items] == [False, False] and "bitrate 1000000" in items[0].fix
    (net / "flags").write_text("0x40081\n")  # up
    items = doctor.check_can("hand", "can0", 1_000_000, tmp_path, read_bitrate=lambda _: 1_000_000)
    assert [i.ok for i in items] == [True, True]
    (net / "type").write_text("1\n")  # an Ethernet interface
    assert doctor.check_can("hand", "can0", 1_000_000, tmp_path)[0].ok is False
    assert doctor.check_can("hand", "can9", 1_000_000, tmp_path)[0].ok is False


@pytest.mark.skipif(Path("/dev/ttyUSB0").exists(), reason="this machine has a /dev/ttyUSB0")
def test_doctor_on_this_machine_reports_missing_hardware():
    r = CliRunner().invoke(app, ["doctor", "roach_real"])
    assert r.exit_code == 1, r.output
    lines = r.output.strip().splitlines()
    assert any(ln.startswith("FAIL") and "/dev/ttyUSB0 does not exist" in ln for ln in lines)
    assert lines[-1] == "roach_real: not ready (1 to fix)"
    r = CliRunner().invoke(app, ["doctor", "roach_sim", "--json"])
    assert r.exit_code == 0 and '"ok": true' in r.output
    # a rig that cannot be read is a usage error (2), not a rig that is not ready (1)
    r = CliRunner().invoke(app, ["doctor", "no_such_rig"])
    assert r.exit_code == 2 and "no such rig config" in r.output
