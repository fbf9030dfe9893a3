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
  ``ok`` is False when any fused input is stale or non-finite; ``flags`` uses the one
  vocabulary :class:`Flag` (every backend, every robot); each input's freshness is a
  :class:`Freshness` record and ``health().extra`` carries ``<input>_age_s``.
* A frozen or dead device: an input without a usable sample for ``fail_after_s``
  (``link_timeout_periods`` control periods, bounded in each robot's config) makes
  ``read()`` and ``write()`` take the error path: stop, UNCONFIGURED, ``last_error``,
  :class:`LinkError`. Sim backends whose physics runs in the driver's own thread cannot
  freeze apart from their host (tests/test_contract.py says which).
* ``write(action)`` is refused unless ACTIVE, rejects wrong shapes and non-finite values
  with :class:`CommandError`, clamps to limits and the rate limit, and returns the
  action actually applied. The rate limit bounds the applied command over time: between
  any two applied values T seconds apart (the held command at activation included) the
  change is at most ``action_rate_per_s * max(T, period_s)``, so several writes at one
  instant together move it by at most one period's worth (see :meth:`Driver.limit`). On
  activation the held command is what the device is running (``_hold_command``, from the
  measured state and what the backend knows of the device), so nothing jumps.
* ``stop()`` brings the robot to its safe state (the spec's ``safe_action``).
* Sim controls (an optional capability, :class:`SimControls`): a simulated backend can also
  ``reset(**pose)`` (put the robot at a pose: a new episode) and, when it models them,
  set perturbations (:class:`Perturbable`). Code above the drivers asks
  :func:`sim_controls` / :func:`perturbable` instead of probing attributes; a real or emulated
  backend has neither.
* ``tick()`` waits for the next control period: wall-clock backends sleep until the
  next period boundary; the sim backend advances physics by one period. A loop written
  as ``read → write → tick`` therefore runs unchanged on every backend.
* ``pacing`` (:class:`Pacing`) is the backend's time model: whether its robot moves in
  ``tick()`` (sim) or on its own clock (real, emulated). It orders the driver node's one
  step and gives the command delay a planner predicts through.

Subclasses implement the underscore hooks; the public methods hold the checks.
"""

from __future__ import annotations

import collections
import enum
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, NoReturn, Protocol, runtime_checkable

import numpy as np

from hilstack.bus.cycle import CycleTimer


class LifecycleError(RuntimeError):
    """A call that is not allowed in the driver's current lifecycle state."""


class CommandError(ValueError):
    """An action that cannot be applied (wrong shape, NaN/inf, ...). Nothing was sent."""


class LinkError(RuntimeError):
    """The link to the device is gone or unusable (port vanished, no reply...)."""


def require_device(path: str | None, source: Any, field: str, what: str) -> None:
    """The one check every real driver makes before it opens a device its config names
    (a serial port, an slcan adapter, a camera's ``/dev/videoN``): a path that does not exist
    is a :class:`~hilstack.configs.schema.ConfigError` naming the file and ``field``, which every
    `hil` verb reports in one line with exit 2 (docs/platform.md, "Exit codes": one code for a
    missing device port on every robot; a port that exists but cannot be used, or stops
    answering, is a :class:`LinkError`, exit 1). URLs (``socket://``, ``loop://``) and
    interface names without a ``/`` (``can0``) are left to the opener."""
    if not path or "://" in path or "/" not in path:
        return
    from pathlib import Path

    if not Path(path).exists():
        from hilstack.configs.schema import ConfigError

        raise ConfigError(source, [(field, f"{path} does not exist ({what} unplugged?); `hil find-port` lists "
                                           "candidates, `hil doctor RIG` checks the rig")])


class Flag(enum.StrEnum):
    """The one vocabulary of ``Observation.flags``, shared by every backend of every robot.

    A backend reports the flags that apply to it (each True or False); a name outside this
    vocabulary is refused by :class:`Observation`. Stale and non-finite inputs also make
    ``ok`` False; device faults (watchdog, battery, motor...) are reported but the reading
    itself stays valid data.
    """

    #: the pose (mocap) is older than its deadline, or none arrived yet
    STALE_POSE = "stale_pose"
    #: the robot's telemetry is older than its deadline, or none arrived yet
    STALE_TELEMETRY = "stale_telemetry"
    #: the camera frame is older than its deadline (camera backends)
    STALE_IMAGE = "stale_image"
    #: a sample with NaN/inf arrived since the last read (it was not used), or the state has NaN/inf
    NONFINITE_INPUT = "nonfinite_input"
    #: the device's own command watchdog stopped it (no command for too long)
    WATCHDOG = "watchdog"
    #: battery below the device's cut-off
    LOW_BATTERY = "low_battery"
    #: motor stall or over-current
    MOTOR_FAULT = "motor_fault"
    #: the device rejected corrupt frames since its last report
    RX_CORRUPT = "rx_corrupt"
    #: the device's own sensor (IMU, encoder) failed to read
    SENSOR_FAULT = "sensor_fault"
    #: the simulation diverged and was reset by the physics engine: the reading is not physics
    SIM_DIVERGED = "sim_diverged"
    #: the device's own e-stop is latched (it holds its safe state until released)
    ESTOP = "estop"
    #: the driver's own watchdog (no write for too long) made it hold the measured state
    DRIVER_WATCHDOG = "driver_watchdog"
    #: tracked object positions (balls from a tracker) are older than their deadline, or missing
    STALE_OBJECTS = "stale_objects"
    #: a manipulated object left the workspace (a dropped ball)
    OBJECT_DROPPED = "object_dropped"
    #: the device reports a latched hardware error (Dynamixel: overheating, overload,
    #: input voltage, electrical shock, encoder); it needs a reboot
    HARDWARE_ERROR = "hardware_error"
    #: a sample that did not decode, was incomplete or out of its valid range (a JointState
    #: missing a joint, a zero quaternion, a pose outside the arena) arrived since the last
    #: read; it was not used and did not refresh its input
    INVALID_INPUT = "invalid_input"


FLAG_NAMES: frozenset[str] = frozenset(f.value for f in Flag)


@dataclass
class Freshness:
    """One input a backend fuses (pose, telemetry, camera frame) and its freshness deadline.

    Times are on the backend clock [s] (``Driver.now()``: monotonic wall clock for
    real/emulated backends, sim time for sim backends). ``last_t_s`` is the arrival time of
    the newest *usable* (finite) sample: a non-finite sample is not used and does not
    refresh the input (an input that only delivers NaN goes stale); it sets ``nonfinite``,
    which stays set until ``read()`` has reported it (a NaN between two reads is never
    lost), and counts in ``nonfinite_samples``. A sample that is malformed, incomplete or
    out of range is not used either (:meth:`reject`): it sets ``invalid`` (reported like
    ``nonfinite``, flag ``invalid_input``) and counts in ``invalid_samples``.

    ``fail_after_s``: an input this old (counting from :meth:`start` before the first
    sample) means the device is gone: frozen, dead, or its link dropped. The contract's
    rule (:meth:`Driver.read`, :meth:`Driver.write`) then takes the error path. Robots set
    it as ``link_timeout_periods * period_s`` (:meth:`fail_after_periods`), N finite and
    bounded in the robot's config schema.
    """

    name: str
    deadline_s: float
    stale_flag: Flag
    fail_after_s: float | None = None
    #: the clock value when the backend started waiting for this input (configure)
    since_t_s: float | None = None
    last_t_s: float | None = None
    nonfinite: bool = False
    nonfinite_samples: int = 0
    invalid: bool = False
    invalid_samples: int = 0
    #: why the newest rejected sample was not used
    last_invalid: str | None = None

    @classmethod
    def fail_after_periods(cls, name: str, deadline_s: float, stale_flag: Flag, periods: int,
                           period_s: float) -> Freshness:
        """The contract's rule for an input the device must keep sending: stale after
        ``deadline_s``, the error path after ``periods`` control periods without a usable sample."""
        if not (isinstance(periods, int) and periods >= 1 and math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"{name}: the error deadline needs a finite number of periods >= 1, got {periods} "
                             f"of {period_s} s")
        if not periods * period_s > deadline_s:
            raise ValueError(f"{name}: {periods} periods of {period_s:g} s = {periods * period_s:g} s must exceed "
                             f"the stale deadline {deadline_s:g} s")
        return cls(name, deadline_s, stale_flag, fail_after_s=periods * period_s)

    def start(self, now_s: float) -> None:
        """Forget every sample; age counts from ``now_s`` for the error deadline."""
        self.since_t_s, self.last_t_s, self.nonfinite, self.nonfinite_samples = now_s, None, False, 0
        self.invalid, self.invalid_samples, self.last_invalid = False, 0, None

    def update(self, t_s: float, finite: bool = True) -> None:
        """One sample arrived at ``t_s``; ``finite`` False: it had NaN/inf and was not used."""
        if finite:
            self.last_t_s = t_s if self.last_t_s is None else max(self.last_t_s, t_s)
        else:
            self.nonfinite = True
            self.nonfinite_samples += 1

    def reject(self, why: str) -> None:
        """A sample arrived that is malformed, incomplete or out of range: not used, it does
        not refresh the input; flagged (``invalid_input``) at the next report and counted."""
        self.invalid = True
        self.invalid_samples += 1
        self.last_invalid = why

    def age_s(self, now_s: float) -> float | None:
        """Seconds since the newest usable sample; None before the first."""
        return None if self.last_t_s is None else max(0.0, now_s - self.last_t_s)

    def stale(self, now_s: float) -> bool:
        age = self.age_s(now_s)
        return age is None or age > self.deadline_s

    def expired(self, now_s: float) -> bool:
        """Older than ``fail_after_s`` (counting from ``start`` when nothing arrived yet)."""
        if self.fail_after_s is None:
            return False
        ref = self.last_t_s if self.last_t_s is not None else self.since_t_s
        return ref is not None and now_s - ref > self.fail_after_s


class Inputs:
    """The inputs a backend fuses, assessed together for ``read()`` and ``health()``."""

    def __init__(self, *inputs: Freshness):
        self._inputs = {i.name: i for i in inputs}

    def __getitem__(self, name: str) -> Freshness:
        return self._inputs[name]

    def __iter__(self):
        return iter(self._inputs.values())

    def start(self, now_s: float) -> None:
        for i in self:
            i.start(now_s)

    def assess(self, now_s: float, report: bool = False) -> tuple[bool, dict[str, bool]]:
        """(ok, flags): each input's stale flag, ``nonfinite_input`` if a non-finite sample
        and ``invalid_input`` if a rejected one arrived since the last report; ok is False
        when any flag is set. ``read()`` passes ``report=True``, which clears the marks it
        reports."""
        flags = {i.stale_flag.value: i.stale(now_s) for i in self}
        flags[Flag.NONFINITE_INPUT.value] = any(i.nonfinite for i in self)
        flags[Flag.INVALID_INPUT.value] = any(i.invalid for i in self)
        if report:
            for i in self:
                i.nonfinite = i.invalid = False
        return not any(flags.values()), flags

    def ages(self, now_s: float) -> dict[str, float | None]:
        """``{"<input>_age_s": seconds since its newest usable sample (None: none yet),
        "<input>_nonfinite_samples": samples dropped for NaN/inf since configure,
        "<input>_invalid_samples": samples rejected as malformed/incomplete/out of range,
        "<input>_last_invalid": why the newest of those was rejected}``."""
        out: dict[str, Any] = {}
        for i in self:
            out[f"{i.name}_age_s"] = i.age_s(now_s)
            out[f"{i.name}_nonfinite_samples"] = i.nonfinite_samples
            out[f"{i.name}_invalid_samples"] = i.invalid_samples
            out[f"{i.name}_last_invalid"] = i.last_invalid
        return out

    def expired(self, now_s: float) -> Freshness | None:
        """The first input past its error deadline, if any."""
        return next((i for i in self if i.expired(now_s)), None)


class Pacing(enum.StrEnum):
    """The time model of a robot as a rig runs it: when it moves relative to the contract's
    calls, and who paces the driver node's loop. The spec carries it (``RobotSpec.pacing``:
    the driver stamps its backend's, the driver node the one it runs, on the bus), so
    nodes above the bus read it from the spec instead of deciding it again.

    One read → update → write loop runs every backend (the driver node's ``step``,
    drivers/bridge.py); the pacing decides only the order of its parts, what paces it and
    how many control periods a command lands after the state it was planned from (as
    ros2_control puts blocking, simulated or periodic time in a pacing policy, not in the
    loop).

    * ``STEPPED`` (sim backends; a rig's ``pace: realtime``): the world stands still between
      calls and advances one period in ``tick()``; the driver node ticks on the wall clock.
      The loop applies the newest command, ticks, then reads: the state published at
      period k+1 is the effect of the command planned from the state of period k. Command
      delay 0.
    * ``LOCKSTEP`` (sim backends; a rig's ``pace: lockstep``): stepped as above, but the
      driver node ticks when the command answering the last published state arrives, so a
      rig runs as fast as its nodes answer. The controller answers every state. Command
      delay 0.
    * ``WALL_CLOCK`` (real, emulated): the device moves on its own clock, under the command
      it holds. The loop reads and publishes first (the state the previous period's command
      produced), then applies the newest command, which acts during the next period: the
      command planned from the state of period k lands at period k+1, while the one sent
      before it acts. Command delay 1. (Applying before reading stamped every state with a
      command that had not acted yet: recorded transitions one period off; docs/mbrl.md.)
    * ``FOLLOWER`` (a sim backend that declares a :class:`Follower`, in a rig's ``pace:
      lockstep``): stepped as ``LOCKSTEP``, but its world is another sim's (the Shadow
      Hand's reset arm in the hand's scene) and that sim's node advances it: ``tick()``
      waits for the world to advance one period. The driver node waits at most the
      follower's ``command_wait_s`` for the answer to its last state, then steps with the
      command it holds, so its states keep coming while nobody commands it and the world's
      time steps are the leader's alone. Command delay 0.
    """

    STEPPED = "stepped"
    LOCKSTEP = "lockstep"
    WALL_CLOCK = "wall_clock"
    FOLLOWER = "follower"

    @classmethod
    def of_backend(cls, backend: str, pace: str = "realtime", follower: bool = False) -> Pacing:
        """The pacing of a backend kind ("sim", "emulated", "real") run at a rig's ``pace``
        ("realtime" or "lockstep"): the one place that maps them. Lockstep needs a sim;
        ``follower``: the backend declares a :class:`Follower` (``Driver.follower``)."""
        if backend == "sim":
            if pace != "lockstep":
                return cls.STEPPED
            return cls.FOLLOWER if follower else cls.LOCKSTEP
        if pace == "lockstep":
            raise ValueError(f"pace 'lockstep' needs a sim backend, not {backend!r}")
        return cls.WALL_CLOCK

    @property
    def answered(self) -> bool:
        """The driver node steps on the answer to its last published state, not on the wall
        clock (``LOCKSTEP``; ``FOLLOWER`` waits for it at most its command wait): a controller
        answers every state, staleness is robot time and a plan has no wall-clock deadline."""
        return self in (Pacing.LOCKSTEP, Pacing.FOLLOWER)

    @property
    def stepped(self) -> bool:
        """The world advances only in ``tick()`` (a sim backend, lockstep or not)."""
        return self is not Pacing.WALL_CLOCK

    @property
    def read_before_apply(self) -> bool:
        """The loop reads and publishes before applying the newest command (the device moved
        during the period that just ended); else it applies, ticks, then reads."""
        return self is Pacing.WALL_CLOCK

    @property
    def command_delay_periods(self) -> int:
        """Commands already on their way when a state is published: a plan from that state
        starts acting after this many periods (the MPC predicts through them first)."""
        return 1 if self is Pacing.WALL_CLOCK else 0


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

    # -- normalization: the one place an action (or state) maps onto [-1, 1] --------------
    def _finite_box(self) -> tuple[np.ndarray, np.ndarray]:
        if not (np.all(np.isfinite(self.low)) and np.all(np.isfinite(self.high))):
            bad = [n for n, lo, hi in zip(self.names, self.low, self.high, strict=True)
                   if not (math.isfinite(lo) and math.isfinite(hi))]
            raise ValueError(f"channels {bad} are unbounded: no normalized range")
        return (self.high + self.low) / 2, (self.high - self.low) / 2

    def normalize(self, x: Any) -> np.ndarray:
        """Values in the space's units → normalized: ``[low, high]`` onto ``[-1, 1]`` per
        channel, symmetric about the centre (not clipped: a value outside stays outside)."""
        mid, half = self._finite_box()
        return (np.asarray(x, dtype=np.float64) - mid) / half

    def denormalize(self, x_norm: Any) -> np.ndarray:
        """Normalized → the space's units, clipped to ``[-1, 1]`` first (so to ``[low, high]``)."""
        mid, half = self._finite_box()
        return mid + half * np.clip(np.asarray(x_norm, dtype=np.float64), -1.0, 1.0)

    def to_dict(self) -> dict[str, Any]:
        return {"names": list(self.names), "units": list(self.units),
                "low": [float(x) for x in self.low], "high": [float(x) for x in self.high]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Space:
        return cls(tuple(d["names"]), tuple(d["units"]), np.array(d["low"], float), np.array(d["high"], float))

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
    #: the action of the robot's home pose, where its episodes start (the hand's cupped hold
    #: pose), in the action space's units; None: the robot has none
    home_action: np.ndarray | None = None
    #: the kinematic chain for viewers, base to tip: (joint, its link's offset from the parent
    #: link [m], rotation axis); joint angles are the state channels ``<joint>_pos`` (or
    #: ``<joint>``) in rad. Recordings derive each link's frame transform from it (bus/recording.py)
    chain: tuple[tuple[str, tuple[float, float, float], tuple[float, float, float]], ...] = ()
    #: the time model the robot runs in (:class:`Pacing`): a driver's spec carries its
    #: backend's (``Driver.spec``), the spec a driver node publishes the one it runs (lockstep
    #: or not); None only in a spec built by hand or read from a recording made before
    #: specs carried it
    pacing: Pacing | None = None

    def __post_init__(self) -> None:
        if not (self.period_s > 0 and math.isfinite(self.period_s)):
            raise ValueError(f"period_s must be a positive number, got {self.period_s}")
        if self.pacing is not None:
            object.__setattr__(self, "pacing", Pacing(self.pacing))
        for attr in ("action_rate_per_s", "safe_action", "home_action"):
            v = getattr(self, attr)
            if v is not None:
                v = np.asarray(v, dtype=np.float64).reshape(-1)
                if v.shape != (self.action.dim,):
                    raise ValueError(f"{attr} has {v.size} entries, action space has {self.action.dim}")
                object.__setattr__(self, attr, v)

    def max_step_normalized(self) -> np.ndarray | None:
        """The action rate limit as the largest change per control period in normalized
        action units (``[-1, 1]`` spans each channel's range: ``rate · period_s / half
        range``), or None when the robot has none. Planners bound their sequences by it."""
        if self.action_rate_per_s is None:
            return None
        _, half = self.action._finite_box()
        return self.action_rate_per_s * self.period_s / half

    def to_dict(self) -> dict[str, Any]:
        """The spec as it crosses the bus (``SpecMsg.spec``) and sits in recordings."""
        return {
            "name": self.name,
            "period_s": self.period_s,
            "state": self.state.to_dict(),
            "action": self.action.to_dict(),
            "action_rate_per_s": None
            if self.action_rate_per_s is None
            else [float(x) for x in self.action_rate_per_s],
            # None: the robot stops by holding its measured position (hand, arm joints)
            "safe_action": None if self.safe_action is None else [float(x) for x in self.safe_action],
            "home_action": None if self.home_action is None else [float(x) for x in self.home_action],
            **({"chain": [{"joint": j, "xyz": [float(v) for v in xyz], "axis": [float(v) for v in ax]}
                          for j, xyz, ax in self.chain]} if self.chain else {}),
            **({"pacing": self.pacing.value} if self.pacing is not None else {}),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RobotSpec:
        """The typed spec again, from :meth:`to_dict`'s dict (a ``SpecMsg`` from the bus, a
        recording). A malformed one is a ValueError naming what is wrong."""
        try:
            return cls(
                name=str(d["name"]),
                state=Space.from_dict(d["state"]),
                action=Space.from_dict(d["action"]),
                period_s=float(d["period_s"]),
                action_rate_per_s=None if d.get("action_rate_per_s") is None
                else np.array(d["action_rate_per_s"], float),
                safe_action=None if d.get("safe_action") is None else np.array(d["safe_action"], float),
                home_action=None if d.get("home_action") is None else np.array(d["home_action"], float),
                description=str(d.get("description", "")),
                chain=tuple((str(c["joint"]), tuple(float(v) for v in c["xyz"]), tuple(float(v) for v in c["axis"]))
                            for c in d.get("chain") or ()),
                pacing=None if d.get("pacing") is None else _pacing(d["pacing"]),
            )
        except KeyError as e:
            raise ValueError(f"robot spec {d.get('name', '?')!r}: missing {e}") from None
        except (TypeError, ValueError) as e:
            raise ValueError(f"robot spec {d.get('name', '?') if isinstance(d, dict) else d!r}: {e}") from None

    def with_pacing(self, pacing: Pacing) -> RobotSpec:
        """The same spec in another time model (the driver node's lockstep pace)."""
        return self if self.pacing is pacing else replace(self, pacing=pacing)

    def joint_names(self) -> list[str]:
        """The joints of a joint-space robot: the state channels ``<joint>_pos``, in order."""
        return [n[: -len("_pos")] for n in self.state.names if n.endswith("_pos")]


#: the longest a follower's driver node waits for a command before it steps on [s, wall]
MAX_FOLLOW_COMMAND_WAIT_S = 1.0


@dataclass(frozen=True)
class Follower:
    """Declared by a sim backend that works in another sim backend's world and follows its
    clock (``Driver.follower``; the Shadow Hand's reset arm joins the hand's scene, and its
    ``tick()`` waits until the hand's driver node has advanced the scene one period). A
    driver node runs it at ``pace: lockstep`` as :attr:`Pacing.FOLLOWER`.

    ``command_wait_s``: how long that node waits [s, wall clock] for the command answering
    its last state before it steps with the one it holds; idle, it so still publishes every
    period of the world (a drop detector watching the arm's ball channels sees a drop
    without lag). Finite, in ``(0, MAX_FOLLOW_COMMAND_WAIT_S]``."""

    command_wait_s: float

    def __post_init__(self) -> None:
        w = self.command_wait_s
        if not (isinstance(w, (int, float)) and math.isfinite(w) and 0 < w <= MAX_FOLLOW_COMMAND_WAIT_S):
            raise ValueError(f"Follower.command_wait_s must be a number in (0, {MAX_FOLLOW_COMMAND_WAIT_S:g}] s, "
                             f"got {w!r}")


def _pacing(value: Any) -> Pacing:
    try:
        return Pacing(value)
    except ValueError:
        raise ValueError(f"pacing {value!r} is not one of {[p.value for p in Pacing]}") from None


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
    #: the device's own clock when its data were sampled [s], for devices that report one (a
    #: Dynamixel's Realtime Tick, unwrapped); None otherwise. Its origin is the device's, not
    #: ``t_s``'s: differences between readings are exact where ``t_s`` (stamped by the host when
    #: a read returns) carries the link's latency and jitter.
    device_t_s: float | None = None

    def __post_init__(self) -> None:
        unknown = sorted(set(self.flags) - FLAG_NAMES)
        if unknown:
            raise ValueError(f"observation flags {unknown} are not in the contract's vocabulary "
                             f"(hilstack.drivers.base.Flag): {sorted(FLAG_NAMES)}")
        # plain str keys (not Flag members): they serialize the same everywhere
        self.flags = {str(k): bool(v) for k, v in self.flags.items()}

    def flag(self, name: Flag | str) -> bool:
        """The flag's value; False when this backend does not report it."""
        return self.flags.get(str(name), False)


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


@runtime_checkable
class SimControls(Protocol):
    """Optional capability of a simulated backend (every ``LockstepSim``): put the robot at a
    pose, at rest, as a new episode starts (keywords are the robot's: ``x, y, yaw`` for the
    roach, a joint vector for the hand...; a pose it cannot take raises TypeError/ValueError)."""

    def reset(self, **pose: Any) -> None: ...


@runtime_checkable
class Perturbable(Protocol):
    """Optional capability of a simulated backend that models perturbations (the roach's
    missing leg, payload, slope...): one by name, or a whole condition
    (:class:`hilstack.tasks.perturbations.PerturbationSettings`), mid-episode included."""

    def set_perturbation(self, name: str, value: Any) -> None: ...

    def apply_perturbations(self, settings: Any) -> None: ...


def sim_controls(driver: Driver) -> SimControls | None:
    """The driver's sim controls, or None when it has none (real and emulated backends)."""
    return driver if driver.backend == "sim" and isinstance(driver, SimControls) else None


def perturbable(driver: Driver) -> Perturbable | None:
    """The driver's perturbation controls, or None when it models none."""
    return driver if sim_controls(driver) is not None and isinstance(driver, Perturbable) else None


class Driver(ABC):
    """Base of every backend. Subclasses set ``spec`` in ``__init__`` (no I/O there).

    A backend registered for a config (``hilstack.backends`` entry points) names its params
    model in ``params_type``; :meth:`from_config` is then written once, here. Its
    constructor takes ``(params, backend=..., source=...)`` (a real driver serves "real"
    and "emulated"), or ``(params, source=...)`` for a sim backend (class ``backend = "sim"``)."""

    #: "real", "emulated" or "sim"
    backend: str = "real"
    #: the pydantic model of the robot config's ``params:`` section (configs/schema.py:
    #: ``Params``); None for a backend that is not built from a config
    params_type: ClassVar[type | None] = None
    #: the inputs the backend fuses (None: none). Any of them past its ``fail_after_s`` is a
    #: dead device: ``read()`` and ``write()`` take the error path (:meth:`_expire_inputs`)
    inputs: Inputs | None = None
    #: a sim backend that works in another sim's world and follows its clock declares how
    #: (:class:`Follower`; a driver node runs it at ``pace: lockstep`` as ``Pacing.FOLLOWER``,
    #: and ``hil up`` runs it in one process with the rig's other sims); None: it owns its clock
    follower: ClassVar[Follower | None] = None

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        if cls.follower is not None and not (isinstance(cls.follower, Follower) and cls.backend == "sim"):
            raise TypeError(f"{cls.__name__}.follower must be a Follower on a sim backend "
                            f"(backend {cls.backend!r}, follower {cls.follower!r}): only a sim follows another's world")

    def __init__(self) -> None:
        self._lifecycle = Lifecycle.UNCONFIGURED
        self._failing = False  # inside fail_link(): the stop it sends must not re-enter
        self._held: np.ndarray | None = None
        # rate-limit references (see ``limit``): anchor time, applied values of the last
        # period as (t, value), and per channel min of a(s) - r·(s - t0) and max of
        # a(s) + r·(s - t0) over the older ones
        self._rate_t0_s: float | None = None
        self._rate_last_t_s: float | None = None
        self._rate_recent: collections.deque[tuple[float, np.ndarray]] = collections.deque()
        self._rate_min: np.ndarray | None = None
        self._rate_max: np.ndarray | None = None
        self._cycle: CycleTimer | None = None  # paces tick() on the wall clock
        self.last_error: str | None = None

    @classmethod
    def from_config(cls, cfg: Any) -> Driver:
        """The backend of a validated robot config (``configs.schema.RobotConfig``): its
        ``params`` parsed into :attr:`params_type` (errors name the file and
        ``params.<field>``), its backend kind and source file passed on."""
        if cls.params_type is None:
            raise TypeError(f"{cls.__name__} cannot be built from a config: it sets no params_type")
        from hilstack.configs.schema import parse_params

        params = parse_params(cfg, cls.params_type)
        if cls.backend == "sim":  # a sim backend is one kind only
            return cls(params, source=cfg.source)
        return cls(params, backend=cfg.backend, source=cfg.source)

    # ------------------------------------------------------------------ spec
    @property
    def spec(self) -> RobotSpec:
        """The robot's spec with this backend's :attr:`pacing` (readable before connecting)."""
        if self._spec_backend != self.backend:  # stamped once per backend kind (read in every write)
            self._spec = self._spec.with_pacing(self.pacing)
            self._spec_backend = self.backend
        return self._spec

    @spec.setter
    def spec(self, value: RobotSpec) -> None:
        self._spec = value
        self._spec_backend: str | None = None

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
            self._anchor(np.asarray(self._hold_command(obs), dtype=np.float64), self.now())
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

    def fail_link(self, error: BaseException | str) -> NoReturn:
        """A backend found its link or device unusable: take the error path once (re-entry
        from the stop it sends is guarded), then raise :class:`LinkError` with ``error``."""
        if not self._failing and self._lifecycle is not Lifecycle.UNCONFIGURED:
            self._failing = True
            try:
                self.fail(error)
            finally:
                self._failing = False
        if isinstance(error, LinkError):
            raise error
        raise LinkError(str(error))

    def fail(self, error: BaseException | str) -> None:
        """The error path: stop the robot (best effort), close, go UNCONFIGURED.

        ``_stop`` must send the stop whenever the port is still open, whatever failed
        (a crashed reader thread, a frozen robot): only a dead link excuses it."""
        self.last_error = str(error)
        try:
            # a position robot holds its held target, as stop() does: the measured pose of a
            # device that stopped answering is stale, and holding it would be a jump back
            if not self._hold_held_target():
                self._stop()
        except Exception as e:  # the link may be the thing that failed; keep going to cleanup
            self.last_error = f"{self.last_error}; the stop was not sent: {type(e).__name__}: {e}"
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
        try:
            obs = self._read()
        except LinkError as e:  # a backend whose link died mid-call: the error path, whoever raised
            self.fail_link(e)
        self._expire_inputs()
        if not np.all(np.isfinite(obs.state)):
            # whatever the backend missed: NaN/inf in the state is never a healthy reading
            obs.ok = False
            obs.flags[Flag.NONFINITE_INPUT.value] = True
        return obs

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
        """Clamp to the spec's limits and to the rate limit; ``now_s`` on the backend clock.

        The rate limit is a property of the applied command over time, not of one write:
        with r = ``action_rate_per_s`` and p = ``period_s``, every applied value a(t) keeps
        |a(t) - a(s)| <= r·max(t - s, p) against every earlier applied value a(s) since the
        last anchor (activation, stop, or the clock going back on a sim reset). Writes
        within one period therefore move it by at most r·p together, one write after
        another at the control rate by r·p each, and over T seconds by at most
        r·max(T, p) <= r·(T + p).

        References younger than p are kept as they are (bound r·p); older ones are folded
        into two running extremes per channel, because r·(t - s) is linear in t:
        min_s(a(s) - r·s) and max_s(a(s) + r·s), with s relative to the anchor time.
        """
        sp = self.spec
        a = np.clip(a, sp.action.low, sp.action.high)
        rate = sp.action_rate_per_s
        if rate is None or self._held is None:
            return a
        if self._rate_t0_s is None or now_s < self._rate_last_t_s:
            self._anchor(self._held, now_s)  # the clock went back (sim reset): restart from the held command
        self._fold_references(now_s)
        lim = np.isfinite(rate)
        r = rate[lim]
        step = r * sp.period_s
        hi = self._rate_min[lim] + r * (now_s - self._rate_t0_s)
        lo = self._rate_max[lim] - r * (now_s - self._rate_t0_s)
        if self._rate_recent:
            recent = np.array([v[lim] for _, v in self._rate_recent])
            hi = np.minimum(hi, recent.min(axis=0) + step)
            lo = np.maximum(lo, recent.max(axis=0) - step)
        # the held command lies in [lo, hi] by construction; min/max keep that under rounding
        held = self._held[lim]
        a[lim] = np.minimum(np.maximum(a[lim], np.minimum(lo, held)), np.maximum(hi, held))
        return np.clip(a, sp.action.low, sp.action.high)

    #: more references than this within one period (a tight write loop): the oldest are
    #: folded early, which only makes the limit stricter
    _MAX_RECENT_REFERENCES = 256

    def _fold_references(self, now_s: float) -> None:
        rate = self.spec.action_rate_per_s
        p = self.spec.period_s
        q = self._rate_recent
        while q and (now_s - q[0][0] >= p or len(q) > self._MAX_RECENT_REFERENCES):
            s, v = q.popleft()
            ds = np.where(np.isfinite(rate), rate, 0.0) * (s - self._rate_t0_s)
            self._rate_min = np.minimum(self._rate_min, v - ds)
            self._rate_max = np.maximum(self._rate_max, v + ds)

    def _anchor(self, value: np.ndarray, now_s: float) -> None:
        """Make ``value`` the held command and the only rate-limit reference.

        The reference is dated one period before ``now_s``, as if the held command had
        been applied in the period that just ended: the first write may then move one
        step, the next one period later a second step. Dated ``now_s`` it would share an
        instant with the first write and stall a ramp for one period."""
        self._held = np.array(value, dtype=np.float64)
        t0 = now_s - self.spec.period_s
        self._rate_t0_s = t0
        self._rate_last_t_s = now_s
        self._rate_recent = collections.deque([(t0, self._held.copy())])
        self._rate_min = np.full(self._held.shape, np.inf)
        self._rate_max = np.full(self._held.shape, -np.inf)

    def _record_applied(self, a: np.ndarray, now_s: float) -> None:
        self._held = a.copy()
        if self.spec.action_rate_per_s is not None and self._rate_t0_s is not None:
            self._rate_recent.append((now_s, a.copy()))
            self._rate_last_t_s = now_s

    def write(self, action: Any) -> np.ndarray:
        """Validate, clamp, send. Returns the action actually applied."""
        if self._lifecycle is not Lifecycle.ACTIVE:
            raise LifecycleError(
                f"{self.spec.name}: write() refused in state {self._lifecycle.value}; call activate() first"
            )
        a = self.validate(action)
        self._refresh_inputs()
        self._expire_inputs()  # never command a robot that stopped answering
        now = self.now()
        a = self.limit(a, now)
        try:
            self._write(a)
        except LinkError as e:  # e.g. the port's write failed (device killed): stop, UNCONFIGURED
            self.fail_link(e)
        self._record_applied(a, now)
        return a.copy()

    def stop(self) -> None:
        """Bring the robot to its safe state. Allowed in any state with a link.

        With a ``safe_action`` (zero leg velocity...) the stop is not rate limited (safety
        first). Without one (position control) the robot holds its held command, the last
        target it was sent (the rate limit already bounded it), so nothing jumps and no
        measurement is used: a stale measured pose would be a jump back to where the robot
        was. A driver that is not ACTIVE (no held command of this activation), or whose device
        refuses that target, holds its measured position (``_stop()``). The rate limit
        restarts from what is held."""
        if self._lifecycle is Lifecycle.UNCONFIGURED:
            return
        held = self._held.copy() if self._hold_held_target() else None
        if held is None:
            held = self._stop()
        if held is None:
            held = self.spec.safe_action
        if held is not None:
            self._anchor(held, self.now())

    def _hold_held_target(self) -> bool:
        """A position robot (no ``safe_action``) that is ACTIVE re-sends its held target
        (:meth:`_hold_target`); True when it did. A refused target (the device's own
        limits) is False, so the caller falls back to the backend's ``_stop()``; a dead link
        raises :class:`LinkError`."""
        if self.spec.safe_action is not None or self._held is None or self._lifecycle is not Lifecycle.ACTIVE:
            return False
        try:
            self._hold_target(self._held)
        except LinkError:
            raise
        except Exception:  # the device refused the target: its own stop
            return False
        return True

    def _hold_target(self, target: np.ndarray) -> None:
        """The stop of a position robot: send its held target again (default: as a write).
        Backends that can read the hold back override it and set what ``stop_confirmed`` says."""
        self._write(target)

    def stop_confirmed(self) -> bool:
        """Whether the device itself confirmed the safe state of the last ``stop()`` (the
        e-stop acknowledgement reports it). Default: the link is healthy now (``health().ok``:
        every input within its deadline); backends that can read the device's stop back
        override it (Dynamixel robots)."""
        try:
            return self._lifecycle is not Lifecycle.UNCONFIGURED and bool(self.health().ok)
        except Exception:
            return False

    def _rehold(self) -> None:
        """After the device's state was changed behind the contract (a sim reset), hold what
        it now runs, anchored at the current time. No-op unless ACTIVE."""
        if self._lifecycle is Lifecycle.ACTIVE:
            self._anchor(np.asarray(self._hold_command(self._read()), dtype=np.float64), self.now())

    def _expire_inputs(self) -> None:
        """The contract's rule for a frozen or dead device: an input that delivered no usable
        sample for its ``fail_after_s`` (``link_timeout_periods`` control periods) while the
        link is open takes the error path: the stop is sent (if the port still takes it),
        the link closed, UNCONFIGURED, ``last_error`` set, :class:`LinkError` raised."""
        if self.inputs is None or self._lifecycle is Lifecycle.UNCONFIGURED:
            return
        now = self.now()
        gone = self.inputs.expired(now)
        if gone is None:
            return
        age = gone.age_s(now)
        since = "since the link came up" if age is None else f"for {age:.2f} s"
        periods = round(gone.fail_after_s / self.spec.period_s)
        self.fail_link(f"{self.spec.name}: no usable {gone.name} {since} (limit: {periods} control periods of "
                       f"{self.spec.period_s:g} s = {gone.fail_after_s:g} s) while the link is open: the device "
                       "is frozen, switched off or unreachable")

    def health(self) -> Health:
        h = self._health()
        if self.last_error and not h.last_error:
            h.last_error = self.last_error
        return h

    @property
    def pacing(self) -> Pacing:
        """This backend's time model (:class:`Pacing`): the driver node's loop order and the
        command delay a planner must predict through."""
        return self.pacing_at("realtime")

    def pacing_at(self, pace: str) -> Pacing:
        """The time model a driver node runs this backend in at a rig's ``pace`` ("realtime"
        or "lockstep"; lockstep needs a sim, ValueError otherwise): ``FOLLOWER`` for a
        declared :attr:`follower` in lockstep."""
        return Pacing.of_backend(self.backend, pace, follower=self.follower is not None)

    @classmethod
    def shared_bus_key(cls, cfg: Any) -> str | None:
        """Robots whose configs (``configs.schema.RobotConfig``) give the same key share one
        device port and must run in one process (``hil up`` groups them: the WidowX and its
        reset mechanism on one Dynamixel adapter); None (the default): the robot owns its link."""
        return None

    def tracking_error(self, state: np.ndarray, action: np.ndarray) -> dict | None:
        """How well a joint-space robot tracked ``action`` (what `hil drive` prints: the
        measured ``state`` against the commanded targets), or None (the default) when the
        robot does not report it."""
        return None

    @property
    def held_command(self) -> np.ndarray | None:
        return None if self._held is None else self._held.copy()

    # ------------------------------------------------------------------ time
    def now(self) -> float:
        """The backend clock in seconds (wall clock unless overridden by sim)."""
        return time.monotonic()

    def tick(self) -> None:
        """Wait until the next control period boundary (wall clock).

        Paced by :class:`hilstack.bus.cycle.CycleTimer`: the first call waits a full period (N
        ticks span N periods); after an overrun the late tick returns at once and
        further missed periods are skipped and counted, never made up in a burst.
        """
        if self._cycle is None:
            self._cycle = CycleTimer(self.spec.period_s)
        self._cycle.wait()

    def tick_ready(self, timeout_s: float) -> bool:
        """Wait at most ``timeout_s`` [s, wall clock] until :meth:`tick` can return at once;
        True when it can. Only a :class:`Follower` waits in ``tick()`` on something outside
        its node (another node advancing its world), and its driver node calls this in short
        slices first, serving e-stops between them, so a world that stands still cannot hold
        an e-stop's acknowledgement back. The default (a backend that paces itself): True."""
        return True

    # ------------------------------------------------------------------ hooks
    def _on_configure(self) -> None:  # noqa: B027 - optional hook
        pass

    def _refresh_inputs(self) -> None:  # noqa: B027
        """Take in what arrived (backends that poll their link in ``_read``), so that
        ``write()`` judges the inputs' ages on the newest samples."""

    def _on_activate(self) -> None:  # noqa: B027
        pass

    def _on_deactivate(self) -> None:  # noqa: B027
        pass

    def _on_cleanup(self) -> None:  # noqa: B027
        pass

    def _hold_command(self, obs: Observation) -> np.ndarray:
        """The command the device is running now (from the measurement ``obs`` and what the
        backend knows of the device), so that activation changes nothing. The default, the
        safe action, is right only for devices that run it whenever they are not commanded;
        a device without one (position control: "hold where you are") must say what it runs,
        since zeros would command a jump."""
        if self.spec.safe_action is not None:
            return self.spec.safe_action
        if self.spec.action.dim == 0:
            return np.zeros(0)  # a sensor
        raise NotImplementedError(
            f"{self.spec.name}: no safe action, so _hold_command must return what the device runs "
            "(e.g. the measured joint positions)")

    @abstractmethod
    def _read(self) -> Observation: ...

    @abstractmethod
    def _write(self, action: np.ndarray) -> None: ...

    @abstractmethod
    def _stop(self) -> np.ndarray | None:
        """Bring the device to its safe state. Robots without a fixed ``safe_action`` (hold
        the measured position) return the command they now hold, so the held command and
        the rate limit restart from it."""

    def _health(self) -> Health:
        return Health(ok=self._lifecycle is not Lifecycle.UNCONFIGURED, last_error=self.last_error)

    def _require(self, state: Lifecycle, what: str) -> None:
        if self._lifecycle is not state:
            raise LifecycleError(
                f"{self.spec.name}: {what}() needs state {state.value}, driver is {self._lifecycle.value}"
            )
