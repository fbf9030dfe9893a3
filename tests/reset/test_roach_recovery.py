"""A VelociRoACH that tipped over, on the lockstep sim rig: the `tipped` detector ends the
episode, `self_right` (optional) gives up on a robot lying on its back, the lab fixture
puts it on its legs, and the robot is driven back. Real driver bridge, supervisor and
controller nodes over Zenoh, real MuJoCo."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilstack.bus.schemas import ResetEvent, RobotState
from hilstack.control.reset.config import StepConfig
from hilstack.control.reset.steps import DONE, HOLD, DriveToStart, LabFixture, SelfRight, StepError
from hilstack.sim_backends.velociroach.emulator import LabFixture as EmulatorFixture
from tests.reset.test_supervisor_sim import _ended_by_supervisor, drive_out

DETECTORS = [{"kind": "tipped", "min_cos": 0.7}, {"kind": "arena", "radius_m": 2.0}]
RECOVERY = [
    {"kind": "self_right", "timeout_s": 1.5, "optional": True},
    {"kind": "lab_fixture", "timeout_s": 5},
    {"kind": "drive_to_start", "timeout_s": 20, "params": {"speed": 0.6, "tolerance_m": 0.1}},
    {"kind": "turn_to_yaw", "timeout_s": 10, "params": {"speed": 0.1, "gain": 0.1, "tolerance_rad": 0.15}},
]


def flip_onto_its_back(rig) -> None:
    """Between two lockstep steps (the driver waits for a command), lay the sim robot on
    its back where it is, as a hard forward kick does on the model."""
    rig.ctl.next_state()
    EmulatorFixture(rig.driver.driver, None).place(upside_down=True)


def test_a_robot_on_its_back_is_put_on_its_legs_by_the_fixture_after_self_right_gives_up(supervised_rig):
    rig = supervised_rig(detectors=DETECTORS, steps=RECOVERY)
    drive_out(rig, steps=8, action=(0.5, 0.5))  # away from the start: the drive back has work to do
    flip_onto_its_back(rig)
    log = drive_out(rig, steps=50, action=(0.0, 0.0), stop_if=_ended_by_supervisor(rig.ctl))
    assert len(log.actions) < 50  # the tipped detector ended the episode
    assert log.states[-1][6] < 0  # cos_roll: on its back
    first = rig.ctl.reset(timeout_s=60, x=0.0, y=0.0, yaw=0.0)
    assert first.episode == 1
    assert first.state[6] > 0.9 and first.state[8] > 0.9  # upright again
    assert math.hypot(first.state[0], first.state[1]) <= 0.25
    h = rig.sup.history
    assert [t.dest for t in h] == ["episode_end", "paused", "resetting", "resetting", "verifying", "resumed", "running"]
    assert "tipped: cos_roll" in h[0].reason
    assert h[3].trigger == "skip" and h[3].step == "self_right" and "next: lab_fixture" in h[3].detail
    rep = rig.sup.report()
    assert rep["completed"] == 1 and rep["failed"] == 0
    assert rep["fixture_recoveries"] == rep["operator_interventions"] == 1
    assert rep["skipped_self_right"] == 1 and rep["self_righted"] == 0
    assert rep["episode_ends"] == {"tipped": 1}
    assert rep["mean_duration_s"] > 0


def test_an_optional_step_that_is_the_last_one_fails_the_reset(supervised_rig):
    rig = supervised_rig(detectors=DETECTORS, steps=RECOVERY[:1])
    flip_onto_its_back(rig)
    drive_out(rig, steps=30, action=(0.0, 0.0), stop_if=_ended_by_supervisor(rig.ctl))
    with pytest.raises(RuntimeError, match="reset step self_right failed after 1 attempt: timed out after 1.5 s"):
        rig.ctl.reset(timeout_s=30)
    assert rig.sup.report()["fixture_recoveries"] == 0


class TipsOnTheWayBack(DriveToStart):
    """drive_to_start whose robot goes over onto its back once, on its first update (in
    the supervisor's thread while the lockstep driver waits for the answer)."""

    def __init__(self, cfg, sim):
        super().__init__(cfg)
        self.sim, self.flips = sim, 0

    def update(self, ctx, state):
        if self.flips == 0:
            self.flips = 1
            EmulatorFixture(self.sim, None).place(upside_down=True)
            return HOLD
        return super().update(ctx, state)


def test_a_robot_that_tips_while_driving_back_gets_the_procedure_again_from_self_right(supervised_rig):
    rig = supervised_rig(detectors=[], steps=RECOVERY, verify={"position_tol_m": 0.25, "retries": 1})
    rig.sup.steps[2] = TipsOnTheWayBack(StepConfig(**RECOVERY[2]), rig.driver.driver)
    drive_out(rig, steps=8, action=(0.5, 0.5))
    first = rig.ctl.reset(timeout_s=60, x=0.0, y=0.0, yaw=0.0)
    assert first.state[6] > 0.9 and math.hypot(first.state[0], first.state[1]) <= 0.25
    h = rig.sup.history
    assert [t.trigger for t in h] == ["end_episode", "pause", "begin", "retry", "skip", "steps_done", "verified",
                                      "resume"]
    assert "not upright; the procedure again from self_right" in h[3].detail
    assert rig.sup.report()["fixture_recoveries"] == 1


# ------------------------------------------------------------------ the steps alone
NAMES = ["x", "y", "cos_roll", "cos_pitch", "cos_yaw", "sin_yaw"]


def st(t_s: float, cos_roll: float = 1.0, health: dict | None = None) -> RobotState:
    return RobotState(robot="roach", t_s=t_s, state=[0.5, 0.2, cos_roll, 1.0, 1.0, 0.0], health=health or {})


class Ctx:
    """A supervisor as the steps see it: a driver node that answers ``phase``."""

    state_names = NAMES

    def __init__(self, phase: str = "done"):
        self.phase = phase
        self.requests: list[tuple[str, dict]] = []
        self.counts: dict[str, int] = {}

    def request_driver(self, phase, pose):
        self.requests.append((phase, dict(pose)))

    def driver_answer(self):
        if not self.requests:
            return None
        return ResetEvent(robot="roach", phase=self.phase, detail="emulated backend cannot reset itself")

    def count(self, what, n=1):
        self.counts[what] = self.counts.get(what, 0) + n


def test_lab_fixture_on_a_rig_without_one_tells_the_operator_to_right_the_robot():
    step = LabFixture(StepConfig(kind="lab_fixture"))
    ctx = Ctx(phase="unsupported")
    step.start(ctx, st(0.0, cos_roll=-1.0), {})
    assert step.update(ctx, st(0.0, cos_roll=-1.0)) == HOLD
    assert ctx.requests == [("teleport", {"x": 0.5, "y": 0.2, "yaw": 0.0})]  # where it lies
    with pytest.raises(StepError, match="no lab fixture.*an operator must put it on its legs"):
        step.update(ctx, st(0.1, cos_roll=-1.0))


def test_lab_fixture_counts_a_recovery_only_when_it_acted_and_the_robot_stayed_up():
    step = LabFixture(StepConfig(kind="lab_fixture", params={"settle_s": 0.5}))
    ctx = Ctx()
    step.start(ctx, st(0.0), {})
    assert step.update(ctx, st(0.0)) == DONE and ctx.counts == {} and ctx.requests == []  # upright: nothing to do
    step.start(ctx, st(1.0, cos_roll=-1.0), {})
    assert step.update(ctx, st(1.0, cos_roll=-1.0)) == HOLD
    assert step.update(ctx, st(1.1, cos_roll=-1.0)) == HOLD  # the answer: done
    assert step.update(ctx, st(1.2)) == HOLD  # up, settling
    assert step.update(ctx, st(1.8)) == DONE
    assert ctx.counts == {"fixture_recoveries": 1}


def test_self_right_counts_only_a_robot_it_found_down():
    ctx = Ctx()
    step = SelfRight(StepConfig(kind="self_right", params={"settle_s": 0.2, "hold_first_s": 0.5}))
    step.start(ctx, st(0.0, cos_roll=0.0), {})
    assert step.update(ctx, st(0.1, cos_roll=0.0)) == HOLD  # holding still first
    a = step.update(ctx, st(0.6, cos_roll=0.0))
    assert isinstance(a, np.ndarray) and a.shape == (2,)  # then kicks
    assert step.update(ctx, st(0.7)) == HOLD
    assert step.update(ctx, st(0.9)) == DONE and ctx.counts == {"self_righted": 1}
    step.start(ctx, st(2.0), {})
    assert step.update(ctx, st(2.0)) == HOLD and step.update(ctx, st(2.3)) == DONE
    assert ctx.counts == {"self_righted": 1}


# ------------------------------------------------------------------ the demo's report
def test_quick_on_a_wall_clock_rig_tunes_fewer_candidates_and_the_sim_quick_run_is_unchanged():
    from hilstack.learning.mbrl import MbrlConfig
    from hilstack.tools.demo import quick_wall_clock

    assert quick_wall_clock("roach_sim") == {}
    assert MbrlConfig.from_preset("quick", **quick_wall_clock("roach_sim")).baseline_candidates == 20
    assert quick_wall_clock("roach_emulated") == {"baseline_candidates": 6}


def test_the_report_states_the_resets():
    from hilstack.tools.demo import resets_markdown

    text = "\n".join(resets_markdown({"requested": 64, "completed": 63, "failed": 1, "mean_duration_s": 4.26,
                                      "max_duration_s": 11.0, "fixture_recoveries": 2, "self_righted": 5,
                                      "episode_ends": {"arena": 1, "tipped": 9}}))
    assert "63 of 64 requested resets completed, 1 failed; 4.3 s mean, 11.0 s longest" in text
    assert "Self-righted 5; lab-fixture recoveries (operator interventions on a real rig) 2" in text
    assert "Episodes ended by detectors: arena 1, tipped 9." in text
