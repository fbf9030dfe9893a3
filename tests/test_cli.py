"""The `hil` command: its verbs, and user errors as one line with exit code 2."""

from __future__ import annotations

from typer.testing import CliRunner

from tools.cli import app


def test_help_lists_the_verbs():
    r = CliRunner().invoke(app, ["--help"])
    assert r.exit_code == 0
    for verb in ("demo", "drive", "record", "replay", "inspect", "viz", "calibrate", "bench", "up", "estop",
                 "nodes", "mpc", "find-port"):
        assert f" {verb} " in r.output, verb
    r = CliRunner().invoke(app, ["bench", "--help"])
    assert all(w in r.output for w in ("bus", "plan", "sim"))


def test_user_errors_are_one_line_exit_2():
    r = CliRunner().invoke(app, ["up", "no_such_rig"])
    assert r.exit_code == 2 and "no such rig config" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, ["replay", "x.mcap", "--speed", "-1"])
    assert r.exit_code == 2
    r = CliRunner().invoke(app, ["viz"])
    assert r.exit_code == 2 and "--rig" in r.output


def _recording(path):
    from bus import keys
    from bus.recording import McapLog
    from bus.schemas import Command, EStop, RobotState

    with McapLog(path) as log:
        for i in range(3):
            log.write(keys.state("clirig", "pm"), RobotState(robot="pm", t_s=float(i), state=[0.0]), log_time_ns=i)
            log.write(keys.cmd("clirig", "pm"), Command(robot="pm", action=[1.0]), log_time_ns=i)
            log.write(keys.estop("clirig"), EStop(engaged=False), log_time_ns=i)
    return path


def test_replay_cli_says_what_it_left_out_and_refuses_a_live_rig(tmp_path, bus):
    from bus import keys
    from bus.node import Node

    path = _recording(tmp_path / "r.mcap")
    r = CliRunner().invoke(app, ["replay", str(path), "--speed", "0", "--endpoint", bus.endpoint])
    assert r.exit_code == 0, r.output
    assert "replayed 3 messages" in r.output
    assert "not replayed: 6 command messages" in r.output and "hil/clirig/estop" in r.output
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
        assert r.exit_code == 0 and "replayed 9 messages" in r.output
