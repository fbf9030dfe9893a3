"""The e-stop: acknowledged by every driver node, latched across driver restarts, loud when unheard."""

from __future__ import annotations

import json
import threading

import pytest
from typer.testing import CliRunner

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.schemas import Command, EStop, ResetEvent, RobotState, decode, encode
from hilstack.configs.schema import load_rig, rig_robot_config
from hilstack.drivers.bridge import DriverNode
from hilstack.drivers.registry import make_driver
from hilstack.tools.cli import app
from tests.helpers import wait_for

RIG = "pointmass_sim"


class Driver:
    """A driver node (`hil up pointmass_sim` in-process) serving in a thread."""

    def __init__(self, bus, estop_sync_s: float = 1.0):
        cfg = load_rig(RIG)
        self.node = DriverNode(
            make_driver(rig_robot_config(cfg, "pm")), RIG, "pm", bus, handle_signals=False, estop_sync_s=estop_sync_s
        )
        self.th = threading.Thread(target=self.node.serve, daemon=True)
        self.th.start()

    def stop(self) -> None:
        self.node.stop_event.set()
        self.th.join(10)
        self.node.close()


def _states(sub) -> list[RobotState]:
    return [decode(p, RobotState) for _, p in sub.drain()]


def _until(sub, cond, what: str, timeout_s: float = 15.0) -> list[RobotState]:
    got: list[RobotState] = []

    def check():
        got.extend(_states(sub))
        return cond(got)

    wait_for(check, timeout_s, what)
    return got


def _estop(bus, *extra: str):
    return CliRunner().invoke(app, ["estop", RIG, "--endpoint", bus.endpoint, "--timeout-s", "3", *extra])


def test_estop_on_a_rig_without_driver_nodes_fails_naming_the_rig(bus):
    r = CliRunner().invoke(app, ["estop", "no_such_rig", "--endpoint", bus.endpoint, "--timeout-s", "0.5"])
    assert r.exit_code == 1, r.output
    assert "no_such_rig" in r.output and "NOT acknowledged" in r.output and "ENGAGED" not in r.output


def test_estop_acked_latched_across_a_driver_restart_and_released(bus):
    ctl = Node("test-ctl", RIG, bus, handle_signals=False)
    state = ctl.subscribe(keys.state(RIG, "pm"), RobotState, latest=False)
    cmd = ctl.publisher(keys.cmd(RIG, "pm"), Command)
    drv = Driver(bus)
    try:
        _until(state, lambda g: len(g) > 0, "first state")
        r = _estop(bus)
        assert r.exit_code == 0, r.output
        assert "ENGAGED" in r.output and "driver-pm" in r.output
        _until(state, lambda g: any(s.stopped_reason == "estop" for s in g), "estop state")
        assert ctl.estop.engaged  # the controller holds the latch too

        # the driver restarts while the e-stop is engaged: it must start stopped
        drv.stop()
        _states(state)
        drv = Driver(bus)
        first = _until(state, lambda g: len(g) > 0, "first state of the restarted driver")[0]
        assert first.stopped_reason == "estop" and not first.active
        got = []
        for _ in range(10):
            cmd.put(Command(robot="pm", action=[2.0, 0.0]))
            got += _until(state, lambda g: len(g) > 0, "states")
        assert all(s.action == [0.0, 0.0] and s.stopped_reason == "estop" for s in got)
        assert got[-1].health["estop_refused"] >= 1

        r = _estop(bus, "--release")
        assert r.exit_code == 0, r.output
        assert "released" in r.output and "driver-pm" in r.output

        def moving(g):
            cmd.put(Command(robot="pm", action=[2.0, 0.0]))
            return any(s.active and s.action and s.action[0] > 0 for s in g)

        _until(state, moving, "commands obeyed after the release")
    finally:
        drv.stop()
        ctl.close()


def test_a_late_driver_adopts_an_engaged_latch_from_any_peer(bus):
    holder = Node("viz", RIG, bus, handle_signals=False)
    holder.publisher(keys.estop(RIG), EStop, reliable=True).put(EStop(reason="test", source="test", id="x"))
    wait_for(lambda: holder.estop.engaged, 5, "the publishing node latches its own e-stop")
    drv = Driver(bus)
    try:
        wait_for(lambda: drv.node.stats.steps > 0, 15, "driver running")
        assert drv.node.estopped and not drv.node.driver.active
        # the bridge's loop is paced and timed by the cycle timer, section by section
        assert {"control", "sim_tick", "read_publish", "step"} <= set(drv.node.cycle.summary())
        assert drv.node.estop.engaged  # and it now answers engaged to later drivers
        # the latched state is retrievable by anyone: `hil nodes` shows it per node
        r = CliRunner().invoke(app, ["nodes", RIG, "--json", "--endpoint", bus.endpoint])
        assert r.exit_code == 0, r.output
        rows = {row["node"]: row for row in json.loads(r.stdout)}
        assert rows["driver-pm"]["estop"] == "engaged" and rows["viz"]["estop"] == "engaged"
        assert rows["viz"]["reason"] == "test"
    finally:
        drv.stop()
        holder.close()


def test_a_malformed_estop_never_replaces_the_latch(bus):
    with Node("a", RIG, bus, handle_signals=False) as a:
        a.publisher(keys.estop(RIG), EStop, reliable=True).put(EStop(reason="r", id="1"))
        wait_for(lambda: a.estop.engaged, 5, "latched")
        a.session.put(keys.estop(RIG), b"\xffnot an estop")
        wait_for(lambda: a.estop.malformed == 1, 5, "malformed counted")
        assert a.estop.engaged and a.estop.latched.id == "1"
        assert [m.id for m in a.estop.take()] == ["1"]
        a.session.put(keys.estop_release(RIG, "tester"), encode(EStop(engaged=False, id="2")))
        wait_for(lambda: not a.estop.engaged, 5, "released")
        assert a.estop.latched.sender == "tester"  # the release key names who released


@pytest.mark.parametrize("bad", ["0", "-1"])
def test_bad_timeout_is_a_user_error(bus, bad):
    r = CliRunner().invoke(app, ["estop", RIG, "--endpoint", bus.endpoint, "--timeout-s", bad])
    assert r.exit_code == 2 and "--timeout-s" in r.output


def test_a_release_the_driver_cannot_honour_is_acknowledged_as_still_engaged(bus):
    from hilstack.bus.estop import command_estop
    from tests.test_driver_base import Fake

    drv = Fake()
    node = DriverNode(drv, "relrig", "fake", bus, handle_signals=False, estop_sync_s=0.3)
    stop = threading.Event()

    def loop():  # the bridge's e-stop handling each period, without the rest of serve()
        while not stop.wait(0.01):
            node._handle_estop()

    drv.configure()
    drv.activate()
    th = threading.Thread(target=loop)
    th.start()
    try:
        with Node("op", "relrig", bus, handle_signals=False) as op:
            assert command_estop(op, engaged=True, timeout_s=3).ok
            assert node.estopped and not drv.active
            drv.fail_read = True  # the link is gone: activate() cannot read the measured state
            res = command_estop(op, engaged=False, timeout_s=1)
        assert not res.ok and res.acked == {"driver-fake": True} and res.missing == ["driver-fake"]
        assert node.estopped and node.stopped_reason == "estop"
    finally:
        stop.set()
        th.join()
        node.close()


def test_every_new_episode_republishes_the_spec(bus):
    """A recording that starts with an episode gets the spec however short it is (the 1 Hz /
    50-step repeat may fall outside it): the node sends the spec again on each reset."""
    cfg = load_rig(RIG)
    node = DriverNode(make_driver(rig_robot_config(cfg, "pm")), RIG, "pm", bus, handle_signals=False)
    try:
        node.driver.configure()
        node.driver.activate()
        sent: list[int] = []
        node.publish_spec = lambda: sent.append(node.episode)  # type: ignore[method-assign]
        ctl = Node("ctl", RIG, bus, handle_signals=False)
        try:
            req = ctl.publisher(keys.reset(RIG, "request"), ResetEvent)

            def served() -> bool:
                req.put(ResetEvent(robot="pm", phase="request", pose={"x": 0.0, "y": 0.0}))
                return node._handle_reset()

            wait_for(served, 10.0, "the reset request reaches the driver node")
        finally:
            ctl.close()
        assert sent == [1]  # one spec, sent for the new episode
    finally:
        node.driver.cleanup()
        node.close()
