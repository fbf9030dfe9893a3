"""Reset steps: the small code behind a reset procedure's data.

A step is started once per attempt (:meth:`ResetStep.start`) and then sees every robot
state (:meth:`ResetStep.update`) until it returns :data:`DONE`. It drives the robot by
returning a normalized action ([-1, 1] of the spec's limits, like every policy here)
or :data:`HOLD` (the supervisor sends the spec's safe action, or, for a robot that stops by
holding its position (safe action None: the hand), the command it holds now). It fails an attempt by
raising :class:`StepError`. The supervisor owns timeouts, retries, the e-stop and the
bus; steps own only their own motion.

Kinds (``reset.steps[].kind`` in a rig config):

- ``self_right``: hold still, then kick the legs at random until the robot is upright again.
- ``lab_fixture``: the lab puts the robot on its legs (drivers/fixture.py: the
  emulator's fixture service; on a sim the driver's teleport where the robot lies; on a
  real rig without a fixture the step fails and an operator must).
- ``drive_to_start``: drive back to the start position with the differential-drive
  baseline (control/baselines.py). For mobile robots with a pose (mocap).
- ``turn_to_yaw``: turn in place (leg sets in opposite directions) to the start heading.
- ``teleport``: ask the driver node to put the robot at the pose (sim backends only).
- ``task_reset``: run a task-reset mechanism (:class:`TaskResetMechanism`; the WidowX
  one comes with the arms issue and registers itself with :func:`register_mechanism`).
- ``arm_pick_place``: the Shadow Hand's reset arm puts the balls from the ramp's
  pick-up spot back into the palm (:class:`ArmPickPlace`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from hilstack.bus.schemas import ResetEvent, ResetPhase, RobotState
from hilstack.configs.schema import ConfigError, parse_model
from hilstack.control.baselines import DifferentialDriveController
from hilstack.control.reset.config import StepConfig
from hilstack.drivers.base import RobotSpec

#: ``update`` results besides an action: the step is over / hold (safe action or held command)
DONE = "done"
HOLD = "hold"
#: the step waits for the driver node's answer and leaves the state unanswered: a lockstep
#: driver node serves the request while it waits for that answer, so the sim does not advance
#: between the request and its effect (a hold sent meanwhile stepped it a period or not,
#: depending on which message came first)
WAIT = "wait"

StepResult = np.ndarray | str


class StepError(RuntimeError):
    """This attempt of the step failed (one line saying what); the supervisor may retry.

    ``from_start``: retrying this step cannot help, an earlier step must run again (the
    robot tipped over while driving back: self_right first). The supervisor then runs the
    procedure again from its first step, within the budget of ``verify.retries``."""

    def __init__(self, detail: str, from_start: bool = False):
        super().__init__(detail)
        self.from_start = from_start


class StepContext(Protocol):
    """What the supervisor offers a step."""

    state_names: list[str]
    #: the robot's spec, as its driver node published it (None before it arrived)
    spec: RobotSpec | None

    def robot_link(self, robot: str) -> Any:
        """Another robot of the rig (:class:`hilstack.control.reset.supervisor.RobotLink`): its state,
        spec, command key and liveliness."""

    def request_driver(self, phase: ResetPhase, pose: dict[str, float]) -> None:
        """Send the robot's driver node a reset request (``teleport``)."""

    def driver_answer(self) -> ResetEvent | None:
        """The driver node's answer to the last :meth:`request_driver`, once it came."""

    def count(self, what: str, n: int = 1) -> None:
        """Count an event for the report (``fixture_recoveries``, ``self_righted``...)."""


class StepParams(BaseModel):
    """A step's ``params`` (``reset.steps[].params``): typed, unknown keys refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ResetStep(ABC):
    """A step's ``params`` are declared as its ``Params`` model; :meth:`parse_params`
    checks them when the rig config loads (control/reset/config.py: ``load_reset``), and
    each validated param becomes an attribute of the step."""

    kind: str = "step"
    Params: type[StepParams] = StepParams

    def __init__(self, cfg: StepConfig):
        self.cfg = cfg
        self.name = cfg.kind
        self.params = self.parse_params(cfg.params, where=f"{cfg.kind}.params")
        for k in type(self.params).model_fields:
            setattr(self, k, getattr(self.params, k))

    @classmethod
    def params_model(cls) -> type[StepParams]:
        return cls.Params

    @classmethod
    def parse_params(cls, params: dict[str, Any], file: str | None = None, where: str = "params") -> StepParams:
        """``params`` validated into :attr:`Params`; a :class:`ConfigError` naming each bad
        field under ``where`` (``reset.steps[2].params``)."""
        try:
            return parse_model(cls.params_model(), params, file)
        except ConfigError as e:
            raise ConfigError(file, [(f"{where}.{loc}" if loc else where, msg) for loc, msg in e.problems]) from None

    @abstractmethod
    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        """Begin an attempt from ``state`` toward ``pose`` ({x, y, yaw}: m, m, rad)."""

    @abstractmethod
    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        """A normalized action, :data:`HOLD` or :data:`DONE`; raise :class:`StepError` to fail."""

    def abort(self) -> None:  # noqa: B027 - optional hook
        """The attempt ends early (timeout, failure, e-stop): stop whatever the step moves
        besides the robot (the supervisor stops commanding the robot itself)."""

    def verify(self, ctx: StepContext, state: RobotState) -> str:
        """After all steps, before resuming: why what this step did is not in place ('' when
        it is). The supervisor checks the robot's pose itself; a step adds its own check."""
        return ""


def turn_in_place(e_rad: float, gain: float, speed: float) -> np.ndarray:
    """Normalized (left, right) leg commands turning toward a heading error ``e_rad``
    (>0: turn left, counter-clockwise): the leg sets at ``∓clip(gain·e, ±speed)``."""
    d = float(np.clip(gain * e_rad, -speed, speed))
    return np.array([-d, d])


class DriveToStart(ResetStep):
    """Drive to the start position: turn in place toward it while the heading error is
    above ``turn_above_rad``, then follow the straight path here → start with the
    differential-drive baseline (re-planned from where the robot is if it passes the
    start: a path follower does not turn back at the end of its path). The start
    heading is the next step's job (``turn_to_yaw``).

    Params: ``speed`` (nominal normalized leg speed, default 0.6), ``tolerance_m``
    (done when this close to the start, default 0.1), ``k_heading`` (per rad, default
    0.1), ``k_perp`` (per m, default 0.5), ``d_max`` (default 0.1), ``turn_above_rad``
    (default 0.6).

    Why gains this low (the baseline's defaults are 0.8/rad, 4/m, 0.4): the VelociRoACH
    emulator turns at about 30 rad/s per unit of differential command (docs/reset.md);
    at 10 Hz with a period of lag the default gains make it spin in place.
    """

    kind = "drive_to_start"

    class Params(StepParams):
        speed: float = Field(0.6, gt=0, le=1)
        tolerance_m: float = Field(0.1, gt=0)
        k_heading: float = Field(0.1, ge=0)
        k_perp: float = Field(0.5, ge=0)
        d_max: float = Field(0.1, gt=0, le=1)
        turn_above_rad: float = Field(0.6, gt=0)

    def __init__(self, cfg: StepConfig):
        super().__init__(cfg)
        self._ctl: DifferentialDriveController | None = None
        self._goal = np.zeros(2)
        self._dir = np.array([1.0, 0.0])

    def _plan(self, here: np.ndarray) -> None:
        self._dir = self._goal - here
        self._ctl = DifferentialDriveController(np.array([here, self._goal]), self._names, omega_nom=self.speed,
                                                k_heading=self.k_heading, k_perp=self.k_perp, d_max=self.d_max)

    def _xy(self, state: RobotState) -> np.ndarray:
        s = state.state
        return np.array([s[self._names.index("x")], s[self._names.index("y")]], dtype=np.float64)

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        self._goal = np.array([pose.get("x", 0.0), pose.get("y", 0.0)])
        self._names = list(ctx.state_names)
        self._plan(self._xy(state))

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        s = np.asarray(state.state, dtype=np.float64)
        if not np.all(np.isfinite(s)):
            raise StepError("drive_to_start: the robot's state is not finite (pose lost?)")
        if not upright(self._names, s, 0.5):
            # on its side or back: driving will not bring it back; self_right (and the lab
            # fixture) may, so the procedure runs again from its start
            raise StepError("drive_to_start: the robot is not upright", from_start=True)
        p = self._xy(state)
        off = p - self._goal
        if np.linalg.norm(off) < self.tolerance_m:
            return DONE
        if float(off @ self._dir) > 0.0:
            self._plan(p)  # passed the start: come back along a new path
        e_heading, _ = self._ctl.errors(s)
        if abs(e_heading) > self.turn_above_rad:
            return turn_in_place(e_heading, self.k_heading, self.d_max)
        return np.asarray(self._ctl(s), dtype=np.float64)


def upright(names: Sequence[str], state: Sequence[float], min_cos: float) -> bool:
    """Roll and pitch both within ``acos(min_cos)`` of level (robots with ``cos_roll``,
    ``cos_pitch`` channels; others count as upright)."""
    return all(state[names.index(c)] >= min_cos for c in ("cos_roll", "cos_pitch") if c in names)


class SelfRight(ResetStep):
    """Right a robot that lies on its side or back by kicking its legs at random
    (uniform in ±``speed``, a new draw every control period). Done when it has stayed
    upright (``cos_roll`` and ``cos_pitch`` ≥ ``upright_above``) for ``settle_s``
    [s of robot time]; already upright at the start: done at once.

    First it holds the legs still for ``hold_first_s``: on the VelociRoACH MuJoCo model
    a robot caught tipping (``cos_pitch`` or ``cos_roll`` below 0.7) and stopped fell
    back onto its legs in 8 of 10 trials. Then random kicks: on the model they righted
    robots lying on their side (8 of 8 within 0.4 s; fixed patterns 3-7 of 8 within
    20 s) but not one lying on its back (docs/reset.md). Then the attempts run out, the
    rig stops and the operator is told.

    Params: ``speed`` (default 1.0), ``upright_above`` (default 0.8), ``settle_s``
    (default 0.5), ``hold_first_s`` (default 1.0), ``seed`` (default 0).
    """

    kind = "self_right"

    class Params(StepParams):
        speed: float = Field(1.0, gt=0, le=1)
        upright_above: float = Field(0.8, gt=0, le=1)
        settle_s: float = Field(0.5, ge=0)
        hold_first_s: float = Field(1.0, ge=0)
        seed: int = 0

    def __init__(self, cfg: StepConfig):
        super().__init__(cfg)
        self.rng = np.random.default_rng(self.seed)

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        self._names = list(ctx.state_names)
        self._upright_since_s: float | None = None
        self._t0_s = state.t_s
        self._was_down = not upright(self._names, state.state, self.upright_above)

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        if upright(self._names, state.state, self.upright_above):
            if self._upright_since_s is None:
                self._upright_since_s = state.t_s
            if state.t_s - self._upright_since_s < self.settle_s:
                return HOLD
            if self._was_down:
                ctx.count("self_righted")
            return DONE
        self._upright_since_s = None
        if state.t_s - self._t0_s < self.hold_first_s:
            return HOLD  # a robot caught mid-tip mostly falls back onto its legs when they stop
        return self.rng.uniform(-self.speed, self.speed, 2)


class LabFixture(ResetStep):
    """The lab puts the robot back on its legs where it lies (same x, y and heading): the
    step a real lab does by hand. Used after ``self_right`` (``optional: true``) failed:
    the MuJoCo roach on its back never righted itself, with random kicks or any fixed
    leg pattern tried (docs/reset.md). Done at once when the robot is upright.

    Where the fixture is: the robot's health names ``lab_fixture_port`` (the emulated
    VelociRoACH: the emulator's UDP service, :mod:`hilstack.drivers.fixture`); otherwise the
    driver node's teleport to where the robot lies (sim backends). A real rig has neither:
    the driver answers ``unsupported``, the step fails, the rig stops and the operator
    is told to put the robot on its legs. Each use counts as ``fixture_recoveries`` (an
    operator intervention on a real rig).

    Params: ``upright_above`` (default 0.8), ``settle_s`` (upright this long after the
    fixture acted [s of robot time], default 0.5), ``resend_s`` (ask again when no answer
    or the robot is still down this long after an answer [s], default 0.5).
    """

    kind = "lab_fixture"

    class Params(StepParams):
        upright_above: float = Field(0.8, gt=0, le=1)
        settle_s: float = Field(0.5, ge=0)
        resend_s: float = Field(0.5, gt=0)

    def __init__(self, cfg: StepConfig):
        super().__init__(cfg)
        self._client = None

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        self._names = list(ctx.state_names)
        self._asked_s: float | None = None
        self._waiting = False
        self._acted = 0
        self._upright_since_s: float | None = None

    def _ask(self, ctx: StepContext, state: RobotState) -> None:
        from hilstack.drivers.fixture import FixtureClient

        port = (state.health or {}).get("lab_fixture_port")
        if port:
            if self._client is None or self._client.address[1] != int(port):
                self.abort()
                self._client = FixtureClient(int(port))
            self._client.request("right")
        else:  # a sim: its teleport is the fixture (x, y and heading where it lies)
            n, s = self._names, state.state
            here = {"x": s[n.index("x")], "y": s[n.index("y")],
                    "yaw": math.atan2(s[n.index("sin_yaw")], s[n.index("cos_yaw")])}
            ctx.request_driver(ResetPhase.TELEPORT, here)
        self._asked_s, self._waiting = state.t_s, True

    def _answer(self, ctx: StepContext) -> tuple[bool, bool] | None:
        """(ok, acted) of the pending request, None while it is pending."""
        if self._client is not None:
            r = self._client.reply()
            if r is None:
                return None
            if not r.get("ok"):
                raise StepError(f"lab fixture: {r.get('detail', 'refused')}")
            return True, bool(r.get("acted"))
        ans = ctx.driver_answer()
        if ans is None:
            return None
        if ans.phase != ResetPhase.DONE:
            raise StepError(f"the robot is not upright and this rig has no lab fixture ({ans.phase}: {ans.detail}); "
                            "an operator must put it on its legs")
        return True, True

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        if self._waiting:
            got = self._answer(ctx)
            if got is not None:
                self._waiting = False
                self._acted += got[1]
                self._asked_s = state.t_s
        if upright(self._names, state.state, self.upright_above):
            if self._asked_s is None:
                return DONE  # upright when the step began: nothing for the fixture to do
            if self._waiting:
                return HOLD  # up, but the fixture has not said yet whether it did it
            if self._upright_since_s is None:
                self._upright_since_s = state.t_s
            if state.t_s - self._upright_since_s < self.settle_s:
                return HOLD
            if self._acted:
                ctx.count("fixture_recoveries")
            self.abort()
            return DONE
        self._upright_since_s = None
        if self._asked_s is None or state.t_s - self._asked_s >= self.resend_s:
            self._ask(ctx, state)  # first ask, a lost datagram, or still down after an answer
        return HOLD

    def abort(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


class TurnToYaw(ResetStep):
    """Turn in place to the start yaw: leg sets at ``∓k·e_ψ`` (clipped to ``speed``).

    Params: ``speed`` (max normalized leg speed, default 0.1), ``gain`` (per rad,
    default 0.1), ``tolerance_rad`` (default 0.15), ``settle_s`` (done after holding
    still within the tolerance this long [s of robot time], default 0.5).

    Why so small: the VelociRoACH emulator turns in place at about 30 rad/s per unit of
    differential command (0.6 rad/s at 0.02, 1.6 at 0.05, 2.8 at 0.1; measured on
    this rig, docs/reset.md). At 10 Hz a gain of 0.1/rad corrects ~30 % of the error
    per period, which stays stable with a period or two of radio and mocap lag.
    """

    kind = "turn_to_yaw"

    class Params(StepParams):
        speed: float = Field(0.1, gt=0, le=1)
        gain: float = Field(0.1, gt=0)
        tolerance_rad: float = Field(0.15, gt=0)
        settle_s: float = Field(0.5, ge=0)

    def __init__(self, cfg: StepConfig):
        super().__init__(cfg)
        self._inside_since_s: float | None = None

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        self._yaw = float(pose.get("yaw", 0.0))
        self._ic, self._is = ctx.state_names.index("cos_yaw"), ctx.state_names.index("sin_yaw")
        self._inside_since_s = None

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        yaw = math.atan2(state.state[self._is], state.state[self._ic])
        e = math.remainder(self._yaw - yaw, math.tau)  # >0: turn left (counter-clockwise)
        if not math.isfinite(e):
            raise StepError("turn_to_yaw: the robot's heading is not finite (pose lost?)")
        if abs(e) < self.tolerance_rad:
            # done once it stays there for settle_s: the pose lags the legs (mocap, radio)
            # and the body coasts, so a first crossing is often an overshoot
            if self._inside_since_s is None:
                self._inside_since_s = state.t_s
            return DONE if state.t_s - self._inside_since_s >= self.settle_s else HOLD
        self._inside_since_s = None
        return turn_in_place(e, self.gain, self.speed)


class Teleport(ResetStep):
    """Sim only: the driver node puts the robot at the pose (the bridge's ``reset``)."""

    kind = "teleport"

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        ctx.request_driver(ResetPhase.TELEPORT, pose)

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        ans = ctx.driver_answer()
        if ans is None:
            return WAIT
        if ans.phase != ResetPhase.DONE:
            raise StepError(f"teleport {ans.phase}: {ans.detail}")
        return DONE


class TaskResetMechanism(ABC):
    """A mechanism that resets the task, not the robot: the interface for the WidowX
    task-reset mechanism of the arms issue (thesis: two motors rotate the fixture 16°
    and translate it 2 cm). Implementations talk to their own driver on the bus."""

    @abstractmethod
    def begin(self, pose: dict[str, float]) -> None:
        """Start moving the task back to its start configuration."""

    @abstractmethod
    def poll(self) -> bool:
        """True once the task is in place; raise :class:`StepError` on a fault."""

    def abort(self) -> None:  # noqa: B027 - optional hook
        """Stop the mechanism (e-stop, timeout)."""


MECHANISMS: dict[str, Callable[[dict[str, Any]], TaskResetMechanism]] = {}


def register_mechanism(name: str, factory: Callable[[dict[str, Any]], TaskResetMechanism]) -> None:
    """Make a task-reset mechanism available to ``task_reset`` steps as ``params.mechanism``."""
    MECHANISMS[name] = factory


class TaskReset(ResetStep):
    """Run a registered :class:`TaskResetMechanism`; the robot holds still meanwhile."""

    kind = "task_reset"

    class Params(StepParams):
        #: the other params go to the mechanism, which checks them
        model_config = ConfigDict(extra="allow", frozen=True)
        mechanism: str

    def __init__(self, cfg: StepConfig):
        super().__init__(cfg)
        name = self.params.mechanism
        if name not in MECHANISMS:
            raise ValueError(
                f"task_reset: no mechanism {name!r} registered (known: {sorted(MECHANISMS)}); "
                "the WidowX mechanism comes with the arms driver"
            )
        self.mechanism = MECHANISMS[name](dict(self.params.model_extra or {}))

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        self.mechanism.begin(pose)

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        return DONE if self.mechanism.poll() else HOLD

    def abort(self) -> None:
        self.mechanism.abort()


#: the robot whose ``pick_place`` skill the ``arm_pick_place`` step runs (the registry finds it:
#: entry points ``hilstack.skills``; the script and its IK live with the arm, sim_backends/reset_arm/)
PICK_PLACE_ARM = "reset_arm"


def _pick_place():
    """The reset arm's pick-and-place module (PickPlaceConfig, PickPlaceScript, PickPlaceError)."""
    from hilstack.drivers.registry import skill

    return skill(PICK_PLACE_ARM, "pick_place")


@functools.cache
def _pick_place_params() -> type[StepParams]:
    """ArmPickPlace's params: the rig-robot name of the arm, the sync wait, and the
    script's ``PickPlaceConfig`` fields (the reset arm's ``pick_place`` skill) (its period
    comes from the arm's spec, not from the config)."""
    import typing

    from pydantic import create_model

    PickPlaceConfig = _pick_place().PickPlaceConfig
    hints = typing.get_type_hints(PickPlaceConfig, include_extras=True)  # keep the bounded types' bounds
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(PickPlaceConfig):
        if f.name == "period_s":
            continue
        if f.default is not dataclasses.MISSING:
            fields[f.name] = (hints[f.name], f.default)
        elif f.default_factory is not dataclasses.MISSING:
            fields[f.name] = (hints[f.name], Field(default_factory=f.default_factory))
        else:
            fields[f.name] = (hints[f.name], ...)
    return create_model("ArmPickPlaceParams", __base__=StepParams, arm=(str, "arm"),
                        sync_wait_s=(float, Field(0.2, ge=0)), **fields)


class ArmPickPlace(ResetStep):
    """The Shadow Hand's reset: the reset arm (its own robot on the bus, rig-robot name
    ``arm``) picks each ball from the ramp's pick-up spot and puts it in the palm
    (sim_backends/reset_arm/pick_place.py: the script, IK on MuJoCo's Jacobian). Meanwhile
    the hand holds its cupped pose. Done when both balls are in the palm and the arm is
    parked; :meth:`verify` checks both balls are in the palm before the episode resumes.

    The arm's state carries the balls' positions (the station's view: the sim's world,
    a camera tracker on a real rig). Every arm state is answered with one arm command
    (lockstep rigs advance on it); each hand state with the hold pose.

    Params (world frame, m): ``arm`` (rig-robot name, default ``arm``), ``base_pos_m``,
    ``spot_m`` (a ball at the pick-up spot), ``palm_center_m`` (where the balls start),
    optional ``spot_wait_s`` (default 5: a ball that has not reached the spot by then
    fails the attempt), ``speed_m_s``, ``joint_speed_rad_s``, ``grip_s``,
    ``in_palm_radius_m``, ``travel_z_m``, ``sync_wait_s`` (how long to wait for the arm's
    state of the same instant as the hand's, wall clock, default 0.2).
    """

    kind = "arm_pick_place"

    @classmethod
    def params_model(cls) -> type[StepParams]:
        return _pick_place_params()  # built on first use: the script's module loads MuJoCo

    def __init__(self, cfg: StepConfig):
        PickPlaceConfig = _pick_place().PickPlaceConfig
        super().__init__(cfg)
        self.pp_cfg = PickPlaceConfig(**self.params.model_dump(exclude={"arm", "sync_wait_s"}))
        self.script = None
        self._link = None
        self._hold: np.ndarray | None = None

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        PickPlaceScript = _pick_place().PickPlaceScript

        home = None if ctx.spec is None else ctx.spec.home_action
        if home is None:
            raise StepError("arm_pick_place: the robot's spec has no home_action (the pose it holds while the "
                            "arm places the balls)")
        self._link = ctx.robot_link(self.arm)
        if self._link.spec(timeout_s=2.0) is None:
            raise StepError(f"arm_pick_place: no spec from robot {self.arm!r}: is its driver node on the bus?")
        s = self._link.state(not_before_t_s=state.t_s, timeout_s=self.sync_wait_s)
        if s is None:
            raise StepError(f"arm_pick_place: no state from robot {self.arm!r}")
        if self.script is None:
            spec = self._link.spec()
            cfg = dataclasses.replace(self.pp_cfg, period_s=spec.period_s)
            self.script = PickPlaceScript(cfg)  # builds the IK model once
        self.script.start(s.t_s, np.asarray(s.state))
        self._hold = ctx.spec.action.normalize(home)

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        PickPlaceError = _pick_place().PickPlaceError
        s = self._link.state(not_before_t_s=state.t_s, timeout_s=self.sync_wait_s)
        try:
            a = self.script.update(s.t_s, np.asarray(s.state))
        except PickPlaceError as e:
            raise StepError(str(e)) from None
        if a is None:
            return DONE
        self._link.answer(s, a)
        return self._hold

    def verify(self, ctx: StepContext, state: RobotState) -> str:
        link = ctx.robot_link(self.arm)
        s = link.state()
        if s is None:
            return f"no state from robot {self.arm!r} (it sees the balls)"
        PickPlaceScript = _pick_place().PickPlaceScript
        balls = PickPlaceScript.balls(np.asarray(s.state))
        d = np.linalg.norm(balls - np.asarray(self.pp_cfg.palm_center_m), axis=1)
        out = [f"ball{i} is {d[i]:.3f} m from the palm centre" for i in range(2)
               if not d[i] <= self.pp_cfg.in_palm_radius_m]
        return "; ".join(out) + f" (tolerance {self.pp_cfg.in_palm_radius_m:g} m)" if out else ""


class LabPlace(ResetStep):
    """The lab's hands put the Baoding balls back in the Shadow Hand's palm: the hand holds its
    home pose (the spec's ``home_action``) for ``hold_s``, then the lab fixture puts both balls
    at rest in the palm; done ``settle_s`` after its answer. On the emulated hand the fixture is
    the emulator's service (drivers/fixture.py, op ``place``; its port in the driver's health,
    ``lab_fixture_port``); a real rig has none: the step fails, the rig stops and the operator
    is told to put the balls back (each use counts as ``fixture_recoveries``: on a real rig an
    operator's intervention). :meth:`verify`: both balls (the hand state's ``ball0_x`` ..
    ``ball1_z``) within ``in_palm_radius_m`` of ``palm_center_m``.

    Params: ``palm_center_m`` (world, m: the Baoding task's centre), ``in_palm_radius_m``
    (default 0.03), ``hold_s`` (default 1.0), ``settle_s`` (default 0.5), ``resend_s`` (ask
    again when no answer came this long after a request [s], default 1.0).
    """

    kind = "lab_place"

    class Params(StepParams):
        palm_center_m: tuple[float, float, float]
        in_palm_radius_m: float = Field(0.03, gt=0, le=0.2)
        hold_s: float = Field(1.0, ge=0, le=30)
        settle_s: float = Field(0.5, ge=0, le=30)
        resend_s: float = Field(1.0, gt=0, le=30)

    def __init__(self, cfg: StepConfig):
        super().__init__(cfg)
        self._client = None

    def start(self, ctx: StepContext, state: RobotState, pose: dict[str, float]) -> None:
        home = None if ctx.spec is None else ctx.spec.home_action
        if home is None:
            raise StepError("lab_place: the robot's spec has no home_action (the pose it holds while the balls "
                            "are put back)")
        self._hold = ctx.spec.action.normalize(home)
        self._t0_s = state.t_s
        self._asked_s: float | None = None
        self._placed_s: float | None = None

    def update(self, ctx: StepContext, state: RobotState) -> StepResult:
        from hilstack.drivers.fixture import FixtureClient

        t = state.t_s
        if t - self._t0_s < self.hold_s:
            return self._hold
        if self._placed_s is None:
            if self._client is not None:
                r = self._client.reply()
                if r is not None:
                    if not r.get("ok"):
                        raise StepError(f"lab fixture: {r.get('detail', 'refused')}")
                    self._placed_s = t
                    return self._hold
            if self._asked_s is None or t - self._asked_s >= self.resend_s:
                port = (state.health or {}).get("lab_fixture_port")
                if not port:
                    raise StepError("this rig has no lab fixture (no lab_fixture_port in the hand's health): an "
                                    "operator must put the balls back in the palm")
                if self._client is None or self._client.address[1] != int(port):
                    self.abort()
                    self._client = FixtureClient(int(port))
                self._client.request("place")
                self._asked_s = t
            return self._hold
        if t - self._placed_s < self.settle_s:
            return self._hold
        ctx.count("fixture_recoveries")
        self.abort()
        return DONE

    def abort(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def verify(self, ctx: StepContext, state: RobotState) -> str:
        names = list(ctx.state_names)
        try:
            idx = [names.index(f"ball{i}_{a}") for i in range(2) for a in "xyz"]
        except ValueError:
            return "the hand's state has no ball positions (objects_in_state: true)"
        balls = np.asarray(state.state)[idx].reshape(2, 3)
        d = np.linalg.norm(balls - np.asarray(self.palm_center_m), axis=1)
        out = [f"ball{i} is {d[i]:.3f} m from the palm centre" for i in range(2) if not d[i] <= self.in_palm_radius_m]
        return "; ".join(out) + f" (tolerance {self.in_palm_radius_m:g} m)" if out else ""


STEP_KINDS: dict[str, type[ResetStep]] = {
    c.kind: c for c in (SelfRight, LabFixture, DriveToStart, TurnToYaw, Teleport, TaskReset, ArmPickPlace, LabPlace)
}


def make_step(cfg: StepConfig) -> ResetStep:
    return STEP_KINDS[cfg.kind](cfg)
