"""Pieces of the MBRL loop that need no rig: the validation split and the baseline search."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from hilstack.learning.datasets import Episode, split_episodes
from hilstack.learning.mbrl import (
    BASELINE_SEARCH,
    baseline_candidates,
    default_baseline_params,
)
from tests.helpers import rig_pacing


def eps(names):
    return [Episode(np.zeros((3, 2)), np.zeros((2, 1)), name=n) for n in names]


def test_validation_split_is_fixed_for_good_as_the_data_grows():
    rng, assigned = np.random.default_rng(0), {}
    first = eps([f"random:{i}" for i in range(70)])
    tr0, va0 = split_episodes(first, 0.1, rng, assigned)
    assert len(va0) == 7 and len(tr0) == 63
    grown = first + eps([f"mpc1:{i}" for i in range(10)])
    tr1, va1 = split_episodes(grown, 0.1, rng, assigned)
    tr0n, va0n = {e.name for e in tr0}, {e.name for e in va0}
    # no training episode of iteration 0 is validation data later, and the reverse
    assert not tr0n & {e.name for e in va1}
    assert va0n <= {e.name for e in va1} and not va0n & {e.name for e in tr1}
    # the new episodes are split too
    assert sum(e.name.startswith("mpc1") for e in va1) == 1
    assert len(tr1) + len(va1) == 80


def test_validation_split_needs_unique_names():
    with pytest.raises(ValueError, match="unique"):
        split_episodes(eps(["a", "a", "b"]), 0.5, np.random.default_rng(0), {})


def test_baseline_candidates_start_at_the_default_and_cover_the_ranges():
    c = baseline_candidates(20, 0.5, seed=0)
    assert len(c) == 20 and c[0] == default_baseline_params(0.5)
    for k, (lo, hi, scaled) in BASELINE_SEARCH.items():
        v = np.array([p[k] for p in c[1:]]) / (0.5 if scaled else 1.0)
        assert v.min() >= lo and v.max() <= hi
        # Latin hypercube: one candidate in each of the 19 equal bins of every gain's range
        bins = np.floor((v - lo) / (hi - lo) * 19).astype(int)
        assert sorted(bins.tolist()) == list(range(19))
    assert baseline_candidates(20, 0.5, seed=0) == c
    with pytest.raises(ValueError):
        baseline_candidates(0, 0.5)


def test_rate_limit_in_normalized_units_per_step():
    from hilstack.drivers.base import RobotSpec
    from hilstack.drivers.velociroach.config import VelociRoachParams, velociroach_spec
    from hilstack.learning.mbrl import MbrlConfig, make_planner

    spec = velociroach_spec(VelociRoachParams(max_leg_accel_rps2=60.0, max_leg_vel_rps=15.0))
    # 60 rev/s² for 0.1 s is 6 rev/s, and [-1, 1] spans ±15 rev/s; the same after the bus
    np.testing.assert_allclose(spec.max_step_normalized(), [0.4, 0.4])
    np.testing.assert_allclose(RobotSpec.from_dict(spec.to_dict()).max_step_normalized(), [0.4, 0.4])
    assert dataclasses.replace(spec, action_rate_per_s=None).max_step_normalized() is None
    rs = make_planner(MbrlConfig(planner="random_shooting"), 0.5, 2, np.array([0.4, 0.4]))
    np.testing.assert_allclose(rs.max_step.numpy(), [0.4, 0.4])
    assert make_planner(MbrlConfig(planner="random_shooting", reachable_set=False), 0.5, 2,
                        np.array([0.4, 0.4])).max_step is None


def test_random_policy_holds_commands_and_drives_forward_when_asked():
    from hilstack.control.policies import SafeRandomPolicy

    names = ["x", "y", "cos_yaw", "sin_yaw"]
    state = np.array([0.0, 0.0, 1.0, 0.0])
    thesis = SafeRandomPolicy(names, 2, seed=0)
    a = np.array([thesis(state) for _ in range(4000)])
    assert np.all(np.abs(np.diff(a, axis=0)).sum(1) > 0)  # a new command every step
    assert a.mean(0) == pytest.approx([0, 0], abs=0.05)
    fwd = SafeRandomPolicy(names, 2, hold_steps=6, forward_fraction=1.0, turn=0.5, seed=0)
    b = np.array([fwd(state) for _ in range(4000)])
    changes = np.flatnonzero(np.abs(np.diff(b, axis=0)).sum(1) > 0)
    runs = np.diff(changes)
    assert runs.min() >= 1 and runs.max() <= 6 and 3.0 < runs.mean() < 4.0  # U{1..6}: mean 3.5
    assert np.all(b.mean(1) >= -1e-9) and np.all(np.abs(b[:, 1] - b[:, 0]) <= 0.5 + 1e-9)
    assert (b.mean(1) > 0.8).mean() > 0.15  # fast forward commands are common
    with pytest.raises(ValueError):
        SafeRandomPolicy(names, 3, forward_fraction=0.5)


def test_speed_coverage():
    from hilstack.learning.mbrl import speed_coverage

    st = np.zeros((5, 2))
    st[:, 0] = [0.0, 0.3, 0.6, 1.0, 1.2]
    c = speed_coverage([Episode(st, np.zeros((4, 1)), name="e")], ["vx", "vy"])
    assert c["fraction_ge_0.5_mps"] == pytest.approx(0.6) and c["fraction_ge_0.9_mps"] == pytest.approx(0.4)
    assert c["speed_p50_mps"] == pytest.approx(0.6)


def test_quick_and_full_are_exclusive(tmp_path):
    from hilstack.tools.demo import run_demo

    with pytest.raises(ValueError, match="--quick or --full"):
        run_demo(tmp_path, quick=True, full=True)
    assert not (tmp_path / "logs").exists()  # refused before any rig process started


def test_full_config_runs_every_experiment_over_three_seeds():
    from hilstack.learning.experiments import EXPERIMENTS
    from hilstack.learning.mbrl import MbrlConfig

    cfg = MbrlConfig.from_preset("full")
    assert set(cfg.experiments) == set(EXPERIMENTS) and len(cfg.seeds) >= 3
    assert cfg.table_sizes == (50, 200, 400) and cfg.random_rollouts >= max(cfg.table_sizes)
    assert len(cfg.sweep_speeds) >= 4 and cfg.terrains == ("carpet", "styrofoam")


@pytest.mark.parametrize(("field", "value"), [("experiments", ("table_9",)), ("time_limit_speed_mps", 0.0),
                                              ("baseline_candidates", 0), ("random_forward_fraction", 1.5),
                                              ("reference_corner_radius_m", -0.1), ("tilt_loss_weight", 0.0),
                                              ("train_horizon", 0)])
def test_bad_config_is_one_clear_error_naming_the_field(field, value):
    from hilstack.learning.mbrl import MbrlConfig

    with pytest.raises(ValueError, match=field) as e:
        MbrlConfig(**{field: value})
    assert "\n" not in str(e.value)


def test_demo_flags_select_the_variants(monkeypatch, tmp_path):
    """--world-frame and --thesis-sampling reach the loop's config; a bad combination is
    one line on stderr and exit code 1."""
    from typer.testing import CliRunner

    import hilstack.tools.demo
    from hilstack.learning.mbrl import MbrlConfig
    from hilstack.tools.cli import app

    seen = {}

    def fake_run_demo(out, quick=False, full=False, **kw):
        seen.update(kw)
        MbrlConfig(**{k: v for k, v in kw.items() if k in MbrlConfig.__dataclass_fields__})
        raise ValueError("stop here")

    monkeypatch.setattr(hilstack.tools.demo, "run_demo", fake_run_demo)
    r = CliRunner().invoke(app, ["demo", "--quick", "--world-frame", "--thesis-sampling", "--tilt-loss-weight", "5",
                                 "--out", str(tmp_path)])
    assert r.exit_code == 1 and "stop here" in r.output
    assert seen["body_frame"] is False and seen["tilt_loss_weight"] == 5.0
    assert seen["random_hold_steps"] == 1 and seen["random_forward_fraction"] == 0.0 and seen["reachable_set"] is False
    monkeypatch.undo()
    r = CliRunner().invoke(app, ["demo", "--quick", "--full", "--out", str(tmp_path / "x")])
    assert r.exit_code == 1 and "choose --quick or --full" in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_planner_samples_fit_the_wall_clock_budget():
    from hilstack.learning.mbrl import fit_samples_to_budget

    def plan_time(n):  # 20 ms overhead + 0.3 ms per sample: 170 ms at N = 500
        return 0.020 + 0.0003 * n

    n, trials = fit_samples_to_budget(plan_time, 500, budget_s=0.2)
    assert n == 500 and len(trials) == 1  # fits: the configured size is kept
    n, trials = fit_samples_to_budget(plan_time, 500, budget_s=0.04)
    assert trials[0] == {"samples": 500, "plan_ms_p50": pytest.approx(170.0)}
    assert 50 <= n < 500 and plan_time(n) <= 0.04 + 0.002  # cut until the median fits (within a round)
    n, _ = fit_samples_to_budget(plan_time, 500, budget_s=0.001, min_samples=50)
    assert n == 50  # never below the floor


def test_the_configured_planner_is_timed_on_the_model_and_fitted_to_the_period():
    """`hil demo` and `hil mpc` on wall-clock rigs: the real planner, planning with the model
    from a state (no wall-clock assertion: a period nothing fits, and one anything fits)."""
    import torch

    from hilstack.control.costs import PathCost
    from hilstack.control.paths import make_path
    from hilstack.learning.mbrl import MbrlConfig, fit_planner_to_period

    names = ["x", "y", "cos_yaw", "sin_yaw"]
    calls = []

    def predict(s, a):  # [B, S], [B, A] -> [E=1, B, S]
        calls.append(s.shape[0])
        return (s + torch.nn.functional.pad(a, (0, 2))).unsqueeze(0)

    cfg = MbrlConfig(samples=200, realtime_min_samples=20)
    args = (cfg, 1.0, 2, None, predict, PathCost(make_path("straight"), names), np.array([0.0, 0.0, 1.0, 0.0]))
    n, trials = fit_planner_to_period(*args, period_s=1e-9)
    assert n == 20 and trials[0]["samples"] == 200  # measured at the configured size, cut to the floor
    assert 200 in calls and 20 in calls  # the planner's rollouts ran through the model at both sizes
    n, trials = fit_planner_to_period(*args, period_s=1e6)
    assert n == 200 and len(trials) == 1


def test_realtime_planner_delay_and_elites(tmp_path):
    from hilstack.configs.schema import BusConfig
    from hilstack.drivers.base import Pacing
    from hilstack.learning.mbrl import MbrlConfig, MbrlRun, make_planner

    for rig, robot, pacing, delay in (("roach_emulated", "roach", Pacing.WALL_CLOCK, 1),
                                      ("roach_sim", "roach", Pacing.LOCKSTEP, 0),
                                      ("pointmass_sim", "pm", Pacing.STEPPED, 0)):  # a realtime sim advances after applying
        run = MbrlRun(MbrlConfig(rig=rig), tmp_path / rig, BusConfig())
        assert run.command_delay == 0 and run.pacing is None  # before the spec arrived
        run.pacing = rig_pacing(rig, robot)
        assert run.pacing is pacing and run.command_delay == delay
    cfg = MbrlConfig()
    assert make_planner(cfg, 1.0, 2).elites == 50  # the thesis' CEM as before
    small = make_planner(cfg, 1.0, 2, samples=120)
    assert small.samples == 120 and small.elites == 12


def test_mpc_plans_from_the_state_after_the_committed_commands():
    import torch

    from hilstack.control.policies import MpcPolicy

    class Recorder:
        """A planner stub: remembers the state it planned from."""

        last_predicted_states = None
        last_costs = None

        def __call__(self, dynamics, cost, state):
            self.start = np.asarray(state, dtype=np.float64)
            self.last_plan = torch.zeros(3, 2)
            return np.zeros(2)

        def reset(self):
            pass

    def dynamics(s, a):  # [B, S], [B, A] -> [E=1, B, S]: x += a0, y += a1
        return (s + torch.nn.functional.pad(a, (0, s.shape[-1] - a.shape[-1]))).unsqueeze(0)

    model = type("M", (), {"predict": staticmethod(dynamics)})()
    pl = Recorder()
    pol = MpcPolicy(model, pl, cost=lambda *a: None, delay_steps=1)
    x = np.array([1.0, 2.0, 0.0])
    pol(x)
    np.testing.assert_allclose(pl.start, x)  # nothing committed: from the measured state
    pol(x, committed=[np.array([0.5, -0.25])])
    np.testing.assert_allclose(pl.start, [1.5, 1.75, 0.0])
    pol(x, committed=[np.array([0.5, 0.0]), np.array([0.5, 1.0])])  # oldest first, each applied
    np.testing.assert_allclose(pl.start, [2.0, 3.0, 0.0])
    # a single model's [B, S] (the adaptation adapters' dynamics, `hil mpc --adapt`) as well
    single = type("M", (), {"predict": staticmethod(lambda s, a: dynamics(s, a)[0])})()
    MpcPolicy(single, pl, cost=lambda *a: None, delay_steps=1)(x, committed=[np.array([0.5, -0.25])])
    np.testing.assert_allclose(pl.start, [1.5, 1.75, 0.0])
    with pytest.raises(ValueError, match="delay_steps"):
        MpcPolicy(model, pl, cost=None, delay_steps=-1)


def test_a_supervisor_timeout_shorter_than_a_path_is_refused_before_the_rig_starts(tmp_path):
    from hilstack.configs.schema import BusConfig
    from hilstack.learning.mbrl import MbrlConfig, MbrlRun, RigError

    src = (Path(__file__).resolve().parents[2] / "configs" / "rigs" / "roach_emulated.yaml").read_text()
    assert "max_s: 60" in src  # the shipped rig leaves the figure-8 its 45.7 s
    rig = tmp_path / "roach_emulated_short.yaml"
    rig.write_text(src.replace("max_s: 60", "max_s: 30").replace("name: roach_emulated", "name: roach_emu_short"))
    run = MbrlRun(MbrlConfig.from_preset("quick", rig=str(rig), progress=False), tmp_path / "out", BusConfig())
    with pytest.raises(RigError, match=r"timeout, max_s 30 s\) would end the figure8 path before its time limit "
                                       r"of 45\.7 s"):
        run.run()
    assert not (tmp_path / "out" / "logs").exists()  # refused before the rig's process started


def test_realtime_samples_fits_the_given_planner_once_on_a_wall_clock_rig_only(tmp_path):
    """`MbrlRun.realtime_samples`: on a wall-clock rig the planner ``make(n)`` is timed from
    the robot's state and cut to the floor when nothing fits the period; the fit is measured
    once and reported; lockstep rigs keep the configured samples (None)."""
    from types import SimpleNamespace

    import torch

    from hilstack.configs.schema import BusConfig
    from hilstack.control.planners import CEM
    from hilstack.learning.mbrl import MbrlConfig, MbrlRun

    made = []

    def make(n):
        made.append(n)
        return CEM(action_low=-1.0, action_high=1.0, horizon=2, samples=n, action_dim=2, iterations=1,
                   elites=max(1, n // 10))

    model = SimpleNamespace(predict=lambda s, a: (s + torch.nn.functional.pad(a, (0, 1))).unsqueeze(0))
    cost = lambda states, actions: states[..., -1, 0]  # noqa: E731

    def run_on(rig, period_s):
        run = MbrlRun(MbrlConfig(rig=rig, samples=200, realtime_min_samples=20), tmp_path / rig, BusConfig())
        run.ctl = SimpleNamespace(next_state=lambda: SimpleNamespace(state=np.zeros(3)))
        run.pacing = rig_pacing(rig, "roach")  # what session() takes from the spec on the bus
        run.period_s = period_s
        return run

    run = run_on("roach_emulated", 1e-9)  # no plan fits a nanosecond
    assert run.realtime_samples(model, make=make, cost=cost) == 20
    assert made[0] == 200 and 20 in made
    assert run.planner_fit["configured_samples"] == 200 and run.planner_fit["trials"][0]["samples"] == 200
    n_made = len(made)
    run.period_s = 1e6
    assert run.realtime_samples(model, make=make, cost=cost) == 20 and len(made) == n_made  # measured once
    assert run_on("roach_emulated", 1e6).realtime_samples(model, make=make, cost=cost) == 200
    assert run_on("roach_sim", 1e-9).realtime_samples(model, make=make, cost=cost) is None  # lockstep


def _slow_planner_episode(n, load, plans=50, per_sample_s=0.00005, overhead_s=0.005, deadline_s=0.08):
    """What one wall-clock episode measures of a planner whose plan takes ``load`` times
    (overhead + n × per-sample) seconds, with a 20 % tail: its plan times and late plans."""
    base = load * (overhead_s + per_sample_s * n)
    times = [base * (1.25 if i % 5 == 0 else 0.95) for i in range(plans)]
    late = sum(int(t // deadline_s) for t in times)  # each period a plan overruns sends the shifted last plan
    return times, late


def test_refit_samples_follows_the_load_from_measured_plan_times():
    """refit_samples: the count follows an injected slow planner as the load rises and falls,
    within [floor, configured], growing at most 2x per refit; no wall clock (plan times given)."""
    from hilstack.control.sample_refit import refit_samples

    kw = dict(max_samples=500, min_samples=50, budget_s=0.04, deadline_s=0.08, max_late_share=0.05)
    n, p50s = 500, {}
    for load in (1.0, 4.0, 4.0, 4.0, 4.0, 1.0, 1.0, 1.0, 1.0, 1.0):  # quiet, a load for minutes, quiet again
        times, late = _slow_planner_episode(n, load)
        n_new, rec = refit_samples(n, times, late, steps=len(times), **kw)
        assert 50 <= n_new <= 500 and n_new <= 2 * n
        assert rec["from"] == n and rec["to"] == n_new and rec["plan_ms_p50"] == pytest.approx(np.median(times) * 1e3)
        n = n_new
        p50s.setdefault(load, []).append((n, _slow_planner_episode(n, load)[0]))
    # under the load (4x, 500 samples: 120 ms p50): cut, each refit closer (proportional: the
    # fixed overhead leaves each cut short), within 10 % of the 40 ms budget after 4 episodes
    # and every plan within the 80 ms deadline
    n_loaded, t_loaded = p50s[4.0][-1]
    gaps = [np.median(t) - 0.04 for _, t in p50s[4.0]]
    assert all(a > b > 0 for a, b in zip(gaps, gaps[1:], strict=False))
    assert np.median(t_loaded) <= 1.1 * 0.04 and max(t_loaded) <= 0.08
    assert n_loaded > 50  # not thrown to the floor: the cut is proportional
    # quiet again (500 samples plan 30 ms p50, 37.5 ms at the tail): back up to the configured count
    assert p50s[1.0][0][0] == 500 and p50s[1.0][-1][0] == 500

    # a planner slower than anything: the floor; plans far within budget: the configured count
    assert refit_samples(60, [1.0] * 10, 50, 10, **kw)[0] == 50
    assert refit_samples(100, [1e-4] * 10, 0, 10, **kw)[0] == 200  # at most 2x per refit
    assert refit_samples(400, [1e-4] * 10, 0, 10, **kw)[0] == 500  # capped at the configured count
    # plans within budget but a quarter of the cycles late (the thread starved): cut, never grown
    n2, rec = refit_samples(400, [0.001] * 40, 10, 40, **kw)
    assert n2 == 300 and "late share" in rec["reason"]
    # noise: a growth under 10 % is not made, a cut however small is; nothing measured: kept
    assert refit_samples(400, [0.038] * 20, 0, 20, **kw)[0] == 400
    assert refit_samples(400, [0.042] * 20, 0, 20, **kw)[0] == 380
    assert refit_samples(400, [], 0, 0, **kw) == (400, pytest.approx({"from": 400, "to": 400, "plans": 0, "late_share": 0.0,
                                                                      "plan_ms_p50": None, "plan_ms_tail": None,
                                                                      "reason": "no plans measured"}))


def test_the_wall_clock_mpc_refits_its_samples_between_episodes_and_reports_them(tmp_path):
    """MbrlRun.run_paths on a wall-clock rig: after each MPC episode the count is refitted
    from that episode's plan times (an injected slow planner whose load rises after the
    first path), the next path's planner gets it, the change is in ``planner_fit["refits"]``;
    the baseline's episodes refit nothing; with ``realtime_refit=False`` the start's fit stays."""
    from types import SimpleNamespace

    from hilstack.configs.schema import BusConfig
    from hilstack.control.controller_node import EpisodeLog
    from hilstack.control.paths import make_path
    from hilstack.learning.mbrl import MbrlConfig, MbrlRun, path_start_pose

    names = ["x", "y", "cos_yaw", "sin_yaw"]
    model = SimpleNamespace(predict=lambda s, a: s.unsqueeze(0))

    def run_with(refit):
        run = MbrlRun(MbrlConfig(rig="roach_emulated", samples=500, realtime_refit=refit, tip_weight=0.0, progress=False),
                      tmp_path / str(refit), BusConfig())
        run.pacing, run.period_s, run.state_names, run.action_names = rig_pacing("roach_emulated", "roach"), 0.1, names, ["l", "r"]
        run.planner_fit = {"samples": 500, "configured_samples": 500, "trials": [], "current_samples": 500, "refits": []}
        seen, loads = [], iter([1.0, 6.0, 6.0, 6.0])

        def episode(policy, steps, pose, stop_if=None):
            p = path_start_pose(make_path("straight"))
            x = np.array([p["x"], p["y"], np.cos(p["yaw"]), np.sin(p["yaw"])])
            log = EpisodeLog(states=[x] * 3, actions=[np.zeros(2)] * 2, actions_norm=[np.zeros(2)] * 2)
            if hasattr(policy, "planner"):
                seen.append(policy.planner.samples)
                log.plan_times_s, log.late_plans = _slow_planner_episode(policy.planner.samples, next(loads))
                log.actions = [np.zeros(2)] * len(log.plan_times_s)
            return log

        run.episode = episode
        res = run.run_paths(run.mpc_for(model), 1.0, paths=("straight", "left", "right", "zigzag"))
        run.run_paths(run.baseline_for(), 1.0, paths=("straight",))
        return run, res, seen

    run, res, seen = run_with(True)
    assert seen[0] == seen[1] == 500  # quiet: 500 samples fit (30 ms p50); cut only once the load says so
    assert seen[-1] < seen[1] and [res[p]["samples"] for p in res] == seen
    refits = run.planner_fit["refits"]
    assert refits and refits[-1]["to"] == run.planner_fit["current_samples"] == run.refit_samples(EpisodeLog(), "x")
    assert all(r["after"].endswith("at 1") for r in refits) and refits[0]["from"] == 500
    n_refits = len(refits)
    assert len(run.planner_fit["refits"]) == n_refits  # the baseline's episode refitted nothing
    run, _, seen = run_with(False)
    assert seen == [500] * 4 and run.planner_fit["refits"] == []
    with pytest.raises(ValueError, match="realtime_max_late_share"):
        MbrlConfig(realtime_max_late_share=1.0)


def test_the_supervisor_ends_an_episode_by_its_detectors_in_that_episode_only(tmp_path):
    """A detector that fires on the first state after the reset (before the loop's first
    look) ends the new episode; a detector's end left over from the episode before, and the
    reset's own transitions, do not."""
    from types import SimpleNamespace

    from hilstack.bus.schemas import ResetTransition, encode
    from hilstack.configs.schema import BusConfig
    from hilstack.learning.mbrl import MbrlConfig, MbrlRun

    def tr(trigger, source, dest, episode, reason=""):
        return ResetTransition(robot="roach", trigger=trigger, source=source, dest=dest, episode=episode, reason=reason)

    the_reset = [tr("end_episode", "running", "episode_end", 4, "request"), tr("pause", "episode_end", "paused", 4),
                 tr("begin", "paused", "resetting", 4), tr("steps_done", "resetting", "verifying", 4),
                 tr("verified", "verifying", "resumed", 4), tr("resume", "resumed", "running", 4)]
    stale = tr("end_episode", "running", "episode_end", 4, "timeout")  # the episode before's last state
    fired = tr("end_episode", "running", "episode_end", 5, "left_arena")  # the new episode's first state
    run = MbrlRun(MbrlConfig(rig="roach_sim"), tmp_path, BusConfig())
    run.supervisor = object()
    run.reset = lambda pose: SimpleNamespace(episode=5)
    run.ctl = SimpleNamespace()
    queue: list = []

    def drain():  # the subscription: every transition published since the last drain
        out = [(None, encode(m)) for m in queue]
        queue.clear()
        return out

    run._transitions = SimpleNamespace(drain=drain)

    for before, during, ended in (([stale, *the_reset], [], False), ([*the_reset, fired], [], True),
                                  ([stale, *the_reset], [fired], True)):
        queue[:] = before
        run.ctl.run_episode = lambda policy, steps, first, stop_if, d=during: [stop_if(first), queue.extend(d),
                                                                                stop_if(first)]
        first_look, _, second_look = run.episode(lambda s: s, 10, {})
        assert second_look == ended and first_look == (ended and not during)
        assert run.last_end_reason == ("supervisor: left_arena" if ended else "")


def test_tilt_loss_weight_lands_on_the_tilt_channels():
    """MbrlConfig.tilt_loss_weight weighs roll, pitch and their rates in the model's loss (issue
    29); the open-loop horizon reaches the body-frame model and needs one."""
    from hilstack.drivers.velociroach.config import STATE_NAMES
    from hilstack.learning.mbrl import TILT_CHANNELS, MbrlConfig, make_model

    m = make_model(MbrlConfig(tilt_loss_weight=5.0, train_horizon=3), list(STATE_NAMES), ["l", "r"])
    w = dict(zip(STATE_NAMES, m.model.config["loss_weights"], strict=True))
    assert {n for n, v in w.items() if v == 5.0} == set(TILT_CHANNELS) and len(TILT_CHANNELS) == 6
    assert all(v == 1.0 for n, v in w.items() if n not in TILT_CHANNELS) and m.train_horizon == 3
    assert make_model(MbrlConfig(), list(STATE_NAMES), ["l", "r"]).model.config["loss_weights"] is None
    with pytest.raises(ValueError, match="train_horizon"):
        MbrlConfig(train_horizon=2, body_frame=False)
