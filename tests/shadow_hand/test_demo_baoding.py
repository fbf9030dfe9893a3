"""PDDM on the Baoding balls: reward math, the drop ending an episode through the reset
supervisor, and `hil demo baoding` end to end at a seconds-long scale (real bus, real
driver process, real MuJoCo, real MCAP)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from hilstack.bus.schemas import ResetTransition
from hilstack.configs.schema import load_rig, rig_robot_config
from hilstack.control.costs import BaodingCost, baoding_episode_metrics
from hilstack.drivers.registry import make_driver
from hilstack.drivers.shadow_hand.config import BALL_CHANNELS, ShadowHandParams, shadow_hand_spec
from hilstack.learning.baoding import BaodingConfig, BaodingRun, UniformRandomPolicy, load_baoding_task
from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim
from hilstack.tasks.baoding import BaodingTask

NAMES = list(shadow_hand_spec(ShadowHandParams(objects_in_state=True)).state.names)


def task() -> BaodingTask:
    return BaodingTask(center_m=np.array([0.0, 0.0, 0.1]), axis=np.array([0.0, 0.0, 1.0]), radius_m=0.025,
                       rate_rad_s=np.pi / 5)


def state_with(balls: np.ndarray) -> np.ndarray:
    s = np.zeros(len(NAMES))
    s[[NAMES.index(c) for c in BALL_CHANNELS]] = np.asarray(balls).reshape(-1)
    return s


# ---------------------------------------------------------------------------- reward math
def test_cost_is_minus_the_task_reward_summed_over_the_horizon_and_a_predicted_drop_sticks():
    """−Σ r over the predicted steps; from a predicted drop on every step costs 500, even when
    the model has the ball back in the palm a step later (the reference's sticky dones)."""
    tk, dt, H = task(), 0.1, 4
    cost = BaodingCost(tk, NAMES, dt)
    cost.reset()
    for _ in range(3):  # two steps into the episode: the current state is at t = 0.2 s
        cost.observe(None)
    rng = np.random.default_rng(0)
    balls = tk.center_m + rng.normal(0, 0.03, (2, H + 1, 2, 3))  # [N=2, H+1, ball, xyz]
    balls[1, 3, 0, 2] = 0.0  # one predicted state with a dropped ball
    states = torch.tensor(np.stack([[state_with(b) for b in seq] for seq in balls]), dtype=torch.float32)[None]
    got = cost(states, None)  # [E=1, N=2]

    def want(n: int) -> float:
        total, done = 0.0, False
        for h in range(1, H + 1):
            done = done or tk.dropped(balls[n, h])
            total += 500.0 if done else -tk.reward(balls[n, h], (2 + h) * dt)
        return total

    assert not tk.dropped(balls[1, 4])  # the model has the ball back up after the drop
    assert got.shape == (1, 2)
    np.testing.assert_allclose(got[0].numpy(), [want(0), want(1)], rtol=1e-5, atol=1e-4)
    assert got[0, 1] > 1000  # the drop at step 3 costs steps 3 and 4


def test_reward_by_hand():
    tk, dt = task(), 0.1
    cost = BaodingCost(tk, NAMES, dt)
    cost.observe(None)  # t = 0
    on = tk.targets(dt)  # the first predicted state is at t = 0.1 s
    def c(balls):
        return float(cost(torch.tensor(np.stack([state_with(tk.center_m + 0 * balls), state_with(balls)]),
                                       dtype=torch.float32)[None, None], None))
    assert c(on) == pytest.approx(0.0, abs=1e-4)  # on the targets: no cost
    off = on.copy()
    off[0, 2] += 0.1  # one ball 10 cm above its target: 5 · 0.1
    assert c(off) == pytest.approx(0.5, abs=1e-4)
    fell = on.copy()
    fell[1, 2] -= 0.05  # 5 cm below the palm centre: a drop (0.04 m); a dropped step costs the penalty alone
    assert c(fell) == pytest.approx(500.0, abs=1e-3)


def test_episode_metrics_turns_drop_and_return():
    tk, dt = task(), 0.1
    # the pair turns 10° per step along the targets for 19 steps (190°), then a ball drops
    ang = np.radians(np.r_[np.arange(20) * 10.0, 190.0])
    d = 0.025 * np.stack([np.cos(ang), np.sin(ang), 0 * ang], 1)
    balls = np.stack([tk.center_m + d, tk.center_m - d], 1)
    balls[-1, 0, 2] = 0.0
    t = np.arange(len(balls)) * dt
    m = baoding_episode_metrics(tk, balls, t)
    assert m["dropped"] == 1.0 and m["steps"] == 20
    assert m["rotation_deg"] == pytest.approx(190.0) and m["turned_90"] == 1.0 and m["turned_180"] == 1.0
    assert m["return"] == pytest.approx(sum(tk.reward(balls[k], t[k]) for k in range(1, 21)))
    # only 100° before the drop: the 180° turn did not happen
    m2 = baoding_episode_metrics(tk, np.concatenate([balls[:11], balls[-1:]]), t[:12])
    assert m2["turned_90"] == 1.0 and m2["turned_180"] == 0.0 and m2["rotation_deg"] == pytest.approx(100.0)
    # turning against the targets counts negative
    m3 = baoding_episode_metrics(tk, balls[:10][::-1], t[:10])  # time reversed
    assert m3["rotation_deg"] < 0 and m3["turned_90"] == 0.0


def test_the_task_config_matches_the_sim_task():
    sim = ShadowHandSim()
    sim.configure()
    cfg = load_baoding_task()
    np.testing.assert_allclose(cfg.center_m, sim.task.center_m, atol=1e-5)
    np.testing.assert_allclose(cfg.axis, sim.task.axis, atol=1e-5)
    assert (cfg.radius_m, cfg.radius_v_m, cfg.rate_rad_s) == pytest.approx(
        (sim.task.radius_m, sim.task.radius_v_m, sim.task.rate_rad_s))


def test_balls_in_the_state_on_the_demo_rig_and_the_drop_threshold_matches_the_task():
    rig = load_rig("hand_sim")
    d = make_driver(rig_robot_config(rig, "hand"))
    assert list(d.spec.state.names[-6:]) == list(BALL_CHANNELS) and d.spec.state.dim == 54
    d.configure()
    obs = d.read()
    np.testing.assert_allclose(obs.state[-6:], obs.extras["balls_m"].reshape(-1))
    # the supervisor's drop detector (world z) fires where the task's drop rule does, at rest
    z_min = next(x["min_height_m"] for x in rig.reset["detectors"] if x["kind"] == "drop")
    tk = load_baoding_task()
    assert z_min == pytest.approx(tk.center_m[2] - tk.drop_below_m * tk.axis[2], abs=2e-3)


# ---------------------------------------------------------------------------- over the bus
def test_a_drop_ends_the_episode_through_the_supervisor(bus, tmp_path):
    run = BaodingRun(BaodingConfig.from_preset("tiny"), tmp_path, bus)
    with run.session():
        transitions = run.ctl.subscribe(f"hil/{run.rig.name}/reset/transition", ResetTransition, latest=False,
                                        capacity=256)
        log = run.episode(UniformRandomPolicy(20, seed=3), 100, {})  # random actions drop a ball in < 3 s
        nxt = run.episode(UniformRandomPolicy(20, seed=4), 2, {})  # the next episode starts: a reset happened
        # the controller ends a lockstep episode on the rig's detectors itself; the supervisor's
        # end of it (its reason) is among the transitions up to the next episode's start
        ended = [t for _, t in transitions.drain()]
    assert len(log.states) < 100
    assert np.min(run.balls(np.array(log.states))[-1, :, 2]) < 0.079
    from hilstack.bus.schemas import decode

    reasons = [decode(p, ResetTransition).reason for p in ended]
    assert any(r.startswith("drop") for r in reasons), reasons
    assert run.supervisor.stats["completed"] >= 2 and run.supervisor.stats["failed"] == 0
    # the reset held the hand in its start pose (not the middle of every joint's range) and
    # the next episode starts with both balls in the palm
    from hilstack.drivers.shadow_hand.config import ACT_INDEX, hold_pose_action, to_action

    start = np.asarray(nxt.states[0])
    assert np.abs(to_action(start[ACT_INDEX]) - hold_pose_action()).max() < 0.1
    assert np.all(run.balls(start[None])[0, :, 2] > 0.1)


def test_demo_baoding_tiny_end_to_end(tmp_path):
    from hilstack.learning.dynamics import cpu_bf16_support
    from hilstack.tools.demo_baoding import run_baoding_demo

    threads = torch.get_num_threads()
    r = run_baoding_demo(tmp_path, preset="tiny", torch_threads=1, inference_dtype="auto")
    assert torch.get_num_threads() == threads  # the run's thread count is restored
    # auto: bf16 only on a CPU with native bf16 where it measured faster (the tiny model: never)
    meas = r["inference_dtype_measured"]
    assert (meas is None) == (cpu_bf16_support() is None)
    assert r["inference_dtype"] == ("bfloat16" if meas and meas["speedup"] >= 1.25 else "float32")
    saved = json.loads((tmp_path / "report.json").read_text())
    # as JSON: a metric without data is NaN (drop recall with no drop window), and NaN != NaN
    assert json.dumps(saved["iterations"], sort_keys=True) == json.dumps(r["iterations"], sort_keys=True)
    metrics = {"points", "mean_return", "return", "drops", "drop_rate", "mean_rotation_deg", "success_90",
               "success_180", "model"}
    assert len(r["iterations"]) == 1 and metrics <= set(r["iterations"][0])
    # scored again from the recordings (``table --rescore``), the run's own turn figures come back
    from hilstack.tools.demo_baoding import rescore_iterations

    again = rescore_iterations(tmp_path)[1]
    for k in ("success_90", "success_180", "held_90", "drops", "mean_rotation_deg", "mean_steps", "episodes"):
        assert again[k] == pytest.approx(r["iterations"][0][k], abs=1e-3), k  # states recorded as float32
    capped = rescore_iterations(tmp_path, rise_limit_m=0.0)[1]  # no turn counts once a ball rises at all
    assert capped["success_90"] <= again["success_90"] and capped["drops"] == again["drops"]
    # the run's model in closed loop with a setting changed, no training (`demo_baoding eval`)
    from hilstack.tools.demo_baoding import eval_model

    row = eval_model(tmp_path, tmp_path / "ev", "lead", 1, {"task.max_lead_rad": 0.5, "horizon": 3})
    assert row["episodes"] == 1 and row["settings"] == {"task.max_lead_rad": 0.5, "horizon": 3}
    assert (tmp_path / "ev" / "lead" / "recordings" / "eval-pddm.mcap").is_file()
    assert json.loads((tmp_path / "ev" / "eval.jsonl").read_text())["name"] == "lead"
    with pytest.raises(FileExistsError):  # never over an earlier evaluation's recordings
        eval_model(tmp_path, tmp_path / "ev", "lead", 1)
    with pytest.raises(ValueError, match="task.lead"):
        eval_model(tmp_path, tmp_path / "ev", "bad", 1, {"task.lead": 1.0})
    assert {"val_1step", "val_h"} <= set(r["iterations"][0]["model"])
    assert metrics - {"points", "model"} <= set(r["random_policy"]) and metrics - {"points", "model"} <= set(r["hold_policy"])
    assert r["random_data"]["rollouts"] == 3 and r["random_data"]["points"] > 0
    assert r["random_policy"]["episodes"] == 2 and r["iterations"][0]["episodes"] == 2
    # hold still: as many episodes as PDDM's per iteration; the policies ranked by turns
    assert r["hold_policy"]["episodes"] == 2
    assert set(r["ranking_by_turns"]) == {"hold (keep the start pose)", "random (uniform actions)", "PDDM iteration 1"}
    w = r["iterations"][0]["weights"]
    assert w["plans"] > 0 and 1.0 <= w["ess_mean"] <= 16 and w["mean_shift_rms"] >= 0
    assert "ball0_vx" in r["model_state"] and len(r["model_state"]) == 36
    p = r["planner"]
    assert (p["horizon"], p["samples"], p["ensemble"], p["hidden"]) == (7, 16, 3, (16, 16))
    assert p["plans"] > 0 and 0 < p["plan_ms_p50"] <= p["plan_ms_p99"]
    rs = r["resets"]
    assert rs["requested"] >= 3 + 2 + 2 + 2 + 1  # one per episode: random walk, random, hold, PDDM, random walk
    assert rs["completed"] == rs["requested"] and rs["failed"] == 0 and rs["mean_duration_s"] > 0
    for f in ("report.md", "turns.png", "demo.rrd", "model.pt"):
        assert (tmp_path / f).is_file(), f
    # random walk, random, hold, PDDM, and the iteration's random walk (the reference aggregates 5 each)
    assert all(p.endswith(".mcap") for p in r["recordings"]) and len(r["recordings"]) == 5
    it = r["iterations"][0]
    assert it["random_walk"]["rollouts"] == 1 and r["recordings"][-1].endswith("001-random.mcap")
    t = it["timing"]  # where the iteration's time went
    assert 0 < t["plan_ms_p50"] <= t["plan_ms_p99"] and t["steps"] > 0 and t["ms_per_step"] >= t["plan_ms_mean"] > 0


def test_reset_handshake_and_lockstep_messages_wait_for_a_full_send_queue(bus):
    """Zenoh drops a message whose send queue stays full for 1 ms (its default for data):
    on a loaded machine that lost a teleport answer and stopped the rig. The reset
    handshake and a lockstep rig's states and commands are declared to wait instead."""
    import zenoh

    from hilstack.control.controller_node import ControllerNode
    from hilstack.control.reset.config import load_reset
    from hilstack.control.reset.supervisor import ResetSupervisor
    from hilstack.drivers.bridge import DriverNode

    rig = load_rig("hand_sim")
    block = zenoh.CongestionControl.BLOCK
    node = DriverNode(make_driver(rig_robot_config(rig, "hand")), rig.name, "hand", bus, pace="lockstep",
                      handle_signals=False)
    sup = ResetSupervisor(rig.name, load_reset(rig), bus, handle_signals=False)
    ctl = ControllerNode(rig.name, "hand", bus, handle_signals=False)
    try:
        for p in (node._state_pub, node._reset_done, node._sup_done, sup._done, sup._to_driver, ctl._cmd,
                  ctl._reset_req):
            assert p._pub.congestion_control == block, p.key
        assert node._image_pub._pub.congestion_control != block  # bulk data may still be dropped
    finally:
        for n in (ctl, sup, node):
            n.close()


def test_drop_prediction_counts_the_drops_a_model_sees_coming():
    from hilstack.learning.baoding import drop_prediction
    from hilstack.learning.datasets import Episode

    tk = task()
    idx = [NAMES.index(c) for c in BALL_CHANNELS]
    z0 = tk.center_m[2]
    # one episode falls (z − 1 cm per step: a drop after 5 steps), one stays put
    fall = np.array([state_with(np.stack([tk.center_m, tk.center_m]) - [0, 0, 0.01 * k]) for k in range(10)])
    stay = np.array([state_with(np.stack([tk.center_m, tk.center_m])) for _ in range(10)])
    eps = [Episode(states=s, actions=np.zeros((9, 20)), times=np.arange(10) * 0.1, name=n)
           for s, n in ((fall, "fall"), (stay, "stay"))]

    class Still:  # predicts no motion: sees no drop coming
        def predict(self, s, a):
            return s.reshape(-1, *s.shape[-2:])[:1] if s.dim() == 3 else s[None]

    class Falls(Still):  # predicts every ball falling 1 cm per step: sees every drop, and false ones
        def predict(self, s, a):
            out = super().predict(s, a).clone()
            out[..., idx[2::3]] -= 0.01
            return out

    still = drop_prediction(Still(), eps, tk, idx, horizon=7)
    assert still["windows_with_drop"] > 0 and still["drop_recall"] == 0.0 and still["false_drop_rate"] == 0.0
    falls = drop_prediction(Falls(), eps, tk, idx, horizon=7)
    assert falls["drop_recall"] == 1.0 and falls["false_drop_rate"] > 0.5
    assert z0 - 0.01 * 9 < z0 - tk.drop_below_m  # the falling episode does drop


def test_a_sim_reset_holds_the_pose_it_resets_to():
    """The contract's held command follows a sim reset: the rate limit and the bus's
    ``RobotState.action`` start from the new pose, not from where the last episode ended."""
    from hilstack.drivers.shadow_hand.config import ACT_INDEX, hold_pose_action, to_action

    sim = ShadowHandSim(ShadowHandParams(objects_in_state=True))
    sim.configure()
    sim.activate()
    for _ in range(5):
        sim.write(-np.ones(20))
        sim.tick()
    assert np.abs(sim.held_command - hold_pose_action()).max() > 0.5
    sim.reset()
    np.testing.assert_allclose(sim.held_command, to_action(sim.read().state[ACT_INDEX]), atol=1e-9)
    assert np.abs(sim.held_command - hold_pose_action()).max() < 0.05


def test_the_pddm_policy_plans_from_the_state_after_the_sent_command_on_a_wall_clock_hand(bus, tmp_path):
    """The emulated (and real) hand applies a command one period after the state it was
    planned from (the spec's pacing, MbrlRun.command_delay); the lockstep sim does not."""
    from tests.helpers import rig_pacing

    for rig, delay in (("hand_emulated", 1), ("hand_sim", 0)):
        run = BaodingRun(BaodingConfig.from_preset("tiny", rig=rig), tmp_path / rig, bus)
        run.state_names = NAMES
        run.action_names = list(shadow_hand_spec(ShadowHandParams()).action.names)
        run.pacing = rig_pacing(rig, "hand")  # what session() takes from the spec on the bus
        assert run.command_delay == delay
        assert run.pddm_policy(model=None, seed=0).delay_steps == delay


def test_a_wall_clock_hand_fits_pddm_k_to_the_period_and_the_sim_keeps_it(bus, tmp_path):
    """PDDM's K on a wall-clock hand: timed through the model with the task's cost from the
    hand's state, cut (here to the floor: no plan fits a nanosecond) and used by every PDDM
    rollout; the lockstep sim keeps the configured K."""
    from types import SimpleNamespace

    from hilstack.learning.mbrl import make_model
    from tests.helpers import rig_pacing

    for rig, want in (("hand_emulated", 50), ("hand_sim", None)):
        run = BaodingRun(BaodingConfig.from_preset("tiny", rig=rig, samples=200), tmp_path / rig, bus)
        run.state_names = NAMES
        run.action_names = list(shadow_hand_spec(ShadowHandParams()).action.names)
        run.ctl = SimpleNamespace(next_state=lambda: SimpleNamespace(state=np.zeros(len(NAMES))))
        run.pacing = rig_pacing(rig, "hand")
        run.period_s = 1e-9
        model = make_model(run.cfg, run.features.names, run.action_names)  # the model's state: the features
        k = run.fit_pddm_to_period(model)
        assert k == want
        assert run.pddm_policy(model, seed=0, samples=k).planner.samples == (want or 200)
        if want:
            assert run.planner_fit["trials"][0]["samples"] == 200
            assert run.pddm_config(k).samples == 50 and run.pddm_config().samples == 200


def test_a_hand_state_without_the_balls_is_refused_before_any_episode(bus, tmp_path):
    """Baoding scores and plans on the balls' positions: a rig whose hand state lacks them (the
    emulated hand without trackers) is a RigError naming the channels, not an IndexError
    after the random rollouts."""
    import contextlib

    from hilstack.learning.mbrl import RigError

    run = BaodingRun(BaodingConfig.from_preset("tiny", rig="hand_emulated_arm"), tmp_path, bus)
    run.session = contextlib.nullcontext  # the rig is up; its hand publishes joints only
    run.state_names = [n for n in NAMES if not n.startswith("ball")]
    run.run_episodes = lambda *a, **k: pytest.fail("an episode ran")
    with pytest.raises(RigError, match=r"no ball0_x, ball0_y, ball0_z, ball1_x, ball1_y, ball1_z.*objects_in_state"):
        run.run()


def test_a_wall_clock_hand_refits_pddm_k_after_each_mpc_episode(bus, tmp_path, monkeypatch):
    """run_episodes on a wall-clock hand: after each PDDM episode K is refitted from that
    episode's plan times (an injected planner whose load rises after the first episode), the next
    episode's policy gets it, the ESS share is taken per plan's own K; random episodes refit
    nothing; the lockstep sim keeps the configured K."""
    import contextlib

    import hilstack.learning.baoding as baoding
    from hilstack.control.controller_node import EpisodeLog
    from tests.helpers import rig_pacing

    monkeypatch.setattr(baoding, "recording", lambda *a, **k: contextlib.nullcontext())
    monkeypatch.setattr(baoding, "baoding_episode_metrics", lambda *a, **k: {"dropped": 0.0})
    for rig in ("hand_emulated", "hand_sim"):
        run = BaodingRun(BaodingConfig.from_preset("tiny", rig=rig, samples=400), tmp_path / rig, bus)
        run.state_names = NAMES
        run.action_names = list(shadow_hand_spec(ShadowHandParams()).action.names)
        run.pacing, run.period_s = rig_pacing(rig, "hand"), 0.1
        if rig == "hand_emulated":
            run.planner_fit = {"samples": 400, "configured_samples": 400, "trials": [], "current_samples": 400,
                               "refits": []}
        loads, seen = iter([0.5, 4.0, 4.0, 4.0]), []

        def episode(policy, steps, pose, seen=seen, loads=loads):
            if not hasattr(policy, "planner"):  # a random episode: fast plans, still measured
                return EpisodeLog(states=[np.zeros(len(NAMES))] * 3, plan_times_s=[1.0] * 20, actions=[0] * 20)
            k = policy.planner.samples
            seen.append(k)
            t = next(loads) * k * 5e-5  # 400 samples: 10 ms quiet, 80 ms loaded (budget 40, deadline 80)
            policy.planner.history = [(0.25 * k, 0.1)] * 10
            return EpisodeLog(states=[np.zeros(len(NAMES))] * 3, plan_times_s=[t] * 20, actions=[0] * 20,
                              late_plans=sum(int(t >= 0.08) for _ in range(20)))

        run.episode = episode
        run.run_episodes(lambda i, run=run: run.pddm_policy(None, seed=i, samples=run.pddm_samples()), 4, "001-mpc", "x")
        assert run.plan_summary()["ess_frac_mean"] == pytest.approx(0.25)  # each plan over its own K
        if rig == "hand_sim":
            assert seen == [400] * 4 and run.planner_fit is None
            continue
        assert seen[:2] == [400, 400] and seen[2] < 400 and seen[3] <= seen[2]  # cut once the load said so
        refits = run.planner_fit["refits"]
        assert refits[0]["after"] == "001-mpc episode 1" and refits[-1]["to"] == run.pddm_samples()
        n = len(refits)
        run.run_episodes(lambda i, run=run: UniformRandomPolicy(len(run.action_names), seed=i), 1, "002-random", "x")
        assert len(run.planner_fit["refits"]) == n


# ---------------------------------------------------------------------------- hil demo baoding --rig
def test_demo_baoding_rig_option_reaches_the_run_and_unfit_rigs_are_refused_in_one_line(tmp_path, monkeypatch):
    """`hil demo baoding --rig RIG` runs on RIG (default the lockstep sim rig); a rig without a
    hand, without the balls in the hand's state or without a reset: section is refused before
    anything starts, in one line naming what is missing (exit 2)."""
    import yaml
    from typer.testing import CliRunner

    import hilstack.tools.demo_baoding as demo
    from hilstack.configs.schema import config_path
    from hilstack.tools.cli import app

    ran: list[dict] = []

    def fake_run(out, preset="quick", seed=0, resume=False, **kw):
        ran.append({"preset": preset, **kw})
        raise ValueError("stop here")  # the run itself is test_demo_baoding_tiny_end_to_end's

    monkeypatch.setattr(demo, "run_baoding_demo", fake_run)

    def invoke(*args: str):
        return CliRunner().invoke(app, ["demo", "baoding", "--quick", *args, "--out", str(tmp_path / "o")])

    for args, rig in (((), "hand_sim"), (("--rig", "hand_emulated"), "hand_emulated")):
        r = invoke(*args)
        assert r.exit_code == 1 and "stop here" in r.output, r.output
        assert ran.pop() == {"preset": "quick", "rig": rig, "task": "baoding"}  # both rigs hold the cupped pose
    no_reset = yaml.safe_load(config_path("rigs", "hand_sim").read_text())
    del no_reset["reset"]
    (tmp_path / "hand_noreset.yaml").write_text(yaml.safe_dump({**no_reset, "name": "hand_noreset"}))
    for rig, why in (("roach_sim", "rig roach_sim has no robot 'hand'"),
                     ("hand_real", "the hand's state has no ball0_x, ball0_y, ball0_z, ball1_x, ball1_y, ball1_z"),
                     ("hand_emulated_arm", "the hand's state has no ball0_x"),
                     (str(tmp_path / "hand_noreset.yaml"), "rig hand_noreset has no reset: section")):
        r = invoke("--rig", rig)
        assert r.exit_code == 2 and why in r.output, (rig, r.output)
        assert len(r.output.strip().splitlines()) == 1, r.output
    assert not ran and not (tmp_path / "o").exists()
    r = CliRunner().invoke(app, ["demo", "arms", "--rig", "hand_sim", "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "--rig is for the roach and baoding demos only" in r.output


def test_the_training_noise_setting_reaches_the_runs_model_and_is_bounded():
    from hilstack.learning.mbrl import make_model

    cfg = BaodingConfig.from_preset("tiny", noise_to_signal=0.05)
    assert make_model(cfg.mbrl(), ["a", "b"], ["u"]).config["noise_to_signal"] == 0.05
    assert make_model(BaodingConfig().mbrl(), ["a", "b"], ["u"]).config["noise_to_signal"] == BaodingConfig.noise_to_signal
    for bad in (-0.1, 2.0, float("inf")):
        with pytest.raises(ValueError, match="noise_to_signal must be in"):
            BaodingConfig(noise_to_signal=bad)
