"""The driver bridge node: any contract robot on the bus.

Each period: take the e-stop commands (latched; each acknowledged on
``hil/<rig>/estop/ack``), take the newest command, apply it or hold the safe action,
read, publish the state. Safety is local: the robot is stopped when commands go stale
(``watchdog_periods`` control periods without a new command, default 3), when an
e-stop arrives, when a command is invalid, or when its reading is not ok (a stale or
non-finite input: the node then refuses commands until ``resume_ok_readings``
consecutive readings are ok again, default 3), whatever other nodes do. At start the
node asks the rig's other nodes for a latched e-stop (``estop_sync_s``) and, when one
is engaged, starts stopped and refuses commands until a release (bus/estop.py).

One loop, ``step()`` (read → update → write); the node's
:class:`~hilstack.drivers.base.Pacing` (the driver's, or ``LOCKSTEP`` for a sim in the rig's
``pace: lockstep``) orders and paces it, and the spec the node publishes carries it
(docs/platform.md, "Time model"). ``WALL_CLOCK`` (real, emulated) and ``STEPPED`` (a sim in
``pace: realtime``) run on the wall clock. In ``LOCKSTEP`` the simulation advances one
period when the command answering the last published state arrives, so a whole rig
runs faster than real time with the same nodes; staleness is then counted in
published states without an answer.
"""

from __future__ import annotations

import logging
import time
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.schemas import (
    NO_DEVICE_CLOCK,
    Command,
    EStop,
    EStopAck,
    Image,
    MalformedMessage,
    ResetEvent,
    ResetPhase,
    RobotState,
    SpecMsg,
    StoppedReason,
    decode,
)
from hilstack.configs.schema import BusConfig
from hilstack.drivers.base import CommandError, Driver, LinkError, Pacing, RobotSpec, sim_controls

log = logging.getLogger(__name__)

#: upper bound of ``resume_ok_readings`` (a node that never resumes is a config error)
MAX_RESUME_OK_READINGS = 100
#: upper bound of ``supervisor_wait_s`` [s]: a supervisor that is not up a minute after the
#: request is not starting; the requester waits for the answer meanwhile
MAX_SUPERVISOR_WAIT_S = 60.0


@dataclass
class BridgeStats:
    steps: int = 0
    commands_applied: int = 0
    commands_rejected: int = 0
    stale_stops: int = 0
    estops: int = 0
    #: commands ignored because the e-stop is engaged
    estop_refused: int = 0
    #: times the robot was stopped because its reading was not ok
    unhealthy_stops: int = 0
    #: commands refused because the robot's reading was not ok (or not yet ok again)
    unhealthy_refused: int = 0
    #: why the last not-ok reading was not ok: its flags that were set, e.g. "stale_pose"
    last_unhealthy: str = ""
    lockstep_timeouts: int = 0
    last_reject: str = ""


class DriverNode(Node):
    def __init__(
        self,
        driver: Driver,
        rig: str,
        robot: str,
        bus: BusConfig | None = None,
        watchdog_periods: float = 3.0,
        pace: str = "realtime",
        lockstep_timeout_s: float = 5.0,
        estop_sync_s: float = 1.0,
        resume_ok_readings: int = 3,
        supervisor_wait_s: float = 5.0,
        **node_kw,
    ):
        if not (isinstance(resume_ok_readings, int) and 1 <= resume_ok_readings <= MAX_RESUME_OK_READINGS):
            raise ValueError(f"resume_ok_readings must be an integer in [1, {MAX_RESUME_OK_READINGS}], "
                             f"got {resume_ok_readings!r}")
        if not (isinstance(supervisor_wait_s, int | float) and 0 < supervisor_wait_s <= MAX_SUPERVISOR_WAIT_S):
            raise ValueError(f"supervisor_wait_s must be a number of seconds in (0, {MAX_SUPERVISOR_WAIT_S:g}], "
                             f"got {supervisor_wait_s!r}")
        try:  # before the session opens
            pacing = driver.pacing_at(pace)
        except ValueError:
            raise ValueError(f"pace {pace!r} needs a sim backend; {robot} is {driver.backend}") from None
        access = bus is not None and bus.access is not None
        if driver.backend in ("real", "emulated") and not access:
            # who may command and release a real robot, or one behind a device emulator, is not
            # left open (docs/platform.md, "Who may command and who may release")
            from hilstack.bus.access import AccessError

            what = "real hardware" if driver.backend == "real" else "emulated hardware"
            raise AccessError(f"rig {rig}: robot {robot} is {what}; its rig needs a bus.access section "
                              "(who may command and release it; docs/platform.md)")
        if "session" not in node_kw:  # on an access rig the driver node is the rig's router (bus/session.py)
            node_kw.update(server=access, robots=[robot])
        node_kw.setdefault("unique", True)  # one driver node per robot and rig (bus/node.py: NodeConflict)
        super().__init__(keys.driver_node(robot), rig, bus, **node_kw)
        self.driver = driver
        self.robot = robot
        #: the time model this node runs its robot in (the driver's, lockstep for a sim in
        #: ``pace: lockstep``); the spec it publishes carries it
        self.pacing = pacing
        self.watchdog_s = watchdog_periods * driver.spec.period_s
        # a sim that follows another robot's clock (the hand's reset arm, whose world the
        # hand's node advances) must not hold its own states back while nobody commands it
        follow = driver.follower if pacing is Pacing.FOLLOWER else None
        self.lockstep_timeout_s = lockstep_timeout_s if follow is None else min(follow.command_wait_s,
                                                                                lockstep_timeout_s)
        #: how long a starting node asks its peers for a latched e-stop [s]
        self.estop_sync_s = estop_sync_s
        self.stats = BridgeStats()
        self.estopped = False
        self.stopped_reason = StoppedReason.WAITING
        #: consecutive ok readings needed before commands are taken again after a not-ok one
        self.resume_ok_readings = resume_ok_readings
        #: the newest reading was not ok, or fewer than resume_ok_readings ok ones followed it
        self.unhealthy = False
        self._ok_run = 0
        # lockstep: the controller answers every state, a lost one stalls the loop
        self._state_pub = self.publisher(keys.state(rig, robot), RobotState, reliable=pacing.answered)
        self._spec_pub = self.publisher(keys.spec(rig, robot), SpecMsg, reliable=True)  # rare; every reader needs it
        self._cmd = self.subscribe(keys.cmd(rig, robot), Command)
        self._estop_ack = self.publisher(keys.estop_ack(rig), EStopAck)
        self._reset_req = self.subscribe(keys.reset(rig, "request"), ResetEvent)
        self._reset_done = self.publisher(keys.reset(rig, "done"), ResetEvent, reliable=True)
        #: a camera image a driver returns in ``extras["image"]`` (H×W×3 uint8), on keys.image(rig, robot);
        #: ``extras["image_encoded"] = (encoding, bytes)`` (jpeg/png) is sent instead of the raw pixels
        self._image_pub = self.publisher(keys.image(rig, robot), Image)
        # the reset supervisor (control/reset) drives resets when it is alive: the node then
        # leaves controllers' requests to it and serves its teleport / new-episode requests
        self._sup_req = self.subscribe(keys.reset_driver(rig), ResetEvent, latest=False, capacity=16)
        self._sup_done = self.publisher(keys.reset_driver_done(rig), ResetEvent, reliable=True)
        self._supervisor = self.watch_alive(keys.RESET_SUPERVISOR_NODE)
        #: how long a supervised request (``ResetEvent.supervised``) waits for the supervisor's
        #: token before it is answered ``failed`` [s, wall clock]
        self.supervisor_wait_s = float(supervisor_wait_s)
        #: the supervised request waiting for the supervisor's token, and until when (monotonic)
        self._supervised_req: tuple[ResetEvent, float] | None = None
        self.episode = 0
        self._last_cmd_t: float | None = None  # node clock when the last command was applied
        self._last_state: RobotState | None = None
        self._spec_t = 0.0

    # ------------------------------------------------------------------ pieces
    def _clock(self) -> float:
        # lockstep staleness is measured in robot time, realtime in wall time
        return self.driver.now() if self.pacing.answered else time.monotonic()

    def _engage(self, m: EStop) -> None:
        if self.estopped:
            return
        self.estopped = True
        self.stats.estops += 1
        log.warning("e-stop from %s: %s", m.source or "?", m.reason)
        self.driver.stop()
        self.driver.deactivate()
        self.stopped_reason = StoppedReason.ESTOP

    def _release(self, m: EStop) -> str:
        """Re-activate holding the measured state; commands must come anew. '' or why not."""
        if not self.estopped:
            return ""
        try:
            self.driver.activate()
        except Exception as e:  # the link may be down: stay stopped, say why in the ack
            log.error("e-stop release from %s failed: %s", m.source or "?", e)
            return f"release failed: {e}"
        log.warning("e-stop released by %s (node %s)", m.sender or "?", m.source or "?")
        self.estopped = False
        self._last_cmd_t = None
        self.stopped_reason = StoppedReason.WAITING
        return ""

    def _handle_estop(self) -> None:
        """Apply every e-stop command heard since the last period and acknowledge each."""
        for m, why in self.estop.take_refused():
            log.warning("e-stop release from %s (node %s) refused: %s", m.sender or "?", m.source or "?", why)
            self._estop_ack.put(EStopAck(node=self.name, robot=self.robot, engaged=self.estopped, estop_id=m.id,
                                         detail=f"release refused: {why}"))
        for m in self.estop.take():
            detail = ""
            if m.engaged:
                self._engage(m)
            else:
                detail = self._release(m)
            self._estop_ack.put(
                EStopAck(node=self.name, robot=self.robot, engaged=self.estopped, estop_id=m.id, detail=detail,
                         device_confirmed=self.estopped and self.driver.stop_confirmed())
            )

    @property
    def last_state(self) -> RobotState | None:
        """The newest state this node published (None before the first): what ``hil up``'s
        status line shows, read from another thread (one reference, replaced whole)."""
        return self._last_state

    @property
    def supervisor_alive(self) -> bool:
        return bool(self._supervisor.alive)

    def _handle_supervisor(self, answers: list) -> bool:
        """Serve the reset supervisor: ``teleport`` (sim backends: put the robot at the pose)
        and ``episode`` (its reset was verified: a new episode starts); the answers go to
        ``answers``. True when the state jumped (teleport or new episode): lockstep publishes
        it at once."""
        jumped = False
        for _, payload in self._sup_req.drain():
            try:
                m = decode(payload, ResetEvent)
            except MalformedMessage:
                continue
            if m.robot != self.robot:
                continue
            reset = sim.reset if (sim := sim_controls(self.driver)) is not None else None
            if self.estopped:
                ans = ResetEvent(robot=self.robot, phase=ResetPhase.FAILED, detail="e-stop engaged")
            elif m.phase == ResetPhase.TELEPORT and reset is not None:
                self.driver.stop()
                try:
                    reset(**m.pose)
                except (TypeError, ValueError) as e:  # a pose this robot cannot take: say so, keep serving
                    ans = ResetEvent(robot=self.robot, phase=ResetPhase.FAILED, detail=f"teleport refused: {e}")
                else:
                    self._last_cmd_t = None
                    self.stopped_reason = StoppedReason.WAITING
                    jumped = True
                    ans = ResetEvent(robot=self.robot, phase=ResetPhase.DONE, pose=m.pose)
            elif m.phase == ResetPhase.TELEPORT:
                ans = ResetEvent(robot=self.robot, phase=ResetPhase.UNSUPPORTED,
                                 detail=f"{self.driver.backend} backend cannot teleport")
            elif m.phase == ResetPhase.EPISODE:
                self.episode += 1
                jumped = True
                ans = ResetEvent(robot=self.robot, phase=ResetPhase.DONE, pose=m.pose)
            else:
                ans = ResetEvent(robot=self.robot, phase=ResetPhase.FAILED, detail=f"unknown phase {m.phase!r}")
            ans.episode = self.episode
            ans.detail = ans.detail or m.detail
            answers.append((self._sup_done, ans))
        return jumped

    def _handle_reset(self, publish_first: bool = False) -> bool:
        """Serve a reset request; True when the robot was reset (a new episode starts).
        The spec goes out again at every new episode, so a recording that starts with an
        episode has it however short it is (the 1 Hz / 50-step repeat may not fall inside).
        ``publish_first`` (lockstep): the state after the reset goes out before the answers,
        so whoever acts on an answer has that state already (the supervisor times its
        verification from it; with the answer first it sometimes took the state before a
        teleport, whose clock had not restarted, and settled 1.4 s instead of 0.4 s)."""
        answers: list = []
        new_episode = self._serve_reset(answers)
        if new_episode:
            self.publish_spec()
            if publish_first:
                self.publish_state()
            # the first state after the jump: the one just sent, or the next one. The answer
            # names it: the receiver's subscriptions each run on their own thread, so the
            # answer can be taken before that state although it was sent after it
            first = self._state_pub.seq + (0 if publish_first else 1)
            for _, msg in answers:
                if msg.phase == ResetPhase.DONE:
                    msg.state_seq = first
        for pub, msg in answers:
            pub.put(msg)
        return new_episode

    def _serve_reset(self, answers: list) -> bool:
        jumped = self._handle_supervisor(answers)
        m = self._reset_req.poll()
        if m is not None and m.robot == self.robot and m.supervised:
            # its sender expects the rig's reset supervisor: never served here, also while this
            # node has not seen the supervisor's token yet (at start-up the token can reach it
            # after the first request: served here and by the supervisor, two resets)
            self._supervised_req = (m, time.monotonic() + self.supervisor_wait_s)
            m = None
        self._await_supervisor(answers)
        if m is None or m.robot != self.robot or self.supervisor_alive:
            return jumped
        reset = sim.reset if (sim := sim_controls(self.driver)) is not None else None
        self.driver.stop()
        if reset is None or self.estopped:
            why = "e-stop engaged" if self.estopped else (
                f"{self.driver.backend} backend cannot reset itself and no reset supervisor is running "
                "(add a reset: section to the rig config, docs/reset.md)"
            )
            answers.append((self._reset_done, ResetEvent(robot=self.robot, phase=ResetPhase.UNSUPPORTED,
                                                         episode=self.episode, detail=why)))
            return jumped
        try:
            reset(**m.pose)
        except TypeError as e:
            answers.append((self._reset_done, ResetEvent(robot=self.robot, phase=ResetPhase.FAILED,
                                                         episode=self.episode, detail=str(e))))
            return jumped
        self.episode += 1
        self._last_cmd_t = None
        self.stopped_reason = StoppedReason.WAITING
        answers.append((self._reset_done, ResetEvent(robot=self.robot, phase=ResetPhase.DONE, episode=self.episode,
                                                     pose=m.pose)))
        return True

    def _await_supervisor(self, answers: list) -> None:
        """A supervised request waits (``supervisor_wait_s``, without holding up the loop) for
        the supervisor's token: once seen the request is the supervisor's; none in time is a
        ``failed`` answer saying so."""
        if self._supervised_req is None:
            return
        if self.supervisor_alive:
            self._supervised_req = None  # the supervisor serves it
            return
        if time.monotonic() < self._supervised_req[1]:
            return
        self._supervised_req = None
        why = (f"the reset request expects the rig's reset supervisor and none was alive on rig {self.rig} "
               f"within {self.supervisor_wait_s:g} s (start it with the rig's reset: section, docs/reset.md)")
        log.error("%s: %s", self.robot, why)
        answers.append((self._reset_done, ResetEvent(robot=self.robot, phase=ResetPhase.FAILED,
                                                     episode=self.episode, detail=why)))

    def _apply(self, cmd: Command | None) -> None:
        if self.estopped:
            if cmd is not None:
                self.stats.estop_refused += 1
            return
        if self.unhealthy:  # held safe by _assess_reading; the command acts on a state not ok
            if cmd is not None:
                self.stats.unhealthy_refused += 1
            return
        if cmd is not None:
            try:
                self.driver.write(np.asarray(cmd.action, dtype=np.float64))
            except CommandError as e:
                self.stats.commands_rejected += 1
                self.stats.last_reject = str(e)
                log.warning("rejected command: %s", e)
                self.driver.stop()
                self.stopped_reason = StoppedReason.BAD_COMMAND
                return
            self.stats.commands_applied += 1
            self._last_cmd_t = self._clock()
            self.stopped_reason = StoppedReason.RUNNING
            return
        stale = self._last_cmd_t is None or self._clock() - self._last_cmd_t > self.watchdog_s
        if stale and self.stopped_reason is StoppedReason.RUNNING:
            self.stats.stale_stops += 1
            self.driver.stop()
            self.stopped_reason = StoppedReason.STALE

    def _assess_reading(self, ok: bool, flags: dict[str, bool]) -> None:
        """Control on unhealthy states: a reading that is not ok (a stale or non-finite
        input, ``Observation.ok``, or ``health().ok`` False) stops the robot at once by the
        same path as the watchdog and the e-stop (``stop()``: the safe action, or holding the
        held target for a position-controlled robot) and makes ``_apply`` refuse commands
        (counted in ``unhealthy_refused``). Commands are taken again after
        ``resume_ok_readings`` consecutive ok readings; the robot holds until the next one."""
        if ok:
            self._ok_run += 1
            if self.unhealthy and self._ok_run >= self.resume_ok_readings:
                self.unhealthy = False
                self._last_cmd_t = None
                if self.stopped_reason is StoppedReason.UNHEALTHY:
                    self.stopped_reason = StoppedReason.WAITING
                log.warning("%s: %d ok readings: taking commands again", self.robot, self._ok_run)
            return
        self._ok_run = 0
        self.stats.last_unhealthy = ",".join(sorted(k for k, v in flags.items() if v)) or "health"
        self.unhealthy = True
        if self.estopped or self.stopped_reason is StoppedReason.UNHEALTHY:
            return
        self.stats.unhealthy_stops += 1
        log.warning("%s: reading not ok (%s): holding, commands refused", self.robot, self.stats.last_unhealthy)
        if self.driver.active:
            self.driver.stop()
        self.stopped_reason = StoppedReason.UNHEALTHY

    def publish_state(self) -> RobotState:
        obs = self.driver.read()
        h = self.driver.health()
        ok = bool(obs.ok and h.ok)
        self._assess_reading(ok, obs.flags)
        held = self.driver.held_command
        msg = RobotState(
            robot=self.robot,
            t_s=obs.t_s,
            state=obs.state.tolist(),
            obs_seq=obs.seq,
            ok=ok,
            active=self.driver.active,
            stopped_reason=self.stopped_reason,
            action=[] if held is None else held.tolist(),
            episode=self.episode,
            device_t_s=NO_DEVICE_CLOCK if obs.device_t_s is None else obs.device_t_s,
            health={
                **h.to_dict(),
                "bus_malformed": self.malformed_count(),
                "commands_rejected": self.stats.commands_rejected,
                "stale_stops": self.stats.stale_stops,
                "estop_refused": self.stats.estop_refused,
                "unhealthy_stops": self.stats.unhealthy_stops,
                "unhealthy_refused": self.stats.unhealthy_refused,
                "unhealthy_reason": self.stats.last_unhealthy,
                "estop_releases_refused": self.estop.refused_releases,
                # the node's own period on the wall clock (realtime pace): late starts and
                # periods skipped after a stall (bus/cycle.py's catch-up rule)
                **({"cycle_late": self.cycle.late, "cycle_missed": self.cycle.missed} if self.cycle else {}),
            },
        )
        self._last_state = self._state_pub.put(msg)
        img = obs.extras.get("image")
        if isinstance(img, np.ndarray) and img.ndim == 3 and img.dtype == np.uint8:
            # a camera driver may hand over its own encoding ("jpeg"/"png", bytes): sent as is
            enc, data = obs.extras.get("image_encoded") or ("rgb8", img.tobytes())
            self._image_pub.put(Image(camera=self.robot, t_s=obs.t_s, width=img.shape[1], height=img.shape[0],
                                      encoding=enc, data=data))
        return msg

    @property
    def spec(self) -> RobotSpec:
        """The driver's spec in the time model this node runs it in (what it publishes)."""
        return self.driver.spec.with_pacing(self.pacing)

    def publish_spec(self) -> None:
        self._spec_pub.put(SpecMsg(robot=self.robot, spec=self.spec.to_dict()))
        self._spec_t = time.monotonic()

    def _maybe_publish_spec(self) -> None:
        # repeated (1 Hz wall clock, and every 50 steps) so that late joiners and every
        # recording, however short, get it
        if self.stats.steps % 50 == 1 or time.monotonic() - self._spec_t > 1.0:
            self.publish_spec()

    # ------------------------------------------------------------------ loops
    def step(self) -> None:
        """One period: read → update → write, in the order the node's pacing says.

        Sections are timed by the cycle timer of ``run()`` (``hil up`` prints them). Each
        published state carries the action held during the period that ended with it
        (``RobotState.action``; ``learning/recordings.py`` pairs ``(s_t, s_{t+1}.action,
        s_{t+1})``). The node's :class:`~hilstack.drivers.base.Pacing` decides the order:

        * ``STEPPED``, ``LOCKSTEP``, ``FOLLOWER`` (sim): apply the newest command, ``tick()`` (physics advances one
          period under it), read and publish.
        * ``WALL_CLOCK`` (real, emulated): the robot moved during the period before this
          step, under the command held then: read and publish *first*, then apply the newest
          command. (Applying first stamped every state with the command that had not acted
          yet: the recorded transitions were one period off and a model trained on them
          learned a wrong action effect; docs/mbrl.md.)

        It also decides where the command comes from: ``STEPPED`` and ``WALL_CLOCK`` take the
        newest one (the loop is paced on the wall clock by ``run()``), ``LOCKSTEP`` waits for
        the answer to the last published state (``lockstep_timeout_s``), ``FOLLOWER`` for at
        most its declared command wait.
        """
        timer = self.cycle
        read_first = self.pacing.read_before_apply
        lockstep = self.pacing.answered
        if lockstep:
            if self._last_state is None:
                self.publish_state()
            cmd = self._await_answer()
        else:
            with timer.section("control") if timer else nullcontext():
                self._handle_estop()
                self._handle_reset()
        if read_first:
            with timer.section("read_publish") if timer else nullcontext():
                self.publish_state()
        with timer.section("apply") if timer else nullcontext():
            self._apply(cmd if lockstep else self._cmd.poll())  # realtime: the newest, taken now
        if not read_first:
            with timer.section("sim_tick") if timer else nullcontext():
                if self.pacing is Pacing.FOLLOWER:
                    # its tick waits for another node to advance its world (for seconds when that
                    # world stands still, e.g. stopped by this very e-stop): serve e-stops meanwhile
                    while not self.driver.tick_ready(0.05):
                        if self.stop_event.is_set():
                            return  # stopping: no further period
                        self._handle_estop()
                self.driver.tick()
            with timer.section("read_publish") if timer else nullcontext():
                self.publish_state()
        self.stats.steps += 1
        self._maybe_publish_spec()

    def _await_answer(self) -> Command | None:
        """Lockstep: serve e-stops and resets while waiting for the command that answers the
        last published state.

        The simulation never advances without that answer (a timeout that stepped it with the
        held command made episode lengths depend on the machine's load): after
        ``lockstep_timeout_s`` without one the node counts it (``lockstep_timeouts``) and waits
        on; meanwhile, once a second, it sends its spec and the same state again (same sequence
        number: a node that has it sees nothing new, one that joined late or missed it can answer),
        and when its status changes (an e-stop) the state as it is now (a new message; an answer
        to either is taken). A ``FOLLOWER`` (a sim in another robot's world, the hand's reset
        arm, whose world the hand's node advances; ``lockstep_timeout_s`` is then its declared
        ``Follower.command_wait_s``) returns None instead, so its states keep coming while
        nobody commands it.
        A reset request that came before the command is served first: the command then
        answers a state from before the reset and waits for its successor's answer (messages
        of one sender arrive in order; the supervisor asks for a teleport before it answers)."""
        want = self._last_state.seq
        deadline = time.monotonic() + self.lockstep_timeout_s
        follower = self.pacing is Pacing.FOLLOWER
        while not self.stop_event.is_set():
            self._handle_estop()
            if self._handle_reset(publish_first=True):  # the fresh state of the new episode; wait for its answer
                want = self._last_state.seq
                deadline = time.monotonic() + self.lockstep_timeout_s
                continue
            last = self._last_state
            if last.stopped_reason != self.stopped_reason or last.active != self.driver.active:
                # its status changed while it waits (an e-stop engaged or released): the rig sees the
                # robot as it is now (the same instant, a new message), not a stale picture of it
                self.publish_state()
            elif time.monotonic() - self._spec_t > 1.0:  # a late joiner gets the spec and the state
                self.publish_spec()
                self._state_pub.resend(last)
            m = self._cmd.wait(min(0.05, max(0.0, deadline - time.monotonic())))
            if m is not None and m.state_seq >= want:
                if self._handle_reset(publish_first=True):  # a reset asked before this command came
                    want = self._last_state.seq
                    deadline = time.monotonic() + self.lockstep_timeout_s
                    continue
                return m
            if time.monotonic() >= deadline:
                self.stats.lockstep_timeouts += 1
                if follower:
                    return None
                if self.stats.lockstep_timeouts in (1, 10, 100) or self.stats.lockstep_timeouts % 1000 == 0:
                    log.warning("%s: no answer to state %d for %.1f s (%d times so far): the sim waits, "
                                "its state is sent again once a second", self.robot, want, self.lockstep_timeout_s,
                                self.stats.lockstep_timeouts)
                deadline = time.monotonic() + self.lockstep_timeout_s
        return None

    def serve(self, max_steps: int | None = None) -> BridgeStats:
        """Run until stopped (signal, ``stop_event``) or ``max_steps``. Always stops the robot."""
        d = self.driver
        try:
            d.configure()
            latched = self.estop.sync_from_peers(self.estop_sync_s)
            if latched is not None:
                # a late (or restarted) driver: the rig's e-stop is engaged, start stopped
                self.estopped = True
                self.stopped_reason = StoppedReason.ESTOP
                log.warning("starting with the rig's e-stop engaged (%s: %s)", latched.source or "?", latched.reason)
            elif not self.stop_event.is_set():  # a stop asked while it loaded: never activated
                d.activate()
            d.stop()  # nothing moves until the first command
            self.publish_spec()
            if self.pacing.answered:  # paced by the answers (a follower: its world), not by a clock
                n = 0
                while not self.stop_event.is_set() and (max_steps is None or n < max_steps):
                    self.step()
                    n += 1
            else:
                self.run(self.step, d.spec.period_s, max_steps)
        except LinkError as e:
            log.error("link failure on %s: %s", self.robot, e)
            d.fail(e)
            raise
        finally:
            try:
                if d.active:
                    d.stop()
            finally:
                d.cleanup()
        return self.stats
