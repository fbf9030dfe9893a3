"""The Baoding diagnosis tools (tools/demo_baoding.py, docs/baoding.md "Why success_90 stays
at 0"): the model probe scores the turn a model predicts against the true one, and the
sim oracle predicts exactly what the hand does."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.drivers.shadow_hand.config import ShadowHandParams, shadow_hand_spec
from hilstack.learning.baoding import BaodingFeatures, hold_action_map, load_baoding_task
from hilstack.learning.datasets import Episode
from hilstack.tools.demo_baoding import SimOracle, probe_model

NAMES = list(shadow_hand_spec(ShadowHandParams(objects_in_state=True)).state.names)
DT = 0.1


def turning_episodes(task, n: int = 4, T: int = 20, seed: int = 0):
    """Model episodes whose pair turns about the task's centre by 0.1·a_0 rad per step (a
    the action), joints still: a known dynamics for the probe."""
    f = BaodingFeatures(NAMES, DT)
    rng = np.random.default_rng(seed)
    u, v = task._basis()[:2]
    eps = []
    for k in range(n):
        th = rng.uniform(-np.pi, np.pi)
        acts = rng.uniform(-1, 1, (T, 20))
        raw = []
        for t in range(T + 1):
            d = 0.015 * (np.cos(th) * u + np.sin(th) * v)
            s = np.full(len(NAMES), 0.1)
            s[-6:] = np.concatenate([task.center_m + d, task.center_m - d])
            raw.append(s)
            if t < T:
                th += 0.1 * acts[t, 0]
        eps.append(f.episode(Episode(states=np.array(raw), actions=acts, times=np.arange(T + 1) * DT, name=f"e{k}")))
    return eps


class Exact:
    """The turning episodes' dynamics, exactly (features: ball velocity by finite difference)."""

    def __init__(self, task, names):
        self.task, self.bp = task, [names.index(f"ball{i}_{c}") for i in range(2) for c in "xyz"]
        self.bv = [names.index(f"ball{i}_v{c}") for i in range(2) for c in "xyz"]

    def predict(self, s, a):
        s = s.double().numpy().reshape(-1, s.shape[-1])
        a = a.double().numpy().reshape(-1, a.shape[-1])
        out = s.copy()
        n = self.task._basis()[2]
        for i in range(len(s)):
            b = s[i, self.bp].reshape(2, 3)
            d = 0.5 * (b[0] - b[1])
            ang = 0.1 * a[i, 0]  # Rodrigues about the palm normal
            d2 = d * np.cos(ang) + np.cross(n, d) * np.sin(ang) + n * (n @ d) * (1 - np.cos(ang))
            nb = np.concatenate([self.task.center_m + d2, self.task.center_m - d2])
            out[i, self.bv] = (nb - s[i, self.bp]) / DT
            out[i, self.bp] = nb
        return torch.from_numpy(out).float()[None]


class Still:
    def predict(self, s, a):
        return (s if s.dim() == 3 else s[None]).clone()


def test_the_probe_scores_the_predicted_turn_against_the_true_one():
    task = load_baoding_task()
    eps = turning_episodes(task)
    exact = probe_model(Exact(task, eps[0].meta["state_names"]), eps, task, horizon=5)
    still = probe_model(Still(), eps, task, horizon=5)
    assert exact["windows"] == still["windows"] == 4 * 16 and exact["turn_true_std_deg"] > 5
    assert exact["turn_r2"] > 0.99 and exact["turn_corr"] > 0.99 and exact["ball_1step_mm"] < 0.05
    # a model that predicts no motion: the balls' error is "the balls stay", no turn predicted
    assert still["turn_r2"] <= 0.0
    np.testing.assert_allclose(still["ball_1step_mm"], still["ball_1step_stay_mm"], rtol=1e-5)
    np.testing.assert_allclose(still["ball_hstep_mm"], still["ball_hstep_stay_mm"], rtol=1e-5)
    assert still["ball_1step_mm"] > 0.5


def test_the_sim_oracle_predicts_what_the_hand_does():
    from hilstack.drivers.registry import make_backend

    sim = make_backend("shadow_hand", "sim", objects_in_state=True)
    sim.configure()
    sim.activate()
    try:
        f, amap = BaodingFeatures(NAMES, DT), hold_action_map()
        oracle = SimOracle(sim, BaodingFeatures(NAMES, DT), amap)
        rng = np.random.default_rng(0)
        o = sim.read()
        f(o.state)
        for _ in range(3):
            z = rng.uniform(-0.5, 0.5, (3, 20))
            oracle.begin()
            s0 = torch.from_numpy(f.transform(o.state[None])).float().expand(3, -1)
            p1 = oracle.predict(s0, torch.from_numpy(z).float())
            p2 = oracle.predict(p1, torch.from_numpy(z[::-1].copy()).float())
            t_before = sim.sim_time_s
            sim.write(amap.to_driver(z[1]))
            sim.tick()
            o = sim.read()
            x = f(o.state)
            assert sim.sim_time_s > t_before  # the oracle's copies did not move the hand's clock
            np.testing.assert_allclose(p1[1].numpy(), x, atol=1e-5)  # candidate 1's step is the hand's
            assert np.abs(p1[0].numpy() - x)[:24].max() > 1e-4  # another action, another state
            assert p2.shape == (3, 36) and np.isfinite(p2.numpy()).all()
    finally:
        sim.cleanup()


def test_oracle_episodes_are_recorded_as_the_demo_records_and_replay_on_the_hand(tmp_path):
    """`oracle-record`'s recordings read back through the demo's loaders: every state the hand
    read, with the command it applied during each period (replaying those commands on the reset
    hand gives the same states), the turn figures of its JSON line, the held-out split by seed;
    and a second recording into the same files is refused."""
    import json

    import pytest

    from hilstack.control.costs import baoding_episode_metrics
    from hilstack.drivers.registry import make_backend
    from hilstack.tools.demo_baoding import oracle_record, oracle_split, run_episodes

    rows = oracle_record(tmp_path, episodes=1, samples=2, seed=3, steps=3)
    oracle_record(tmp_path, episodes=1, samples=2, seed=4, steps=2)
    eps = run_episodes(tmp_path)
    assert sorted(eps) == ["oracle-s3-000", "oracle-s4-000"]
    (ep,) = eps["oracle-s3-000"]
    assert ep.states.shape == (4, len(NAMES)) and ep.actions.shape == (3, 20)
    line = json.loads((tmp_path / "oracle_episodes.jsonl").read_text().splitlines()[0])
    assert line == rows[0] | {"loadavg": line["loadavg"]} and line["states"] == 4
    sim = make_backend("shadow_hand", "sim", objects_in_state=True)
    sim.configure()
    sim.activate()
    try:
        sim.reset()
        got = [sim.read().state]
        for a in ep.actions:  # the recorded (applied) commands, replayed on the reset hand
            sim.write(a)
            sim.tick()
            got.append(sim.read().state)
        # the loader gives the actions in float32: the replay matches to its rounding
        np.testing.assert_allclose(np.array(got), ep.states, rtol=1e-4, atol=1e-6)
        assert np.abs(np.diff(ep.states[:, :24], axis=0)).max() > 1e-2  # the hand did move
        m = baoding_episode_metrics(sim.task, ep.states[:, -6:].reshape(-1, 2, 3), None,
                                    wrist_rad=ep.states[:, NAMES.index("WRJ0_pos")], period_s=DT)
        assert m["rotation_deg"] == pytest.approx(line["rotation_deg"], abs=1e-3)  # float32 states
    finally:
        sim.cleanup()
    train, held = oracle_split(tmp_path, BaodingFeatures(NAMES, DT), hold_action_map(), (4,))
    assert [len(e) for e in held] == [2] and [len(e) for e in train] == [3, 3]  # seed 3's, twice (balls swapped)
    np.testing.assert_allclose(train[1].states[:, 24:30], train[0].states[:, 30:36])
    with pytest.raises(FileExistsError, match="oracle-s3-000.mcap"):
        oracle_record(tmp_path, episodes=1, samples=2, seed=3, steps=3)


def test_an_oracle_episode_stopped_midway_keeps_the_unfinished_name(tmp_path, monkeypatch):
    """A recording gets the name the loaders read only when its episode has ended: one stopped
    mid-episode (Ctrl-C here; a killed process likewise) stays `*.unfinished.mcap`, which the
    loaders skip, and a new run with that seed is refused rather than writing over it."""
    import pytest

    from hilstack.tools import demo_baoding
    from hilstack.tools.demo_baoding import oracle_record, run_episodes

    real = demo_baoding._episode

    def stopped(sim, pol, task, steps, wrist, plan_s, **kw):
        real(sim, pol, task, 1, wrist, plan_s, **kw)  # one period recorded, then the stop
        raise KeyboardInterrupt

    monkeypatch.setattr(demo_baoding, "_episode", stopped)
    with pytest.raises(KeyboardInterrupt):
        oracle_record(tmp_path, episodes=2, samples=2, seed=5, steps=3)
    rec = tmp_path / "recordings"
    assert sorted(p.name for p in rec.iterdir()) == ["oracle-s5-000.unfinished.mcap"]
    assert run_episodes(tmp_path) == {}
    with pytest.raises(FileExistsError, match="unfinished"):
        oracle_record(tmp_path, episodes=1, samples=2, seed=5, steps=3)


def test_the_run_tools_refuse_a_run_of_another_hold_pose(tmp_path):
    """diagnose / oracle-train build the default (cupped) hand and its action map: a run of the
    pddm hold pose is refused in one line, not probed with the wrong pose's action units."""
    import json

    from hilstack.tools.demo_baoding import run_split

    (tmp_path / "report.json").write_text(json.dumps({"config": {"task": "baoding_pddm_pose"}}))
    with pytest.raises(ValueError, match=r"ran task baoding_pddm_pose: diagnose and oracle-train model") as e:
        run_split(tmp_path, 3)
    assert "\n" not in str(e.value)
