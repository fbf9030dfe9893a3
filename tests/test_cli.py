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
