"""MB, MF and Mb-Mf on gymnasium (learning/mbmf.py, `hil demo mbrl-gym`)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from hilstack.learning import mbmf
from hilstack.learning.mbmf import TASKS, MbmfConfig


def _random_transitions(name: str, steps: int, seed: int = 0):
    env = mbmf.make_env(name, steps)
    rng = np.random.default_rng(seed)
    s, _ = env.reset(seed=seed)
    S, A, R = [s], [], []
    for _ in range(steps):
        a = rng.uniform(-1, 1, TASKS[name].action_dim).astype(np.float32)
        s, r, term, trunc, _ = env.step(a)
        S.append(s), A.append(a), R.append(r)
        if term or trunc:
            break
    env.close()
    return torch.tensor(np.array(S)), torch.tensor(np.array(A)), np.array(R)


@pytest.mark.parametrize("name", ["swimmer", "half_cheetah", "hopper"])
def test_reward_on_the_observation_tracks_the_environments_reward(name):
    """The planner's reward, computed from the next observation (qvel[0] at the step's end
    against gymnasium's finite difference of x), follows the environment's reward."""
    S, A, R = _random_transitions(name, 150)
    r = mbmf.step_rewards(TASKS[name], S[1:], A).numpy()
    assert np.corrcoef(r, R)[0, 1] > 0.85
    assert abs(r.sum() - R.sum()) < 0.1 * np.abs(R).sum()


def test_reward_stops_after_the_hopper_falls():
    task = TASKS["hopper"]
    s = torch.zeros(4, task.obs_dim)
    s[:, 0] = 1.2          # torso height: healthy
    s[:, task.velocity_index] = 1.0
    s[2, 0] = 0.5          # fallen at the third step
    r = mbmf.step_rewards(task, s, torch.zeros(4, task.action_dim))
    assert r.tolist() == pytest.approx([2.0, 2.0, 0.0, 0.0])  # velocity + healthy, then the episode is over


def test_dagger_labels_the_learners_states_with_the_experts_actions():
    env = mbmf.make_env("swimmer", 30)
    learner = lambda s: np.array([0.8, -0.8])               # noqa: E731 - what the policy does
    expert = lambda s: np.tanh(s[:2] * 3.0)                 # noqa: E731 - what the MPC would do
    states, labels, rets, steps = mbmf.dagger_iteration(env, learner, expert, rollouts=2, seed=5)
    # the states are the ones the learner visited (replayed: same seeds, same actions)
    visited = np.concatenate([mbmf.run_episode(env, learner, 5 + j)[0].states[:-1] for j in range(2)])
    env.close()
    assert steps == 60 and len(rets) == 2
    np.testing.assert_allclose(states, visited)
    np.testing.assert_allclose(labels, np.tanh(visited[:, :2] * 3.0), rtol=1e-6)
    assert not np.allclose(labels, [0.8, -0.8])


def test_imitation_fits_the_gaussian_and_its_std_is_reset_to_one():
    torch.manual_seed(0)
    cfg = MbmfConfig.tiny()
    algo = mbmf.new_trpo("swimmer", cfg, 0)
    pol = algo.policy
    rng = np.random.default_rng(0)
    X = rng.normal(size=(400, 8)).astype(np.float32)
    Y = np.tanh(X[:, :2] @ np.array([[0.8, -0.3], [0.2, 0.5]], dtype=np.float32))
    before = mbmf.behaviour_clone(pol, X, Y, epochs=1, lr=3e-3, batch=100, seed=0)
    after = mbmf.behaviour_clone(pol, X, Y, epochs=60, lr=3e-3, batch=100, seed=0)
    assert after < 0.2 * before                                  # the mean learned the labels
    assert float(pol.log_std.detach().exp().max()) < 0.6                 # likelihood: the std shrank to the error
    with torch.no_grad():
        mean = mbmf.policy_mean(pol, X[:5]).clone()
    mbmf.reset_policy_std(pol, 1.0)
    np.testing.assert_allclose(pol.log_std.exp().detach().numpy(), 1.0, rtol=1e-6)
    with torch.no_grad():
        torch.testing.assert_close(mbmf.policy_mean(pol, X[:5]), mean)  # the mean is untouched
    algo.env.close()


def test_mb_moves_the_swimmer_forward_where_random_actions_do_not():
    """A few hundred random steps, one fit, then random-shooting MPC on the model: the
    MPC's return beats the random rollouts' (swimmer, 60-step episodes)."""
    torch.manual_seed(0)
    cfg = MbmfConfig.tiny(episode_len=60, random_rollouts=8, mpc_rollouts=2, hidden=(64, 64), epochs=40,
                          samples=200, horizon=8)
    mb = mbmf.run_mb("swimmer", cfg, seed=0, log=lambda m: None)
    rand = mbmf.do_nothing_return("swimmer", 60)["random_mean"]
    assert mb.steps == 8 * 60 + 2 * 60
    assert mb.curve[-1]["return_mean"] > rand + 1.0, (mb.curve, rand)


def test_comparison_finds_where_mbmf_reaches_mfs_final_return():
    def curve(points):
        return [{"steps": s, "return_mean": r, "return_std": 0.0} for s, r in points]

    mf = [{"seed": 0, "curve": curve([(0, 0), (10, 40), (20, 100), (30, 90)])}]
    mbmf_runs = [{"seed": 0, "curve": curve([(3, 50), (6, 95), (9, 120)]), "info": {"imitation_steps": 3}}]
    r = mbmf.compare({"mb": [], "mf": mf, "mbmf": mbmf_runs})
    assert r["mf_final"] == 90 and r["mf_budget"] == 30
    assert r["mf_first_reach"] == 20          # MF's curve first reached 90 at 20
    assert r["mbmf_steps_to_mf_final"] == 6
    assert r["speedup_vs_mf_first_reach"] == pytest.approx(20 / 6)
    assert r["reached_ratio"]
    mbmf_runs[0]["curve"] = curve([(3, 50), (6, 80), (9, 89)])
    r = mbmf.compare({"mb": [], "mf": mf, "mbmf": mbmf_runs})
    assert r["mbmf_steps_to_mf_final"] is None and not r["reached_ratio"]


def test_demo_cli_tiny_writes_the_report_and_reuses_finished_runs(tmp_path, capsys):
    from hilstack.tools import demo_mbmf

    r = demo_mbmf.run_demo(tmp_path, tiny=True, envs=("swimmer",))
    v = r["envs"]["swimmer"]
    assert set(v["curves"]) == {"mb", "mf", "mbmf"} and v["do_nothing"] is not None
    assert (tmp_path / "rewards.png").stat().st_size > 0 and "| swimmer |" in (tmp_path / "report.md").read_text()
    run = json.loads((tmp_path / "runs" / "swimmer_mf_s0.json").read_text())
    assert run["curve"][0]["steps"] == 0 and run["curve"][-1]["steps"] >= MbmfConfig.tiny().mf_steps
    mb_mf = json.loads((tmp_path / "runs" / "swimmer_mbmf_s0.json").read_text())
    assert mb_mf["info"]["finetune_start_index"] == 1  # one DAgger point, then the fine-tuning's
    assert mb_mf["curve"][0]["steps"] == mb_mf["info"]["imitation_steps"]
    assert json.loads((tmp_path / "runs" / "swimmer_mf_s0.partial.json").read_text())["curve"] == run["curve"]
    mtimes = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").glob("*.json")}
    demo_mbmf.run_demo(tmp_path, tiny=True, envs=("swimmer",))
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "runs").glob("*.json")} == mtimes
    with pytest.raises(ValueError, match="unknown --envs"):
        demo_mbmf.parse_envs("swimmer,walker", quick=False)
