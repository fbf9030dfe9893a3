"""Reset procedures as data: config validation, detectors, steps, the start check, the diagram."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hilstack.bus.schemas import RobotState
from hilstack.configs.schema import ConfigError, RigConfig, load_rig, parse_model
from hilstack.control.reset.config import (
    DetectorConfig,
    ResetUnavailable,
    StepConfig,
    VerifyConfig,
    load_reset,
    require_reset,
)
from hilstack.control.reset.detectors import ArenaDetector, DropDetector, TimeoutDetector, make_detector
from hilstack.control.reset.steps import (
    DONE,
    HOLD,
    MECHANISMS,
    DriveToStart,
    SelfRight,
    StepError,
    TaskReset,
    TaskResetMechanism,
    TurnToYaw,
    register_mechanism,
)
from hilstack.control.reset.supervisor import pose_error, state_diagram_mermaid

NAMES = ["x", "y", "cos_yaw", "sin_yaw", "ball_z"]


def st(t_s=0.0, x=0.0, y=0.0, yaw=0.0, ball_z=0.1) -> RobotState:
    return RobotState(robot="r", t_s=t_s, state=[x, y, math.cos(yaw), math.sin(yaw), ball_z])


def rig(reset, robots=None) -> RigConfig:
    return parse_model(RigConfig, {"name": "t", "robots": robots or {"roach": {"config": "velociroach",
                                                                                "backend": "emulated"}},
                                   "reset": reset}, "t.yaml")


def test_timeout_detector_counts_robot_time_from_the_episode_start():
    d = TimeoutDetector(max_s=2.0)
    d.bind(NAMES)
    d.start(st(t_s=10.0))
    assert d(st(t_s=11.9)) is None
    assert "timeout" in d(st(t_s=12.0))


def test_arena_detector_fires_outside_the_radius_and_ignores_nan():
    d = ArenaDetector(radius_m=1.0, center_xy_m=(1.0, 0.0))
    d.bind(NAMES)
    assert d(st(x=1.9)) is None
    assert "1.10 m" in d(st(x=1.0, y=1.1))
    assert d(st(x=float("nan"))) is None


def test_drop_detector_watches_named_height_channels():
    d = make_detector(DetectorConfig(kind="drop", channels=["ball_z"], min_height_m=0.05))
    d.bind(NAMES)
    assert d(st(ball_z=0.06)) is None
    assert "ball_z" in d(st(ball_z=0.01))
    with pytest.raises(ValueError, match="no channel"):
        DropDetector(["ball2_z"], 0.05).bind(NAMES)


def test_reset_config_errors_name_the_field():
    with pytest.raises(ConfigError, match=r"reset.steps\[0\].kind.*unknown step 'fly'"):
        load_reset(rig({"robot": "roach", "steps": [{"kind": "fly"}]}))
    with pytest.raises(ConfigError, match=r"reset.detectors\[0\].radius_m.*required"):
        load_reset(rig({"robot": "roach", "detectors": [{"kind": "arena"}], "steps": [{"kind": "drive_to_start"}]}))
    with pytest.raises(ConfigError, match=r"steps"):
        load_reset(rig({"robot": "roach", "steps": []}))
    with pytest.raises(ConfigError, match=r"reset.robot.*not on the rig"):
        load_reset(rig({"robot": "hand", "steps": [{"kind": "drive_to_start"}]}))
    with pytest.raises(ConfigError, match=r"timeout_s"):
        load_reset(rig({"robot": "roach", "steps": [{"kind": "drive_to_start", "timeout_s": -1}]}))
    # a step's params are checked when the config loads, not when the supervisor starts
    with pytest.raises(ConfigError, match=r"reset.steps\[1\].params.speed: Input should be less than or equal to 1"):
        load_reset(rig({"robot": "roach", "steps": [{"kind": "self_right"},
                                                   {"kind": "drive_to_start", "params": {"speed": 6}}]}))
    with pytest.raises(ConfigError, match=r"reset.steps\[0\].params.spot_m: Field required"):
        load_reset(rig({"robot": "roach", "steps": [{"kind": "arm_pick_place", "params": {
            "base_pos_m": [0, 0, 0], "palm_center_m": [0, 0, 0.1]}}]}))
    with pytest.raises(ConfigError, match=r"reset.steps\[0\].params.period_s: unknown field"):
        load_reset(rig({"robot": "roach", "steps": [{"kind": "arm_pick_place", "params": {
            "base_pos_m": [0, 0, 0], "spot_m": [0, 0, 0], "palm_center_m": [0, 0, 0.1], "period_s": 0.1}}]}))


def test_a_rig_that_nothing_can_reset_refuses_at_start_with_what_to_add():
    real = load_rig("roach_real")
    with pytest.raises(ResetUnavailable) as e:
        require_reset(real, "roach")
    msg = str(e.value)
    assert "\n" not in msg and "add a 'reset:' section" in msg and "--operator-resets" in msg
    assert require_reset(real, "roach", operator_resets=True) is None
    assert require_reset(load_rig("roach_sim"), "roach") is None  # the sim teleports
    emulated = require_reset(load_rig("roach_emulated"), "roach")
    assert [s.kind for s in emulated.steps] == ["self_right", "lab_fixture", "drive_to_start", "turn_to_yaw"]
    assert {d.kind for d in emulated.detectors} == {"arena", "timeout", "tipped"}


def test_max_duration_covers_every_attempt():
    cfg = load_reset(rig({"robot": "roach", "steps": [{"kind": "drive_to_start", "timeout_s": 10, "retries": 1},
                                                      {"kind": "turn_to_yaw", "timeout_s": 5}],
                          "verify": {"retries": 2}}))
    assert cfg.max_duration_s() == pytest.approx((2 * 10 + 5) * 3)


class _Ctx:
    state_names = NAMES


def test_turn_to_yaw_turns_the_short_way_and_finishes_within_tolerance():
    t = TurnToYaw(StepConfig(kind="turn_to_yaw", params={"speed": 0.3, "gain": 0.5, "tolerance_rad": 0.1,
                                                         "settle_s": 0.5}))
    t.start(_Ctx, st(), {"yaw": 3.0})
    a = t.update(_Ctx, st(yaw=-3.0))  # 3.0 is 0.28 rad clockwise from -3.0: turn right
    assert a[0] > 0 > a[1] and a[0] == pytest.approx(0.5 * (2 * math.pi - 6.0))
    assert t.update(_Ctx, st(t_s=1.0, yaw=2.95)) == HOLD  # inside: hold still, then check it stays
    assert isinstance(t.update(_Ctx, st(t_s=1.2, yaw=2.7)), type(a))  # coasted out: turn again
    assert t.update(_Ctx, st(t_s=1.3, yaw=2.95)) == HOLD
    assert t.update(_Ctx, st(t_s=1.8, yaw=2.96)) == DONE
    with pytest.raises(ConfigError, match=r"turn_to_yaw.params.sped: unknown field \(allowed here: \['gain', 'settle_s', 'speed', 'tolerance_rad'\]\)"):
        TurnToYaw(StepConfig(kind="turn_to_yaw", params={"sped": 1}))


def test_task_reset_runs_a_registered_mechanism_and_says_when_none_is():
    calls = []

    class Fixture(TaskResetMechanism):
        def __init__(self, params):
            self.params, self.n = params, 0

        def begin(self, pose):
            calls.append(("begin", pose))

        def poll(self):
            self.n += 1
            return self.n >= 2

        def abort(self):
            calls.append(("abort",))

    with pytest.raises(ValueError, match="no mechanism 'widowx' registered.*arms driver"):
        TaskReset(StepConfig(kind="task_reset", params={"mechanism": "widowx"}))
    register_mechanism("fixture", Fixture)
    try:
        step = TaskReset(StepConfig(kind="task_reset", params={"mechanism": "fixture", "rotate_deg": 16}))
        assert step.mechanism.params == {"rotate_deg": 16}
        step.start(_Ctx, st(), {"x": 0.0})
        assert step.update(_Ctx, st()) == HOLD
        assert step.update(_Ctx, st()) == DONE
        step.abort()
        assert calls == [("begin", {"x": 0.0}), ("abort",)]
    finally:
        MECHANISMS.pop("fixture")


def test_docs_draw_the_machine_as_defined():
    """docs/reset.md carries the diagram generated from the machine's definition."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "reset.md").read_text()
    assert state_diagram_mermaid() in doc
    assert "running --> episode_end: end_episode" in state_diagram_mermaid()


def test_pose_verification_wraps_heading_and_rejects_bad_readings():
    v = VerifyConfig(position_tol_m=0.2, yaw_tol_rad=0.3)
    assert pose_error(NAMES, st(x=0.1, yaw=-3.1), {"x": 0.0, "y": 0.0, "yaw": 3.1}, v) == ""  # 0.08 rad apart
    assert "heading 0.50 rad" in pose_error(NAMES, st(yaw=0.5), {"yaw": 0.0}, v)
    assert "0.25 m from the start" in pose_error(NAMES, st(x=0.25), {"x": 0.0}, v)
    assert "m from the start" in pose_error(NAMES, st(x=float("nan")), {"x": 0.0}, v)
    bad = st()
    bad.ok = False
    assert "bad reading" in pose_error(NAMES, bad, {}, v)
    assert pose_error(NAMES, st(yaw=2.0), {"yaw": 0.0}, VerifyConfig(position_tol_m=0.2)) == ""  # no yaw check


ROACH = ["x", "y", "cos_roll", "cos_pitch", "cos_yaw", "sin_yaw"]


class _RoachCtx:
    state_names = ROACH

    @staticmethod
    def count(what, n=1):
        pass


def roach(x=0.0, y=0.0, yaw=0.0, cos_roll=1.0) -> RobotState:
    return RobotState(robot="r", t_s=0.0, state=[x, y, cos_roll, 1.0, math.cos(yaw), math.sin(yaw)])


def test_drive_to_start_turns_in_place_first_then_drives_and_refuses_a_flipped_robot():
    step = DriveToStart(StepConfig(kind="drive_to_start"))
    step.start(_RoachCtx, roach(x=1.0), {"x": 0.0, "y": 0.0})
    # facing away from the start (+x, start is at -x): turn in place, slowly
    a = step.update(_RoachCtx, roach(x=1.0, yaw=0.0))
    assert a[0] == pytest.approx(-a[1]) and abs(a[0]) == pytest.approx(step.d_max)
    # facing the start: both leg sets forward
    a = step.update(_RoachCtx, roach(x=1.0, yaw=math.pi))
    assert a[0] > 0.4 and a[1] > 0.4
    # passed the start: a new path from here back to it (heading now points back: turn)
    a = step.update(_RoachCtx, roach(x=-0.5, yaw=math.pi))
    assert a[0] == pytest.approx(-a[1])
    assert step.update(_RoachCtx, roach(x=0.05, yaw=0.0)) == DONE
    with pytest.raises(StepError, match="not upright"):
        step.update(_RoachCtx, roach(x=1.0, cos_roll=-0.6))
    with pytest.raises(StepError, match="not finite"):
        step.update(_RoachCtx, roach(x=float("nan")))


def test_tipped_detector_and_self_right_step():
    d = make_detector(DetectorConfig(kind="tipped", min_cos=0.5))
    d.bind(ROACH)
    assert d(roach()) is None
    assert "tipped: cos_roll = -0.60" in d(roach(cos_roll=-0.6))
    step = SelfRight(StepConfig(kind="self_right", params={"settle_s": 0.5, "hold_first_s": 1.0}))
    step.start(_RoachCtx, roach(cos_roll=-0.9), {})
    assert step.update(_RoachCtx, roach(cos_roll=-0.9)) == HOLD  # first: legs still, it may fall back
    tipped = roach(cos_roll=-0.9)
    tipped.t_s = 1.0
    kicks = [step.update(_RoachCtx, tipped) for _ in range(20)]
    assert all(isinstance(k, np.ndarray) and np.all(np.abs(k) <= 1.0) for k in kicks)
    assert np.std(np.array(kicks)) > 0.3  # random kicks, not a fixed pattern
    up = roach()
    assert step.update(_RoachCtx, up) == HOLD  # upright: hold still and see that it stays so
    up.t_s = 0.6
    assert step.update(_RoachCtx, up) == DONE


@pytest.mark.parametrize("rig_file", ["tests/reset/rig_roach_reset.yaml", "configs/rigs/hand_sim_arm.yaml"])
def test_everything_the_supervisor_sends_is_reliable(rig_file, bus):
    """Its commands (a lockstep robot steps on each, the linked reset arm too), its requests and
    answers, and its transitions (a recording splits its episodes by them) wait for room in
    Zenoh's send queue instead of being dropped: a loaded machine lost a transition from a
    recording once (test_leaving_the_arena_ends_the_episode_and_the_robot_is_driven_back)."""
    import zenoh

    from hilstack.bus.node import Publisher
    from hilstack.control.reset.supervisor import ResetSupervisor

    root = Path(__file__).resolve().parents[2]
    rig = load_rig(root / rig_file)
    sup = ResetSupervisor(rig.name, load_reset(rig), bus, handle_signals=False)
    try:
        pubs = {p.key: p._pub.congestion_control for p in sup._closeables if isinstance(p, Publisher)}
        assert any(k.endswith("/reset/transition") for k in pubs) and len(pubs) >= 4 + len(sup.links)
        assert {k: c for k, c in pubs.items() if c != zenoh.CongestionControl.BLOCK} == {}
    finally:
        sup.close()
