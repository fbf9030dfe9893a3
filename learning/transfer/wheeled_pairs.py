"""Expert/novice wheeled robots for SIDM: the paper's setting (Wang & Johnson).

Four-wheeled skid-steer robots with spring-damper suspension on rough terrain, from the
``wheeled`` sim backend (sim_backends/wheeled, got through the registry: learning imports no
robot). The pairs differ in the suspension as the paper's do:

* expert: 400 N/m per wheel, 10 N·s/m, ±40 mm travel (damping ratio ~0.25 on a quarter of the
  4 kg chassis: a soft, bouncy suspension);
* similar novice: 5x stiffer, 2x damped (2000 N/m, 20 N·s/m);
* dissimilar novice: 667x stiffer, 100x damped, 1.5x less travel (266800 N/m, 1000 N·s/m,
  ±26.7 mm): in effect a rigid suspension.

Each spring is preloaded to sit mid-travel at rest (backend docstring). Data: random wheel
speed commands, uniform in ±max each 0.1 s period, episodes of ``episode_s`` from a reset at a
random place and heading; each collection drives on its own terrain (seeded by the
collection's seed, same statistics), so validation also tests new ground.

Model input: the state without x, y, z and yaw (the dynamics do not depend on where the robot
is, given the ground around it), the ground heights relative to the chassis at a 3x3 grid
(``PATCH_XY_M``, chassis yaw frame) and the command. Target: the state change over a period,
with the position change in the chassis' yaw frame at the start and the yaw change wrapped.
"""

from __future__ import annotations

import math

import numpy as np

from hilstack.drivers.registry import make_backend
from hilstack.learning.transfer.roach_pairs import Rollouts

EXPERT: dict = {"stiffness_n_per_m": 400.0, "damping_ns_per_m": 10.0, "travel_m": 0.04}
PAIRS: dict[str, dict] = {
    "similar": {"stiffness_n_per_m": 400.0 * 5, "damping_ns_per_m": 10.0 * 2, "travel_m": 0.04},
    "dissimilar": {"stiffness_n_per_m": 400.0 * 667, "damping_ns_per_m": 10.0 * 100, "travel_m": 0.04 / 1.5},
}

#: ground sample points in the chassis' yaw frame [m]: the wheels' lines and the centre line
PATCH_XY_M = np.array([(dx, dy) for dx in (-0.2, 0.0, 0.2) for dy in (-0.15, 0.0, 0.15)])
#: state channels that are model inputs (not x, y, z, yaw)
INPUT_CHANNELS = np.array([3, 4] + list(range(6, 24)))


def collect(overrides: dict, minutes: float, seed: int, episode_s: float = 10.0) -> Rollouts:
    """Random-command rollouts of the robot with ``overrides`` (``WheeledParams`` fields) on a
    terrain seeded by ``seed``, ``minutes`` of robot time."""
    sim = make_backend("wheeled", "sim", **{**overrides, "seed": seed})
    p = sim.params
    sim.configure()
    sim.activate()
    steps = int(round(episode_s / p.period_s))
    n_ep = max(1, int(round(minutes * 60.0 / episode_s)))
    rng = np.random.default_rng(seed)
    vmax, room = p.max_wheel_speed_rad_s, p.terrain_size_m / 2 - 3.0
    S, A, P = [], [], []
    for _ in range(n_ep):
        x, y = rng.uniform(-room, room, 2)
        sim.reset(x=float(x), y=float(y), yaw=float(rng.uniform(-math.pi, math.pi)))
        s, a, pa = [sim.read().state], [], []
        for _ in range(steps):
            pa.append(sim.terrain_patch_m(PATCH_XY_M))
            a.append(sim.write(rng.uniform(-vmax, vmax, 2)))
            sim.tick()
            s.append(sim.read().state)
        S.append(s)
        A.append(a)
        P.append(pa)
    sim.cleanup()
    return Rollouts(np.asarray(S), np.asarray(A, float), np.asarray(P))


def state_change(s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Δs [N, 24]: position change in the yaw frame of s0, yaw change wrapped to (−π, π]."""
    d = s1 - s0
    c, s = np.cos(s0[:, 5]), np.sin(s0[:, 5])
    dx, dy = d[:, 0].copy(), d[:, 1].copy()
    d[:, 0], d[:, 1] = c * dx + s * dy, -s * dx + c * dy
    d[:, 5] = (d[:, 5] + np.pi) % (2 * np.pi) - np.pi
    return d


def transitions(r: Rollouts):
    """(x [N, 31], Δs [N, 24]) over all episodes."""
    from hilstack.learning.transfer.sidm import ModelSamples

    n = r.states.shape[2]
    s0 = r.states[:, :-1].reshape(-1, n)
    s1 = r.states[:, 1:].reshape(-1, n)
    x = np.concatenate([s0[:, INPUT_CHANNELS], r.patches.reshape(len(s0), -1), r.actions.reshape(len(s0), -1)], 1)
    return ModelSamples(x, state_change(s0, s1))
