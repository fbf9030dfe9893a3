"""The automated-reset supervisor node: an explicit state machine on the bus.

::

    running ─end_episode→ episode_end ─pause→ paused ─begin→ resetting ─steps_done→ verifying
       ↑                                                   ↑   └retry┘           │ └retry→ resetting
       └──────────────resume── resumed ←──verified─────────┘                     │
    any reset state ─fail→ failed (e-stop engaged, operator told)
    any state ─estop_engaged→ estopped ─estop_released→ running

The machine is `transitions` (pytransitions): states and transitions are data
(:data:`STATES`, :data:`TRANSITIONS`), invalid triggers raise, and the diagram in
docs/reset.md is generated from the same definition (:func:`state_diagram_mermaid`).

Protocol (keys in bus/keys.py):

- ``running``: the supervisor runs the episode-end detectors on each state of the robot
  while commands flow (driver node active, not stopped). When one fires it publishes
  ``end_episode``; controllers stop commanding on it (the MBRL loop does) and ask for a
  reset.
- A controller's ``reset/request`` is the pause: it has stopped commanding. (A request
  while ``running`` is an episode that ended at the controller: length, path end.)
  The driver node leaves requests to the supervisor while its liveliness token
  ``hil/<rig>/alive/reset-supervisor`` is present.
- ``resetting``: the procedure's steps (control/reset/steps.py) run one after the other,
  each answering every state with one command (lockstep rigs advance on it), each with a
  timeout in robot time and a number of retries. An ``optional`` step that runs out of
  attempts is skipped (``skip``): the next step backs it up (self_right → lab_fixture).
- ``verifying``: the robot holds still for ``settle_s`` and its pose is checked against
  the start pose. Failing: the steps run again (``verify.retries``) or the reset fails.
- ``resumed``: the supervisor asks the driver node to start a new episode
  (``reset/driver`` phase ``episode``: ``RobotState.episode`` is bumped there, so
  recordings split), then answers the controller on ``reset/done``; ``resume`` → running.
- ``failed``: a step ran out of attempts, the verification failed, the driver node
  disappeared or went silent. The supervisor engages the rig's e-stop
  (bus/estop.py :func:`~hilstack.bus.estop.command_estop`), answers the controller ``failed`` with
  the reason, logs it and publishes it; the e-stop latch then moves it to ``estopped``.
- The e-stop wins: whenever the node's latch is engaged the machine goes to
  ``estopped`` from any state, stops commanding, and answers a pending request
  ``failed``. Releasing the e-stop returns it to ``running``.

Every transition is published as a :class:`~hilstack.bus.schemas.ResetTransition` on
``hil/<rig>/reset/transition`` (recorded with the rest of the rig).
"""

from __future__ import annotations

import logging
import math
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import zenoh
from transitions import EventData, Machine

from hilstack.bus import keys
from hilstack.bus.estop import command_estop
from hilstack.bus.node import Node
from hilstack.bus.schemas import (
    Command,
    MalformedMessage,
    ResetEvent,
    ResetPhase,
    ResetTransition,
    RobotState,
    SpecMsg,
    StoppedReason,
    decode,
)
from hilstack.configs.schema import BusConfig
from hilstack.control.reset.config import ResetConfig, VerifyConfig
from hilstack.control.reset.detectors import EpisodeEndDetector, make_detector
from hilstack.control.reset.steps import DONE, HOLD, WAIT, ResetStep, StepError, make_step
from hilstack.drivers.base import RobotSpec, Space

log = logging.getLogger(__name__)
logging.getLogger("transitions").setLevel(logging.WARNING)  # it logs every callback at INFO

#: how long a detector watching another robot waits for that robot's state of the same
#: instant as the reset robot's [s, wall clock]; then it sees the newest it has
LINK_SYNC_S = 0.05
#: how long a reset request waits for the state its sender saw last (``ResetEvent.state_seq``)
#: to be judged by the detectors before the episode ends as "request" [s, wall clock]
REQUEST_STATE_WAIT_S = 1.0

STATES = ["running", "episode_end", "paused", "resetting", "verifying", "resumed", "failed", "estopped"]
_RESETTING = ["episode_end", "paused", "resetting", "verifying", "resumed"]
TRANSITIONS: list[dict[str, Any]] = [
    {"trigger": "end_episode", "source": "running", "dest": "episode_end"},
    {"trigger": "pause", "source": "episode_end", "dest": "paused"},
    {"trigger": "begin", "source": "paused", "dest": "resetting"},
    {"trigger": "retry", "source": ["resetting", "verifying"], "dest": "resetting"},
    {"trigger": "skip", "source": "resetting", "dest": "resetting"},
    {"trigger": "steps_done", "source": "resetting", "dest": "verifying"},
    {"trigger": "verified", "source": "verifying", "dest": "resumed"},
    {"trigger": "resume", "source": "resumed", "dest": "running"},
    {"trigger": "fail", "source": _RESETTING, "dest": "failed"},
    {"trigger": "estop_engaged", "source": [s for s in STATES if s != "estopped"], "dest": "estopped"},
    {"trigger": "estop_released", "source": "estopped", "dest": "running"},
]


def state_diagram_mermaid() -> str:
    """The machine as a mermaid ``stateDiagram-v2`` (transitions' own graph export)."""
    from transitions.extensions import GraphMachine

    m = _Fsm()
    GraphMachine(m, states=STATES, transitions=TRANSITIONS, initial="running", auto_transitions=False,
                 graph_engine="mermaid", title="reset supervisor")
    src = m.get_graph().draw(None)
    # drop the styling lines (classDef/Class): they mark the current state, not the design
    return "\n".join(ln.rstrip() for ln in src.splitlines()
                     if ln.strip() and not ln.strip().startswith(("classDef", "Class "))) + "\n"


def pose_error(names: list[str], s: RobotState, pose: dict[str, float], verify: VerifyConfig) -> str:
    """Why ``s`` is not at ``pose`` ({x, y, yaw}: m, m, rad; world frame) within the
    tolerances of ``verify``; '' when it is. Heading error wraps at ±π."""
    v = s.state
    if not s.ok:
        return "robot reports a bad reading"
    if "x" in names and "y" in names:  # a robot without a world position (a hand) has no pose to check
        err_m = math.hypot(v[names.index("x")] - pose.get("x", 0.0), v[names.index("y")] - pose.get("y", 0.0))
        if not err_m <= verify.position_tol_m:  # NaN fails too
            return f"{err_m:.2f} m from the start (tolerance {verify.position_tol_m:g} m)"
    tol = verify.yaw_tol_rad
    if tol is not None and "cos_yaw" in names:
        yaw = math.atan2(v[names.index("sin_yaw")], v[names.index("cos_yaw")])
        e = abs(math.remainder(yaw - pose.get("yaw", 0.0), math.tau))
        if not e <= tol:
            return f"heading {e:.2f} rad off the start yaw (tolerance {tol:g} rad)"
    return ""


def _attempts(n: int) -> str:
    return f"{n} attempt{'s' if n > 1 else ''}"


class _Fsm:
    """The machine's model (kept apart from the Node so trigger names cannot clash)."""

    state: str


class RobotLink:
    """Another robot of the rig that a reset step drives (the hand's reset arm) or a
    detector watches: its state and spec, its command key and its driver node's
    liveliness, on the supervisor's session. The supervisor fails the reset when that
    driver node disappears, as it does for its own robot."""

    def __init__(self, sup: ResetSupervisor, robot: str):
        self.robot = robot
        self._sup = sup
        self._state = sup.subscribe(keys.state(sup.rig, robot), RobotState)
        self._spec = sup.subscribe(keys.spec(sup.rig, robot), SpecMsg)
        # reliable, like the supervisor's own commands: a lost one leaves the linked robot holding a period
        self._cmd = sup.publisher(keys.cmd(sup.rig, robot), Command, reliable=True)
        #: None until the driver node's token was seen, then True/False (Zenoh callback sets it)
        self.alive: bool | None = None
        tok = sup.session.liveliness().declare_subscriber(keys.alive(sup.rig, keys.driver_node(robot)),
                                                          self._on_alive, history=True)
        sup._closeables.append(SimpleNamespace(close=tok.undeclare))
        self.state_names: list[str] = []
        #: the newest state when the robot last changed under it (a reset): older states
        #: describe a world that is gone (:meth:`outdate`)
        self._outdated: RobotState | None = None
        self._answered_seq = -1
        self._answered_wall: float | None = None

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self.alive = sample.kind == zenoh.SampleKind.PUT  # one store: no work in callbacks

    def spec(self, timeout_s: float = 0.0) -> RobotSpec | None:
        m = self._spec.wait(timeout_s) if timeout_s > 0 else (self._spec.poll() or self._spec.last)
        if m is not None:
            spec = RobotSpec.from_dict(m.spec)
            self.state_names = list(spec.state.names)
            return spec
        return None

    def outdate(self) -> None:
        """The world changed (a reset put the balls back): states received so far are
        history. :meth:`state` answers None until this robot publishes again, so a detector
        never ends the new episode on a picture of the old one (an idle lockstep arm
        publishes only once per lockstep timeout)."""
        self._outdated = self._state.poll() or self._state.last

    def state(self, not_before_t_s: float | None = None, timeout_s: float = 0.0) -> RobotState | None:
        """The newest state (None before any, or none since :meth:`outdate`); with
        ``not_before_t_s``, wait up to ``timeout_s`` (wall clock) for one at least that
        recent in robot time (lockstep rigs: the state of this period)."""
        m = self._state.poll() or self._state.last
        deadline = time.monotonic() + timeout_s
        while not_before_t_s is not None and (m is None or m.t_s < not_before_t_s - 1e-9):
            left = deadline - time.monotonic()
            if left <= 0:
                break
            m = self._state.wait(left) or m
        if m is not None and m is self._outdated:
            return None
        return m

    def answer(self, state: RobotState, action: np.ndarray) -> bool:
        """Send ``action`` (robot units) answering ``state``; False when that state was answered already."""
        if state.seq <= self._answered_seq:
            return False
        self._cmd.put(Command(robot=self.robot, action=[float(x) for x in action], state_seq=state.seq,
                              source=self._sup.name))
        self._answered_seq = state.seq
        self._answered_wall = time.monotonic()
        return True

    def lost(self, state_timeout_s: float) -> str:
        if self.alive is False:
            return f"driver node {keys.driver_node(self.robot)} disappeared (liveliness lost)"
        # counted from the first command a step sent it: an idle lockstep driver node
        # publishes rarely (it waits for a command), which is not a fault
        t = self._answered_wall
        rx = self._state.last_rx_s
        if t is not None and (rx is None or rx < t) and time.monotonic() - t > state_timeout_s:
            return f"no state from {self.robot} for {time.monotonic() - t:.1f} s"
        return ""


class ResetSupervisor(Node):
    """Runs one robot's reset procedure (:class:`~hilstack.control.reset.config.ResetConfig`).

    ``serve()`` runs until stopped; ``spin_once()`` is one iteration (tests drive it).
    Times in steps and detectors are robot time (``RobotState.t_s``); ``settle_s`` too.
    """

    def __init__(
        self,
        rig: str,
        cfg: ResetConfig,
        bus: BusConfig | None = None,
        settle_s: float = 0.3,
        detectors: list[EpisodeEndDetector] | None = None,
        steps: list[ResetStep] | None = None,
        **node_kw: Any,
    ):
        super().__init__(keys.RESET_SUPERVISOR_NODE, rig, bus, **node_kw)
        self.cfg = cfg
        self.robot = cfg.robot
        self.settle_s = settle_s
        self.detectors = detectors if detectors is not None else [make_detector(d) for d in cfg.detectors]
        self.steps = steps if steps is not None else [make_step(s) for s in cfg.steps]
        self.fsm = _Fsm()
        self.machine = Machine(self.fsm, states=STATES, transitions=TRANSITIONS, initial="running",
                               auto_transitions=False, send_event=True, after_state_change=self._on_transition)
        self._state = self.subscribe(keys.state(rig, self.robot), RobotState)
        self._spec = self.subscribe(keys.spec(rig, self.robot), SpecMsg)
        self._requests = self.subscribe(keys.reset(rig, "request"), ResetEvent, latest=False, capacity=64)
        self._done = self.publisher(keys.reset(rig, "done"), ResetEvent, reliable=True)
        # reliable: a lockstep sim advances on these answers (a lost one stalls it)
        self._cmd = self.publisher(keys.cmd(rig, self.robot), Command, reliable=True)
        self._to_driver = self.publisher(keys.reset_driver(rig), ResetEvent, reliable=True)
        self._from_driver = self.subscribe(keys.reset_driver_done(rig), ResetEvent)
        # reliable: a recording splits its episodes by these (ResetTransition.state_seq); with
        # Zenoh's default (dropped when the send queue stays full 1 ms) a loaded machine lost one
        self._transitions = self.publisher(keys.reset_transition(rig), ResetTransition, reliable=True)
        #: driver node liveliness: None until first seen, then True/False (Zenoh callback sets it)
        self.driver_alive: bool | None = None
        self._alive_sub = self.session.liveliness().declare_subscriber(
            keys.alive(rig, keys.driver_node(self.robot)), self._on_driver_alive, history=True
        )
        self._closeables.append(SimpleNamespace(close=self._alive_sub.undeclare))
        #: other robots of the rig that steps drive or detectors watch (robot -> link)
        self.links: dict[str, RobotLink] = {}
        self._linked_bound: set[int] = set()  # indices of detectors bound to another robot's names
        for d in self.detectors:
            if d.robot:
                self.robot_link(d.robot)
        #: the robot's spec (typed, from its driver node's SpecMsg); None before it arrived
        self.spec: RobotSpec | None = None
        self.state_names: list[str] = []
        #: the robot's action space (from its spec): normalized actions of the steps → units
        self.action_space: Space | None = None
        self._zero: np.ndarray | None = None
        #: what the operator was told on the last failure
        self.last_failure = ""
        self.history: list[ResetTransition] = []
        self.stats = {"requested": 0, "completed": 0, "failed": 0}
        #: what the steps did (``fixture_recoveries``, ``self_righted``; StepContext.count)
        #: and the optional steps skipped (``skipped_<kind>``)
        self.counts: dict[str, int] = {}
        #: episodes each detector ended (its name: timeout, arena, tipped, drop)
        self.ended_by: dict[str, int] = {}
        self.durations_s: list[float] = []
        self._reset_t0_wall = 0.0
        self._pending: ResetEvent | None = None
        self._pose: dict[str, float] = dict(cfg.start_pose)
        self._reason = ""
        self._episode = -1
        #: sequence number of the first state of the running episode (a request whose
        #: requester's newest state is older asks to end an episode already over)
        self._episode_first_seq = -1
        #: the newest state of the episode that ended last (ResetTransition.state_seq)
        self._end_seq = -1
        #: the episode counter when the reset was verified (its states are answered while
        #: the driver node starts the next one, the next one's are not)
        self._verified_episode = -1
        self._last: RobotState | None = None
        self._last_rx_wall = time.monotonic()
        self._i = 0
        self._attempt = 0
        self._verify_attempt = 0
        self._t0_s = 0.0
        self._answer_wait_s = 0.0
        #: the running step returned WAIT on the newest state (it waits for the driver node)
        self._step_waits = False
        #: the driver node's last answer named its first state after the jump (-1: none)
        self._jump_seq = -1

    # ------------------------------------------------------------------ plumbing
    @property
    def state(self) -> str:
        return self.fsm.state

    def _on_driver_alive(self, sample: zenoh.Sample) -> None:
        self.driver_alive = sample.kind == zenoh.SampleKind.PUT  # one store: no work in callbacks

    def _on_transition(self, ev: EventData) -> None:
        step = self.steps[self._i].name if self.state in ("resetting",) and self._i < len(self.steps) else ""
        msg = ResetTransition(
            robot=self.robot, trigger=ev.event.name, source=ev.transition.source, dest=ev.transition.dest,
            reason=self._reason, step=step, attempt=self._attempt if step else 0,
            episode=self._last.episode if self._last else 0, detail=str(ev.kwargs.get("detail", "")),
            state_seq=self._end_seq if ev.event.name == "end_episode" else (self._last.seq if self._last else -1),
        )
        self.history.append(self._transitions.put(msg))
        (log.error if msg.dest == "failed" else log.info)(
            "reset %s: %s → %s%s", self.robot, msg.source, msg.dest, f" ({msg.detail})" if msg.detail else ""
        )

    def _bind_spec(self, spec: dict[str, Any]) -> None:
        typed = RobotSpec.from_dict(spec)
        self.spec = typed
        self.state_names = list(typed.state.names)
        self.action_space = typed.action
        # what "hold" sends: the safe action (legs stopped); for a robot that stops by holding
        # its position (the hand: safe_action None) the command it holds now (RobotState.action),
        # not zeros, which would be mid-range joint targets
        self._zero = None if typed.safe_action is None else np.clip(typed.safe_action, typed.action.low,
                                                                    typed.action.high)
        for d in self.detectors:
            if not d.robot:
                d.bind(self.state_names)

    def _bind_linked_detectors(self, timeout_s: float) -> None:
        for i, d in enumerate(self.detectors):
            if d.robot and i not in self._linked_bound:
                link = self.links[d.robot]
                if link.spec(timeout_s) is None:
                    raise TimeoutError(f"reset supervisor: no spec from {keys.spec(self.rig, d.robot)} within "
                                       f"{timeout_s} s (the {d.name} detector watches {d.robot})")
                d.bind(link.state_names)
                self._linked_bound.add(i)

    def wait_ready(self, timeout_s: float = 20.0) -> None:
        """Wait for the robot's spec (its driver node publishes it)."""
        m = self._spec.wait(timeout_s)
        if m is None:
            raise TimeoutError(f"reset supervisor: no spec from {keys.spec(self.rig, self.robot)} within {timeout_s} s")
        self._bind_spec(m.spec)
        self._bind_linked_detectors(timeout_s)

    def _send(self, s: RobotState, action_norm: np.ndarray | None) -> None:
        if action_norm is not None:
            a = self.action_space.denormalize(action_norm)
        elif self._zero is not None:
            a = self._zero
        elif s.action:
            a = np.asarray(s.action, dtype=np.float64)  # hold what it holds
        else:
            return  # nothing held yet: the driver node holds the measured position itself
        self._cmd.put(Command(robot=self.robot, action=a.tolist(), state_seq=s.seq, source=self.name))

    # StepContext
    def robot_link(self, robot: str) -> RobotLink:
        """The link to another robot of the rig (created on first use)."""
        if robot not in self.links:
            self.links[robot] = RobotLink(self, robot)
        return self.links[robot]

    def request_driver(self, phase: ResetPhase, pose: dict[str, float]) -> None:
        self._from_driver.poll()  # forget earlier answers
        self._jump_seq = -1
        self._to_driver.put(ResetEvent(robot=self.robot, phase=phase, pose=dict(pose)))

    def driver_answer(self) -> ResetEvent | None:
        m = self._from_driver.poll()
        if m is None or m.robot != self.robot:
            return None
        self._jump_seq = m.state_seq  # the first state after a teleport or a new episode (-1: unknown)
        return m

    def count(self, what: str, n: int = 1) -> None:
        self.counts[what] = self.counts.get(what, 0) + n

    def report(self) -> dict[str, Any]:
        """The ``resets`` section of a demo's report.json: requests, completed and failed
        resets, their wall-clock duration [s], what the steps did and why episodes ended.
        ``fixture_recoveries`` is also ``operator_interventions``: on a real rig a person
        does what the emulator's lab fixture does."""
        d = self.durations_s
        fixture = self.counts.get("fixture_recoveries", 0)
        return {
            **self.stats,
            "mean_duration_s": float(np.mean(d)) if d else 0.0,
            "max_duration_s": float(np.max(d)) if d else 0.0,
            "fixture_recoveries": fixture,
            "operator_interventions": fixture,
            "self_righted": self.counts.get("self_righted", 0),
            **{k: v for k, v in sorted(self.counts.items()) if k not in ("fixture_recoveries", "self_righted")},
            "episode_ends": dict(sorted(self.ended_by.items())),
        }

    # ------------------------------------------------------------------ loop
    def serve(self, ready_timeout_s: float = 60.0) -> None:
        """Run until ``stop_event`` (signal or close)."""
        self.wait_ready(ready_timeout_s)
        while not self.stop_event.is_set():
            try:
                self.spin_once()
            except Exception as e:
                # a bug in a step must not leave a robot half-way through a reset
                log.exception("reset supervisor crashed")
                if self.state in _RESETTING:
                    self._fail(f"reset supervisor error: {type(e).__name__}: {e}")
                raise

    def spin_once(self, wait_s: float = 0.05) -> None:
        if self.action_space is None:
            m = self._spec.poll()
            if m is not None:
                self._bind_spec(m.spec)
        s = self._state.wait(wait_s)
        if s is not None and self._last is not None and s.seq == self._last.seq:
            # a lockstep driver node sending its state again while it waits for an answer: the
            # same instant, judged and answered already (a step's update must not run twice on it)
            self._last_rx_wall = time.monotonic()
            s = None
        elif s is not None:
            self._last, self._last_rx_wall = s, time.monotonic()
        self._take_requests()
        # the e-stop wins over everything
        if self.estop.engaged:
            if self.state != "estopped":
                self._abort_estop()
            return
        if self.state == "estopped":
            self._fire("estop_released")
            return
        if self.state == "failed" or self.action_space is None:
            return
        if self.state == "running":
            self._running(s)
        if self.state == "episode_end" and self._pending is not None:
            self._fire("pause")
        if self.state == "paused" and self._last is not None:
            self._i = self._verify_attempt = 0
            self._begin_step(self._last, first=True)
            # a lockstep rig waits for an answer to the state the controller left unanswered
            s = s or self._last
        if self.state in ("paused", "resetting", "verifying", "resumed"):
            why = self._lost()
            if why:
                self._fail(why)
                return
        if self.state == "resumed" and self._last is not None:
            # the driver node's answer may follow the new episode's first state, after which
            # no state comes until the controller answers it: look for the answer every spin
            self._resumed(s or self._last, fresh=s is not None)
            return
        if self.state == "resetting" and s is None and self._step_waits and self._last is not None:
            s = self._last  # its state stays unanswered: the driver node's answer is what comes next
        if s is None:
            return
        if self.state == "resetting":
            self._resetting(s)
        elif self.state == "verifying":
            self._verifying(s)

    def _take_requests(self) -> None:
        for _, payload in self._requests.drain():
            try:
                m = decode(payload, ResetEvent)
            except MalformedMessage:
                continue
            if m.robot != self.robot or m.phase != ResetPhase.REQUEST:
                continue
            self.stats["requested"] += 1
            if self.state in ("failed", "estopped"):
                why = self.last_failure if self.state == "failed" else "e-stop engaged"
                self._answer(ResetPhase.FAILED, f"rig stopped: {why}; release the e-stop after fixing it")
                continue
            if (self.state == "running" and self._pending is None and 0 <= m.state_seq < self._episode_first_seq):
                # the requester's newest state is older than the running episode: the episode it
                # asks to end was ended (a detector) and reset already; this one has not begun
                # (a lockstep rig waits for the requester's answer to its first state)
                self._answer(ResetPhase.DONE, episode=self._episode)
                continue
            if self._pending is None and self.state in ("running", "episode_end"):
                self._reset_t0_wall = time.monotonic()
                self._pose = {**self.cfg.start_pose, **m.pose}
            # a repeated request during a reset (a controller that asked again) is answered
            # with the reset under way; the pose being driven to does not change mid-reset
            self._pending = m

    def _answer(self, phase: ResetPhase, detail: str = "", episode: int | None = None) -> None:
        ep = episode if episode is not None else (self._last.episode if self._last else 0)
        if phase == ResetPhase.FAILED:  # counted before the answer goes out: whoever acts on it sees the count
            self.stats["failed"] += 1
        self._done.put(ResetEvent(robot=self.robot, phase=phase, pose=dict(self._pose), episode=ep, detail=detail))
        self._pending = None

    def _running(self, s: RobotState | None) -> None:
        if s is not None:
            if s.episode != self._episode:
                self._start_episode(s)
            # nothing drives the robot when it is not active and running: no episode is running
            if s.active and s.stopped_reason == StoppedReason.RUNNING:
                for d in self.detectors:
                    ds = self._detector_state(d, s)
                    if ds is None:
                        continue
                    why = d(ds)
                    if why:
                        self.ended_by[d.name] = self.ended_by.get(d.name, 0) + 1
                        self._reason = why
                        self._end_seq = s.seq
                        self._fire("end_episode", detail=why)
                        return
        if self._pending is not None:
            newest = self._last.seq if self._last else -1
            if self._pending.state_seq > newest and time.monotonic() - self._reset_t0_wall < REQUEST_STATE_WAIT_S:
                # the requester's last state is on its way: judged first, so an episode a detector
                # ended is said to be ended by it even when the request came first (a lockstep
                # controller judges the same detectors and asks at once)
                return
            self._reason = "request"
            # the episode's last state: the requester's newest (it may be ahead of ours)
            self._end_seq = max(newest, self._pending.state_seq)
            self._fire("end_episode")

    def _start_episode(self, s: RobotState) -> None:
        """``s`` is the first state of a new episode: the detectors start on it."""
        self._episode = s.episode
        self._episode_first_seq = s.seq
        for d in self.detectors:
            ds = self._detector_state(d, s)
            if ds is not None:
                d.start(ds)

    def _detector_state(self, d: EpisodeEndDetector, s: RobotState) -> RobotState | None:
        """What ``d`` watches: the robot's state, or the newest state of the robot it names
        (None until that robot's spec and a state arrived)."""
        if not d.robot:
            return s
        if self.detectors.index(d) not in self._linked_bound:
            try:
                self._bind_linked_detectors(0.0)
            except TimeoutError:
                return None
        # the other robot's state of the same instant (lockstep: it follows a moment later)
        return self.links[d.robot].state(not_before_t_s=s.t_s, timeout_s=LINK_SYNC_S)

    def _begin_step(self, s: RobotState, first: bool = False, retry_detail: str = "") -> None:
        self._t0_s = s.t_s
        step = self.steps[self._i]
        if first:
            self._attempt = 1
            self._fire("begin")
        if retry_detail:
            self._fire("retry", detail=retry_detail)
        try:
            step.start(self, s, self._pose)
        except StepError as e:
            self._attempt_failed(s, str(e))

    def _abort_step(self) -> None:
        if self.state == "resetting" and self._i < len(self.steps):
            try:
                self.steps[self._i].abort()
            except Exception as e:  # an abort must not stop the supervisor from stopping the rig
                log.error("reset step %s: abort failed: %s", self.steps[self._i].name, e)

    def _attempt_failed(self, s: RobotState, detail: str) -> None:
        step = self.steps[self._i]
        self._abort_step()
        if self._attempt <= step.cfg.retries:
            self._attempt += 1
            self._begin_step(s, retry_detail=f"{detail}; attempt {self._attempt} of {step.cfg.retries + 1}")
        elif step.cfg.optional and self._i + 1 < len(self.steps):
            self.count(f"skipped_{step.name}")
            self._fire("skip", detail=f"optional step {step.name} gave up after {_attempts(step.cfg.retries + 1)}: "
                                      f"{detail}; next: {self.steps[self._i + 1].name}")
            self._i += 1
            self._attempt = 1
            self._begin_step(s)
        else:
            self._fail(f"reset step {step.name} failed after {_attempts(step.cfg.retries + 1)}: {detail}")

    def _resetting(self, s: RobotState) -> None:
        step = self.steps[self._i]
        if s.t_s - self._t0_s > step.cfg.timeout_s:
            self._send(s, None)
            self._attempt_failed(s, f"timed out after {step.cfg.timeout_s:g} s")
            return
        self._step_waits = False
        try:
            r = step.update(self, s)
        except StepError as e:
            self._send(s, None)
            if e.from_start and self._i > 0 and self._verify_attempt < self.cfg.verify.retries:
                self._abort_step()
                self._verify_attempt += 1
                self._i = 0
                self._attempt = 1
                self._begin_step(s, retry_detail=f"{e}; the procedure again from {self.steps[0].name}")
                return
            self._attempt_failed(s, str(e))
            return
        if isinstance(r, str) and r == WAIT:
            self._step_waits = True
        elif isinstance(r, str):
            if r == DONE:
                # the step's work is done (a teleport answered): go on from the state after it,
                # which the answer names. Verifying timed from the one before (the sim's clock
                # restarts at a teleport) settled 1.9 s instead of 0.3 s
                s = self._state_after_jump(self._newest(s))
            self._send(s, None)
            if r == DONE:
                self._i += 1
                if self._i < len(self.steps):
                    self._attempt = 1
                    self._begin_step(s)
                else:
                    self._t0_s = s.t_s
                    self._fire("steps_done")
            elif r != HOLD:
                raise ValueError(f"reset step {step.name} returned {r!r}")
        else:
            self._send(s, r)

    def check_pose(self, s: RobotState) -> str:
        """Why the reset is not done ('' when it is): the robot at the start pose (robots
        with ``x``, ``y`` channels), then each step's own check (the hand: both balls in
        the palm, :meth:`ResetStep.verify`)."""
        if "x" in self.state_names and "y" in self.state_names:
            why = pose_error(self.state_names, s, self._pose, self.cfg.verify)
            if why:
                return why
        elif not s.ok:
            return "robot reports a bad reading"
        for step in self.steps:
            why = step.verify(self, s)
            if why:
                return why
        return ""

    def _state_after_jump(self, s: RobotState) -> RobotState:
        """``s``, or the driver node's first state after the teleport it answered (the answer's
        ``state_seq``) when ``s`` is older. That state was sent before the answer, but the two
        come through different subscriptions, each with its own receiving thread, so on a loaded
        machine the answer can be taken first: wait for the state (at most
        ``REQUEST_STATE_WAIT_S``; then go on from ``s``, as before the answer named it). Each
        wait is counted in the report's ``teleport_answer_before_its_state``."""
        want, self._jump_seq = self._jump_seq, -1
        if s.seq < want:  # the race this waits out, counted in the resets' report
            self.count("teleport_answer_before_its_state")
        deadline = time.monotonic() + REQUEST_STATE_WAIT_S
        while s.seq < want and (left := deadline - time.monotonic()) > 0:
            m = self._state.wait(left)
            if m is not None and m.seq > s.seq:
                self._last, self._last_rx_wall = m, time.monotonic()
                s = m
        if s.seq < want:
            self.count("state_after_teleport_late")
        return s

    def _newest(self, s: RobotState) -> RobotState:
        """``s`` or a newer state of the robot already received (taken)."""
        m = self._state.poll()
        if m is not None and m.seq > s.seq:
            self._last, self._last_rx_wall = m, time.monotonic()
            return m
        return s

    def _verifying(self, s: RobotState) -> None:
        if s.t_s - self._t0_s < self.settle_s:
            self._send(s, None)
            return
        why = self.check_pose(s)
        if not why:
            self._fire("verified")
            for link in self.links.values():
                link.outdate()
            # this state stays unanswered: a lockstep driver node, waiting for its answer, serves
            # the request and starts the episode on it (with a hold sent too, the sim stepped a
            # period first or not, depending on which message came first)
            self.request_driver(ResetPhase.EPISODE, self._pose)
            self._verified_episode = s.episode
            self._answer_wait_s = time.monotonic()
            return
        self._send(s, None)
        if self._verify_attempt < self.cfg.verify.retries:
            self._verify_attempt += 1
            self._i = 0
            self._attempt = 1
            self._begin_step(s, retry_detail=f"verification failed: {why}")
        else:
            self._fail(f"reset of {self.robot} failed verification: {why}")

    def _resumed(self, s: RobotState, fresh: bool = True) -> None:
        ans = self.driver_answer()
        if ans is None:
            if fresh and s.episode <= self._verified_episode:  # the new episode's states are its controller's
                self._send(s, None)  # lockstep: keep the sim stepping until the driver answers
            if time.monotonic() - self._answer_wait_s > self.cfg.state_timeout_s:
                self._fail(f"driver node {keys.driver_node(self.robot)} did not start the new episode")
            return
        if ans.phase != ResetPhase.DONE:
            self._fail(f"driver node refused the new episode: {ans.phase} {ans.detail}")
            return
        self.stats["completed"] += 1
        self.durations_s.append(time.monotonic() - self._reset_t0_wall)
        self._reason = ""
        # the new episode's first state came before the answer: the episode starts on it (a
        # request that arrives next, about the episode before, is then known to be answered)
        s = self._newest(s)
        if s.episode >= ans.episode and s.episode != self._episode:
            self._start_episode(s)
        self._fire("resume")
        if self._pending is not None:
            self._answer(ResetPhase.DONE, episode=ans.episode)

    def _lost(self) -> str:
        if self.driver_alive is False:
            return f"driver node {keys.driver_node(self.robot)} disappeared (liveliness lost)"
        # counted from the request at the earliest: a lockstep robot publishes nothing while
        # its controller thinks (trains a model) before asking for the reset
        age = time.monotonic() - max(self._last_rx_wall, self._reset_t0_wall)
        if age > self.cfg.state_timeout_s:
            return f"no state from {self.robot} for {age:.1f} s"
        for link in self.links.values():  # the robots the steps drive (the hand's reset arm)
            why = link.lost(self.cfg.state_timeout_s)
            if why:
                return why
        return ""

    def _fail(self, detail: str) -> None:
        self._abort_step()
        self.last_failure = detail
        self._fire("fail", detail=detail)
        log.error("reset supervisor: %s; engaging the e-stop of rig %s", detail, self.rig)
        # stop the rig first, then tell the controller (it may act on the answer at once)
        command_estop(self, True, reason=f"reset failed: {detail}", timeout_s=1.0, settle_s=0.0)
        if self._pending is not None:
            self._answer(ResetPhase.FAILED, detail)
        else:
            self.stats["failed"] += 1

    def _abort_estop(self) -> None:
        m = self.estop.latched
        detail = f"e-stop engaged ({m.source or '?'}: {m.reason})" if m else "e-stop engaged"
        was = self.state
        self._abort_step()
        self._fire("estop_engaged", detail=detail)
        if self._pending is not None and was != "failed":
            self._answer(ResetPhase.FAILED, f"{detail} during the reset")

    def _fire(self, trigger: str, **kw: Any) -> None:
        """Fire a machine trigger (``MachineError`` if the current state does not allow it)."""
        self.fsm.trigger(trigger, **kw)
