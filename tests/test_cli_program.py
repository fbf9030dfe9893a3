"""The installed ``hil`` program is ``tools/cli.py: main``, not the bare typer app: a stuck
process prints its stacks on SIGUSR1, an error exit is bounded (``HARD_EXIT_AFTER_ERROR``), and
SIGINT stops a verb even when the process inherited it ignored (a background job of a
non-interactive shell). Runs the console script's target as pip's generated script does."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import importlib, signal, sys, time
signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job of a non-interactive shell inherits it
from hilstack.tools import cli, common

@cli.app.command("nap")
def nap() -> None:
    print("ready", common.HARD_EXIT_AFTER_ERROR, flush=True)
    time.sleep(60)

module, fn = sys.argv[1].split(":")
sys.argv = ["hil", "nap"]
sys.exit(getattr(importlib.import_module(module), fn)())
"""


def test_the_hil_program_dumps_stacks_exits_bounded_and_stops_on_sigint():
    target = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]["hil"]
    target = target.split("#")[0].strip()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, "-c", CHILD, target], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=env, cwd=ROOT)
    try:
        line = p.stdout.readline()
        assert line.split() == ["ready", "True"], (line, target)  # the bounded error exit is armed
        p.send_signal(signal.SIGUSR1)
        time.sleep(0.5)
        p.send_signal(signal.SIGINT)
        code = p.wait(timeout=20)
    finally:
        p.kill()
        err = p.stderr.read()
    assert "in nap" in err, err[-2000:]  # the stack dump names the verb's frame
    assert code in (1, 130), (code, err[-2000:])  # stopped by the SIGINT (click's abort), not the 60 s nap
