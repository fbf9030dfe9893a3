"""The model-based RL loop (Nagabandi et al., Alg. 1) with every node on the bus.

    random data (safe random policy) → train dynamics → MPC collects on-policy rollouts
    → aggregate → retrain (warm start) → ... → evaluate MPC vs the differential-drive
    baseline on the paths at a low and a high commanded speed.

The rig is real nodes over a real Zenoh session: the driver bridge runs in its own
process (``hil up <rig>``), the controller node (random policy, MPC, baseline) and the
recorder run here. Training data is read back from the MCAP recordings, the same path a
lab takes with recordings from a real robot. On a sim rig with ``pace: lockstep`` the
simulation advances when the controller answers, so the loop runs faster than real time;
on a real or emulated rig the same code runs on the wall clock (``realtime=True``).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bus import keys
from bus.recording import Recorder
from bus.schemas import ResetTransition, decode
from configs.schema import BusConfig, load_rig
from control.baselines import DifferentialDriveController
from control.controller_node import ControllerNode, EpisodeLog
from control.costs import PathCost, evaluate_path_following
from control.paths import make_path
from control.planners import CEM, PDDM, RandomShooting
from control.policies import BaselinePolicy, MpcPolicy, SafeRandomPolicy
from control.reset.config import ResetConfig, ResetUnavailable, require_reset
from control.reset.supervisor import ResetSupervisor
from learning.datasets import Episode
from learning.dynamics import EnsembleDynamics
from learning.frames import BodyFrameDynamics
from learning.recordings import episodes_from_mcap


class RigError(RuntimeError):
    """The rig stopped answering (driver node crashed or link lost); the robot's own
    watchdogs have stopped it. Recordings written so far are complete up to that point."""


@dataclass
class MbrlConfig:
    rig: str = "roach_sim"
    robot: str = "roach"
    seed: int = 0
    # data collection (thesis: 200 rollouts x 50 steps at 10 Hz per terrain)
    random_rollouts: int = 200
    rollout_steps: int = 50
    arena_radius_m: float = 3.0
    # model (thesis: 2x500 ReLU MLP, Adam 1e-3)
    hidden: tuple[int, ...] = (500, 500)
    ensemble: int = 1
    epochs: int = 60
    retrain_epochs: int = 20
    batch_size: int = 512
    input_noise_std: float = 0.01
    val_fraction: float = 0.1
    #: learn in the robot's body frame (translation and heading invariance; learning.frames)
    body_frame: bool = True
    #: otherwise: inputs the model ignores (planar translation invariance)
    invariant_inputs: tuple[str, ...] = ("x", "y")
    # planner (thesis: random shooting, N=500, H=4; CEM by default here: see docs/mbrl.md)
    planner: str = "cem"
    samples: int = 500
    horizon: int = 4
    # MBRL iterations: on-policy MPC rollouts on the paths, aggregated, warm-start retrain
    iterations: int = 1
    # tasks
    paths: tuple[str, ...] = ("straight", "left", "right", "zigzag", "figure8")
    path_scale: float = 1.5
    speeds: dict[str, float] = field(default_factory=lambda: {"low_speed": 0.5, "high_speed": 1.0})
    eval_steps: int = 100
    # Table 3.1: MPC cost vs amount of random data (subsets of the random rollouts)
    data_sizes: tuple[int, ...] = ()
    progress: bool = True
    #: how long to wait for the driver node to come up (emulator start, radio link)
    rig_timeout_s: float = 60.0
    #: real rigs: when the driver cannot reset itself, ask an operator on the terminal
    operator_resets: bool = False

    @classmethod
    def quick(cls, **kw: Any) -> MbrlConfig:
        base = dict(random_rollouts=60, epochs=40, retrain_epochs=10, eval_steps=80, data_sizes=(15, 60))
        base.update(kw)
        return cls(**base)


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
        [sys.executable, "-m", "tools.cli", "up", rig, "--endpoint", bus.endpoint],
        stdout=err,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"},
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
    """Episode end for path following: the robot has travelled 3/4 of the path
    length (closed paths pass their end point half way) and passed the final waypoint."""

    def __init__(self, waypoints: np.ndarray, state_names: list[str]):
        self.wp = np.asarray(waypoints)
        self.ix, self.iy = state_names.index("x"), state_names.index("y")
        self.min_travel = 0.75 * float(np.linalg.norm(np.diff(self.wp, axis=0), axis=1).sum())
        self.travelled = 0.0
        self.last: np.ndarray | None = None

    def __call__(self, state: np.ndarray) -> bool:
        p = np.array([state[self.ix], state[self.iy]])
        if self.last is not None:
            self.travelled += float(np.linalg.norm(p - self.last))
        self.last = p
        return self.travelled > self.min_travel and past_end(p, self.wp)


def past_end(p_xy: np.ndarray, waypoints: np.ndarray, tol_m: float = 0.05) -> bool:
    """True once the robot has passed the end of the path (beyond the last waypoint
    along the last segment, or within ``tol_m`` of it): the episode is over."""
    a, b = waypoints[-2], waypoints[-1]
    d = b - a
    along = float((p_xy - a) @ d / max(float(d @ d), 1e-12))
    return along >= 1.0 or float(np.linalg.norm(p_xy - b)) < tol_m


# ---------------------------------------------------------------------------- model
def make_model(cfg: MbrlConfig, state_names: list[str], action_names: list[str]):
    model = EnsembleDynamics(
        len(state_names),
        len(action_names),
        ensemble=cfg.ensemble,
        hidden=cfg.hidden,
        input_noise_std=cfg.input_noise_std,
        state_names=state_names,
        action_names=action_names,
        seed=cfg.seed,
    )
    if cfg.body_frame:
        return BodyFrameDynamics(model, state_names)
    ignore = [state_names.index(n) for n in cfg.invariant_inputs if n in state_names]
    if ignore:
        model.ignore_inputs(ignore)
    return model


def split_episodes(eps: list[Episode], val_fraction: float, seed: int) -> tuple[list[Episode], list[Episode]]:
    rng = np.random.default_rng(seed)
    idx = rng.permutation(len(eps))
    n_val = max(1, int(round(val_fraction * len(eps)))) if len(eps) > 1 else 0
    return [eps[i] for i in idx[n_val:]], [eps[i] for i in idx[:n_val]]


def make_planner(cfg: MbrlConfig, speed: float, action_dim: int):
    kw = dict(action_low=-speed, action_high=speed, horizon=cfg.horizon, samples=cfg.samples,
              seed=cfg.seed, action_dim=action_dim)
    if cfg.planner == "random_shooting":
        return RandomShooting(**kw)
    if cfg.planner == "cem":
        return CEM(**kw, iterations=3)
    if cfg.planner == "pddm":
        return PDDM(**kw)
    raise ValueError(f"unknown planner {cfg.planner!r}: random_shooting | cem | pddm")


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
        self.supervisor: ResetSupervisor | None = None
        self.reset_timeout_s = 10.0

    # -- episodes over the bus ------------------------------------------------------------
    def episode(self, policy: Any, steps: int, pose: dict[str, float], stop_if=None) -> EpisodeLog:
        """Reset (the sim puts the robot at ``pose``; a real robot is placed by an operator)
        and run one episode: lockstep on sim rigs, on the wall clock otherwise."""
        first = self.reset(pose)
        if self.supervisor is not None:
            self._transitions.drain()  # transitions of the reset just done
        if hasattr(policy, "reset"):
            policy.reset()
        if self.supervisor is not None:  # the supervisor's detectors end episodes too
            stop_if = _or_stop(stop_if, self._episode_ended)
        if self.rig.pace == "lockstep":
            return self.ctl.run_lockstep(policy, steps, first, stop_if=stop_if)
        return self.ctl.run_realtime(policy, steps, stop_if=stop_if)

    def _episode_ended(self, state) -> bool:
        """The reset supervisor's detectors ended the episode (arena left, timeout...)."""
        ended = False
        for _, p in self._transitions.drain():
            t = decode(p, ResetTransition)
            # "request": the end of an episode this loop asked for itself (an earlier one)
            ended |= t.dest == "episode_end" and t.reason != "request"
        return ended

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
        except RuntimeError as e:
            if self.supervisor is not None:  # the supervisor stopped the rig and says why
                raise RigError(str(e)) from None
            if "unsupported" not in str(e) or not self.cfg.operator_resets:
                raise
        # a rig without a reset procedure: the operator places the robot
        input(f"place the robot at x={pose['x']:.2f} y={pose['y']:.2f} yaw={pose['yaw']:.2f}, then press Enter ")
        return self.ctl.next_state()

    def collect_random(self, n: int, name: str) -> Path:
        path = self.rec_dir / f"{name}.mcap"
        pol = SafeRandomPolicy(self.state_names, len(self.action_names), self.cfg.arena_radius_m,
                               seed=self.cfg.seed)
        with recording(self.rig.name, path, self.bus):
            for i in _progress(range(n), self.cfg, f"random rollouts → {path.name}"):
                yaw = float(self.rng.uniform(-np.pi, np.pi))
                self.episode(pol, self.cfg.rollout_steps, {"x": 0.0, "y": 0.0, "yaw": yaw})
                del i
        self.recordings.append(str(path))
        return path

    def run_paths(self, policy_for, speed: float, steps: int) -> dict[str, dict[str, Any]]:
        """One episode per path; returns per-path metrics and trajectories."""
        out = {}
        for name in self.cfg.paths:
            wp = make_path(name, scale=self.cfg.path_scale)
            cost = PathCost(wp, self.state_names)
            log = self.episode(policy_for(wp, cost, speed), steps, path_start_pose(wp),
                               stop_if=PathEnd(wp, self.state_names))
            states = np.array(log.states)
            m = evaluate_path_following(states, cost)
            m["plan_ms_p50"] = float(np.percentile(log.plan_times_s, 50) * 1e3) if log.plan_times_s else 0.0
            m["plan_ms_p99"] = float(np.percentile(log.plan_times_s, 99) * 1e3) if log.plan_times_s else 0.0
            m["xy"] = states[:, [self.state_names.index("x"), self.state_names.index("y")]].tolist()
            m["waypoints"] = wp.tolist()
            out[name] = m
        return out

    def mpc_for(self, model):
        def make(wp, cost, speed):
            return MpcPolicy(model, make_planner(self.cfg, speed, len(self.action_names)), cost)
        return make

    @staticmethod
    def baseline_for(state_names):
        def make(wp, cost, speed):
            return BaselinePolicy(
                DifferentialDriveController(wp, state_names, omega_nom=0.7 * speed, d_max=0.4 * speed)
            )
        return make

    # -- training --------------------------------------------------------------------------
    def train(self, model, eps: list[Episode], epochs: int) -> dict[str, float]:
        train, val = split_episodes(eps, self.cfg.val_fraction, self.cfg.seed)
        hist = model.fit(train, epochs=epochs, batch_size=self.cfg.batch_size, val=val or None,
                         horizon=self.cfg.horizon, progress=self.cfg.progress)
        last = hist[-1] if hist else {}
        return {k: float(v) for k, v in last.items() if isinstance(v, (int, float))}

    # -- everything -------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        torch.manual_seed(cfg.seed)
        t0 = time.monotonic()
        report: dict[str, Any] = {"config": _jsonable(asdict(cfg)), "rig": self.rig.name}
        try:
            return self._run(report, t0)
        except TimeoutError as e:
            raise RigError(f"{e} (driver log: {self.out / 'logs' / 'driver.log'})") from None

    def _run(self, report: dict[str, Any], t0: float) -> dict[str, Any]:
        cfg = self.cfg
        try:  # refuse before anything starts when nothing can reset the robot
            reset_cfg = require_reset(self.rig, cfg.robot, cfg.operator_resets)
        except ResetUnavailable as e:
            raise RigError(str(e)) from None
        with rig_processes(self.rig.source or self.rig.name, self.bus, self.out / "logs"), \
                ControllerNode(self.rig.name, cfg.robot, self.bus, name="mbrl-controller",
                               handle_signals=False, state_timeout_s=20.0) as ctl, \
                self._supervised(reset_cfg):
            self.ctl = ctl
            self._transitions = ctl.subscribe(keys.reset_transition(self.rig.name), ResetTransition,
                                              latest=False, capacity=256)
            spec = ctl.wait_ready(timeout_s=cfg.rig_timeout_s)
            self.state_names = list(spec["state"]["names"])
            self.action_names = list(spec["action"]["names"])

            _log(cfg, f"collecting {cfg.random_rollouts} random rollouts x {cfg.rollout_steps} steps")
            rand_path = self.collect_random(cfg.random_rollouts, "000-random")
            random_eps = episodes_from_mcap(rand_path, cfg.robot)
            data = list(random_eps)
            _log(cfg, f"{len(data)} episodes, {sum(len(e) for e in data)} transitions from {rand_path.name}")

            model = make_model(cfg, self.state_names, self.action_names)
            training = [{"iteration": 0, "episodes": len(data), **self.train(model, data, cfg.epochs)}]
            _log(cfg, f"trained: {training[-1]}")

            for it in range(1, cfg.iterations + 1):
                path = self.rec_dir / f"{it:03d}-mpc.mcap"
                with recording(self.rig.name, path, self.bus):
                    for speed in cfg.speeds.values():
                        self.run_paths(self.mpc_for(model), speed, cfg.eval_steps)
                self.recordings.append(str(path))
                new = episodes_from_mcap(path, cfg.robot)
                data += new
                training.append({"iteration": it, "episodes": len(data),
                                 **self.train(model, data, cfg.retrain_epochs)})
                _log(cfg, f"iteration {it}: +{len(new)} on-policy episodes, {training[-1]}")
            model.save(self.out / "model.pt")

            results: dict[str, Any] = {}
            eval_path = self.rec_dir / "900-eval.mcap"
            with recording(self.rig.name, eval_path, self.bus):
                for label, speed in cfg.speeds.items():
                    _log(cfg, f"evaluating MPC and differential drive at {label} ({speed:.2f})")
                    mpc = self.run_paths(self.mpc_for(model), speed, cfg.eval_steps)
                    dd = self.run_paths(self.baseline_for(self.state_names), speed, cfg.eval_steps)
                    results[label] = {
                        "speed": speed,
                        "mpc_cost": float(np.mean([m["cost"] for m in mpc.values()])),
                        "differential_drive_cost": float(np.mean([m["cost"] for m in dd.values()])),
                        "paths": {p: {"mpc": mpc[p], "differential_drive": dd[p]} for p in cfg.paths},
                    }
                    _log(cfg, f"{label}: mpc {results[label]['mpc_cost']:.1f} "
                              f"vs differential drive {results[label]['differential_drive_cost']:.1f}")
            self.recordings.append(str(eval_path))

            data_curve = []
            for n in cfg.data_sizes:
                n = min(n, len(random_eps))
                m = make_model(cfg, self.state_names, self.action_names)
                self.train(m, random_eps[:n], cfg.epochs)
                speed = cfg.speeds.get("high_speed", max(cfg.speeds.values()))
                r = self.run_paths(self.mpc_for(m), speed, cfg.eval_steps)
                data_curve.append({"random_rollouts": n, "mpc_cost": float(np.mean([x["cost"] for x in r.values()]))})
                _log(cfg, f"data size {n} rollouts: mpc cost {data_curve[-1]['mpc_cost']:.1f}")

        report.update(results)
        report["training"] = training
        report["data_size_curve"] = data_curve
        report["recordings"] = self.recordings
        report["model"] = str(self.out / "model.pt")
        if self.supervisor is not None:
            sup = self.supervisor
            report["resets"] = {**sup.stats, "mean_duration_s": float(np.mean(sup.durations_s)) if sup.durations_s else 0.0}
        report["wall_s"] = time.monotonic() - t0
        return report


def _or_stop(a, b):
    if a is None:
        return b
    return lambda state: bool(a(state)) or bool(b(state))


def _progress(it, cfg: MbrlConfig, desc: str):
    if not cfg.progress:
        return it
    from tqdm import tqdm

    return tqdm(it, desc=desc, file=sys.stderr, leave=False)


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {k: _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    return o
