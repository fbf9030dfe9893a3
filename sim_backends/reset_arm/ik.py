"""Inverse kinematics of the reset arm: damped least squares on MuJoCo's own Jacobian.

The model is the arm alone built by the same MjSpec code as the simulated arm
(sim_backends/reset_arm/model.py :func:`build_arm_kinematics`), so the IK and the sim
agree by construction; on a real arm it is the arm's kinematic description. Forward
kinematics and the tool-centre-point Jacobian are MuJoCo's (``mj_kinematics``,
``mj_jacSite``); the solver is the textbook damped least squares step
``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ e`` (Wampler 1986; Buss, "Introduction to inverse kinematics
with Jacobian transpose, pseudoinverse and damped least squares methods", 2004) on a
6-D error: position [m] and orientation (rotation vector [rad]), with joint limits by
clipping and a small pull towards a rest posture in the null space.

Targets: the tool centre point's position [m, world] and the gripper's approach axis
pointing down (world -z) with the jaws closing along ``jaw_dir`` (a horizontal unit
vector): the only grasp this station uses.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hilstack.drivers.reset_arm.config import JOINT_LIMITS_RAD

#: a folded posture reaching towards -x (the hand), elbow up, tool down that seeds the first solve [rad]
READY_Q_RAD = np.array([0.0, -0.5, 0.0, -1.7, 0.0, -0.9, 0.0])


def down_frame(jaw_dir: np.ndarray) -> np.ndarray:
    """Rotation (columns: tool x, y, z in the world) with z down and y along ``jaw_dir``."""
    y = np.array([jaw_dir[0], jaw_dir[1], 0.0], dtype=np.float64)
    y /= np.linalg.norm(y)
    z = np.array([0.0, 0.0, -1.0])
    return np.column_stack([np.cross(y, z), y, z])


class ArmIK:
    def __init__(self, base_pos_m, damping: float = 0.05, rest_gain: float = 0.02):
        from hilstack.sim_backends.reset_arm.model import ArmIndex, build_arm_kinematics

        self.model = build_arm_kinematics(base_pos_m)
        self.data = mujoco.MjData(self.model)
        self.ix = ArmIndex(self.model)
        self.damping = damping
        self.rest_gain = rest_gain
        self.lo = np.array([lo for lo, _ in JOINT_LIMITS_RAD])
        self.hi = np.array([hi for _, hi in JOINT_LIMITS_RAD])
        self._jp = np.zeros((3, self.model.nv))
        self._jr = np.zeros((3, self.model.nv))

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool centre point position [m, world] and rotation (3×3) at joint angles ``q``."""
        d = self.data
        d.qpos[self.ix.qpos] = q
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_comPos(self.model, d)  # cdof, for the Jacobian
        return d.site_xpos[self.ix.tcp].copy(), d.site_xmat[self.ix.tcp].reshape(3, 3).copy()

    def error(self, q: np.ndarray, pos_m: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(6,) position error [m] and orientation error (rotation vector [rad]) target − current."""
        p, r = self.fk(q)
        # rotation vector of rot·rᵀ (small-angle-safe via MuJoCo's quaternion difference)
        qt, qc, dq = np.zeros(4), np.zeros(4), np.zeros(3)
        mujoco.mju_mat2Quat(qt, rot.reshape(-1))
        mujoco.mju_mat2Quat(qc, r.reshape(-1))
        mujoco.mju_subQuat(dq, qt, qc)  # in the current frame
        return np.concatenate([np.asarray(pos_m) - p, r @ dq])

    def solve(self, q0: np.ndarray, pos_m: np.ndarray, rot: np.ndarray, iters: int = 60,
              tol_m: float = 1e-4) -> tuple[np.ndarray, float]:
        """Joint angles reaching (``pos_m``, ``rot``) from ``q0``; returns (q, position error [m])."""
        q = np.clip(np.asarray(q0, dtype=np.float64).copy(), self.lo, self.hi)
        lam2 = self.damping ** 2
        for _ in range(iters):
            e = self.error(q, pos_m, rot)
            if np.linalg.norm(e[:3]) < tol_m and np.linalg.norm(e[3:]) < 1e-3:
                break
            mujoco.mj_jacSite(self.model, self.data, self._jp, self._jr, self.ix.tcp)
            jac = np.vstack([self._jp[:, self.ix.dof], self._jr[:, self.ix.dof]])
            jjt = jac @ jac.T + lam2 * np.eye(6)
            dq = jac.T @ np.linalg.solve(jjt, e)
            # null-space pull towards the ready posture keeps the elbow up, away from limits
            null = np.eye(7) - np.linalg.pinv(jac) @ jac
            dq += null @ (self.rest_gain * (READY_Q_RAD - q))
            q = np.clip(q + dq, self.lo, self.hi)
        return q, float(np.linalg.norm(self.error(q, pos_m, rot)[:3]))
