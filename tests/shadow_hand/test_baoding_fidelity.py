"""Baoding as the reference code (google-research/pddm) poses it (issue 30): the model's state
with the balls' velocities, actions about the hold pose, the targets' ellipse and period,
the x-y distance and the wrist term, targets that do not drag a lagging pair backwards,
and turns (not return) ranking the policies."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.control.costs import BaodingCost, baoding_episode_metrics
from hilstack.drivers.shadow_hand.config import (
    BALL_CHANNELS,
    JOINT_NAMES,
    ShadowHandParams,
    hold_pose_action,
    shadow_hand_spec,
)
from hilstack.learning.baoding import (
    BaodingFeatures,
    BaodingPolicy,
    HoldActionMap,
    hold_action_map,
    load_baoding_task,
    summarize,
    turn_rank_key,
)
from hilstack.learning.datasets import Episode
from hilstack.tasks.baoding import BaodingTask, TargetPhase

NAMES = list(shadow_hand_spec(ShadowHandParams(objects_in_state=True)).state.names)
DT = 0.1


def raw_state(balls: np.ndarray, q: float = 0.1) -> np.ndarray:
    s = np.full(len(NAMES), q)
    s[[NAMES.index(c) for c in BALL_CHANNELS]] = np.asarray(balls).reshape(-1)
    return s


def flat_task(**kw) -> BaodingTask:
    base = dict(center_m=np.array([0.0, 0.0, 0.1]), axis=np.array([0.0, 0.0, 1.0]), radius_m=0.02, radius_v_m=0.036,
                rate_rad_s=2 * np.pi / 6, distance="plane", wrist_limit_rad=0.15)
    base.update(kw)
    return BaodingTask(**base)


# ---------------------------------------------------------------------------- the model's state
def test_the_model_state_has_joint_angles_and_each_balls_position_and_velocity():
    f = BaodingFeatures(NAMES, DT)
    want_balls = [f"ball{i}_{q}" for i in range(2) for q in ("x", "y", "z", "vx", "vy", "vz")]
    assert f.names == [f"{j}_pos" for j in JOINT_NAMES] + want_balls and f.dim == 36  # the reference's 40 less targets
    assert len(BaodingFeatures(NAMES, DT, joint_velocities=True).names) == 60
    # velocities: finite differences over the period, zero at the episode's first state
    p = np.array([[[0.0, 0.0, 0.1], [0.01, 0.0, 0.1]], [[0.002, 0.001, 0.1], [0.01, -0.003, 0.099]],
                  [[0.005, 0.001, 0.1], [0.01, -0.003, 0.099]]])
    states = np.stack([raw_state(b) for b in p])
    x = f.transform(states)
    vel = np.stack([x[:, 27:30], x[:, 33:36]], 1)
    np.testing.assert_allclose(vel[0], 0.0)
    np.testing.assert_allclose(vel[1:], (p[1:] - p[:-1]) / DT, atol=1e-12)
    np.testing.assert_allclose(np.stack([x[:, 24:27], x[:, 30:33]], 1), p)
    # the per-step call of a running episode gives the same as the recorded episode's
    f.reset()
    np.testing.assert_allclose(np.stack([f(s) for s in states]), x, atol=1e-12)
    ep = f.episode(Episode(states=states, actions=np.zeros((2, 20)), times=np.arange(3) * DT, name="e"))
    assert ep.meta["state_names"] == f.names and ep.states.shape == (3, 36)


def test_the_planner_plans_from_the_balls_velocities():
    """The state the planner rolls the model out from (its dynamics' first input) carries the
    balls' measured velocities: a model without them could not tell a ball rolling off from
    one at rest."""
    from hilstack.control.planners import PDDM
    from hilstack.control.policies import MpcPolicy

    seen = []

    class Model:
        def predict(self, s, a):
            if s.dim() == 2:
                seen.append(s[0].clone())
            return s.clone()

    f = BaodingFeatures(NAMES, DT)
    tk = load_baoding_task()
    planner = PDDM(-1.0, 1.0, horizon=3, samples=8, action_dim=20, init_mean=np.zeros(20), filter="actions")
    pol = BaodingPolicy(MpcPolicy(Model(), planner, BaodingCost(tk, f.names, DT)), f, hold_action_map())
    pol.reset()
    b0 = np.stack([tk.center_m, tk.center_m]) + [[0.02, 0, 0], [-0.02, 0, 0]]
    b1 = b0 + [[0.0, 0.003, 0.0], [0.0, -0.003, 0.0]]  # the pair turning: 3 cm/s each way
    pol(raw_state(b0))
    pol(raw_state(b1))
    vx = [f.names.index(f"ball{i}_v{c}") for i in range(2) for c in "xyz"]
    np.testing.assert_allclose(seen[0][vx].numpy(), 0.0, atol=1e-6)
    np.testing.assert_allclose(seen[-1][vx].numpy(), [0, 0.03, 0, 0, -0.03, 0], atol=1e-5)
    # a new episode (the policy reset, the balls put back elsewhere) starts at rest: no velocity
    # from the last episode's balls to the new ones
    pol.reset()
    pol(raw_state(b0 + [0.0, 0.0, -0.05]))
    np.testing.assert_allclose(seen[-1][vx].numpy(), 0.0, atol=1e-6)


def test_the_run_trains_and_plans_on_the_features(bus, tmp_path):
    from hilstack.learning.baoding import BaodingConfig, BaodingRun

    run = BaodingRun(BaodingConfig.from_preset("tiny"), tmp_path, bus)
    run.state_names = NAMES
    run.action_names = list(shadow_hand_spec(ShadowHandParams()).action.names)
    assert run.pddm_config().state_dim == 36
    assert {"ball0_vx", "ball1_vz"} <= set(run.features.names)
    ep = Episode(states=np.stack([raw_state(np.zeros((2, 3)))] * 3), actions=np.tile(hold_pose_action(), (2, 1)),
                 times=np.arange(3) * DT, name="e")
    m = run.model_episodes([ep])[0]
    assert m.states.shape[1] == 36
    np.testing.assert_allclose(m.actions, 0.0, atol=1e-6)  # the hold pose is z = 0


def test_training_doubles_the_data_with_the_balls_swapped_and_validates_unswapped(bus, tmp_path):
    """The reference code's data doubling (``duplicateData_switchObjs``): every training
    episode once more with ball 0's and ball 1's position and velocity exchanged; validation
    episodes are never swapped (nor their swapped copies trained on)."""
    from hilstack.learning.baoding import BaodingConfig, BaodingRun

    f = BaodingFeatures(NAMES, DT)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4, f.dim))
    ep = Episode(states=x, actions=np.zeros((3, 20)), name="e")
    sw = f.swap_balls(ep)
    b0, b1 = f.names.index("ball0_x"), f.names.index("ball1_x")
    np.testing.assert_array_equal(sw.states[:, :b0], ep.states[:, :b0])  # joints as they were
    np.testing.assert_array_equal(sw.states[:, b0:b0 + 6], ep.states[:, b1:b1 + 6])
    np.testing.assert_array_equal(sw.states[:, b1:b1 + 6], ep.states[:, b0:b0 + 6])
    assert f.names[b0:b0 + 6] == ["ball0_x", "ball0_y", "ball0_z", "ball0_vx", "ball0_vy", "ball0_vz"]
    np.testing.assert_array_equal(f.swap_balls(sw).states, ep.states)

    seen = {}

    class Model:
        def fit(self, train, epochs, batch_size, val, horizon, progress):
            seen.update(train=[e.name for e in train], val=[e.name for e in val or []])
            return [{"train_loss": 1.0}]

    for swap in (True, False):
        run = BaodingRun(BaodingConfig.from_preset("tiny", swap_balls=swap), tmp_path / str(swap), bus)
        run.state_names = NAMES
        eps = [Episode(states=rng.normal(size=(4, f.dim)), actions=np.zeros((3, 20)), name=f"e{i}") for i in range(10)]
        run.train(Model(), eps, 1)
        plain = [n for n in seen["train"] if not n.endswith("#swapped")]
        assert len(seen["val"]) == 1 and not any(n.endswith("#swapped") for n in seen["val"])
        assert sorted(plain + seen["val"]) == sorted(e.name for e in eps)
        assert sorted(n for n in seen["train"] if n.endswith("#swapped")) == (
            sorted(f"{n}#swapped" for n in plain) if swap else [])


# ---------------------------------------------------------------------------- actions about the hold pose
def test_the_baoding_run_starts_every_pddm_rollout_at_the_hold_pose(bus, tmp_path):
    """learning/baoding.py gives the planner init_mean: z = 0, the hold pose in the planner's
    units (the reference code's zero mean); "mid" is the middle of every joint's range."""
    from hilstack.learning.baoding import BaodingConfig, BaodingRun

    for init, want in (("hold", hold_pose_action()), ("mid", np.zeros(20))):
        run = BaodingRun(BaodingConfig.from_preset("tiny", init_mean=init), tmp_path / init, bus)
        run.state_names = NAMES
        run.action_names = list(shadow_hand_spec(ShadowHandParams()).action.names)
        pol = run.pddm_policy(model=None, seed=0)
        first = pol.planner.mean.numpy()
        assert np.allclose(first, first[0]) and pol.planner.previous.numpy() == pytest.approx(first[0])
        np.testing.assert_allclose(run.amap.to_driver(first[0]), want, atol=1e-6)
    np.testing.assert_allclose(hold_action_map().to_driver(np.zeros(20)), hold_pose_action(), atol=1e-9)


def test_actions_about_the_hold_pose():
    h = np.array([-0.5, 0.0, 0.8])
    m = HoldActionMap(h, 0.9)
    np.testing.assert_allclose(m.to_driver(np.zeros(3)), h)
    np.testing.assert_allclose(m.to_driver(np.ones(3)), h + 0.9 * (1 - h))  # 0.9 of the way to the upper limit
    np.testing.assert_allclose(m.to_driver(-np.ones(3)), h - 0.9 * (h + 1))
    z = np.array([0.3, -0.7, 0.05])
    np.testing.assert_allclose(m.from_driver(m.to_driver(z)), z, atol=1e-12)
    assert np.all(np.abs(m.to_driver(np.array([5.0, -5.0, 2.0]))) <= 1.0)


# ---------------------------------------------------------------------------- the task
def test_targets_on_the_reference_ellipse_at_a_turn_per_60_steps():
    tk = load_baoding_task()
    assert tk.radii == pytest.approx((0.02, 0.036)) and 2 * np.pi / tk.rate_rad_s == pytest.approx(6.0)
    t = flat_task()
    np.testing.assert_allclose(t.targets(0.0), [[0.02, 0, 0.1], [-0.02, 0, 0.1]], atol=1e-12)
    np.testing.assert_allclose(t.targets(1.5), [[0, 0.036, 0.1], [0, -0.036, 0.1]], atol=1e-12)  # a quarter turn
    np.testing.assert_allclose(t.targets(6.0), t.targets(0.0), atol=1e-12)
    assert t.pair_phase(t.targets(1.0)) == pytest.approx(2 * np.pi / 6)


def test_reward_x_y_distance_and_wrist_term():
    t = flat_task()
    on = t.targets(0.5)
    assert t.reward(on, 0.5) == pytest.approx(0.0)
    up = on + [0, 0, 0.01]  # 1 cm above the targets: no x-y distance
    assert t.reward(up, 0.5) == pytest.approx(0.0)
    assert flat_task(distance="3d").reward(up, 0.5) == pytest.approx(-5 * 0.02)
    side = on + [[0.01, 0, 0], [0, 0, 0]]
    assert t.reward(side, 0.5) == pytest.approx(-0.05)
    assert t.reward(on, 0.5, wrist_rad=0.2) == pytest.approx(-10.0)
    assert t.reward(on, 0.5, wrist_rad=0.1) == pytest.approx(0.0)
    # the cost reads the wrist from WRJ0_pos
    f = BaodingFeatures(NAMES, DT)
    cost = BaodingCost(t, f.names, DT)
    cost.observe(None)
    s = np.zeros((2, f.dim))
    s[:, 24:27], s[:, 30:33] = t.targets(DT)[0], t.targets(DT)[1]
    s[1, f.names.index("WRJ0_pos")] = 0.3
    c = cost(torch.tensor(s, dtype=torch.float32)[None, None], None)
    assert float(c) == pytest.approx(10.0, abs=1e-4)


def test_targets_lead_a_lagging_pair_forward_not_back():
    """The pair stayed where it started while the clock's targets went 200° round: by the
    clock the short way to them is backwards (−160°); the led targets are ahead of the pair."""
    t = flat_task(max_lead_rad=np.pi / 3)
    ph = TargetPhase(t, DT)
    start = t.targets(0.0)
    steps = int(round(np.radians(200) / (t.rate_rad_s * DT)))
    for _ in range(steps + 1):
        ph.observe(start)
    lead = ph.phases(3)
    assert lead[0] == pytest.approx(np.pi / 3 + t.rate_rad_s * DT)  # 60° ahead of the pair, plus one step
    assert np.all(np.diff(lead) > 0)
    clock = TargetPhase(flat_task(), DT)
    for _ in range(steps + 1):
        clock.observe(start)
    wrapped = (clock.phases(1)[0] + np.pi) % (2 * np.pi) - np.pi
    assert wrapped < 0  # by the clock alone the nearest way to the targets is backwards
    # a pair that keeps up follows the clock exactly
    ph.reset()
    for k in range(10):
        ph.observe(t.targets(k * DT))
    np.testing.assert_allclose(ph.phases(2), t.rate_rad_s * DT * np.array([10, 11]))


def test_the_cost_prefers_turning_forward_when_the_pair_lags():
    t = flat_task(max_lead_rad=np.pi / 3)
    f = BaodingFeatures(NAMES, DT)
    cost = BaodingCost(t, f.names, DT)
    start = t.targets(0.0)
    for _ in range(34):  # 200° of clock
        cost.observe(np.concatenate([np.zeros(24), start[0], np.zeros(3), start[1], np.zeros(3)]))

    def seq(step_rad):
        s = np.zeros((4, f.dim))
        for h in range(4):
            b = t.targets_at(h * step_rad)
            s[h, 24:27], s[h, 30:33] = b[0], b[1]
        return s

    c = cost(torch.tensor(np.stack([seq(0.2), seq(-0.2)]), dtype=torch.float32)[None], None)[0]
    assert c[0] < c[1]  # forward is cheaper


# ---------------------------------------------------------------------------- turns rank the policies
def test_a_policy_that_holds_still_does_not_rank_above_one_that_turns():
    t = flat_task(max_lead_rad=np.pi / 3)
    n = 60
    still = np.stack([t.targets(0.0)] * (n + 1))
    ang = np.radians(np.arange(n + 1) * 3.0)  # turns 3° a step: 120° in 4 s, then drops
    turn = t.targets_at(ang)
    turn[41:, 0, 2] = 0.0
    turn = turn[:42]
    hold = summarize([baoding_episode_metrics(t, still, np.arange(n + 1) * DT)] * 3)
    turns = summarize([baoding_episode_metrics(t, turn, np.arange(42) * DT)] * 3)
    assert turns["success_90"] == 1.0 and turns["drop_rate"] == 1.0 and hold["success_90"] == 0.0
    assert turns["held_90"] == 0.0 and hold["held_90"] == 0.0  # turned, then lost: not a held turn
    kept = t.targets_at(np.radians(np.arange(n + 1) * 3.0))  # the same turn, the pair kept to the end
    assert summarize([baoding_episode_metrics(t, kept, np.arange(n + 1) * DT)])["held_90"] == 1.0
    assert turns["mean_return"] < hold["mean_return"]  # the return would rank holding first
    ranked = sorted([("hold", hold), ("turns", turns)], key=lambda kv: turn_rank_key(kv[1]))
    assert ranked[0][0] == "turns"
    assert turns["mean_steps"] == 41 and hold["mean_steps"] == n


def test_a_pair_spinning_as_it_flies_off_is_not_a_turn():
    """Random flicks throw the balls out spinning: the steps with a ball outside the palm
    (task.in_palm) add no rotation, so a throw scores no 90° turn (it did before: the random
    policy had 20 % of 90° turns in a quick run)."""
    t = flat_task(radius_v_m=None)
    ang = np.radians(np.arange(12) * 15.0)  # 165° of spin ...
    grow = np.r_[np.ones(4), np.linspace(3.5, 5.0, 8)][:, None, None]  # ... while the pair flies apart
    b = t.center_m + (t.targets_at(ang) - t.center_m) * grow  # (to 10 cm from the centre, not yet a drop)
    assert not any(t.dropped(x) for x in b)
    m = baoding_episode_metrics(t, b, np.arange(12) * DT)
    assert m["turned_90"] == 0.0 and m["rotation_deg"] < 60
    circle = flat_task(radius_v_m=None)  # the same spin in the palm (a circle: the angle is the phase)
    held = baoding_episode_metrics(circle, circle.targets_at(ang), np.arange(12) * DT)
    assert held["turned_90"] == 1.0 and held["rotation_deg"] == pytest.approx(165.0)


def test_a_turn_made_with_a_ball_lifted_counts_only_without_a_rise_limit():
    """``in_palm`` has no upper bound: a pair that turns while one ball rides 3 cm up (over the
    other, up the fingers) turns in the palm's plane. ``rise_limit_m`` counts a step's turn only
    while both balls stay within that rise of where they started; ``max_rise_m`` reports it."""
    t = flat_task(radius_v_m=None)
    ang = np.radians(np.arange(12) * 15.0)  # 165° in the palm's plane
    b = t.targets_at(ang)
    b[3:9, 0] += 0.03 * t.normal  # ball 0 lifted 3 cm for six steps of it
    free = baoding_episode_metrics(t, b, None)
    assert free["turned_90"] == 1.0 and free["max_rise_m"] == pytest.approx(0.03)
    low = baoding_episode_metrics(t, b, None, rise_limit_m=0.02)
    assert low["turned_90"] == 0.0 and low["rotation_deg"] == pytest.approx(165.0 - 7 * 15.0)
    assert baoding_episode_metrics(t, b, None, rise_limit_m=0.04)["rotation_deg"] == pytest.approx(165.0)


def test_fixed_gradient_steps_per_iteration_do_not_grow_with_the_data(bus, tmp_path):
    from hilstack.learning.baoding import BaodingConfig, BaodingRun

    ep = lambda n: Episode(states=np.zeros((n + 1, 3)), actions=np.zeros((n, 1)), name="e")  # noqa: E731
    run = BaodingRun(BaodingConfig.from_preset("tiny", train_steps=100, batch_size=500, swap_balls=False), tmp_path, bus)
    small, big = run.epochs_for([ep(1000)], 1), run.epochs_for([ep(100_000)], 5)
    assert small == int(np.ceil(100 * 500 / 900)) and big == 1  # ~100 steps either way
    # with the balls swapped every training episode counts twice
    swapped = BaodingRun(BaodingConfig.from_preset("tiny", train_steps=100, batch_size=500), tmp_path / "s", bus)
    assert swapped.epochs_for([ep(1000)], 1) == int(np.ceil(100 * 500 / 1800))
    assert BaodingRun(BaodingConfig.from_preset("tiny", epochs=7, retrain_epochs=3), tmp_path / "b", bus).epochs_for([ep(10)], 2) == 3
    with pytest.raises(ValueError, match="train_steps"):
        BaodingConfig(train_steps=0)


def test_the_thesis_scale_cost_command_measures_every_lever():
    """`python -m hilstack.tools.demo_baoding cost` at a seconds-long size: plan times per K,
    dtype (bf16 only where the CPU has it natively) and thread count, training, the sim."""
    from hilstack.learning.dynamics import cpu_bf16_support
    from hilstack.tools.demo_baoding import thesis_scale_cost

    out = thesis_scale_cost(calls=2, sizes=(16,), train_points=100)
    want = {f"K16_{dt}_{th}thread" for dt in (("fp32", "bf16") if cpu_bf16_support() else ("fp32",)) for th in (1, 2)}
    assert set(out["plan_ms"]) == want
    assert all(0 < v["p50"] <= v["p99"] for v in out["plan_ms"].values())
    assert out["train_ms_per_step"] > 0 and out["sim_ms_per_period"] > 0


def test_every_ablation_is_a_valid_config():
    from hilstack.learning.baoding import BaodingConfig
    from hilstack.tools.demo_baoding import ABLATIONS

    for name, kw in ABLATIONS.items():
        c = BaodingConfig.from_preset("quick", **kw)
        replace_task = kw.get("task_overrides", {})
        from dataclasses import replace

        replace(load_baoding_task(), **replace_task)  # the task accepts the overrides
        assert c.preset == "quick", name


def test_the_quick_preset_is_the_gamma_100_ablation_and_ref_the_reference_sampler():
    """The docs' quick numbers are the `gamma_100` row (the same config as the preset), and
    `old_sampler` is the quick preset of before, with the thesis' γ 20."""
    from hilstack.learning.baoding import BaodingConfig
    from hilstack.tools.demo_baoding import ABLATIONS

    assert BaodingConfig.from_preset("quick") == BaodingConfig.from_preset("quick", **ABLATIONS["gamma_100"])
    assert BaodingConfig.from_preset("quick", **ABLATIONS["old_sampler"]).gamma == 20.0
    ref = BaodingConfig.from_preset("quick", **ABLATIONS["ref"])
    assert (ref.sigma, ref.filter, ref.beta, ref.low_noise_fraction, ref.gamma) == (0.9, "actions", 0.6, 0.1, 20.0)
    d = BaodingConfig()
    assert (d.sigma, d.filter, d.beta, d.low_noise_fraction, d.gamma) == (0.9, "actions", 0.6, 0.1, 20.0)


def test_a_stopped_run_resumes_after_its_last_finished_iteration(bus, tmp_path):
    """A thesis-scale run takes hours: report.json is rewritten after every iteration
    (``partial: true``) and a checkpoint written, so a run stopped in its second iteration keeps
    its curve and `--resume` goes on from there: the data read back from the recordings, the
    model, Adam and the validation split as they were, the stopped iteration's recording set
    aside (not overwritten)."""
    import json
    from dataclasses import replace

    from hilstack.learning.baoding import BaodingConfig, BaodingRun
    from hilstack.learning.recordings import episodes_from_mcap

    cfg = BaodingConfig.from_preset("tiny", iterations=2, random_rollouts_per_iteration=0)  # those: the end-to-end test
    run = BaodingRun(cfg, tmp_path, bus)
    real, calls = run.pddm_policy, []

    def pddm_policy(*a, **kw):
        calls.append(1)
        if len(calls) == 4:  # the second episode of iteration 2: its recording is half written
            raise KeyboardInterrupt
        return real(*a, **kw)

    run.pddm_policy = pddm_policy
    with pytest.raises(KeyboardInterrupt):
        run.run()
    r = json.loads((tmp_path / "report.json").read_text())
    assert r["partial"] is True and [it["iteration"] for it in r["iterations"]] == [1]
    it = r["iterations"][0]
    assert it["episodes"] == 2 and {"success_90", "mean_rotation_deg", "points"} <= set(it)
    assert 0 < it["wall_s"]["train"] <= it["wall_s"]["iteration"] <= it["wall_s"]["since_start"]
    assert r["hold_policy"]["episodes"] == 2 and any(p.endswith("001-mpc.mcap") for p in r["recordings"])
    state = json.loads((tmp_path / "checkpoint" / "state.json").read_text())
    assert state["iteration"] == 1 and (tmp_path / "recordings" / "002-mpc.mcap").exists()
    points = sum(len(e) for p in state["data_recordings"] for e in episodes_from_mcap(p, "hand"))
    from hilstack.tools.demo_baoding import main

    main(["plot", str(tmp_path)])  # the curve so far, of a stopped run
    assert (tmp_path / "turns.png").stat().st_size > 0

    with pytest.raises(ValueError, match="--resume"):  # never over a run without being asked
        BaodingRun(cfg, tmp_path, bus).run()
    with pytest.raises(ValueError, match="seed"):  # not with other settings
        BaodingRun(replace(cfg, seed=1), tmp_path, bus, resume=True).run()

    # as if the run had started in bf16: a resumed "auto" run keeps its precision, not measured again
    r["inference_dtype"] = "bfloat16"
    (tmp_path / "report.json").write_text(json.dumps(r))
    again = BaodingRun(cfg, tmp_path, bus, resume=True)
    fits = []
    real_fit = again.train

    def train(model, eps, epochs):
        # the checkpoint's model, Adam and split generator (new episodes are drawn as they would have been)
        fits.append((len(model.history), len(model._optimizer.state), again.split_rng.bit_generator.state))
        return real_fit(model, eps, epochs)

    again.train = train
    r2 = again.run()
    assert [it["iteration"] for it in r2["iterations"]] == [1, 2] and r2["resumed"][0]["after_iteration"] == 1
    assert json.dumps(r2["iterations"][0], sort_keys=True) == json.dumps(r["iterations"][0], sort_keys=True)
    assert r2["iterations"][1]["points"] == points  # everything recorded up to iteration 1, read back
    from hilstack.learning.dynamics import cpu_bf16_support

    assert r2["inference_dtype"] == ("bfloat16" if cpu_bf16_support() else "float32")
    assert r2["inference_dtype_measured"] is None
    assert len(fits) == 1 and fits[0][0] > 0 and fits[0][1] > 0 and fits[0][2] == state["split_rng"]
    assert again.val_assigned == {**state["val_assigned"], **again.val_assigned}
    unfinished = tmp_path / "recordings" / "002-mpc.unfinished.mcap"
    assert unfinished.exists() and str(unfinished) in r2["set_aside"]
    assert (tmp_path / "recordings" / "002-mpc.mcap").exists() and r2["wall_s"] > it["wall_s"]["since_start"]


def test_full_resume_reads_finished_seeds_resumes_the_stopped_one_and_starts_the_rest(tmp_path, monkeypatch):
    import json

    import hilstack.tools.demo_baoding as demo

    def report(s90):
        it = {"mean_rotation_deg": 1.0, "mean_steps": 100.0, "mean_return": -1.0, "drop_rate": 0.0,
              "success_90": s90, "success_180": 0.0, "points": 3000}
        return {"iterations": [it], "hold_policy": {"success_90": 0.0, "mean_rotation_deg": 0.0},
                "random_policy": {"mean_return": -500.0}}

    (tmp_path / "seed_0").mkdir()
    (tmp_path / "seed_0" / "report.json").write_text(json.dumps(report(0.5)))  # finished
    (tmp_path / "seed_1").mkdir()
    (tmp_path / "seed_1" / "report.json").write_text(json.dumps({**report(0.0), "partial": True}))  # stopped
    calls = []

    def fake(out, preset, seed, rig, resume=False, **kw):
        calls.append((seed, resume))
        return report(0.25)

    monkeypatch.setattr(demo, "run_baoding_demo", fake)
    s = demo.run_full(tmp_path, resume=True)
    assert calls == [(1, True), (2, False)]
    assert s["final_success_90"]["per_seed"] == [0.5, 0.25, 0.25]


def test_the_reachable_set_in_planner_units_is_the_drivers_rate_limit():
    """HoldActionMap.reachable: the z reachable one step after z_prev are exactly those whose
    driver action is within the rate limit's step of z_prev's (either side of the hold pose,
    and clipped at the joint limits)."""
    amap = hold_action_map()
    step = 0.4  # shadow_hand.yaml: 4 per s x 0.1 s
    bounds = amap.reachable(np.full(20, step))
    rng = np.random.default_rng(0)
    z = rng.uniform(-1, 1, (200, 20))
    lo, hi = (t.double().numpy() for t in bounds(torch.from_numpy(z).float()))
    a, a_lo, a_hi = amap.to_driver(z), amap.to_driver(lo), amap.to_driver(hi)
    top, bottom = amap.to_driver(np.ones(20)), amap.to_driver(-np.ones(20))  # z = ±1: 0.9 of the way to a limit
    np.testing.assert_allclose(a_hi, np.minimum(a + step, top), atol=1e-5)
    np.testing.assert_allclose(a_lo, np.maximum(a - step, bottom), atol=1e-5)
    assert np.all(lo <= z + 1e-6) and np.all(hi >= z - 1e-6)


def test_a_rate_aware_run_plans_with_the_drivers_rate_limit(bus, tmp_path):
    from hilstack.learning.baoding import BaodingConfig, BaodingRun

    run = BaodingRun(BaodingConfig.from_preset("tiny", rate_aware=True), tmp_path, bus)
    run.state_names = NAMES
    run.action_names = [f"a{i}" for i in range(20)]
    reach = run.reachable()
    lo, hi = reach(torch.zeros(1, 20))
    a_hi = hold_action_map().to_driver(hi.double().numpy()[0])
    top = hold_action_map().to_driver(np.ones(20))
    np.testing.assert_allclose(a_hi, np.minimum(hold_pose_action() + 0.4, top), atol=1e-5)
    assert BaodingRun(BaodingConfig.from_preset("tiny"), tmp_path, bus).reachable() is None
