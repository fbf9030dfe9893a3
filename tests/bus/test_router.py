"""`hil router`: a rig whose nodes reach each other only through the rig's own Zenoh router
(bus.router) on another loopback address, with the rig's credentials and ACL (issue 26, item 2).

Processes: the router (`hil router`), the driver node (`hil up`, a client as the drive user),
the recorder (`hil record`) and the commander (this test, a client as the operator). No node
listens on a port of its own: every message crosses the router."""

from __future__ import annotations

import signal
import time

from hilstack.bus import keys
from hilstack.bus.access import acl, generate
from hilstack.bus.node import Node, alive_nodes
from hilstack.bus.schemas import Command, RobotState, decode, encode
from hilstack.bus.session import BusUnavailable
from hilstack.configs.schema import BusAccess, BusConfig, load_rig
from tests.bus.test_access import _plain_session
from tests.helpers import free_port, wait_for

ROBOT = "  roach:\n    config: velociroach\n    backend: sim"


def _rig(tmp_path) -> tuple[str, BusConfig]:
    creds = tmp_path / "rt.credentials"
    generate(creds, ["operator", "driver"])
    router = f"tcp/127.0.0.2:{free_port()}"
    path = tmp_path / "rt_roach.yaml"
    path.write_text(f"name: rt_roach\nrobots:\n{ROBOT}\nwatchdog_periods: 3\npace: realtime\n"
                    f"bus:\n  endpoint: tcp/127.0.0.3:{free_port()}\n  router: {router}\n"
                    f"  access: {{credentials: {creds}}}\n")
    return str(path), load_rig(path).bus


def _operator(bus: BusConfig, timeout_s: float = 60) -> Node:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return Node("test-operator", "rt_roach", bus, handle_signals=False)
        except BusUnavailable:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def test_the_router_acl_lets_drivers_publish_states_and_only_commanders_command():
    a = acl("r", ["roach"], BusAccess(credentials="x"), drivers=True)
    drive = next(r for r in a["rules"] if r["id"] == "drive")
    assert drive["key_exprs"] == ["hil/r/**"] and drive["flows"] == ["ingress"]
    assert {"id": "drivers", "usernames": ["driver"]} in a["subjects"]
    assert "drive" not in [r["id"] for r in acl("r", ["roach"], BusAccess(credentials="x"))["rules"]]


def test_rig_through_the_router(tmp_path, spawn):
    rig_file, bus = _rig(tmp_path)
    router = spawn("router", rig_file)
    up = spawn("up", rig_file)
    op = _operator(bus)
    plain = None
    rec_file = tmp_path / "rt.mcap"
    rec = None
    try:
        sub = op.subscribe(keys.state("rt_roach", "roach"), RobotState, latest=False)
        got: list[RobotState] = []

        def new() -> list[RobotState]:
            out = [decode(p, RobotState) for _, p in sub.drain()]
            got.extend(out)
            return out

        wait_for(lambda: new(), 60, "the driver's states through the router")
        rec = spawn("record", "--rig", rig_file, "--out", str(rec_file))
        # the recorder joins the router (its token; its subscription follows within the same start-up)
        wait_for(lambda: "recorder" in alive_nodes(op.session, "rt_roach", timeout_s=0.3), 60, "the recorder")
        time.sleep(0.5)

        # a session without the rig's credentials cannot join: its commands go nowhere
        plain = _plain_session(BusConfig(endpoint=bus.router))
        for _ in range(20):
            plain.put(keys.cmd("rt_roach", "roach"), encode(Command(robot="roach", action=[1.0, 1.0])))
            time.sleep(0.05)
        assert all(abs(x) < 1e-9 for s in new() for x in s.action), "an uncredentialed command was applied"

        # the operator drives the roach through the router
        cmd = op.publisher(keys.cmd("rt_roach", "roach"), Command)

        def moving():
            cmd.put(Command(robot="roach", action=[0.6, 0.6]))
            time.sleep(0.02)
            return any(s.action and s.action[0] > 0.1 and s.stopped_reason == "" for s in new())

        wait_for(moving, 30, "the operator's command applied")
        for _ in range(20):
            cmd.put(Command(robot="roach", action=[0.6, 0.6]))
            time.sleep(0.02)

        # the router dies mid-command: the driver hears no command and its watchdog stops the robot
        router.p.send_signal(signal.SIGKILL)
        router.p.wait(5)
        t_kill = time.time()
        time.sleep(1.0)
        router2 = spawn("router", rig_file)  # the same endpoint again: the clients reconnect
        wait_for(lambda: "recorder" in alive_nodes(op.session, "rt_roach", timeout_s=0.3), 60, "the recorder back")
        late = wait_for(lambda: [s for s in new() if s.stamp_s > t_kill + 0.5], 30, "states after the outage")
        assert all(s.stopped_reason == "stale" and all(abs(x) < 1e-9 for x in s.action) for s in late), late[0]
        rec_rc = rec.stop(20)
        assert router2.stop(10) == 0
    finally:
        op.close()
        if plain is not None:
            plain.close()
        up.stop(20)
    assert rec_rc == 0, rec.p.stderr.read()[-2000:]
    from mcap.reader import make_reader

    with open(rec_file, "rb") as f:
        topics = {}
        for _, ch, _ in make_reader(f).iter_messages():
            topics[ch.topic] = topics.get(ch.topic, 0) + 1
    assert topics.get(keys.state("rt_roach", "roach"), 0) > 20, topics
    assert topics.get(keys.cmd("rt_roach", "roach"), 0) > 5, topics  # the recorder heard the commands
