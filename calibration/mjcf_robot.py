"""Calibrate a robot's own MuJoCo model (its MJCF) against a rig recording, and name the effect it lacks.

`hil calibrate --model configs/robots/widowx.yaml --data REC.mcap` (docs/calibration.md, "The
robots' own MuJoCo models"). The parameter fit is MuJoCo's own ``mujoco.sysid``
(``sysid.optimize``: box-constrained Gauss-Newton; ``sysid.calculate_intervals``: confidence
intervals from the Jacobian at the optimum; ``sysid.Parameter`` modifiers write each value into an
``MjSpec``), the rollouts are ``mujoco.rollout`` (threaded, many models in one call). hilstack's
part is choosing *which* effect is missing:

* Candidates are expressed in the MJCF: joint ``frictionloss``, ``damping``, ``armature``, the
  servo loop's gain, an input delay (one parameter per arm joint, the delay shared).
* Each candidate is fitted alone (then, stepwise, together with the effects already accepted,
  all refitted) on training time blocks; it is scored by the open-loop (multi-step) error on
  held-out time blocks, with a gap of one block between a held-out block and any training block,
  and selected by the same evidence rule as the axis model (:func:`selection.gain_evidence`:
  held-out gain ≥ 0.02 and a bootstrap interval above 0; "moderate" or better enters).
* A pruning pass drops an accepted effect whose removal (and refit of the rest) costs less than
  the minimum gain.

The robot's sim backend says how its joints are driven (``calibration_bench()``, found through
the driver registry): for the WidowX, each servo's velocity-mode PI loop, expressed in the
rollout model as an ``intvelocity`` actuator (the I part on the integrated goal, plus the P
part's damping) beside a ``motor`` carrying the P part's feed-forward, with the joint's
``actuatorfrcrange`` as the stall torque. The integrator's state at the start of a block is
recovered from the measured current (torque = kt·I = P part + I part).

The calibrated MJCF written is the backend's own bench model with the identified joint values
(and an input delay as ``<custom><numeric name="hilstack_input_delay_s">``, which the bench
applies to its servos); ``params.sim.mjcf`` in the robot config points the sim backend at it.
"""

from __future__ import annotations

import io
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from hilstack.calibration.data import DataError, Recording

#: the candidate effects, in the order ties are broken (simplest physics first)
CANDIDATES = ("joint_frictionloss", "joint_damping", "joint_armature", "input_delay", "servo_gain")
#: effects that may each look useless alone and only help together; tried jointly when no single one enters
PAIRS = (("joint_frictionloss", "input_delay"), ("joint_frictionloss", "joint_damping"))
#: the bench turns this numeric into its servos' goal delay (sim_backends/widowx/world.py DELAY_NUMERIC)
DELAY_NUMERIC = "hilstack_input_delay_s"
#: the first blocks start this far into each episode [s]
START_S = 1.0
#: a sample period longer than this many median periods is a stall no block spans
STALL_PERIODS = 2.0


class SysidNotAvailable(RuntimeError):
    """``mujoco.sysid`` needs the ``mujoco[sysid]`` extra (absl-py, ...)."""


def _sysid():
    try:
        from mujoco import sysid
        sysid.optimize  # noqa: B018 - the package imports empty without its extra
    except (ImportError, AttributeError):
        raise SysidNotAvailable("calibrating a robot's MJCF needs mujoco.sysid: install hilstack[calib] "
                                "(mujoco[sysid])") from None
    return sysid


ACTIONS = ("goal_velocity", "goal_position_normalized")


@runtime_checkable
class CalibrationBench(Protocol):
    """A sim backend class that says how its joints are driven, for calibrating its MJCF and
    recording an excitation (the WidowX's, the hand's): ``calibration_bench(params=None)``, a
    classmethod, returns the layout :meth:`Bench.from_layout` reads (and ``"excite"``, what
    :func:`hilstack.calibration.robot_rig.record_excitation` needs). A backend has it by having
    the method (sim backends sit below calibration, so they cannot name this protocol)."""

    def calibration_bench(self, params: Any = None) -> dict: ...


@dataclass
class Bench:
    """A robot's bench as calibration sees it (from its sim backend's ``calibration_bench()``).

    ``joints`` are fitted and scored; ``loop_joints`` (default: ``joints``) are every joint a
    firmware loop drives (the hand: all 20 actuated, the wrist fitted); ``loop_q``/``loop_qd``
    their state columns, ``current`` the columns of what each loop's motor reports (WidowX: current
    [A]; the hand: effort [N·m]), from which the loops' integrators start."""

    spec: object  # mujoco.MjSpec of the backend's model
    joints: list[str]
    loops: dict[str, dict]
    q: list[int]
    qd: list[int]
    current: list[int]
    #: the goal delay a calibrated MJCF carries (its DELAY_NUMERIC) [s]
    input_delay_s: float = 0.0
    action: str = "goal_velocity"
    loop_joints: list[str] = field(default_factory=list)
    loop_q: list[int] = field(default_factory=list)
    loop_qd: list[int] = field(default_factory=list)
    #: goal_position_normalized: the targets' range in rad ([-1, 1] maps onto [low, high])
    low: np.ndarray | None = None
    high: np.ndarray | None = None
    #: bodies the rollout model leaves out (the hand's balls, parked away from it while recording)
    drop_bodies: list[str] = field(default_factory=list)
    #: state columns of measured joint positions (then velocities) set at each block's start, by joint name
    state_joints: dict[str, tuple[int, int]] = field(default_factory=dict)
    #: the goal register's resolution (the WidowX: one Goal Velocity count, 0.024 rad/s): the servo
    #: runs the recorded goal rounded to it, as the driver writes it (0: goals are not quantised)
    goal_step: float = 0.0
    #: samples back from a block's first sample to the goal acting on its loops then (their
    #: integrators are started from it): 1 when a goal written after sample k acts from sample k on
    goal_lag: int = 2

    @classmethod
    def from_layout(cls, layout: dict) -> Bench:
        action = layout.get("action")
        if action not in ACTIONS:
            raise DataError(f"calibration bench: actions {action!r} are not supported ({', '.join(ACTIONS)})")
        spec = layout["spec"]
        delay = 0.0
        for n in [n for n in spec.numerics if n.name == layout.get("delay_numeric", DELAY_NUMERIC)]:
            delay = float(list(n.data)[0])
            spec.delete(n)  # the rollout model applies it to the recorded goals instead
        joints = list(layout["joints"])
        loop_joints = list(layout.get("loop_joints", joints))
        loop_q = list(layout.get("loop_q", layout["q"]))
        loop_qd = list(layout.get("loop_qd", layout["qd"]))
        state_joints = {j: (a, b) for j, a, b in zip(loop_joints, loop_q, loop_qd, strict=True)}
        state_joints.update({j: (a, b) for j, a, b in zip(joints, layout["q"], layout["qd"], strict=True)})
        state_joints.update(layout.get("state_joints", {}))
        lo, hi = layout.get("low"), layout.get("high")
        return cls(spec, joints, dict(layout["loops"]), list(layout["q"]), list(layout["qd"]),
                   list(layout["current"]), delay, action, loop_joints, loop_q, loop_qd,
                   None if lo is None else np.asarray(lo, float), None if hi is None else np.asarray(hi, float),
                   list(layout.get("drop_bodies", [])), state_joints, float(layout.get("goal_step", 0.0)),
                   int(layout.get("goal_lag", 2)))

    def goals(self, actions: np.ndarray) -> np.ndarray:
        """Recorded actions -> the loops' goals (rad/s for velocity loops, rad for position loops)."""
        if self.action == "goal_position_normalized":
            return self.low + (np.asarray(actions, float) + 1.0) * 0.5 * (self.high - self.low)
        g = np.asarray(actions, float)
        return np.round(g / self.goal_step) * self.goal_step if self.goal_step > 0 else g


@dataclass
class Blocks:
    """Contiguous time blocks of the recording (open-loop horizon each), split into train/test."""

    episodes: list[Recording]
    #: (episode index, first sample, samples) per block
    spans: list[tuple[int, int, int]]
    train: list[int]
    test: list[int]
    dt_s: float
    period_s: float
    #: per-joint scale of position / velocity residuals (their std over the recording)
    q_scale: np.ndarray
    qd_scale: np.ndarray


def make_blocks(episodes: list[Recording], bench: Bench, dt_s: float, horizon_s: float = 2.0,
                gap_blocks: int = 1, split: bool = True) -> Blocks:
    """Cut episodes into blocks of ``horizon_s``; blocks alternate train, gap, test, gap (a block
    next to a held-out block never trains: its samples are correlated with the test's)."""
    if not episodes:
        raise DataError("no episodes in the recording")
    period = float(np.median(np.concatenate([np.diff(e.t_s) for e in episodes])))
    h = max(2, int(round(horizon_s / period)))
    spans = []
    for i, e in enumerate(episodes):
        if e.states is None or e.actions is None:
            raise DataError(f"episode {e.name}: no full state/actions (a rig .mcap recording is needed)")
        need = max(bench.current + bench.qd + bench.q + bench.loop_q + bench.loop_qd) + 1
        if e.states.shape[1] < need:
            raise DataError(f"episode {e.name}: {e.states.shape[1]} state columns, the bench needs {need} "
                            "(positions, velocities, currents)")
        # after the first second: the goal acting at a block's start (two samples back) is recorded, and
        # the rig has left its hold (the hand's first block, started as the targets leave the hold
        # pose, was replayed 30x worse than the others on a clean recording)
        # no block spans a stall: a period longer than STALL_PERIODS median periods (a wall-clock rig
        # whose emulator or host fell behind: the emulator's physics gives up the time it could not
        # catch up with, so the samples after it are not the physics of the time between the stamps)
        stalls = np.flatnonzero(np.diff(e.t_s) > STALL_PERIODS * period)
        starts = [max(2, int(round(START_S / period)))] + [int(g) + 3 for g in stalls]
        ends = [int(g) + 1 for g in stalls] + [e.n]
        for a, z in zip(starts, ends, strict=True):
            for s in range(a, z - h, h):
                spans.append((i, s, h))
    cycle = 2 * (gap_blocks + 1)
    train = [k for k in range(len(spans)) if k % cycle == 0]
    test = [k for k in range(len(spans)) if k % cycle == gap_blocks + 1]
    if not split:  # score every block (a new recording: nothing trains)
        train, test = [], list(range(len(spans)))
        if not test:
            raise DataError(f"recording shorter than one block of {horizon_s:g} s")
    elif len(test) < 4 or len(train) < 2:
        raise DataError(f"recording too short: {len(spans)} blocks of {horizon_s:g} s; need at least "
                        f"{4 * cycle} (≈{4 * cycle * horizon_s:g} s) for 4 held-out blocks")
    allq = np.concatenate([e.states[:, bench.q] for e in episodes])
    allqd = np.concatenate([e.states[:, bench.qd] for e in episodes])
    return Blocks(episodes, spans, train, test, dt_s, period, np.maximum(allq.std(0), 1e-3),
                  np.maximum(allqd.std(0), 1e-3))


# ----------------------------------------------------------------------------- the rollout model


def servo_spec(bench: Bench):
    """A copy of the bench spec whose loop actuators are the firmware's loops in MJCF: velocity
    PI (the WidowX's servos) as an ``intvelocity`` actuator plus a feed-forward ``motor``;
    position PID (the hand's motor boards) as MuJoCo's ``mujoco.pid`` actuator plugin (integral
    clamped at the torque limit, as the firmware's). Dropped bodies are deleted."""
    import mujoco

    spec = bench.spec.copy()
    for b in bench.drop_bodies:
        spec.delete(spec.body(b))
    if bench.action == "goal_position_normalized":
        spec.activate_plugin("mujoco.pid")
    for j in bench.loop_joints:
        lp = bench.loops[j]
        if lp.get("mode", "velocity") == "position":
            act = spec.actuator(lp["actuator"])
            set_pid(spec, act, j, lp["kp_nm_per_rad"], lp["ki_nm_per_rad_s"], lp["kd_nm_s"], lp["tau_max_nm"])
            continue
        act = spec.actuator(j)
        act.set_to_intvelocity(kp=lp["ki_nm"], kv=lp["kp_nm_s"])
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_FALSE
        act.actlimited = mujoco.mjtLimited.mjLIMITED_FALSE
        spec.add_actuator(name=f"{j}_ff", target=j, trntype=mujoco.mjtTrn.mjTRN_JOINT,
                          gear=[lp["kp_nm_s"], 0, 0, 0, 0, 0])
        jt = spec.joint(j)
        jt.actfrcrange = [-lp["tau_max_nm"], lp["tau_max_nm"]]
        jt.actfrclimited = mujoco.mjtLimited.mjLIMITED_TRUE
    return spec


def _pid_instance(joint: str) -> str:
    return f"pid:{joint}"


def set_pid(spec, act, joint: str, kp: float, ki: float, kd: float, tau_max: float) -> None:
    """Make ``act`` a ``mujoco.pid`` plugin actuator (one plugin instance per joint, so gains can be
    fitted per joint): force = clip(kp·e + ki·∫e − kd·q̇, ±tau_max), ki·∫e clamped at ±tau_max."""
    import mujoco

    name = _pid_instance(joint)
    inst = next((p for p in spec.plugins if p.name == name), None)
    if inst is None:
        inst = spec.add_plugin(name=name, plugin_name="mujoco.pid")
    inst.config = {"kp": repr(float(kp)), "ki": repr(float(ki)), "kd": repr(float(kd)), "imax": repr(float(tau_max))}
    act.plugin.plugin_name = "mujoco.pid"
    act.plugin.name = name
    act.plugin.active = True
    act.actdim = 1
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    act.forcerange = [-tau_max, tau_max]
    act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE


@dataclass
class Candidate:
    name: str
    describe: str
    #: (bench, accepted values) -> sysid Parameters
    params: Callable


def get_joint_attr(joint, attr: str) -> float:
    """A joint's scalar value; MuJoCo 4's ``damping`` is a polynomial (linear term first)."""
    return float(np.ravel(getattr(joint, attr))[0])


def set_joint_attr(joint, attr: str, value: float) -> None:
    cur = getattr(joint, attr)
    if np.ndim(cur):
        new = np.array(cur, float)
        new.flat[0] = value
        setattr(joint, attr, new)
    else:
        setattr(joint, attr, float(value))


def _joint_attr(attr: str, lo: float, hi: float, what: str):
    def make(bench: Bench, sysid):
        base = np.array([get_joint_attr(bench.spec.joint(j), attr) for j in bench.joints], float)

        def mod(spec, p, attr=attr):
            for j, v in zip(bench.joints, p.value, strict=True):
                set_joint_attr(spec.joint(j), attr, float(v))

        start = np.clip(base, lo + 0.02 * (hi - lo), hi)
        p = sysid.Parameter(f"joint_{attr}", nominal=base, min_value=np.full_like(base, lo),
                            max_value=np.full_like(base, hi), modifier=mod)
        p.value = start.copy()
        return p
    return Candidate(f"joint_{attr}", what, make)


def _servo_gain(bench: Bench, sysid):
    n = len(bench.joints)

    def mod(spec, p):
        for j, g in zip(bench.joints, p.value, strict=True):
            lp = bench.loops[j]
            if lp.get("mode", "velocity") == "position":
                set_pid(spec, spec.actuator(lp["actuator"]), j, lp["kp_nm_per_rad"] * float(g),
                        lp["ki_nm_per_rad_s"] * float(g), lp["kd_nm_s"] * float(g), lp["tau_max_nm"])
                continue
            spec.actuator(j).set_to_intvelocity(kp=lp["ki_nm"] * float(g), kv=lp["kp_nm_s"] * float(g))
            spec.actuator(f"{j}_ff").gear = [lp["kp_nm_s"] * float(g), 0, 0, 0, 0, 0]
    return sysid.Parameter("servo_gain", nominal=np.ones(n), min_value=np.full(n, 0.3), max_value=np.full(n, 3.0),
                           modifier=mod)


def _input_delay(bench: Bench, sysid):
    # the nominal: the bench's own goal delay (a base calibration's, else 0)
    p = sysid.Parameter("input_delay", nominal=bench.input_delay_s, min_value=0.0, max_value=0.15, modifier=None)
    p.value = np.array([max(0.004, bench.input_delay_s)])
    return p


CATALOGUE: dict[str, Candidate] = {
    "joint_frictionloss": _joint_attr("frictionloss", 0.0, 2.0, "dry (Coulomb) friction at each joint [N·m]"),
    "joint_damping": _joint_attr("damping", 0.0, 5.0, "viscous friction at each joint [N·m·s/rad]"),
    "joint_armature": _joint_attr("armature", 0.001, 0.2, "reflected rotor inertia at each joint [kg·m²]"),
    "input_delay": Candidate("input_delay", "a pure delay of the goals [s]", _input_delay),
    "servo_gain": Candidate("servo_gain", "the servo loop's gain, a factor per joint", _servo_gain),
}


class Replay:
    """Replays blocks of a recording through a model built from sysid parameters."""

    def __init__(self, bench: Bench, blocks: Blocks, n_threads: int = 2, use_current: bool = False):
        import mujoco

        self.bench = bench
        self.blocks = blocks
        self.base = servo_spec(bench)
        m0 = self.base.compile()
        self.dt = float(m0.opt.timestep)
        self.nu = m0.nu
        self.position = bench.action == "goal_position_normalized"
        self.goal_lag = bench.goal_lag
        lj = bench.loop_joints or bench.joints
        self.i_int = [mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_ACTUATOR, bench.loops[j].get("actuator", j))
                      for j in lj]
        self.i_ff = [] if self.position else [mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_ACTUATOR, f"{j}_ff")
                                              for j in lj]
        self.act_adr = [int(m0.actuator_actadr[i]) for i in self.i_int]
        self.loop_cols = (list(bench.loop_q or bench.q), list(bench.loop_qd or bench.qd))
        self.loop_fitted = [lj.index(j) for j in bench.joints]
        self.qadr = [int(m0.jnt_qposadr[m0.joint(j).id]) for j in bench.joints]
        self.vadr = [int(m0.jnt_dofadr[m0.joint(j).id]) for j in bench.joints]
        sj = bench.state_joints or {j: (a, b) for j, a, b in zip(bench.joints, bench.q, bench.qd, strict=True)}
        self.state_cols = (np.array([a for a, _ in sj.values()]), np.array([b for _, b in sj.values()]))
        self.state_adr = (np.array([int(m0.jnt_qposadr[m0.joint(j).id]) for j in sj]),
                          np.array([int(m0.jnt_dofadr[m0.joint(j).id]) for j in sj]))
        self.n_threads = n_threads
        #: the reported motor current as a third output (velocity loops): fitted and scored beside q
        self.use_current = bool(use_current) and not self.position
        if self.use_current:
            fl = [bench.loops[j] for j in bench.joints]
            self.kt = np.array([lp["kt_nm_per_a"] for lp in fl])
            self.tau_max = np.array([lp["tau_max_nm"] for lp in fl])
            allc = np.concatenate([e.states[:, bench.current] for e in blocks.episodes])
            self.cur_scale = np.maximum(allc.std(0), 1e-3)
        self._datas: list = []
        # the rollout step after which each later sample of a block was measured: from the samples'
        # own stamps (a wall-clock rig's periods jitter), at least one step past the previous sample
        self._after: dict[int, np.ndarray] = {}
        for k, (ei, s, h) in enumerate(blocks.spans):
            rel = blocks.episodes[ei].t_s[s:s + h] - blocks.episodes[ei].t_s[s]
            n = np.round(rel[1:] / self.dt).astype(int)
            for i in range(n.size):  # strictly increasing (two stamps within one step stay apart)
                n[i] = max(n[i], n[i - 1] + 1 if i else 1)
            self._after[k] = n

    def build(self, params) -> object:
        spec = self.base.copy()
        for p in params.values():
            p.apply_modifier(spec)
        return spec.compile()

    def delay_of(self, params) -> float:
        return float(params["input_delay"].value[0]) if "input_delay" in params else self.bench.input_delay_s

    def gain_of(self, params) -> np.ndarray:
        """The loops' gain factors (1 but where ``servo_gain`` is fitted)."""
        g = np.ones(len(self.i_int))
        if "servo_gain" in params:
            g[self.loop_fitted] = np.asarray(params["servo_gain"].value, float).ravel()
        return g

    def _controls(self, blocks: list[int], delay_s: float) -> np.ndarray:
        """(blocks, steps, nu): each block's recorded goals, zero-order held and delayed by ``delay_s``
        (linear between neighbouring whole steps, so the fit sees a smooth function of the delay)."""
        b = self.blocks
        rows = []
        m, frac = divmod(delay_s / self.dt, 1.0)
        m = int(m)
        steps = self.steps(blocks)
        for k in blocks:
            ei, s, h = b.spans[k]
            e = b.episodes[ei]
            t = e.t_s[s] + np.arange(steps) * self.dt

            def goals(shift_steps: int, t=t, e=e):
                idx = np.searchsorted(e.t_s, t - shift_steps * self.dt, side="right") - 1
                return self.bench.goals(e.actions[np.clip(idx, 0, e.n - 1)])
            u = (1 - frac) * goals(m) + frac * goals(m + 1)
            c = np.zeros((steps, self.nu))
            c[:, self.i_int] = u
            if self.i_ff:
                c[:, self.i_ff] = u
            rows.append(c)
        return np.stack(rows) if rows else np.zeros((0, 0, self.nu))

    def steps(self, blocks: list[int]) -> int:
        """Rollout length (physics steps) that reaches every block's last sample."""
        return int(max(self._after[k][-1] for k in blocks)) if blocks else 0

    def _initial(self, model, blocks: list[int], delay_s: float, gain: np.ndarray | None = None) -> np.ndarray:
        """Full-physics states at the blocks' first samples: measured q, qd; each loop's integrator
        from what its motor reported (the goal acting then is the previous period's, ``delay_s``
        back). Velocity PI (current I): act = q + (kt·I − kp·(goal − q̇)) / ki. Position PID
        (effort E): act = ∫e = (E − kp·(goal − q) + kd·q̇) / ki, clamped as the firmware clamps it."""
        import mujoco

        d = mujoco.MjData(model)
        spec_ = mujoco.mjtState.mjSTATE_FULLPHYSICS
        out = np.zeros((len(blocks), mujoco.mj_stateSize(model, spec_)))
        b = self.blocks
        lj = self.bench.loop_joints or self.bench.joints
        loops = [self.bench.loops[j] for j in lj]
        if self.position:
            g = np.ones(len(lj)) if gain is None else gain
            kp = g * np.array([lp["kp_nm_per_rad"] for lp in loops])
            ki = g * np.array([lp["ki_nm_per_rad_s"] for lp in loops])
            kd = g * np.array([lp["kd_nm_s"] for lp in loops])
            tau = np.array([lp["tau_max_nm"] for lp in loops])
        else:
            ki = np.array([model.actuator_gainprm[i, 0] for i in self.i_int])
            kp = np.array([model.actuator_gear[i, 0] for i in self.i_ff])
            kt = np.array([lp["kt_nm_per_a"] for lp in loops])
        cq, cqd = self.loop_cols
        for r, k in enumerate(blocks):
            ei, s, _ = b.spans[k]
            e = b.episodes[ei]
            mujoco.mj_resetData(model, d)
            d.qpos[self.state_adr[0]] = e.states[s, self.state_cols[0]]
            d.qvel[self.state_adr[1]] = e.states[s, self.state_cols[1]]
            q, qd = e.states[s, cq], e.states[s, cqd]
            cur = e.states[s, self.bench.current]
            kg = int(np.searchsorted(e.t_s, e.t_s[s] - delay_s - 1e-9, side="right")) - self.goal_lag
            goal = self.bench.goals(e.actions[max(kg, 0)])
            if self.position:
                integ = np.divide(cur - kp * (goal - q) + kd * qd, ki, out=np.zeros(len(ki)), where=ki > 0)
                lim = np.divide(tau, ki, out=np.zeros(len(ki)), where=ki > 0)
                d.act[self.act_adr] = np.clip(integ, -lim, lim)
            else:
                d.act[self.act_adr] = q + (kt * cur - kp * (goal - qd)) / ki
            mujoco.mj_getState(model, d, out[r], spec_)
        return out

    def predict(self, models: list, delays: list[float], blocks: list[int], gains: list | None = None) -> np.ndarray:
        """(models, blocks, samples-1, 2·joints): predicted q, qd at the blocks' later samples."""
        import mujoco
        from mujoco import rollout

        if len(self._datas) < self.n_threads:
            self._datas = [mujoco.MjData(models[0]) for _ in range(self.n_threads)]
        states, ctrls, mods = [], [], []
        for i, (m, dl) in enumerate(zip(models, delays, strict=True)):
            states.append(self._initial(m, blocks, dl, None if gains is None else gains[i]))
            ctrls.append(self._controls(blocks, dl))
            mods += [m] * len(blocks)
        st, _ = rollout.rollout(mods, self._datas, np.concatenate(states), np.concatenate(ctrls))
        # state layout (FULLPHYSICS): time, qpos, qvel, act, ...
        nq = models[0].nq
        # the state after n steps is row n-1: each block's later samples at their own stamps
        idx = np.stack([self._after[k] - 1 for k in blocks])
        pick = st[np.arange(st.shape[0])[:, None], np.tile(idx, (len(models), 1))]
        q = pick[:, :, 1 + np.array(self.qadr)]
        qd = pick[:, :, 1 + nq + np.array(self.vadr)]
        cols = [q, qd]
        if self.use_current:  # the motor current the servo reports: its loop's torque / kt (last tick's goal)
            nv = models[0].nv
            act = pick[:, :, 1 + nq + nv + np.array(self.act_adr)[self.loop_fitted]]
            ctrl = np.concatenate(ctrls)
            goal = ctrl[np.arange(ctrl.shape[0])[:, None], np.tile(idx, (len(models), 1))][:, :, np.array(self.i_int)[self.loop_fitted]]
            cur = []
            for i, m in enumerate(models):
                sl = slice(i * len(blocks), (i + 1) * len(blocks))
                ki = m.actuator_gainprm[np.array(self.i_int)[self.loop_fitted], 0]
                kp = m.actuator_gear[np.array(self.i_ff)[self.loop_fitted], 0]
                tau = ki * (act[sl] - q[sl]) + kp * (goal[sl] - qd[sl])
                cur.append(np.clip(tau, -self.tau_max, self.tau_max) / self.kt)
            cols.append(np.concatenate(cur))
        return np.concatenate(cols, axis=2).reshape(len(models), len(blocks), -1, len(cols) * len(self.qadr))

    def measured(self, blocks: list[int]) -> np.ndarray:
        b = self.blocks
        out = []
        for k in blocks:
            ei, s, h = b.spans[k]
            e = b.episodes[ei]
            cols = [e.states[s + 1:s + h, self.bench.q], e.states[s + 1:s + h, self.bench.qd]]
            if self.use_current:
                cols.append(e.states[s + 1:s + h, self.bench.current])
            out.append(np.concatenate(cols, 1))
        return np.stack(out)

    def scale(self) -> np.ndarray:
        sc = [self.blocks.q_scale, self.blocks.qd_scale]
        if self.use_current:
            sc.append(self.cur_scale)
        return np.concatenate(sc)


# ----------------------------------------------------------------------------- fit and score


@dataclass
class Fit:
    effects: list[str]
    params: object  # sysid.ParameterDict
    values: dict[str, list[float]] = field(default_factory=dict)
    intervals: dict[str, list[float]] = field(default_factory=dict)
    unidentifiable: dict[str, list[str]] = field(default_factory=dict)
    fit_s: float = 0.0
    fit_cpu_s: float = 0.0
    #: held-out per block and joint: sum of squared position errors (scaled)
    test_sse: np.ndarray | None = None


def _param_dict(sysid, bench: Bench, effects: list[str], start: dict | None = None):
    pd = sysid.ParameterDict()
    for name in effects:
        p = CATALOGUE[name].params(bench, sysid)
        if start and name in start:
            p.value = np.clip(np.asarray(start[name], float), p.min_value, p.max_value)
        pd.add(p)
    return pd


def fit_effects(replay: Replay, effects: list[str], max_fit_blocks: int = 8, max_iters: int = 12,
                start: dict | None = None, seed: int = 0) -> Fit:
    """Fit the parameters of ``effects`` together on (up to ``max_fit_blocks``) training blocks with
    ``mujoco.sysid``; confidence intervals from its Jacobian; held-out errors on the test blocks."""
    sysid = _sysid()
    t0, c0 = time.perf_counter(), time.process_time()
    b = replay.blocks
    rng = np.random.default_rng(seed)
    train = sorted(rng.choice(b.train, min(max_fit_blocks, len(b.train)), replace=False).tolist())
    meas = replay.measured(train)
    scale = replay.scale()
    params = _param_dict(sysid, replay.bench, effects, start)

    def residual_fn(x, pd):
        x2 = x.reshape(len(x), -1) if x.ndim > 1 else x[:, None]
        models, delays, gains = [], [], []
        for c in range(x2.shape[1]):
            pd.update_from_vector(x2[:, c])
            models.append(replay.build(pd))
            delays.append(replay.delay_of(pd))
            gains.append(replay.gain_of(pd))
        pred = replay.predict(models, delays, train, gains)
        r = ((pred - meas[None]) / scale).reshape(x2.shape[1], -1)
        if x.ndim > 1:
            return [r.T], None, None
        return [r[0]], None, None

    fit = Fit(list(effects), params)
    if effects:
        # xtol 1e-4: parameters to 0.01 % (their intervals are far wider); the backend's log to a buffer
        opt, res = sysid.optimize(params, residual_fn, optimizer="mujoco", verbose=False, max_iters=max_iters,
                                  xtol=1e-4, output=io.StringIO())
        r_star = residual_fn(opt.as_vector(), opt)[0]
        jac = np.asarray(res.jac)
        _, half = sysid.calculate_intervals(r_star, jac)
        fit.params = opt
        k = 0
        for name, p in opt.items():
            v = p.value.ravel()
            hw = np.asarray(half[k:k + v.size], float)
            k += v.size
            fit.values[name] = [float(a) for a in v]
            fit.intervals[name] = [float(a) for a in hw]
            lo, hi = p.min_value.ravel(), p.max_value.ravel()
            labels = replay.bench.joints if v.size == len(replay.bench.joints) else [name]
            # unidentifiable: the interval is unbounded or wider than the box, or the value sits on a bound
            bad = [lab for lab, vi, hi_, lo_, up_ in zip(labels, v, hw, lo, hi, strict=True)
                   if not np.isfinite(hi_) or hi_ > 0.5 * (up_ - lo_) or vi <= lo_ + 1e-9 or vi >= up_ - 1e-9]
            if bad:
                fit.unidentifiable[name] = bad
    fit.fit_s = time.perf_counter() - t0
    fit.fit_cpu_s = time.process_time() - c0
    fit.test_sse = heldout_sse(replay, fit.params)
    return fit


def heldout_sse(replay: Replay, params) -> np.ndarray:
    """(test blocks, joints): open-loop squared position error summed over each block, scaled."""
    b = replay.blocks
    model = replay.build(params)
    pred = replay.predict([model], [replay.delay_of(params)], b.test, [replay.gain_of(params)])[0]
    meas = replay.measured(b.test)
    nj = len(replay.bench.joints)
    err = (pred[..., :nj] - meas[..., :nj]) / b.q_scale
    sse = (err ** 2).sum(1)
    if replay.use_current:  # position and current errors, each over its own spread
        ec = (pred[..., 2 * nj:] - meas[..., 2 * nj:]) / replay.cur_scale
        sse = sse + (ec ** 2).sum(1)
    return sse


def nrmse(sse: np.ndarray, samples: int) -> float:
    """Multi-step position NRMSE (per joint, normalised by the joint's std), mean over joints."""
    return float(np.mean(np.sqrt(sse.sum(0) / (sse.shape[0] * samples))))


# ----------------------------------------------------------------------------- selection


def select(replay: Replay, candidates: tuple[str, ...] = CANDIDATES, max_rounds: int = 3, seed: int = 0,
           log: Callable[[str], None] = lambda m: None, max_fit_blocks: int = 8) -> dict:
    """Stepwise: each round fits every remaining candidate together with the accepted effects (all
    refitted), accepts the best at "moderate" or better; then a pruning pass. Returns the report."""
    from hilstack.calibration.selection import LEVELS, SelectionConfig, gain_evidence

    cfg = SelectionConfig()
    sysid = _sysid()
    nominal = Fit([], _param_dict(sysid, replay.bench, []))
    nominal.test_sse = heldout_sse(replay, nominal.params)
    current = nominal
    rounds = []
    for r in range(max_rounds):
        tried = []
        for name in candidates:
            if name in current.effects:
                continue
            f = fit_effects(replay, current.effects + [name], max_fit_blocks=max_fit_blocks,
                            start=current.values, seed=seed)
            ev = gain_evidence(current.test_sse, f.test_sse, cfg, seed=seed)
            log(f"round {r + 1}: {'+'.join(f.effects)}: held-out gain {ev.gain:+.3f} "
                f"[{ev.interval[0]:+.3f}, {ev.interval[1]:+.3f}] {ev.level} ({f.fit_s:.1f} s, cpu {f.fit_cpu_s:.1f} s)")
            tried.append((f, ev))
        if not tried:
            break
        # best by evidence level, then gain; ties within 1e-6 go to the catalogue's order
        tried.sort(key=lambda fe: (LEVELS.index(fe[1].level), -round(fe[1].gain, 6)))
        rounds.append([{"effects": f.effects, "added": f.effects[-1], "evidence": ev.to_dict()} for f, ev in tried])
        best, ev = tried[0]
        if not ev.at_least("moderate"):
            # effects that may only show together (friction + delay, friction + damping): fitted jointly
            pairs = [pr for pr in PAIRS if all(e in candidates and e not in current.effects for e in pr)]
            for pr in pairs:
                f = fit_effects(replay, current.effects + list(pr), max_fit_blocks=max_fit_blocks,
                                start=current.values, seed=seed)
                pev = gain_evidence(current.test_sse, f.test_sse, cfg, seed=seed)
                log(f"round {r + 1} pair: {'+'.join(f.effects)}: held-out gain {pev.gain:+.3f} {pev.level}")
                rounds[-1].append({"effects": f.effects, "added": "+".join(pr), "evidence": pev.to_dict()})
                if pev.at_least("moderate") and (not ev.at_least("moderate") or pev.gain > ev.gain):
                    best, ev = f, pev
            if not ev.at_least("moderate"):
                break
        current = best
    pruned = []
    if len(current.effects) > 1:
        for name in list(current.effects):
            rest = [e for e in current.effects if e != name]
            f = fit_effects(replay, rest, max_fit_blocks=max_fit_blocks, start=current.values, seed=seed)
            ev = gain_evidence(f.test_sse, current.test_sse, cfg, seed=seed)
            log(f"prune {name}: keeping it gains {ev.gain:+.3f} over {'+'.join(rest)} ({ev.level})")
            if not ev.at_least("moderate"):
                pruned.append(name)
                current = f
    ns = replay.blocks.spans[replay.blocks.test[0]][2] - 1
    before = nrmse(nominal.test_sse, ns)
    after = nrmse(current.test_sse, ns)
    out = {"effects": current.effects, "values": current.values, "intervals_95": current.intervals,
           "unidentifiable": current.unidentifiable, "rounds": rounds, "pruned": pruned,
           "before_multi_step_nrmse": before, "after_multi_step_nrmse": after,
           "ratio": after / before if before > 0 else math.nan, "fit": current,
           "outputs": "position+current" if replay.use_current else "position"}
    if replay.use_current:  # the position part alone, as without --current
        replay.use_current = False
        try:
            out["before_position_nrmse"] = nrmse(heldout_sse(replay, nominal.params), ns)
            out["after_position_nrmse"] = nrmse(heldout_sse(replay, current.params), ns)
        finally:
            replay.use_current = True
    return out


# ----------------------------------------------------------------------------- output


def calibrated_spec(bench: Bench, values: dict[str, list[float]]):
    """The backend's bench spec with the identified joint values (and the delay as a custom numeric)."""
    import os

    spec = bench.spec.copy()
    base = spec.modelfiledir
    if base:  # the file is written elsewhere: asset paths made absolute
        if spec.meshdir and not os.path.isabs(spec.meshdir):
            spec.meshdir = os.path.normpath(os.path.join(base, spec.meshdir))
        if spec.texturedir and not os.path.isabs(spec.texturedir):
            spec.texturedir = os.path.normpath(os.path.join(base, spec.texturedir))
    for name, v in values.items():
        if name.startswith("joint_"):
            attr = name[len("joint_"):]
            for j, x in zip(bench.joints, v, strict=True):
                set_joint_attr(spec.joint(j), attr, float(x))
    delay = float(values["input_delay"][0]) if "input_delay" in values else bench.input_delay_s
    if delay > 0:  # fitted now, or the base model's (a two-stage calibration keeps it)
        spec.add_numeric(name=DELAY_NUMERIC, data=[delay])
    return spec


def evaluate(bench: Bench, episodes: list[Recording], values: dict[str, list[float]] | None = None,
             horizon_s: float = 2.0) -> float:
    """Multi-step position NRMSE of the bench model (with ``values`` applied) on every block of
    ``episodes`` (e.g. a NEW recording): all blocks are scored, none trains."""
    sysid = _sysid()
    blocks = make_blocks(episodes, bench, float(bench.spec.option.timestep), horizon_s=horizon_s, split=False)
    rp = Replay(bench, blocks)
    pd = _param_dict(sysid, bench, list((values or {}).keys()), values)
    sse = heldout_sse(rp, pd)
    return nrmse(sse, blocks.spans[0][2] - 1)


def base_mjcf(base: str | Path) -> Path:
    """``--base``: a previous calibration's directory (its ``calibrated.xml``) or an MJCF file."""
    p = Path(base)
    xml = p / "calibrated.xml" if p.is_dir() else p
    if not xml.is_file():
        raise DataError(f"--base {base}: no {'calibrated.xml in that directory' if p.is_dir() else 'such file'} "
                        "(give the directory of a previous `hil calibrate --model` run, or its calibrated.xml)")
    return xml


def bench_of(robot_config: str | Path, base: str | Path | None = None) -> Bench:
    """The robot's calibration bench from its sim backend (found through the driver registry); with
    ``base``, on that MJCF (a previous calibration's) instead of the robot's own."""
    from hilstack.drivers.registry import make_driver

    driver = make_driver(str(robot_config), backend="sim")
    if not isinstance(driver, CalibrationBench):
        raise DataError(f"{robot_config}: robot {driver.spec.name!r}'s sim backend has no calibration_bench() "
                        "(the MJCF calibration needs it)")
    params = driver.params
    if base is not None:
        params = params.model_copy(update={"sim": {**dict(params.sim or {}), "mjcf": str(base_mjcf(base))}})
    try:
        layout = driver.calibration_bench(params)
    except ValueError as e:  # an MJCF MuJoCo cannot load
        raise DataError(f"--base {base}: {str(e).splitlines()[0]}") from None
    if base is not None:
        for j in list(layout["joints"]) + list(layout.get("loop_joints", [])):
            if layout["spec"].joint(j) is None:
                raise DataError(f"--base {base_mjcf(base)}: no joint named {j!r} (not a calibration of this robot)")
    return Bench.from_layout(layout)


def run_mjcf_calibration(data_path: str | Path, robot_config: str | Path, out_dir: str | Path, seed: int = 0,
                         progress: bool = True, horizon_s: float = 2.0, force: bool = False,
                         candidates: tuple[str, ...] = CANDIDATES, max_rounds: int = 3,
                         max_fit_blocks: int = 8, base: str | Path | None = None, current: bool = False) -> dict:
    """`hil calibrate --model <robot config>`: select and fit the missing effect, write
    ``calibrated.xml``, ``report.json`` and ``report.md`` to ``out_dir``.

    ``base`` (``--base``): judge the candidates against a previous calibration (its directory or
    ``calibrated.xml``) instead of the MJCF as shipped: calibrate the rig clean first, then look for
    what an effect adds on top of it (a wall-clock rig's link gives the clean rig a lag of its own;
    docs/calibration.md, "Two-stage calibration").

    ``current`` (``--current``; velocity-loop benches, the WidowX): the motor current the servos
    report is a model output beside the joint positions, fitted and scored (each over its spread):
    a servo's velocity loop hides a viscous loss in the motion but not in the current."""
    import sys

    from hilstack.calibration.data import load_episodes

    def log(msg: str) -> None:
        if progress:
            print(f"[calibrate] {msg}", file=sys.stderr, flush=True)

    t0, c0 = time.perf_counter(), time.process_time()
    bench = bench_of(robot_config, base)
    out = Path(out_dir)
    xml_path = out / "calibrated.xml"
    if xml_path.exists() and not force:
        raise DataError(f"{xml_path} exists (pass --force to overwrite)")
    episodes = load_episodes(data_path, robot=None, warn=lambda m: log(f"warning: {m}"))
    blocks = make_blocks(episodes, bench, float(bench.spec.option.timestep), horizon_s=horizon_s)
    clocks = sorted({str(e.meta.get("clock", "host")) for e in episodes})
    log(f"{sum(e.n for e in episodes)} samples in {len(episodes)} episode(s) on the {'/'.join(clocks)} clock, "
        f"{len(blocks.spans)} blocks of {horizon_s:g} s: {len(blocks.train)} train, {len(blocks.test)} held out")
    if current and bench.action != "goal_velocity":
        raise DataError(f"--current: {robot_config}'s loops are position loops; the current output is for "
                        "velocity-loop servos (the WidowX)")
    replay = Replay(bench, blocks, use_current=current)
    unknown = [c for c in candidates if c not in CATALOGUE]
    if unknown:
        raise DataError(f"unknown candidate effects {unknown}; the catalogue: {list(CATALOGUE)}")
    rep = select(replay, candidates=tuple(candidates), max_rounds=max_rounds, seed=seed, log=log,
                 max_fit_blocks=max_fit_blocks)
    fit = rep.pop("fit")
    out.mkdir(parents=True, exist_ok=True)
    xml_path.write_text(calibrated_spec(bench, fit.values).to_xml())
    rep.update({"model": str(robot_config), "data": str(data_path), "samples": int(sum(e.n for e in episodes)),
                "calibrated_mjcf": str(xml_path), "base": None if base is None else str(base_mjcf(base)), "wall_s": round(time.perf_counter() - t0, 2), "cpu_s": round(time.process_time() - c0, 2),
                "catalogue": {k: c.describe for k, c in CATALOGUE.items()}, "joints": bench.joints,
                "horizon_s": horizon_s, "blocks": {"train": len(blocks.train), "test": len(blocks.test)},
                # the samples' time: the device's own clock where the robot reports one, else the host's
                "clock": clocks, "episodes": len(episodes)})
    (out / "report.json").write_text(json.dumps(rep, indent=1))
    (out / "report.md").write_text(_markdown(rep))
    return rep


def _markdown(rep: dict) -> str:
    lines = [f"# MJCF calibration of {rep['model']}", "", f"data: {rep['data']} ({rep['samples']} samples, "
             f"{rep['episodes']} episode(s) on the {'/'.join(rep['clock'])} clock)", "",
             f"nominal (the model effects are judged against): {rep.get('base') or 'the MJCF as shipped'}", "",
             f"effects: {', '.join(rep['effects']) or 'none'}", "",
             f"held-out multi-step (open-loop, {rep['horizon_s']:g} s) position NRMSE: "
             f"{rep['before_multi_step_nrmse']:.4f} → {rep['after_multi_step_nrmse']:.4f} "
             f"(×{rep['ratio']:.3f})" + (f"; outputs {rep['outputs']}, the position alone "
                                          f"{rep['before_position_nrmse']:.4f} → {rep['after_position_nrmse']:.4f}"
                                          if rep.get("outputs") == "position+current" else ""),
             "", "| effect | joint | value | ±95 % | identifiable |", "|---|---|---|---|---|"]
    for name, vals in rep["values"].items():
        labels = rep["joints"] if len(vals) == len(rep["joints"]) else [name]
        for lab, v, h in zip(labels, vals, rep["intervals_95"][name], strict=True):
            ok = "no" if lab in rep["unidentifiable"].get(name, []) else "yes"
            lines.append(f"| {name} | {lab} | {v:.4g} | {h:.2g} | {ok} |")
    lines += ["", "## Rounds", ""]
    for i, rnd in enumerate(rep["rounds"]):
        for c in rnd:
            ev = c["evidence"]
            lines.append(f"- round {i + 1}: {'+'.join(c['effects'])}: gain {ev['gain']:+.3f} "
                         f"[{ev['interval'][0]:+.3f}, {ev['interval'][1]:+.3f}] {ev['level']}")
    if rep["pruned"]:
        lines += ["", f"pruned: {', '.join(rep['pruned'])}"]
    lines += ["", f"calibrated MJCF: {rep['calibrated_mjcf']} (set `params.sim.mjcf` in the robot config to use it)"]
    return "\n".join(lines) + "\n"
