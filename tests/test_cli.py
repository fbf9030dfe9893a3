"""The `hil` command: its verbs, and user errors as one line with exit code 2."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from hilstack.tools.cli import app


def test_help_lists_the_verbs():
    r = CliRunner().invoke(app, ["--help"])
    assert r.exit_code == 0
    for verb in ("demo", "drive", "record", "replay", "inspect", "viz", "calibrate", "bench", "up", "estop",
                 "nodes", "mpc", "teleop", "find-port", "data"):
        assert f" {verb} " in r.output, verb
    r = CliRunner().invoke(app, ["bench", "--help"])
    assert all(w in r.output for w in ("bus", "plan", "sim"))


def test_boolean_flags_are_shown_as_flags():
    """Issue 27 item 6: `--json`, not `--json <bool>` (typer 0.29 gives flags a type column)."""
    import typer

    def leaves(cmd, path):
        subs = getattr(cmd, "commands", None)
        return [x for n, c in subs.items() for x in leaves(c, [*path, n])] if subs else [path]

    verbs = leaves(typer.main.get_command(app), [])
    assert ["teleop"] in verbs and ["bench", "bus"] in verbs
    for verb in verbs:
        r = CliRunner().invoke(app, [*verb, "--help"], env={"COLUMNS": "200"})
        assert r.exit_code == 0 and "--help" in r.output
        assert "<bool>" not in r.output, verb
    r = CliRunner().invoke(app, ["mpc", "--help"], env={"COLUMNS": "200"})
    assert "--json" in r.output and "--no-reset" in r.output and "<int>" in r.output  # values keep their type


def test_user_errors_are_one_line_exit_2():
    r = CliRunner().invoke(app, ["up", "no_such_rig"])
    assert r.exit_code == 2 and "no such rig config" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, ["replay", "x.mcap", "--speed", "-1"])
    assert r.exit_code == 2
    r = CliRunner().invoke(app, ["viz"])
    assert r.exit_code == 2 and "--rig" in r.output


def _recording(path):
    from hilstack.bus import keys
    from hilstack.bus.recording import McapLog
    from hilstack.bus.schemas import Command, EStop, RobotState

    with McapLog(path) as log:
        for i in range(3):
            log.write(keys.state("clirig", "pm"), RobotState(robot="pm", t_s=float(i), state=[0.0]), log_time_ns=i)
            log.write(keys.cmd("clirig", "pm"), Command(robot="pm", action=[1.0]), log_time_ns=i)
            log.write(keys.estop("clirig"), EStop(engaged=False), log_time_ns=i)
    return path


def test_replay_cli_says_what_it_left_out_and_refuses_a_live_rig(tmp_path, bus):
    from hilstack.bus import keys
    from hilstack.bus.node import Node

    path = _recording(tmp_path / "r.mcap")
    r = CliRunner().invoke(app, ["replay", str(path), "--speed", "0", "--endpoint", bus.endpoint])
    assert r.exit_code == 0, r.output
    assert "replayed 3 messages" in r.output
    assert "not replayed: 3 command messages" in r.output
    assert "never replayed: 3 e-stop releases on hil/clirig/estop" in r.output
    r = CliRunner().invoke(app, ["replay", str(path), "--topics", "hil//x", "--endpoint", bus.endpoint])
    assert r.exit_code == 2 and "--topics: bad topic pattern 'hil//x'" in r.output

    with Node(keys.driver_node("pm"), "clirig", bus, handle_signals=False):
        r = CliRunner().invoke(app, ["replay", str(path), "--speed", "0", "--endpoint", bus.endpoint])
        assert r.exit_code == 2, r.output
        assert "rig 'clirig' has live driver nodes (driver-pm)" in r.output and "--force" in r.output
        assert len(r.output.strip().splitlines()) == 1 and "Traceback" not in r.output
        r = CliRunner().invoke(
            app, ["replay", str(path), "--speed", "0", "--force", "--include-commands", "--endpoint", bus.endpoint]
        )
        assert r.exit_code == 0 and "replayed 6 messages" in r.output and "never replayed: 3 e-stop releases" in r.output


def test_version_is_the_package_version():
    from importlib.metadata import version

    r = CliRunner().invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.strip() == f"hilstack {version('hilstack')}"


def access_section(tmp_path) -> str:
    """A rig's bus section with access control on a private endpoint, its credentials generated."""
    from hilstack.bus.access import generate
    from tests.helpers import free_port

    creds = tmp_path / "creds.txt"
    generate(creds, ["operator"])
    return f"bus:\n  endpoint: tcp/127.0.0.1:{free_port()}\n  access: {{credentials: {creds}}}\n"


def real_roach(tmp_path, port: str):
    robot = tmp_path / "my_roach.yaml"
    robot.write_text(f"robot: velociroach\nbackend: real\nparams:\n  port: {port}\n")
    rig = tmp_path / "my_rig.yaml"
    rig.write_text(f"name: my_rig\nrobots:\n  roach:\n    config: {robot}\n" + access_section(tmp_path))
    return robot, rig


def test_a_real_robot_on_a_rig_without_access_control_is_refused(tmp_path):
    robot, _ = real_roach(tmp_path, "/dev/ttyNOPE_hilstack")
    rig = tmp_path / "open_rig.yaml"
    rig.write_text(f"name: open_rig\nrobots:\n  roach:\n    config: {robot}\n")
    r = CliRunner().invoke(app, ["up", str(rig), "--steps", "1"])
    assert r.exit_code == 2, r.output
    assert r.output.strip() == ("error: rig open_rig: robot roach is real hardware; its rig needs a bus.access "
                                "section (who may command and release it; docs/platform.md)")


def test_drive_uses_the_backend_of_the_config_file(tmp_path):
    robot, _ = real_roach(tmp_path, "/dev/ttyNOPE_hilstack")
    # the file says real: the driver looks for its (missing) port instead of driving the sim
    r = CliRunner().invoke(app, ["drive", str(robot), "--action", "0.1,0.1", "--seconds", "0.2"])
    assert r.exit_code == 2, r.output
    assert "params.port: /dev/ttyNOPE_hilstack does not exist" in r.output and "Traceback" not in r.output
    # --backend still overrides the file
    r = CliRunner().invoke(app, ["drive", str(robot), "--backend", "sim", "--action", "0.1,0.1",
                                 "--seconds", "0.2", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output.strip().splitlines()[-1])["backend"] == "sim"


def test_link_errors_exit_1_in_up_and_drive_alike(tmp_path):
    """One convention for every verb: 2 = fix your input, 1 = the robot or link failed."""
    not_a_tty = tmp_path / "not_a_tty"
    not_a_tty.write_bytes(b"")  # exists, but no serial port can be configured on it
    robot, rig = real_roach(tmp_path, str(not_a_tty))
    codes = {}
    for verb, args in (("drive", [str(robot), "--action", "0,0"]), ("up", [str(rig), "--steps", "1"])):
        r = CliRunner().invoke(app, [verb, *args])
        codes[verb] = r.exit_code
        err = [ln for ln in r.output.splitlines() if ln.startswith("link error:")]
        assert len(err) == 1 and "cannot open serial port" in err[0], r.output
    assert codes == {"drive": 1, "up": 1}


def test_a_rig_whose_robot_fails_exits_like_the_robot(tmp_path):
    """`hil up` of a multi-robot rig runs one process per robot; a failing one is not hidden."""
    not_a_tty = tmp_path / "not_a_tty"
    not_a_tty.write_bytes(b"")
    robot, _ = real_roach(tmp_path, str(not_a_tty))
    rig = tmp_path / "two.yaml"
    rig.write_text(f"name: two\nrobots:\n  a:\n    config: {robot}\n  b:\n    config: {robot}\n"
                   + access_section(tmp_path))
    r = CliRunner().invoke(app, ["up", str(rig), "--steps", "1"])
    assert r.exit_code == 1, r.output


def test_config_errors_are_one_line_exit_2(tmp_path):
    bad, rig = real_roach(tmp_path, "/dev/ttyUSB0")
    bad.write_text("robot: velociroach\nbackend: real\nparams:\n  prot: /dev/ttyUSB0\n")
    for verb, args in (("drive", [str(bad), "--action", "0,0"]), ("up", [str(rig), "--steps", "1"])):
        r = CliRunner().invoke(app, [verb, *args])
        assert r.exit_code == 2, r.output
        lines = [ln for ln in r.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and "params.prot" in lines[0] and str(bad) in lines[0], r.output
    r = CliRunner().invoke(app, ["drive", "pointmass", "--backend", "warp", "--action", "0,0"])
    assert r.exit_code == 2 and "--backend 'warp'" in r.output


def test_optional_packages_missing_say_which_extra(monkeypatch):
    """pytorch-mppi and natnet are extras: without them the error names the extra to install."""
    import sys

    import pytest

    from hilstack.drivers.mocap.natnet_client import NatNetPoseSource
    from hilstack.tools import bench_plan

    monkeypatch.setitem(sys.modules, "natnet", None)  # import natnet -> ImportError
    monkeypatch.setitem(sys.modules, "pytorch_mppi", None)
    with pytest.raises(ModuleNotFoundError, match=r"hilstack\[mocap\]"):
        NatNetPoseSource().connect(timeout_s=0.1)
    with pytest.raises(ModuleNotFoundError, match=r"hilstack\[bench\]"):
        bench_plan._make_peer(None, None, next(iter(bench_plan.WORKLOADS.values())), None, None)


def test_required_dependencies_are_imported_somewhere():
    """Every required dependency is used by the code (optional ones live in extras)."""
    import re
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    deps = tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]
    names = [re.split(r"[<>=!~\[ ;]", d)[0].lower() for d in deps]
    import_name = {"eclipse-zenoh": "zenoh", "rerun-sdk": "rerun", "pyserial": "serial", "digi-xbee": "digi",
                   "python-can": "can", "pyyaml": "yaml", "scipy": "scipy", "pyarrow": "pyarrow",
                   "foxglove-sdk": "foxglove", "dynamixel-sdk": "dynamixel_sdk", "stable-baselines3": "stable_baselines3",
                   "sb3-contrib": "sb3_contrib"}
    src = "\n".join(p.read_text() for pkg in ("drivers", "sim_backends", "control", "learning", "calibration",
                                              "bus", "tools", "configs") for p in (root / pkg).rglob("*.py"))
    unused = [n for n in names
              if not re.search(rf"^\s*(import|from)\s+{re.escape(import_name.get(n, n))}\b", src, re.M)]
    # pyarrow: the Parquet engine behind pandas.read_parquet (data loaders); msgpack: python-can's
    # udp_multicast bus (the hand's emulated transport) needs it; gymnasium-robotics: only its
    # assets, located with importlib.util.find_spec (sim_backends/shadow_hand/model.py)
    assert set(unused) <= {"pyarrow", "msgpack", "gymnasium-robotics"}, unused
    assert "pytorch-mppi" not in names and "natnet" not in names


def test_a_link_error_keeps_its_diagnosis_indented_below_the_one_line():
    import typer

    from hilstack.drivers.base import LinkError
    from hilstack.tools.common import user_errors

    mini = typer.Typer()

    @mini.command()
    @user_errors
    def go() -> None:
        raise LinkError("no heartbeat from the robot within 10 s; emulator log:\nline one\nline two")

    r = CliRunner().invoke(mini, [])
    assert r.exit_code == 1
    assert r.output.splitlines() == ["link error: no heartbeat from the robot within 10 s; emulator log:",
                                     "  line one", "  line two"]


def test_every_rig_verb_takes_a_name_or_a_file_and_uses_its_bus_section(tmp_path, spawn, monkeypatch):
    """Issue 22 item 9: `hil estop configs/rigs/X.yaml` was a traceback and `hil estop NAME`
    ignored the rig's bus: section (a rig on its own endpoint: "no driver node alive")."""
    import re

    from hilstack.configs import schema
    from tests.helpers import ROOT, free_port, wait_for

    ep = f"tcp/127.0.0.1:{free_port()}"
    root = tmp_path / "configs"
    (root / "rigs").mkdir(parents=True)
    rig = root / "rigs" / "own_ep.yaml"  # a rig on its own endpoint, nothing on the command line says where
    rig.write_text(f"name: own_ep\nrobots:\n  pm:\n    config: {ROOT / 'configs/robots/pointmass.yaml'}\n"
                   f"bus:\n  endpoint: {ep}\n")
    up = spawn("up", str(rig))
    monkeypatch.setattr(schema, "CONFIG_ROOT", root)  # so that the name own_ep is a rig config here
    try:
        wait_for(lambda: "driver-pm" in CliRunner().invoke(app, ["nodes", "own_ep"]).output, 60, "the driver node")
        for form in (str(rig), "own_ep"):
            r = CliRunner().invoke(app, ["estop", form, "--timeout-s", "5"])
            assert r.exit_code == 0 and "ENGAGED e-stop on rig own_ep: acknowledged by driver-pm" in r.output, r.output
            r = CliRunner().invoke(app, ["estop", form, "--release", "--timeout-s", "5"])
            assert r.exit_code == 0 and "released e-stop on rig own_ep" in r.output, r.output
            r = CliRunner().invoke(app, ["nodes", form, "--json"])
            assert r.exit_code == 0 and any(x["node"] == "driver-pm" for x in json.loads(r.output)), r.output
        out = tmp_path / "s.mcap"
        r = CliRunner().invoke(app, ["record", "--rig", str(rig), "--seconds", "1.5", "--out", str(out)])
        assert r.exit_code == 0, r.output
        n = int(re.search(r"wrote (\d+) messages", r.output).group(1))
        assert n > 0  # it heard the rig on the rig's endpoint
        # replay onto the rig by its file: the live-driver check looks on the rig's endpoint
        r = CliRunner().invoke(app, ["replay", str(out), "--rig", str(rig), "--speed", "0"])
        assert r.exit_code == 2 and "rig 'own_ep' has live driver nodes (driver-pm)" in r.output, r.output
        r = CliRunner().invoke(app, ["replay", str(out), "--speed", "0"])  # the recorded rig: its config's bus
        assert r.exit_code == 2 and "rig 'own_ep' has live driver nodes (driver-pm)" in r.output, r.output
        r = CliRunner().invoke(app, ["foxglove", "--rig", "own_ep", "--seconds", "1", "--port", "0"])
        assert r.exit_code == 0 and int(re.search(r"forwarded (\d+)", r.output).group(1)) > 0, r.output
        # its 1 s counts once it is linked to the rig (Node join_wait_s: 1 s logged nothing once under load)
        r = CliRunner().invoke(app, ["viz", "--rig", str(rig), "--seconds", "1", "--save", str(tmp_path / "v.rrd")])
        assert r.exit_code == 0 and int(re.search(r"logged (\d+)", r.output).group(1)) > 0, r.output
    finally:
        assert up.stop(20) == 0
    # the one helper: name or file, --endpoint replaces the endpoint only, a bad path is one line
    from hilstack.tools.common import rig_bus

    name, bus, cfg = rig_bus(str(rig), "tcp/127.0.0.1:1")
    assert (name, bus.endpoint, cfg.name) == ("own_ep", "tcp/127.0.0.1:1", "own_ep")
    assert rig_bus("made_up_rig")[1:] == (schema.BusConfig(), None)
    r = CliRunner().invoke(app, ["estop", str(tmp_path / "nope.yaml")])
    assert r.exit_code == 2 and r.output.startswith("error: ") and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_endpoint_override_keeps_the_rigs_access_control(tmp_path):
    from hilstack.tools.common import rig_bus

    rig = tmp_path / "r.yaml"
    rig.write_text("name: r\nrobots:\n  pm:\n    config: pointmass\nbus:\n  access: {credentials: /x/creds}\n")
    _, bus, _ = rig_bus(str(rig), "tcp/127.0.0.1:9")
    assert bus.endpoint == "tcp/127.0.0.1:9" and bus.access is not None and bus.access.credentials == "/x/creds"


def test_shell_completion_names_verbs_rigs_robots_and_rig_files():
    """Issue 27 item 6: `hil --install-completion` (typer's); what bash asks of `hil` completes."""

    def complete(words: str) -> list[str]:
        env = {"_HIL_COMPLETE": "complete_bash", "COMP_WORDS": words, "COMP_CWORD": str(len(words.split()) - 1)}
        r = CliRunner().invoke(app, [], prog_name="hil", env=env)
        assert r.exit_code == 0, r.output
        return r.output.split()

    assert complete("hil mp") == ["mpc"]
    assert complete("hil up arm_wid") == ["arm_widowx_emulated", "arm_widowx_sim"]
    assert "roach_emulated_router" in complete("hil router roach_") and "velociroach" not in complete("hil up v")
    assert complete("hil drive velo") == ["velociroach"]  # a robot, not a rig
    assert complete("hil teleop ./configs/rigs/roach_s") == ["./configs/rigs/roach_sim.yaml"]
    assert complete("hil console no_such_rig") == []
    r = CliRunner().invoke(app, ["--show-completion", "bash"], prog_name="hil")
    assert r.exit_code == 0 and "_HIL_COMPLETE=complete_bash" in r.output and "complete " in r.output


def test_up_set_overrides_rig_values_checked_by_the_schema():
    """Issue 27 item 6: `hil up RIG --set key=value`, bounded like the file's own values."""
    from hilstack.configs.schema import rig_robot_config
    from hilstack.tools.common import rig_bus

    _, bus, cfg = rig_bus("pointmass_sim", sets=["watchdog_periods=5", "pm.params.mass_kg=2.5",
                                                 "bus.endpoint=tcp/127.0.0.1:17001"])
    assert cfg.watchdog_periods == 5 and bus.endpoint == "tcp/127.0.0.1:17001"
    assert rig_robot_config(cfg, "pm").params["mass_kg"] == 2.5  # what make_driver gets
    assert rig_bus("pointmass_sim")[2].watchdog_periods == 3  # the file is unchanged
    for bad, says in (("watchdog_periods=50", "watchdog_periods: Input should be less than or equal to 10"),
                      ("watchdog_periods=.nan", "finite"),
                      ("nosuch=1", "nosuch: unknown field"),
                      ("pm.params.bogus=3", "robots.pm.params.bogus: unknown field"),
                      ("watchdog_periods", "expected key=value"),
                      ("pm.config.x=1", "robots.pm.config is not a mapping")):
        r = CliRunner().invoke(app, ["up", "pointmass_sim", "--set", bad, "--steps", "1"])
        assert r.exit_code == 2 and says in r.output and len(r.output.strip().splitlines()) == 1, (bad, r.output)
