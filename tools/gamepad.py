"""``hil teleop RIG --gamepad [DEVICE]``: a gamepad through Linux's input subsystem (evdev).

The device is read with python-evdev (the ``operator`` extra), the maintained binding of the
kernel's evdev interface that every Linux gamepad driver (xpad, hid-sony, hid-nintendo, the
generic HID joystick driver) reports through. The gamepad drives the same
:class:`~hilstack.tools.teleop.TeleopMapper` as the keyboard, so the command goes through the
same clamping, the driver node's limits and rate limit, and the rig's access control.

Map (codes from ``linux/input-event-codes.h``, the names evdev gives them):

* **drive** (the roach): left stick up/down (``ABS_Y``) = forward speed, left/right
  (``ABS_X``) = turn, proportional to the deflection.
* **jog** (the arms): left stick up/down jogs the selected channel at a rate proportional to
  the deflection (a velocity channel: up to ``jog_frac`` of its limit; a position channel: its
  target moves up to ``step`` of its range per second); the D-pad left/right (``ABS_HAT0X``)
  or the shoulder buttons (``BTN_TL``/``BTN_TR``) select the channel.
* buttons: south (A / cross) = stop (held until every stick is back at centre), east
  (B / circle) = engage the rig's e-stop, select (back / share) = quit.

Dead man: a gamepad reports the stick's release (a terminal does not), so the command follows
the stick: the stick back within the dead zone is the spec's safe action at once, nothing is
latched. A device that goes away (unplugged, its battery empty: the read fails with ENODEV)
raises :class:`GamepadLost`; teleop then sends the safe action and ends (exit 1).
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass
from typing import Any

from hilstack.tools.teleop import Event, TeleopMapper

# event types and codes of linux/input-event-codes.h (a stable kernel ABI; a test checks them
# against evdev.ecodes), so the mapping needs evdev only to read a real device
EV_SYN, EV_KEY, EV_ABS = 0, 1, 3
ABS_X, ABS_Y, ABS_HAT0X = 0x00, 0x01, 0x10
BTN_SOUTH, BTN_EAST, BTN_TL, BTN_TR, BTN_SELECT = 0x130, 0x131, 0x136, 0x137, 0x13A
BTN_GAMEPAD, BTN_JOYSTICK = 0x130, 0x120

#: stick deflection (fraction of its half range) read as centred: beyond the driver's own
#: ``flat`` (xpad: 128 of 32768) a worn stick rests a few percent off centre
DEAD_ZONE = 0.12


class GamepadLost(Exception):
    """The gamepad stopped answering (unplugged, battery empty): the robot must be stopped."""


class NoGamepad(Exception):
    """No gamepad to open (none found, or the named device is not one)."""


@dataclass(frozen=True)
class Axis:
    """One absolute axis's range as the kernel reports it (evdev's ``AbsInfo``)."""

    min: int
    max: int
    flat: int = 0

    def normalize(self, value: int) -> float:
        """``value`` as a deflection in [-1, 1] (min → -1), 0 inside the dead zone; the rest of
        the travel is rescaled so that the command starts from 0 at the zone's edge (no jump)."""
        half = (self.max - self.min) / 2.0
        if half <= 0:
            return 0.0
        x = max(-1.0, min(1.0, (value - self.min) / half - 1.0))
        zone = max(DEAD_ZONE, self.flat / half)
        if abs(x) <= zone:
            return 0.0
        return (abs(x) - zone) / (1.0 - zone) * (1.0 if x > 0 else -1.0)


class GamepadInput:
    """Gamepad events → the teleop mapper's command (and stop / e-stop / quit events).

    ``axes``: the device's absolute axes (code → :class:`Axis`), from its capabilities.
    :meth:`feed` takes evdev ``InputEvent``s (anything with ``type``, ``code``, ``value``) as
    the device delivers them and returns the :class:`~hilstack.tools.teleop.Event`s of the
    buttons pressed; the sticks set the mapper's speed/turn or continuous jog directly."""

    def __init__(self, mapper: TeleopMapper, axes: dict[int, Axis]):
        missing = [n for n, c in (("ABS_X", ABS_X), ("ABS_Y", ABS_Y)) if c not in axes]
        if missing:
            raise NoGamepad(f"the device has no {' or '.join(missing)} axis (no left stick)")
        self.mapper = mapper
        self.axes = axes
        self.pos = {c: 0.0 for c in axes}  # deflections in [-1, 1]
        self.stop_held = False  # the stop button was pressed: stay stopped until the sticks are centred

    def feed(self, events: Any) -> list[Event]:
        out: list[Event] = []
        for ev in events:
            if ev.type == EV_SYN:
                self._apply()  # one report complete (a stick centred within a read counts)
            elif ev.type == EV_ABS and ev.code in self.axes:
                if ev.code == ABS_HAT0X and ev.value != 0 and self.mapper.mode == "jog":
                    self._select(1 if ev.value > 0 else -1)
                self.pos[ev.code] = self.axes[ev.code].normalize(ev.value)
            elif ev.type == EV_KEY and ev.value == 1:  # a press (0: release, 2: autorepeat)
                if ev.code == BTN_SOUTH:
                    self.stop_held = True
                elif ev.code == BTN_EAST:
                    self.stop_held = True
                    out.append(Event("estop"))
                elif ev.code == BTN_SELECT:
                    self.stop_held = True
                    out.append(Event("quit"))
                elif ev.code in (BTN_TL, BTN_TR) and self.mapper.mode == "jog":
                    self._select(1 if ev.code == BTN_TR else -1)
        self._apply()
        return out

    def _select(self, d: int) -> None:
        m = self.mapper
        m._select((m.joint + d) % len(m.names))

    def _apply(self) -> None:
        x, y = self.pos.get(ABS_X, 0.0), self.pos.get(ABS_Y, 0.0)
        if self.stop_held and x == 0.0 and y == 0.0:
            self.stop_held = False  # sticks back at centre: the stop is taken, the stick counts again
        if self.stop_held:
            x = y = 0.0
        m = self.mapper
        if m.mode == "drive":
            # stick up is the axis' minimum (evdev's convention): forward; stick left: turn left
            m.speed, m.turn = -y, -x
        else:
            m.set_jog(-y)


def gamepad_axes(device: Any) -> dict[int, Axis]:
    """The absolute axes of an evdev ``InputDevice`` (code → :class:`Axis`)."""
    caps = device.capabilities(absinfo=True)
    return {code: Axis(info.min, info.max, info.flat) for code, info in caps.get(EV_ABS, [])}


def is_gamepad(device: Any) -> bool:
    """A device with gamepad or joystick buttons and a stick (``ABS_X``, ``ABS_Y``)."""
    caps = device.capabilities()
    keys = set(caps.get(EV_KEY, []))
    absc = {c if isinstance(c, int) else c[0] for c in caps.get(EV_ABS, [])}
    return bool(keys & {BTN_GAMEPAD, BTN_JOYSTICK}) and {ABS_X, ABS_Y} <= absc


class Gamepad:
    """A gamepad device read without blocking, once per control period by teleop's loop.

    ``device``: an evdev ``InputDevice`` (or an object with its ``read_one()``,
    ``capabilities()``, ``close()``, ``path`` and ``name``: how the tests play recorded events
    through this same code)."""

    def __init__(self, device: Any, mapper: TeleopMapper):
        self.device = device
        self.input = GamepadInput(mapper, gamepad_axes(device))

    @property
    def label(self) -> str:
        return f"{getattr(self.device, 'name', '?')} ({getattr(self.device, 'path', '?')})"

    def poll(self) -> list[Event]:
        """Every event queued since the last call, applied to the mapper; the buttons' events.
        Raises :class:`GamepadLost` when the device is gone."""
        events = []
        try:
            while (ev := self.device.read_one()) is not None:
                events.append(ev)
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                pass  # nothing queued
            else:  # ENODEV: unplugged; EIO...: the device failed
                self.input.stop_held = True
                self.input.feed(events)
                raise GamepadLost(f"gamepad {self.label} lost ({os.strerror(e.errno or 0) or e}): "
                                  "the robot was sent the stop") from None
        return self.input.feed(events)

    def close(self) -> None:
        try:
            self.device.close()
        except Exception:  # noqa: S110 - a lost device may fail to close; nothing to keep
            pass


def open_gamepad(device: str | None) -> Any:
    """The evdev ``InputDevice`` to read: ``device`` (a path such as ``/dev/input/event3``), or
    the first gamepad among ``/dev/input/event*``. Raises :class:`NoGamepad` (one line) when
    there is none, :class:`FileNotFoundError` for a path that does not exist."""
    from hilstack.configs.extras import require

    evdev = require("evdev", "hil teleop --gamepad")
    if device is not None:
        if not os.path.exists(device):
            raise FileNotFoundError(f"--gamepad {device} does not exist (gamepad unplugged?); "
                                    "`python -m evdev.evtest` lists the input devices")
        try:
            dev = evdev.InputDevice(device)
        except OSError as e:
            raise NoGamepad(f"--gamepad {device}: cannot open it ({e.strerror}; reading input devices "
                            "needs the 'input' group: usermod -aG input $USER)") from None
        if not is_gamepad(dev):
            dev.close()
            raise NoGamepad(f"--gamepad {device} ({dev.name}) is no gamepad: it has no gamepad buttons "
                            "and left stick")
        return dev
    paths = evdev.list_devices()
    unreadable = 0
    for p in sorted(paths):
        try:
            dev = evdev.InputDevice(p)
        except OSError:
            unreadable += 1
            continue
        if is_gamepad(dev):
            return dev
        dev.close()
    why = (f"{len(paths)} input devices, {unreadable} not readable by this user (the 'input' group: "
           "usermod -aG input $USER)" if paths else "no /dev/input/event* device at all")
    raise NoGamepad(f"--gamepad: no gamepad found ({why}); plug one in or name it: --gamepad /dev/input/eventN")


HELP_TAIL = "A stop  B e-stop  Select quit"
PAD_HELP = {
    "drive": f"left stick speed/turn (release: stop)  {HELP_TAIL}",
    "jog": f"left stick jog  D-pad/LB/RB joint  {HELP_TAIL}",
}
