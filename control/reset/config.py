"""The ``reset:`` section of a rig config: a reset procedure as data.

Validated with pydantic at the edge (``load_reset``); errors name the rig file and the
field. Example (configs/rigs/roach_emulated.yaml)::

    reset:
      robot: roach
      start_pose: {x: 0.0, y: 0.0, yaw: 0.0}
      detectors:
        - {kind: arena, radius_m: 2.5}
        - {kind: timeout, max_s: 30}
      steps:
        - {kind: drive_to_start, timeout_s: 40, retries: 1, params: {speed: 0.6}}
      verify: {position_tol_m: 0.25, yaw_tol_rad: 0.8}

Times are robot time (``RobotState.t_s``): the wall clock on real and emulated rigs,
sim time on lockstep rigs.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from hilstack.configs.schema import (
    ConfigError,
    FailAfterS,
    RigConfig,
    Strict,
    TimeoutS,
    bounded_int,
    finite,
    parse_model,
)

#: an arena's radius [m]
ArenaRadiusM = finite(gt=0, le=20.0, source="≤ 20 m: larger than any lab's motion-capture volume (the mocap's ±10 m)")
#: a position tolerance [m]
PositionTolM = finite(gt=0, le=2.0, source="≤ 2 m: a looser tolerance accepts a robot outside the roach's 2.5 m arena")
#: a heading tolerance [rad]
YawTolRad = finite(gt=0, le=3.141592653589793, source="≤ π: any heading is within π")
#: a height [m]
HeightM = finite(ge=-10.0, le=10.0, source="within the mocap volume's ±10 m")
#: a planar position [m]
PlanarM = finite(ge=-20.0, le=20.0, source="within 20 m of the origin: beyond any lab's motion-capture volume")
#: retries of a step or of the whole procedure
Retries = bounded_int(ge=0, le=10, source="≤ 10: each retry moves the robot again; a step failing 11 times is broken")


class DetectorConfig(Strict):
    """One episode-end detector (control/reset/detectors.py)."""

    kind: Literal["timeout", "arena", "tipped", "drop"]
    #: timeout: episode length [s of robot time]
    max_s: TimeoutS | None = None
    #: arena: radius [m] around ``center_xy_m`` (world frame, the mocap's)
    radius_m: ArenaRadiusM | None = None
    center_xy_m: tuple[PlanarM, PlanarM] = (0.0, 0.0)
    #: tipped: cos_roll or cos_pitch below this ends the episode
    min_cos: float = Field(0.5, ge=-1, le=1)
    #: drop: state channels holding heights [m] (e.g. each ball's z in the hand frame)
    channels: list[str] = Field(default_factory=list)
    #: drop: a channel below this height [m] means a drop
    min_height_m: HeightM | None = None
    #: watch this robot's state instead of the reset robot's (the hand rig: the balls are
    #: in the reset arm's state, which sees them; a camera tracker's, when it is a robot)
    robot: str | None = None


class StepConfig(Strict):
    """One reset step (control/reset/steps.py): ``kind`` picks the code, ``params`` tune it."""

    kind: str
    #: per attempt [s of robot time]
    timeout_s: TimeoutS = 30.0
    #: extra attempts after a timeout or a step error
    retries: Retries = 0
    #: when every attempt failed, go on with the next step (``skip``) instead of failing
    #: the reset: a best-effort step that a later one backs up (self_right → lab_fixture)
    optional: bool = False
    params: dict[str, Any] = Field(default_factory=dict)


class VerifyConfig(Strict):
    """What "reset done" means: the robot is at the start pose, within tolerances."""

    position_tol_m: PositionTolM = 0.25
    yaw_tol_rad: YawTolRad | None = None
    #: whole-procedure attempts after a failed verification
    retries: Retries = 0


class ResetConfig(Strict):
    robot: str
    #: where a reset puts the robot when the request names no pose ({x, y, yaw}: m, m, rad)
    start_pose: dict[str, PlanarM] = Field(default_factory=lambda: {"x": 0.0, "y": 0.0, "yaw": 0.0})
    detectors: list[DetectorConfig] = Field(default_factory=list)
    steps: list[StepConfig] = Field(min_length=1)
    verify: VerifyConfig = VerifyConfig()
    #: no state from the robot for this long (wall clock) during a reset: the reset fails [s]
    state_timeout_s: FailAfterS = 2.0

    def max_duration_s(self) -> float:
        """Upper bound of one reset in robot time [s]: every attempt of every step, times
        the verification attempts (a controller waits this long, with a margin)."""
        steps = sum(s.timeout_s * (s.retries + 1) for s in self.steps)
        return steps * (self.verify.retries + 1)


def load_reset(rig: RigConfig) -> ResetConfig | None:
    """The rig's reset procedure, or None when it has none. Checks the step kinds, each
    step's params and that the robot is on the rig; raises :class:`ConfigError` naming
    file and field."""
    if rig.reset is None:
        return None
    try:
        cfg = parse_model(ResetConfig, rig.reset, rig.source)
    except ConfigError as e:
        raise ConfigError(rig.source, [(f"reset.{f}" if f else "reset", m) for f, m in e.problems]) from None
    if cfg.robot not in rig.robots:
        raise ConfigError(rig.source, [("reset.robot", f"{cfg.robot!r} is not on the rig; robots: {list(rig.robots)}")])
    from hilstack.control.reset.steps import STEP_KINDS

    for i, s in enumerate(cfg.steps):
        if s.kind not in STEP_KINDS:
            raise ConfigError(rig.source, [(f"reset.steps[{i}].kind", f"unknown step {s.kind!r}; known: {sorted(STEP_KINDS)}")])
        STEP_KINDS[s.kind].parse_params(s.params, rig.source, f"reset.steps[{i}].params")
    for i, d in enumerate(cfg.detectors):
        if d.robot is not None and d.robot not in rig.robots:
            raise ConfigError(rig.source, [(f"reset.detectors[{i}].robot",
                                            f"{d.robot!r} is not on the rig; robots: {list(rig.robots)}")])
        need = {"timeout": ("max_s",), "arena": ("radius_m",), "tipped": (), "drop": ("channels", "min_height_m")}[d.kind]
        for f in need:
            if getattr(d, f) in (None, []):  # a height of 0 m is a height
                raise ConfigError(rig.source, [(f"reset.detectors[{i}].{f}", f"required for a {d.kind} detector")])
    return cfg


class ResetUnavailable(RuntimeError):
    """A rig whose robot cannot be reset by anything: one line saying what to add."""


def require_reset(rig: RigConfig, robot: str, operator_resets: bool = False) -> ResetConfig | None:
    """The rig's reset procedure for ``robot``; None when the driver resets itself (sim
    backends teleport) or an operator places the robot. Raises :class:`ResetUnavailable`
    at start, before anything moves, when nothing can reset the robot."""
    from hilstack.configs.schema import rig_robot_config

    cfg = load_reset(rig)
    if cfg is not None and cfg.robot == robot:
        return cfg
    backend = rig_robot_config(rig, robot).backend
    if backend == "sim" or operator_resets:
        return None
    where = rig.source or f"configs/rigs/{rig.name}.yaml"
    raise ResetUnavailable(
        f"rig {rig.name}: robot {robot} ({backend} backend) cannot reset itself and the rig has no reset "
        f"procedure: add a 'reset:' section for {robot} to {where} (docs/reset.md) or pass --operator-resets"
    )
