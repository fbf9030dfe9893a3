"""hil teleop: the key map (pure), the refusals, and the verb in a real terminal (tmux)."""

import math
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from hilstack.drivers.registry import spec_of
from hilstack.tools.cli import app
from hilstack.tools.teleop import TeleopMapper, parse_keys
from tests.helpers import ROOT, free_port, wait_for

ROACH = spec_of("velociroach", "sim").to_dict()
ARM = spec_of("widowx", "sim").to_dict()


def test_arrow_escapes_and_plain_keys():
    assert parse_keys("w\x1b[A\x1b[Dq ") == ["w", "up", "left", "q", " "]


def test_drive_keys_map_to_leg_velocities_within_limits():
    m = TeleopMapper(ROACH, step=0.25)
    assert m.mode == "drive"
    np.testing.assert_allclose(m.action([0, 0]), [0, 0])  # nothing pressed: the safe action
    for k in "ww":
        m.key(k)
    np.testing.assert_allclose(m.action([0, 0]), [7.5, 7.5])  # half speed, both legs forward
    m.key("a")  # turn left: the left leg slower than the right
    a = m.action([0, 0])
    assert a[0] < a[1] and a[0] == pytest.approx(3.75) and a[1] == pytest.approx(11.25)
    for _ in range(10):
        m.key("up")
    np.testing.assert_allclose(m.action([0, 0]), [11.25, 15.0])  # full speed, still turning: clamped
    m.key("d")
    np.testing.assert_allclose(m.action([0, 0]), [15.0, 15.0])
    assert m.key(" ") is None
    np.testing.assert_allclose(m.action([3, 3]), [0, 0])
    assert m.key("e").kind == "estop" and m.key("q").kind == "quit"


def test_jog_selects_a_joint_and_pulses_its_velocity_for_jog_periods():
    m = TeleopMapper(ARM, jog_periods=3)
    assert m.mode == "jog"
    m.key("2")
    m.key("+")
    acts = [m.action([0.0] * 6) for _ in range(5)]
    for a in acts[:3]:
        np.testing.assert_allclose(a, [0, 0.5, 0, 0, 0, 0])  # half the shoulder's 1 rad/s limit
    for a in acts[3:]:
        np.testing.assert_allclose(a, np.zeros(6))  # the jog ended: stop
    m.key("-")
    assert m.action([0.0] * 6)[1] == pytest.approx(-0.5)
    m.key("+")  # the other way during a jog: stops it first
    np.testing.assert_allclose(m.action([0.0] * 6), np.zeros(6))
    m.key("9")  # no ninth joint: the selection stays
    assert m.joint == 1


def test_jog_of_a_position_channel_steps_its_target_from_the_held_command():
    spec = {"action": {"names": ["a_pos", "b_pos"], "units": ["rad", "rad"], "low": [-1, -1], "high": [1, 1]},
            "safe_action": None}
    m = TeleopMapper(spec, step=0.25)
    np.testing.assert_allclose(m.action([0.2, -0.3]), [0.2, -0.3])  # holds what the driver holds
    m.key("2")
    m.key("+")
    np.testing.assert_allclose(m.action([0.2, -0.3]), [0.2, 0.2])  # one step: 0.25 of the 2 rad range
    for _ in range(10):
        m.key("+")
    np.testing.assert_allclose(m.action([0.2, -0.3]), [0.2, 1.0])


def test_status_line_shows_the_pose_the_state_and_a_silent_driver():
    from hilstack.bus.schemas import RobotState
    from hilstack.tools.teleop import status_line

    names = ROACH["state"]["names"]
    st = [0.0] * len(names)
    st[names.index("x")], st[names.index("cos_yaw")] = 1.5, 1.0
    m = TeleopMapper(ROACH)
    m.key("w")
    m.action([0, 0])
    s = RobotState(robot="roach", t_s=0.0, state=st, active=False, stopped_reason="estop")
    line = status_line("roach", m, s, names, "")
    assert "speed +0.25" in line and "cmd +3.75 +3.75" in line and "x +1.500" in line and "stopped (estop)" in line
    assert "NO STATE" not in line and "NO STATE for 3 s" in status_line("roach", m, s, names, "", 3.2)


def test_refusals_are_one_line(monkeypatch):
    r = CliRunner().invoke(app, ["teleop", "roach_sim", "--step", "0"])
    assert r.exit_code == 2 and "--step 0.0" in r.output
    r = CliRunner().invoke(app, ["teleop", "roach_sim", "--robot", "arm"])
    assert r.exit_code == 2 and "has no robot 'arm'" in r.output
    # the rig's access control: a bus user outside bus.access.command may not drive
    monkeypatch.setenv("HIL_BUS_USER", "viewer")
    r = CliRunner().invoke(app, ["teleop", "roach_emulated"])
    assert r.exit_code == 2 and "user 'viewer' may not command rig roach_emulated" in r.output
    monkeypatch.delenv("HIL_BUS_USER")
    r = CliRunner().invoke(app, ["teleop", "roach_sim"])  # CliRunner's stdin is no terminal
    assert r.exit_code == 2 and "stdin is not a terminal" in r.output


# ---------------------------------------------------------------- in a real terminal
needs_tmux = pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux not installed (scripts/setup.sh installs it)")


class Tmux:
    """`hil teleop` in a detached tmux session on a private tmux server."""

    def __init__(self, args: list[str]):
        self.sock = f"hil-teleop-{os.getpid()}-{free_port()}"
        env = f"PYTHONPATH={ROOT} PYTHONUNBUFFERED=1 HOME={os.environ['HOME']}"
        cmd = f"cd {ROOT} && {env} {sys.executable} -m hilstack.tools.cli teleop {' '.join(args)}; " \
              "echo TELEOP_EXIT=$?; sleep 600"
        self._tmux("new-session", "-d", "-s", "t", "-x", "200", "-y", "20", cmd)

    def _tmux(self, *a: str) -> str:
        return subprocess.run(["tmux", "-L", self.sock, *a], check=True, capture_output=True, text=True).stdout

    def keys(self, *keys: str) -> None:
        for k in keys:
            self._tmux("send-keys", "-t", "t", k)
            time.sleep(0.05)

    def screen(self) -> str:
        return self._tmux("capture-pane", "-p", "-t", "t")

    def close(self) -> None:
        subprocess.run(["tmux", "-L", self.sock, "kill-server"], capture_output=True)


def _states(bus, rig, robot):
    from hilstack.bus import keys
    from hilstack.bus.node import Node
    from hilstack.bus.schemas import RobotState

    node = Node("teleop-test", rig, bus, handle_signals=False)
    return node, node.subscribe(keys.state(rig, robot), RobotState)


def _teleop_session(spawn, bus, rig, robot, up_args, teleop_args=()):
    from tests.helpers import wait_rig_router

    spawn("up", rig, "--endpoint", bus.endpoint, *up_args)
    wait_rig_router(bus)  # an access rig: its driver node is the router every client joins
    node, sub = _states(bus, rig, robot)
    term = Tmux([rig, "--robot", robot, "--endpoint", bus.endpoint, *teleop_args])
    # generous: `hil up` and `hil teleop` start slowly on a loaded machine
    wait_for(lambda: "| active" in term.screen(), 120, "teleop's status line with an active robot")
    return node, sub, term


@needs_tmux
@pytest.mark.parametrize("rig", ["roach_sim", "roach_emulated"])
def test_teleop_drives_the_roach_in_a_terminal(spawn, bus, rig_bus, rig, tmp_path):
    """The sim roach (lockstep, open rig) and the emulated one (the real radio driver, the rig's
    access control: teleop joins the rig's router with the operator's credentials), recorded."""
    if rig != "roach_sim":
        bus = rig_bus(rig)
    rec = tmp_path / "teleop.mcap"
    node, sub, term = _teleop_session(spawn, bus, rig, "roach", [], ["--record", str(rec)])
    try:
        s0 = wait_for(lambda: sub.wait(1.0), 30, "a roach state")
        names = ROACH["state"]["names"]
        x0, y0 = s0.state[names.index("x")], s0.state[names.index("y")]
        term.keys("w", "w")

        def moved():
            s = sub.wait(1.0)
            return s is not None and math.hypot(s.state[names.index("x")] - x0, s.state[names.index("y")] - y0) > 0.1

        wait_for(moved, 60, "the roach to move 0.1 m on the bus")
        assert "speed +0.50" in term.screen()
        term.keys("Space")
        wait_for(lambda: (s := sub.wait(1.0)) is not None and s.action == [0.0, 0.0], 30, "the stop on the bus")
        term.keys("q")
        wait_for(lambda: "TELEOP_EXIT=0" in term.screen(), 60, "teleop to quit with exit 0")
    finally:
        term.close()
        node.close()
    # the demonstration: teleop's forward commands and the robot's states, in one MCAP
    from hilstack.bus.recording import read_messages
    from hilstack.bus.schemas import Command, RobotState

    msgs = [m.msg for m in read_messages(rec).messages]
    cmds = [m for m in msgs if isinstance(m, Command) and m.source == "teleop"]
    assert any(c.action[0] > 5 and c.action[1] > 5 for c in cmds)
    assert sum(isinstance(m, RobotState) for m in msgs) > 5


@needs_tmux
@pytest.mark.parametrize("rig", ["arm_widowx_sim", "arm_widowx_emulated"])
def test_teleop_jogs_a_widowx_joint_in_a_terminal(spawn, bus, rig_bus, rig):
    """The sim WidowX and the emulated one (the real Dynamixel driver over a virtual link, the
    rig's access control), its e-stop engaged from the keyboard."""
    if rig != "arm_widowx_sim":
        bus = rig_bus(rig)
    node, sub, term = _teleop_session(spawn, bus, rig, "arm", ["--robot", "arm"])
    try:
        names = ARM["state"]["names"]
        i = names.index("shoulder_pos")
        q0 = wait_for(lambda: sub.wait(1.0), 30, "an arm state").state[i]
        term.keys("2", "+", "+", "+")
        wait_for(lambda: (s := sub.wait(1.0)) is not None and s.state[i] > q0 + 0.05, 60,
                 "the shoulder to jog up 0.05 rad on the bus")
        assert "joint 2:shoulder_vel" in term.screen()
        term.keys("e")  # the rig's e-stop, engaged from the keyboard
        wait_for(lambda: (s := sub.wait(1.0)) is not None and s.stopped_reason == "estop", 60,
                 "the driver to report the e-stop")
        term.keys("q")
        wait_for(lambda: "TELEOP_EXIT=0" in term.screen(), 60, "teleop to quit with exit 0")
    finally:
        term.close()
        node.close()


# ---------------------------------------------------------------- a stop while it waits for the spec
@needs_tmux
def test_ctrl_c_while_teleop_waits_for_the_spec_ends_it_at_once():
    """No rig up: teleop waits for the robot's spec (--timeout-s 60). Ctrl-C typed in a real
    terminal (tmux) ends it within 2 s, exit 0 (before: ignored until the timeout)."""
    term = Tmux(["roach_sim", "--endpoint", f"tcp/127.0.0.1:{free_port()}", "--timeout-s", "60"])
    try:
        wait_for(lambda: "waiting up to 60 s" in term.screen(), 60, "teleop to wait for the spec")
        t0 = time.monotonic()
        term.keys("C-c")
        wait_for(lambda: "TELEOP_EXIT=" in term.screen(), 10, "teleop to exit")
        took = time.monotonic() - t0
        screen = term.screen()
    finally:
        term.close()
    assert "TELEOP_EXIT=0" in screen and "stopped while waiting for the spec" in screen, screen
    assert took < 2.0, f"teleop took {took:.1f} s to end after Ctrl-C"

