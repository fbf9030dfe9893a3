"""Online adaptation on the bus: the adaptation node and the MPC's model swap.

:class:`AdaptationNode` (``hil adapt``) listens to a robot's state stream and turns each
pair of consecutive states into a transition ``(s_t, a_t, s_{t+1})`` (a one-row
:class:`hilstack.learning.datasets.Transitions`, learning's one transition record) in the units of the
adaptation model (learning/adaptation/base.py: world-frame state in spec units, action
normalized to [-1, 1] of the spec's limits; the model does its own body-frame conversion,
learning/frames.py). ``a_t`` is the action the driver actually applied during the period
(``RobotState.action``, after clamping and rate limits), as the MBRL loop's recordings use
it; a driver that does not report it falls back to the command that answered ``s_t``. Each
control step it feeds the adapter the new transitions, calls ``adapter.update()`` and
publishes the result as a :class:`hilstack.bus.schemas.ModelUpdate` on ``hil/<rig>/model/update``
(and MOLe's task posterior on ``hil/<rig>/model/posterior``).

What it refuses to learn from (counted in :class:`AdaptationStats`): readings flagged not
``ok``, repeated or out-of-order states, gaps (a lost state: the pair would span more than
one control period, which the model does not predict), periods in which the driver held its
safe action (``stopped_reason``) and transitions the adapter rejects (NaN, shape). An episode
change or any reset message clears the window (``adapter.reset()``: back to θ*), so no
transition spans a reset. While the rig's e-stop is engaged the node learns and publishes
nothing; it starts from θ* after the release.

:class:`ModelSwap` is the MPC's side: the Zenoh callback only stores the newest update (a
latest-value subscription); the planner thread calls the swap at the start of each plan
(``MpcPolicy(model_source=...)``), which decodes, validates and builds the new dynamics there,
so the control loop never waits for it. A bad update is rejected with a one-line reason and
counted; the MPC keeps the model it has.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from hilstack.bus import keys
from hilstack.bus.node import Node, Subscription
from hilstack.bus.schemas import (
    Command,
    MalformedMessage,
    ModelUpdate,
    ResetEvent,
    ResetTransition,
    RobotState,
    SpecMsg,
    TaskPosterior,
    decode,
)
from hilstack.configs.schema import BusConfig
from hilstack.drivers.base import RobotSpec
from hilstack.learning.adaptation.base import Adapter
from hilstack.learning.adaptation.base import ModelUpdate as AdaptedModel
from hilstack.learning.datasets import Transitions

log = logging.getLogger(__name__)

#: how far the time between two states may stray from the control period (fraction of it)
#: before the pair is not a one-step transition
GAP_TOLERANCE = 0.5


@dataclass
class AdaptationStats:
    states: int = 0
    transitions: int = 0
    updates: int = 0
    #: readings flagged not ok (link trouble, stale input, sim blow-up): no transition into or out of them
    skipped_not_ok: int = 0
    #: a state not newer than the previous one (repeat, reorder)
    skipped_repeat: int = 0
    #: a lost state or a period off the grid: the pair spans more than one control period
    skipped_gap: int = 0
    #: the driver held its safe action (stale commands, e-stop, bad command, waiting)
    skipped_stopped: int = 0
    #: no applied action in the state and no command answering the previous one
    skipped_no_action: int = 0
    #: transitions the adapter refused (its one-line error in ``last_error``)
    rejected: int = 0
    #: malformed state messages
    malformed: int = 0
    #: window clears: episode changes and reset messages
    window_clears: int = 0
    #: control steps spent idle because the e-stop was engaged
    estop_steps: int = 0
    #: updates not published because a tensor was NaN/inf (the adapter was reset to θ*)
    nonfinite_updates: int = 0
    last_error: str = ""
    #: adapter.update() + encode + put per published update, wall clock [s] (the last 1000)
    update_s: collections.deque = field(default_factory=lambda: collections.deque(maxlen=1000))
    #: the same in CPU time of the node's thread [s]: what it costs, whatever else the machine runs
    update_cpu_s: collections.deque = field(default_factory=lambda: collections.deque(maxlen=1000))

    def summary(self) -> dict[str, Any]:
        out = {k: v for k, v in asdict(self).items() if k not in ("update_s", "update_cpu_s")}
        for key, vals in (("update_ms", self.update_s), ("update_cpu_ms", self.update_cpu_s)):
            if vals:
                u = np.asarray(vals) * 1e3
                out[f"{key}_p50"] = float(np.percentile(u, 50))
                out[f"{key}_p99"] = float(np.percentile(u, 99))
        return out


class TransitionBuilder:
    """Consecutive ``RobotState`` messages → transitions in the adaptation model's units.

    Pure bookkeeping (no bus, no model): :meth:`push` takes each state in arrival order and
    returns the transition it closes as a one-row :class:`~hilstack.learning.datasets.Transitions`
    (the one transition record of learning, with the spec's channel names), or None; the
    reasons for None are counted in ``stats``. ``new_episode`` is set when the state starts a
    new episode (the caller clears its window).
    """

    def __init__(self, spec: RobotSpec, stats: AdaptationStats | None = None):
        self.action_space = spec.action
        self.period_s = spec.period_s
        self.state_dim = spec.state.dim
        self.state_names = tuple(spec.state.names)
        self.action_names = tuple(spec.action.names)
        self.stats = stats or AdaptationStats()
        self.prev: RobotState | None = None
        self.new_episode = False
        #: state seq → action (spec units) of the command that answered it (fallback for drivers
        #: that do not report the applied action)
        self._answers: collections.OrderedDict[int, list[float]] = collections.OrderedDict()

    def forget(self) -> None:
        """The next state starts afresh (after a reset or an e-stop)."""
        self.prev = None

    def command(self, cmd: Command) -> None:
        self._answers[cmd.state_seq] = cmd.action
        while len(self._answers) > 64:
            self._answers.popitem(last=False)

    def push(self, m: RobotState) -> Transitions | None:
        st = self.stats
        st.states += 1
        self.new_episode = False
        prev = self.prev
        if prev is not None and m.seq <= prev.seq:
            st.skipped_repeat += 1
            return None  # keep prev: a late repeat must not break the chain
        self.prev = m
        if prev is None:
            return None
        if m.episode != prev.episode:
            self.new_episode = True
            return None
        if not (m.ok and prev.ok) or len(m.state) != self.state_dim or len(prev.state) != self.state_dim:
            st.skipped_not_ok += 1
            return None
        dt = m.t_s - prev.t_s
        if dt <= 0:
            st.skipped_repeat += 1
            return None
        if m.seq != prev.seq + 1 or abs(dt - self.period_s) > GAP_TOLERANCE * self.period_s:
            st.skipped_gap += 1
            return None
        if m.stopped_reason or not m.active:
            st.skipped_stopped += 1
            return None
        action = m.action or self._answers.get(prev.seq)
        if not action:
            st.skipped_no_action += 1
            return None
        return Transitions(np.asarray([prev.state], dtype=np.float64),
                           np.asarray([self.action_space.normalize(action)], dtype=np.float64),
                           np.asarray([m.state], dtype=np.float64), self.state_names, self.action_names)


def last_layer(adapter: Adapter) -> list[str]:
    """Names of the parameters of the model's output layer (``6.weight``, ``6.bias`` for 3 hidden layers)."""
    layers = {k.rsplit(".", 1)[0] for k in adapter.theta_star}
    last = max(layers, key=lambda p: [int(x) if x.isdigit() else x for x in p.split(".")])
    return [k for k in adapter.theta_star if k.rsplit(".", 1)[0] == last]


def update_kind(adapter: Adapter, names: list[str]) -> str:
    """``full`` (every parameter), ``subset`` (some parameters; θ* for the rest, also none)
    or ``context`` (tensors that are not parameters, e.g. ReBAL's ``h``)."""
    params = set(adapter.theta_star)
    if not set(names) <= params:
        return "context"
    return "full" if set(names) == params else "subset"


def to_message(update: AdaptedModel, adapter: Adapter, state: RobotState | None,
               send: set[str] | None = None) -> ModelUpdate:
    """The bus form of an adapter's update; ``send``: only these tensor names (a subset)."""
    tensors = update.tensors if send is None else {k: v for k, v in update.tensors.items() if k in send}
    info = {k: v for k, v in update.info.items() if isinstance(v, (int, float, str, bool))}
    return ModelUpdate.pack(
        tensors, method=update.method, kind=update_kind(adapter, list(tensors)), update_seq=update.seq,
        state_stamp_ns=update.state_stamp_ns, state_seq=0 if state is None else state.seq,
        episode=0 if state is None else state.episode, info=info)


def stamp_ns(state: RobotState) -> int:
    """The state → model delay reference: the driver node's publish time (wall clock) [ns]."""
    return int(round(state.stamp_s * 1e9))


class AdaptationNode(Node):
    """Feeds an :class:`~hilstack.learning.adaptation.base.Adapter` from a robot's state stream and
    publishes its updates (see the module docstring).

    Args:
        adapter: built from the same checkpoint as the MPC's (``load_adapter``).
        send: tensor names to publish (e.g. the last layer); None: everything the adapter returns.
    """

    def __init__(self, adapter: Adapter, rig: str, robot: str, bus: BusConfig | None = None,
                 name: str = "adaptation", send: list[str] | None = None, **kw: Any):
        unknown = sorted(set(send or ()) - set(adapter.theta_star))
        if unknown:
            raise ValueError(f"send: {unknown} are not parameters of the {adapter.name} model "
                             f"(it has {sorted(adapter.theta_star)})")
        self.adapter = adapter
        # before the session opens: a long first call holding the GIL starved the new session's
        # callbacks (states were lost right after it, under load)
        self._warm_up()
        super().__init__(name, rig, bus, **kw)
        self.robot = robot
        self.send = None if send is None else set(send)
        self.stats = AdaptationStats()
        # every state matters (a dropped one is a gap): a FIFO, drained each step
        self._state = self.subscribe(keys.state(rig, robot), RobotState, latest=False, capacity=256)
        self._spec = self.subscribe(keys.spec(rig, robot), SpecMsg)
        self._cmd = self.subscribe(keys.cmd(rig, robot), Command, latest=False, capacity=64)
        self._reset = self.subscribe(keys.reset_all(rig), ResetEvent | ResetTransition, latest=False, capacity=64)
        self._pub = self.publisher(keys.model_update(rig), ModelUpdate)
        self._posterior = self.publisher(keys.task_posterior(rig), TaskPosterior)
        self.builder: TransitionBuilder | None = None
        self.last: ModelUpdate | None = None
        self._estopped = False

    def wait_ready(self, timeout_s: float = 20.0) -> RobotSpec:
        """Wait for the robot's spec; check it matches the adapter's model."""
        if self.builder is not None:
            return self.spec
        m = self._spec.poll() or self._spec.last or self._spec.wait(timeout_s)
        if m is None:
            raise TimeoutError(f"no spec from {keys.spec(self.rig, self.robot)} within {timeout_s} s: "
                               "is the driver node up?")
        spec = RobotSpec.from_dict(m.spec)
        names = list(spec.state.names)
        model = self.adapter.model
        if names != list(model.state_names) or spec.action.dim != model.action_dim:
            raise ValueError(f"the {self.adapter.name} checkpoint models states {list(model.state_names)} and "
                             f"{model.action_dim} actions; robot {self.robot} has {names} and {spec.action.dim}")
        self.spec = spec
        self.builder = TransitionBuilder(spec, self.stats)
        return self.spec

    def _warm_up(self) -> None:
        # the first torch.func gradient of a process took ~5 s here (lazy imports and
        # set-up): pay it before the first real state, not on it
        model = self.adapter.model
        s = np.zeros(model.state_dim)
        s[[i for i, n in enumerate(model.state_names) if n == "cos_yaw"]] = 1.0
        self.adapter.reset()
        self.adapter.observe(s, np.zeros(model.action_dim), s)
        self.adapter.update()
        self.adapter.reset()

    def _clear(self) -> None:
        self.adapter.reset()
        self.builder.forget()
        self.stats.window_clears += 1

    def step(self) -> ModelUpdate | None:
        """Take what arrived; observe new transitions; update and publish once. Returns the
        published message (None: nothing new, or e-stop engaged)."""
        st, b = self.stats, self.builder
        for _, raw in self._cmd.drain():
            try:
                b.command(decode(raw, Command))
            except MalformedMessage:
                pass
        states = self._state.drain()
        if self.estop.engaged:
            # the robot is held stopped: nothing to learn; start from θ* after the release
            if not self._estopped:
                self._clear()
                self._estopped = True
            st.estop_steps += len(states)
            self._reset.drain()
            return None
        changed = self._estopped
        self._estopped = False
        if self._reset.drain():  # a reset requested, in progress or done: no transition spans it
            self._clear()
            changed = True
        newest: RobotState | None = None
        for _, raw in states:
            try:
                m = decode(raw, RobotState)
            except MalformedMessage as e:
                st.malformed += 1
                st.last_error = str(e)
                continue
            if m.robot != self.robot:
                continue
            tr = b.push(m)
            newest = b.prev
            if b.new_episode:
                self._clear()
                b.prev = m
                changed = True
            if tr is None:
                continue
            try:
                self.adapter.observe_transitions(tr)
            except ValueError as e:
                st.rejected += len(tr)
                st.last_error = str(e)
                continue
            st.transitions += len(tr)
            changed = True
        if not changed:
            return None
        return self._publish(newest)

    def _publish(self, state: RobotState | None) -> ModelUpdate | None:
        st = self.stats
        t0, c0 = time.perf_counter(), time.thread_time()
        upd = self.adapter.update(stamp_ns(state) if state is not None else 0)
        bad = [k for k, v in upd.tensors.items() if not np.isfinite(v).all()]
        if bad:
            # never send a broken model: count it and start over from θ*
            st.nonfinite_updates += 1
            st.last_error = f"{upd.method} update {upd.seq}: non-finite tensors {bad}; adapter reset to θ*"
            log.warning(st.last_error)
            self._clear()
            return None
        msg = self._pub.put(to_message(upd, self.adapter, state, self.send))
        post = upd.info.get("posterior")
        if post:  # MOLe (empty before its first task exists)
            self._posterior.put(TaskPosterior(
                method=upd.method, update_seq=upd.seq, state_stamp_ns=upd.state_stamp_ns,
                state_seq=msg.state_seq, posterior=[float(p) for p in post],
                task=int(upd.info.get("task", int(np.argmax(post)))),
                tasks_created=int(upd.info.get("tasks_created", len(post)))))
        st.updates += 1
        st.update_s.append(time.perf_counter() - t0)
        st.update_cpu_s.append(time.thread_time() - c0)
        self.last = msg
        return msg

    def run(self, max_updates: int | None = None, idle_timeout_s: float | None = None) -> AdaptationStats:
        """Serve until stopped (SIGINT/SIGTERM), ``max_updates`` updates, or no state for
        ``idle_timeout_s``. The node is event driven: it wakes on each state."""
        self.wait_ready()
        self.adapter.reset()
        idle_since = time.monotonic()
        while not self.stop_event.is_set() and (max_updates is None or self.stats.updates < max_updates):
            if not self._state.wait_queued(0.1):
                if idle_timeout_s is not None and time.monotonic() - idle_since > idle_timeout_s:
                    break
                continue
            idle_since = time.monotonic()
            self.step()
        return self.stats


@dataclass
class SwapStats:
    applied: int = 0
    #: updates refused (bad tensors, wrong method, the adapter could not build them)
    rejected: int = 0
    last_error: str = ""
    #: state stamp → new model built in the planner thread [ms] (the last 1000)
    delay_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=1000))

    def summary(self) -> dict[str, Any]:
        out = {k: v for k, v in asdict(self).items() if k != "delay_ms"}
        if self.delay_ms:
            d = np.asarray(self.delay_ms)
            out["delay_ms_p50"] = float(np.percentile(d, 50))
            out["delay_ms_p99"] = float(np.percentile(d, 99))
        return out


class ModelSwap:
    """The MPC's source of adapted models: ``MpcPolicy(model_source=ModelSwap(...))``.

    ``subscription``: a latest-value subscription to ``hil/<rig>/model/update`` (its Zenoh
    callback only stores the newest sample; older unread updates are superseded). Calling the
    swap (in the planner thread, at the start of a plan) returns the dynamics of the newest
    valid update, or None when there is nothing new or it was rejected.
    """

    def __init__(self, adapter: Adapter, subscription: Subscription):
        self.adapter = adapter
        self.sub = subscription
        self.params = {k: tuple(v.shape) for k, v in adapter.theta_star.items()}
        self.stats = SwapStats()
        self.current: ModelUpdate | None = None

    def initial(self):
        """The dynamics before any update: θ* / the prior."""
        return self.adapter.dynamics(None)

    def __call__(self):
        m = self.sub.poll()
        if m is None:
            return None
        try:
            if m.method != self.adapter.name:
                raise ValueError(f"an update of method {m.method!r}; this MPC runs {self.adapter.name!r}")
            # contexts are checked by the adapter that interprets them
            tensors = m.tensors(None if m.kind == "context" else self.params)
            dyn = self.adapter.dynamics(AdaptedModel(m.method, m.update_seq, m.state_stamp_ns, tensors, dict(m.info)))
        except (MalformedMessage, ValueError, KeyError, TypeError, RuntimeError) as e:
            self.stats.rejected += 1
            why = e.args[0] if isinstance(e, KeyError) and e.args else e
            self.stats.last_error = f"model update {m.method}#{m.update_seq} rejected: {why}"
            log.warning(self.stats.last_error)
            return None
        self.stats.applied += 1
        if m.state_stamp_ns:
            self.stats.delay_ms.append((time.time_ns() - m.state_stamp_ns) / 1e6)
        self.current = m
        return dyn

    def summary(self) -> dict[str, Any]:
        out = self.stats.summary()
        out["malformed"] = self.sub.malformed
        return out
