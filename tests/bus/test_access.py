"""Who may command and who may release a rig (issue 22, item 8): Zenoh user/password
authentication and ACL, with real sessions and a real driver node process.

The rig's driver node (`hil up`, its own process) owns the rig's endpoint as a Zenoh router
with the rig's credentials and ACL. A plain Zenoh session without credentials, and one with
credentials but no command/release role, try to release the e-stop and drive the robot: the
robot must not move and the e-stop must stay engaged. A credentialed operator can.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time

import pytest
import zenoh
from typer.testing import CliRunner

from hilstack.bus import keys
from hilstack.bus.access import AccessError, acl, generate, provision, read_credentials
from hilstack.bus.estop import command_estop
from hilstack.bus.node import Node
from hilstack.bus.schemas import Command, EStop, RobotState, decode, encode
from hilstack.bus.session import BusUnavailable, zenoh_config
from hilstack.configs.schema import BusAccess, BusConfig, load_rig
from hilstack.tools.cli import app
from hilstack.tools.common import with_endpoint
from tests.helpers import ROOT, free_port, wait_for


def _rig_file(tmp_path, name: str, robots: str, **access) -> tuple[str, BusConfig]:
    creds = tmp_path / f"{name}.credentials"
    generate(creds, ["operator", "viewer"])
    ep = f"tcp/127.0.0.1:{free_port()}"
    acc = json.dumps({"credentials": str(creds), **access})
    path = tmp_path / f"{name}.yaml"
    path.write_text(f"name: {name}\nrobots:\n{robots}\nwatchdog_periods: 3\npace: realtime\n"
                    f"bus:\n  endpoint: {ep}\n  access: {acc}\n")
    return str(path), load_rig(path).bus


def _as(bus: BusConfig, user: str) -> BusConfig:
    return BusConfig.model_validate({**bus.model_dump(), "access": {**bus.access.model_dump(), "user": user}})


def _still(s: RobotState) -> bool:
    """The state's held action is the safe one (nothing commanded was applied)."""
    return all(abs(a) < 1e-9 for a in s.action)


def _plain_session(bus: BusConfig) -> zenoh.Session:
    """What any process on the host can open: a peer on the rig's endpoint, no credentials."""
    return zenoh.open(zenoh_config(BusConfig(endpoint=bus.endpoint)))


def _hil(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hilstack.tools.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


class States:
    def __init__(self, node: Node, rig: str, robot: str):
        self.sub = node.subscribe(keys.state(rig, robot), RobotState, latest=False)
        self.got: list[RobotState] = []

    def new(self) -> list[RobotState]:
        out = [decode(p, RobotState) for _, p in self.sub.drain()]
        self.got += out
        return out

    def until(self, cond, what: str, timeout_s: float = 30.0) -> RobotState:
        found: list[RobotState] = []

        def check():
            found.extend(s for s in self.new() if cond(s))
            return found

        wait_for(check, timeout_s, what)
        return found[0]


# ---------------------------------------------------------------------------- the emulated roach
ROACH = "  roach:\n    config: velociroach\n    backend: emulated\n    params: {link_timeout_periods: 30, " \
        "write_timeout_s: 3.0}"


def test_without_the_rigs_credentials_nobody_drives_or_releases_the_emulated_roach(tmp_path, spawn):
    rig_file, bus = _rig_file(tmp_path, "acc_roach", ROACH)
    up = spawn("up", rig_file)
    _wait_up(bus, "acc_roach", "roach")
    op = Node("test-operator", "acc_roach", _as(bus, "operator"), handle_signals=False)
    plain = viewer = None
    try:
        states = States(op, "acc_roach", "roach")
        first = states.until(lambda s: s.ok, "the roach's first state", 90)
        x0, y0 = first.state[0], first.state[1]

        # 1. a plain session (no credentials): cannot even join; its commands and release go nowhere
        plain = _plain_session(bus)
        p_cmd = plain.declare_publisher(keys.cmd("acc_roach", "roach"))
        for _ in range(40):  # 2 s of full-speed commands, and releases on both keys
            p_cmd.put(encode(Command(robot="roach", action=[1.0, 1.0], source="intruder")))
            plain.put(keys.estop_release("acc_roach", "operator"), encode(EStop(engaged=False, sender="operator")))
            plain.put(keys.estop("acc_roach"), encode(EStop(engaged=False)))
            time.sleep(0.05)
        states.new()
        during = [s for s in states.got if s.stamp_s > first.stamp_s]
        assert during and all(_still(s) for s in during), "an uncredentialed command was applied"
        assert all(s.stopped_reason != "" for s in during)

        # 2. the operator engages the e-stop
        res = command_estop(op, engaged=True, reason="test", timeout_s=10)
        assert res.ok, res
        states.until(lambda s: s.stopped_reason == "estop", "the e-stop")

        # 3. an authenticated user without the release role engages fine but cannot release or command
        viewer = Node("test-viewer", "acc_roach", _as(bus, "viewer"), handle_signals=False)
        assert command_estop(viewer, engaged=True, reason="viewer engages", timeout_s=10).ok
        v_rel = command_estop(viewer, engaged=False, timeout_s=1.5)
        assert not v_rel.confirmed  # the ACL dropped it: no driver heard a release
        v_cmd = viewer.publisher(keys.cmd("acc_roach", "roach"), Command)
        for _ in range(20):
            v_cmd.put(Command(robot="roach", action=[1.0, 1.0]))
            viewer.session.put(keys.estop_release("acc_roach", "operator"), encode(EStop(engaged=False)))
            plain.put(keys.estop_release("acc_roach", "operator"), encode(EStop(engaged=False)))
            time.sleep(0.05)
        t_mark = time.time()
        late = states.until(lambda s: s.stamp_s > t_mark, "a state after the attempts")
        assert late.stopped_reason == "estop" and not late.active and _still(late)
        assert math.hypot(late.state[0] - x0, late.state[1] - y0) < 0.05

        # 4. the operator releases with the CLI (the rig file gives the endpoint and credentials)
        r = _hil("estop", rig_file, "--release", "--timeout-s", "10")
        assert r.returncode == 0, r.stderr
        assert "released e-stop on rig acc_roach: acknowledged by driver-roach (released by operator)" in r.stderr
        states.until(lambda s: s.active, "the release")
        r = _hil("nodes", rig_file, "--json")
        assert r.returncode == 0, r.stderr
        row = next(x for x in json.loads(r.stdout) if x["node"] == "driver-roach")
        assert row["estop"] == "released" and row["sender"] == "operator"

        # 5. and drives the robot
        cmd = op.publisher(keys.cmd("acc_roach", "roach"), Command)

        def moving():
            cmd.put(Command(robot="roach", action=[0.6, 0.6]))
            return any(s.action and s.action[0] > 0.1 for s in states.new())

        wait_for(moving, 30, "the operator's command applied")
    finally:
        for n in (viewer, op):
            if n is not None:
                n.close()
        if plain is not None:
            plain.close()
        assert up.stop(30) == 0


# ---------------------------------------------------------------------------- finer points (sim)
PM = "  pm:\n    config: pointmass\n    backend: sim"


@pytest.fixture
def pm_rig(tmp_path, spawn):
    rig_file, bus = _rig_file(tmp_path, "acc_pm", PM, command=["operator"], release=["operator", "viewer"])
    up = spawn("up", rig_file)
    _wait_up(bus, "acc_pm", "pm")
    yield rig_file, bus
    assert up.stop(20) == 0


def _wait_up(bus: BusConfig, rig: str, robot: str, timeout_s: float = 90) -> None:
    """Until the driver node's router takes the operator and its first state arrives."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            node = Node("test-wait", rig, _as(bus, "operator"), handle_signals=False)
            break
        except BusUnavailable:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    try:
        States(node, rig, robot).until(lambda s: True, "the first state", timeout_s)
    finally:
        node.close()


def test_wildcard_puts_and_releases_on_anothers_key_are_dropped(pm_rig):
    """Zenoh's ACL does not match a key wider than a rule's: with default deny a put on
    hil/<rig>/** is dropped (with default allow + deny rules it would reach the command
    subscriber). A release user may release only on their own key."""
    _, bus = pm_rig
    op = Node("test-operator", "acc_pm", _as(bus, "operator"), handle_signals=False)
    viewer = Node("test-viewer", "acc_pm", _as(bus, "viewer"), handle_signals=False)
    try:
        states = States(op, "acc_pm", "pm")
        states.until(lambda s: True, "first state")
        for key in ("hil/acc_pm/**", "hil/acc_pm/*/cmd", "hil/**", "**"):
            for _ in range(10):
                viewer.session.put(key, encode(Command(robot="pm", action=[1.0, 0.0])))
                time.sleep(0.02)
        time.sleep(0.3)
        assert all(_still(s) for s in states.new() + states.got)
        assert command_estop(op, engaged=True, reason="t", timeout_s=10).ok
        # viewer may release, but only as viewer: a release on the operator's key is dropped
        for _ in range(10):
            viewer.session.put(keys.estop_release("acc_pm", "operator"), encode(EStop(engaged=False)))
            viewer.session.put("hil/acc_pm/estop/release/*", encode(EStop(engaged=False)))
            time.sleep(0.02)
        t_mark = time.time()
        assert states.until(lambda s: s.stamp_s > t_mark, "state").stopped_reason == "estop"
        res = command_estop(viewer, engaged=False, timeout_s=10)
        assert res.ok, res
        assert op.estop.latched.sender == "viewer" and not op.estop.engaged
    finally:
        viewer.close()
        op.close()


def test_a_client_with_wrong_credentials_gets_one_line(pm_rig, tmp_path):
    rig_file, bus = pm_rig
    wrong = tmp_path / "wrong.txt"
    wrong.write_text("operator:not-the-password\n")
    wrong.chmod(0o600)
    r = subprocess.run([sys.executable, "-m", "hilstack.tools.cli", "estop", rig_file, "--timeout-s", "1"],
                       cwd=ROOT, capture_output=True, text=True, timeout=60,
                       env={**__import__("os").environ, "HIL_CREDENTIALS": str(wrong)})
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: cannot join the rig at tcp/127.0.0.1:")
    assert "as user 'operator'" in lines[0]


def test_a_second_rig_on_a_taken_endpoint_fails_closed(pm_rig, tmp_path):
    """Rigs on one host do not share an access-controlled endpoint silently."""
    _, bus = pm_rig
    other = tmp_path / "other.yaml"
    other.write_text(f"name: other\nrobots:\n{PM}\nbus:\n  endpoint: {bus.endpoint}\n"
                     f"  access: {{credentials: {bus.access.credentials}}}\n")
    r = _hil("up", str(other), "--steps", "5")
    assert r.returncode == 1, r.stderr
    assert f"rig other: cannot own its endpoint {bus.endpoint}" in r.stderr and "Traceback" not in r.stderr


def test_a_user_without_the_release_role_is_told_before_sending(pm_rig):
    rig_file, _ = pm_rig
    r = _hil("estop", rig_file, "--release", "--timeout-s", "1")  # operator may release here: acked or not alive
    assert "may not release" not in r.stderr
    import os

    r = subprocess.run([sys.executable, "-m", "hilstack.tools.cli", "estop", rig_file, "--release"], cwd=ROOT,
                       capture_output=True, text=True, timeout=60, env={**os.environ, "HIL_BUS_USER": "mallory"})
    assert r.returncode == 2 and r.stderr.strip() == (
        "error: user 'mallory' may not release rig acc_pm's e-stop (bus.access.release: ['operator', 'viewer'])")


# ---------------------------------------------------------------------------- no I/O
def test_credentials_files_are_checked(tmp_path):
    p = tmp_path / "c.txt"
    with pytest.raises(AccessError, match="not found: create it with `hil credentials RIG`"):
        read_credentials(p)
    assert generate(p, ["operator", "mpc", "operator"]) == ["operator", "mpc"]
    assert (p.stat().st_mode & 0o777) == 0o600
    first = read_credentials(p)
    assert set(first) == {"operator", "mpc"} and len(first["operator"]) >= 30
    assert generate(p, ["operator", "viewer"]) == ["viewer"]
    assert read_credentials(p)["operator"] == first["operator"]  # existing lines are kept
    p.chmod(0o644)
    with pytest.raises(AccessError, match="readable by others \\(mode 644\\): chmod 600"):
        read_credentials(p)
    p.chmod(0o600)
    p.write_text("operator\n")
    with pytest.raises(AccessError, match="line 1: expected user:password"):
        read_credentials(p)


def test_the_acl_is_default_deny_and_binds_releases_to_their_user():
    a = acl("r", ["pm"], BusAccess(credentials="x", command=["mpc"], release=["alice", "bob"]))
    assert a["default_permission"] == "deny"
    rules = {r["id"]: r for r in a["rules"]}
    assert rules["command"]["key_exprs"][0] == "hil/r/pm/cmd"
    assert rules["release-alice"]["key_exprs"] == ["hil/r/estop/release/alice"]
    assert rules["engage"]["key_exprs"] == ["hil/r/estop"]
    pol = {p["id"]: p for p in a["policies"]}
    assert pol["release-bob"]["subjects"] == ["user-bob"]
    with pytest.raises(AccessError, match="reserved"):
        acl("r", ["reset"], BusAccess(credentials="x"))


def test_a_missing_credentials_file_is_one_line_exit_2(tmp_path):
    rig = tmp_path / "r.yaml"
    rig.write_text(f"name: nocred\nrobots:\n{PM}\nbus:\n  access: {{credentials: {tmp_path / 'absent.txt'}}}\n")
    r = CliRunner().invoke(app, ["nodes", str(rig)])
    assert r.exit_code == 2
    assert r.output.strip() == (f"error: credentials file {tmp_path / 'absent.txt'} not found: create it with "
                                "`hil credentials RIG` (or point HIL_CREDENTIALS at yours)")
    r = CliRunner().invoke(app, ["credentials", str(rig)])
    assert r.exit_code == 0, r.output
    assert set(read_credentials(tmp_path / "absent.txt")) == {"operator"}


def test_no_session_opens_without_the_credentials_a_client_needs(tmp_path):
    creds = tmp_path / "c.txt"
    generate(creds, ["operator"])
    bus = BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}", access=BusAccess(credentials=str(creds), user="eve"))
    with pytest.raises(AccessError, match="has no line for user 'eve'"):
        Node("n", "r", bus, handle_signals=False)
    bus = BusConfig(endpoint=bus.endpoint, access=BusAccess(credentials=str(creds)))
    with pytest.raises(BusUnavailable, match="no driver node listening there"):
        Node("n", "r", bus, handle_signals=False)


def test_a_second_driver_node_of_the_same_rig_and_robot_is_refused(spawn):
    """Two rigs of one name on one endpoint (another user's `hil up` of the same rig on this
    host) no longer share the robot's command key silently: the second driver node refuses."""
    import socket

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    spawn("up", "pointmass_sim", "--endpoint", ep)
    # the first driver node owns the rendezvous port (a test node opened earlier would own it instead)
    wait_for(lambda: socket.socket().connect_ex(("127.0.0.1", port)) == 0, 60, "the first driver's listener")
    with Node("test-watch", "pointmass_sim", BusConfig(endpoint=ep), handle_signals=False) as w:
        States(w, "pointmass_sim", "pm").until(lambda s: True, "the first driver's state", 60)
    r = _hil("up", "pointmass_sim", "--endpoint", ep, "--steps", "50")
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        f"error: a node driver-pm is already alive on rig pointmass_sim at {ep}: another process (another user's "
        "rig of the same name?) drives it; give each rig its own bus.endpoint")


# ---------------------------------------------------------------------------- the rigs as shipped
def test_the_shipped_emulated_roach_rig_admits_only_its_credentials(tmp_path, spawn, monkeypatch):
    """configs/rigs/roach_emulated.yaml as shipped (only the endpoint private, so parallel runs do
    not meet): `hil up` on a fresh HOME creates its credentials unattended; a plain Zenoh session
    can neither command nor release; the operator engages, releases and drives."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))  # this test's nodes and the `hil up` it starts
    rig = "roach_emulated"
    bus = with_endpoint(load_rig(rig).bus, f"tcp/127.0.0.1:{free_port()}")
    creds = home / ".config" / "hilstack" / "roach_emulated.credentials"
    assert not creds.exists()
    up = spawn("up", rig, "--endpoint", bus.endpoint)
    wait_for(lambda: creds.is_file() and creds.stat().st_size > 0, 60, "hil up to create the credentials")
    _wait_up(bus, rig, "roach")
    assert (creds.stat().st_mode & 0o777) == 0o600 and set(read_credentials(creds)) == {"operator"}
    op = Node("test-operator", rig, bus, handle_signals=False)
    plain = None
    try:
        states = States(op, rig, "roach")
        first = states.until(lambda s: s.ok, "the roach's first state", 90)

        def intrude(n: int) -> None:
            for _ in range(n):  # full-speed commands, and releases on every release key
                plain.put(keys.cmd(rig, "roach"), encode(Command(robot="roach", action=[1.0, 1.0])))
                plain.put(keys.estop_release(rig, "operator"), encode(EStop(engaged=False, sender="operator")))
                plain.put(keys.estop(rig), encode(EStop(engaged=False)))
                time.sleep(0.05)

        plain = _plain_session(bus)
        intrude(40)
        states.new()
        during = [s for s in states.got if s.stamp_s > first.stamp_s]
        assert during and all(_still(s) for s in during), "an uncredentialed command was applied"

        assert command_estop(op, engaged=True, reason="test", timeout_s=10).ok
        states.until(lambda s: s.stopped_reason == "estop", "the e-stop")
        intrude(20)
        t_mark = time.time()
        late = states.until(lambda s: s.stamp_s > t_mark, "a state after the release attempts")
        assert late.stopped_reason == "estop" and not late.active and _still(late)

        res = command_estop(op, engaged=False, timeout_s=10)
        assert res.ok, res
        states.until(lambda s: s.active, "the operator's release")
        cmd = op.publisher(keys.cmd(rig, "roach"), Command)

        def moving():
            cmd.put(Command(robot="roach", action=[0.6, 0.6]))
            return any(s.action and s.action[0] > 0.1 for s in states.new())

        wait_for(moving, 30, "the operator's command applied")
    finally:
        op.close()
        if plain is not None:
            plain.close()
        assert up.stop(30) == 0
    err = up.p.stderr.read()
    assert f"created credentials for rig roach_emulated in {creds} (users operator; mode 600)" in err


def test_every_rig_with_hardware_has_access_control_on_its_own_endpoint():
    """Emulated and real robots: bus.access and an endpoint no other rig config uses; sim-only rigs stay open."""
    seen: dict[str, str] = {}
    for path in sorted((ROOT / "configs" / "rigs").glob("*.yaml")):
        cfg = load_rig(path)
        hardware = any(r.backend in ("emulated", "real") for r in cfg.robots.values())
        assert (cfg.bus.access is not None) == hardware, f"{path.name}: access {cfg.bus.access}"
        if hardware:  # a rig with its own router (`hil router`): that is its endpoint
            ep = cfg.bus.router or cfg.bus.endpoint
            assert ep not in seen, f"{path.name} and {seen.get(ep)} share an endpoint"
            seen[ep] = path.name
    assert len(seen) >= 6


def test_an_emulated_robot_on_a_rig_without_access_is_refused(tmp_path):
    rig = tmp_path / "open_roach.yaml"
    rig.write_text(f"name: open_roach\nrobots:\n{ROACH}\nwatchdog_periods: 3\npace: realtime\n")
    r = _hil("up", str(rig), "--endpoint", f"tcp/127.0.0.1:{free_port()}", "--steps", "5")
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        "error: rig open_roach: robot roach is emulated hardware; its rig needs a bus.access section "
        "(who may command and release it; docs/platform.md)")


def test_credentials_are_created_unattended_for_emulated_rigs_only(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    real = load_rig("roach_real")
    r = CliRunner().invoke(app, ["up", "roach_real", "--endpoint", f"tcp/127.0.0.1:{free_port()}", "--steps", "1"])
    assert r.exit_code == 2
    path = tmp_path / ".config" / "hilstack" / "roach_real.credentials"
    assert r.output.strip().splitlines()[-1] == (
        f"error: credentials file {path} not found: create it with `hil credentials RIG` "
        "(or point HIL_CREDENTIALS at yours)")
    assert provision("roach_real", real.bus, ["real"]) is None and not path.exists()
    emu = load_rig("hand_emulated")
    line = provision("hand_emulated", emu.bus, ["emulated"])
    path = tmp_path / ".config" / "hilstack" / "hand_emulated.credentials"
    assert line == f"created credentials for rig hand_emulated in {path} (users operator; mode 600)"
    assert (path.stat().st_mode & 0o777) == 0o600 and set(read_credentials(path)) == {"operator"}
    before = path.read_text()
    assert provision("hand_emulated", emu.bus, ["emulated"]) is None and path.read_text() == before  # kept
    # HIL_CREDENTIALS names the file instead (an operator's own copy, a CI secret)
    monkeypatch.setenv("HIL_CREDENTIALS", str(tmp_path / "ci.credentials"))
    assert "in " + str(tmp_path / "ci.credentials") in provision("hand_emulated", emu.bus, ["emulated"])
