"""The Dynamixel X-series control table, as data.

Addresses and sizes come from the control-table file ROBOTIS ships inside the
``dynamixel-sdk`` wheel (``dynamixel_easy_sdk/control_table/<model>.model``), so this
module holds no address constants of its own. What the file does not say (signedness of
every item, units of position/current/temperature/voltage, the hardware-error bits and
operating-mode values) is added below from the XM430-W350 e-Manual
(https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/).

Units: positions in rad (count 2048 is 0 rad, 4096 counts per turn), velocities in
rad/s (0.229 rev/min per count), current in A (2.69 mA per count), temperature in °C,
input voltage in V.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from importlib import resources

#: the model file of each supported servo (inside the dynamixel-sdk wheel)
MODEL_FILES = {"XM430-W350": "xm430_w350.model", "XM540-W270": "xm540_w270.model",
               "XL430-W250": "xl430_w250.model"}
DEFAULT_MODEL = "XM430-W350"

#: items whose raw value is two's-complement (the model file lists only some)
SIGNED_ITEMS = frozenset({
    "Homing Offset", "Goal PWM", "Goal Current", "Goal Velocity", "Goal Position",
    "Present PWM", "Present Current", "Present Velocity", "Present Position",
    "Velocity Trajectory", "Position Trajectory", "Max Position Limit", "Min Position Limit", "Present Load",
    "Bus Watchdog",  # -1: the watchdog tripped (X-series e-Manual, Bus Watchdog(98))
})

#: SI value per count (X series e-Manual)
RAD_PER_COUNT = 2.0 * math.pi / 4096.0
POSITION_ZERO_COUNT = 2048
#: the SDK's model files give 0.0239691227 rad/s (0.2289 rev/min) per count; the
#: e-Manual rounds it to 0.229 rev/min. The file's value is used (``units`` below).
RAD_S_PER_COUNT = 0.0239691227
AMP_PER_COUNT = 2.69e-3
VOLT_PER_COUNT = 0.1

#: Operating Mode (address in the table) values
OPERATING_MODES = {"current": 0, "velocity": 1, "position": 3, "extended_position": 4,
                   "current_based_position": 5, "pwm": 16}

#: Bus Watchdog (98): 1..127 arm it in units of 20 ms, 0 disarms and clears a trip, the
#: servo sets -1 when it tripped (no instruction packet for the set time with torque on: it
#: stops, and Goal PWM/Current/Velocity/Position refuse writes until 0 is written);
#: available from firmware v38 (X-series e-Manual, "Bus Watchdog(98)")
BUS_WATCHDOG_UNIT_S = 0.02
BUS_WATCHDOG_MAX_UNITS = 127
BUS_WATCHDOG_TRIPPED = -1
BUS_WATCHDOG_MIN_FIRMWARE = 38
GOAL_ITEMS = ("Goal PWM", "Goal Current", "Goal Velocity", "Goal Position")

#: Realtime Tick (120, 2 bytes): the servo's own clock, 1 ms per count, 0..32,767, back to 0 after
#: 32,767 (X-series e-Manual, "Realtime Tick(120)"; address and size from the SDK's model file)
REALTIME_TICK_S = 0.001
REALTIME_TICK_MODULUS = 32768


def unwrap_tick(last_raw: int | None, raw: int, total: int) -> int:
    """The servo clock in ticks since its first reading, continued across the 32,767 -> 0 wrap.

    ``total`` is the unwrapped count at ``last_raw`` (0 at the first reading, ``last_raw`` None).
    Readings must come less than 32.768 s apart (at the control rate they are a period apart);
    a reboot, which restarts the clock at 0, reads as one step forward.
    """
    if last_raw is None:
        return 0
    return total + (int(raw) - int(last_raw)) % REALTIME_TICK_MODULUS


#: Hardware Error Status bits
HARDWARE_ERROR_BITS = {0: "input voltage", 2: "overheating", 3: "motor encoder",
                       4: "electrical shock", 5: "overload"}

#: Protocol 2.0 status-packet error byte: bit 7 is the hardware alert, the rest a code
STATUS_ALERT_BIT = 0x80
STATUS_ERRORS = {1: "result fail", 2: "instruction error", 3: "crc error", 4: "data range error",
                 5: "data length error", 6: "data limit error", 7: "access error"}


@dataclass(frozen=True)
class Item:
    name: str
    address: int
    size: int
    signed: bool

    def decode(self, raw: bytes | int) -> int:
        """Raw little-endian bytes (or an unsigned int as dynamixel-sdk returns it) -> int."""
        u = int.from_bytes(raw, "little") if isinstance(raw, bytes | bytearray) else int(raw)
        if self.signed and u >= 1 << (8 * self.size - 1):
            u -= 1 << (8 * self.size)
        return u

    def encode(self, value: int) -> bytes:
        v = int(value)
        lo = -(1 << (8 * self.size - 1)) if self.signed else 0
        hi = (1 << (8 * self.size - (1 if self.signed else 0))) - 1
        if not lo <= v <= hi:
            raise ValueError(f"{self.name}: {v} does not fit {self.size} byte(s)"
                             f"{' signed' if self.signed else ''} [{lo}, {hi}]")
        return v.to_bytes(self.size, "little", signed=self.signed)


class ControlTable:
    """Name -> :class:`Item` for one servo model; ``table["Goal Velocity"].address``."""

    def __init__(self, model: str, items: dict[str, Item], zero_count: int = POSITION_ZERO_COUNT,
                 units: dict[str, tuple[float, str]] | None = None):
        self.model = model
        #: SI value per count where the model file states it: name -> (scale, unit)
        self.units = units or {}
        self.items = items
        self.zero_count = zero_count
        #: bytes a device needs to hold its whole table (RAM + EEPROM, without indirect data)
        self.size = max(i.address + i.size for i in items.values() if not i.name.startswith("Indirect"))

    def __getitem__(self, name: str) -> Item:
        try:
            return self.items[name]
        except KeyError:
            raise KeyError(f"{self.model} has no control-table item {name!r}") from None

    def __contains__(self, name: str) -> bool:
        return name in self.items

    def span(self, first: str, last: str) -> tuple[int, int]:
        """(start address, length) of a block from item ``first`` to item ``last`` inclusive."""
        a, b = self[first], self[last]
        return a.address, b.address + b.size - a.address


def parse_model_file(text: str, model: str) -> ControlTable:
    """Parse ROBOTIS' ``.model`` format: ``[control table]`` rows ``address<TAB>size<TAB>name``."""
    items: dict[str, Item] = {}
    zero = POSITION_ZERO_COUNT
    units: dict[str, tuple[float, str]] = {}
    section = ""
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        if line.startswith("["):
            section = line
            continue
        parts = line.split("\t")
        if section == "[type info]" and parts[0] == "value_of_zero_radian_position":
            zero = int(parts[1])
        if section == "[unit info]" and len(parts) >= 3 and parts[0] != "Data Name":
            units[parts[0]] = (float(parts[1]), parts[2])
        if section != "[control table]" or not parts[0].isdigit():
            continue
        addr, size, name = int(parts[0]), int(parts[1]), parts[2]
        if name not in items:  # the file lists indirect blocks twice; keep the first
            items[name] = Item(name, addr, size, name in SIGNED_ITEMS)
    if "Goal Velocity" not in items:
        raise ValueError(f"{model}: no control table found in the model file")
    return ControlTable(model, items, zero, units)


@cache
def control_table(model: str = DEFAULT_MODEL) -> ControlTable:
    """The control table of a servo model, read from dynamixel-sdk's data files."""
    try:
        fname = MODEL_FILES[model]
    except KeyError:
        raise ValueError(f"unknown Dynamixel model {model!r}; known: {sorted(MODEL_FILES)}") from None
    text = (resources.files("dynamixel_easy_sdk") / "control_table" / fname).read_text()
    return parse_model_file(text, model)


def describe_hardware_error(bits: int) -> str:
    """'overload, overheating' for a Hardware Error Status value; '' for 0."""
    names = [n for b, n in HARDWARE_ERROR_BITS.items() if bits & (1 << b)]
    other = bits & ~sum(1 << b for b in HARDWARE_ERROR_BITS)
    if other:
        names.append(f"unknown bits 0x{other:02x}")
    return ", ".join(names)


def describe_status_error(err: int) -> str:
    code = err & 0x7F
    parts = [STATUS_ERRORS.get(code, f"error code {code}")] if code else []
    if err & STATUS_ALERT_BIT:
        parts.append("hardware alert")
    return ", ".join(parts)


def pos_rad(counts: int, zero_count: int = POSITION_ZERO_COUNT) -> float:
    return (counts - zero_count) * RAD_PER_COUNT


def pos_counts(rad: float, zero_count: int = POSITION_ZERO_COUNT) -> int:
    return int(round(rad / RAD_PER_COUNT)) + zero_count


def vel_rad_s(counts: int) -> float:
    return counts * RAD_S_PER_COUNT


def vel_counts(rad_s: float) -> int:
    return int(round(rad_s / RAD_S_PER_COUNT))
