"""The emulator's lab fixture over its real interface (UDP beside the robot, not its radio):
alone, and as the reset supervisor's `lab_fixture` step finds it through the emulated
driver's health (`hil up` in its own process, the real radio driver over a pty)."""

from __future__ import annotations

import json
import math
import socket
import threading
from pathlib import Path

import yaml

from hilstack.configs.schema import load_rig
from hilstack.control.controller_node import ControllerNode
from hilstack.control.reset.config import require_reset
from hilstack.control.reset.supervisor import ResetSupervisor
from hilstack.drivers.emulator_process import EmulatorProcess
from hilstack.drivers.fixture import FixtureClient
from hilstack.drivers.mocap.udp import UdpPoseClient
from hilstack.drivers.velociroach.config import quat_to_rpy
from tests.helpers import wait_for, wait_rig_router


def _cos_roll(pc: UdpPoseClient) -> float:
    s = pc.latest()
    return math.cos(quat_to_rpy(s.quaternion_wxyz)[0]) if s is not None else float("nan")


def _ask(client: FixtureClient) -> dict:
    client.request("right")
    return wait_for(client.reply, 5, "the fixture's reply")


def test_the_emulator_fixture_puts_a_robot_on_its_back_onto_its_legs():
    with UdpPoseClient("127.0.0.1", 0) as pc:
        emu = EmulatorProcess("hilstack.sim_backends.velociroach.emulator", [
            "--print-pty", "--pose-port", str(pc.port), "--fixture-port", "0",
            "--config", json.dumps({"emulator": {"start_upside_down": True}})])
        try:
            port = emu.start()["fixture_port"]
            wait_for(lambda: _cos_roll(pc) < -0.9, 10, "the robot on its back")
            client = FixtureClient(port)
            try:
                r = _ask(client)
                assert r["ok"] and r["acted"]
                wait_for(lambda: _cos_roll(pc) > 0.95, 5, "the robot upright")
                assert _ask(client)["acted"] is False  # upright: the fixture leaves it alone
            finally:
                client.close()
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.settimeout(5)
                s.sendto(b'{"op": "fly"}', ("127.0.0.1", port))
                bad = json.loads(s.recv(512))
            assert bad == {"ok": False, "detail": "bad lab-fixture request: unknown op 'fly'; known: ['right']"}
        finally:
            emu.stop()


def test_the_supervisor_rights_the_emulated_roach_through_the_fixture_and_drives_it_back(rig_bus, spawn, tmp_path):
    rig = yaml.safe_load(Path(load_rig("roach_emulated").source).read_text())
    rig["name"] = "roach_flipped"
    rig["robots"]["roach"]["params"] = {**rig["robots"]["roach"].get("params", {}),
                                        "emulator": {"start_upside_down": True}}
    # self_right holds still until it gives up: random kicks right a robot on its back about
    # once in a hundred tries (docs/reset.md), which would make this test flaky
    rig["reset"]["steps"][0].update(timeout_s=1.5, params={"hold_first_s": 2.0})
    path = tmp_path / "roach_flipped.yaml"
    path.write_text(yaml.safe_dump(rig))
    bus = rig_bus(str(path))  # roach_emulated's access control: the supervisor and controller log in
    spawn("up", str(path), "--endpoint", bus.endpoint)
    wait_rig_router(bus)
    cfg = require_reset(load_rig(path), "roach")
    sup = ResetSupervisor("roach_flipped", cfg, bus, handle_signals=False)
    th = threading.Thread(target=sup.serve, daemon=True)
    th.start()
    try:
        with ControllerNode("roach_flipped", "roach", bus, handle_signals=False, state_timeout_s=20) as ctl:
            ctl.wait_ready(60)
            s = ctl.next_state()
            assert s.state[6] < -0.9  # cos_roll: on its back
            assert s.health["lab_fixture_port"] > 0
            first = ctl.reset(timeout_s=1.5 * cfg.max_duration_s() + 10, x=0.0, y=0.0, yaw=0.0)
            assert first.episode == 1
            assert first.state[6] > 0.9 and first.state[8] > 0.9
        h = sup.history
        assert [t.trigger for t in h][:4] == ["end_episode", "pause", "begin", "skip"]
        assert h[3].step == "self_right" and [t.dest for t in h][-2:] == ["resumed", "running"]
        rep = sup.report()
        assert rep["fixture_recoveries"] == 1 and rep["completed"] == 1 and rep["failed"] == 0
    finally:
        sup.stop_event.set()
        th.join(10)
        sup.close()
