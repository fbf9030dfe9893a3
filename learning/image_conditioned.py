"""The image-conditioned dynamics model on terrains (thesis ch. 3.3, Table 3.2; issue 29).

The robot's camera sees the ground ahead; a fixed image encoder
(:class:`hilstack.perception.terrain_features.RandomConvEncoder`) turns each image into a few
numbers, and the dynamics model takes them beside the state and the action:
f(s, a, I) = f([s, φ(I)], a). The model, its training and the planner are the roach's MBRL
ones (:func:`hilstack.learning.mbrl.make_model`, :func:`~hilstack.learning.mbrl.fit_episodes`,
:func:`~hilstack.learning.mbrl.make_planner`, :func:`~hilstack.learning.mbrl.task_cost`,
:class:`hilstack.control.policies.MpcPolicy`); the features join the state as channels the
model reads but does not predict (:class:`HeldInputs`): during a plan they stay at the value
of the image the robot sees now, as the thesis conditions every step of a plan on the current
image (a future image cannot be known).

The experiment (:func:`run_seed` per seed and :func:`aggregate`, run by ``hil demo roach --part
terrain``, tools/demo_terrain.py): per seed,
random rollouts on every terrain with the camera on (the same data for every model), then

* a **per-terrain** model for each terrain, trained on that terrain's data only;
* the **all-data** model, trained on every terrain's data, without images;
* the **image-conditioned** model, trained on the same data with the image features;
* a control: the image-conditioned model fed the features of **another terrain's images**
  (recorded on the next terrain of the list), which says whether the model uses the images;

each driving the same paths on every terrain with the same planner; path cost per metre and
completions, mean ± std over seeds. It runs in this process on the sim backend (made through
the registry, like the adaptation demo's), not over the bus: the bus cannot yet carry images
into the controller node's state, and the lockstep loop is the same either way.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from hilstack.configs.presets import Presets
from hilstack.control.costs import PathCost, evaluate_path_following, rank_key, summarize_paths
from hilstack.control.paths import fillet, make_path, path_length
from hilstack.control.policies import MpcPolicy, SafeRandomPolicy
from hilstack.control.policy_api import Resettable
from hilstack.learning.datasets import Episode
from hilstack.learning.dynamics import h_step_error, h_step_windows
from hilstack.learning.frames import ensemble_of
from hilstack.learning.mbrl import (
    MbrlConfig,
    PathEnd,
    fit_episodes,
    make_model,
    make_planner,
    path_start_pose,
    task_cost,
)

__all__ = ["FeatureStream", "HeldInputs", "TerrainConfig", "TerrainSim", "aggregate", "feature_transform",
           "run_seed", "running_mean", "with_features"]


# ---------------------------------------------------------------------------- the model
class HeldInputs:
    """A dynamics model whose input holds channels it does not predict (image features).

    ``model`` (an :class:`~hilstack.learning.dynamics.EnsembleDynamics` or its body-frame
    wrapper, made by :func:`~hilstack.learning.mbrl.make_model` over ``state_names``, the
    held channels included) learns every channel; it is trained on one-step transitions in
    which the held channels do not change (their target delta is 0), and :meth:`predict`
    copies them from the input, so over a plan they stay at their value at its start.
    """

    def __init__(self, model, state_names: Sequence[str], held: Sequence[str]):
        self.model = model
        self.state_names = list(state_names)
        missing = [n for n in held if n not in self.state_names]
        if missing:
            raise ValueError(f"held channels {missing} are not in the state names")
        self.held = [self.state_names.index(n) for n in held]
        self.free = [i for i in range(len(self.state_names)) if i not in self.held]

    @property
    def history(self) -> list[dict]:
        return self.model.history

    def held_episodes(self, episodes: Sequence[Episode]) -> list[Episode]:
        """Each transition as a one-step episode whose next state keeps the held channels
        of the state before it (what the model is asked: the next state seen from this image)."""
        out = []
        for ep in episodes:
            nxt = ep.states[1:].copy()
            nxt[:, self.held] = ep.states[:-1, self.held]
            for t in range(len(ep)):
                out.append(Episode(np.stack([ep.states[t], nxt[t]]), ep.actions[t:t + 1], name=f"{ep.name}#{t}"))
        return out

    def fit(self, episodes: Sequence[Episode], val: Sequence[Episode] | None = None, **kw) -> list[dict]:
        """Fit on :meth:`held_episodes`; with ``val``, the last history entry gets the open-loop
        ``horizon``-step error over the free channels with the held ones kept at each window's
        start (the planner's situation): ``val_h`` (normalized by the training states' std) and
        ``val_h_raw``."""
        horizon = int(kw.pop("horizon", 4))
        hist = self.model.fit(self.held_episodes(episodes), val=self.held_episodes(val) if val else None,
                              horizon=1, **kw)
        if val and hist:
            for k in ("val_h_body", "val_h_xy_mse_m2"):  # the inner model's, over one-step windows
                hist[-1].pop(k, None)
            hist[-1].update(self.open_loop_error(episodes, val, horizon))
        return hist

    def open_loop_error(self, train: Sequence[Episode], val: Sequence[Episode], horizon: int) -> dict[str, float]:
        """``val_h``/``val_h_raw`` of :meth:`fit` (thesis Eqn 2.2 over the free channels)."""
        try:
            start, actions, truth = h_step_windows(val, horizon)
        except ValueError:
            return {}
        truth = truth.copy()
        truth[:, :, self.held] = start[:, None, self.held]  # held: no error by construction
        st = np.concatenate([e.states for e in train]).astype(np.float32)
        std = torch.as_tensor(st.std(0)).clamp_min(1e-6)
        std[self.held] = float("inf")  # a held channel adds nothing to the normalized error
        n, r = h_step_error(self, start, actions, truth, state_std=std)
        return {"val_h": n, "val_h_raw": r, "horizon": horizon}

    def predict(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        nxt = self.model.predict(state, action)
        ref = state if state.dim() == nxt.dim() else state.unsqueeze(0).expand_as(nxt)
        nxt[..., self.held] = ref[..., self.held]
        return nxt

    def input_width(self) -> int:
        """Inputs of the network's first layer: state (with the held channels) + action."""
        return int(ensemble_of(self.model).weights[0].shape[1])

    def save(self, path: str | Path) -> None:
        self.model.save(path)


def running_mean(f: np.ndarray, k: int) -> np.ndarray:
    """``f [T, F]`` averaged over its last ``k`` rows at every step (fewer at the start)."""
    f = np.asarray(f, dtype=np.float64)
    c = np.cumsum(np.vstack([np.zeros((1, f.shape[1])), f]), axis=0)
    t = np.arange(1, len(f) + 1)
    lo = np.maximum(0, t - int(k))
    return ((c[t] - c[lo]) / (t - lo)[:, None]).astype(np.float32)


def feature_transform(cfg: TerrainConfig, train: Sequence[Episode]):
    """What the model reads of the raw encoder features (``[N, F] → [N, F']``): the PCA
    whitening fitted on ``train``'s features (averaged over ``cfg.average_frames``) when
    ``cfg.whiten_min_share`` > 0, otherwise the features as they are."""
    if cfg.whiten_min_share <= 0:
        return lambda f: np.asarray(f, dtype=np.float32)
    from hilstack.perception.terrain_features import FeatureWhitening

    return FeatureWhitening(np.concatenate([running_mean(e.meta["features"], cfg.average_frames) for e in train]),
                            min_share=cfg.whiten_min_share)


def transformed(ep: Episode, transform, k: int) -> Episode:
    """``ep`` with ``meta["features"]`` averaged over the last ``k`` images and transformed."""
    return Episode(ep.states, ep.actions, ep.times, name=ep.name,
                   meta={**ep.meta, "features": transform(running_mean(ep.meta["features"], k))})


class FeatureStream:
    """The features the image-conditioned model reads at each step of an episode: ``encode``
    of the current image, averaged with the episode's previous ``k − 1`` and transformed
    (:func:`feature_transform`); :meth:`reset` at every episode start."""

    def __init__(self, encode: Callable[[np.ndarray], np.ndarray], transform, k: int = 1):
        self.encode, self.transform, self.k = encode, transform, int(k)
        self.history: list[np.ndarray] = []

    def reset(self) -> None:
        self.history = []

    def __call__(self, image: np.ndarray) -> np.ndarray:
        self.history = [*self.history[-(self.k - 1):], np.asarray(self.encode(image), np.float32)] if self.k > 1 \
            else [np.asarray(self.encode(image), np.float32)]
        return self.transform(np.mean(self.history, axis=0)[None])[0]


def with_features(ep: Episode) -> Episode:
    """``ep`` with its image features (``meta["features"]``, ``[T+1, F]``) appended to the states."""
    f = ep.meta["features"]
    return Episode(np.concatenate([ep.states, f], axis=1), ep.actions, ep.times, name=ep.name,
                   meta={k: v for k, v in ep.meta.items() if k != "features"})


# ---------------------------------------------------------------------------- config
@dataclass
class TerrainConfig(Presets):
    """``hil demo roach --part terrain``: terrains, data, seeds; the model and planner are ``mbrl``'s."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        # --quick: <= 20 min on 2 shared cores (docs/mbrl.md gives the measured wall time)
        "quick": dict(rollouts_per_terrain=40, epochs=40, paths=("straight", "left")),
        # --full: the thesis' data size per terrain (200 rollouts x 50 steps, ~17 min of driving)
        "full": dict(rollouts_per_terrain=200, epochs=60, paths=("straight", "left", "right")),
    }

    robot: str = "velociroach"
    terrains: tuple[str, ...] = ("carpet", "styrofoam", "gravel", "turf")
    seeds: tuple[int, ...] = (0, 1, 2)
    rollouts_per_terrain: int = 100
    rollout_steps: int = 50
    #: further random rollouts per terrain no model trains on: each model's open-loop error there
    heldout_rollouts: int = 5
    epochs: int = 60
    # the camera and the encoder
    camera_px: int = 64
    features: int = 16
    encoder_seed: int = 0
    #: the model reads the features PCA-whitened (fitted on the training data), keeping the
    #: principal directions with at least this share of the variance (0: the raw features). The
    #: 16 features are near-collinear (3 directions carry > 99 %), so per-channel normalisation
    #: alone hands the network 16 copies of 3 signals (docs/mbrl.md, "Why it helped on one terrain")
    whiten_min_share: float = 0.01
    #: the features are averaged over the episode's last this many images (1: the current one,
    #: as the thesis); the robot's tilt moves the view and explains ~90 % of a terrain's feature spread
    average_frames: int = 1
    #: rough terrains' periodic map: half its period (m); 0.5 keeps rendering the heightfield at
    #: ~10 ms a frame (the backend's default 2.0 m: ~40 ms, measured); the map is endless either way
    terrain_half_size_m: float = 0.5
    # evaluation
    paths: tuple[str, ...] = ("straight", "left", "right")
    path_scale: float = 1.5
    speed: float = 1.0
    time_limit_speed_mps: float = 0.15
    threads: int = 1
    progress: bool = True
    #: the MBRL settings (model, training, planner, cost): the roach loop's defaults
    mbrl: MbrlConfig = field(default_factory=lambda: MbrlConfig(progress=False))

    def __post_init__(self) -> None:
        problems = []
        if len(self.terrains) < 2 or len(set(self.terrains)) != len(self.terrains):
            problems.append(f"terrains: at least two distinct terrains, got {list(self.terrains)}")
        if not self.seeds:
            problems.append("seeds: at least one")
        if self.rollouts_per_terrain < 2 or self.rollout_steps < 2:
            problems.append("rollouts_per_terrain and rollout_steps must be >= 2")
        if not 8 <= self.camera_px <= 256:
            problems.append(f"camera_px must be in [8, 256], got {self.camera_px}")
        if self.features < 1:
            problems.append(f"features must be >= 1, got {self.features}")
        if not (math.isfinite(self.whiten_min_share) and 0 <= self.whiten_min_share < 1):
            problems.append(f"whiten_min_share must be in [0, 1), got {self.whiten_min_share}")
        if self.average_frames < 1:
            problems.append(f"average_frames must be >= 1, got {self.average_frames}")
        if not (math.isfinite(self.speed) and 0 < self.speed <= 1):
            problems.append(f"speed must be in (0, 1], got {self.speed}")
        if problems:
            raise ValueError("TerrainConfig: " + "; ".join(problems))


def _log(cfg: TerrainConfig, msg: str) -> None:
    if cfg.progress:
        print(f"[terrain {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------- the sim
class TerrainSim:
    """The robot's sim backend (through the registry) with its camera on; the terrain is
    chosen per episode through the ``terrain`` perturbation (applied at the reset)."""

    def __init__(self, cfg: TerrainConfig, seed: int):
        from hilstack.drivers.base import perturbable
        from hilstack.drivers.registry import make_backend

        self.drv = make_backend(cfg.robot, "sim", sim={"camera_px": cfg.camera_px, "seed": seed,
                                                       "terrain_half_size_m": cfg.terrain_half_size_m})
        self.drv.configure()
        self.drv.activate()
        self.controls = perturbable(self.drv)
        if self.controls is None:
            raise ValueError(f"{cfg.robot}: its sim backend cannot change terrains (no perturbations)")
        spec = self.drv.spec
        self.state_names = list(spec.state.names)
        self.action_space = spec.action
        self.period_s = float(spec.period_s)
        self.max_step = spec.max_step_normalized()

    def start(self, terrain: str, pose: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """A new episode on ``terrain`` at ``pose``: (state, camera image)."""
        from hilstack.tasks.perturbations import PerturbationSettings

        self.controls.apply_perturbations(PerturbationSettings(terrain=terrain))
        self.drv.reset(**pose)
        return self._read()

    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        obs = self.drv.read()
        if "image" not in obs.extras:
            raise RuntimeError("the sim backend returned no camera image (params.sim.camera_px)")
        return obs.state.copy(), obs.extras["image"]

    def step(self, a_norm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply a normalized action: (applied action normalized, next state, its image)."""
        applied = self.drv.write(self.action_space.denormalize(np.asarray(a_norm, dtype=np.float64)))
        self.drv.tick()
        s, img = self._read()
        return self.action_space.normalize(applied).astype(np.float32), s, img

    def close(self) -> None:
        self.drv.deactivate()
        self.drv.cleanup()


def random_episodes(env: TerrainSim, terrain: str, encoder, cfg: TerrainConfig, seed: int,
                    keep_images: int = 0, n: int | None = None) -> tuple[list[Episode], list[np.ndarray]]:
    """``n`` (default ``cfg.rollouts_per_terrain``) random rollouts on ``terrain`` (the MBRL loop's safe random
    policy, its defaults), each image encoded (``meta["features"]``). Returns the episodes and
    up to ``keep_images`` images (for the report and the wrong-image control)."""
    m = cfg.mbrl
    pol = SafeRandomPolicy(env.state_names, len(env.action_space.names), m.arena_radius_m,
                           hold_steps=m.random_hold_steps, forward_fraction=m.random_forward_fraction, seed=seed)
    rng = np.random.default_rng([seed, 5])
    out, kept = [], []
    for i in range(cfg.rollouts_per_terrain if n is None else n):
        s, img = env.start(terrain, {"x": 0.0, "y": 0.0, "yaw": float(rng.uniform(-np.pi, np.pi))})
        if isinstance(pol, Resettable):
            pol.reset()
        states, actions, images = [s], [], [img]
        for _ in range(cfg.rollout_steps):
            a, s, img = env.step(pol(s))
            states.append(s)
            actions.append(a)
            images.append(img)
        imgs = np.stack(images)
        if len(kept) < keep_images:
            kept.extend(imgs[:: max(1, len(imgs) // 4)][: keep_images - len(kept)])
        out.append(Episode(np.array(states), np.array(actions), name=f"{terrain}#{i}",
                           meta={"terrain": terrain, "features": encoder.encode(imgs)}))
    return out, kept


# ---------------------------------------------------------------------------- evaluation
def drive_path(env: TerrainSim, terrain: str, policy, path: str, cfg: TerrainConfig,
               features: Callable[[np.ndarray], np.ndarray] | None) -> dict[str, Any]:
    """One episode on ``path`` on ``terrain`` until the robot passes its end or the time limit
    (as :meth:`hilstack.learning.mbrl.MbrlRun.run_paths`); ``features(image)``: the image
    features appended to the state the policy sees (None: the state alone)."""
    wp = make_path(path, scale=cfg.path_scale)
    names = env.state_names
    limit_s = path_length(wp) / cfg.time_limit_speed_mps
    steps = int(np.ceil(limit_s / env.period_s - 1e-9))
    end = PathEnd(PathCost(wp, names))
    s, img = env.start(terrain, path_start_pose(wp))
    policy.reset()
    if isinstance(features, Resettable):
        features.reset()
    states = [s]
    t_plan = []
    for _ in range(steps):
        x = s if features is None else np.concatenate([s, features(img)])
        t0 = time.perf_counter()
        a = policy(x)
        t_plan.append(time.perf_counter() - t0)
        _, s, img = env.step(a)
        states.append(s)
        if end(s):
            break
    m = evaluate_path_following(np.array(states), PathCost(wp, names), period_s=env.period_s, time_limit_s=limit_s)
    m["plan_ms_p50"] = float(np.percentile(t_plan, 50) * 1e3)
    m["xy"] = np.array(states)[:, [names.index("x"), names.index("y")]].tolist()
    return m


def _mpc(model, cfg: TerrainConfig, env: TerrainSim, state_names: list[str]):
    """The roach loop's MPC (planner, cost) for ``model`` over ``state_names``; a factory per path."""
    def make(wp):
        ref = fillet(wp, cfg.mbrl.reference_corner_radius_m)
        planner = make_planner(cfg.mbrl, cfg.speed, len(env.action_space.names), env.max_step)
        return MpcPolicy(model, planner, task_cost(cfg.mbrl, ref, state_names))
    return make


def _fit(cfg: TerrainConfig, seed: int, episodes: list[Episode], state_names: list[str], action_names: list[str],
         held: Sequence[str] = ()):
    """A fresh roach MBRL model (``make_model``, initialized from ``seed``) fitted by ``fit_episodes``."""
    m = dataclasses.replace(cfg.mbrl, seed=seed)
    model = make_model(m, state_names, action_names)
    if held:
        model = HeldInputs(model, state_names, held)
    info = fit_episodes(model, episodes, cfg.epochs, m.batch_size, m.val_fraction,
                        np.random.default_rng([seed, 1]), {}, horizon=m.horizon)
    return model, info


def h_step_xy_mse(model, episodes: Sequence[Episode], horizon: int) -> float:
    """Mean squared error [m²] of the position ``horizon`` steps ahead, open loop from every
    start of ``episodes`` with their logged actions (thesis Eqn 2.2's windows; channels 0, 1 are
    x, y; image features, if any, stay at the start's: :class:`HeldInputs`)."""
    start, actions, truth = h_step_windows(episodes, horizon, max_starts=None)
    with torch.inference_mode():
        x = torch.as_tensor(start)
        for h in range(horizon):
            x = model.predict(x, torch.as_tensor(actions[:, h])).mean(0)
    return float(((x.numpy()[:, :2] - truth[:, -1, :2]) ** 2).sum(-1).mean())


def mean_std(values) -> dict[str, Any]:
    v = [float(x) for x in values]
    return {"mean": float(np.mean(v)) if v else float("nan"),
            "std": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0, "n": len(v), "values": v}


ROWS = ("per-terrain", "all data, no images", "image-conditioned", "image-conditioned, another terrain's images")


def run_seed(cfg: TerrainConfig, seed: int, encoder) -> dict[str, Any]:
    """Data, the models and the evaluation matrix of one seed."""
    torch.manual_seed(seed)
    env = TerrainSim(cfg, seed)
    t0 = time.monotonic()
    try:
        data: dict[str, list[Episode]] = {}
        images: dict[str, list[np.ndarray]] = {}
        for i, t in enumerate(cfg.terrains):
            data[t], images[t] = random_episodes(env, t, encoder, cfg, seed=int(1000 * seed + i), keep_images=8)
            _log(cfg, f"seed {seed}: {len(data[t])} random rollouts on {t}")
        heldout = {t: random_episodes(env, t, encoder, cfg, seed=int(1000 * seed + 500 + i), n=cfg.heldout_rollouts)[0]
                   for i, t in enumerate(cfg.terrains)} if cfg.heldout_rollouts > 0 else {}
        t_data = time.monotonic() - t0
        names, acts = env.state_names, list(env.action_space.names)
        k = cfg.average_frames
        every = [e for t in cfg.terrains for e in data[t]]
        transform = feature_transform(cfg, every)  # fitted on the training data's features
        feat_names = [f"img_{i}" for i in range(transform(every[0].meta["features"][:1]).shape[1])]
        models, training = {}, {}
        for t in cfg.terrains:
            models[("per-terrain", t)], training[f"per-terrain {t}"] = _fit(cfg, seed, data[t], names, acts)
        models["all"], training["all data, no images"] = _fit(cfg, seed, every, names, acts)
        models["image"], training["image-conditioned"] = _fit(
            cfg, seed, [with_features(transformed(e, transform, k)) for e in every], names + feat_names, acts,
            held=feat_names)
        t_train = time.monotonic() - t0 - t_data
        _log(cfg, f"seed {seed}: trained {len(models)} models ({t_train:.0f} s)")
        wrong = {t: encoder.encode(np.stack(images[cfg.terrains[(i + 1) % len(cfg.terrains)]]))
                 for i, t in enumerate(cfg.terrains)}
        prediction: dict[str, dict[str, float]] = {r: {} for r in ROWS}
        for t, eps in heldout.items():  # open-loop error on rollouts no model trained on
            H = cfg.mbrl.horizon
            seen = [with_features(transformed(e, transform, k)) for e in eps]
            rng = np.random.default_rng([seed, 8])
            other = [Episode(e.states.copy(), e.actions, name=e.name) for e in seen]
            for e in other:  # another terrain's images, averaged and transformed as the right ones
                w = wrong[t][rng.integers(len(wrong[t]), size=len(e.states))]
                e.states[:, len(names):] = transform(running_mean(w, k))
            prediction["per-terrain"][t] = h_step_xy_mse(models[("per-terrain", t)], eps, H)
            prediction["all data, no images"][t] = h_step_xy_mse(models["all"], eps, H)
            prediction["image-conditioned"][t] = h_step_xy_mse(models["image"], seen, H)
            prediction["image-conditioned, another terrain's images"][t] = h_step_xy_mse(models["image"], other, H)
        if heldout:
            _log(cfg, f"seed {seed}: {H}-step position error (mm RMS) on held-out rollouts: " + "; ".join(
                f"{t} " + "/".join(f"{1e3 * prediction[r][t] ** 0.5:.0f}" for r in ROWS) for t in heldout))
        matrix: dict[str, dict[str, Any]] = {r: {} for r in ROWS}
        for t in cfg.terrains:
            rng = np.random.default_rng([seed, 9])
            variants = {
                "per-terrain": (models[("per-terrain", t)], names, None),
                "all data, no images": (models["all"], names, None),
                "image-conditioned": (models["image"], names + feat_names, FeatureStream(encoder.encode, transform, k)),
                "image-conditioned, another terrain's images": (
                    models["image"], names + feat_names,
                    FeatureStream(lambda img, t=t, rng=rng: wrong[t][rng.integers(len(wrong[t]))], transform, k)),
            }
            for row, (model, snames, feats) in variants.items():
                make = _mpc(model, cfg, env, snames)
                res = {p: drive_path(env, t, make(make_path(p, scale=cfg.path_scale)), p, cfg, feats)
                       for p in cfg.paths}
                matrix[row][t] = {"summary": summarize_paths(res), "paths": res}
            _log(cfg, f"seed {seed} on {t}: " + "; ".join(
                f"{r} {matrix[r][t]['summary']['cost_per_m']:.1f}/m ({matrix[r][t]['summary']['completed']}"
                f"/{len(cfg.paths)})" for r in ROWS))
        return {"seed": seed, "matrix": matrix, "training": training, "prediction_xy_mse_m2": prediction,
                "features": {"model_inputs": len(feat_names), "encoder_outputs": encoder.out_dim,
                             "variance_shares": getattr(transform, "shares", None)},
                "images": {t: np.stack(v[:4]) for t, v in images.items()},  # what the camera saw
                "wall_s": {"data": t_data, "train": t_train, "total": time.monotonic() - t0}}
    finally:
        env.close()


def aggregate(cfg: TerrainConfig, per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Per row and terrain over seeds: cost per metre and completions (mean ± std), and the
    issue's checks: on which terrains the image-conditioned model completes as many paths as
    the per-terrain model and its mean cost per metre is not worse than the per-terrain model's
    by more than that model's std (one-sided: a better image model passes), and on which it
    beats the all-data model."""
    table: dict[str, dict[str, Any]] = {}
    for row in ROWS:
        table[row] = {}
        for t in cfg.terrains:
            sums = [r["matrix"][row][t]["summary"] for r in per_seed]
            table[row][t] = {"cost_per_m": mean_std(s["cost_per_m"] for s in sums),
                             "completed": mean_std(s["completed"] for s in sums), "paths": len(cfg.paths)}
    checks = {}
    for t in cfg.terrains:
        img, pt, al = (table[r][t] for r in ("image-conditioned", "per-terrain", "all data, no images"))
        ci, cp, ca = (x["completed"]["mean"] for x in (img, pt, al))
        mi, mp, ma = (x["cost_per_m"]["mean"] for x in (img, pt, al))
        # ranked like every path result here: completions first, then cost per metre
        paired = [rank_key(a["matrix"]["image-conditioned"][t]["summary"])
                  < rank_key(a["matrix"]["all data, no images"][t]["summary"]) for a in per_seed]
        checks[t] = {
            # one-sided: as many completions and not worse by more than the per-terrain std
            "within_per_terrain_spread": bool(ci >= cp and mi - mp <= table["per-terrain"][t]["cost_per_m"]["std"]),
            "better_than_all_data": bool((ci, -mi) > (ca, -ma)),
            "seeds_image_better_than_all_data": int(sum(paired)),
        }
    pred = {}
    if all(r.get("prediction_xy_mse_m2", {}).get(ROWS[0]) for r in per_seed):
        pred = {row: {t: mean_std(1e3 * r["prediction_xy_mse_m2"][row][t] ** 0.5 for r in per_seed)
                      for t in cfg.terrains} for row in ROWS}
    return {"table": table, "checks": checks, "prediction_rms_mm": pred,
            "within_spread_terrains": [t for t, c in checks.items() if c["within_per_terrain_spread"]],
            "better_than_all_data_terrains": [t for t, c in checks.items() if c["better_than_all_data"]]}
