"""Expert/novice VelociRoACH pairs for SIDM, from the MuJoCo backend on rough terrain.

The expert is the nominal robot; each novice differs by config overrides of the sim
backend (``params.sim``, sim_backends/velociroach/backend.py ``SimParams``) and the leg-speed
scaling (``params.max_leg_vel_rps``):

* similar: foot-ground contact 5x less stiff and 2x less damped (the paper's 5x/2x
  suspension change; MuJoCo's ``solref`` time constant scales as 1/sqrt(stiffness)),
  chassis 20 % heavier;
* dissimilar: gearbox 14:1 instead of 21.3:1, motor constant 1.2 instead of 1.5 mV·s/rad,
  chassis 67 % heavier, leg speed scaled to 10 rev/s at full command, contact 25x softer.

Both robots walk on ``gravel`` (a seeded heightfield, 3 mm RMS); the model input includes a
local heightfield patch: heights [m] of the ground at a 3x3 grid (2 cm spacing) around the
chassis in its yaw frame, read from the MuJoCo heightfield (bilinear, scipy.ndimage).

Random data: each control period (0.1 s) both leg-velocity commands are drawn uniformly in
±max_leg_vel_rps (held one period), episodes of ``episode_s`` seconds from a reset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from hilstack.drivers.registry import make_backend

#: the nominal contact of ``gravel`` (sim_backends/velociroach/backend.py TERRAINS)
_GRAVEL_SOLREF = (0.006, 1.0)

EXPERT: dict = {"sim": {"terrain": "gravel", "terrain_half_size_m": 0.5}}

PAIRS: dict[str, dict] = {
    "similar": {"sim": {"terrain": "gravel", "terrain_half_size_m": 0.5,
                        "solref": (_GRAVEL_SOLREF[0] * math.sqrt(5.0), 0.5), "chassis_mass_kg": 0.036}},
    "dissimilar": {"max_leg_vel_rps": 10.0,
                   "sim": {"terrain": "gravel", "terrain_half_size_m": 0.5,
                           "solref": (_GRAVEL_SOLREF[0] * 5.0, 0.5), "chassis_mass_kg": 0.050,
                           "gear_ratio": 14.0, "motor_k_v_s_per_rad": 1.2e-3}},
}

#: patch sample points in the body's yaw frame [m]
PATCH_XY_M = np.array([(dx, dy) for dx in (-0.02, 0.0, 0.02) for dy in (-0.02, 0.0, 0.02)])


def terrain_patch_m(sim) -> np.ndarray:
    """Ground heights [m] at ``PATCH_XY_M`` around the chassis (zeros on a plane)."""
    m, d = sim.model, sim.data
    if m.nhfield == 0:
        return np.zeros(len(PATCH_XY_M))
    half_x, half_y, zmax, _ = m.hfield_size[0]
    nrow, ncol = int(m.hfield_nrow[0]), int(m.hfield_ncol[0])
    w, z = d.qpos[3], d.qpos[6]  # yaw of a (nearly level) body from its quaternion
    yaw = 2.0 * math.atan2(z, w)
    c, s = math.cos(yaw), math.sin(yaw)
    xy = d.qpos[0:2] + PATCH_XY_M @ np.array([[c, s], [-s, c]])  # body → heightfield frame
    col = (xy[:, 0] + half_x) / (2 * half_x) * (ncol - 1)
    row = (xy[:, 1] + half_y) / (2 * half_y) * (nrow - 1)
    grid = np.asarray(m.hfield_data, float).reshape(nrow, ncol)
    return zmax * map_coordinates(grid, [row, col], order=1, mode="nearest")


@dataclass
class Rollouts:
    """Episodes of states [E, T+1, 24], actions [E, T, 2] (rev/s) and patches [E, T, 9] (m)."""

    states: np.ndarray
    actions: np.ndarray
    patches: np.ndarray

    def minutes(self) -> float:
        return self.actions.shape[0] * self.actions.shape[1] * 0.1 / 60.0


def collect(overrides: dict, minutes: float, seed: int, episode_s: float = 10.0) -> Rollouts:
    """Random-action rollouts of the robot configured by ``overrides`` (``VelociRoachParams``
    fields, ``sim`` merged into the backend's ``params.sim``), ``minutes`` of robot time."""
    sim_cfg = {**overrides.get("sim", {}), "seed": seed}
    sim = make_backend("velociroach", "sim", **{**overrides, "sim": sim_cfg})
    params = sim.params
    sim.configure()
    sim.activate()
    steps = int(round(episode_s / params.period_s))
    n_ep = max(1, int(round(minutes * 60.0 / episode_s)))
    rng = np.random.default_rng(seed)
    vmax = params.max_leg_vel_rps
    S, A, P = [], [], []
    for _ in range(n_ep):
        sim.reset(yaw=float(rng.uniform(-math.pi, math.pi)))
        s, a, p = [sim.read().state], [], []
        for _ in range(steps):
            act = rng.uniform(-vmax, vmax, 2)
            p.append(terrain_patch_m(sim))
            a.append(sim.write(act))
            sim.tick()
            s.append(sim.read().state)
        S.append(s)
        A.append(a)
        P.append(p)
    sim.cleanup()
    return Rollouts(np.asarray(S), np.asarray(A, float), np.asarray(P))


def features(states: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """Model input from states [N, 24] and ``extra`` = [patch (9) m, action (2) rev/s]:
    the state without x, y (the dynamics are invariant to where the robot is), then extra."""
    return np.concatenate([states[:, 2:], extra], axis=1).astype(np.float32)


def extras(r: Rollouts) -> np.ndarray:
    """[E, T, 11] per-step inputs that the model does not predict (patch, action)."""
    return np.concatenate([r.patches, r.actions], axis=2)


def transitions(r: Rollouts):
    """(x [N, 33], Δs [N, 24]) over all episodes."""
    from hilstack.learning.transfer.sidm import ModelSamples

    s0 = r.states[:, :-1].reshape(-1, r.states.shape[2])
    s1 = r.states[:, 1:].reshape(-1, r.states.shape[2])
    return ModelSamples(features(s0, extras(r).reshape(-1, extras(r).shape[2])), s1 - s0)


def first_minutes(r: Rollouts, minutes: float) -> Rollouts:
    """The first ``minutes`` of robot time (whole episodes, at least one)."""
    per_ep = r.actions.shape[1] * 0.1 / 60.0
    n = max(1, int(round(minutes / per_ep)))
    return Rollouts(r.states[:n], r.actions[:n], r.patches[:n])


@dataclass(frozen=True)
class SidmExperiment:
    """The SIDM sweep on an expert/novice setting (docs/transfer.md lists what each run used)."""

    expert_minutes: float = 20.0
    novice_minutes: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 15.0, 30.0, 60.0, 120.0)
    validation_minutes: float = 5.0
    trials: int = 3
    p_e: tuple[tuple[str, float], ...] = (("similar", 0.75), ("dissimilar", 0.5))  # the paper's values
    drift_steps: int = 25
    episode_s: float = 10.0
    #: sizes where SIDM is also trained without distribution matching (match_iters 0): an ablation
    ablation_minutes: tuple[float, ...] = ()
    #: also train SIDM as the paper defines it (no warm start: ``warm_rounds`` 0), key "sidm_paper"
    paper_sidm: bool = False
    #: also fine-tune the expert's own model on the novice data (``train_sidm(init=...)``), key "finetune"
    finetune: bool = False
    seed: int = 0


def run_sidm(exp: SidmExperiment, cfg, log=print, setting=None) -> dict:
    """For each pair: validation error (normalised MSE of Δs on separate novice data) against
    novice minutes with and without SIDM (median and interquartile range over trials), the data
    multiplier per size, and (where the setting has ``features``) the open-loop drift [m].
    ``cfg`` is the ``SidmConfig`` (p_e is set per pair; "with_sidm" uses its ``warm_rounds``).
    ``setting``: a module with ``EXPERT``, ``PAIRS``, ``collect`` and ``transitions`` (this one,
    the VelociRoACH, by default; ``wheeled_pairs`` for the paper's wheeled robots). Trials differ
    in the training seed and in which novice episodes form each size."""
    import sys
    from dataclasses import replace

    from hilstack.learning.transfer.sidm import (
        data_multiplier,
        data_multipliers,
        open_loop_drift,
        target_scale,
        train_sidm,
        validation_mse,
    )

    S = setting or sys.modules[__name__]
    drift = getattr(S, "features", None) is not None and exp.drift_steps > 0
    expert_r = S.collect(S.EXPERT, exp.expert_minutes, exp.seed, exp.episode_s)
    expert = S.transitions(expert_r)
    log(f"sidm: expert {expert_r.minutes():.1f} min")
    # the expert's own model (no novice data), one per trial: how different each pair really is,
    # and where fine-tuning starts
    expert_models = [train_sidm(expert, replace(cfg, seed=exp.seed + trial)) for trial in range(exp.trials)]
    variants = ["with_sidm", "without_sidm"] + (["sidm_paper"] if exp.paper_sidm else []) + (
        ["finetune"] if exp.finetune else [])
    out: dict = {"pairs": {}, "variants": variants}
    for pi, (pair, p_e) in enumerate(exp.p_e):
        ov = S.PAIRS[pair]
        nov_all = S.collect(ov, max(exp.novice_minutes), exp.seed + 100 + pi, exp.episode_s)
        val_r = S.collect(ov, exp.validation_minutes, exp.seed + 200 + pi, exp.episode_s)
        val = S.transitions(val_r)
        scale = target_scale(val)  # one fixed error scale for every model of this pair
        expert_only = [validation_mse(m, val, scale=scale) for m in expert_models]
        curve = []
        for minutes in exp.novice_minutes:
            runs: dict[str, list[float]] = {k: [] for k in variants}
            for trial in range(exp.trials):
                perm = np.random.default_rng(exp.seed + trial).permutation(len(nov_all.actions))
                shuffled = Rollouts(nov_all.states[perm], nov_all.actions[perm], nov_all.patches[perm])
                nov = S.transitions(first_minutes(shuffled, minutes))
                c = replace(cfg, p_e=p_e, seed=exp.seed + trial)
                models = {"with_sidm": lambda c=c, nov=nov: train_sidm(nov, c, expert),
                          "without_sidm": lambda c=c, nov=nov: train_sidm(nov, c, None),
                          "sidm_paper": lambda c=c, nov=nov: train_sidm(nov, replace(c, warm_rounds=0), expert),
                          "finetune": lambda c=c, nov=nov, t=trial: train_sidm(nov, c, None, init=expert_models[t])}
                for key in variants:
                    model = models[key]()
                    runs[key].append(validation_mse(model, val, scale=scale))
                    if drift and key in ("with_sidm", "without_sidm"):
                        d = np.mean([open_loop_drift(model, S.extras(val_r)[e], val_r.states[e], S.features,
                                                     exp.drift_steps) for e in range(len(val_r.states))])
                        runs.setdefault("drift_with_m" if key == "with_sidm" else "drift_without_m", []).append(
                            float(d))
                if minutes in exp.ablation_minutes:
                    model = train_sidm(nov, replace(c, match_iters=0), expert)
                    runs.setdefault("with_sidm_no_matching", []).append(validation_mse(model, val, scale=scale))
            row = {"minutes": minutes}
            for k, v in runs.items():
                row[k] = float(np.median(v))
                row[k + "_iqr"] = [float(np.percentile(v, 25)), float(np.percentile(v, 75))]
                row[k + "_trials"] = [float(x) for x in v]
            log(f"sidm {pair}: {minutes:g} min novice: val MSE " + "  ".join(
                f"{k} {row[k]:.4f}" for k in runs if not k.startswith("drift")))
            curve.append(row)
        minutes_ = [r["minutes"] for r in curve]
        base = [r["without_sidm"] for r in curve]
        res = {"curve": curve, "p_e": p_e, "overrides": ov,
               "expert_model_on_novice": float(np.median(expert_only)),
               "expert_model_on_novice_iqr": [float(np.percentile(expert_only, 25)),
                                              float(np.percentile(expert_only, 75))]}
        for k in variants[2:] + ["with_sidm"]:
            tag = "" if k == "with_sidm" else f"_{k}"
            res["data_multiplier" + tag] = data_multiplier(minutes_, [r[k] for r in curve], base)
            res["data_multiplier_per_size" + tag] = data_multipliers(minutes_, [r[k] for r in curve], base)
        if drift:
            res["drift_no_motion_m"] = float(np.mean([open_loop_drift(None, S.extras(val_r)[e], val_r.states[e],
                                                                      S.features, exp.drift_steps)
                                                      for e in range(len(val_r.states))]))
        log(f"sidm {pair}: multiplier {res['data_multiplier']}; expert's own model on novice validation "
            f"{res['expert_model_on_novice']:.4f} (novice-only at {curve[-1]['minutes']:g} min: "
            f"{curve[-1]['without_sidm']:.4f})")
        out["pairs"][pair] = res
    out["expert_minutes"] = expert_r.minutes()
    return out
