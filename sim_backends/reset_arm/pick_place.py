"""The scripted pick-and-place of the hand's reset arm: balls from the ramp's pick-up spot
back into the palm. Pure computation on the arm's state (no bus, no I/O): the reset step
``arm_pick_place`` (control/reset/steps.py) feeds it the arm's states and sends its
commands; tests run it on the sim directly too.

One ball at a time: wait for a ball at the spot (it rolls there down the ramp), move
above it (joint-space move from wherever the arm is, then Cartesian), descend, close the
jaws, lift, check the grasp, carry it above its place in the palm, lower, open, rise.
When both balls are in the palm the arm goes back to its parked pose (q = 0, upright,
out of the balls' way) and the script is done.

Cartesian moves run the tool centre point along a straight line at ``speed_m_s`` with
IK (sim_backends/reset_arm/ik.py) every period, warm-started from the last command;
joint-space moves interpolate at ``joint_speed_rad_s``. A phase ends when the command has
reached its goal and the measured tool point (forward kinematics of the measured joints)
is within ``tolerance_m`` of it.

Positions are world-frame [m]; times are robot time [s] (the state's ``t_s``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hilstack.configs.schema import finite
from hilstack.drivers.reset_arm.config import GRIPPER_OPEN_M, ArmJointRateRadS
from hilstack.sim_backends.reset_arm.ik import READY_Q_RAD, ArmIK, down_frame

#: the tool point's Cartesian speed [m/s]
ToolSpeedMS = finite(gt=0, le=1.7, source="the Franka Panda's Cartesian translation limit (1.7 m/s), the layout "
                     "the reset arm copies")


class PickPlaceError(RuntimeError):
    """This attempt failed (one line saying what): a failed grasp, a ball that never came."""


@dataclass
class PickPlaceConfig:
    base_pos_m: tuple[float, float, float]
    #: a ball resting at the pick-up spot: its centre [m, world]
    spot_m: tuple[float, float, float]
    #: the palm's centre, where the Baoding task's balls start [m, world]
    palm_center_m: tuple[float, float, float]
    #: where the balls are put, from the centre [m, world]: where two balls come to rest in
    #: the cupped hand (the sim after a reset and 3 s of holding: (-0.003, 0.005, 0.002) and
    #: (0.036, 0.005, 0.008)); the task's own start (±0.022 m along x) is not a resting
    #: place, and a ball let go there rolled out of the palm
    place_offsets_m: tuple[tuple[float, float, float], ...] = ((0.0, 0.005, 0.0), (0.036, 0.005, 0.006))
    #: a ball counts as in the palm within this distance of the centre [m] (balls at rest
    #: in the cupped hand lie within 0.04 m of it: docs/reset.md)
    in_palm_radius_m: float = 0.06
    #: a ball counts as at the spot within this distance [m], and at rest (moves < 1 mm per period)
    spot_tol_m: float = 0.015
    #: how long to wait for a ball to reach the spot [s]
    spot_wait_s: float = 5.0
    #: height of the moves between spot and palm [m]: clear of the hand (top ~0.15 m) and
    #: low enough that the arm stays away from full stretch above the palm
    travel_z_m: float = 0.22
    #: the tool point's height above a palm place when the jaws open [m]
    release_above_m: float = 0.02
    speed_m_s: ToolSpeedMS = 0.25
    joint_speed_rad_s: ArmJointRateRadS = 1.2
    tolerance_m: float = 0.01
    grip_s: float = 0.5
    open_m: float = 0.07
    #: after lifting, the ball must be this close to the tool point [m] (else: grasp failed)
    grasp_tol_m: float = 0.03
    jaw_dir: tuple[float, float, float] = (0.0, 1.0, 0.0)
    #: the arm's control period [s]: one command per period
    period_s: float = 0.1
    park_q_rad: tuple[float, ...] = field(default_factory=lambda: (0.0,) * 7)


@dataclass
class _Phase:
    name: str
    kind: str  # "joint" | "cart" | "wait"
    goal: np.ndarray | None = None
    gripper_m: float = 0.0
    wait_s: float = 0.0
    tol_m: float | None = None


class PickPlaceScript:
    """``update(t_s, arm_state) -> action (8,) | None`` (None: done). Raises
    :class:`PickPlaceError`. Arm state layout: drivers/reset_arm/config.py."""

    def __init__(self, cfg: PickPlaceConfig, ik: ArmIK | None = None):
        self.cfg = cfg
        self.ik = ik or ArmIK(cfg.base_pos_m)
        self.rot = down_frame(np.asarray(cfg.jaw_dir))
        self.spot = np.asarray(cfg.spot_m, dtype=np.float64)
        self.center = np.asarray(cfg.palm_center_m, dtype=np.float64)
        self.places = self.center + np.asarray(cfg.place_offsets_m, dtype=np.float64)
        self.log: list[str] = []
        self._parked = False
        self._joint_goal_cache: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ state
    @staticmethod
    def balls(s: np.ndarray) -> np.ndarray:
        return np.asarray(s[15:21], dtype=np.float64).reshape(2, 3)

    def in_palm(self, balls: np.ndarray) -> list[bool]:
        """Per ball: within ``in_palm_radius_m`` of the palm centre."""
        return [bool(x) for x in np.linalg.norm(balls - self.center, axis=1) <= self.cfg.in_palm_radius_m]

    def start(self, t_s: float, s: np.ndarray) -> None:
        self._q_cmd = np.asarray(s[:7], dtype=np.float64).copy()
        self._grip = float(s[14])
        self._phases: list[_Phase] = []
        self._phase_t0 = t_s
        self._wait_since = t_s
        self._prev_balls = self.balls(s)
        self._ball: int | None = None
        self._p_cmd: np.ndarray | None = None
        self._parked = False

    # ------------------------------------------------------------------ planning
    def _plan_pick(self, ball: int, at: np.ndarray, place: np.ndarray) -> None:
        c = self.cfg
        up = np.array([0.0, 0.0, 1.0])
        above_spot = at.copy()
        above_spot[2] = c.travel_z_m
        above_place = place.copy()
        above_place[2] = c.travel_z_m
        self._ball = ball
        self._phases = [
            _Phase("approach", "joint", above_spot, c.open_m),
            _Phase("descend", "cart", at, c.open_m, tol_m=c.tolerance_m / 2),
            _Phase("close", "wait", None, 0.0, wait_s=c.grip_s),
            _Phase("lift", "cart", above_spot, 0.0),
            _Phase("check_grasp", "check"),
            _Phase("carry", "cart", above_place, 0.0),
            _Phase("lower", "cart", place + c.release_above_m * up, 0.0, tol_m=c.tolerance_m / 2),
            _Phase("release", "wait", None, c.open_m, wait_s=c.grip_s),
            _Phase("retreat", "cart", above_place, c.open_m),
        ]

    # ------------------------------------------------------------------ control
    def update(self, t_s: float, s: np.ndarray) -> np.ndarray | None:
        s = np.asarray(s, dtype=np.float64)
        if not np.all(np.isfinite(s)):
            raise PickPlaceError("arm_pick_place: the arm's state is not finite")
        balls = self.balls(s)
        if not self._phases:
            done = self._choose(t_s, s, balls)
            if done:
                return None
        self._prev_balls = balls
        if not self._phases:
            return self._action()  # waiting for a ball: hold
        ph = self._phases[0]
        q_meas = s[:7]
        if ph.kind == "check":
            tcp, _ = self.ik.fk(q_meas)
            gap = float(np.linalg.norm(balls[self._ball] - tcp))
            if gap > self.cfg.grasp_tol_m:
                raise PickPlaceError(f"arm_pick_place: grasp of ball{self._ball} failed (the ball is {gap:.3f} m "
                                     f"from the jaws after lifting)")
            self._next(t_s)
            return self._action()
        self._grip = ph.gripper_m
        if ph.kind == "wait":
            if t_s - self._phase_t0 >= ph.wait_s:
                self._next(t_s)
            return self._action()
        reached = self._move(ph)
        if ph.name == "park":
            there = float(np.abs(q_meas - ph.goal).max()) <= 0.05  # [rad]
        else:
            tcp, _ = self.ik.fk(q_meas)
            there = float(np.linalg.norm(tcp - ph.goal)) <= (ph.tol_m or self.cfg.tolerance_m)
        if reached and there:
            self._next(t_s)
        return self._action()

    def _choose(self, t_s: float, s: np.ndarray, balls: np.ndarray) -> bool:
        """Plan the next pick, or the park; True when all is done."""
        inp = self.in_palm(balls)
        if all(inp):
            if self._parked:
                return True
            self._phases = [_Phase("park", "joint", np.asarray(self.cfg.park_q_rad, dtype=np.float64), self.cfg.open_m)]
            return False
        c = self.cfg
        d_spot = np.linalg.norm(balls - self.spot, axis=1)
        moving = np.linalg.norm(balls - self._prev_balls, axis=1) > 1e-3
        cand = [i for i in range(2) if not inp[i] and d_spot[i] <= c.spot_tol_m and not moving[i]]
        if not cand:
            if t_s - self._wait_since > c.spot_wait_s:
                i = min((i for i in range(2) if not inp[i]), key=lambda i: d_spot[i])
                raise PickPlaceError(
                    f"arm_pick_place: ball{i} did not reach the pick-up spot within {c.spot_wait_s:g} s "
                    f"(it is {d_spot[i]:.2f} m away, at {np.round(balls[i], 3).tolist()})")
            return False
        i = cand[0]
        # the free place: the one farther from a ball already in the palm
        taken = [balls[j] for j in range(2) if inp[j]]
        if taken:
            k = int(np.argmax(np.linalg.norm(self.places - taken[0], axis=1)))
        else:
            k = 0
        self._plan_pick(i, balls[i].copy(), self.places[k].copy())
        self._phase_t0 = t_s
        self._p_cmd = None
        return False

    def _next(self, t_s: float) -> None:
        ph = self._phases.pop(0)
        self.log.append(ph.name)
        if ph.name == "park":
            self._parked = True
        self._phase_t0 = t_s
        self._wait_since = t_s
        self._p_cmd = None

    def _move(self, ph: _Phase) -> bool:
        """Advance the command one period toward the phase's goal; True once it is there."""
        dt = self.cfg.period_s
        if ph.kind == "joint":
            goal_q = ph.goal if ph.name == "park" else self._joint_goal(ph.goal)
            step = goal_q - self._q_cmd
            n = np.abs(step).max()
            lim = self.cfg.joint_speed_rad_s * dt
            self._q_cmd = goal_q.copy() if n <= lim else self._q_cmd + step * (lim / n)
            return bool(n <= lim)
        if self._p_cmd is None:
            self._p_cmd, _ = self.ik.fk(self._q_cmd)
        d = ph.goal - self._p_cmd
        n = float(np.linalg.norm(d))
        lim = self.cfg.speed_m_s * dt
        self._p_cmd = ph.goal.copy() if n <= lim else self._p_cmd + d * (lim / n)
        self._q_cmd, _ = self.ik.solve(self._q_cmd, self._p_cmd, self.rot, iters=30)
        return n <= lim

    def _joint_goal(self, pos: np.ndarray) -> np.ndarray:
        # solved once per goal (from the folded posture: a good branch, far from the limits)
        if self._joint_goal_cache is None or self._joint_goal_cache[0] is not pos:
            q, err = self.ik.solve(READY_Q_RAD, pos, self.rot, iters=200)
            if err > 0.005:
                raise PickPlaceError(f"arm_pick_place: no IK solution for {np.round(pos, 3).tolist()} "
                                     f"(off by {err:.3f} m)")
            self._joint_goal_cache = (pos, q)
        return self._joint_goal_cache[1]

    def _action(self) -> np.ndarray:
        return np.concatenate([self._q_cmd, [float(np.clip(self._grip, 0.0, GRIPPER_OPEN_M))]])
