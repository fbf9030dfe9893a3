"""hil teleop --gamepad: the gamepad's events → the command, the dead man, a lost device, and
"no gamepad found".

This machine has no /dev/input and no uinput, so no gamepad device can exist here. The events
are fed through the code the real device goes through (``tools/gamepad.py: Gamepad.poll``,
``GamepadInput``, the teleop mapper): only the event source is a stand-in, a device object
with evdev ``InputDevice``'s ``read_one``/``capabilities``/``close`` that plays evdev
``InputEvent``s of an Xbox 360 pad (the xpad driver's axis ranges: sticks -32768..32767, fuzz
16, flat 128; D-pad -1..1). The CLI's refusals run for real."""

import errno

import numpy as np
import pytest
from typer.testing import CliRunner

from hilstack.drivers.registry import spec_of
from hilstack.tools import gamepad as gp
from hilstack.tools.cli import app
from hilstack.tools.teleop import TeleopMapper

evdev = pytest.importorskip("evdev", reason="evdev (the operator extra) is not installed")
from evdev import AbsInfo, InputEvent, ecodes  # noqa: E402

ROACH = spec_of("velociroach", "sim").to_dict()
ARM = spec_of("widowx", "sim").to_dict()

STICK = AbsInfo(value=0, min=-32768, max=32767, fuzz=16, flat=128, resolution=0)
TRIGGER = AbsInfo(value=0, min=0, max=255, fuzz=0, flat=0, resolution=0)
HAT = AbsInfo(value=0, min=-1, max=1, fuzz=0, flat=0, resolution=0)
XPAD_CAPS = {
    ecodes.EV_KEY: [ecodes.BTN_SOUTH, ecodes.BTN_EAST, ecodes.BTN_NORTH, ecodes.BTN_WEST, ecodes.BTN_TL,
                    ecodes.BTN_TR, ecodes.BTN_SELECT, ecodes.BTN_START, ecodes.BTN_MODE],
    ecodes.EV_ABS: [(ecodes.ABS_X, STICK), (ecodes.ABS_Y, STICK), (ecodes.ABS_Z, TRIGGER), (ecodes.ABS_RX, STICK),
                    (ecodes.ABS_RY, STICK), (ecodes.ABS_RZ, TRIGGER), (ecodes.ABS_HAT0X, HAT),
                    (ecodes.ABS_HAT0Y, HAT)],
}


class PlayedDevice:
    """The event source only: evdev InputDevice's reading interface over a list of reports
    (one list of events per `poll`, as the kernel queues them between two reads); after the
    last one, ``gone`` makes reads fail with ENODEV as an unplugged device's do."""

    def __init__(self, caps=XPAD_CAPS, gone=False):
        self.caps, self.gone, self.queue, self.closed = caps, gone, [], False
        self.name, self.path = "Microsoft X-Box 360 pad", "/dev/input/event7"

    def capabilities(self, absinfo=True):
        if absinfo:
            return self.caps
        return {t: [c[0] if isinstance(c, tuple) else c for c in v] for t, v in self.caps.items()}

    def read_one(self):
        if self.queue:
            return self.queue.pop(0)
        if self.gone:
            raise OSError(errno.ENODEV, "No such device")
        return None

    def close(self):
        self.closed = True


def report(*events):
    """Events of one report, closed by SYN_REPORT, stamped as the kernel does."""
    out = [InputEvent(1000, 1000 * i, t, c, v) for i, (t, c, v) in enumerate(events)]
    return out + [InputEvent(1000, 999_999, ecodes.EV_SYN, ecodes.SYN_REPORT, 0)]


def abs_(code, v):
    return (ecodes.EV_ABS, code, v)


def key(code, v=1):
    return (ecodes.EV_KEY, code, v)


def test_the_event_codes_are_the_kernels():
    assert (gp.EV_SYN, gp.EV_KEY, gp.EV_ABS) == (ecodes.EV_SYN, ecodes.EV_KEY, ecodes.EV_ABS)
    assert (gp.ABS_X, gp.ABS_Y, gp.ABS_HAT0X) == (ecodes.ABS_X, ecodes.ABS_Y, ecodes.ABS_HAT0X)
    assert (gp.BTN_SOUTH, gp.BTN_EAST, gp.BTN_TL, gp.BTN_TR, gp.BTN_SELECT, gp.BTN_GAMEPAD, gp.BTN_JOYSTICK) == (
        ecodes.BTN_SOUTH, ecodes.BTN_EAST, ecodes.BTN_TL, ecodes.BTN_TR, ecodes.BTN_SELECT, ecodes.BTN_GAMEPAD,
        ecodes.BTN_JOYSTICK)


def test_axis_dead_zone_and_travel():
    ax = gp.Axis(STICK.min, STICK.max, STICK.flat)
    assert ax.normalize(-32768) == -1.0 and ax.normalize(32767) == 1.0
    assert ax.normalize(-128) == 0.0 and ax.normalize(3000) == 0.0  # a worn stick at rest: centred
    assert ax.normalize(-16384) == pytest.approx(-(0.5 - gp.DEAD_ZONE) / (1 - gp.DEAD_ZONE), abs=1e-4)


def _poll(pad, dev, *reports):
    for r in reports:
        dev.queue += r
    return pad.poll()


def test_stick_drives_the_roach_and_its_release_is_the_stop():
    dev = PlayedDevice()
    m = TeleopMapper(ROACH)
    pad = gp.Gamepad(dev, m)
    np.testing.assert_allclose(m.action([0, 0]), [0, 0])
    # the stick pushed forward over three reports (up is the axis' minimum)
    assert _poll(pad, dev, report(abs_(ecodes.ABS_Y, -9000)), report(abs_(ecodes.ABS_Y, -24000)),
                 report(abs_(ecodes.ABS_Y, -32768))) == []
    np.testing.assert_allclose(m.action([0, 0]), [15.0, 15.0])  # full speed: the legs' 15 rev/s limit
    _poll(pad, dev, report(abs_(ecodes.ABS_X, -32768)))  # and fully left: turn left
    a = m.action([0, 0])
    np.testing.assert_allclose(a, [0.0, 15.0])  # left = speed - turn, right = speed + turn, clamped
    # released: the stick springs back and rests slightly off centre; one report later the stop
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, -700), abs_(ecodes.ABS_X, 260)))
    np.testing.assert_allclose(m.action([7.0, 9.0]), [0.0, 0.0])  # the spec's safe action, at once
    # half back: proportional, no latching
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, 16384)))
    a = m.action([0, 0])
    assert a[0] == a[1] and -15 < a[0] < -5


def test_stop_button_holds_until_the_stick_is_centred_and_e_stop_and_quit():
    dev = PlayedDevice()
    m = TeleopMapper(ROACH)
    pad = gp.Gamepad(dev, m)
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, -32768)))
    assert _poll(pad, dev, report(key(ecodes.BTN_SOUTH)), report(key(ecodes.BTN_SOUTH, 0))) == []
    np.testing.assert_allclose(m.action([0, 0]), [0, 0])  # stopped, although the stick is still forward
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, -30000)))
    np.testing.assert_allclose(m.action([0, 0]), [0, 0])  # still held: the stick must come back first
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, 0)), report(abs_(ecodes.ABS_Y, -32768)))
    np.testing.assert_allclose(m.action([0, 0]), [15, 15])  # centred once: the stick counts again
    evs = _poll(pad, dev, report(key(ecodes.BTN_EAST)))
    assert [e.kind for e in evs] == ["estop"]
    np.testing.assert_allclose(m.action([0, 0]), [0, 0])  # an e-stop press also stops the command
    assert [e.kind for e in _poll(pad, dev, report(key(ecodes.BTN_SELECT)))] == ["quit"]
    assert _poll(pad, dev, report(key(ecodes.BTN_EAST, 2))) == []  # autorepeat is no new press


def test_stick_jogs_the_selected_widowx_joint_and_stops_on_release():
    dev = PlayedDevice()
    m = TeleopMapper(ARM)
    pad = gp.Gamepad(dev, m)
    assert m.mode == "jog" and m.joint == 0
    _poll(pad, dev, report(abs_(ecodes.ABS_HAT0X, 1)), report(abs_(ecodes.ABS_HAT0X, 0)))  # D-pad right
    assert m.joint == 1
    _poll(pad, dev, report(key(ecodes.BTN_TR)), report(key(ecodes.BTN_TR, 0)), report(key(ecodes.BTN_TL)))
    assert m.joint == 1  # right then left shoulder
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, -32768)))
    for _ in range(3):  # held: every period, not a timed pulse
        np.testing.assert_allclose(m.action([0.0] * 6), [0, 0.5, 0, 0, 0, 0])  # half the 1 rad/s limit
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, 32767)))
    assert m.action([0.0] * 6)[1] == pytest.approx(-0.5)
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, 100)))  # released
    np.testing.assert_allclose(m.action([0.0] * 6), np.zeros(6))


def test_stick_moves_a_position_target_at_a_rate():
    spec = {"action": {"names": ["a_pos", "b_pos"], "units": ["rad", "rad"], "low": [-1, -1], "high": [1, 1]},
            "safe_action": None, "period_s": 0.1}
    dev = PlayedDevice()
    m = TeleopMapper(spec, step=0.25)
    pad = gp.Gamepad(dev, m)
    np.testing.assert_allclose(m.action([0.2, -0.3]), [0.2, -0.3])
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, -32768)))
    for k in range(1, 4):  # full stick: 0.25 of the 2 rad range per second, 0.05 rad per 0.1 s period
        np.testing.assert_allclose(m.action([0.2, -0.3]), [0.2 + 0.05 * k, -0.3])
    _poll(pad, dev, report(abs_(ecodes.ABS_Y, 0)))
    np.testing.assert_allclose(m.action([0.0, 0.0]), [0.35, -0.3])  # released: the target holds


def test_a_lost_gamepad_stops_the_command_and_says_so():
    dev = PlayedDevice(gone=True)
    m = TeleopMapper(ROACH)
    pad = gp.Gamepad(dev, m)
    dev.queue += report(abs_(ecodes.ABS_Y, -32768))  # its last report, then ENODEV
    with pytest.raises(gp.GamepadLost, match=r"X-Box 360 pad \(/dev/input/event7\) lost .*No such device"):
        pad.poll()
    np.testing.assert_allclose(m.action([0, 0]), [0, 0])


def test_which_devices_are_gamepads():
    assert gp.is_gamepad(PlayedDevice())
    keyboard = {ecodes.EV_KEY: [ecodes.KEY_A, ecodes.KEY_Q]}
    assert not gp.is_gamepad(PlayedDevice(caps=keyboard))
    no_stick = {ecodes.EV_KEY: [ecodes.BTN_SOUTH], ecodes.EV_ABS: [(ecodes.ABS_HAT0X, HAT)]}
    assert not gp.is_gamepad(PlayedDevice(caps=no_stick))


def test_no_gamepad_found_is_one_line_exit_2(tmp_path, monkeypatch):
    # this machine's own /dev/input: none at all (a stand-in list makes the test not depend on it)
    monkeypatch.setattr(evdev, "list_devices", lambda: [])
    r = CliRunner().invoke(app, ["teleop", "roach_sim", "--gamepad"])
    assert r.exit_code == 2 and "no gamepad found (no /dev/input/event* device at all)" in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1
    r = CliRunner().invoke(app, ["teleop", "roach_sim", "--gamepad", str(tmp_path / "event99")])
    assert r.exit_code == 2 and "event99 does not exist (gamepad unplugged?)" in r.output, r.output
    r = CliRunner().invoke(app, ["teleop", "roach_sim", str(tmp_path / "event99")])
    assert r.exit_code == 2 and "with --gamepad" in r.output, r.output
    # without evdev: the one-line install hint
    monkeypatch.setitem(__import__("sys").modules, "evdev", None)
    r = CliRunner().invoke(app, ["teleop", "roach_sim", "--gamepad"])
    assert r.exit_code == 2 and "pip install 'hilstack[operator]'" in r.output, r.output


class UnpluggedLater(PlayedDevice):
    """The stick held forward, then the device unplugged after ``after_s`` of reading."""

    def __init__(self, after_s):
        super().__init__()
        self.after_s, self.t0 = after_s, None
        self.queue = report(abs_(ecodes.ABS_Y, -32768))

    def read_one(self):
        import time

        self.t0 = self.t0 or time.monotonic()
        self.gone = time.monotonic() - self.t0 > self.after_s
        return super().read_one() if self.queue or self.gone else None


def test_hil_teleop_stops_the_roach_when_its_gamepad_is_lost(bus, monkeypatch):
    """`hil teleop roach_sim --gamepad` (in-process, stdin no terminal: gamepad only) against a sim
    roach driver node: the held stick drives it, the unplugged device ends teleop with exit 1
    after its last command, the stop, was sent (the driver's own watchdog is not what stopped it)."""
    import threading

    from hilstack.bus import keys
    from hilstack.bus.node import Node
    from hilstack.bus.schemas import Command
    from hilstack.configs.schema import load_rig, rig_robot_config
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver

    rig = load_rig("roach_sim")
    node = DriverNode(make_driver(rig_robot_config(rig, "roach")), rig.name, "roach", bus, pace="lockstep",
                      handle_signals=False, estop_sync_s=0.05, watchdog_periods=3, lockstep_timeout_s=0.3)
    th = threading.Thread(target=node.serve, daemon=True)
    th.start()
    spy = Node("spy", rig.name, bus, handle_signals=False)
    cmds = spy.subscribe(keys.cmd(rig.name, "roach"), Command, latest=False)
    dev = UnpluggedLater(after_s=0.6)
    monkeypatch.setattr(gp, "open_gamepad", lambda device: dev)
    try:
        r = CliRunner().invoke(app, ["teleop", "roach_sim", "--gamepad", "--endpoint", bus.endpoint])
    finally:
        node.stop_event.set()
        th.join(10)
        node.close()
        got = [p for _, p in cmds.drain()]
        spy.close()
    assert r.exit_code == 1 and "gamepad Microsoft X-Box 360 pad (/dev/input/event7) lost" in r.output, r.output
    assert dev.closed
    from hilstack.bus.schemas import decode

    sent = [m for m in (decode(p) for p in got) if isinstance(m, Command) and m.source == "teleop"]
    assert any(c.action == [15.0, 15.0] for c in sent), [c.action for c in sent][:5]
    assert sent[-1].action == [0.0, 0.0]
