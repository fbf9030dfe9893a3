"""MELD's image tasks on our simulated robots, built through the registry and the driver contract
(``hilstack.drivers.registry.make_driver``): the robot-specific wiring of ``hil demo meld``.

* ``widowx_port``: the WidowX brings the cable's plug (held at the gripper's ``ee`` site, pointing
  along the gripper's axis) to the port of the switch that the task-reset mechanism moves, lined
  up with the port's axis: the pose an insertion starts from. Tasks are mechanism poses (rotation
  × rail offset over ±8° × ±1 cm, the thesis' 16° × 2 cm), set by writing the mechanism's driver,
  as on the real bench: 20 training tasks on a 5 × 4 grid and 10 held-out poses drawn inside the
  range. The rotation turns the port's axis, so the end-effector goals differ by up to 16° in
  heading and ~2 cm in place (the port itself sits 3 cm from the turntable's axis and moves
  little). Insertion itself is not simulated (the arm model does not collide,
  sim_backends/widowx/model.py); success is the insertion tolerance's stand-in: the plug within
  ``success_m`` (5 mm) of the port and its axis within ``success_deg`` (3°) of the port's at the
  episode end. 3.3 Hz policy (6 driver periods of 50 ms).
* ``sawyer_reach``: the Sawyer reacher of the thesis (Fig. 7.8): the goal is a point in space,
  invisible in the images; 20 training and 10 held-out goals; success within 10 cm at the end;
  4 Hz policy (5 driver periods).

Both: 40 steps per episode, reward ``−(d² + log(d + 1e-5))`` on the end-effector distance ``d``
[m] computed by forward kinematics of the measured joint angles (WidowX: plus ``ALIGN_LEVER_M`` ×
the angle [rad] between the plug's and the port's axes, the port from the mechanism's measured
pose), images from the sim backends' fixed + wrist cameras (``extras["image"]``, H × 2H RGB).
"""

from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np

from hilstack.drivers.registry import make_driver
from hilstack.learning.kinematics import ChainKinematics


def reach_reward(d_m: float) -> float:
    return -(d_m * d_m + math.log(d_m + 1e-5))


class _DriverTask:
    episode_steps = 40
    hold: int = 1
    success_m: float = 0.1
    #: the angle criterion of a task scored by position and axis (None: position only)
    success_deg: float | None = None

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
        self.q = np.asarray(o.state[self.q_idx], dtype=np.float64)
        self._score = self.score(self.q)
        img = o.extras["image"] if self.cameras else self._blank
        return img, reach_reward(self._score["distance_m"]), self._score["distance_m"]

    def score(self, q: np.ndarray) -> dict[str, Any]:
        """``{distance_m, success, ...}`` of joint angles ``q`` on the current task."""
        d = float(np.linalg.norm(self.fk.position(q) - self.goal))
        return {"distance_m": d, "success": d < self.success_m}

    def state(self) -> np.ndarray:
        """The measured joint angles [rad] of the last observation (the diagnostics' oracle state)."""
        return self.q

    def goal_features(self) -> np.ndarray:
        """What tells the task apart, as a vector (the diagnostics' oracle task)."""
        return np.asarray(self.goal, dtype=np.float64)

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
        img, r, _ = self._obs()
        return img, r, dict(self._score)

    def close(self) -> None:
        for drv in self._drivers():
            try:
                drv.stop()
                drv.cleanup()
            except Exception:  # noqa: BLE001 - closing a sim: best effort
                pass


#: the WidowX's distance adds this lever [m] × the plug-to-port axis angle [rad] (3° ≈ 5 mm)
ALIGN_LEVER_M = 0.1


class WidowXPortTask(_DriverTask):
    name = "widowx_port"
    task_param_names = ("rotation_rad", "offset_m")
    hold = 6              # 3.3 Hz policy on the 20 Hz driver (thesis: 3.3 Hz on the real WidowX)
    success_m = 0.005     # plug within 5 mm of the port ...
    success_deg = 3.0     # ... and its axis within 3° of the port's (our stand-in for insertion)
    settle_periods = 30   # driver periods for the mechanism to reach a new pose

    def __init__(self, camera_px: int = 64, seed: int = 0, cameras: bool = True):
        self.arm = make_driver("widowx", backend="sim", sim=self._setup_images(camera_px, cameras))
        self.mech = make_driver("reset_mechanism", backend="sim")
        for drv in (self.arm, self.mech):
            drv.configure()
            drv.activate()
        self.task_params = widowx_task_params(self.mech.spec.action.low, self.mech.spec.action.high, seed)
        self.train_tasks, self.test_tasks = list(range(20)), list(range(20, 30))
        self.action_dim = self.arm.spec.action.dim
        names = list(self.arm.spec.state.names)
        from hilstack.drivers.widowx.config import JOINT_NAMES

        self.q_idx = [names.index(f"{j}_pos") for j in JOINT_NAMES]
        self.kin = PortKinematics(self.arm.world.model, JOINT_NAMES)  # the bench's MuJoCo model: kinematics only
        self.fk = self.kin  # position() of the plug, as the other task's chain
        self.goal = np.zeros(3)
        self.goal_axis = np.array([1.0, 0.0, 0.0])
        self.task = -1

    def _drivers(self):
        return (self.arm, self.mech)

    def set_task(self, task: int) -> None:
        """The mechanism moves the switch to the task's pose; the goal is the port (and its axis)
        at the pose the mechanism measures."""
        if task == self.task:
            return
        target = self.task_params[task]
        for _ in range(self.settle_periods):
            self.mech.write(target)
            self.mech.tick()
        rotate, offset = (float(v) for v in self.mech.read().state[:2])
        self.goal, self.goal_axis = self.kin.port(rotate, offset)
        self.task = task

    def score(self, q: np.ndarray) -> dict[str, Any]:
        return port_score(self.kin, q, self.goal, self.goal_axis, self.success_m, self.success_deg)

    def goal_features(self) -> np.ndarray:
        return np.concatenate([self.goal, self.goal_axis])


def widowx_task_params(lo: np.ndarray, hi: np.ndarray, seed: int) -> np.ndarray:
    """[30, 2] mechanism poses (rotation rad, rail offset m): a 5 × 4 grid over the mechanism's
    range (the 20 training tasks), then 10 held-out poses drawn uniformly inside it."""
    grid = [(r, o) for r in np.linspace(lo[0], hi[0], 5) for o in np.linspace(lo[1], hi[1], 4)]
    held_out = np.random.default_rng([seed, 25]).uniform(lo, hi, size=(10, 2))
    return np.concatenate([np.array(grid), held_out])


class PortKinematics:
    """Forward kinematics of the bench's MuJoCo model (``mj_kinematics`` on a private ``MjData``):
    the plug (site ``ee``; its axis is the gripper's x axis) from the arm's joint angles, and the
    port (site ``port``; its axis, into the switch, is the housing's x axis) from the mechanism's."""

    def __init__(self, model: mujoco.MjModel, joints):
        self.model, self.data = model, mujoco.MjData(model)
        adr = lambda n: int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)])  # noqa: E731
        self.q_adr = [adr(j) for j in joints]
        self.rail_adr, self.rot_adr = adr("mech_rail"), adr("mech_rotate")
        self.ee = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "ee")
        self.port_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "port")

    def _site(self, sid: int) -> tuple[np.ndarray, np.ndarray]:
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[sid].copy(), self.data.site_xmat[sid].reshape(3, 3)[:, 0].copy()

    def plug(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(position [m], unit axis) of the plug at joint angles ``q``."""
        self.data.qpos[self.q_adr] = q
        return self._site(self.ee)

    def position(self, q: np.ndarray) -> np.ndarray:
        return self.plug(q)[0]

    def port(self, rotation_rad: float, offset_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(position [m], unit insertion axis) of the port at a mechanism pose."""
        self.data.qpos[self.rot_adr], self.data.qpos[self.rail_adr] = rotation_rad, offset_m
        return self._site(self.port_id)


def port_score(kin: PortKinematics, q: np.ndarray, goal: np.ndarray, goal_axis: np.ndarray, success_m: float,
               success_deg: float) -> dict[str, Any]:
    p, u = kin.plug(q)
    pos = float(np.linalg.norm(p - goal))
    ang = float(np.arccos(np.clip(u @ goal_axis, -1.0, 1.0)))
    return {"distance_m": pos + ALIGN_LEVER_M * ang, "position_m": pos, "angle_deg": math.degrees(ang),
            "success": pos < success_m and math.degrees(ang) < success_deg}


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


def goal_spread(env: Any) -> dict[str, Any]:
    """How much the tasks differ at the end effector: the goals' distance from their mean [m]
    (WidowX: and the port axis' angle from the mean axis [deg]), and the held-out success of the
    best task-blind pose (the mean goal, reached exactly): what a policy that ignores the task
    would score."""
    if isinstance(env, WidowXPortTask):
        poses = [env.kin.port(float(r), float(o)) for r, o in env.task_params]
        pos, ax = np.stack([p for p, _ in poses]), np.stack([a for _, a in poses])
        m_ax = ax.mean(0) / np.linalg.norm(ax.mean(0))
        ang = np.degrees(np.arccos(np.clip(ax @ m_ax, -1.0, 1.0)))
        m_pos = pos.mean(0)
        d = np.linalg.norm(pos - m_pos, axis=1)
        blind = [(d[t] < env.success_m) and (ang[t] < env.success_deg) for t in env.test_tasks]
        return {"mean_m": float(d.mean()), "max_m": float(d.max()), "angle_mean_deg": float(ang.mean()),
                "angle_max_deg": float(ang.max()), "task_blind_success": float(np.mean(blind))}
    g = np.asarray(env.task_params)
    d = np.linalg.norm(g - g.mean(0), axis=1)
    return {"mean_m": float(d.mean()), "max_m": float(d.max()),
            "task_blind_success": float(np.mean([d[t] < env.success_m for t in env.test_tasks]))}


def port_ik(env: WidowXPortTask, q0: np.ndarray | None = None) -> np.ndarray:
    """Joint angles [rad] that put the plug at the current task's port on its axis (least squares
    on the bench's kinematics, within the joints' limits): the reference for the task's
    reachability and for the scripted check that the arm can do it through the driver."""
    from scipy.optimize import least_squares

    names = list(env.arm.spec.state.names)
    lo = np.array([env.arm.spec.state.low[names.index(n)] for n in names if n.endswith("_pos")])
    hi = np.array([env.arm.spec.state.high[names.index(n)] for n in names if n.endswith("_pos")])

    def res(q: np.ndarray) -> np.ndarray:
        p, u = env.kin.plug(q)
        return np.concatenate([p - env.goal, ALIGN_LEVER_M * (u - env.goal_axis)])

    q0 = np.zeros(len(lo)) if q0 is None else q0
    return least_squares(res, np.clip(q0, lo + 1e-3, hi - 1e-3), bounds=(lo, hi)).x


class BenchView:
    """The WidowX bench seen at measured joint and mechanism poses: the fixed | wrist image the
    sim backend's cameras give, and the port task's reward, for :class:`MeldRigController` on the
    emulated rig (its emulator process has no camera stream; a real rig's camera node publishes
    the images). The goal comes from the mechanism's measured pose, as in :class:`WidowXPortTask`."""

    success_m, success_deg = WidowXPortTask.success_m, WidowXPortTask.success_deg

    def __init__(self, camera_px: int = 32):
        from hilstack.drivers.registry import skill, spec_of
        from hilstack.sim_backends.widowx.cameras import BenchCameras

        self.model = skill("widowx", "kinematics").kinematics_model()
        joints = tuple(spec_of("widowx").joint_names())
        self.kin = PortKinematics(self.model, joints)
        self.cameras = BenchCameras(self.model, camera_px)

    def __call__(self, q: np.ndarray, mech_state: np.ndarray) -> tuple[np.ndarray, float, dict[str, Any]]:
        rotate, offset = float(mech_state[0]), float(mech_state[1])
        goal, axis = self.kin.port(rotate, offset)
        sc = port_score(self.kin, q, goal, axis, self.success_m, self.success_deg)  # leaves q and the pose set
        mujoco.mj_forward(self.model, self.kin.data)
        return self.cameras.render(self.kin.data), reach_reward(sc["distance_m"]), sc

    def close(self) -> None:
        self.cameras.close()
