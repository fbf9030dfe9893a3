"""A device emulator in its own process, as the emulated backends start it.

The emulator prints one JSON line on stdout when it is ready (where to connect: a pty
path, a UDP port...) and logs to stderr, which goes to a temporary file so that a
failure can quote its tail. It exits with us: its environment names us as its parent
(bus/lifetime.py, the one convention of every child process).

A failure is one line for the user (what happened, the log's last lines, where the whole
log is), and a log that explains a failure is kept when the process is stopped.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from hilstack.bus.lifetime import child_env
from hilstack.drivers.base import LinkError

REPO_ROOT = Path(__file__).resolve().parents[1]
#: how many of the log's last lines a failure message quotes
FAILURE_TAIL_LINES = 3


#: entry-point group of the device emulators (pyproject.toml: name = "module")
EMULATORS = "hilstack.emulators"


def emulator_module(name: str) -> str:
    """The module of the device emulator registered as ``name`` (run as ``python -m``)."""
    from hilstack.drivers.registry import entry_point_map

    mod = entry_point_map(EMULATORS).get(name)
    if mod is not None:
        return mod
    raise LinkError(f"no device emulator registered as {name!r} (entry points {EMULATORS!r}): "
                    "install hilstack (pip install -e .)")


class EmulatorProcess:
    """``python -m <module> <args>`` with us as its parent (bus/lifetime.py); ``start()``
    returns its ready line."""

    def __init__(self, module: str, args: list[str], *, start_timeout_s: float = 30.0, keep_log: bool = False):
        self.module = module
        self.args = list(args)
        self.start_timeout_s = start_timeout_s
        self.keep_log = keep_log
        self.proc: subprocess.Popen | None = None
        self.log_path: Path | None = None
        self._explains_failure = False  # keep the log: a failure message points at it

    def start(self) -> dict[str, Any]:
        fd, log_path = tempfile.mkstemp(prefix=self.module.rsplit(".", 2)[-2] + "-emulator-", suffix=".log")
        os.close(fd)
        self.log_path = Path(log_path)
        cmd = [sys.executable, "-m", self.module, *self.args]
        env = child_env()
        env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), *filter(None, [env.get("PYTHONPATH")])])
        with open(self.log_path, "wb") as errf:
            # its own session (process group): a Ctrl-C in the terminal reaches the driver,
            # which stops the robot and then the emulator (stop()); the emulator itself
            # must not die first. It still exits with us (bus/lifetime.py).
            self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=errf, stdin=subprocess.DEVNULL,
                                         cwd=str(REPO_ROOT), env=env, start_new_session=True)
        assert self.proc.stdout is not None
        deadline = time.monotonic() + self.start_timeout_s
        line = b""
        while not line.endswith(b"\n"):
            if self.proc.poll() is not None:
                raise LinkError(self.failure(f"emulator exited with code {self.proc.returncode} before it was ready"))
            left = deadline - time.monotonic()
            if left <= 0:
                raise LinkError(self.failure(f"emulator did not start within {self.start_timeout_s:g} s"))
            r, _, _ = select.select([self.proc.stdout], [], [], min(left, 0.1))
            if r:
                line += os.read(self.proc.stdout.fileno(), 1)
        return json.loads(line)

    def failure(self, what: str) -> str:
        """One line for the user: ``what``, the log's last lines, where the whole log is
        (kept by :meth:`stop`)."""
        self._explains_failure = True
        lines = [ln.strip() for ln in self.tail(FAILURE_TAIL_LINES).splitlines() if ln.strip()]
        return f"{what}: {' | '.join(lines)} (full log: {self.log_path})"

    def tail(self, n: int = 15) -> str:
        if self.log_path is None or not self.log_path.exists():
            return "(no emulator log)"
        lines = self.log_path.read_text(errors="replace").splitlines()
        return "\n".join(lines[-n:]) or "(emulator log empty)"

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        """Kill it without cleanup (tests: the device vanishes)."""
        if self.alive:
            self.proc.kill()

    def stop(self) -> None:
        """Terminate (then kill), close the pipe, remove the log unless ``keep_log`` or it
        explains a failure."""
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.terminate()
                self.proc.send_signal(signal.SIGCONT)  # a frozen (SIGSTOPped) emulator handles it now
                try:
                    self.proc.wait(timeout=3.0)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(timeout=3.0)
            if self.proc.stdout is not None:
                self.proc.stdout.close()
            self.proc = None
        if self.log_path is not None and not (self.keep_log or self._explains_failure):
            self.log_path.unlink(missing_ok=True)
            self.log_path = None
