"""`hil doctor RIG` and `hil find-port`: what a real rig needs from this computer, one line per item.

Everything is read from Linux's sysfs and /dev (under ``root``, so the tests run on a fake tree):

- USB serial devices: ``/sys/class/tty/<name>/device`` leads to the USB device, whose ``idVendor``
  / ``idProduct`` name it through :data:`KNOWN_USB` (not every FTDI chip is an XBee: a ROBOTIS
  U2D2 is an FTDI FT232H);
- FTDI latency timer: ``/sys/bus/usb-serial/devices/<name>/latency_timer`` (default 16 ms; a
  Dynamixel or XBee link wants 1 ms: at 16 ms every status packet waits up to 16 ms in the chip);
- CAN: ``/sys/class/net/<iface>`` (``type`` 280 = ARPHRD_CAN, ``flags`` bit 0 = up) and the
  bit rate from ``ip -details -json link show`` (iproute2);
- rendering: libEGL / libOSMesa found by the dynamic loader (MuJoCo's offscreen GL);
- cameras: ``/dev/videoN``.

``--scan`` opens the devices: Dynamixel IDs by a broadcast ping (dynamixel-sdk, protocol 2.0)
at the configured baud rate, and the XBee's AT settings (digi-xbee: AP, CH, ID, BD).
"""

from __future__ import annotations

import ctypes.util
import json
import os
import shutil
import subprocess
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

#: USB VID:PID -> (what it is, role). Roles: "xbee" (the roach's base station), "dynamixel"
#: (WidowX, pan unit, reset arm: a U2D2 or an OpenCR), "slcan" (a USB-serial CAN adapter for the
#: hand, python-can's slcan), "socketcan" (a CAN adapter with a kernel driver: a net interface, not
#: a tty), "serial" (a generic USB-serial chip: could be anything). Sources: FTDI's product ids
#: (FT232R 6001, FT2232 6010, FT232H 6014, FT-X 6015), ROBOTIS' U2D2 manual (FT232H), the CANable
#: firmwares (slcan 16d0:117e, candleLight gs_usb 1d50:606f), USBtin (04d8:000a), PEAK PCAN-USB
#: (0c72:000c), STM32 virtual COM (0483:5740, ROBOTIS OpenCR).
KNOWN_USB: dict[tuple[int, int], tuple[str, str]] = {
    (0x0403, 0x6001): ("FTDI FT232R (Digi XBee USB boards, FTDI cables)", "xbee"),
    (0x0403, 0x6015): ("FTDI FT-X (XBee USB explorers)", "xbee"),
    (0x0403, 0x6014): ("FTDI FT232H (ROBOTIS U2D2, Dynamixel)", "dynamixel"),
    (0x0403, 0x6010): ("FTDI FT2232 (dual USB-serial)", "serial"),
    (0x0483, 0x5740): ("STM32 virtual COM (ROBOTIS OpenCR, Dynamixel)", "dynamixel"),
    (0x16D0, 0x117E): ("CANable (slcan firmware)", "slcan"),
    (0x04D8, 0x000A): ("USBtin (slcan)", "slcan"),
    (0x1D50, 0x606F): ("CANable / candleLight (gs_usb, SocketCAN)", "socketcan"),
    (0x0C72, 0x000C): ("PEAK PCAN-USB (SocketCAN)", "socketcan"),
    (0x10C4, 0xEA60): ("Silicon Labs CP210x USB-serial", "serial"),
    (0x1A86, 0x7523): ("WCH CH340 USB-serial", "serial"),
}
#: what each role is for, in `hil find-port`'s table
ROLE_USE = {"xbee": "XBee base station?", "dynamixel": "Dynamixel bus (U2D2)", "slcan": "CAN (slcan)",
            "socketcan": "CAN (SocketCAN)", "serial": "", "": ""}
ARPHRD_CAN = 280
FTDI_VID = 0x0403
#: latency timer a real-time serial link wants [ms]
LATENCY_MS = 1


@dataclass(frozen=True)
class Item:
    """One line of the doctor's report. ``ok`` None: information, not a requirement."""

    what: str
    ok: bool | None
    detail: str
    fix: str = ""

    def line(self) -> str:
        tag = {True: "ok  ", False: "FAIL", None: "info"}[self.ok]
        return f"{tag} {self.what}: {self.detail}" + (f" -> {self.fix}" if self.fix else "")


def _read(p: Path) -> str | None:
    try:
        return p.read_text().strip()
    except OSError:
        return None


def _usb_device(dev: Path) -> Path | None:
    """The USB device directory (the one with idVendor) above a tty's sysfs device."""
    try:
        p = dev.resolve()
    except OSError:
        return None
    for d in (p, *p.parents):
        if (d / "idVendor").is_file():
            return d
    return None


def serial_ports(root: Path = Path("/")) -> list[dict[str, Any]]:
    """USB serial ports (ttyUSB*, ttyACM* and any tty with a USB device), identified by VID:PID."""
    out = []
    cls = root / "sys" / "class" / "tty"
    for tty in sorted(cls.glob("*")) if cls.is_dir() else []:
        usb = _usb_device(tty / "device")
        if usb is None:
            continue
        try:
            vid, pid = int(_read(usb / "idVendor") or "", 16), int(_read(usb / "idProduct") or "", 16)
        except ValueError:
            continue
        what, role = KNOWN_USB.get((vid, pid), ("", ""))
        out.append({
            "device": f"/dev/{tty.name}", "vid_pid": f"{vid:04x}:{pid:04x}", "known_as": what, "role": role,
            "manufacturer": _read(usb / "manufacturer"), "product": _read(usb / "product"),
            "serial_number": _read(usb / "serial"),
            "latency_timer_ms": _int(_read(root / "sys" / "bus" / "usb-serial" / "devices" / tty.name / "latency_timer")),
        })
    return out


def _int(s: str | None) -> int | None:
    try:
        return None if s is None else int(s)
    except ValueError:
        return None


def _dev(root: Path, device: str) -> Path:
    return root / device.lstrip("/")


def check_serial(name: str, port: str | None, role: str, root: Path = Path("/"),
                 latency_ms: int = LATENCY_MS) -> list[Item]:
    """The port is set, exists, is readable and writable (dialout), is the device it should be,
    and an FTDI chip's latency timer is at most ``latency_ms`` (the config's ``latency_timer_ms``,
    what the Dynamixel driver's status timeout assumes; 1 ms otherwise)."""
    what = f"{name}: serial port"
    if not port:
        return [Item(what, False, "not set", "set params.port in the rig or robot config (or pass --port); "
                                             "`hil find-port` lists candidates")]
    if "://" in port:
        return [Item(what, None, f"{port} is a URL: not checked")]
    path = _dev(root, port)
    if not path.exists():
        want = {"xbee": "the base-station XBee", "dynamixel": "the U2D2", "slcan": "the CAN adapter"}.get(role, "it")
        return [Item(what, False, f"{port} does not exist", f"plug {want} in; `hil find-port` lists candidates")]
    items = []
    if os.access(path, os.R_OK | os.W_OK):
        items.append(Item(what, True, f"{port} readable and writable"))
    else:
        try:
            import grp

            group = grp.getgrgid(path.stat().st_gid).gr_name
        except (KeyError, OSError, ImportError):
            group = "dialout"
        items.append(Item(what, False, f"{port}: no read/write permission",
                          f"sudo usermod -aG {group} $USER, then log in again"))
    info = next((p for p in serial_ports(root) if p["device"] == "/dev/" + Path(port).name), None)
    if info is None:
        items.append(Item(f"{name}: USB device", None, f"{port} is not a USB serial device (or not in sysfs)"))
        return items
    label = info["known_as"] or f"unknown USB device {info['vid_pid']} ({info['product'] or '?'})"
    mismatch = info["role"] not in (role, "serial", "") and role != ""
    items.append(Item(f"{name}: USB device", False if mismatch else True,
                      f"{port} is {label} [{info['vid_pid']}]",
                      f"this robot needs {ROLE_USE.get(role) or role}: check the port" if mismatch else ""))
    vid = int(info["vid_pid"].split(":")[0], 16)
    lat = info["latency_timer_ms"]
    if vid == FTDI_VID and lat is not None:
        dev = Path(port).name
        items.append(Item(f"{name}: FTDI latency timer", lat <= latency_ms, f"{lat} ms (wanted ≤ {latency_ms} ms)",
                          "" if lat <= latency_ms else
                          f"echo {latency_ms} | sudo tee /sys/bus/usb-serial/devices/{dev}/latency_timer "
                          "(or a udev rule, docs/arms.md)"))
    return items


def can_bitrate(iface: str) -> int | None:
    """The bit rate iproute2 reports for a CAN interface, or None (no `ip`, not configured)."""
    ip = shutil.which("ip")
    if ip is None:
        return None
    try:
        out = subprocess.run([ip, "-details", "-json", "link", "show", "dev", iface], capture_output=True,
                             text=True, timeout=5, check=False).stdout
        return int(json.loads(out)[0]["linkinfo"]["info_data"]["bittiming"]["bitrate"])
    except (ValueError, KeyError, IndexError, TypeError, OSError, subprocess.SubprocessError):
        return None


def check_can(name: str, iface: str | None, bitrate: int, root: Path = Path("/"), read_bitrate=can_bitrate) -> list[Item]:
    what = f"{name}: CAN interface"
    up_cmd = f"sudo ip link set {iface} up type can bitrate {bitrate} restart-ms 100"
    if not iface:
        return [Item(what, False, "not set", "set params.channel (e.g. can0)")]
    net = root / "sys" / "class" / "net" / iface
    if not net.exists():
        return [Item(what, False, f"{iface} does not exist", "plug the CAN adapter in (`ip -br link` lists interfaces)")]
    if _int(_read(net / "type")) != ARPHRD_CAN:
        return [Item(what, False, f"{iface} is not a CAN interface", "set params.channel to the CAN adapter's interface")]
    flags = _read(net / "flags")
    up = flags is not None and int(flags, 16) & 1 == 1
    items = [Item(what, up, f"{iface} {'up' if up else 'down'}", "" if up else up_cmd)]
    rate = read_bitrate(iface)
    if rate is None:
        items.append(Item(f"{name}: CAN bit rate", None, f"{iface}: not reported by `ip -details link`"))
    else:
        items.append(Item(f"{name}: CAN bit rate", rate == bitrate, f"{iface} at {rate} bit/s (the hand: {bitrate})",
                          "" if rate == bitrate else f"sudo ip link set {iface} down; {up_cmd}"))
    return items


def check_rendering(required: bool) -> Item:
    """MuJoCo's offscreen rendering: EGL (GPU or Mesa) or OSMesa (software)."""
    found = [lib for lib in ("EGL", "OSMesa") if ctypes.util.find_library(lib)]
    gl = os.environ.get("MUJOCO_GL", "egl")
    if found:
        return Item("rendering", True if required else None, f"{' and '.join(found)} found (MUJOCO_GL={gl})")
    return Item("rendering", False if required else None, "neither libEGL nor libOSMesa found",
                "sudo apt-get install libegl1 libgl1-mesa-dri libosmesa6 (scripts/setup.sh)")


def check_camera(name: str, device: Any, root: Path = Path("/")) -> Item:
    what = f"{name}: camera"
    path = f"/dev/video{device}" if isinstance(device, int) else str(device)
    if not path.startswith("/dev/"):
        ok = Path(path).is_file()
        return Item(what, ok, f"{path} ({'a video file' if ok else 'no such file'})")
    p = _dev(root, path)
    if not p.exists():
        return Item(what, False, f"{path} does not exist", "plug the camera in (`ls /dev/video*`)")
    if not os.access(p, os.R_OK | os.W_OK):
        return Item(what, False, f"{path}: no read/write permission", "sudo usermod -aG video $USER, then log in again")
    return Item(what, True, f"{path} present")


def scan_dynamixel(name: str, port: str, baudrate: int, ids: dict[str, int]) -> Item:
    """Broadcast ping (protocol 2.0) at ``baudrate``: which of the expected IDs answer."""
    from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler

    ph = PortHandler(port)
    try:
        if not ph.openPort() or not ph.setBaudRate(baudrate):
            return Item(f"{name}: Dynamixel scan", False, f"cannot open {port} at {baudrate} baud")
        found, res = PacketHandler(2.0).broadcastPing(ph)
    finally:
        ph.closePort()
    want = set(ids.values())
    got = set(found) if res == COMM_SUCCESS or found else set()
    missing = {k: v for k, v in ids.items() if v not in got}
    detail = f"IDs {sorted(got)} answer at {baudrate} baud; expected {sorted(want)}"
    if not missing:
        return Item(f"{name}: Dynamixel scan", True, detail)
    return Item(f"{name}: Dynamixel scan", False, detail + f"; missing {missing}",
                "check power and cables; a servo at another baud rate or ID: Dynamixel Wizard or `ids`/`baudrate` "
                "in the config")


def scan_xbee(name: str, port: str, baudrate: int) -> list[Item]:
    """The base station's AT settings (API mode 1 required; channel and PAN id reported)."""
    from digi.xbee.devices import XBeeDevice

    dev = XBeeDevice(port, baudrate)
    try:
        dev.open()
        ap = dev.get_parameter("AP")[0]
        ch = dev.get_parameter("CH").hex()
        pan = dev.get_parameter("ID").hex()
    except Exception as e:  # noqa: BLE001 - any failure is the answer
        return [Item(f"{name}: XBee", False, f"no answer to AT commands on {port} at {baudrate} baud: {e}",
                     "check the module's baud rate (BD) and that it runs 802.15.4 firmware")]
    finally:
        if dev.is_open():
            dev.close()
    return [Item(f"{name}: XBee API mode", ap == 1, f"AP={ap}", "" if ap == 1 else "set ATAP1 (XCTU), then ATWR"),
            Item(f"{name}: XBee radio", None, f"channel CH={ch}, PAN ID={pan} (must match the robot's radio)")]


def check_rig(rig: str, scan: bool = False, root: Path = Path("/"), read_bitrate=can_bitrate) -> list[Item]:
    """Every prerequisite of a rig's robots, from its config (hilstack.configs.schema)."""
    from hilstack.configs.schema import load_rig, rig_robot_config

    cfg = load_rig(rig)
    items: list[Item] = []
    renders = False
    for key in cfg.robots:
        rc = rig_robot_config(cfg, key)
        p = rc.params
        name = f"{key} ({rc.robot}, {rc.backend})"
        if rc.backend != "real":
            items.append(Item(name, True, f"{rc.backend} backend: no hardware needed"))
            renders = renders or rc.robot == "camera" or bool(p.get("camera"))
            continue
        if "transport" in p:  # a CAN robot (the hand)
            bitrate = int(p.get("bitrate", 1_000_000))
            if p["transport"] == "socketcan":
                items += check_can(name, p.get("channel"), bitrate, root, read_bitrate)
            elif p["transport"] == "slcan":
                items += check_serial(name, p.get("channel"), "slcan", root)
            else:
                items.append(Item(name, None, f"transport {p['transport']}: network, not checked"))
        elif "left_device" in p:  # the stereo camera
            items += [check_camera(name, p.get(k), root) for k in ("left_device", "right_device")]
        elif "port" in p and not isinstance(p["port"], int):  # a serial robot (mocap's int port is UDP): Dynamixel servos (ids) or the roach's XBee
            role = "dynamixel" if "ids" in p else "xbee"
            serial_items = check_serial(name, p.get("port"), role, root, int(p.get("latency_timer_ms", LATENCY_MS)))
            items += serial_items
            port_ok = all(i.ok is not False for i in serial_items[:1])
            if scan and port_ok:
                if role == "dynamixel":
                    items.append(scan_dynamixel(name, p["port"], int(p.get("baudrate", 1_000_000)), p["ids"]))
                else:
                    items += scan_xbee(name, p["port"], int(p.get("baudrate", 230400)))
            elif not scan and port_ok:
                items.append(Item(f"{name}: {'Dynamixel IDs' if role == 'dynamixel' else 'XBee settings'}", None,
                                  "not scanned (hil doctor --scan opens the port and asks the devices)"))
        else:
            items.append(Item(name, None, "no local device to check (network source)"))
    items.append(check_rendering(renders))
    return items


def report(items: list[Item]) -> dict[str, Any]:
    return {"ok": all(i.ok is not False for i in items), "items": [asdict(i) for i in items]}
