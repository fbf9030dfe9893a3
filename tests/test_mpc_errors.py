"""`hil mpc` on a rig it cannot drive says why in one line and sends nothing: a robot whose
state has no planar pose (a path needs position and heading), and a robot that cannot reset
itself on a rig with no reset supervisor (before: a KeyError and a RuntimeError traceback)."""

from __future__ import annotations

import subprocess
import sys

from hilstack.learning.dynamics import EnsembleDynamics
from tests.helpers import ROOT


def _mpc(rig: str, model, bus, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hilstack.tools.cli", "mpc", rig, "--model", str(model),
                           "--endpoint", bus.endpoint, "--steps", "5", *extra],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_mpc_refuses_a_robot_without_a_planar_pose(tmp_path, bus, spawn):
    spawn("up", "pointmass_sim", "--endpoint", bus.endpoint)
    model = tmp_path / "m.pt"
    EnsembleDynamics(4, 2, hidden=(8,), state_names=["x", "y", "vx", "vy"]).save(model)
    r = _mpc("pointmass_sim", model, bus)
    assert r.returncode == 2, r.stderr
    err = r.stderr.strip()
    assert err.count("\n") == 0 and "planar path" in err and "pm" in err and "Traceback" not in err, err


def test_mpc_says_why_a_reset_failed_and_sends_nothing(tmp_path, bus, spawn):
    up = spawn("up", "roach_emulated", "--endpoint", bus.endpoint)
    from hilstack.drivers.velociroach.config import STATE_NAMES

    model = tmp_path / "m.pt"
    EnsembleDynamics(len(STATE_NAMES), 2, hidden=(8,), state_names=list(STATE_NAMES)).save(model)
    r = _mpc("roach_emulated", model, bus)
    assert r.returncode == 1, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("error: reset of roach unsupported: emulated backend cannot reset itself") and \
        "--no-reset" in last, r.stderr
    assert "Traceback" not in r.stderr
    assert up.p.poll() is None, "the rig stays up"
