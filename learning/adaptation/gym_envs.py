"""gymnasium's MuJoCo half-cheetah and ant, modified as the thesis' simulated benchmarks.

The modifications are those of the GrBAL/MOLe experiments (thesis ch. 5.6 and 6.5; the
public GrBAL environments, ``iclavera/learning_to_adapt``, were read for them):

* **disabled joint** (HC, ch. 5.6): one actuator's command is multiplied by 0 (the reference
  code's ``cripple_mask``). Meta-training disables a random joint of 1..5 per rollout; the
  test disables joint 0 (the back thigh), never seen in training.
* **motor malfunction** (HC, ch. 6.5): the commands of some actuators are negated (a
  sign-flipped motor): multiplier −1 on those joints.
* **crippled leg** (ant, ch. 5.6): both actuators of one leg multiplied by 0 (legs 0..2 in
  training, leg 3 at test, the reference code's numbering). The reference code also halves
  the leg's geoms; this module only disables the actuators (stated in docs/adaptation.md).

The condition is a per-actuator multiplier vector applied to the policy's action before the
simulator sees it, and it can change mid-rollout (:meth:`GymBenchmarkEnv.set_condition`):
a switch is a new multiplier at a given step. The reward is the reference code's: forward
velocity of the root minus ``ctrl_cost`` · Σ a² of the *applied* action (HC 0.05, ant 0 plus
0.05 for staying alive). Episodes have a fixed length (the ant's unhealthy-termination is off).

The state the models see is gymnasium's v5 observation (positions without the root x, then
velocities) followed by one channel more: the root's **mean forward velocity over the last
step**, (x_after − x_before)/dt, the displacement the reward pays for (gymnasium's own
``forward_reward``; the reference code puts the torso's centre of mass in its observation and
its planner's reward is the predicted change of it over dt). ``velocity_index`` is that
channel; the planners' cost reads it from the predicted states, so the model predicts the
rewarded quantity itself, not the instantaneous qvel[0], which swings within a gait cycle
(docs/adaptation.md, "The reference code's settings line by line"). At reset the channel holds qvel[0].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["EnvSpec", "ENVS", "GymBenchmarkEnv", "disabled_joint", "malfunction", "crippled_leg"]


@dataclass(frozen=True)
class EnvSpec:
    gym_id: str
    state_dim: int
    action_dim: int
    velocity_index: int
    ctrl_cost: float
    alive_bonus: float
    kwargs: tuple[tuple[str, object], ...] = ()


ENVS: dict[str, EnvSpec] = {
    # obs: qpos[1:] (8) then qvel (9), then the mean forward velocity over the last step (17)
    "half_cheetah": EnvSpec("HalfCheetah-v5", 18, 6, 17, 0.05, 0.0),
    # obs: qpos[2:] (13) then qvel (14), then the mean forward velocity (27). No termination, no contact forces.
    "ant": EnvSpec("Ant-v5", 28, 8, 27, 0.0, 0.05,
                   (("terminate_when_unhealthy", False), ("include_cfrc_ext_in_observation", False))),
}

#: the ant's actuators per leg (reference numbering: legs 0..2 train, 3 test)
ANT_LEGS = {0: (2, 3), 1: (4, 5), 2: (6, 7), 3: (0, 1)}


def disabled_joint(action_dim: int, joint: int | None) -> np.ndarray:
    """Multipliers with ``joint``'s command at 0 (None: all 1, the normal robot)."""
    m = np.ones(action_dim, dtype=np.float32)
    if joint is not None:
        if not 0 <= joint < action_dim:
            raise ValueError(f"joint must be in [0, {action_dim}), got {joint}")
        m[joint] = 0.0
    return m


def malfunction(action_dim: int, joints) -> np.ndarray:
    """Multipliers with the commands of ``joints`` negated."""
    m = np.ones(action_dim, dtype=np.float32)
    for j in joints:
        if not 0 <= j < action_dim:
            raise ValueError(f"joint must be in [0, {action_dim}), got {j}")
        m[j] = -1.0
    return m


def crippled_leg(leg: int | None) -> np.ndarray:
    """The ant's multipliers with both actuators of ``leg`` at 0 (None: all 1)."""
    m = np.ones(8, dtype=np.float32)
    if leg is not None:
        if leg not in ANT_LEGS:
            raise ValueError(f"leg must be one of {sorted(ANT_LEGS)}, got {leg}")
        m[list(ANT_LEGS[leg])] = 0.0
    return m


class GymBenchmarkEnv:
    """A gymnasium MuJoCo env whose actions pass through a condition's multipliers.

    ``reset(seed)`` seeds gymnasium's initial-state noise (the same seed gives every method
    the same start). ``step(a)`` returns ``(next_state, reward)``; ``a`` is clipped to
    [-1, 1] (both envs' action bounds).
    """

    def __init__(self, name: str, frame_skip: int | None = None):
        import gymnasium as gym

        if name not in ENVS:
            raise ValueError(f"unknown benchmark env {name!r}; known: {sorted(ENVS)}")
        if frame_skip is not None and not (isinstance(frame_skip, int) and 1 <= frame_skip <= 50):
            raise ValueError(f"frame_skip must be an int in [1, 50] (MuJoCo steps per action), got {frame_skip!r}")
        self.name, self.spec = name, ENVS[name]
        kw = dict(self.spec.kwargs)
        if frame_skip is not None:
            kw["frame_skip"] = frame_skip
        self.env = gym.make(self.spec.gym_id, **kw).unwrapped
        if self.env.observation_space.shape != (self.spec.state_dim - 1,):
            raise RuntimeError(f"{self.spec.gym_id} observation is {self.env.observation_space.shape}, "
                               f"this module expects ({self.spec.state_dim - 1},) plus its forward-velocity channel")
        self.condition = np.ones(self.spec.action_dim, dtype=np.float32)

    def set_condition(self, multipliers: np.ndarray) -> None:
        m = np.asarray(multipliers, dtype=np.float32).reshape(-1)
        if m.shape != (self.spec.action_dim,) or not np.all(np.isfinite(m)):
            raise ValueError(f"condition must be {self.spec.action_dim} finite multipliers, got {m.tolist()}")
        self.condition = m

    def reset(self, seed: int) -> np.ndarray:
        obs, _ = self.env.reset(seed=int(seed))
        return np.append(obs, self.env.data.qvel[0]).astype(np.float32)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float]:
        """``(next_state, reward)``: reward = (x_after − x_before)/dt − ctrl_cost·Σ a² (+ alive)."""
        a = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0) * self.condition
        x0 = float(self.env.data.qpos[0])
        obs, _, _, _, _ = self.env.step(a)
        v = (float(self.env.data.qpos[0]) - x0) / self.env.dt
        return (np.append(obs, v).astype(np.float32),
                v - self.spec.ctrl_cost * float(np.sum(a * a)) + self.spec.alive_bonus)

    def close(self) -> None:
        self.env.close()
