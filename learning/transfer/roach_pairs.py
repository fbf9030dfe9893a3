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

from drivers.velociroach.config import VelociRoachParams
from sim_backends.velociroach.backend import VelociRoachSim

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


def terrain_patch_m(sim: VelociRoachSim) -> np.ndarray:
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
    params = VelociRoachParams(**{**overrides, "sim": sim_cfg})
    sim = VelociRoachSim(params)
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
    from learning.transfer.sidm import Transitions

    s0 = r.states[:, :-1].reshape(-1, r.states.shape[2])
    s1 = r.states[:, 1:].reshape(-1, r.states.shape[2])
    return Transitions(features(s0, extras(r).reshape(-1, extras(r).shape[2])), s1 - s0)


def first_minutes(r: Rollouts, minutes: float) -> Rollouts:
    """The first ``minutes`` of robot time (whole episodes, at least one)."""
    per_ep = r.actions.shape[1] * 0.1 / 60.0
    n = max(1, int(round(minutes / per_ep)))
    return Rollouts(r.states[:n], r.actions[:n], r.patches[:n])
