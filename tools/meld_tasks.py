"""MELD's image tasks on our simulated robots, built through the registry and the driver contract
(``hilstack.drivers.registry.make_driver``): the robot-specific wiring of ``hil demo meld``.

* ``widowx_port``: the WidowX reaches the port of the switch that the task-reset mechanism moves.
  Tasks are mechanism poses (rotation × rail offset over ±8° × ±1 cm, the thesis' 16° × 2 cm), set
  by writing the mechanism's driver, as on the real bench: 20 training tasks on a 5 × 4 grid and
  10 held-out poses drawn inside the range. Insertion itself is not simulated (the arm model does
  not collide, sim_backends/widowx/model.py), so this is a reach-to-port task, success within
  ``success_m`` (1 cm) of the port at the episode end. 3.3 Hz policy (6 driver periods of 50 ms).
* ``sawyer_reach``: the Sawyer reacher of the thesis (Fig. 7.8): the goal is a point in space,
  invisible in the images; 20 training and 10 held-out goals; success within 10 cm at the end;
  4 Hz policy (5 driver periods).

Both: 40 steps per episode, reward ``−(d² + log(d + 1e-5))`` on the end-effector distance ``d``
[m] computed by forward kinematics of the measured joint angles (and the mechanism's measured
pose), images from the sim backends' fixed + wrist cameras (``extras["image"]``, H × 2H RGB).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hilstack.drivers.registry import make_driver
from hilstack.learning.kinematics import ChainKinematics


def reach_reward(d_m: float) -> float:
    return -(d_m * d_m + math.log(d_m + 1e-5))


class _DriverTask:
    episode_steps = 40
    hold: int = 1
    success_m: float = 0.1

    def _setup_images(self, camera_px: int, cameras: bool) -> dict:
        """``cameras=False``: a constant black image (the benchmark's peer without rendering)."""
        self.cameras = cameras
        self._blank = np.zeros((camera_px, 2 * camera_px, 3), np.uint8)
        return {"cameras": cameras, "camera_px": camera_px}

    def _episode_start(self) -> None:
        self.arm.reset()
        if not self.arm.active:
            self.arm.activate()

    def _obs(self) -> tuple[np.ndarray, float, float]:
        o = self.arm.read()
        if not o.ok:
            raise RuntimeError(f"{self.arm.spec.name}: observation not ok ({o.flags})")
        d = float(np.linalg.norm(self.fk.position(o.state[self.q_idx]) - self.goal))
        img = o.extras["image"] if self.cameras else self._blank
        return img, reach_reward(d), d

    def reset(self) -> tuple[np.ndarray, float]:
        self._episode_start()
        img, r, _ = self._obs()
        return img, r

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, dict[str, Any]]:
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        cmd = self.arm.spec.action.low + (a + 1.0) * 0.5 * (self.arm.spec.action.high - self.arm.spec.action.low)
        for _ in range(self.hold):
            self.arm.write(cmd)
            self.arm.tick()
        img, r, d = self._obs()
        return img, r, {"success": d < self.success_m, "distance_m": d}

    def close(self) -> None:
        for drv in self._drivers():
            try:
                drv.stop()
                drv.cleanup()
            except Exception:  # noqa: BLE001 - closing a sim: best effort
                pass


class WidowXPortTask(_DriverTask):
    name = "widowx_port"
    task_param_names = ("rotation_rad", "offset_m")
    hold = 6              # 3.3 Hz policy on the 20 Hz driver (thesis: 3.3 Hz on the real WidowX)
    success_m = 0.01
    settle_periods = 30   # driver periods for the mechanism to reach a new pose

    def __init__(self, camera_px: int = 64, seed: int = 0, cameras: bool = True):
        self.arm = make_driver("widowx", backend="sim", sim=self._setup_images(camera_px, cameras))
        self.mech = make_driver("reset_mechanism", backend="sim")
        for drv in (self.arm, self.mech):
            drv.configure()
            drv.activate()
        lo, hi = self.mech.spec.action.low, self.mech.spec.action.high
        grid = [(r, o) for r in np.linspace(lo[0], hi[0], 5) for o in np.linspace(lo[1], hi[1], 4)]
        rng = np.random.default_rng([seed, 25])
        held_out = rng.uniform(lo, hi, size=(10, 2))
        self.task_params = np.concatenate([np.array(grid), held_out])  # (rotation rad, offset m)
        self.train_tasks, self.test_tasks = list(range(20)), list(range(20, 30))
        self.action_dim = self.arm.spec.action.dim
        names = list(self.arm.spec.state.names)
        from hilstack.drivers.widowx.config import JOINT_NAMES

        self.q_idx = [names.index(f"{j}_pos") for j in JOINT_NAMES]
        model = self.arm.world.model  # the bench's MuJoCo model: kinematics only
        self.fk = ChainKinematics(model, "ee", JOINT_NAMES)
        self.port_fk = ChainKinematics(model, "port", ("mech_rail", "mech_rotate"))
        self.goal = np.zeros(3)
        self.task = -1

    def _drivers(self):
        return (self.arm, self.mech)

    def set_task(self, task: int) -> None:
        """The mechanism moves the switch to the task's pose; the goal is the port at the pose
        the mechanism measures."""
        if task == self.task:
            return
        target = self.task_params[task]
        for _ in range(self.settle_periods):
            self.mech.write(target)
            self.mech.tick()
        rotate, offset = (float(v) for v in self.mech.read().state[:2])
        self.goal = self.port_fk.position(np.array([offset, rotate]))
        self.task = task


#: Sawyer goal region [m, world]: in front of the start hand position (0.0, 0.59, 0.18)
SAWYER_GOAL_LO = np.array([-0.25, 0.55, 0.08])
SAWYER_GOAL_HI = np.array([0.25, 0.85, 0.30])
SAWYER_START_M = np.array([0.0, 0.59, 0.18])
#: no goal within this distance of the start: holding still must never succeed (0.10 m success + margin)
SAWYER_GOAL_MIN_TRAVEL_M = 0.15


def sawyer_goals(seed: int, n: int = 30) -> np.ndarray:
    """``n`` goals uniform in the goal box, each at least ``SAWYER_GOAL_MIN_TRAVEL_M`` from the start
    hand position (in a box that held the start, doing nothing succeeded on 20 % of held-out goals)."""
    rng = np.random.default_rng([seed, 7])
    goals = []
    while len(goals) < n:
        g = rng.uniform(SAWYER_GOAL_LO, SAWYER_GOAL_HI)
        if np.linalg.norm(g - SAWYER_START_M) >= SAWYER_GOAL_MIN_TRAVEL_M:
            goals.append(g)
    return np.array(goals)


class SawyerReachTask(_DriverTask):
    name = "sawyer_reach"
    task_param_names = ("goal_x_m", "goal_y_m", "goal_z_m")
    hold = 5              # 4 Hz policy on the 20 Hz driver (thesis: 4 Hz)
    success_m = 0.10      # thesis: reacher within 10 cm

    def __init__(self, camera_px: int = 64, seed: int = 0, cameras: bool = True):
        self.arm = make_driver("sawyer", backend="sim", sim=self._setup_images(camera_px, cameras))
        self.arm.configure()
        self.arm.activate()
        self.task_params = sawyer_goals(seed)
        self.train_tasks, self.test_tasks = list(range(20)), list(range(20, 30))
        self.action_dim = self.arm.spec.action.dim
        names = list(self.arm.spec.state.names)
        from hilstack.drivers.sawyer.config import JOINTS
        from hilstack.sim_backends.sawyer.model import build_model

        self.q_idx = [names.index(f"{j}_pos") for j in JOINTS]
        self.fk = ChainKinematics(build_model(), "endEffector", JOINTS)
        self.goal = self.task_params[0]

    def _drivers(self):
        return (self.arm,)

    def set_task(self, task: int) -> None:
        self.goal = self.task_params[task]


TASKS = {"widowx_port": WidowXPortTask, "sawyer_reach": SawyerReachTask}
