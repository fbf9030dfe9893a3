"""A supervised rig in one process: the simulated VelociRoACH's driver node (lockstep),
the reset supervisor and a controller node, each with its own Zenoh session on a
private endpoint (real bus, real MuJoCo, real driver bridge)."""

from __future__ import annotations

import copy
import threading
from pathlib import Path

import pytest
import yaml

from hilstack.configs.schema import RigConfig, parse_model, rig_robot_config
from hilstack.control.controller_node import ControllerNode
from hilstack.control.reset.config import load_reset
from hilstack.control.reset.supervisor import ResetSupervisor
from hilstack.drivers.bridge import DriverNode
from hilstack.drivers.registry import make_driver

RIG_FILE = Path(__file__).with_name("rig_roach_reset.yaml")


def rig_config(**reset_overrides) -> RigConfig:
    data = yaml.safe_load(RIG_FILE.read_text())
    data["reset"] = {**copy.deepcopy(data["reset"]), **reset_overrides}
    return parse_model(RigConfig, data, RIG_FILE)


class SupervisedRig:
    def __init__(self, bus, rig: RigConfig, serve: bool = False):
        """``serve``: run the supervisor's own ``serve()`` loop (it re-raises what crashes it)
        instead of the test's spin loop."""
        self.rig = rig
        self.driver = DriverNode(make_driver(rig_robot_config(rig, "roach")), rig.name, "roach", bus,
                                 pace="lockstep", handle_signals=False, estop_sync_s=0.3)
        self._dt = threading.Thread(target=self.driver.serve, daemon=True, name="driver")
        self._dt.start()
        self.sup = ResetSupervisor(rig.name, load_reset(rig), bus, handle_signals=False)
        self.sup.wait_ready(20)
        self.crash: list[BaseException] = []
        self._st = threading.Thread(target=self._serve if serve else self._spin, daemon=True, name="supervisor")
        self._st.start()
        self.ctl = ControllerNode(rig.name, "roach", bus, handle_signals=False, state_timeout_s=10, supervised=True)
        self.ctl.wait_ready(20)

    def _serve(self):
        try:
            self.sup.serve()
        except Exception as e:  # the test inspects it
            self.crash.append(e)

    def _spin(self):
        while not self.sup.stop_event.is_set():
            self.sup.spin_once()

    def dests(self) -> list[str]:
        return [t.dest for t in list(self.sup.history)]

    def stop_driver(self):
        self.driver.stop_event.set()
        self._dt.join(10)
        self.driver.close()

    def close(self):
        self.ctl.close()
        self.sup.stop_event.set()
        self._st.join(10)
        self.sup.close()
        if not self.driver._closed:
            self.stop_driver()


@pytest.fixture
def supervised_rig(bus):
    rigs: list[SupervisedRig] = []

    def start(**reset_overrides) -> SupervisedRig:
        r = SupervisedRig(bus, rig_config(**reset_overrides))
        rigs.append(r)
        return r

    yield start
    for r in rigs:
        r.close()
