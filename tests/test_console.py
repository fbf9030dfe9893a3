"""hil console: the robot rows (rate, stale, overruns), the refusals, and the console in a real
terminal (tmux) engaging and releasing the sim roach rig's e-stop."""

import os
import shutil
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from hilstack.bus.schemas import RobotState
from hilstack.tools.cli import app
from hilstack.tools.console import STALE_S, RobotView, release_refusal
from tests.helpers import ROOT, free_port, wait_for


def _st(t_s, **kw):
    return RobotState(robot="roach", t_s=t_s, state=[0.0], **kw)


def test_rate_comes_from_the_states_timestamps_not_the_arrival():
    v = RobotView("roach")
    assert v.rate_hz() is None and v.row(0.0)[1] == "NO STATE"
    # 21 states 20 ms apart in robot time, all arriving within 0.1 s of wall clock (a burst)
    for i in range(21):
        v.add(_st(10.0 + 0.02 * i), now=100.0 + 0.005 * i)
    assert v.rate_hz() == pytest.approx(50.0)
    assert v.row(100.2)[3] == "50.0 Hz"
    # states older than the window (wall clock) leave the rate
    v.add(_st(20.0), now=103.0)
    assert v.rate_hz() is None


def test_row_flags_stale_stopped_and_only_the_overruns_that_happened():
    v = RobotView("roach")
    h = {"ok": True, "frames_sent": 12, "frames_received": 11, "corrupt_frames": 1, "cycle_late": 3,
         "cycle_missed": 0, "heartbeat_missed": 2}
    v.add(_st(1.0, ok=False, active=False, stopped_reason="estop", health=h), now=50.0)
    robot, flags, why, _rate, link, over = v.row(50.1)
    assert robot == "roach" and flags == "NOT OK stopped" and why == "estop"
    assert "sent=12" in link and "recv=11" in link and "corrupt=1" in link
    assert "cycle_late=3" in over and "heartbeat_missed=2" in over and "cycle_missed" not in over
    assert v.row(50.0 + STALE_S + 1.5)[1].startswith("NOT OK STALE 2s")
    v.add(_st(1.1, active=True), now=60.0)
    assert v.row(60.0)[1:3] == ["ok active", "-"] and v.row(60.0)[5] == "none"


def test_release_is_refused_for_a_user_outside_the_rigs_release_list(monkeypatch):
    from hilstack.tools.common import rig_bus

    _, bus, _ = rig_bus("roach_emulated")
    assert release_refusal("roach_emulated", bus) is None  # the rig's default user may release
    monkeypatch.setenv("HIL_BUS_USER", "viewer")
    why = release_refusal("roach_emulated", bus)
    assert why is not None and "user 'viewer' may not release rig roach_emulated" in why
    _, open_bus, _ = rig_bus("roach_sim")
    assert release_refusal("roach_sim", open_bus) is None  # no access control: anyone


def test_refusals_are_one_line(monkeypatch):
    r = CliRunner().invoke(app, ["console", "roach_sim", "--robot", "arm"])
    assert r.exit_code == 2 and "has no robot 'arm'" in r.output
    r = CliRunner().invoke(app, ["console", "roach_sim"])  # CliRunner's stdin is no terminal
    assert r.exit_code == 2 and "stdin is not a terminal" in r.output
    monkeypatch.setitem(sys.modules, "textual", None)  # as if the operator extra were not installed
    r = CliRunner().invoke(app, ["console", "roach_sim"])
    assert r.exit_code == 2 and "hilstack[operator]" in r.output and r.output.count("\n") == 1


needs_tmux = pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux not installed (scripts/setup.sh installs it)")


class Tmux:
    """`hil console` in a detached tmux session on a private tmux server."""

    def __init__(self, args: list[str]):
        self.sock = f"hil-console-{os.getpid()}-{free_port()}"
        env = f"PYTHONPATH={ROOT} PYTHONUNBUFFERED=1 HOME={os.environ['HOME']}"
        cmd = f"cd {ROOT} && {env} {sys.executable} -m hilstack.tools.cli console {' '.join(args)}; " \
              "echo CONSOLE_EXIT=$?; sleep 600"
        subprocess.run(["tmux", "-L", self.sock, "new-session", "-d", "-s", "t", "-x", "160", "-y", "24", cmd],
                       check=True)

    def key(self, k: str) -> None:
        subprocess.run(["tmux", "-L", self.sock, "send-keys", "-t", "t", k], check=True)

    def screen(self) -> str:
        return subprocess.run(["tmux", "-L", self.sock, "capture-pane", "-p", "-t", "t"], check=True,
                              capture_output=True, text=True).stdout

    def close(self) -> None:
        subprocess.run(["tmux", "-L", self.sock, "kill-server"], capture_output=True)


def _row(screen: str, robot: str) -> str:
    return next((ln for ln in screen.splitlines() if ln.strip().startswith(robot + " ")), "")


@needs_tmux
def test_console_shows_the_sim_roach_and_engages_and_releases_the_estop(spawn, bus):
    from hilstack.bus import keys
    from hilstack.bus.node import Node

    term = Tmux(["roach_sim", "--endpoint", bus.endpoint])
    node = None
    try:
        wait_for(lambda: "rig roach_sim as" in term.screen(), 60, "the console's header")
        # the console is up first: it sees the lockstep sim's first state (the sim then waits
        # for a command, which the console never sends)
        spawn("up", "roach_sim", "--endpoint", bus.endpoint)
        node = Node("console-test", "roach_sim", bus, handle_signals=False)
        sub = node.subscribe(keys.state("roach_sim", "roach"), RobotState)
        wait_for(lambda: " ok " in _row(term.screen(), "roach"), 90, "the roach row with ok")
        # the driver node's liveliness: polled apart from the state stream, so it may show a poll later
        wait_for(lambda: "driver-roach" in term.screen(), 10, "the driver node in the console's node list")

        term.key("e")
        wait_for(lambda: (s := sub.wait(1.0)) is not None and s.stopped_reason == "estop", 30,
                 "the driver node's state stopped by the e-stop")
        wait_for(lambda: "E-STOP: ENGAGED" in (sc := term.screen()) and "acknowledged by driver-roach" in sc
                 and "estop" in _row(sc, "roach"), 30, "the console to show the engaged e-stop")

        term.key("r")
        wait_for(lambda: (s := sub.wait(1.0)) is not None and s.stopped_reason != "estop", 30,
                 "the driver node's state released")
        wait_for(lambda: "released by" in term.screen() and "E-STOP: released" in term.screen(), 30,
                 "the console to show the release")
        term.key("q")
        wait_for(lambda: "CONSOLE_EXIT=0" in term.screen(), 30, "the console to quit with exit 0")
    finally:
        term.close()
        if node is not None:
            node.close()
