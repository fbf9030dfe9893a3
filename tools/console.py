"""``hil console RIG``: the operator's terminal view of a live rig, with the e-stop keys.

:class:`RigWatch` (no UI, testable alone) joins the rig as one more node, in this process's bus
user's name, and keeps what the operator needs: the nodes alive (liveliness tokens), each
robot's newest :class:`~hilstack.bus.schemas.RobotState` (ok/stale flags, ``stopped_reason``,
the link counters of its health, the rate measured from the states' own timestamps, the
deadline overruns the driver node counts), the reset supervisor's last transition, and the
rig's e-stop as the nodes' latches hold it. :class:`ConsoleApp` draws it with textual (the
``operator`` extra) and sends the e-stop: ``e`` engages (every session may), ``r`` releases
in the user's name (the rig's access control applies: a user outside ``bus.access.release``
is told so and nothing is sent), ``q`` quits. The console never commands a robot.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from hilstack.bus.schemas import MalformedMessage, ResetTransition, RobotState, decode

#: a robot whose newest state is older than this is shown STALE [s] (the driver node's stale rule)
STALE_S = 1.0
#: the rate is measured over the states of this last stretch of wall clock [s]
RATE_WINDOW_S = 2.0
#: health keys shown as link counters and as deadline overruns (present ones only)
LINK_KEYS = {"frames_sent": "sent", "frames_received": "recv", "corrupt_frames": "corrupt",
             "dropped_frames": "dropped", "link_quality": "quality"}
OVERRUN_KEYS = ("cycle_late", "cycle_missed", "heartbeat_missed", "deadline_missed", "stale_stops",
                "commands_rejected")


@dataclass
class RobotView:
    """What the console knows of one robot."""

    robot: str
    state: RobotState | None = None
    #: wall clock of the newest state (monotonic) [s]
    seen_s: float = 0.0
    #: (wall clock, state t_s) of the recent states, for the rate
    times: deque = field(default_factory=lambda: deque(maxlen=4096))

    def add(self, st: RobotState, now: float) -> None:
        self.state = st
        self.seen_s = now
        self.times.append((now, float(st.t_s)))
        while self.times and now - self.times[0][0] > RATE_WINDOW_S:
            self.times.popleft()

    def rate_hz(self) -> float | None:
        """States per second of robot clock over the window (None: fewer than two states)."""
        if len(self.times) < 2:
            return None
        dt = self.times[-1][1] - self.times[0][1]
        return (len(self.times) - 1) / dt if dt > 0 else None

    def stale(self, now: float) -> bool:
        return self.state is None or now - self.seen_s > STALE_S

    def row(self, now: float) -> list[str]:
        """robot, flags, stopped, rate, link, overruns (text cells)."""
        st = self.state
        if st is None:
            return [self.robot, "NO STATE", "", "", "", ""]
        flags = ["ok" if st.ok else "NOT OK"]
        if self.stale(now):
            flags.append(f"STALE {now - self.seen_s:.0f}s")
        flags.append("active" if st.active else "stopped")
        h = st.health or {}
        rate = self.rate_hz()
        link = " ".join(f"{label}={_fmt(h[k])}" for k, label in LINK_KEYS.items() if k in h)
        over = " ".join(f"{k}={_fmt(h[k])}" for k in OVERRUN_KEYS if k in h and h[k])
        return [self.robot, " ".join(flags), st.stopped_reason or "-",
                "-" if rate is None else f"{rate:.1f} Hz", link or "-", over or "none"]


def _fmt(v: Any) -> str:
    return f"{v:.2f}" if isinstance(v, float) else str(v)


def release_refusal(rig: str, bus: Any) -> str | None:
    """Why this process's bus user may not release ``rig``'s e-stop (None: it may). The rig's
    router refuses such a release anyway (bus/access.py); the console says so instead of waiting."""
    acc = getattr(bus, "access", None)
    if acc is None:
        return None
    from hilstack.bus.access import user_of

    user = user_of(acc)
    if user in acc.release:
        return None
    return f"user {user!r} may not release rig {rig}'s e-stop (bus.access.release: {acc.release})"


class RigWatch:
    """The rig as the console sees it, kept by a background thread (``start``/``close``)."""

    def __init__(self, rig: str, bus: Any, robots: list[str], name: str = "console", poll_s: float = 0.5):
        from hilstack.bus import keys
        from hilstack.bus.node import Node

        self.rig = rig
        self.bus = bus
        self.node = Node(name, rig, bus, handle_signals=False)
        self.robots = {r: RobotView(r) for r in robots}
        self._subs = {r: self.node.subscribe(keys.state(rig, r), RobotState, latest=False, capacity=4096)
                      for r in robots}
        self._resets = self.node.subscribe(keys.reset_transition(rig), ResetTransition, latest=False, capacity=256)
        self.reset: dict[str, ResetTransition] = {}
        self.nodes: list[str] = []
        #: node → "engaged"/"released"/"none heard"
        self.latches: dict[str, str] = {}
        self.estop_detail = ""
        self.message = ""
        self.poll_s = poll_s
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="console-watch", daemon=True)

    @property
    def user(self) -> str:
        return self.node.user

    def start(self) -> RigWatch:
        self._thread.start()
        return self

    def drain_states(self) -> None:
        now = time.monotonic()
        for r, sub in self._subs.items():
            for _, payload in sub.drain():
                try:
                    st = decode(payload, RobotState)
                except MalformedMessage:
                    continue
                with self.lock:
                    self.robots[r].add(st, now)
        for _, payload in self._resets.drain():
            try:
                tr = decode(payload, ResetTransition)
            except MalformedMessage:
                continue
            with self.lock:
                self.reset[tr.robot] = tr

    def poll_rig(self) -> None:
        """Liveliness and the e-stop latches (blocking queries, a few hundred ms)."""
        from hilstack.bus.estop import query_latches
        from hilstack.bus.node import alive_nodes

        names = sorted(n for n in alive_nodes(self.node.session, self.rig, timeout_s=0.3) if n != self.node.name)
        latches = query_latches(self.node.session, self.rig, timeout_s=0.3)
        detail = ""
        for m in latches.values():
            if m is not None and m.engaged:
                detail = f"{m.reason or '-'}, from {m.source or '?'}" + (f" by {m.sender}" if m.sender else "")
        with self.lock:
            self.nodes = names
            self.latches = {n: "none heard" if m is None else ("engaged" if m.engaged else "released")
                            for n, m in latches.items() if n != self.node.name}
            self.estop_detail = detail

    def estop_state(self) -> str:
        """ENGAGED when any node's latch or any robot's state says so, else released/none."""
        with self.lock:
            vals = set(self.latches.values())
            by_state = any(v.state is not None and v.state.stopped_reason == "estop" for v in self.robots.values())
            detail = self.estop_detail
        if "engaged" in vals or by_state:
            return "ENGAGED" + (f" ({detail})" if detail else "")
        return "released" if "released" in vals else "not engaged"

    def _loop(self) -> None:
        next_poll = 0.0
        while not self._stop.is_set():
            self.drain_states()
            now = time.monotonic()
            if now >= next_poll:
                try:
                    self.poll_rig()
                except Exception as e:  # noqa: BLE001 - a failed query is shown, the view keeps going
                    self.message = f"rig query failed: {e}"
                next_poll = time.monotonic() + self.poll_s
            self._stop.wait(0.05)

    def may_release(self) -> str | None:
        return release_refusal(self.rig, self.bus)

    def send_estop(self, engaged: bool) -> str:
        """Engage or release (in the user's name); the outcome in one line."""
        from hilstack.bus.estop import command_estop

        if not engaged and (why := self.may_release()):
            return f"refused: {why}"
        res = command_estop(self.node, engaged=engaged, reason="console", timeout_s=2.0)
        what = "e-stop ENGAGED" if engaged else f"e-stop released by {self.user}"
        if res.ok:
            return f"{what}: acknowledged by {', '.join(res.confirmed)}"
        extra = "; ".join(res.details) or (f"not acknowledged by {', '.join(res.missing)}" if res.missing
                                           else "no driver node answered")
        return f"{'engage' if engaged else 'release'} NOT acknowledged: {extra}"

    def snapshot(self) -> dict[str, Any]:
        now = time.monotonic()
        with self.lock:
            rows = [v.row(now) for v in self.robots.values()]
            resets = {r: f"{t.dest} (after {t.trigger}{', ' + t.detail if t.detail else ''})"
                      for r, t in self.reset.items()}
            nodes = list(self.nodes)
            latches = dict(self.latches)
        return {"rows": rows, "resets": resets, "nodes": nodes, "latches": latches,
                "estop": self.estop_state(), "message": self.message}

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.node.close()


COLUMNS = ("robot", "flags", "stopped_reason", "rate", "link", "overruns")


def make_app(watch: RigWatch, refresh_s: float = 0.25):  # noqa: ANN201 - a textual App (optional import)
    """The textual app over ``watch`` (textual imported here: the ``operator`` extra)."""
    from hilstack.configs.extras import require

    require("textual", "hil console")
    from rich.text import Text
    from textual.app import App, ComposeResult
    from textual.widgets import DataTable, Footer, Static

    class ConsoleApp(App):
        TITLE = "hil console"
        CSS = "#top { height: 2; } #nodes { height: auto; } #msg { height: 2; }"
        BINDINGS = [("e", "engage", "engage e-stop"), ("r", "release", "release e-stop"), ("q", "quit", "quit")]

        def compose(self) -> ComposeResult:
            # markup=False: node names and messages are shown as they are ("[engaged]" is no tag)
            yield Static(id="top", markup=False)
            yield DataTable(id="robots", show_cursor=False)
            yield Static(id="nodes", markup=False)
            yield Static(id="msg", markup=False)
            yield Footer()

        def on_mount(self) -> None:
            self.query_one("#robots", DataTable).add_columns(*COLUMNS)
            self.refresh_view()
            self.set_interval(refresh_s, self.refresh_view)

        def refresh_view(self) -> None:
            s = watch.snapshot()
            self.query_one("#top", Static).update(
                f"rig {watch.rig} as {watch.user}   E-STOP: {s['estop']}")
            t = self.query_one("#robots", DataTable)
            t.clear()
            for row in s["rows"]:
                t.add_row(*(Text(c) for c in row))  # plain text: a cell is no markup
            resets = "; ".join(f"{r}: {v}" for r, v in s["resets"].items()) or "no reset supervisor heard"
            nodes = ", ".join(f"{n} [{s['latches'].get(n, '?')}]" for n in s["nodes"]) or "(no nodes)"
            self.query_one("#nodes", Static).update(f"nodes: {nodes}\nreset: {resets}")
            self.query_one("#msg", Static).update(s["message"])

        def _send(self, engaged: bool) -> None:
            watch.message = "engaging e-stop..." if engaged else "releasing e-stop..."
            self.run_worker(lambda: self._finish(engaged), thread=True, exclusive=True)

        def _finish(self, engaged: bool) -> None:
            watch.message = watch.send_estop(engaged)

        def action_engage(self) -> None:
            self._send(True)

        def action_release(self) -> None:
            self._send(False)

    return ConsoleApp()
