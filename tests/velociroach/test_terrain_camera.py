"""The roach's terrains seen by its camera (issue 29, thesis ch. 3.3): each terrain looks and
behaves differently, is chosen per episode, and the image encoder's features tell them apart.

Renders offscreen (MUJOCO_GL=egl, tests/conftest.py); images at 64×64 on the small periodic
map (terrain_half_size_m 0.5) the terrain demo uses.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilstack.drivers.velociroach.config import VelociRoachParams
from hilstack.perception.terrain_features import RandomConvEncoder
from hilstack.sim_backends.velociroach.backend import TERRAINS, VelociRoachSim
from hilstack.tasks.perturbations import PerturbationSettings

NAMES = ("carpet", "styrofoam", "gravel", "turf")


def make(**sim) -> VelociRoachSim:
    s = VelociRoachSim(VelociRoachParams(sim={"terrain_half_size_m": 0.5, **sim}))
    s.configure()
    s.activate()
    return s


@pytest.fixture(scope="module")
def views():
    """Per terrain, 6 camera images at seeded poses, some after a few random steps (tilted,
    moving), and whether the robot was upright (roll and pitch within 25°); terrains switched
    per episode through the ``terrain`` perturbation."""
    s = make(camera_px=64)
    rng = np.random.default_rng(0)
    out, upright = {}, {}
    try:
        for t in NAMES:
            s.apply_perturbations(PerturbationSettings(terrain=t))
            ims, ok = [], []
            for _ in range(6):
                s.reset(x=float(rng.uniform(-1, 1)), y=float(rng.uniform(-1, 1)), yaw=float(rng.uniform(-3, 3)))
                a = rng.uniform(0.2, 1.0, 2) * s.spec.action.high
                for _ in range(int(rng.integers(0, 4))):
                    s.write(a)
                    s.tick()
                obs = s.read()
                ims.append(obs.extras["image"])
                ok.append(min(obs.state[6], obs.state[8]) > math.cos(math.radians(25)))  # cos roll, cos pitch
            out[t], upright[t] = np.stack(ims), np.array(ok)
    finally:
        s.cleanup()
    return out, upright


def nearest_centroid_accuracy(feats: dict[str, np.ndarray], margin: float = 0.8) -> float:
    """Leave-one-out nearest-centroid accuracy of the terrain labels, an image counting only
    when its own terrain's centroid (without it) is nearer than ``margin`` times the nearest
    other one: identical features everywhere score 0, not a coin toss of rounding."""
    ok = n = 0
    eps = 1e-6 * float(np.mean([np.linalg.norm(g, axis=1).mean() for g in feats.values()]))  # rounding
    for t, f in feats.items():
        for i in range(len(f)):
            d = {u: float(np.linalg.norm(f[i] - (np.delete(g, i, 0) if u == t else g).mean(0)))
                 for u, g in feats.items()}
            ok += d[t] + eps < margin * min(v for u, v in d.items() if u != t)
            n += 1
    return ok / n


def test_camera_renders_what_the_terrain_looks_like(views):
    views, upright = views
    # each image of an upright robot (a tipped one sees past the ground's edge): its mean colour is nearest to its own terrain's texture colour (base and marks
    # mixed by their coverage) times one lighting gain common to every terrain
    albedo = {t: (1 - TERRAINS[t]["look"].marks) * np.array(TERRAINS[t]["look"].rgb)
              + TERRAINS[t]["look"].marks * np.array(TERRAINS[t]["look"].mark_rgb) for t in NAMES}
    means = {t: v[upright[t]].reshape(int(upright[t].sum()), -1, 3).mean(1) / 255.0 for t, v in views.items()}
    assert all(len(m) >= 4 for m in means.values())
    a = np.concatenate([np.repeat(albedo[t][None], len(means[t]), 0) for t in NAMES]).ravel()
    m = np.concatenate([means[t] for t in NAMES]).ravel()
    gain = float(a @ m / (a @ a))
    for t in NAMES:
        for mu in means[t]:
            assert min(NAMES, key=lambda u: np.linalg.norm(mu - gain * albedo[u])) == t
    assert views["carpet"].shape[1:] == (64, 64, 3) and views["carpet"].dtype == np.uint8
    # the camera rides on the robot: another pose, another view of the same ground
    assert not np.array_equal(views["gravel"][0], views["gravel"][1])


def test_features_separate_terrains_and_constant_images_do_not(views):
    views, _ = views  # tipped robots included: the model sees those images too
    enc = RandomConvEncoder(16, seed=0)
    feats = {t: enc.encode(v) for t, v in views.items()}
    assert next(iter(feats.values())).shape == (6, 16)
    assert nearest_centroid_accuracy(feats) >= 0.95
    # the same check on constant images (every terrain the same grey view) is at chance: it can fail
    const = {t: enc.encode(np.full_like(v, 128)) for t, v in views.items()}
    assert nearest_centroid_accuracy(const) == 0.0
    # fixed: the same seed gives the same features, another seed others
    np.testing.assert_array_equal(RandomConvEncoder(16, seed=0).encode(views["turf"]), feats["turf"])
    assert not np.allclose(RandomConvEncoder(16, seed=1).encode(views["turf"]), feats["turf"])


def test_terrain_is_chosen_per_episode_and_behaves_differently():
    s = make()  # no camera: no image in the reading
    try:
        assert "image" not in s.read().extras
        friction = lambda: float(s.model.geom_friction[s.model.geom("ground").id, 0])  # noqa: E731
        assert friction() == TERRAINS["carpet"]["friction"]
        s.set_perturbation("terrain", "styrofoam")
        assert friction() == TERRAINS["carpet"]["friction"]  # not under a standing robot
        with pytest.raises(ValueError, match="unknown terrain 'ice'"):
            s.set_perturbation("terrain", "ice")
        travelled = {}
        for t in ("carpet", "styrofoam", "gravel"):
            s.apply_perturbations(PerturbationSettings(terrain=t))
            s.reset(x=0.0, y=0.0, yaw=0.0)
            assert friction() == TERRAINS[t]["friction"]
            assert s.model.geom("ground").type == (0 if TERRAINS[t]["roughness_m"] == 0 else 1)  # plane | hfield
            a = 0.8 * s.spec.action.high
            for _ in range(15):
                s.write(a)
                s.tick()
            st = s.read().state
            travelled[t] = (math.hypot(st[0], st[1]), math.atan2(st[11], st[10]))
        # the same command walks a different course on each terrain
        d = [travelled[t][0] for t in travelled]
        assert max(d) - min(d) > 0.1, travelled
        s.apply_perturbations(PerturbationSettings())  # back to the configured terrain at the next reset
        s.reset()
        assert friction() == TERRAINS["carpet"]["friction"]
    finally:
        s.cleanup()
