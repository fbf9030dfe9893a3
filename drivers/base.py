"""The driver contract every robot and sensor implements, real, emulated or simulated.

Shape (after ros2_control's hardware lifecycle and LeRobot's robot base):

* ``spec`` is readable before connecting: named state/action spaces with units and
  limits, the control period and the action rate limit.
* lifecycle: UNCONFIGURED --configure()--> CONFIGURED --activate()--> ACTIVE
  --deactivate()--> CONFIGURED --cleanup()--> UNCONFIGURED. Any failure goes through
  ``fail()``: the robot is stopped (best effort) and the driver returns to UNCONFIGURED
  with ``last_error`` set. ``with driver:`` configures and activates, and always stops
  and cleans up on exit.
* ``read()`` returns a timestamped :class:`Observation`; never blocks longer than one period.
* ``write(action)`` is refused unless ACTIVE, rejects wrong shapes and non-finite values
  with :class:`CommandError`, clamps to limits and the rate limit, and returns the
  action actually applied. On activation the held command is the measured state
  (``_hold_command``) so nothing jumps.
* ``stop()`` brings the robot to its safe state (the spec's ``safe_action``).
* ``tick()`` waits for the next control period: wall-clock backends sleep until the
  next period boundary; the sim backend advances physics by one period. A loop written
  as ``read → write → tick`` therefore runs unchanged on every backend.

Subclasses implement the underscore hooks; the public methods hold the checks.
"""

from __future__ import annotations

import enum
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bus.cycle import CycleTimer


class LifecycleError(RuntimeError):
    """A call that is not allowed in the driver's current lifecycle state."""


class CommandError(ValueError):
    """An action that cannot be applied (wrong shape, NaN/inf, ...). Nothing was sent."""


class LinkError(RuntimeError):
    """The link to the device is gone or unusable (port vanished, no reply...)."""


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONFIGURED = "configured"
    ACTIVE = "active"


@dataclass(frozen=True)
class Space:
    """A named box space. ``low``/``high`` may be ±inf for unbounded channels."""

    names: tuple[str, ...]
    units: tuple[str, ...]
    low: np.ndarray
    high: np.ndarray

    def __post_init__(self) -> None:
        low = np.asarray(self.low, dtype=np.float64).reshape(-1)
        high = np.asarray(self.high, dtype=np.float64).reshape(-1)
        n = len(self.names)
        if len(self.units) != n or low.shape != (n,) or high.shape != (n,):
            raise ValueError(
                f"space sizes disagree: {n} names, {len(self.units)} units, "
                f"{low.size} low, {high.size} high"
            )
        if np.any(low > high):
            bad = [self.names[i] for i in np.flatnonzero(low > high)]
            raise ValueError(f"space low > high for {bad}")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    @property
    def dim(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no channel {name!r}; channels are {list(self.names)}") from None

    @classmethod
    def build(cls, channels: list[tuple[str, str, float, float]]) -> Space:
        """From ``[(name, unit, low, high), ...]``."""
        names, units, low, high = zip(*channels, strict=True) if channels else ((), (), (), ())
        return cls(tuple(names), tuple(units), np.array(low, float), np.array(high, float))


@dataclass(frozen=True)
class RobotSpec:
    """Everything a controller needs to know about a robot before connecting."""

    name: str
    state: Space
    action: Space
    period_s: float
    #: maximum change of each action channel per second (inf: no limit)
    action_rate_per_s: np.ndarray | None = None
    #: the action that brings the robot to rest (zero leg velocity...); None: hold position
    safe_action: np.ndarray | None = None
    description: str = ""

    def __post_init__(self) -> None:
        if not (self.period_s > 0 and math.isfinite(self.period_s)):
            raise ValueError(f"period_s must be a positive number, got {self.period_s}")
        for attr in ("action_rate_per_s", "safe_action"):
            v = getattr(self, attr)
            if v is not None:
                v = np.asarray(v, dtype=np.float64).reshape(-1)
                if v.shape != (self.action.dim,):
                    raise ValueError(f"{attr} has {v.size} entries, action space has {self.action.dim}")
                object.__setattr__(self, attr, v)

    def to_dict(self) -> dict[str, Any]:
        def sp(s: Space) -> dict[str, Any]:
            return {
                "names": list(s.names),
                "units": list(s.units),
                "low": [float(x) for x in s.low],
                "high": [float(x) for x in s.high],
            }

        return {
            "name": self.name,
            "period_s": self.period_s,
            "state": sp(self.state),
            "action": sp(self.action),
            "action_rate_per_s": None
            if self.action_rate_per_s is None
            else [float(x) for x in self.action_rate_per_s],
        }


@dataclass
class Observation:
    """One reading. ``t_s`` is the backend clock (wall clock for real/emulated,
    sim time for sim) at which the state was measured."""

    t_s: float
    state: np.ndarray
    seq: int
    ok: bool = True
    flags: dict[str, bool] = field(default_factory=dict)
    #: extra sensor data: images (H×W×3 uint8), raw IMU, mocap pose...
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass
class Health:
    ok: bool = True
    link_quality: float = 1.0
    frames_sent: int = 0
    frames_received: int = 0
    corrupt_frames: int = 0
    dropped_frames: int = 0
    latency_s: float | None = None
    last_heartbeat_s: float | None = None
    last_error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "link_quality": self.link_quality,
            "frames_sent": self.frames_sent,
            "frames_received": self.frames_received,
            "corrupt_frames": self.corrupt_frames,
            "dropped_frames": self.dropped_frames,
            "latency_s": self.latency_s,
            "last_heartbeat_s": self.last_heartbeat_s,
            "last_error": self.last_error,
            **self.extra,
        }


class Driver(ABC):
    """Base of every backend. Subclasses set ``spec`` in ``__init__`` (no I/O there)."""

    spec: RobotSpec
    #: "real", "emulated" or "sim"
    backend: str = "real"

    def __init__(self) -> None:
        self._lifecycle = Lifecycle.UNCONFIGURED
        self._held: np.ndarray | None = None
        self._last_write_t: float | None = None
        self._cycle: CycleTimer | None = None  # paces tick() on the wall clock
        self.last_error: str | None = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def lifecycle(self) -> Lifecycle:
        return self._lifecycle

    @property
    def active(self) -> bool:
        return self._lifecycle is Lifecycle.ACTIVE

    def configure(self) -> None:
        """Bring the link up; afterwards ``read()`` works."""
        self._require(Lifecycle.UNCONFIGURED, "configure")
        try:
            self._on_configure()
        except Exception as e:
            self.fail(e)
            raise
        self._lifecycle = Lifecycle.CONFIGURED

    def activate(self) -> None:
        """Start accepting commands; the held command becomes the measured state."""
        self._require(Lifecycle.CONFIGURED, "activate")
        try:
            obs = self.read()
            self._held = np.asarray(self._hold_command(obs), dtype=np.float64).copy()
            self._last_write_t = None
            self._on_activate()
        except Exception as e:
            self.fail(e)
            raise
        self._lifecycle = Lifecycle.ACTIVE

    def deactivate(self) -> None:
        """Stop the robot and stop accepting commands."""
        if self._lifecycle is not Lifecycle.ACTIVE:
            return
        try:
            self.stop()
            self._on_deactivate()
        finally:
            self._lifecycle = Lifecycle.CONFIGURED

    def cleanup(self) -> None:
        """Close the link (from CONFIGURED or ACTIVE)."""
        if self._lifecycle is Lifecycle.ACTIVE:
            self.deactivate()
        if self._lifecycle is Lifecycle.UNCONFIGURED:
            return
        try:
            self._on_cleanup()
        finally:
            self._lifecycle = Lifecycle.UNCONFIGURED

    def fail(self, error: BaseException | str) -> None:
        """The error path: stop the robot (best effort), close, go UNCONFIGURED."""
        self.last_error = str(error)
        try:
            self._stop()
        except Exception:
            pass  # the link may be the thing that failed; keep going to cleanup
        try:
            self._on_cleanup()
        except Exception:
            pass
        self._lifecycle = Lifecycle.UNCONFIGURED

    def __enter__(self) -> Driver:
        if self._lifecycle is Lifecycle.UNCONFIGURED:
            self.configure()
        if self._lifecycle is Lifecycle.CONFIGURED:
            self.activate()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if self._lifecycle is Lifecycle.ACTIVE:
                self.stop()
        finally:
            self.cleanup()

    # ------------------------------------------------------------------ I/O
    def read(self) -> Observation:
        if self._lifecycle is Lifecycle.UNCONFIGURED:
            raise LifecycleError(f"{self.spec.name}: read() needs configure() first")
        return self._read()

    def validate(self, action: Any) -> np.ndarray:
        """Shape and finiteness check; returns a float64 vector. Raises CommandError."""
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise CommandError(f"{self.spec.name}: action is not numeric: {e}") from None
        n = self.spec.action.dim
        if a.shape != (n,):
            raise CommandError(
                f"{self.spec.name}: action has shape {a.shape}, expected ({n},) = {list(self.spec.action.names)}"
            )
        bad = ~np.isfinite(a)
        if bad.any():
            names = [self.spec.action.names[i] for i in np.flatnonzero(bad)]
            raise CommandError(f"{self.spec.name}: non-finite action for {names}: {a.tolist()}")
        return a

    def limit(self, a: np.ndarray, now_s: float) -> np.ndarray:
        """Clamp to the spec's limits and rate limit relative to the held command."""
        sp = self.spec
        a = np.clip(a, sp.action.low, sp.action.high)
        rate = sp.action_rate_per_s
        if rate is not None and self._held is not None:
            dt = sp.period_s if self._last_write_t is None else max(now_s - self._last_write_t, 0.0)
            # at least one period's worth: a late write must not be frozen by a tiny dt
            dt = max(dt, sp.period_s)
            step = rate * dt
            a = np.clip(a, self._held - step, self._held + step)
        return a

    def write(self, action: Any) -> np.ndarray:
        """Validate, clamp, send. Returns the action actually applied."""
        if self._lifecycle is not Lifecycle.ACTIVE:
            raise LifecycleError(
                f"{self.spec.name}: write() refused in state {self._lifecycle.value}; call activate() first"
            )
        a = self.validate(action)
        now = self.now()
        a = self.limit(a, now)
        self._write(a)
        self._held = a
        self._last_write_t = now
        return a.copy()

    def stop(self) -> None:
        """Bring the robot to its safe state. Allowed in any state with a link."""
        if self._lifecycle is Lifecycle.UNCONFIGURED:
            return
        self._stop()
        if self.spec.safe_action is not None:
            self._held = self.spec.safe_action.copy()

    def health(self) -> Health:
        h = self._health()
        if self.last_error and not h.last_error:
            h.last_error = self.last_error
        return h

    @property
    def held_command(self) -> np.ndarray | None:
        return None if self._held is None else self._held.copy()

    # ------------------------------------------------------------------ time
    def now(self) -> float:
        """The backend clock in seconds (wall clock unless overridden by sim)."""
        return time.monotonic()

    def tick(self) -> None:
        """Wait until the next control period boundary (wall clock).

        Paced by :class:`bus.cycle.CycleTimer`: the first call waits a full period (N
        ticks span N periods); after an overrun the late tick returns at once and
        further missed periods are skipped and counted, never made up in a burst.
        """
        if self._cycle is None:
            self._cycle = CycleTimer(self.spec.period_s)
        self._cycle.wait()

    # ------------------------------------------------------------------ hooks
    def _on_configure(self) -> None:  # noqa: B027 - optional hook
        pass

    def _on_activate(self) -> None:  # noqa: B027
        pass

    def _on_deactivate(self) -> None:  # noqa: B027
        pass

    def _on_cleanup(self) -> None:  # noqa: B027
        pass

    def _hold_command(self, obs: Observation) -> np.ndarray:
        """The command that keeps the robot where it is, from a measurement."""
        if self.spec.safe_action is not None:
            return self.spec.safe_action
        return np.zeros(self.spec.action.dim)

    @abstractmethod
    def _read(self) -> Observation: ...

    @abstractmethod
    def _write(self, action: np.ndarray) -> None: ...

    @abstractmethod
    def _stop(self) -> None: ...

    def _health(self) -> Health:
        return Health(ok=self._lifecycle is not Lifecycle.UNCONFIGURED, last_error=self.last_error)

    def _require(self, state: Lifecycle, what: str) -> None:
        if self._lifecycle is not state:
            raise LifecycleError(
                f"{self.spec.name}: {what}() needs state {state.value}, driver is {self._lifecycle.value}"
            )
