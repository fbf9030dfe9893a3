"""The hand's hold pose is a setting (``params.hold_pose``: ``cupped``, ours, or ``pddm``, the PDDM
reference code's keyframe; drivers/shadow_hand/config.py ``HOLD_POSES``): the spec's home action,
the sim's reset, the task geometry read for it, and a Baoding run's start and action units follow
it; a rig and a task read for different poses are refused in one line (docs/baoding.md, "Where the
balls sit")."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.configs.schema import load_rig, rig_robot_config
from hilstack.drivers.registry import make_driver
from hilstack.drivers.shadow_hand.config import ShadowHandParams, hold_pose_action
from hilstack.learning.baoding import BaodingConfig, BaodingRun, baoding_rig_problem, load_baoding_task
from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim

RIGS = {"cupped": ("hand_sim", "baoding"), "pddm": ("hand_sim_pddm_pose", "baoding_pddm_pose")}


def rig_sim(rig: str) -> ShadowHandSim:
    return ShadowHandSim(make_driver(rig_robot_config(load_rig(rig), "hand")).params)


@pytest.mark.parametrize("pose", ["cupped", "pddm"])
def test_each_pose_holds_both_balls_10_s_and_its_task_config_is_its_sims(pose):
    rig, task = RIGS[pose]
    sim = rig_sim(rig)
    try:
        assert sim.params.hold_pose == pose
        with sim:
            np.testing.assert_allclose(sim.held_command, hold_pose_action(pose), atol=1e-9)  # the reset's pose
            cfg = load_baoding_task(task)
            np.testing.assert_allclose(cfg.center_m, sim.task.center_m, atol=1e-5)
            np.testing.assert_allclose(cfg.axis, sim.task.axis, atol=1e-5)
            assert cfg.phase0_rad == pytest.approx(sim.task.phase0_rad, abs=1e-5)
            held = sim.held_command
            for _ in range(100):  # 10 s at 10 Hz
                sim.write(held)
                sim.tick()
                obs = sim.read()
                assert not obs.flags["object_dropped"], f"{pose}: a ball dropped at {obs.t_s:.1f} s"
            assert sim.tracking_error(obs.state, held)["max_rad"] < 0.01
            balls = obs.extras["balls_m"]
            assert not cfg.dropped(balls) and cfg.in_palm(balls)
            assert -5 * 0.2 < sim.task.reward(balls, obs.t_s) < 0  # the distance term only: no drop
    finally:
        sim.cleanup()


def test_the_pddm_pose_holds_the_balls_side_by_side_on_the_fingers():
    """Ours rest one behind the other in the palm; the reference's pose holds them across the
    hand, further out along the fingers (its hooked middle joints make the wall)."""
    out = {}
    for pose, (rig, _) in RIGS.items():
        sim = rig_sim(rig)
        try:
            with sim:
                d, palm = sim.data, sim.model.body("robot0:palm").id
                rot = d.xmat[palm].reshape(3, 3)
                out[pose] = (sim.balls_m() - d.xpos[palm]) @ rot  # palm frame: x across, z along the fingers
        finally:
            sim.cleanup()
    across = {k: abs(v[0, 0] - v[1, 0]) for k, v in out.items()}
    along = {k: abs(v[0, 2] - v[1, 2]) for k, v in out.items()}
    assert across["pddm"] > 0.04 and along["pddm"] < 0.015, out["pddm"]
    assert along["cupped"] > 0.02, out["cupped"]
    assert out["pddm"][:, 2].mean() > out["cupped"][:, 2].mean() + 0.02  # further out along the fingers


def test_a_run_starts_where_its_rig_holds_and_a_mismatch_is_refused(tmp_path, bus):
    run = BaodingRun(BaodingConfig.from_preset("tiny", rig="hand_sim_pddm_pose", task="baoding_pddm_pose"),
                     tmp_path / "run", bus)
    np.testing.assert_allclose(run.hold, hold_pose_action("pddm"), atol=1e-9)
    np.testing.assert_allclose(run.amap.to_driver(np.zeros(20)), hold_pose_action("pddm"), atol=1e-9)  # z = 0 holds
    assert not np.allclose(hold_pose_action("pddm"), hold_pose_action("cupped"))
    assert ShadowHandParams().hold_pose == "cupped"
    # the thesis preset holds the reference's pose (measured: the pair turns in it), quick and tiny ours
    thesis, quick = BaodingConfig(), BaodingConfig.from_preset("quick")
    assert (thesis.rig, thesis.task) == RIGS["pddm"] and (quick.rig, quick.task) == RIGS["cupped"]
    assert (BaodingConfig.from_preset("tiny").rig, BaodingConfig.from_preset("tiny").task) == RIGS["cupped"]
    for pose, (rig, task) in RIGS.items():
        assert baoding_rig_problem(rig, task=task) is None, pose
    msg = baoding_rig_problem("hand_sim_pddm_pose", task="baoding")
    assert msg == ("rig hand_sim_pddm_pose's hand holds the 'pddm' pose but task baoding's geometry is for 'cupped' "
                   "(hil demo baoding --hold-pose pddm; docs/baoding.md)")
    assert "holds the 'cupped' pose" in baoding_rig_problem("hand_sim", task="baoding_pddm_pose")


def test_hold_pose_from_the_command_line(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import hilstack.tools.demo_baoding as demo
    from hilstack.tools.cli import app

    got = []

    def fake_run(out, preset, seed, resume, rig, **overrides):
        got.append((rig, overrides.get("task")))
        raise ValueError("stopped before the rig")

    monkeypatch.setattr(demo, "run_baoding_demo", fake_run)
    r = CliRunner().invoke(app, ["demo", "baoding", "--quick", "--hold-pose", "pddm", "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and got == [("hand_sim_pddm_pose", "baoding_pddm_pose")], r.output
    # without --hold-pose: --rig's own pose picks the task's geometry; neither: the preset's pose
    # (the thesis preset the reference's, the quick one ours)
    for args, want in [(["--quick", "--rig", "hand_sim_pddm_pose"], ("hand_sim_pddm_pose", "baoding_pddm_pose")),
                       (["--rig", "hand_emulated"], ("hand_emulated", "baoding")),
                       (["--quick"], ("hand_sim", "baoding")),
                       ([], ("hand_sim_pddm_pose", "baoding_pddm_pose")),
                       (["--hold-pose", "cupped"], ("hand_sim", "baoding"))]:
        got.clear()
        r = CliRunner().invoke(app, ["demo", "baoding", *args, "--out", str(tmp_path / "o")])
        assert r.exit_code == 1 and got == [want], (args, r.output)
    r = CliRunner().invoke(app, ["demo", "baoding", "--hold-pose", "pddm", "--rig", "hand_sim", "--out", str(tmp_path / "o")])
    assert r.exit_code != 0 and "holds the 'cupped' pose but task baoding_pddm_pose's geometry" in r.output, r.output
    got.clear()
    r = CliRunner().invoke(app, ["demo", "baoding", "--quick", "--hold-pose", "flat", "--out", str(tmp_path / "o")])
    assert r.exit_code != 0 and "--hold-pose must be cupped or pddm, got 'flat'" in r.output, r.output
    assert not got
    # --full passes the pose's task (and --targets) to every seed's run
    full = []

    def fake_full(out, rig, ray, workers, resume, **overrides):
        full.append((rig, overrides))
        raise ValueError("stopped before the rig")

    monkeypatch.setattr(demo, "run_full", fake_full)
    r = CliRunner().invoke(app, ["demo", "baoding", "--full", "--hold-pose", "pddm", "--targets", "clock",
                                 "--out", str(tmp_path / "f")])
    assert r.exit_code == 1 and full == [("hand_sim_pddm_pose", {"task": "baoding_pddm_pose",
                                                                   "task_overrides": {"max_lead_rad": None}})], r.output


def test_a_run_of_the_old_default_pose_is_told_how_to_resume(tmp_path, bus):
    """A thesis-preset run from before its default was the reference's pose: --resume names the flag."""
    import json
    from dataclasses import asdict

    out = tmp_path / "run"
    (out / "checkpoint").mkdir(parents=True)
    (out / "checkpoint" / "state.json").write_text(json.dumps({"iteration": 3}))
    old = {**asdict(BaodingConfig()), "rig": "hand_sim", "task": "baoding"}
    (out / "report.json").write_text(json.dumps({"config": old, "partial": True}, default=list))
    with pytest.raises(ValueError, match=r"other settings \(rig, task\).*it held the cupped pose: add --hold-pose cupped"):
        BaodingRun(BaodingConfig(), out, bus, resume=True).load_checkpoint()
    run = BaodingRun(BaodingConfig(rig="hand_sim", task="baoding"), out, bus, resume=True)
    assert run.load_checkpoint()["state"]["iteration"] == 3
