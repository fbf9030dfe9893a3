"""The vendor side of the Sawyer: what Rethink's joint controller does with intera
``JointCommand`` messages, on the MuJoCo model. Shared by the sim backend and the emulator.

Pure computation, no I/O; the caller passes ``now_s``.
* velocity mode: each joint tracks its velocity (clamped to its limit);
* position mode: a proportional velocity towards the target (hold);
* command timeout (intera's default 0.2 s): without a fresh command the arm holds the
  position it had when commands stopped, as the real controller does.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hilstack.sim_backends.sawyer.model import JOINTS, VELOCITY_LIMITS_RAD_S, build_model

POSITION_MODE, VELOCITY_MODE = 1, 2
COMMAND_TIMEOUT_S = 0.2
HOLD_GAIN_PER_S = 5.0
#: start pose [rad]: the hand ~20 cm above metaworld's table, over its workspace
#: (metaworld's own hand start is (0, 0.6, 0.2) m)
NEUTRAL_RAD = (1.3, -1.4, 0.0, 2.13, 0.0, 0.4, 0.0)


class SawyerArm:
    def __init__(self):
        self.model = build_model()
        self.data = mujoco.MjData(self.model)
        self._qadr = [self.model.joint(j).qposadr[0] for j in JOINTS]
        self._dadr = [self.model.joint(j).dofadr[0] for j in JOINTS]
        self._act = [self.model.actuator(f"{j}_vel").id for j in JOINTS]
        self.vel_limit = np.array(VELOCITY_LIMITS_RAD_S)
        self.lo = self.model.jnt_range[[self.model.joint(j).id for j in JOINTS], 0]
        self.hi = self.model.jnt_range[[self.model.joint(j).id for j in JOINTS], 1]
        self.reset()

    def reset(self) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qadr] = NEUTRAL_RAD
        mujoco.mj_forward(self.model, self.data)
        self.mode = POSITION_MODE
        self.target = np.array(NEUTRAL_RAD)
        self.last_cmd_s: float | None = None
        self.timeouts = 0
        self.rejected = 0

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    def q(self) -> np.ndarray:
        return self.data.qpos[self._qadr].copy()

    def qd(self) -> np.ndarray:
        return self.data.qvel[self._dadr].copy()

    def effort(self) -> np.ndarray:
        return self.data.actuator_force[self._act].copy()

    def ee_pos(self) -> np.ndarray:
        return self.data.site("endEffector").xpos.copy()

    def command(self, mode: int, names: list[str], values: np.ndarray, now_s: float) -> bool:
        """A JointCommand; False (and ignored) if it does not name the 7 joints with finite values."""
        if list(names) != list(JOINTS) or len(values) != 7 or not np.all(np.isfinite(values)) \
                or mode not in (POSITION_MODE, VELOCITY_MODE):
            self.rejected += 1
            return False
        self.mode = mode
        self.target = np.array(values, dtype=np.float64)
        self.last_cmd_s = now_s
        return True

    def step(self, now_s: float) -> None:
        if self.last_cmd_s is not None and now_s - self.last_cmd_s > COMMAND_TIMEOUT_S:
            self.mode, self.target, self.last_cmd_s = POSITION_MODE, self.q(), None
            self.timeouts += 1
        if self.mode == VELOCITY_MODE:
            v = self.target
        else:
            v = HOLD_GAIN_PER_S * (self.target - self.q())
        self.data.ctrl[self._act] = np.clip(v, -self.vel_limit, self.vel_limit)
        mujoco.mj_step(self.model, self.data)

    def advance(self, duration_s: float, now_s: float | None = None) -> None:
        n = int(round(duration_s / self.model.opt.timestep))
        for _ in range(n):
            self.step(self.time_s if now_s is None else now_s)
