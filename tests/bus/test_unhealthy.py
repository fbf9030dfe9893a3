"""Control on unhealthy states: the driver node does not apply commands to a robot whose
reading is not ok; it holds the robot safe and resumes after ``resume_ok_readings`` ok
readings, counting and publishing why it refused."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.schemas import Command, RobotState, decode
from hilstack.drivers.bridge import DriverNode
from hilstack.drivers.mocap.udp import encode_pose
from tests.helpers import free_port, wait_rig_router
from tests.test_driver_base import HoldsMeasured

RIG = "unhealthy_roach"
PERIOD_S = 0.1  # configs/robots/velociroach.yaml


class MocapSource:
    """The roach's mocap stream, as a lab's mocap bridge sends it (drivers/mocap/udp.py), from
    this test: ``mode`` "ok" (a fixed pose at 100 Hz), "silent" (the stream stops) or "nan"."""

    def __init__(self, port: int):
        self.port = port
        self.mode = "ok"
        self.last_ok_t = 0.0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True, name="mocap")
        self._th.start()

    def _run(self) -> None:
        seq = 0
        while not self._stop.wait(0.01):
            if self.mode == "silent":
                continue
            seq += 1
            pos = [float("nan")] * 3 if self.mode == "nan" else [0.0, 0.0, 0.03]
            self._sock.sendto(encode_pose(seq, time.monotonic(), 1, pos, [1.0, 0.0, 0.0, 0.0]),
                              ("127.0.0.1", self.port))
            if self.mode == "ok":
                self.last_ok_t = time.monotonic()

    def close(self) -> None:
        self._stop.set()
        self._th.join(2)
        self._sock.close()


@pytest.fixture
def roach_rig(rig_bus, spawn, tmp_path):
    """`hil up` of the emulated VelociRoACH (its firmware emulator in its own process, the real
    radio driver over a pty) whose mocap pose comes from this test over UDP."""
    port = free_port()
    rig = tmp_path / f"{RIG}.yaml"
    rig.write_text(f"""name: {RIG}
robots:
  roach:
    config: velociroach
    backend: emulated
    params: {{mocap_udp_port: {port}, link_timeout_periods: 30, write_timeout_s: 3.0, emulator: {{pose: false}}}}
watchdog_periods: 3
pace: realtime
bus:
  access: {{credentials: {tmp_path / 'rig.credentials'}}}
""")
    bus = rig_bus(str(rig))  # emulated hardware: access control; `hil up` and this test log in as operator
    mocap = MocapSource(port)
    proc = spawn("up", str(rig), "--endpoint", bus.endpoint)
    wait_rig_router(bus)
    node = Node("test-ctl", RIG, bus, handle_signals=False)
    state = node.subscribe(keys.state(RIG, "roach"), RobotState, latest=False, capacity=4096)
    cmd = node.publisher(keys.cmd(RIG, "roach"), Command)
    try:
        yield mocap, state, cmd, proc
    finally:
        node.close()
        mocap.close()


def _drive(state, cmd, action, until, timeout_s, what) -> list[tuple[float, RobotState]]:
    """Send ``action`` every 50 ms (a controller at twice the robot's rate) until ``until(got)``;
    every state seen, with its arrival time."""
    got: list[tuple[float, RobotState]] = []

    def cond():
        cmd.put(Command(robot="roach", action=list(action)))
        t = time.monotonic()
        got.extend((t, decode(p, RobotState)) for _, p in state.drain())
        return until(got)

    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            tail = [(s.ok, s.stopped_reason, s.action) for _, s in got[-5:]]
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; last states {tail}")
        time.sleep(0.05)
    return got


def _moving(s: RobotState) -> bool:
    return bool(s.action) and s.action[0] > 1.0


def test_not_ok_readings_hold_the_roach_and_refuse_commands_until_ok_again(roach_rig):
    mocap, state, cmd, proc = roach_rig
    go = [5.0, 5.0]  # crank rev/s; the safe action is [0, 0]
    _drive(state, cmd, go, lambda g: any(s.ok and _moving(s) and s.stopped_reason == "" for _, s in g), 60,
           "the roach to take commands")

    for fault, flag in (("silent", "stale_pose"), ("nan", "nonfinite_input")):
        mocap.mode = fault
        t_fault = time.monotonic()
        got = _drive(state, cmd, go, lambda g: sum(not s.ok for _, s in g) >= 10, 30, f"10 readings with {fault} mocap")
        bad = [(t, s) for t, s in got if not s.ok]
        # every not-ok state holds the safe action: the command it answered was refused
        assert all(s.action == [0.0, 0.0] and s.stopped_reason == "unhealthy" for _, s in bad), \
            [(s.action, s.stopped_reason) for _, s in bad]
        first_bad = next(i for i, (_, s) in enumerate(got) if not s.ok)
        assert all(s.action == [0.0, 0.0] for _, s in got[first_bad:])  # and it stays held
        h = bad[-1][1].health
        assert flag in h["unhealthy_reason"] and h["unhealthy_refused"] >= 5 and h["unhealthy_stops"] >= 1
        print(f"{fault} mocap: first held state {bad[0][0] - t_fault:.3f} s after the fault began "
              f"(pose deadline 0.25 s, period {PERIOD_S} s)")

        mocap.mode = "ok"
        t_ok = time.monotonic()
        got = _drive(state, cmd, go, lambda g: any(_moving(s) for _, s in g), 30, "commands obeyed again")
        i = next(k for k, (_, s) in enumerate(got) if _moving(s))
        print(f"{fault} mocap: commands obeyed again {got[i][0] - t_ok:.3f} s after the mocap recovered "
              "(3 ok readings)")
        # the state that first carries the command was preceded by >= 3 ok readings in a row
        run = 0
        for _, s in reversed(got[:i]):
            if not s.ok:
                break
            run += 1
        assert run >= 3, [(s.ok, s.action) for _, s in got[: i + 1]]
    assert proc.p.poll() is None  # the node kept serving


def test_a_position_robot_held_on_a_not_ok_reading_keeps_its_target(bus):
    """A position-controlled robot (no safe action): the node's hold is the held target, re-sent
    (drivers/base.py ``stop``), not a zero or a stale measured pose; commands are refused until
    ``resume_ok_readings`` ok readings."""
    drv = HoldsMeasured(rate=1.0)
    node = DriverNode(drv, "unhealthy_pos", "fake", bus, handle_signals=False, resume_ok_readings=2)
    try:
        drv.configure()
        drv.activate()
        for _ in range(4):  # ramp 0.3 -> 0.7 while the readings are ok
            node.publish_state()
            node._apply(Command(robot="fake", action=[1.0]))
            drv.t += 0.1
        target = drv.held_command
        assert target == pytest.approx([0.7])
        drv.q = float("nan")  # the reading goes not ok (the base class flags NaN in the state)
        s = node.publish_state()
        assert not s.ok and s.stopped_reason == "unhealthy" and "nonfinite_input" in s.health["unhealthy_reason"]
        assert drv.sent[-1] == pytest.approx(target) and drv.stopped == 0  # held where it was sent, no jump
        node._apply(Command(robot="fake", action=[1.0]))
        assert drv.held_command == pytest.approx(target) and node.stats.unhealthy_refused == 1
        drv.q, drv.t = 0.7, drv.t + 0.1
        node.publish_state()  # one ok reading: still refused
        node._apply(Command(robot="fake", action=[1.0]))
        assert drv.held_command == pytest.approx(target) and node.stats.unhealthy_refused == 2
        drv.t += 0.1
        s = node.publish_state()  # the second: commands are taken again, from the held target
        assert s.stopped_reason == "waiting"
        node._apply(Command(robot="fake", action=[1.0]))
        # from the held 0.7, 0.2 s after the hold: the rate limit allows r·(0.2 + p) = 0.3
        assert drv.held_command == pytest.approx([1.0]) and drv.sent[-1] == pytest.approx([1.0])
    finally:
        drv.cleanup()
        node.close()


@pytest.mark.parametrize("bad", [0, -1, 101, 2.5, float("nan")])
def test_resume_ok_readings_is_bounded(bus, bad):
    with pytest.raises(ValueError, match="resume_ok_readings"):
        DriverNode(HoldsMeasured(), "unhealthy_pos", "fake", bus, handle_signals=False, resume_ok_readings=bad)


