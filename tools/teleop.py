"""``hil teleop RIG``: drive a robot from the keyboard, through the bus like any controller.

Teleop is one more controller node (``control/controller_node.py``): it reads the robot's
spec and states from the bus and publishes :class:`hilstack.bus.schemas.Command` on the
robot's command key, in this process's bus user's name, so the rig's access control
applies (a user outside ``bus.access.command`` is refused by the rig's router; the verb says
so before it starts). The driver node applies the contract's limits and rate limit to what
teleop sends, exactly as for the MPC; teleop never talks to a driver directly.

Two key maps, chosen from the robot's spec:

* **drive** (a differential robot: two action channels named ``*_l``/``*_r`` or
  ``*left*``/``*right*``, the roach's leg velocities): ``w``/``s`` or up/down change the
  forward speed, ``a``/``d`` or left/right the turn, each press by ``step`` of the range;
  the command stays until changed (space stops).
* **jog** (any other robot, the arms): ``1``..``9`` (or left/right) select a channel,
  ``+``/``-`` (or up/down) jog it. A velocity channel (unit ``*/s``) moves at ``jog_frac``
  of its limit for ``jog_periods`` control periods per press (a held key repeats);
  a position channel steps its target by ``step`` of its range.

Both: space = stop (the spec's safe action), ``e`` = engage the rig's e-stop (latched;
release with ``hil estop RIG --release``), ``q`` or Ctrl-C = quit (sends the safe action first).
"""

from __future__ import annotations

import os
import select
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

# key names the mapper understands (escape sequences of the arrow keys included)
UP, DOWN, LEFT, RIGHT = "up", "down", "left", "right"
_ESCAPES = {"\x1b[A": UP, "\x1b[B": DOWN, "\x1b[C": RIGHT, "\x1b[D": LEFT,
            "\x1bOA": UP, "\x1bOB": DOWN, "\x1bOC": RIGHT, "\x1bOD": LEFT}


def parse_keys(data: str) -> list[str]:
    """Split terminal input into keys: arrow escape sequences become ``up``/``down``/...,
    every other character is itself."""
    out: list[str] = []
    i = 0
    while i < len(data):
        seq = data[i:i + 3]
        if seq in _ESCAPES:
            out.append(_ESCAPES[seq])
            i += 3
            continue
        out.append(data[i])
        i += 1
    return out


class KeyReader:
    """Reads keys from a terminal without waiting for Enter (cbreak mode, restored on exit).

    Ctrl-C still raises KeyboardInterrupt (cbreak keeps the terminal's signals). Standard
    library only (termios/tty/select): a key reader needs nothing more.
    """

    def __init__(self, fd: int | None = None):
        self.fd = sys.stdin.fileno() if fd is None else fd
        self._old: Any = None

    def __enter__(self) -> KeyReader:
        import termios
        import tty

        self._old = termios.tcgetattr(self.fd)
        tty.setcbreak(self.fd)
        return self

    def __exit__(self, *exc: object) -> None:
        import termios

        if self._old is not None:
            termios.tcsetattr(self.fd, termios.TCSADRAIN, self._old)

    def read(self, timeout_s: float = 0.0) -> list[str]:
        """The keys typed since the last call (waits at most ``timeout_s`` for the first)."""
        data = b""
        wait = timeout_s
        while select.select([self.fd], [], [], wait)[0]:
            chunk = os.read(self.fd, 64)
            if not chunk:
                break
            data += chunk
            wait = 0.0
        return parse_keys(data.decode("utf-8", "replace"))


def is_differential(names: list[str]) -> bool:
    """Two action channels that are a left and a right side (the roach's legs)."""
    if len(names) != 2:
        return False
    a, b = (n.lower() for n in names)
    return (a.endswith("_l") and b.endswith("_r")) or ("left" in a and "right" in b)


@dataclass
class Event:
    """What a key asks of the loop beside changing the command."""

    kind: str  # "estop" | "quit"


class TeleopMapper:
    """Keys → the command to send, in the robot's action units, from the robot's spec
    (a plain dict, as published on the bus). Clamps to the spec's action range; the
    driver applies the limits and rate limit again (the contract), whatever teleop sends."""

    def __init__(self, spec: dict[str, Any], step: float = 0.25, jog_frac: float = 0.5, jog_periods: int = 5):
        if not (0 < step <= 1 and 0 < jog_frac <= 1 and 1 <= jog_periods <= 1000):
            raise ValueError(f"teleop: step {step} and jog_frac {jog_frac} must be in (0, 1], jog_periods "
                             f"{jog_periods} in [1, 1000]")
        act = spec["action"]
        self.names: list[str] = list(act["names"])
        self.units: list[str] = list(act.get("units") or [""] * len(self.names))
        self.low = np.asarray(act["low"], dtype=np.float64)
        self.high = np.asarray(act["high"], dtype=np.float64)
        safe = spec.get("safe_action")
        self.safe = None if safe is None else np.asarray(safe, dtype=np.float64)
        self.step = step
        self.jog_frac = jog_frac
        self.jog_periods = jog_periods
        #: the control period [s] (a continuous jog of a position channel moves its target per second)
        self.period_s = float(spec.get("period_s") or 0.1)
        self.mode = "drive" if is_differential(self.names) else "jog"
        self.speed = 0.0  # drive: normalized forward speed, [-1, 1]
        self.turn = 0.0  # drive: normalized turn (positive: left), [-1, 1]
        self.joint = 0  # jog: selected channel
        self._jog_dir = 0.0
        self._jog_left = 0  # periods of the current velocity jog still to send
        self._rate = 0.0  # a continuous jog (a gamepad's stick), [-1, 1]; 0: none
        self._target: np.ndarray | None = None  # jog of a position robot: the commanded target
        self.last: np.ndarray | None = None

    def is_velocity(self, i: int) -> bool:
        return self.units[i].endswith("/s")

    def stop(self) -> None:
        self.speed = self.turn = 0.0
        self._jog_left = 0
        self._jog_dir = 0.0
        self._rate = 0.0

    def set_jog(self, rate: float) -> None:
        """A continuous jog of the selected channel (a gamepad's stick), ``rate`` in [-1, 1] of
        the jog speed, held until changed (0: none, the channel rests). It replaces a timed
        jog: a velocity channel moves at ``|rate|·jog_frac`` of its limit, a position channel's
        target moves by ``rate·step`` of its range per second."""
        self._rate = float(np.clip(rate, -1.0, 1.0))
        if self._rate:
            self._jog_left = 0

    def key(self, k: str) -> Event | None:
        if k == " ":
            self.stop()
            return None
        if k in ("e", "E"):
            self.stop()
            return Event("estop")
        if k in ("q", "Q", "\x03", "\x04"):
            self.stop()
            return Event("quit")
        if self.mode == "drive":
            dv = {"w": 1, "W": 1, UP: 1, "s": -1, "S": -1, DOWN: -1}.get(k, 0)
            dt = {"a": 1, "A": 1, LEFT: 1, "d": -1, "D": -1, RIGHT: -1}.get(k, 0)
            self.speed = float(np.clip(round(self.speed + dv * self.step, 6), -1, 1))
            self.turn = float(np.clip(round(self.turn + dt * self.step, 6), -1, 1))
            return None
        n = len(self.names)
        if k.isdigit() and 1 <= int(k) <= min(n, 9):
            self._select(int(k) - 1)
        elif k == LEFT:
            self._select((self.joint - 1) % n)
        elif k == RIGHT:
            self._select((self.joint + 1) % n)
        elif k in ("+", "=", UP, "-", "_", DOWN):
            self._jog(1.0 if k in ("+", "=", UP) else -1.0)
        return None

    def _select(self, i: int) -> None:
        if i != self.joint:
            self._jog_left = 0
        self.joint = i

    def _jog(self, direction: float) -> None:
        i = self.joint
        if self.is_velocity(i):
            if self._jog_left and direction != self._jog_dir:
                self._jog_left = 0  # a press the other way stops the jog first
                return
            self._jog_dir = direction
            self._jog_left = self.jog_periods
        elif self._target is not None:
            span = self.high[i] - self.low[i]
            self._target[i] = np.clip(self._target[i] + direction * self.step * span, self.low[i], self.high[i])

    def _rest(self, held: list[float]) -> np.ndarray:
        """What the robot does when nobody asks: the safe action, else hold the held command."""
        if self.safe is not None:
            return self.safe.copy()
        if len(held) == len(self.names) and np.all(np.isfinite(held)):
            return np.asarray(held, dtype=np.float64)
        return (self.low + self.high) / 2  # unreachable for the shipped robots (they publish one or the other)

    def action(self, held: list[float]) -> np.ndarray:
        """The command for the next period; ``held`` is the command the driver holds now
        (``RobotState.action``). Advances a velocity jog by one period."""
        if self.mode == "drive":
            left = float(np.clip(self.speed - self.turn, -1, 1))
            right = float(np.clip(self.speed + self.turn, -1, 1))
            rest = self._rest(held)
            # 0 → the safe action; ±1 → the channel's limits
            a = np.array([rest[j] + (v * (self.high[j] - rest[j]) if v >= 0 else -v * (self.low[j] - rest[j]))
                          for j, v in enumerate((left, right))])
        else:
            if self._target is None:
                self._target = self._rest(held)
            a = self._target.copy()
            for j in range(len(self.names)):
                if self.is_velocity(j):
                    a[j] = 0.0 if self.safe is None else self.safe[j]
            i = self.joint
            if self._rate and self.is_velocity(i):
                lim = self.high[i] if self._rate > 0 else self.low[i]
                a[i] = a[i] + abs(self._rate) * self.jog_frac * (lim - a[i])
            elif self._rate:
                span = self.high[i] - self.low[i]
                self._target[i] = np.clip(self._target[i] + self._rate * self.step * span * self.period_s,
                                          self.low[i], self.high[i])
                a[i] = self._target[i]
            elif self.is_velocity(i) and self._jog_left > 0:
                lim = self.high[i] if self._jog_dir > 0 else self.low[i]
                a[i] = a[i] + self.jog_frac * (lim - a[i])
                self._jog_left -= 1
        self.last = np.clip(a, self.low, self.high)
        return self.last

    def describe(self) -> str:
        if self.mode == "drive":
            return f"speed {self.speed:+.2f} turn {self.turn:+.2f}"
        jog = f" jog {'+' if self._jog_dir > 0 else '-'}{self._jog_left}" if self._jog_left else ""
        if self._rate:
            jog = f" jog {self._rate:+.2f}"
        return f"joint {self.joint + 1}:{self.names[self.joint]}{jog}"


HELP = {
    "drive": "w/s speed  a/d turn  space stop  e e-stop  q quit",
    "jog": "1-9 joint  +/- jog  space stop  e e-stop  q quit",
}


def status_line(robot: str, mapper: TeleopMapper, state: Any, state_names: list[str], estop: str,
                state_age_s: float = 0.0) -> str:
    """One line: what teleop commands and what the robot reports (its pose or the selected joint);
    a state older than a second says so (the driver node stopped publishing)."""
    from hilstack.bus.recording import planar_pose

    parts = [robot, mapper.mode, mapper.describe()]
    if mapper.last is not None:
        parts.append("cmd " + " ".join(f"{v:+.2f}" for v in mapper.last))
    if state is None:
        parts.append("no state yet")
    else:
        pose = planar_pose(state_names, list(state.state))
        if mapper.mode == "drive" and pose is not None:
            x, y, _z, yaw = pose
            parts.append(f"x {x:+.3f} y {y:+.3f} yaw {np.degrees(yaw):+.0f}°")
        elif mapper.mode == "jog":
            jn = mapper.names[mapper.joint]
            pos = jn.rsplit("_", 1)[0] + "_pos"
            if pos in state_names:
                parts.append(f"{pos} {state.state[state_names.index(pos)]:+.3f}")
        parts.append("active" if state.active else f"stopped ({state.stopped_reason or '?'})")
        if state_age_s > 1.0:
            parts.append(f"NO STATE for {state_age_s:.0f} s (is the driver node up?)")
    if estop:
        parts.append(estop)
    return " | ".join(parts)
