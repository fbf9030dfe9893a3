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
