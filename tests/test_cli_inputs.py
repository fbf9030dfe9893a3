"""Issue 22, item 16: inputs the review saw crash with a traceback are one line, exit 2."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from hilstack.tools.cli import app


@pytest.mark.parametrize("opt, why", [("--model", "not a dynamics checkpoint"),
                                      ("--adapt", "")])
def test_mpc_with_a_file_that_is_not_a_checkpoint(tmp_path, opt, why):
    f = tmp_path / "x.csv"
    f.write_text("t,x\n0,1\n")
    r = CliRunner().invoke(app, ["mpc", "pointmass_sim", opt, str(f)])
    assert r.exit_code == 2, (r.output, r.exception)
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
    assert str(f) in r.output and why in r.output and r.output.strip().count("\n") == 0, r.output


@pytest.mark.parametrize("args", [["up", "pointmass_sim", "--steps", "0"], ["up", "pointmass_sim", "--steps", "-5"],
                                  ["estop", "pointmass_sim", "--timeout-s", "inf"],
                                  ["estop", "pointmass_sim", "--timeout-s", "nan"]])
def test_bounded_numbers(args):
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2 and r.output.strip().count("\n") == 0, (args, r.output, r.exception)


def test_an_error_exit_is_bounded_even_with_a_node_left_open(bus):
    """A verb that fails with a Zenoh node still open (its callback threads are not daemons
    and keep an interpreter from exiting: that is how `hil record --out DIR` hung) still
    ends, with its exit code, within ERROR_EXIT_GRACE_S."""
    import subprocess
    import sys
    import time

    from tests.helpers import ROOT

    script = f"""
import sys, typer
from hilstack.bus.node import Node
from hilstack.configs.schema import BusConfig
from hilstack.tools import common
common.HARD_EXIT_AFTER_ERROR = True  # as in the `hil` program

@common.user_errors
def verb():
    Node("left-open", "exit_test", BusConfig(endpoint="{bus.endpoint}"), handle_signals=False)
    raise common.UserError("bad input")

try:
    verb()
except typer.Exit as e:
    sys.exit(e.exit_code)
"""
    t0 = time.monotonic()
    try:
        r = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("the process did not exit within 60 s after its error")
    print(f"exited {r.returncode} {time.monotonic() - t0:.2f} s after start (grace 5 s)")
    assert r.returncode == 2 and "error: bad input" in r.stderr, r.stderr


@pytest.mark.parametrize("every", ["nan", "-1", "inf"])
def test_mpc_refit_period_is_bounded(tmp_path, every):
    f = tmp_path / "model.pt"
    f.write_bytes(b"x")
    r = CliRunner().invoke(app, ["mpc", "pointmass_sim", "--model", str(f), "--refit-every", every])
    assert r.exit_code == 2 and "--refit-every" in r.output and r.output.strip().count("\n") == 0, (r.output, r.exception)
