"""The gym suite (issue 24): the modified half-cheetah/ant, the planners' cost, the report's keys."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from hilstack.learning.adaptation import gym_suite
from hilstack.learning.adaptation.gym_envs import GymBenchmarkEnv, crippled_leg, disabled_joint, malfunction


def _next(env, cond, a, seed=3):
    env.set_condition(cond)
    env.reset(seed)
    return env.step(a)


@pytest.mark.parametrize("name", ["half_cheetah", "ant"])
def test_conditions_act_on_the_commands(name):
    env = GymBenchmarkEnv(name)
    A = env.spec.action_dim
    a = np.linspace(-0.9, 0.8, A).astype(np.float32)
    normal = np.ones(A, dtype=np.float32)
    # a disabled joint is the normal robot given 0 on that joint
    dis = disabled_joint(A, 0) if name == "half_cheetah" else crippled_leg(3)
    a0 = a * dis
    s1, r1 = _next(env, dis, a)
    s2, r2 = _next(env, normal, a0)
    np.testing.assert_array_equal(s1, s2)
    assert r1 == pytest.approx(r2)
    assert not np.array_equal(s1, _next(env, normal, a)[0])
    # a malfunction is the normal robot given the negated command
    mal = malfunction(A, [0, 2])
    np.testing.assert_array_equal(_next(env, mal, a)[0], _next(env, normal, a * mal)[0])
    # the same reset seed: the same start
    np.testing.assert_array_equal(env.reset(5), env.reset(5))
    with pytest.raises(ValueError, match="finite multipliers"):
        env.set_condition(np.full(A, np.nan))
    with pytest.raises(ValueError, match="joint must be"):
        disabled_joint(A, A)
    env.close()


@pytest.mark.parametrize("name", ["half_cheetah", "ant"])
def test_forward_channel_is_the_rewarded_displacement_over_the_step(name):
    env = GymBenchmarkEnv(name)
    sp = env.spec
    s = env.reset(4)
    assert s.shape == (sp.state_dim,) and s[sp.velocity_index] == pytest.approx(env.env.data.qvel[0], abs=1e-6)
    rng = np.random.default_rng(0)
    for _ in range(5):
        x0 = float(env.env.data.qpos[0])
        a = rng.uniform(-1, 1, sp.action_dim).astype(np.float32)
        s, r = env.step(a)
        v = (float(env.env.data.qpos[0]) - x0) / env.env.dt
        assert s[sp.velocity_index] == pytest.approx(v, rel=1e-5, abs=1e-5)
        assert r == pytest.approx(v - sp.ctrl_cost * float(np.sum(a * a)) + sp.alive_bonus, rel=1e-5, abs=1e-5)
        # the rest of the state is gymnasium's observation
        np.testing.assert_allclose(s[:-1], env.env._get_obs(), rtol=1e-6, atol=1e-6)
    # not the instantaneous velocity: within a gait they differ
    assert s[sp.velocity_index] != pytest.approx(float(env.env.data.qvel[0]), abs=1e-3)
    env.close()


def test_switch_mid_rollout_changes_the_condition_at_that_step():
    env = GymBenchmarkEnv("half_cheetah")
    seen = []
    orig = env.step

    def step(a):
        seen.append(env.condition.copy())
        return orig(a)
    env.step = step
    gym_suite.rollout(env, 6, 0, {0: disabled_joint(6, 2), 3: disabled_joint(6, 0)}, lambda t, s: np.zeros(6))
    assert [int(np.argmin(c)) for c in seen] == [2, 2, 2, 0, 0, 0]


def test_cost_prefers_forward_velocity_and_small_actions():
    cost = gym_suite.reward_cost("half_cheetah")
    st = torch.zeros(1, 2, 4, 18)
    st[0, 0, 1:, 17] = 1.0  # candidate 0 runs forward at 1 m/s (mean over each step)
    st[0, 1, 1:, 8] = 5.0   # candidate 1's instantaneous qvel[0] is not what the reward pays
    act = torch.zeros(2, 3, 6)
    c = cost(st, act)
    assert c.shape == (1, 2) and c[0, 0] == pytest.approx(-3.0) and c[0, 1] == 0
    act[1] = 1.0
    assert cost(st, act)[0, 1] == pytest.approx(0.05 * 18)


def test_tiny_gym_suite_writes_the_issue_report(tmp_path):
    from hilstack.tools.demo_adaptation import run_gym_demo

    run_gym_demo(tmp_path, tiny=True)
    r = json.loads((tmp_path / "report.json").read_text())
    b = r["benchmarks"]
    assert set(b) == {"hc_normal", "hc_disabled_joint", "hc_malfunction_switch", "hc_disabled_joint_next_k"}
    assert set(b["hc_disabled_joint"]) == {*gym_suite.JOINT_METHODS, "zero_action"}
    # the sanity check: MB on the unperturbed robot beside the do-nothing floor (no oracle: no ratio)
    assert set(b["hc_normal"]) == {"mb", "zero_action"}
    assert all(c["normalized"] is None for c in b["hc_normal"].values())
    # iterated on-policy rounds: one mean return of MB's MPC rollouts per round
    assert len(r["per_seed"][0]["training"]["disabled_joint"]["mb"]["onpolicy_returns"]) == r["config"]["onpolicy_rounds"] == 2
    assert set(b["hc_malfunction_switch"]) == set(gym_suite.MOLE_METHODS)
    nk = b.pop("hc_disabled_joint_next_k")
    assert set(nk) == set(gym_suite.JOINT_METHODS)
    for cell in nk.values():
        assert cell["next_k_error"]["mean"] > 0 and len(cell["next_k_error"]["seeds"]) == 1
    for row in b.values():
        for cell in row.values():
            assert {"return_mean", "return_std", "normalized", "seeds"} <= set(cell)
            assert np.isfinite(cell["return_mean"]) and len(cell["seeds"]) == 1
    mole = b["hc_malfunction_switch"]["mole"]
    cfg = r["config"]
    steps = cfg["switch_every"] * cfg["switch_segments"]
    assert mole["tasks_created"][0] >= 1 and len(mole["posterior_trace"][0]) == steps
    for p in mole["posterior_trace"][0]:
        assert abs(sum(p) - 1) < 1e-3
    assert r["switch_conditions"] == ["normal", "malfunction", "normal"]
    assert (tmp_path / "gym_mole_posterior.png").is_file() and (tmp_path / "report.md").is_file()
    # what the CLI prints: one line per benchmark, open-loop rows included
    lines = gym_suite.summary_lines(json.loads((tmp_path / "report.json").read_text()))
    assert len(lines) == 4 and any(ln.startswith("hc_disabled_joint_next_k: mb ") for ln in lines)
    assert "| grbal |" in (tmp_path / "report.md").read_text()


def test_cli_refuses_an_unknown_suite(tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    res = CliRunner().invoke(app, ["demo", "adaptation", "--suite", "mars", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "unknown --suite 'mars'" in res.output
    res = CliRunner().invoke(app, ["demo", "transfer", "--suite", "gym", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--suite is for the adaptation demo only" in res.output


def test_part_overrides_are_typed_like_the_config_and_refuse_unknown_fields():
    o = gym_suite.parse_overrides(["onpolicy_rounds=4", "hidden=256,256", "gamma=10"])
    assert o == {"onpolicy_rounds": 4, "hidden": (256, 256), "gamma": 10.0}
    assert gym_suite.GymSuiteConfig(**o).hidden == (256, 256)
    with pytest.raises(ValueError, match="FIELD one of"):
        gym_suite.parse_overrides(["epoch=3"])
    with pytest.raises(ValueError, match="is not a int"):
        gym_suite.parse_overrides(["onpolicy_rounds=many"])
    with pytest.raises(ValueError, match="not finite"):
        gym_suite.parse_overrides(["gamma=nan"])
