"""The reset arm's sim backend: the contract on the arm inside the simulated hand's scene.

The arm and the hand share one MuJoCo world (the balls the arm carries are the hand's),
so this backend does not own physics: it joins the scene of the hand sim backend named
``params.world`` in the same process (a hand configured with ``params.sim.reset_station:
true``) and follows its clock. ``tick()`` waits until the hand's scene has advanced one
arm period past the previous tick (the hand's driver node advances it, in lockstep or
on the wall clock); reads and writes take the scene's lock. One world, one clock: the
Baoding task's time steps are the hand's alone, whether the arm is busy or idle.

State and action: drivers/reset_arm/config.py. A command sets the joints' position
servo targets and the jaws' opening target; ``stop()`` holds the measured pose (the
gripper keeps its target, so a held ball is not dropped).
"""

from __future__ import annotations

import time
from typing import Any

import mujoco
import numpy as np

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import Follower, Health, LinkError, Observation
from hilstack.drivers.reset_arm.config import ResetArmParams, reset_arm_spec
from hilstack.sim_backends.base import LockstepSim
from hilstack.sim_backends.reset_arm.model import ArmIndex

#: how long ``tick()`` waits for the hand's scene to advance [s, wall clock] before it reads anyway
FOLLOW_TIMEOUT_S = 2.0


def arm_state(scene, ix: ArmIndex) -> tuple[float, np.ndarray]:
    """(t_s, state (21,)) of the arm in ``scene`` (a ShadowHandSim; caller holds its lock)."""
    d = scene.data
    s = np.concatenate([d.qpos[ix.qpos], d.qvel[ix.dof], [d.qpos[ix.finger_qpos].sum()], scene.balls_m().reshape(-1)])
    return float(d.time), s


def arm_command(scene, ix: ArmIndex, action: np.ndarray) -> None:
    """Servo targets from an action (7 joint angles [rad], opening [m]); caller holds the lock."""
    d = scene.data
    d.ctrl[ix.ctrl] = action[:7]
    d.ctrl[ix.finger_ctrl] = action[7] / 2  # each jaw moves half the opening


def arm_hold(scene, ix: ArmIndex) -> np.ndarray:
    """Hold the measured joints, the jaws keep their target; returns the held action."""
    d = scene.data
    d.ctrl[ix.ctrl] = d.qpos[ix.qpos]
    return np.concatenate([d.qpos[ix.qpos], [2 * d.ctrl[ix.finger_ctrl[0]]]])


class ResetArmSim(LockstepSim):
    params_type = ResetArmParams
    #: it works in the hand's world and follows its clock: ``hil up`` runs it in one process
    #: with the rig's sims; in lockstep its driver node waits 10 ms for a command, then holds
    #: and steps on with the world (drivers/base.py: ``Pacing.FOLLOWER``), so idle it still
    #: publishes every period and a drop detector watching its ball channels sees a drop without lag
    follower = Follower(command_wait_s=0.01)

    def __init__(self, params: ResetArmParams | None = None, source: str | None = None):
        super().__init__()
        self.params = params or ResetArmParams()
        self.source = source
        self.spec = reset_arm_spec(self.params)
        self.scene = None  # the ShadowHandSim whose world holds the arm
        self.idx: ArmIndex | None = None
        self._seq = 0
        self._t_ref_s = 0.0
        self.follow_timeouts = 0
        #: while ``tick()`` or ``tick_ready()`` waits: the scene time [s] it waits for (None otherwise)
        self.waiting_for_s: float | None = None
        #: when this period's wait for the scene gives up [s, monotonic]: set by its first wait,
        #: shared by ``tick_ready()``'s slices and ``tick()``, so the period waits FOLLOW_TIMEOUT_S in all
        self._follow_deadline: float | None = None

    @property
    def sim_time_s(self) -> float:
        return self.scene.sim_time_s if self.scene is not None else 0.0

    # ------------------------------------------------------------------ lifecycle
    def _on_configure(self) -> None:
        from hilstack.sim_backends.shadow_hand.backend import SCENES

        p = self.params
        deadline = time.monotonic() + p.world_wait_s
        while (scene := SCENES.get(p.world)) is None or scene.data is None:
            if time.monotonic() > deadline:
                raise LinkError(
                    f"reset arm: no simulated hand scene {p.world!r} with a reset station in this process after "
                    f"{p.world_wait_s:g} s; run the hand with backend sim and params.sim.reset_station: true "
                    "in the same rig (configs/rigs/hand_sim_arm.yaml)")
            time.sleep(0.02)
        base = scene.model.body("arm:base").pos
        if not np.allclose(base, p.base_pos_m, atol=1e-6):
            raise ConfigError(self.source, [("params.base_pos_m", f"{list(p.base_pos_m)} is not where the scene's "
                                             f"arm stands ({base.tolist()}): the IK would miss")])
        self.scene = scene
        self.idx = ArmIndex(scene.model)
        self._t_ref_s = scene.sim_time_s

    def _on_cleanup(self) -> None:
        self.scene = None

    def reset(self, **pose: Any) -> None:
        """Sim only: the arm back to its parked pose (q = 0, jaws open), at rest."""
        with self.scene.world_lock:
            d, ix = self.scene.data, self.idx
            d.qpos[ix.qpos] = 0.0
            d.qvel[ix.dof] = 0.0
            d.ctrl[ix.ctrl] = 0.0
            d.ctrl[ix.finger_ctrl] = 0.0
            mujoco.mj_forward(self.scene.model, d)

    # ------------------------------------------------------------------ clock
    def _wait_scene(self, timeout_s: float) -> bool:
        """Wait at most ``timeout_s`` (and never past this period's follow deadline) for the
        hand's scene to reach the next arm period; True when it has or the deadline passed.
        Caller holds no lock."""
        now = time.monotonic()
        if self._follow_deadline is None:
            self._follow_deadline = now + FOLLOW_TIMEOUT_S
        cond = self.scene.world_lock
        with cond:
            target = self._t_ref_s + self.spec.period_s
            if self.scene.sim_time_s < self._t_ref_s:
                target = self.scene.sim_time_s  # the scene was reset: its clock went back
            self.waiting_for_s = target
            ok = cond.wait_for(lambda: self.scene.data is None or self.scene.sim_time_s >= target - 1e-9,
                               timeout=max(0.0, min(timeout_s, self._follow_deadline - now)))
            self.waiting_for_s = None
        return ok or time.monotonic() >= self._follow_deadline

    def tick_ready(self, timeout_s: float) -> bool:
        """True when ``tick()`` returns at once: the hand's scene has advanced one arm period
        past the last tick, or this period's follow timeout ran out (waits at most ``timeout_s``)."""
        if self.scene is None:
            return True
        return self._wait_scene(timeout_s)

    def _advance(self, duration_s: float) -> None:
        """Wait for the hand's scene to reach the next period (it owns the clock), at most
        FOLLOW_TIMEOUT_S since this period's first wait (``tick_ready()``'s included)."""
        self._wait_scene(FOLLOW_TIMEOUT_S)
        with self.scene.world_lock:
            if self.scene.data is None:
                self.fail_link("reset arm: the hand's scene was closed")
            target = self._t_ref_s + duration_s
            if self.scene.sim_time_s < target - 1e-9 and self.scene.sim_time_s >= self._t_ref_s:
                self.follow_timeouts += 1
            self._t_ref_s = self.scene.sim_time_s
        self._follow_deadline = None

    # ------------------------------------------------------------------ contract
    def _read(self) -> Observation:
        scene, ix = self.scene, self.idx
        if scene is None or scene.data is None:
            self.fail_link("reset arm: the hand's scene is gone")
        with scene.world_lock:
            t, s = arm_state(scene, ix)
            tcp = scene.data.site_xpos[ix.tcp].copy()
        finite = bool(np.all(np.isfinite(s)))
        self._seq += 1
        return Observation(t_s=t, state=s, seq=self._seq, ok=finite, flags={"nonfinite_input": not finite},
                           extras={"tcp_m": tcp})

    def _hold_command(self, obs: Observation) -> np.ndarray:
        return np.clip(obs.state[list(range(7)) + [14]], self.spec.action.low, self.spec.action.high)

    def _write(self, action: np.ndarray) -> None:
        with self.scene.world_lock:
            arm_command(self.scene, self.idx, action)

    def _stop(self) -> np.ndarray | None:
        """Hold the measured joints; the jaws keep their target (a held ball stays held)."""
        if self.scene is None or self.scene.data is None:
            return None
        with self.scene.world_lock:
            return arm_hold(self.scene, self.idx)

    def _health(self) -> Health:
        return Health(ok=self.scene is not None and self.scene.data is not None,
                      extra={"backend": "sim", "world": self.params.world, "follow_timeouts": self.follow_timeouts})
