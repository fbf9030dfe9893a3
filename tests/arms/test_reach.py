"""The arms' reaching task (learning/reach.py, `hil demo arms`): kinematics, cost, IK,
policy-rate data, and one tiny run through the bus on the Sawyer sim rig."""

from __future__ import annotations

import inspect
import json

import mujoco
import numpy as np
import pytest
import torch

from hilstack.drivers.sawyer.config import JOINTS as SAWYER_JOINTS
from hilstack.drivers.widowx.config import JOINT_NAMES as WIDOWX_JOINTS
from hilstack.learning.datasets import Episode
from hilstack.learning.kinematics import ChainKinematics
from hilstack.learning.reach import (
    HeldPolicy,
    IkController,
    ReachConfig,
    ReachCost,
    policy_rate_episode,
    reach_cost,
    summarize,
)
from hilstack.sim_backends.sawyer.model import build_model
from hilstack.sim_backends.widowx.world import ArmWorld


@pytest.fixture(scope="module")
def widowx_model():
    return ArmWorld().model


@pytest.fixture(scope="module")
def sawyer_model():
    return build_model()


def _mj_site(model, site, joints, q):
    d = mujoco.MjData(model)
    for n, v in zip(joints, q, strict=True):
        d.joint(n).qpos[0] = v
    mujoco.mj_kinematics(model, d)
    mujoco.mj_comPos(model, d)
    jac = np.zeros((3, model.nv))
    mujoco.mj_jacSite(model, d, jac, None, model.site(site).id)
    cols = [model.joint(n).dofadr[0] for n in joints]
    return d.site(site).xpos.copy(), jac[:, cols]


@pytest.mark.parametrize("arm", ["widowx", "sawyer", "port"])
def test_chain_kinematics_matches_mujoco(arm, widowx_model, sawyer_model):
    model, site, joints, scale = {
        "widowx": (widowx_model, "ee", WIDOWX_JOINTS, 1.5),
        "sawyer": (sawyer_model, "endEffector", SAWYER_JOINTS, 2.0),
        "port": (widowx_model, "port", ("mech_rail", "mech_rotate"), 0.01),
    }[arm]
    fk = ChainKinematics(model, site, joints, dtype=torch.float64)
    rng = np.random.default_rng(3)
    qs = rng.uniform(-scale, scale, (4, len(joints)))
    batch = fk.position(qs)  # batched in one call
    for q, x in zip(qs, batch, strict=True):
        want, jac = _mj_site(model, site, joints, q)
        np.testing.assert_allclose(x, want, atol=1e-9)
        np.testing.assert_allclose(fk.jacobian(q), jac, atol=1e-6)


def test_chain_kinematics_refuses_a_joint_off_the_chain(widowx_model):
    with pytest.raises(ValueError, match="mech_rail.*not on the chain"):
        ChainKinematics(widowx_model, "ee", ("waist", "mech_rail"))
    with pytest.raises(ValueError, match="no site"):
        ChainKinematics(widowx_model, "nope", ("waist",))


def test_reach_cost_is_the_thesis_reward_negated():
    d = torch.tensor([0.0, 0.01, 0.1, 1.0])
    want = d**2 + torch.log(d + 1e-5)
    assert torch.allclose(reach_cost(d), want)
    assert reach_cost(torch.tensor(0.0)) == pytest.approx(np.log(1e-5))
    assert bool(torch.all(torch.diff(reach_cost(torch.linspace(0, 2, 50))) > 0))  # closer is always better


def test_reach_cost_sums_the_predicted_steps_not_the_current_state(widowx_model):
    fk = ChainKinematics(widowx_model, "ee", WIDOWX_JOINTS)
    q0 = np.zeros(6, dtype=np.float32)
    goal = fk.position(q0)
    cost = ReachCost(fk, goal, 6)
    far = np.full(6, 0.5, dtype=np.float32)
    # [E=1, N=2, H+1=3, S=12]: sample 0 stays at the goal, sample 1 moves away after step 1
    s = np.zeros((1, 2, 3, 12), dtype=np.float32)
    s[0, 1, 2, :6] = far
    s[0, :, 0, :6] = far  # the current state is not scored
    c = cost(torch.as_tensor(s), torch.zeros(2, 2, 6))
    d_far = float(np.linalg.norm(fk.position(far) - goal))
    assert c.shape == (1, 2)
    assert float(c[0, 0]) == pytest.approx(2 * np.log(1e-5), abs=1e-3)
    assert float(c[0, 1]) == pytest.approx(np.log(1e-5) + d_far**2 + np.log(d_far + 1e-5), abs=1e-3)


@pytest.mark.parametrize("arm", ["widowx", "sawyer"])
def test_ik_controller_reaches_a_reachable_goal_kinematically(arm, widowx_model, sawyer_model):
    model, site, joints, q0 = {
        "widowx": (widowx_model, "ee", WIDOWX_JOINTS, np.array([0, -1.0, 1.0, 0, 0.5, 0])),
        "sawyer": (sawyer_model, "endEffector", SAWYER_JOINTS, np.array([1.3, -1.4, 0, 2.13, 0, 0.4, 0])),
    }[arm]
    fk = ChainKinematics(model, site, joints, dtype=torch.float64)
    goal = fk.position(q0 + 0.3)
    vmax = np.ones(len(joints))
    ik = IkController(fk, goal, vmax, gain_per_s=2.0, damping_m=0.01)
    q = q0.copy()
    for _ in range(60):  # a perfect velocity loop at 0.25 s per step
        q = q + 0.25 * vmax * ik(np.concatenate([q, np.zeros_like(q)]))
    assert np.linalg.norm(fk.position(q) - goal) < 1e-3
    assert np.all(np.abs(ik(np.concatenate([q0, q0]))) <= 1.0)  # a normalized action


def test_policy_rate_episode_keeps_every_hold_th_state_and_the_commanded_action():
    states = np.arange(13 * 3, dtype=np.float32).reshape(13, 3)
    # 12 steps, 4 blocks of 3; the recorded (applied) action ramps to the held command
    actions = (np.repeat(np.arange(4, dtype=np.float32), 3) - np.tile([0.5, 0.2, 0.0], 4))[:, None]
    ep = Episode(states, actions, name="e", meta={"state_names": ["a", "b", "c"], "state_units": ["1", "2", "3"]})
    out = policy_rate_episode(ep, 3, [2, 0])
    np.testing.assert_array_equal(out.states, states[[0, 3, 6, 9, 12]][:, [2, 0]])
    np.testing.assert_array_equal(out.actions[:, 0], [0, 1, 2, 3])
    assert out.meta["state_names"] == ["c", "a"] and out.meta["state_units"] == ["3", "1"]
    short = policy_rate_episode(Episode(states[:12], actions[:11]), 3, [0])  # an incomplete last block is dropped
    assert len(short) == 3


def test_held_policy_acts_every_hold_calls_on_the_model_channels():
    seen = []

    def inner(x):
        seen.append(x.copy())
        return np.array([len(seen)], dtype=float)

    p = HeldPolicy(inner, 3, [1])
    out = [float(p(np.array([10.0, float(i)]))[0]) for i in range(7)]
    assert out == [1, 1, 1, 2, 2, 2, 3]
    assert [float(x[0]) for x in seen] == [0, 3, 6]
    p.reset()
    p(np.array([0.0, 9.0]))
    assert float(seen[-1][0]) == 9.0


def test_scaled_random_actions_cover_small_commands():
    from hilstack.learning.reach import RandomPolicy

    uni = np.array([RandomPolicy(7, s)(None) for s in range(400)])
    sca = np.array([RandomPolicy(7, s, scaled=True)(None) for s in range(400)])
    assert np.all(np.abs(sca) <= 1.0)
    small = lambda a: float(np.mean(np.abs(a).max(axis=1) < 0.3))  # noqa: E731
    assert small(sca) > 0.2 > 0.01 > small(uni)  # all 7 joints below 0.3: common only when scaled


def test_summary_success_is_within_2_cm():
    s = summarize([0.005, 0.019, 0.021, 0.3])
    assert s["success_rate"] == 0.5
    assert s["final_distance_m"]["mean"] == pytest.approx(np.mean([0.005, 0.019, 0.021, 0.3]))


def test_config_refuses_bad_settings_and_matches_the_ik_effort_to_the_data():
    with pytest.raises(ValueError, match="arm: unknown 'ur5'"):
        ReachConfig(arm="ur5")
    c = ReachConfig(random_episodes=40, tune_goals=3)
    assert c.tune_candidates * c.tune_goals >= c.random_episodes


def test_hil_demo_arms_is_registered_with_the_shared_signature():
    import importlib

    from hilstack.tools.cmd_demo import OTHER_DEMOS

    module, fn, _ = OTHER_DEMOS["arms"]
    f = getattr(importlib.import_module(module), fn)
    assert list(inspect.signature(f).parameters) == ["out", "quick", "full", "seed"]


def test_a_tiny_reach_run_on_the_sawyer_rig(tmp_path):
    """The whole loop over the bus: random data → model → MPC, IK and random; report.json."""
    from hilstack.tools.demo_arms import run_arms

    r = run_arms(tmp_path, quick=True, arms=("sawyer",), random_episodes=3, epochs=3, episode_steps=8,
                 samples=60, horizon=2, tune_candidates=2, tune_goals=1, progress=False)["sawyer"]
    saved = json.loads((tmp_path / "sawyer" / "report.json").read_text())
    assert saved["command"] == f"hil demo arms --quick --seed 0 --out {tmp_path}"
    run = saved["seeds"][0]
    assert run["random_transitions"] == 3 * 8
    for c in ("mpc", "ik", "random"):
        eps = run["episodes"][c]
        assert [e["box"] for e in eps] == [0, 1, 2]
        assert len(eps[0]["distance_m"]) == 8 + 1
        assert all(e["success"] == (e["final_distance_m"] < 0.02) for e in eps)
        assert saved["summary"][c]["episodes"] == 3
    # IK drives straight to the box: far closer than where it started
    assert all(e["final_distance_m"] < 0.5 * e["distance_m"][0] for e in run["episodes"]["ik"])
    assert len(run["ik_tuning"]["candidates"]) == 2
    assert (tmp_path / "report.md").is_file() and r["summary"] == saved["summary"]


def test_widowx_goals_come_from_the_mechanism_pose(tmp_path, widowx_model):
    """On the bench rig the mechanism (its own robot on the bus) moves to each task's target
    and the goal is the switch port at the pose it measures."""
    from hilstack.tools.demo_arms import run_arms

    r = run_arms(tmp_path, quick=True, arms=("widowx",), random_episodes=2, epochs=2, episode_steps=4,
                 samples=60, horizon=2, tune_candidates=1, tune_goals=1, eval_goals=3, progress=False)["widowx"]
    port = ChainKinematics(widowx_model, "port", ("mech_rail", "mech_rotate"), dtype=torch.float64)
    eps = r["seeds"][0]["episodes"]["ik"]
    assert len(eps) == 3
    for e in eps:
        target = np.array(e["mechanism_target"])  # normalized: ±1 = ±8°, ±1 cm
        pose = e["mechanism_pose"]
        measured = np.array([pose["rotate_rad"] / np.radians(8.0), pose["offset_m"] / 0.01])
        np.testing.assert_allclose(measured, target, atol=0.15)  # the mechanism got there
        np.testing.assert_allclose(e["goal_m"], port.position([pose["offset_m"], pose["rotate_rad"]]), atol=1e-4)
    goals = np.array([e["goal_m"] for e in eps])
    assert np.ptp(goals[:, 1]) > 0.003  # the rail moved the port between tasks


def test_reach_episodes_report_the_plan_times_of_the_policy_calls_even_with_a_gap(tmp_path):
    """HeldPolicy runs its inner policy on every hold-th call; the episode's plan times are
    those calls' (what the report's percentiles and the sample refit use). A call that left
    no time (one still running when a realtime episode ended) must not shift the selection
    onto the held calls, as taking every hold-th entry of the list did."""
    from hilstack.configs.schema import BusConfig
    from hilstack.control.controller_node import EpisodeLog
    from hilstack.learning.reach import ARMS, ReachRun

    run = ReachRun(ReachConfig(arm="sawyer", progress=False), ARMS["sawyer"](), tmp_path, BusConfig(), 0)
    run.hold, run.channels, run.n_joints = 3, list(range(14)), 7
    inner = {0: 0.10, 3: 0.11, 6: 0.12, 9: 0.13}  # the policy's own calls plan; held ones take ~0
    calls = [c for c in range(12) if c != 4]  # held call 4 left no time
    log = EpisodeLog(states=[np.zeros(20)] * 13, plan_calls=calls, plan_times_s=[inner.get(c, 1e-5) for c in calls],
                     late_plans=1)
    run.loop.episode = lambda pol, steps, pose: log
    r = run.run_episode(None)
    assert r["plan_s"] == [0.10, 0.11, 0.12, 0.13] and r["late_plans"] == 1
    assert r["q"].shape == (5, 7)  # every hold-th state: the policy's time grid


def test_the_reach_mpc_refits_its_samples_after_each_goal_on_a_wall_clock_arm(tmp_path):
    """evaluate(after=refit_mpc): on a wall-clock arm the CEM's count follows the plan times
    of the policy steps of each MPC episode (injected: 4x slower after the first goal), within
    [floor, configured], elites kept at their share; on a lockstep rig nothing changes."""
    from hilstack.configs.schema import BusConfig
    from hilstack.control.planners import CEM
    from hilstack.drivers.base import Pacing
    from hilstack.learning.reach import ARMS, ReachRun

    for pacing in (Pacing.WALL_CLOCK, Pacing.LOCKSTEP):
        cfg = ReachConfig(arm="sawyer", samples=300, progress=False)
        run = ReachRun(cfg, ARMS["sawyer"](), tmp_path / pacing.name, BusConfig(), 0)
        run.loop.pacing, run.loop.period_s = pacing, 0.1
        if pacing is Pacing.WALL_CLOCK:
            run.loop.planner_fit = {"samples": 300, "configured_samples": 300, "trials": [], "current_samples": 300,
                                    "refits": []}
        planner = CEM(horizon=2, samples=300, elites=50, action_dim=7)
        loads, seen = iter([0.5, 4.0, 4.0]), []

        def episode(inner, planner=planner, loads=loads, seen=seen):
            seen.append(planner.samples)
            t = next(loads) * planner.samples * 1e-4  # 300 samples: 15 ms quiet, 120 ms loaded
            return {"q": np.zeros((3, 7)), "plan_s": [t] * 10, "late_plans": 10 * int(t > 0.08)}

        run.run_episode, run.apply_goal = episode, lambda g: np.zeros(3)
        run.score = lambda q, goal: {"final_distance_m": 0.1}
        run.evaluate(lambda goal: None, [{}, {}, {}], after=lambda r, i, run=run, p=planner: run.refit_mpc(p, r, i))
        if pacing is Pacing.LOCKSTEP:
            assert seen == [300] * 3
            continue
        assert seen[:2] == [300, 300] and seen[2] < 300 and planner.samples <= seen[2]
        assert planner.elites == max(1, round(planner.samples / 6))
        assert run.loop.planner_fit["refits"][0]["after"] == "mpc goal 1"
