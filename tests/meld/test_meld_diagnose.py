"""The state-SAC diagnostic: its budget arithmetic (updates per sample) and held-out evaluation."""

import numpy as np

from hilstack.learning.meld.diagnose import StateSacConfig, state_sac


class PointTasks:
    """A point moved by its action towards a goal that differs per task (the goal is given)."""

    episode_steps = 10
    action_dim = 2
    success_m = 0.1

    def __init__(self):
        self.goals = np.random.default_rng(0).uniform(-1, 1, (6, 2))
        self.train_tasks, self.test_tasks = [0, 1, 2, 3], [4, 5]
        self.resets = 0

    def set_task(self, t):
        self.goal = self.goals[t]

    def reset(self):
        self.p = np.zeros(2)
        self.resets += 1
        return None, 0.0

    def step(self, a):
        self.p = self.p + 0.2 * np.clip(a, -1, 1)
        d = float(np.linalg.norm(self.p - self.goal))
        return None, -d, {"success": d < self.success_m, "distance_m": d}

    def state(self):
        return self.p

    def goal_features(self):
        return self.goal


def test_state_sac_spends_the_configured_updates_and_evaluates_held_out_tasks():
    env = PointTasks()
    cfg = StateSacConfig(samples=60, updates_per_sample=0.5, batch=16, random_episodes=2, eval_every=3)
    res = state_sac(env, cfg)
    # 6 episodes of 10 samples; updates start after the 2nd (random) episode: 5 episodes × 10 × 0.5
    assert [p["samples"] for p in res["curve"]] == [30, 60]
    assert res["final"]["gradient_steps"] == 25
    assert res["curve"][0]["gradient_steps"] == 10
    # one reset to size the observation, 6 training episodes, one episode per held-out task per evaluation
    assert env.resets == 1 + 6 + 2 * len(env.test_tasks)
    assert 0.0 <= res["final"]["success_rate"] <= 1.0 and res["final"]["final_distance_m"] > 0


def test_curve_probe_spends_the_updates_per_sample_and_reports_rates():
    """``demo_meld curve``: gradient steps per epoch = updates per sample × samples per epoch, the
    held-out curve records samples and gradient steps at each evaluation."""
    from hilstack.tools.demo_meld import run_curve

    # toy: 20 training tasks × 20 steps of random start, then epochs of 4 episodes (80 samples)
    res = run_curve("toy", "sac_history", seed=0, samples=560, updates_per_sample=0.025, eval_every_samples=160,
                    log=lambda m: None)
    assert res["train_steps_per_epoch"] == 2 and res["epochs"] == 2 and res["gradient_steps"] == 4
    assert [(p["samples"], p["gradient_steps"]) for p in res["curve"]] == [(400, 0), (560, 4)]
    assert res["samples_per_s"] > 0 and res["gradient_steps_per_s"] > 0
    assert 0.0 <= res["final"]["success_rate"] <= 1.0 and res["final"]["episodes"] == 10
