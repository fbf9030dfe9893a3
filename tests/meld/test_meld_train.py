"""Algorithms 7 and 8 on the toy reacher (tiny images), and the robot image tasks through the registry."""

import numpy as np
import pytest
import torch

from hilstack.learning.meld.agents import AGENTS, AgentConfig
from hilstack.learning.meld.model import LatentConfig
from hilstack.learning.meld.toy import ToyReach
from hilstack.learning.meld.train import MetaTrainConfig, apply_probe, meta_test, meta_train, task_probe

CFG = AgentConfig(latent=LatentConfig(image_hw=(8, 16), action_dim=2, channels=(4, 8), feature_dim=16),
                  batch=4, seq_len=4, history=2)


@pytest.mark.parametrize("name", ["meld", "slac", "sac_history"])
def test_meta_train_runs_algorithm_7_and_8(name):
    torch.manual_seed(0)
    env = ToyReach(episode_steps=5, n_train=3, n_test=2)
    agent = AGENTS[name](CFG)
    res = meta_train(env, agent, MetaTrainConfig(env_samples=40, tasks_per_epoch=2, train_steps_per_epoch=2,
                                                   eval_every=1))
    rp = res["replay"]
    # 3 random episodes, then 2 per epoch until 40 samples: 15 + 10 + 10 + 10
    assert res["samples"] == rp.n_samples == 45 and res["epochs"] == 3 and res["gradient_steps"] == 6
    assert set(rp.episodes) <= set(env.train_tasks)  # held-out tasks never enter the replay
    for task, eps in rp.episodes.items():
        assert all(e.task == task for e in eps)
    assert [p["samples"] for p in res["curve"]] == [15, 25, 35, 45]
    assert all(p["episodes"] == 2 for p in res["curve"])
    assert np.isfinite(res["last_stats"]["critic_loss"])


def test_meta_train_refuses_more_tasks_per_epoch_than_tasks():
    env = ToyReach(episode_steps=3, n_train=2, n_test=1)
    with pytest.raises(ValueError, match="tasks_per_epoch 3: must be 1..2"):
        meta_train(env, AGENTS["meld"](CFG), MetaTrainConfig(env_samples=10, tasks_per_epoch=3))


def test_meta_test_success_is_the_tasks_own_test():
    """A controller that knows the goal succeeds on every held-out task, one that stays put fails."""
    env = ToyReach(episode_steps=8, n_train=2, n_test=3)

    class Oracle:
        name = "oracle"

        def reset(self):
            pass

        def observe(self, img, r):
            pass

        def act(self, deterministic=False):
            return np.clip((env.goal - env.p) / env.step_size, -1, 1)

    class Still(Oracle):
        def act(self, deterministic=False):
            return np.zeros(2)

    assert meta_test(env, Oracle(), env.test_tasks)["success_rate"] == 1.0
    assert meta_test(env, Still(), env.test_tasks)["success_rate"] == 0.0


def test_task_probe_recovers_a_linear_map():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(50, 4))
    w = rng.normal(size=(4, 2))
    p = f @ w + 0.5
    assert np.allclose(apply_probe(task_probe(f, p, ridge=1e-9), f), p, atol=1e-5)


def test_demo_never_overwrites_a_report(tmp_path):
    from hilstack.tools.common import UserError
    from hilstack.tools.demo_meld import cli_meld

    (tmp_path / "report.json").write_text("{}")
    with pytest.raises(UserError, match="exists"):
        cli_meld(tmp_path, quick=True)
    assert (tmp_path / "report.json").read_text() == "{}"
