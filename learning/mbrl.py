"""The model-based RL loop (Nagabandi et al., Alg. 1) with every node on the bus.

    random data (safe random policy) → train dynamics → MPC collects on-policy rollouts
    → aggregate → retrain (warm start) → ... → tune the differential-drive baseline per
    speed on separate tuning paths → evaluate MPC vs the tuned baseline on the paths at a
    low and a high commanded speed (paths completed, then cost per metre; docs/mbrl.md)
    → with ``experiments``, the thesis' tables over seeds (:mod:`hilstack.learning.experiments`).

The rig is real nodes over a real Zenoh session: the driver bridge runs in its own
process (``hil up <rig>``), the controller node (random policy, MPC, baseline) and the
recorder run here. Training data is read back from the MCAP recordings, the same path a
lab takes with recordings from a real robot. On a sim rig with ``pace: lockstep`` the
simulation advances when the controller answers, so the loop runs faster than real time;
on a real or emulated rig the same code runs on the wall clock (``realtime=True``).
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from hilstack.bus import keys
from hilstack.bus.lifetime import child_env
from hilstack.bus.recording import Recorder
from hilstack.bus.schemas import ResetTransition, RobotState, StoppedReason, decode
from hilstack.bus.session import BusUnavailable
from hilstack.configs.presets import Presets
from hilstack.configs.schema import BusConfig, load_rig
from hilstack.control.baselines import DifferentialDriveController
from hilstack.control.controller_node import REALTIME_DEADLINE_FRAC, ControllerNode, DriverGone, EpisodeLog
from hilstack.control.costs import PathCost, evaluate_path_following, rank_key, summarize_paths
from hilstack.control.paths import fillet, make_path, path_length
from hilstack.control.planners import CEM, PDDM, RandomShooting
from hilstack.control.policies import BaselinePolicy, MpcPolicy, SafeRandomPolicy
from hilstack.control.policy_api import Resettable
from hilstack.control.reset.config import ResetConfig, ResetUnavailable, require_reset
from hilstack.control.reset.detectors import make_detector
from hilstack.control.reset.supervisor import ResetSupervisor
from hilstack.control.sample_refit import refit_samples
from hilstack.drivers.base import Pacing, RobotSpec
from hilstack.learning.datasets import Episode, split_episodes
from hilstack.learning.dynamics import EnsembleDynamics
from hilstack.learning.frames import BodyFrameDynamics
from hilstack.learning.progress import progress
from hilstack.learning.recordings import episodes_from_mcap


class RigError(RuntimeError):
    """The rig stopped answering (driver node crashed or link lost); the robot's own
    watchdogs have stopped it. Recordings written so far are complete up to that point."""


#: the thesis' experiments `hil demo --full` runs (hilstack.learning.experiments)
EXPERIMENTS = ("table_3_1", "speed_sweep", "table_3_2")


@dataclass
class MbrlConfig(Presets):
    #: the presets of ``from_preset(name, **overrides)`` (configs/presets.py): overrides of the defaults
    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        # `hil demo --full`: the thesis' data sizes and every experiment over three seeds.
        "full": dict(random_rollouts=400, experiments=EXPERIMENTS),
        "quick": dict(random_rollouts=60, epochs=40, retrain_epochs=10, baseline_candidates=20),
    }

    rig: str = "roach_sim"
    robot: str = "roach"
    seed: int = 0
    # data collection (thesis: 200 rollouts x 50 steps at 10 Hz per terrain)
    random_rollouts: int = 200
    rollout_steps: int = 50
    arena_radius_m: float = 3.0
    #: random data: each random command is held 1..random_hold_steps steps, and this fraction
    #: of them are forward commands (hilstack.control.policies.SafeRandomPolicy) so the data covers
    #: the speeds the evaluation asks for; 1 and 0.0 give the thesis' uniform steps
    random_hold_steps: int = 6
    random_forward_fraction: float = 0.6
    # model (thesis: 2x500 ReLU MLP, Adam 1e-3)
    hidden: tuple[int, ...] = (500, 500)
    ensemble: int = 1
    epochs: int = 60
    retrain_epochs: int = 20
    batch_size: int = 512
    input_noise_std: float = 0.01
    #: supervised-learning noise while training, as a share of each channel's std (states and
    #: deltas; :class:`~hilstack.learning.dynamics.EnsembleDynamics` ``noise_to_signal``)
    noise_to_signal: float = 0.0
    val_fraction: float = 0.1
    #: issue 29, a model that sees a tip coming: the weight of the tilt channels (cos/sin of roll
    #: and pitch, and the body rates wx, wy) in the training loss, the others 1 (EnsembleDynamics
    #: loss_weights); and the horizon of the open-loop training loss after the one-step fit
    #: (BodyFrameDynamics.fit_open_loop; 1: one-step only, the thesis)
    tilt_loss_weight: float = 1.0
    train_horizon: int = 1
    #: learn in the robot's body frame (translation and heading invariance; hilstack.learning.frames)
    body_frame: bool = True
    #: otherwise: inputs the model ignores (planar translation invariance)
    invariant_inputs: tuple[str, ...] = ("x", "y")
    # planner (thesis: random shooting, N=500, H=4; CEM by default here: see docs/mbrl.md)
    planner: str = "cem"
    samples: int = 500
    horizon: int = 4
    #: random shooting samples within the actuator's reachable set (the rig's rate limit
    #: times the period, :class:`hilstack.control.planners.RandomShooting` ``max_step``); False: the
    #: thesis' independent uniform steps
    reachable_set: bool = True
    # MBRL iterations: on-policy MPC rollouts on the paths, aggregated, warm-start retrain
    iterations: int = 1
    # tasks
    paths: tuple[str, ...] = ("straight", "left", "right", "zigzag", "figure8")
    path_scale: float = 1.5
    speeds: dict[str, float] = field(default_factory=lambda: {"low_speed": 0.5, "high_speed": 1.0})
    #: the controllers track the path with its corners rounded to this radius (m,
    #: hilstack.control.paths.fillet): at a polyline's sharp corner the H-step MPC parks (docs/mbrl.md);
    #: episodes are scored on the original path. 0: track the polyline itself
    reference_corner_radius_m: float = 0.2
    #: time limit of an evaluation episode = path length / this speed (m/s): long enough for
    #: a slow but correct controller (the sim walks ~0.68 m/s at command 0.5, docs/mbrl.md)
    time_limit_speed_mps: float = 0.15
    #: stability (issue 29): the planner's path cost adds tip_weight (1/rad) times the predicted
    #: roll and pitch beyond tip_threshold_deg (hilstack.control.costs, tipping term), and the
    #: differential drive stops turning harder beyond the same threshold. 0: the thesis' cost
    tip_weight: float = 50.0
    tip_threshold_deg: float = 20.0
    # the differential-drive baseline is tuned per speed by a random search (Latin hypercube)
    # on tuning paths that are not the evaluation paths (other shapes and scale)
    baseline_candidates: int = 24
    tune_paths: tuple[str, ...] = ("left", "zigzag", "figure8")
    tune_path_scale: float = 1.0
    # the thesis' experiments with statistics (`hil demo --full`, hilstack.learning.experiments):
    # any of "table_3_1", "speed_sweep", "table_3_2", each repeated for every seed in seeds
    experiments: tuple[str, ...] = ()
    seeds: tuple[int, ...] = (0, 1, 2)
    table_sizes: tuple[int, ...] = (50, 200, 400)
    table_paths: tuple[str, ...] = ("straight", "left", "right")
    sweep_speeds: tuple[float, ...] = (0.4, 0.6, 0.8, 1.0)
    terrains: tuple[str, str] = ("carpet", "styrofoam")
    terrain_rollouts: int = 200
    progress: bool = True
    #: wall-clock rigs: the planner's samples are cut until its median plan time is within
    #: this fraction of the control period (the deadline is 0.8; load spikes take the rest),
    #: never below realtime_min_samples (fit_samples_to_budget). Lockstep sims: no limit
    realtime_plan_budget: float = 0.4
    realtime_min_samples: int = 50
    #: wall-clock rigs: after every MPC episode the sample count is refitted from its plan
    #: times and late-plan share (refit_samples; the load changes within minutes), at most
    #: this share of late plans wanted. False: the start's fit is kept for the whole run
    realtime_refit: bool = True
    realtime_max_late_share: float = 0.05
    #: how long to wait for the driver node to come up (emulator start, radio link)
    rig_timeout_s: float = 60.0
    #: real rigs: when the driver cannot reset itself, ask an operator on the terminal
    operator_resets: bool = False

    def __post_init__(self) -> None:
        # refuse a bad setting before any rig process starts, naming the field
        problems = []
        if set(self.experiments) - set(EXPERIMENTS):
            problems.append(f"experiments: unknown {sorted(set(self.experiments) - set(EXPERIMENTS))}, "
                            f"choose from {list(EXPERIMENTS)}")
        if self.time_limit_speed_mps <= 0:
            problems.append(f"time_limit_speed_mps must be > 0, got {self.time_limit_speed_mps}")
        if not 0.0 <= self.realtime_max_late_share < 1.0:
            problems.append(f"realtime_max_late_share must be in [0, 1), got {self.realtime_max_late_share}")
        if not 0 < self.realtime_plan_budget <= 1 or self.realtime_min_samples < 1:
            problems.append(f"realtime_plan_budget must be in (0, 1] and realtime_min_samples >= 1, got "
                            f"{self.realtime_plan_budget} and {self.realtime_min_samples}")
        if self.baseline_candidates < 1:
            problems.append(f"baseline_candidates must be >= 1, got {self.baseline_candidates}")
        if not 0.0 <= self.random_forward_fraction <= 1.0:
            problems.append(f"random_forward_fraction must be in [0, 1], got {self.random_forward_fraction}")
        if self.reference_corner_radius_m < 0:
            problems.append(f"reference_corner_radius_m must be >= 0, got {self.reference_corner_radius_m}")
        if not (math.isfinite(self.tip_weight) and 0.0 <= self.tip_weight <= 1e4):
            problems.append(f"tip_weight must be in [0, 1e4], got {self.tip_weight}")
        if not (math.isfinite(self.tip_threshold_deg) and 0.0 < self.tip_threshold_deg < 90.0):
            problems.append(f"tip_threshold_deg must be in (0, 90), got {self.tip_threshold_deg}")
        if not (math.isfinite(self.tilt_loss_weight) and 0.0 < self.tilt_loss_weight <= 1e3):
            problems.append(f"tilt_loss_weight must be in (0, 1e3], got {self.tilt_loss_weight}")
        if not 1 <= self.train_horizon <= 50:
            problems.append(f"train_horizon must be in 1..50, got {self.train_horizon}")
        if self.train_horizon > 1 and not self.body_frame:
            problems.append("train_horizon > 1 needs body_frame (the open-loop loss rolls the body-frame model)")
        if self.experiments and not self.seeds:
            problems.append("seeds: the experiments need at least one seed")
        if problems:
            raise ValueError("MbrlConfig: " + "; ".join(problems))


def task_cost(cfg: MbrlConfig, waypoints, state_names) -> PathCost:
    """The path cost the planner optimizes: the thesis' terms plus the tipping term
    (``cfg.tip_weight`` beyond ``cfg.tip_threshold_deg``) when the state has roll and pitch."""
    tilt = {"cos_roll", "sin_roll", "cos_pitch", "sin_pitch"} <= {n.lower() for n in state_names}
    return PathCost(waypoints, state_names, f_tip=cfg.tip_weight if tilt else 0.0,
                    tip_threshold_rad=math.radians(cfg.tip_threshold_deg))


def max_tilt_deg(states, state_names) -> float:
    """The largest |roll| or |pitch| (degrees) over ``states [T, S]``; NaN without those channels."""
    names = [n.lower() for n in state_names]
    if not {"cos_roll", "sin_roll", "cos_pitch", "sin_pitch"} <= set(names):
        return float("nan")
    s = np.asarray(states, dtype=np.float64)
    ang = [np.arctan2(s[:, names.index(f"sin_{a}")], s[:, names.index(f"cos_{a}")]) for a in ("roll", "pitch")]
    return float(np.degrees(np.abs(np.stack(ang)).max()))


def _log(cfg: MbrlConfig, msg: str) -> None:
    if cfg.progress:
        print(f"[mbrl {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------- the rig
@contextlib.contextmanager
def rig_processes(rig: str, bus: BusConfig, log_dir: Path) -> Iterator[subprocess.Popen]:
    """The rig's driver bridge in its own process (``hil up``), stopped on exit."""
    log_dir.mkdir(parents=True, exist_ok=True)
    err = open(log_dir / "driver.log", "w")  # noqa: SIM115 - closed below
    p = subprocess.Popen(
        [sys.executable, "-m", "hilstack", "up", rig, "--endpoint", bus.endpoint],
        stdout=err,
        stderr=subprocess.STDOUT,
        # the rig stops itself if this process dies without stopping it (SIGKILL, a crash):
        # bus/lifetime.py, exit_with_parent
        env=child_env({**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}),
    )
    try:
        yield p
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        err.close()


@contextlib.contextmanager
def recording(rig: str, path: Path, bus: BusConfig) -> Iterator[Recorder]:
    rec = Recorder(rig, path, bus, handle_signals=False)
    th = threading.Thread(target=rec.record, name="recorder", daemon=True)
    th.start()
    time.sleep(0.3)  # let the subscription reach the driver node
    try:
        yield rec
    finally:
        time.sleep(0.2)
        rec.stop_event.set()
        th.join(10)
        rec.close()


def path_start_pose(waypoints: np.ndarray) -> dict[str, float]:
    d = waypoints[1] - waypoints[0]
    return {"x": float(waypoints[0, 0]), "y": float(waypoints[0, 1]), "yaw": float(np.arctan2(d[1], d[0]))}


class PathEnd:
    """Episode end for path following: the robot has passed the end of the path, its
    place on the path tracked with the cost's progress window (so a closed path such as
    the figure-8, which starts where it ends, ends only after a full lap)."""

    def __init__(self, path: PathCost):
        self.path = path
        self.path.reset()

    def __call__(self, state: np.ndarray) -> bool:
        self.path.observe(state)
        return self.path.at_end(np.asarray(state)[[self.path.ix, self.path.iy]])


# ---------------------------------------------------------------------------- model
#: the channels ``tilt_loss_weight`` weighs: roll and pitch and their rates
TILT_CHANNELS = ("cos_roll", "sin_roll", "cos_pitch", "sin_pitch", "wx", "wy")


def make_model(cfg: MbrlConfig, state_names: list[str], action_names: list[str]):
    weights = None
    if cfg.tilt_loss_weight != 1.0:
        weights = [cfg.tilt_loss_weight if n in TILT_CHANNELS else 1.0 for n in state_names]
    model = EnsembleDynamics(
        len(state_names),
        len(action_names),
        ensemble=cfg.ensemble,
        hidden=cfg.hidden,
        input_noise_std=cfg.input_noise_std,
        loss_weights=weights,
        noise_to_signal=cfg.noise_to_signal,
        state_names=state_names,
        action_names=action_names,
        seed=cfg.seed,
    )
    if cfg.body_frame:
        return BodyFrameDynamics(model, state_names, train_horizon=cfg.train_horizon)
    ignore = [state_names.index(n) for n in cfg.invariant_inputs if n in state_names]
    if ignore:
        model.ignore_inputs(ignore)
    return model


def fit_episodes(model, eps: list[Episode], epochs: int, batch_size: int, val_fraction: float,
                 rng: np.random.Generator, assigned: dict[str, bool], horizon: int = 10,
                 progress: bool = False) -> dict[str, float]:
    """One (re)fit of the MBRL loop: split ``eps`` by episode once and for good
    (:func:`split_episodes`), fit ``model`` on the training episodes (warm start when it was
    fitted before) and return the last epoch's losses (with the held-out one-step and
    ``horizon``-step errors when there is a validation episode). The roach's loop
    (:meth:`MbrlRun.train`) and the gym benchmarks' (``learning/mbmf.py``) both train this way."""
    train, val = split_episodes(eps, val_fraction, rng, assigned)
    hist = model.fit(train, epochs=epochs, batch_size=batch_size, val=val or None, horizon=horizon,
                     progress=progress)
    last = hist[-1] if hist else {}
    return {k: float(v) for k, v in last.items() if isinstance(v, (int, float))}


#: differential-drive search space: (low, high, scaled by the speed setting?). Gains in
#: normalized action per rad (k_heading) and per m (k_perp); omega_nom and d_max are
#: fractions of the speed setting, which also clips the commands (the bound MPC plans in).
BASELINE_SEARCH: dict[str, tuple[float, float, bool]] = {
    "omega_nom": (0.4, 1.0, True),
    "k_heading": (0.2, 3.0, False),
    "k_perp": (0.0, 10.0, False),
    "d_max": (0.2, 1.0, True),
}


def speed_coverage(episodes: list[Episode], state_names: list[str]) -> dict[str, float]:
    """How fast the robot went in ``episodes``: ground-speed percentiles (m/s, from the
    world-frame vx, vy channels) and the fraction of steps at or above 0.5 and 0.9 m/s."""
    ivx, ivy = state_names.index("vx"), state_names.index("vy")
    v = np.concatenate([np.hypot(e.states[:, ivx], e.states[:, ivy]) for e in episodes])
    p50, p90, p99 = np.percentile(v, [50, 90, 99])
    return {"speed_p50_mps": float(p50), "speed_p90_mps": float(p90), "speed_p99_mps": float(p99),
            "fraction_ge_0.5_mps": float((v >= 0.5).mean()), "fraction_ge_0.9_mps": float((v >= 0.9).mean())}


def default_baseline_params(speed: float) -> dict[str, float]:
    """The untuned starting point: ω_nom = 0.7·speed, d_max = 0.4·speed, k_ψ = 0.8, k_⊥ = 4."""
    return {"omega_nom": 0.7 * speed, "k_heading": 0.8, "k_perp": 4.0, "d_max": 0.4 * speed}


def baseline_candidates(n: int, speed: float, seed: int = 0) -> list[dict[str, float]]:
    """``n`` gain sets: the default first, then a Latin hypercube over :data:`BASELINE_SEARCH`
    (``scipy.stats.qmc``: every gain's range is covered evenly even with few candidates)."""
    from scipy.stats import qmc

    if n < 1:
        raise ValueError(f"baseline_candidates must be >= 1, got {n}")
    names = list(BASELINE_SEARCH)
    out = [default_baseline_params(speed)]
    if n > 1:
        u = qmc.LatinHypercube(d=len(names), seed=seed).random(n - 1)
        for row in u:
            p = {}
            for k, x in zip(names, row, strict=True):
                lo, hi, scaled = BASELINE_SEARCH[k]
                p[k] = float((lo + x * (hi - lo)) * (speed if scaled else 1.0))
            out.append(p)
    return out


def make_planner(cfg: MbrlConfig, speed: float, action_dim: int, max_step: np.ndarray | None = None,
                 samples: int | None = None):
    """The configured planner within ±``speed`` (normalized actions). ``max_step``: the
    rig's per-step rate limit in normalized units (random shooting's reachable set).
    ``samples``: instead of ``cfg.samples`` (wall-clock rigs, :func:`fit_samples_to_budget`);
    CEM keeps a tenth of them as elites (50 of 500)."""
    n = cfg.samples if samples is None else int(samples)
    kw = dict(action_low=-speed, action_high=speed, horizon=cfg.horizon, samples=n,
              seed=cfg.seed, action_dim=action_dim)
    if cfg.planner == "random_shooting":
        return RandomShooting(**kw, max_step=max_step if cfg.reachable_set else None)
    if cfg.planner == "cem":
        return CEM(**kw, iterations=3, elites=max(1, min(n, round(0.1 * n))))
    if cfg.planner == "pddm":
        return PDDM(**kw)
    raise ValueError(f"unknown planner {cfg.planner!r}: random_shooting | cem | pddm")


def fit_samples_to_budget(plan_time_s, samples: int, budget_s: float, min_samples: int = 50,
                          reps: int = 5, rounds: int = 3) -> tuple[int, list[dict[str, float]]]:
    """The planner's sample count for a wall-clock rig: ``samples`` if its median plan
    time (``plan_time_s(n)`` → seconds of one plan with ``n`` samples, ``reps`` calls) is
    within ``budget_s``, else scaled down in proportion (at most ``rounds`` measurements,
    never below ``min_samples``). Returns it and every measurement.

    On the lockstep sim planning time costs nothing; on the wall clock a plan that misses
    the control period's deadline is replaced by the shifted last plan, and with the
    thesis' N = 500 (CEM, 3 iterations) a plan took 100-170 ms median on the shared 2-core
    machine, more than the 100 ms period (docs/mbrl.md, "Wall-clock rigs")."""
    n = int(samples)
    trials: list[dict[str, float]] = []
    for _ in range(rounds):
        t = float(np.median([plan_time_s(n) for _ in range(reps)]))
        trials.append({"samples": n, "plan_ms_p50": t * 1e3})
        if t <= budget_s:
            break
        guess = n * budget_s / t  # proportional; then the line through the last two (fixed overhead)
        if len(trials) >= 2:
            (n0, t0), (n1, t1) = ((d["samples"], d["plan_ms_p50"] / 1e3) for d in trials[-2:])
            if t0 > t1 and n0 > n1:
                guess = n1 + (budget_s - t1) * (n0 - n1) / (t0 - t1)
        n_new = max(int(min_samples), int(guess))
        if n_new >= n:
            break
        n = n_new
    return n, trials


def fit_planner_to_period(cfg: MbrlConfig, speed: float, action_dim: int, max_step: np.ndarray | None,
                          predict, cost, state: np.ndarray, period_s: float) -> tuple[int, list[dict[str, float]]]:
    """:func:`fit_planner_samples` for the configured planner (:func:`make_planner`) within
    ``cfg.realtime_plan_budget`` of ``period_s``. ``hil demo`` and ``hil mpc`` on wall-clock rigs."""
    return fit_planner_samples(lambda n: make_planner(cfg, speed, action_dim, max_step, n), cfg.samples,
                               predict, cost, state, cfg.realtime_plan_budget * period_s, cfg.realtime_min_samples)


def fit_planner_samples(make, samples: int, predict, cost, state: np.ndarray, budget_s: float,
                        min_samples: int = 50) -> tuple[int, list[dict[str, float]]]:
    """:func:`fit_samples_to_budget` for any planner: ``make(n)`` builds it with ``n``
    samples; each plan is timed with ``predict`` and ``cost`` from ``state`` (a first call
    per size fills the buffers and is not timed). The path MPC, the Baoding PDDM and the
    arms' reach CEM share it (:meth:`MbrlRun.realtime_samples`)."""

    def plan_time_s(n: int) -> float:
        pl = make(n)
        pl(predict, cost, state)
        t0 = time.perf_counter()
        pl(predict, cost, state)
        return time.perf_counter() - t0

    return fit_samples_to_budget(plan_time_s, samples, budget_s, min_samples)


# ---------------------------------------------------------------------------- the loop
class MbrlRun:
    def __init__(self, cfg: MbrlConfig, out_dir: Path, bus: BusConfig):
        self.cfg = cfg
        self.out = Path(out_dir)
        self.rec_dir = self.out / "recordings"
        self.rec_dir.mkdir(parents=True, exist_ok=True)
        self.bus = bus
        self.rig = load_rig(cfg.rig)
        self.ctl: ControllerNode | None = None
        self.state_names: list[str] = []
        self.action_names: list[str] = []
        self.recordings: list[str] = []
        self.rng = np.random.default_rng(cfg.seed)
        self.split_rng = np.random.default_rng([cfg.seed, 1])
        #: per-seed train/validation split generators of the seeded experiments (experiments.py):
        #: a seed's split never depends on which seeds ran before it in this process, so a seed run
        #: alone (a sweep task) gives the serial run's numbers
        self.seed_split_rngs: dict[int, np.random.Generator] = {}
        self.val_assigned: dict[str, bool] = {}
        self.period_s = 0.1
        self.max_step: np.ndarray | None = None
        #: the robot's time model, from the spec its driver node publishes (session()): lockstep
        #: or not, and the command delay the MPC predicts through
        self.pacing: Pacing | None = None
        #: wall-clock rigs: the planner's fitted sample count and its measurements (realtime_samples)
        self.planner_fit: dict[str, Any] | None = None
        self.supervisor: ResetSupervisor | None = None
        #: the rig's reset procedure (None: the robot resets itself or an operator does)
        self.reset_cfg: ResetConfig | None = None
        self.reset_timeout_s = 10.0
        #: why the last episode ended early: "supervisor: <detector's reason>", or ""
        self.last_end_reason = ""
        self._ended = False  # the supervisor ended the current episode (_scan_transitions)
        self._episode_no = 0  # the robot's episode counter of the current episode

    def _wait_for_rig(self, ctl: ControllerNode, proc: subprocess.Popen) -> RobotSpec:
        """The robot's spec once its driver node is up; a rig process that exits first (a
        wrong port, a bad config) is a :class:`RigError` at once, with its log's last line."""
        deadline = time.monotonic() + self.cfg.rig_timeout_s
        while True:
            try:
                return ctl.wait_ready(timeout_s=0.5)
            except TimeoutError:
                if proc.poll() is not None:
                    raise self._rig_exited(proc) from None
                if time.monotonic() > deadline:
                    raise RigError(f"the rig's driver node sent no spec within rig_timeout_s = "
                                   f"{self.cfg.rig_timeout_s:g} s (driver log: {self.out / 'logs' / 'driver.log'})") from None

    def _rig_exited(self, proc: subprocess.Popen) -> RigError:
        log = self.out / "logs" / "driver.log"
        lines = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()] if log.exists() else []
        why = lines[-1].strip() if lines else "it printed nothing"
        return RigError(f"the rig's process exited (code {proc.returncode}) before its driver came up: "
                        f"{why} (driver log: {log})")

    def _controller(self, proc: subprocess.Popen) -> ControllerNode:
        """This loop's controller node. On an access-controlled rig the driver node is the router:
        joining fails until it listens, and for good when the rig's process exits first (a
        :class:`RigError` naming the driver's reason, not a bus error)."""
        deadline = time.monotonic() + self.cfg.rig_timeout_s
        while True:
            try:
                # a rig with a reset: section: this loop runs its supervisor (_supervised), which
                # alone serves the resets, also before the driver node has seen it
                return ControllerNode(self.rig.name, self.cfg.robot, self.bus, name="mbrl-controller",
                                      handle_signals=False, state_timeout_s=20.0,
                                      supervised=self.reset_cfg is not None)
            except BusUnavailable:
                if proc.poll() is not None:
                    raise self._rig_exited(proc) from None
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    @contextlib.contextmanager
    def session(self) -> Iterator[ControllerNode]:
        """The rig's driver node (own process) and this loop's controller node, up until exit."""
        cfg = self.cfg
        try:  # refuse before anything starts when nothing can reset the robot
            reset_cfg = require_reset(self.rig, cfg.robot, cfg.operator_resets)
        except ResetUnavailable as e:
            raise RigError(str(e)) from None
        self.reset_cfg = reset_cfg
        with rig_processes(self.rig.source or self.rig.name, self.bus, self.out / "logs") as proc, \
                self._controller(proc) as ctl, \
                self._supervised(reset_cfg):
            self.ctl = ctl
            self._transitions = ctl.subscribe(keys.reset_transition(self.rig.name), ResetTransition,
                                              latest=False, capacity=256)
            spec = self._wait_for_rig(ctl, proc)
            self.state_names = list(spec.state.names)
            self.action_names = list(spec.action.names)
            self.period_s = spec.period_s
            self.max_step = spec.max_step_normalized()
            self.pacing = ctl.pacing
            try:
                yield ctl
            finally:
                self.ctl = None

    def _check_episode_timeout(self, reset_cfg: ResetConfig | None) -> None:
        """The supervisor's timeout detector must not end an evaluation episode before the
        evaluation's own time limit (it cut the figure-8, 45.7 s at scale 1.5, at 30 s)."""
        if reset_cfg is None:
            return
        cfg = self.cfg
        limits = {p: self.time_limit_s(make_path(p, scale=cfg.path_scale)) for p in cfg.paths}
        limits.update({f"{p} (tuning)": self.time_limit_s(make_path(p, scale=cfg.tune_path_scale))
                       for p in cfg.tune_paths})
        longest = max(limits, key=limits.get)
        for i, d in enumerate(reset_cfg.detectors):
            if d.kind == "timeout" and d.max_s is not None and d.max_s < limits[longest]:
                raise RigError(f"{self.rig.source or self.rig.name}: reset.detectors[{i}] (timeout, max_s "
                               f"{d.max_s:g} s) would end the {longest} path before its time limit of "
                               f"{limits[longest]:.1f} s; raise max_s above it")

    @property
    def command_delay(self) -> int:
        """Control periods a command planned from a state lands after it (the spec's pacing:
        0 on sim backends, lockstep or realtime; 1 on wall-clock robots, real or emulated,
        whose driver node publishes the state of period k and applies the command planned
        from it at period k+1). The MPC plans from the state its model predicts after the
        command already sent (:class:`hilstack.control.policies.MpcPolicy`)."""
        return 0 if self.pacing is None else self.pacing.command_delay_periods

    # -- episodes over the bus ------------------------------------------------------------
    def episode(self, policy: Any, steps: int, pose: dict[str, float], stop_if=None) -> EpisodeLog:
        """Reset (the sim puts the robot at ``pose``; a real robot is placed by an operator)
        and run one episode: lockstep on sim rigs, on the wall clock otherwise."""
        first = self.reset(pose)
        self._ended, self.last_end_reason = False, ""
        self._episode_no = int(getattr(first, "episode", 0))
        if self.supervisor is not None:
            self._scan_transitions()  # the reset's own end nothing; a detector's on the first state does
        if isinstance(policy, Resettable):
            policy.reset()
        end_if = None
        if self.supervisor is not None:  # the supervisor's detectors end episodes too
            stop_if = _or_stop(stop_if, self._episode_ended)
            if self.pacing is not None and self.pacing.answered:
                end_if = self._rig_detectors(first)
        return self.ctl.run_episode(policy, steps, first, stop_if=stop_if,
                                    **({"end_if": end_if} if end_if is not None else {}))

    def _rig_detectors(self, first: RobotState):
        """Lockstep rigs: the rig's episode-end detectors (those on this robot's state) judged
        here on each state before it is answered, so an episode ends on the state where one
        fires. The supervisor judges the same states, but its word reaches this loop a few
        states later or sooner depending on the machine's load, and the episodes' lengths
        then did too (a seed did not repeat itself). The supervisor still ends the episode
        and resets (a request names the episode's last state, ResetEvent.state_seq)."""
        dets = [make_detector(d) for d in self.reset_cfg.detectors if not d.robot]
        for d in dets:
            d.bind(self.state_names)
            d.start(first)

        def ended(s: RobotState) -> bool:
            if not (s.active and s.stopped_reason == StoppedReason.RUNNING):
                return False  # as the supervisor: nothing drives the robot, no episode runs
            for d in dets:
                why = d(s)
                if why:
                    self._ended, self.last_end_reason = True, f"supervisor: {why}"
                    return True
            return False

        return ended

    def _episode_ended(self, state) -> bool:
        """The reset supervisor's detectors ended the episode (arena left, timeout...)."""
        return self._scan_transitions()

    def _scan_transitions(self) -> bool:
        """Read the supervisor's transitions since the last scan: a detector's end of episode
        (not "request": the end this loop asked for itself) in the current episode (the
        robot's episode counter, ``ResetTransition.episode``) ends it. So a detector that
        fired on the episode's first state, before the episode's first scan, still ends it,
        and one that fired at the end of the episode before does not."""
        for _, p in self._transitions.drain():
            t = decode(p, ResetTransition)
            if t.dest == "episode_end" and t.reason != "request" and t.episode >= self._episode_no:
                self._ended, self.last_end_reason = True, f"supervisor: {t.reason}"
        return self._ended

    @contextlib.contextmanager
    def _supervised(self, reset_cfg: ResetConfig | None) -> Iterator[None]:
        """The rig's reset supervisor node, when it has a reset procedure (docs/reset.md)."""
        if reset_cfg is None:
            yield
            return
        sup = ResetSupervisor(self.rig.name, reset_cfg, self.bus, handle_signals=False)
        th = threading.Thread(target=sup.serve, kwargs={"ready_timeout_s": self.cfg.rig_timeout_s},
                              name="reset-supervisor", daemon=True)
        th.start()
        self.supervisor = sup
        self.reset_timeout_s = 1.5 * reset_cfg.max_duration_s() + 10.0
        try:
            yield
        finally:
            sup.stop_event.set()
            th.join(10)
            sup.close()

    def reset(self, pose: dict[str, float]):
        try:
            return self.ctl.reset(timeout_s=self.reset_timeout_s, **pose)
        except DriverGone:
            raise
        except RuntimeError as e:
            if self.supervisor is not None:  # the supervisor stopped the rig and says why
                raise RigError(str(e)) from None
            if "unsupported" not in str(e) or not self.cfg.operator_resets:
                raise
        # a rig without a reset procedure: the operator places the robot
        input(f"place the robot at x={pose['x']:.2f} y={pose['y']:.2f} yaw={pose['yaw']:.2f}, then press Enter ")
        return self.ctl.next_state()

    def collect_random(self, n: int, name: str, seed: int | None = None) -> Path:
        """``n`` random rollouts recorded to ``rec_dir/name.mcap`` (``seed``: the policy's,
        default the config's)."""
        path = self.rec_dir / f"{name}.mcap"
        pol = SafeRandomPolicy(self.state_names, len(self.action_names), self.cfg.arena_radius_m,
                               hold_steps=self.cfg.random_hold_steps,
                               forward_fraction=self.cfg.random_forward_fraction,
                               seed=self.cfg.seed if seed is None else seed)
        rng = self.rng if seed is None else np.random.default_rng([seed, 2])
        with recording(self.rig.name, path, self.bus):
            for i in _progress(range(n), self.cfg, f"random rollouts → {path.name}"):
                yaw = float(rng.uniform(-np.pi, np.pi))
                self.episode(pol, self.cfg.rollout_steps, {"x": 0.0, "y": 0.0, "yaw": yaw})
                del i
        self.recordings.append(str(path))
        return path

    def time_limit_s(self, waypoints: np.ndarray) -> float:
        """Evaluation time limit (s) for a path: its length at ``time_limit_speed_mps``."""
        return path_length(waypoints) / self.cfg.time_limit_speed_mps

    def run_paths(self, policy_for, speed: float, paths: tuple[str, ...] | None = None,
                  path_scale: float | None = None) -> dict[str, dict[str, Any]]:
        """One episode per path (default: the config's), each until the robot passes the
        path's end or the time limit; returns per-path metrics and trajectories."""
        out = {}
        for name in paths or self.cfg.paths:
            wp = make_path(name, scale=path_scale or self.cfg.path_scale)
            cost = PathCost(wp, self.state_names)
            ref = fillet(wp, self.cfg.reference_corner_radius_m)  # what the controllers track
            limit_s = self.time_limit_s(wp)
            steps = int(np.ceil(limit_s / self.period_s - 1e-9))
            policy = policy_for(ref, self.task_cost(ref), speed)
            log = self.episode(policy, steps, path_start_pose(wp), stop_if=PathEnd(PathCost(wp, self.state_names)))
            states = np.array(log.states)
            m = evaluate_path_following(states, cost, period_s=self.period_s, time_limit_s=limit_s)
            m["time_limit_s"] = limit_s
            m["plan_ms_p50"] = float(np.percentile(log.plan_times_s, 50) * 1e3) if log.plan_times_s else 0.0
            m["plan_ms_p99"] = float(np.percentile(log.plan_times_s, 99) * 1e3) if log.plan_times_s else 0.0
            m["late_plans"] = log.late_plans  # realtime: steps that sent the shifted last plan instead
            m["unhealthy_states"] = log.unhealthy_states  # not ok: nothing planned, the driver node held the robot
            m["end"] = ("completed" if m["completed"] else self.last_end_reason
                        or ("time_limit" if len(log.actions) + log.unhealthy_states >= steps else "stopped"))
            m["xy"] = states[:, [self.state_names.index("x"), self.state_names.index("y")]].tolist()
            m["max_tilt_deg"] = max_tilt_deg(states, self.state_names)
            m["waypoints"] = wp.tolist()
            if isinstance(policy, MpcPolicy):
                m["samples"] = policy.planner.samples
                self.refit_samples(log, f"{name} at {speed:g}")
            out[name] = m
        return out

    def task_cost(self, waypoints) -> PathCost:
        """The path cost the planner optimizes (:func:`task_cost`)."""
        return task_cost(self.cfg, waypoints, self.state_names)

    def mpc_for(self, model):
        """The MPC on ``model`` for each path; on a wall-clock rig each one gets the sample
        count of the moment (:meth:`realtime_samples`, refitted after every MPC episode)."""
        self.realtime_samples(model)

        def make(wp, cost, speed):
            samples = None if self.planner_fit is None else self.planner_fit["current_samples"]
            return MpcPolicy(model, make_planner(self.cfg, speed, len(self.action_names), self.max_step, samples),
                             cost, delay_steps=self.command_delay)
        return make

    def refit_samples(self, log: EpisodeLog, label: str) -> int | None:
        """Wall-clock rigs: the sample count refitted from the episode just run (its plan
        times and late plans, :func:`refit_samples`), for the next one; a change is logged and
        recorded in ``planner_fit["refits"]`` (the report's ``planner_realtime``). None
        on lockstep rigs, and when ``realtime_refit`` is off."""
        cfg, fit = self.cfg, self.planner_fit
        if fit is None or not cfg.realtime_refit:
            return None
        n, rec = refit_samples(fit["current_samples"], log.plan_times_s, log.late_plans,
                               len(log.actions), max_samples=cfg.samples, min_samples=cfg.realtime_min_samples,
                               budget_s=cfg.realtime_plan_budget * self.period_s,
                               deadline_s=REALTIME_DEADLINE_FRAC * self.period_s,
                               max_late_share=cfg.realtime_max_late_share)
        if n != fit["current_samples"]:
            rec["after"] = label
            fit["refits"].append(rec)
            fit["current_samples"] = n
            _log(cfg, f"planner samples {rec['from']} → {n} after {label}: plan p50 {rec['plan_ms_p50']:.0f} ms, "
                      f"p{100 * (1 - cfg.realtime_max_late_share):.0f} {rec['plan_ms_tail']:.0f} ms, "
                      f"late {rec['late_share']:.0%} ({rec['reason']})")
        return n

    def realtime_samples(self, model, make=None, cost=None) -> int | None:
        """Wall-clock rigs: the planner's sample count fitted to the control period on this
        machine, measured once with ``model`` from the robot's current state
        (:func:`fit_planner_samples`; ``self.planner_fit`` records it for the report), then
        refitted after every MPC episode (:meth:`refit_samples`): the count of the moment.
        ``make(n)`` / ``cost``: the planner with ``n`` samples and its cost (default: the
        path-tracking planner on a straight path at the top speed). None on lockstep rigs
        (the configured samples)."""
        if self.pacing is not None and self.pacing.answered:
            return None
        if self.planner_fit is None:
            cfg = self.cfg
            x = np.asarray(self.ctl.next_state().state)
            if make is None:
                cost = PathCost(make_path("straight", scale=cfg.path_scale), self.state_names)
                speed, n_act = max(cfg.speeds.values()), len(self.action_names)
                make = partial(make_planner, cfg, speed, n_act, self.max_step)
            budget = cfg.realtime_plan_budget * self.period_s
            n, trials = fit_planner_samples(make, cfg.samples, model.predict, cost, x, budget,
                                            cfg.realtime_min_samples)
            self.planner_fit = {"samples": n, "configured_samples": cfg.samples, "budget_ms": budget * 1e3,
                                "torch_threads": torch.get_num_threads(), "trials": trials,
                                # refitted after every MPC episode (refit_samples): the count now, its changes
                                "current_samples": n, "refits": []}
            _log(cfg, f"planner on the wall clock: {n} samples (median plan within {budget * 1e3:.0f} ms: {trials})")
        return self.planner_fit["current_samples"]

    def baseline_for(self, params: dict[str, float] | None = None):
        """Differential drive with ``params`` (gains; default: the untuned defaults scaled to the speed)."""
        def make(wp, cost, speed):
            p = params or default_baseline_params(speed)
            tip = math.radians(self.cfg.tip_threshold_deg) if self.cfg.tip_weight > 0 else None
            return BaselinePolicy(DifferentialDriveController(wp, self.state_names, max_action=speed,
                                                              tip_threshold_rad=tip, **p))
        return make

    def tune_baseline(self, speed: float) -> dict[str, Any]:
        """Random search over the differential-drive gains at ``speed`` on the tuning paths;
        candidates are ranked like the evaluation (completions, then cost per metre)."""
        cfg = self.cfg
        cands = baseline_candidates(cfg.baseline_candidates, speed, cfg.seed)
        scored = []
        for p in _progress(cands, cfg, f"tuning differential drive at {speed:.2f}"):
            res = self.run_paths(self.baseline_for(p), speed, paths=cfg.tune_paths, path_scale=cfg.tune_path_scale)
            scored.append({"params": p, **summarize_paths(res)})
        best = min(scored, key=rank_key)
        return {"best_params": best["params"], "best": {k: best[k] for k in ("completed", "cost", "cost_per_m")},
                "default": {k: scored[0][k] for k in ("completed", "cost", "cost_per_m")}, "candidates": scored}

    def compare(self, speed: float, model, baseline_params: dict[str, float] | None) -> dict[str, Any]:
        """MPC and the differential drive on the evaluation paths at ``speed``."""
        mpc = self.run_paths(self.mpc_for(model), speed)
        dd = self.run_paths(self.baseline_for(baseline_params), speed)
        sm, sd = summarize_paths(mpc), summarize_paths(dd)
        return {
            "speed": speed,
            "mpc_cost": sm["cost"], "differential_drive_cost": sd["cost"],
            "mpc_completed": sm["completed"], "differential_drive_completed": sd["completed"],
            "mpc_cost_per_m": sm["cost_per_m"], "differential_drive_cost_per_m": sd["cost_per_m"],
            "mpc_better": rank_key(sm) < rank_key(sd),
            "paths": {p: {"mpc": mpc[p], "differential_drive": dd[p]} for p in mpc},
        }

    # -- training --------------------------------------------------------------------------
    def train(self, model, eps: list[Episode], epochs: int, seed: int | None = None) -> dict[str, float]:
        """Fit ``model``; ``seed`` draws the split from that seed's own generator (see seed_split_rngs)."""
        rng = self.split_rng if seed is None else self.seed_split_rngs.setdefault(
            seed, np.random.default_rng([seed, 2]))
        return fit_episodes(model, eps, epochs, self.cfg.batch_size, self.cfg.val_fraction, rng,
                            self.val_assigned, horizon=self.cfg.horizon, progress=self.cfg.progress)

    # -- everything -------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        torch.manual_seed(cfg.seed)
        t0 = time.monotonic()
        report: dict[str, Any] = {"config": _jsonable(asdict(cfg)), "rig": self.rig.name}
        try:
            return self._run(report, t0)
        except (TimeoutError, DriverGone) as e:
            raise RigError(f"{e} (driver log: {self.out / 'logs' / 'driver.log'})") from None

    def _run(self, report: dict[str, Any], t0: float) -> dict[str, Any]:
        cfg = self.cfg
        try:
            self._check_episode_timeout(require_reset(self.rig, cfg.robot, cfg.operator_resets))
        except ResetUnavailable:
            pass  # session() says so
        with self.session():
            _log(cfg, f"collecting {cfg.random_rollouts} random rollouts x {cfg.rollout_steps} steps")
            rand_path = self.collect_random(cfg.random_rollouts, "000-random")
            random_eps = episodes_from_mcap(rand_path, cfg.robot)
            data = list(random_eps)
            report["random_data"] = speed_coverage(random_eps, self.state_names)
            _log(cfg, f"{len(data)} episodes, {sum(len(e) for e in data)} transitions from {rand_path.name}")

            model = make_model(cfg, self.state_names, self.action_names)
            training = [{"iteration": 0, "episodes": len(data), **self.train(model, data, cfg.epochs)}]
            _log(cfg, f"trained: {training[-1]}")

            for it in range(1, cfg.iterations + 1):
                path = self.rec_dir / f"{it:03d}-mpc.mcap"
                with recording(self.rig.name, path, self.bus):
                    for speed in cfg.speeds.values():
                        self.run_paths(self.mpc_for(model), speed)
                self.recordings.append(str(path))
                new = episodes_from_mcap(path, cfg.robot)
                data += new
                training.append({"iteration": it, "episodes": len(data),
                                 **self.train(model, data, cfg.retrain_epochs)})
                _log(cfg, f"iteration {it}: +{len(new)} on-policy episodes, {training[-1]}")
            model.save(self.out / "model.pt")

            results: dict[str, Any] = {}
            tuning: dict[str, Any] = {}
            tune_path = self.rec_dir / "800-tune-baseline.mcap"
            with recording(self.rig.name, tune_path, self.bus):
                for label, speed in cfg.speeds.items():
                    _log(cfg, f"tuning the differential drive at {label} ({speed:.2f}): "
                              f"{cfg.baseline_candidates} candidates on {list(cfg.tune_paths)}")
                    tuning[label] = self.tune_baseline(speed)
                    _log(cfg, f"{label}: default {tuning[label]['default']} → best {tuning[label]['best']}")
            self.recordings.append(str(tune_path))

            eval_path = self.rec_dir / "900-eval.mcap"
            with recording(self.rig.name, eval_path, self.bus):
                for label, speed in cfg.speeds.items():
                    _log(cfg, f"evaluating MPC and differential drive at {label} ({speed:.2f})")
                    results[label] = r = self.compare(speed, model, tuning[label]["best_params"])
                    _log(cfg, f"{label}: completed mpc {r['mpc_completed']}/{len(r['paths'])} "
                              f"dd {r['differential_drive_completed']}/{len(r['paths'])}; cost/m mpc "
                              f"{r['mpc_cost_per_m']:.1f} dd {r['differential_drive_cost_per_m']:.1f}")
            self.recordings.append(str(eval_path))

            if cfg.experiments:
                from hilstack.learning.experiments import run_experiments

                report.update(run_experiments(self))

        if "table_3_2" in cfg.experiments:
            from hilstack.learning.experiments import table_3_2

            high = cfg.speeds.get("high_speed", max(cfg.speeds.values()))
            report["table_3_2"] = table_3_2(self, cfg.seeds, cfg.terrains, cfg.terrain_rollouts, high)

        report["baseline_tuning"] = {
            "method": "random search (Latin hypercube, scipy.stats.qmc) over "
                      + ", ".join(f"{k} in [{lo}, {hi}]{'·speed' if sc else ''}" for k, (lo, hi, sc) in BASELINE_SEARCH.items())
                      + "; the untuned default is candidate 0; ranked by paths completed, then cost per metre",
            "candidates": cfg.baseline_candidates,
            "tuning_paths": [f"{p} (scale {cfg.tune_path_scale})" for p in cfg.tune_paths],
            "best_params": {k: v["best_params"] for k, v in tuning.items()},
            "per_speed": tuning,
        }
        report.update(results)
        report["training"] = training
        report["recordings"] = self.recordings
        report["model"] = str(self.out / "model.pt")
        if self.planner_fit is not None:
            report["planner_realtime"] = self.planner_fit
        if self.supervisor is not None:
            report["resets"] = self.supervisor.report()
        report["wall_s"] = time.monotonic() - t0
        return report


def _or_stop(a, b):
    if a is None:
        return b
    return lambda state: bool(a(state)) or bool(b(state))


def _progress(it, cfg: MbrlConfig, desc: str):
    if not cfg.progress:
        return it
    return progress(it, desc=desc, file=sys.stderr)  # plain lines when stderr is a log file


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    return o
