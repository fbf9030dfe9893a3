"""Forward kinematics of a MuJoCo model's joint chain, batched in torch.

The reaching task needs the end-effector position of thousands of predicted joint
states per MPC step (samples × ensemble × horizon); MuJoCo's ``mj_kinematics`` works on
one ``MjData`` at a time. :class:`ChainKinematics` reads the kinematic tree once from
an ``MjModel`` (body offsets and orientations, joint axes, anchors and reference
positions) and evaluates the same transforms as ``mj_kinematics`` for a site on a
serial chain of hinge and slide joints, for any batch shape, differentiably (the IK
baseline takes its Jacobian with ``torch.func``). Tests check it against MuJoCo.

Frames: positions in the model's world frame [m]; joint values in the model's units
([rad] for hinges, [m] for slides), measured like ``qpos`` (MuJoCo rotates by
``qpos − qpos0``).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np
import torch


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, dtype=np.float64))
    return m.reshape(3, 3)


def _axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] about a unit ``axis`` [3] by ``angle`` [...] (Rodrigues)."""
    x, y, z = axis
    k = torch.stack([torch.stack([0 * x, -z, y]), torch.stack([z, 0 * x, -x]), torch.stack([-y, x, 0 * x])])
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=axis.dtype) + s * k + (1 - c) * (k @ k)


class ChainKinematics:
    """Position of ``site`` [m, world frame] as a function of ``joints`` (their order is
    the order of the input's last axis). Joints of the chain that are not listed stay at
    their reference position ``qpos0``; joints elsewhere in the model do not matter."""

    def __init__(self, model: mujoco.MjModel, site: str, joints: Sequence[str], dtype: torch.dtype = torch.float32):
        self.joints = tuple(joints)
        self.site = site
        self.dtype = dtype
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        if sid < 0:
            raise ValueError(f"model has no site {site!r}")
        chain = []
        b = int(model.site_bodyid[sid])
        while b > 0:
            chain.append(b)
            b = int(model.body_parentid[b])
        chain.reverse()
        col = {n: i for i, n in enumerate(self.joints)}
        seen = set()
        #: per body: (pos [3], rot [3,3], [(type, column or None, anchor, axis, qpos0)])
        self._bodies = []
        for b in chain:
            if model.body_mocapid[b] >= 0:
                raise ValueError(f"site {site!r} hangs on a mocap body: no joint chain")
            js = []
            for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
                name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
                jt = int(model.jnt_type[j])
                if jt not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
                    raise ValueError(f"joint {name!r} on the chain to {site!r} is not a hinge or slide")
                seen.add(name)
                js.append((jt, col.get(name), torch.tensor(model.jnt_pos[j], dtype=dtype),
                           torch.tensor(model.jnt_axis[j], dtype=dtype), float(model.qpos0[model.jnt_qposadr[j]])))
            self._bodies.append((torch.tensor(model.body_pos[b], dtype=dtype),
                                 torch.tensor(_quat_to_mat(model.body_quat[b]), dtype=dtype), js))
        missing = [n for n in self.joints if n not in seen]
        if missing:
            raise ValueError(f"joints {missing} are not on the chain from the world to site {site!r}")
        self._site_pos = torch.tensor(model.site_pos[sid], dtype=dtype)

    def __call__(self, q: torch.Tensor) -> torch.Tensor:
        """``q`` [..., n joints] → site position [..., 3]."""
        q = torch.as_tensor(q, dtype=self.dtype)
        batch = q.shape[:-1]
        pos = torch.zeros(*batch, 3, dtype=self.dtype)
        rot = torch.eye(3, dtype=self.dtype).expand(*batch, 3, 3)
        for bpos, brot, js in self._bodies:
            pos = pos + (rot @ bpos[:, None])[..., 0]
            rot = rot @ brot
            for jt, c, anchor, axis, q0 in js:
                if c is None:
                    continue  # held at qpos0: no motion
                v = q[..., c] - q0
                if jt == mujoco.mjtJoint.mjJNT_SLIDE:
                    pos = pos + (rot @ axis[:, None])[..., 0] * v[..., None]
                else:  # hinge about the axis through the anchor: p' = p + R a − R R_j a
                    rj = _axis_angle(axis, v)
                    a = (rot @ anchor[:, None])[..., 0]
                    rot = rot @ rj
                    pos = pos + a - (rot @ anchor[:, None])[..., 0]
        return pos + (rot @ self._site_pos[:, None])[..., 0]

    def position(self, q: np.ndarray) -> np.ndarray:
        """Numpy convenience: ``q`` [..., n] → [..., 3] (float64)."""
        with torch.no_grad():
            return self(torch.as_tensor(np.asarray(q), dtype=self.dtype)).double().numpy()

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """d site position / d q at one configuration ``q`` [n] → [3, n]."""
        qt = torch.as_tensor(np.asarray(q, dtype=np.float64), dtype=self.dtype)
        return torch.func.jacrev(self)(qt).double().numpy()
