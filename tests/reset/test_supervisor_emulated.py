"""The one wall-clock test: the real radio driver over a pty to the firmware emulator
(`hil up roach_emulated`), reset by the supervisor driving it back.

Before the supervisor the same request was answered "unsupported: emulated backend
cannot reset itself" and `hil demo --rig roach_emulated` died after one rollout."""

from __future__ import annotations

import math
import threading

import numpy as np

from hilstack.configs.schema import load_rig
from hilstack.control.controller_node import ControllerNode
from hilstack.control.reset.config import require_reset
from hilstack.control.reset.supervisor import ResetSupervisor
from hilstack.learning.mbrl import MbrlConfig, MbrlRun, RigError
from tests.helpers import wait_rig_router


def test_the_emulated_roach_is_driven_back_and_a_new_episode_starts(rig_bus, spawn):
    bus = rig_bus("roach_emulated")  # its access control: the supervisor and controller log in as operator
    spawn("up", "roach_emulated", "--endpoint", bus.endpoint)
    wait_rig_router(bus)
    cfg = require_reset(load_rig("roach_emulated"), "roach")
    sup = ResetSupervisor("roach_emulated", cfg, bus, handle_signals=False)
    th = threading.Thread(target=sup.serve, daemon=True)
    th.start()
    try:
        with ControllerNode("roach_emulated", "roach", bus, handle_signals=False, state_timeout_s=20) as ctl:
            ctl.wait_ready(60)
            ctl.run_realtime(lambda x: np.array([0.6, 0.3]), 15)  # 1.5 s forward, veering
            s = ctl.next_state()
            assert math.hypot(s.state[0], s.state[1]) > 0.2  # it went somewhere
            first = ctl.reset(timeout_s=1.5 * cfg.max_duration_s() + 10, x=0.0, y=0.0, yaw=0.5)
            assert first.episode == 1
            assert math.hypot(first.state[0], first.state[1]) <= cfg.verify.position_tol_m
        assert [t.dest for t in sup.history] == ["episode_end", "paused", "resetting", "verifying", "resumed", "running"]
        assert sup.stats == {"requested": 1, "completed": 1, "failed": 0}
    finally:
        sup.stop_event.set()
        th.join(10)
        sup.close()


def test_a_rig_without_reset_procedure_or_operator_refuses_before_starting(bus, tmp_path):
    run = MbrlRun(MbrlConfig(rig="roach_real", progress=False), tmp_path, bus)
    try:
        run.run()
    except RigError as e:
        msg = str(e)
    else:  # pragma: no cover - the assertion below reports it
        msg = ""
    assert "add a 'reset:' section for roach" in msg and "--operator-resets" in msg and "\n" not in msg
    assert not (tmp_path / "logs" / "driver.log").exists()  # nothing was started
