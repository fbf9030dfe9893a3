"""Foxglove client publish: a WebSocket client (Foxglove's protocol) sends a teleop command, a
Twist and an e-stop engage through `hil foxglove`'s node; a release and bad input are refused;
the rig's access control decides who may command."""

import json
import struct

import pytest

from hilstack.bus import keys
from hilstack.bus.schemas import Command, EStop, RobotState, SpecMsg, decode, encode
from hilstack.drivers.registry import spec_of
from hilstack.tools.foxglove_live import FoxgloveLive, command_refusal
from tests.helpers import wait_for

RIG = "fgpub"
ROACH = spec_of("velociroach", "sim").to_dict()


def test_commands_are_refused_for_a_user_outside_the_rigs_command_list(monkeypatch):
    from hilstack.tools.common import rig_bus

    _, bus, _ = rig_bus("roach_emulated")
    assert command_refusal("roach_emulated", bus) is None  # the rig's operator may command
    monkeypatch.setenv("HIL_BUS_USER", "viewer")
    assert "user 'viewer' may not command rig roach_emulated" in command_refusal("roach_emulated", bus)
    assert command_refusal(RIG, None) is None


def test_client_publishes_a_command_a_twist_and_an_estop_engage(bus):
    from websockets.sync.client import connect

    from hilstack.bus.node import Node

    live = FoxgloveLive(RIG, bus, port=0, handle_signals=False)
    node = Node("fg-test", RIG, bus, handle_signals=False)
    cmds = node.subscribe(keys.cmd(RIG, "roach"), Command, latest=False)
    estops = node.subscribe(keys.estop(RIG), EStop, latest=False)
    got_cmds: list[Command] = []
    got_estops: list[EStop] = []
    statuses: list[str] = []
    try:
        with connect(live.url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            info = json.loads(ws.recv(timeout=5))
            assert info["op"] == "serverInfo" and "clientPublish" in info["capabilities"]
            assert "json" in info["supportedEncodings"]
            ws.send(json.dumps({"op": "advertise", "channels": [
                {"id": 1, "topic": keys.cmd(RIG, "roach"), "encoding": "json", "schemaName": "hil.Command"},
                {"id": 2, "topic": keys.estop(RIG), "encoding": "json", "schemaName": "hil.EStop"},
                {"id": 3, "topic": f"hil/{RIG}/roach/state", "encoding": "json", "schemaName": "x"}]}))

            def send(ch, body):
                ws.send(struct.pack("<BI", 0x01, ch) + (body if isinstance(body, bytes) else json.dumps(body).encode()))

            # the robot's spec and newest state on the bus (a driver node would publish them)
            node.session.put(keys.spec(RIG, "roach"), encode(SpecMsg(robot="roach", spec=ROACH, seq=1)))
            node.session.put(keys.state(RIG, "roach"), encode(RobotState(robot="roach", t_s=1.0, state=[0.0] * 3,
                                                                         action=[0.0, 0.0], seq=7)))
            wait_for(lambda: live.pump() >= 0 and "roach" in live._specs and "roach" in live._state_seq, 10,
                     "the spec and state at the node")
            send(1, {"action": [3.0, -2.0]})
            send(1, {"linear": {"x": 0.5, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}})
            send(1, b'{"action": [1.0, NaN]}')
            send(1, b"not json")
            send(3, {"robot": "roach"})  # not a topic a client may publish on
            send(2, {"engaged": False})  # a release: refused
            send(2, {"reason": "foxglove button"})

            def step():
                live.pump()
                got_cmds.extend(decode(b, Command) for _, b in cmds.drain())
                got_estops.extend(decode(b, EStop) for _, b in estops.drain())
                try:
                    while True:
                        frame = ws.recv(timeout=0.02)
                        if isinstance(frame, str) and json.loads(frame)["op"] == "status":
                            statuses.append(json.loads(frame)["message"])
                except TimeoutError:
                    pass
                return len(got_cmds) >= 2 and got_estops and len(live.refused) >= 4 and len(statuses) >= 4

            wait_for(step, 20, "two commands, an e-stop and four refusals")
    finally:
        node.close()
        live.close()
    assert got_cmds[0].action == [3.0, -2.0] and got_cmds[0].source == "foxglove" and got_cmds[0].state_seq == 7
    # Twist: half speed, no turn → hil teleop's drive map (both legs at half their 15 rad/s range)
    assert got_cmds[1].action == pytest.approx([7.5, 7.5])
    assert live.client_commands == 2 and live.client_estops == 1
    assert all(e.engaged for e in got_estops) and got_estops[0].reason == "foxglove button"
    assert got_estops[0].sender == live.user and got_estops[0].source == "foxglove"
    refused = "\n".join(live.refused)
    assert "finite numbers" in refused and "not JSON" in refused and "not a topic a client may publish" in refused
    assert "a release is not taken from Foxglove" in refused
    assert any("a release is not taken" in s for s in statuses)
