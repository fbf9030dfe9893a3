"""Controller node: runs any policy against a robot on the bus.

A policy is ``policy(state [S]) -> action [A]`` in *normalized* units ([-1, 1] of the
spec's limits, as the research normalizes actions); the node scales to the spec's
units on the way out. A policy may expose ``last_plan``/``last_predicted_states`` (the
MPC policy does) and the node publishes them for rerun on ``hil/<rig>/mpc/plan``.

Two timing modes, same node; :meth:`ControllerNode.run_episode` picks the one the robot's
spec says (``RobotSpec.pacing``, published by its driver node):

* **realtime** (``WALL_CLOCK``: real and emulated robots; ``STEPPED``: a sim paced on the
  wall clock): commands go out at a fixed rate whatever the planning time. Planning runs
  in a worker thread; if the plan for the newest state is not ready by the deadline, the
  next action of the last good plan (shifted one step) is sent instead, or, when none is
  left, what the robot's stop holds (the spec's ``safe_action``, else, for a
  position-controlled robot, the command it holds, ``RobotState.action``; never a
  normalized zero, which is the middle of the range: a jump for a position-controlled
  robot), and the late plan is counted.
* **lockstep** (``LOCKSTEP``: sim rigs with ``pace: lockstep``): the node answers each
  published state with one command tagged with that state's sequence number, and the sim
  advances when it arrives, so a rig runs faster than real time with the same nodes.

A state that is not ok (``RobotState.ok``: a stale or non-finite input) is never planned
from: realtime sends nothing for it (the driver node holds the robot), lockstep answers it
with what the robot's stop holds so the sim advances (the driver node refuses it while the
robot is not ok); both count it in ``EpisodeLog.unhealthy_states`` and leave it out of the log.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hilstack.bus import keys
from hilstack.bus.cycle import CycleTimer
from hilstack.bus.lifetime import StopRequested
from hilstack.bus.node import Node
from hilstack.bus.schemas import Command, Plan, ResetEvent, ResetPhase, RobotState, SpecMsg
from hilstack.configs.schema import BusConfig
from hilstack.control.policy_api import DelayAware, HasPlanner, PlanDetails, PlanningPolicy, Shiftable
from hilstack.control.sample_refit import SampleRefit
from hilstack.drivers.base import Pacing, RobotSpec

Policy = Callable[[np.ndarray], np.ndarray]
_log = logging.getLogger("hil")


@dataclass
class EpisodeLog:
    """What a controller saw and did (robot units for actions, and normalized)."""

    states: list[np.ndarray] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    actions_norm: list[np.ndarray] = field(default_factory=list)
    times_s: list[float] = field(default_factory=list)
    episode: int = 0
    #: how long each policy call took [s], in the order the calls were made
    plan_times_s: list[float] = field(default_factory=list)
    #: for each entry of ``plan_times_s``, which policy call of the episode it timed (0 = the
    #: first): a call with no time (the realtime plan still running when the episode ended)
    #: leaves a gap here instead of shifting every later time onto the wrong call
    plan_calls: list[int] = field(default_factory=list)
    late_plans: int = 0
    #: realtime mode: cycles whose state did not arrive within half a period (the newest was used)
    stale_states: int = 0
    #: states that were not ok: nothing planned from them (realtime: nothing sent)
    unhealthy_states: int = 0
    timeouts: int = 0
    #: realtime mode: the cycle timer's summary (late/missed periods, p50/p99 per section)
    timing: dict[str, Any] = field(default_factory=dict)
    #: realtime mode with a :class:`SampleRefit`: the planner's sample count at the end, and
    #: its changes during the episode (refit_samples' records, with ``at_step``)
    samples: int | None = None
    sample_refits: list[dict[str, Any]] = field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.states), np.array(self.actions_norm)


#: realtime mode: a plan not back within this fraction of the period is late (the shifted
#: last plan is sent); the rest of the period carries the command to the driver node
REALTIME_DEADLINE_FRAC = 0.8

#: after the driver node is gone, how long a reset still waits for an answer (the reset
#: supervisor's, saying why it failed the reset) before it raises :class:`DriverGone` [s]
DRIVER_GONE_GRACE_S = 2.0


class ResetFailed(RuntimeError):
    """The rig answered a reset request with a failure (no reset supervisor for a robot that
    cannot reset itself, the e-stop engaged, a refused teleport): ``str()`` says why."""


class DriverGone(RuntimeError):
    """The robot's driver node left the bus (link failure, stopped, killed) while waited for."""


class ControllerNode(Node):
    def __init__(
        self,
        rig: str,
        robot: str,
        bus: BusConfig | None = None,
        name: str = "controller",
        state_timeout_s: float = 5.0,
        supervised: bool = False,
        **kw: Any,
    ):
        super().__init__(name, rig, bus, **kw)
        self.robot = robot
        self.state_timeout_s = state_timeout_s
        #: the rig has a reset supervisor (its ``reset:`` section; the MBRL loop runs it): every
        #: reset request says so (``ResetEvent.supervised``) and only the supervisor serves it
        self.supervised = supervised
        self._state = self.subscribe(keys.state(rig, robot), RobotState)
        self._spec = self.subscribe(keys.spec(rig, robot), SpecMsg)
        self._cmd = self.publisher(keys.cmd(rig, robot), Command, reliable=True)  # lockstep steps on each
        self._plan = self.publisher(keys.plan(rig), Plan)
        self._reset_req = self.publisher(keys.reset(rig, "request"), ResetEvent, reliable=True)
        self._reset_done = self.subscribe(keys.reset(rig, "done"), ResetEvent)
        #: the robot's driver node: a wait for its answer ends once it is gone
        self.driver = self.watch_alive(keys.driver_node(robot))
        #: the robot's spec, typed again from its driver node's SpecMsg (wait_ready)
        self.spec: RobotSpec | None = None
        self.late_count = 0

    # ------------------------------------------------------------------ plumbing
    def wait_ready(self, timeout_s: float = 20.0) -> RobotSpec:
        """Wait for the robot's spec (published by its driver node). A stop of this node
        (``stop_event``: Ctrl-C or SIGTERM when it handles signals) ends the wait within 0.1 s
        with :class:`~hilstack.bus.lifetime.StopRequested`: before, a Ctrl-C while `hil teleop`
        waited for a rig that was not up was ignored until ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while self.spec is None:
            if self.stop_event.is_set():
                raise StopRequested(f"stopped while waiting for the spec on {keys.spec(self.rig, self.robot)}")
            m = self._spec.wait(0.1)
            if m is not None:
                self.spec = RobotSpec.from_dict(m.spec)
            elif time.monotonic() > deadline:
                raise TimeoutError(
                    f"no spec from {keys.spec(self.rig, self.robot)} within {timeout_s} s: is the driver node up?"
                )
        return self.spec

    @property
    def pacing(self) -> Pacing:
        """The robot's time model, from its spec (:class:`~hilstack.drivers.base.Pacing`):
        lockstep or not, and ``command_delay_periods``, the commands already on their way
        when a state arrives (what an MPC predicts through)."""
        p = self.wait_ready().pacing
        if p is None:
            raise ValueError(f"the spec of {self.robot} on {keys.spec(self.rig, self.robot)} carries no pacing "
                             "(a driver node of an older hilstack?)")
        return p

    def state_names(self) -> tuple[str, ...]:
        return self.wait_ready().state.names

    def next_state(self, after_seq: int = -1, timeout_s: float | None = None) -> RobotState:
        """The newest state with a sequence number above ``after_seq``."""
        timeout_s = self.state_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        last = self._state.last
        if last is not None and last.seq > after_seq:
            m = self._state.poll()
            return m if m is not None else last
        while True:
            m = self._state.wait(max(0.0, deadline - time.monotonic()))
            if m is not None and m.seq > after_seq:
                return m
            if time.monotonic() >= deadline:
                raise TimeoutError(f"no new state from {self.robot} within {timeout_s} s")

    def held_norm(self, s: RobotState) -> np.ndarray | None:
        """The command the robot runs now, normalized: the state's ``action`` (the driver's
        held command), else the spec's safe action; None when neither is known."""
        if len(s.action) == self.spec.action.dim and np.all(np.isfinite(s.action)):
            return self.spec.action.normalize(s.action)
        return self.safe_norm(s, held=False)

    def safe_norm(self, s: RobotState, held: bool = True) -> np.ndarray | None:
        """What the controller sends when it has no plan, normalized: what ``Driver.stop()``
        holds. The spec's safe action (zero leg or joint velocity...), else, for a
        position-controlled robot, the command it holds (its current target); None when
        neither is known (then nothing may be sent). Never the normalized zero: that is the
        middle of each range, a jump for a position robot and not a stop for an asymmetric one."""
        if self.spec.safe_action is not None:
            return self.spec.action.normalize(self.spec.safe_action)
        return self.held_norm(s) if held else None

    def send(self, action_norm: np.ndarray, state_seq: int) -> np.ndarray:
        return self.send_action(self.spec.action.denormalize(action_norm), state_seq)

    def send_action(self, action: np.ndarray, state_seq: int) -> np.ndarray:
        """Publish a command in the robot's units (the driver node applies the contract's limits)."""
        a = np.asarray(action, dtype=np.float64)
        self._cmd.put(Command(robot=self.robot, action=a.tolist(), state_seq=state_seq, source=self.name))
        return a

    def reset(self, timeout_s: float = 10.0, **pose: float) -> RobotState:
        """Ask the driver node to reset the robot (sim) and return the first state of the new episode."""
        self.wait_ready()
        self._reset_done.poll()
        last = self._state.last  # the episode it ends: its newest state
        self._reset_req.put(ResetEvent(robot=self.robot, phase=ResetPhase.REQUEST, pose={k: float(v) for k, v in pose.items()},
                                       state_seq=-1 if last is None else last.seq, supervised=self.supervised))
        deadline = time.monotonic() + timeout_s
        gone_by: float | None = None
        while True:
            m = self._reset_done.wait(min(0.5, max(0.0, deadline - time.monotonic())))
            if m is not None and m.robot == self.robot:
                if m.phase != ResetPhase.DONE:
                    raise ResetFailed(f"reset of {self.robot} {m.phase}: {m.detail}")
                break
            now = time.monotonic()
            if self.driver.gone:
                # its link failed or it was stopped: no DONE can come (a demo waited 352 s); a reset
                # supervisor's own answer (why it failed the reset) still may, for DRIVER_GONE_GRACE_S
                gone_by = now if gone_by is None else gone_by
                if now - gone_by >= DRIVER_GONE_GRACE_S:
                    raise DriverGone(f"the driver node of {self.robot} is gone (its link failed, or it was "
                                     "stopped): no reset answer can come")
            else:
                gone_by = None
            if now >= deadline:
                raise TimeoutError(f"no reset answer from {self.robot} within {timeout_s} s")
        while True:
            s = self.next_state(timeout_s=timeout_s)
            if s.episode >= m.episode:
                return s

    def publish_plan(self, policy: Any, plan_time_s: float, late: bool) -> None:
        if not isinstance(policy, PlanningPolicy) or policy.last_plan is None:
            return
        plan = policy.last_plan
        states = policy.last_predicted_states if isinstance(policy, PlanDetails) else None
        st = [] if states is None else np.asarray(states).reshape(-1, np.asarray(states).shape[-1]).tolist()
        self._plan.put(
            Plan(
                robot=self.robot,
                actions=np.asarray(plan).tolist(),
                states=st,
                cost=float(policy.last_cost) if isinstance(policy, PlanDetails) else 0.0,
                plan_time_s=plan_time_s,
                late=late,
                late_count=self.late_count,
                samples=int(policy.planner.samples) if isinstance(policy, HasPlanner) and policy.planner is not None
                else 0,
            )
        )

    # ------------------------------------------------------------------ episodes
    def run_episode(self, policy: Policy, steps: int, first: RobotState | None = None,
                    stop_if: Callable[[np.ndarray], bool] | None = None,
                    end_if: Callable[[RobotState], bool] | None = None,
                    refit: SampleRefit | None = None) -> EpisodeLog:
        """Run ``policy`` for up to ``steps`` states in the robot's time model (the spec's
        :attr:`pacing`): :meth:`run_lockstep` on a sim stepped on its answers (``LOCKSTEP``,
        ``FOLLOWER``), :meth:`run_realtime`
        otherwise (``first``, a state already taken, is where a lockstep episode starts; the
        realtime loop starts on fresh states). ``end_if`` (lockstep): see :meth:`run_lockstep`.
        ``refit``: realtime only (the sample count follows the load); a lockstep sim has no
        deadline and ignores it."""
        if self.pacing.answered:
            return self.run_lockstep(policy, steps, first, stop_if=stop_if, end_if=end_if)
        return self.run_realtime(policy, steps, stop_if=stop_if, refit=refit)

    def run_lockstep(self, policy: Policy, steps: int, first: RobotState | None = None,
                     stop_if: Callable[[np.ndarray], bool] | None = None,
                     end_if: Callable[[RobotState], bool] | None = None) -> EpisodeLog:
        """Answer ``steps`` states with ``policy``; the sim advances on each answer.
        ``stop_if(state array)`` and ``end_if(RobotState)`` are asked about every state after
        the first before it is answered; the episode ends, unanswered, on the first one either
        says is the end (the rig's episode-end rules judged here make the end a property of the
        states, not of when another node's word arrives)."""
        self.wait_ready()
        log = EpisodeLog()
        s = first or self.next_state()
        log.episode = s.episode
        for _ in range(steps):
            x = np.asarray(s.state)
            if not s.ok:  # nothing planned from it; what stop() holds lets the sim advance
                log.unhealthy_states += 1
                hold = self.safe_norm(s)
                if hold is not None:
                    self.send(hold, s.seq)
                s = self._answered(s, None if hold is None else self.spec.action.denormalize(hold))
                continue
            t0 = time.perf_counter()
            a_norm = np.asarray(policy(x), dtype=np.float64)
            dt = time.perf_counter() - t0
            a = self.send(a_norm, s.seq)
            self.publish_plan(policy, dt, False)
            log.states.append(x)
            log.actions.append(a)
            log.actions_norm.append(self.spec.action.normalize(a))
            log.times_s.append(s.t_s)
            log.plan_calls.append(len(log.plan_times_s))  # lockstep: every call is timed
            log.plan_times_s.append(dt)
            s = self._answered(s, a)
            if end_if is not None and end_if(s):
                break
            if stop_if is not None and stop_if(np.asarray(s.state)):
                break
        log.states.append(np.asarray(s.state))
        log.times_s.append(s.t_s)
        return log

    def _answered(self, s: RobotState, action: np.ndarray | None, resend_s: float = 1.0) -> RobotState:
        """Lockstep: the state after ``s``, which the driver node publishes once our answer to
        ``s`` arrives. The answer is sent again every ``resend_s`` until then (same
        ``state_seq``: once the sim has stepped on it, the driver node ignores it): a command
        sent just after joining can reach no one, and a lockstep sim no longer steps on its
        own to hide that."""
        deadline = time.monotonic() + self.state_timeout_s
        while True:
            try:
                return self.next_state(after_seq=s.seq, timeout_s=min(resend_s, max(0.0, deadline - time.monotonic())))
            except TimeoutError:
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"no new state from {self.robot} within {self.state_timeout_s} s") from None
                if action is not None:
                    self.send_action(action, s.seq)

    def run_realtime(self, policy: Policy, steps: int, period_s: float | None = None,
                     deadline_frac: float = REALTIME_DEADLINE_FRAC,
                     stop_if: Callable[[np.ndarray], bool] | None = None,
                     refit: SampleRefit | None = None) -> EpisodeLog:
        """Fixed-rate commands; planning in a worker with a deadline of ``deadline_frac`` periods.

        Paced by :class:`hilstack.bus.cycle.CycleTimer` (``self.cycle`` afterwards: late and
        missed periods, p50/p99 of the wait for the plan); ``log.timing`` holds its summary.

        The cycle grid is started when a fresh state arrives, so it runs in phase with the
        driver node's (same period, same clock): each cycle plans from the state published
        at its start, and its command (sent within ``deadline_frac`` periods) reaches the
        driver node before that node's next period. (A free-running grid had a random
        phase per episode: a state up to a period old, and a command that missed the next
        period half of the time.) A cycle whose state has not arrived within half a period
        uses the newest one and counts it in ``log.stale_states``.

        A policy with ``delay_steps`` > 0 (:class:`hilstack.control.policies.MpcPolicy` on a
        wall-clock robot) is called as ``policy(state, committed=...)`` with the last
        ``delay_steps`` commands sent (normalized, oldest first): those act before the one
        it plans. A plan that comes in late is used shifted by the cycles it missed, and the
        policy's ``shift(n)`` (the planner's warm start) is told so.

        ``refit`` (:class:`hilstack.control.sample_refit.SampleRefit`; the policy has a
        ``planner`` with ``set_samples``): the planner's sample count follows the load during the
        episode, refitted from the plan times and late plans measured, applied between two
        plans (while the worker is idle) and logged when it changes; ``log.samples`` and
        ``log.sample_refits`` say the count at the end and its changes.
        """
        spec = self.wait_ready()
        period = period_s or spec.period_s
        log = EpisodeLog()
        job: dict[str, Any] = {}
        done = threading.Event()
        ready = threading.Event()
        go = threading.Event()
        delay = int(policy.delay_steps or 0) if isinstance(policy, DelayAware) else 0

        def worker() -> None:
            while not done.is_set():
                if not go.wait(0.1):
                    continue
                go.clear()
                t0 = time.perf_counter()
                if delay:
                    a = np.asarray(policy(job["x"], committed=job["committed"]), dtype=np.float64)
                else:
                    a = np.asarray(policy(job["x"]), dtype=np.float64)
                plan = policy.last_plan if isinstance(policy, PlanningPolicy) else None
                job["result"] = (a, None if plan is None else np.array(plan), time.perf_counter() - t0, job["seq"])
                ready.set()

        th = threading.Thread(target=worker, daemon=True, name="planner")
        th.start()
        fallback: list[np.ndarray] = []  # remaining actions of the last good plan
        busy = False
        calls = 0  # policy calls started (EpisodeLog.plan_calls)
        unhealthy_cycle = -1  # the last cycle whose state was not ok
        # align the grid with the state stream (see above): the least delayed of three
        # fresh arrivals marks the driver node's grid (a single one may come late)
        s = self._state.poll() or self._state.last  # take what is queued: the next ones are fresh
        phase = []
        for j in range(3):
            s = self.next_state(after_seq=s.seq if s is not None else -1)
            phase.append(time.monotonic() - j * period)
        held = self.held_norm(s)
        sent: list[np.ndarray] = [] if held is None else [held]
        timer = self.cycle = CycleTimer(period, sleep=self.stop_event.wait)
        timer.start(at_s=min(phase) + 2 * period)
        planner = policy.planner if isinstance(policy, HasPlanner) and refit is not None else None
        if planner is not None:
            refit.start(planner.samples)
        try:
            for i in range(steps):
                if i:
                    timer.wait()
                    if self.stop_event.is_set():
                        break
                    try:  # the state the driver node published at the start of this period
                        s = self.next_state(after_seq=s.seq, timeout_s=0.5 * period)
                    except TimeoutError:
                        log.stale_states += 1
                        s = self.next_state()
                if self.stop_event.is_set():
                    break
                x = np.asarray(s.state)
                if not s.ok:
                    # nothing planned from it, nothing sent: the driver node holds the robot;
                    # a plan under way or left over started before it and is dropped
                    log.unhealthy_states += 1
                    fallback = []
                    unhealthy_cycle = i
                    continue
                if stop_if is not None and log.states and stop_if(x):
                    break
                if not busy:
                    if planner is not None:  # between two plans: the worker is idle
                        n = refit.update(log, planner.samples)
                        if n != planner.samples:
                            r = refit.refits[-1]
                            _log.info("%s: planner samples %d -> %d at step %d: plan p50 %.0f ms, tail %.0f ms, "
                                      "late %.0f%% (%s)", self.robot, r["from"], n, r["at_step"], r["plan_ms_p50"],
                                      r["plan_ms_tail"], 100 * r["late_share"], r["reason"])
                            planner.set_samples(n)
                    job["x"], job["seq"], job["cycle"], job["call"] = x, s.seq, i, calls
                    calls += 1
                    job["committed"] = [a.copy() for a in sent[-delay:]] if delay else []
                    ready.clear()
                    go.set()
                    busy = True
                with timer.section("plan_wait"):
                    got = ready.wait(max(0.0, timer.deadline_s(deadline_frac) - time.monotonic()))
                if got and job["cycle"] <= unhealthy_cycle:  # planned before a not-ok state
                    busy, got = False, False
                    log.plan_times_s.append(job["result"][2])
                    log.plan_calls.append(job["call"])
                if got:
                    a, plan, dt, _ = job["result"]
                    busy = False
                    skip = i - job["cycle"]  # cycles this plan missed: its first actions are gone
                    steps_left = [] if plan is None else [np.asarray(p) for p in plan]
                    if skip and len(steps_left) > skip:
                        a = steps_left[skip]
                    if skip and isinstance(policy, Shiftable):
                        policy.shift(skip)  # the planner's warm start moves on with it
                    fallback = steps_left[skip + 1:]
                    self.publish_plan(policy, dt, False)
                    log.plan_times_s.append(dt)
                    log.plan_calls.append(job["call"])
                else:
                    if busy:
                        self.late_count += 1
                        log.late_plans += 1
                    # the shifted last plan, else what stop() holds: never a normalized zero
                    a = fallback.pop(0) if fallback else self.safe_norm(s)
                    if a is None:
                        continue
                a_sent = self.send(a, s.seq)
                sent = (sent + [self.spec.action.normalize(a_sent)])[-max(delay, 1):]
                log.states.append(x)
                log.actions.append(a_sent)
                log.actions_norm.append(self.spec.action.normalize(a_sent))
                log.times_s.append(s.t_s)
        finally:
            done.set()
            th.join(1.0)
            log.timing = timer.summary()
            if planner is not None:
                log.samples, log.sample_refits = planner.samples, list(refit.refits)
        s = self.next_state()
        log.states.append(np.asarray(s.state))
        log.times_s.append(s.t_s)
        return log
