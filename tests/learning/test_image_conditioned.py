"""The image-conditioned model f(s, a, I) (issue 29): the roach's MBRL model with the image
features as inputs it reads and does not predict (learning/image_conditioned.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.learning.datasets import Episode
from hilstack.learning.image_conditioned import HeldInputs, TerrainConfig, aggregate, with_features
from hilstack.learning.mbrl import MbrlConfig, fit_episodes, make_model

ROBOT = ["x", "y", "vx", "vy", "cos_yaw", "sin_yaw", "w"]
FEATS = ["img_0", "img_1", "img_2"]
ACTS = ["left", "right"]


def toy_episodes(n: int, steps: int, rng: np.random.Generator) -> list[Episode]:
    """A planar robot whose forward speed answers the mean command with a gain of +1 on one
    terrain and -1 on the other (the image features, a noisy code of the terrain, say which)."""
    out = []
    for i in range(n):
        terrain = i % 2
        gain = 1.0 if terrain == 0 else -1.0
        code = np.array([1.0, -0.5, 0.3]) * (1 if terrain == 0 else -1)
        s = np.zeros(len(ROBOT))
        s[4] = 1.0
        states, feats, acts = [s.copy()], [code + 0.05 * rng.standard_normal(3)], []
        yaw = rng.uniform(-np.pi, np.pi)
        s[4], s[5] = np.cos(yaw), np.sin(yaw)
        states[0] = s.copy()
        for _ in range(steps):
            a = rng.uniform(-1, 1, 2)
            v = gain * a.mean()
            w = 0.5 * (a[1] - a[0])
            yaw = np.arctan2(s[5], s[4]) + 0.1 * w
            s = np.array([s[0] + 0.1 * v * s[4], s[1] + 0.1 * v * s[5], v * np.cos(yaw), v * np.sin(yaw),
                          np.cos(yaw), np.sin(yaw), w])
            states.append(s)
            feats.append(code + 0.05 * rng.standard_normal(3))
            acts.append(a)
        out.append(Episode(np.array(states), np.array(acts), name=f"t{terrain}#{i}",
                           meta={"terrain": terrain, "features": np.array(feats, dtype=np.float32)}))
    return out


def one_step_error(model, eps: list[Episode], names_with_features: bool) -> float:
    """Mean squared error of the predicted next x, y over the episodes' transitions."""
    err = []
    with torch.inference_mode():
        for e in eps:
            s = torch.as_tensor(with_features(e).states if names_with_features else e.states)
            pred = model.predict(s[:-1], torch.as_tensor(e.actions)).mean(0)
            err.append(((pred[:, :2] - s[1:, :2]) ** 2).sum(-1).numpy())
    return float(np.concatenate(err).mean())


def test_model_input_width_includes_the_features_and_holds_them():
    cfg = MbrlConfig(hidden=(16, 16), progress=False)
    m = HeldInputs(make_model(cfg, ROBOT + FEATS, ACTS), ROBOT + FEATS, FEATS)
    assert m.input_width() == len(ROBOT) + len(FEATS) + len(ACTS)
    plain = make_model(cfg, ROBOT, ACTS)
    assert plain.model.weights[0].shape[1] == len(ROBOT) + len(ACTS)
    s = torch.zeros(5, len(ROBOT) + len(FEATS))
    s[:, 4] = 1.0
    s[:, len(ROBOT):] = torch.randn(5, len(FEATS))
    with torch.inference_mode():
        nxt = m.predict(s, torch.zeros(5, 2))
    assert nxt.shape == (1, 5, len(ROBOT) + len(FEATS))
    torch.testing.assert_close(nxt[0, :, len(ROBOT):], s[:, len(ROBOT):])  # held over a plan
    with pytest.raises(ValueError, match="not in the state names"):
        HeldInputs(make_model(cfg, ROBOT, ACTS), ROBOT, ["img_9"])


def test_features_let_one_model_fit_two_terrains_that_the_blind_model_cannot():
    rng = np.random.default_rng(0)
    train, test = toy_episodes(24, 20, rng), toy_episodes(6, 20, rng)
    cfg = MbrlConfig(hidden=(64, 64), progress=False, input_noise_std=0.0)

    def fit(model, eps):
        fit_episodes(model, eps, epochs=40, batch_size=128, val_fraction=0.1, rng=np.random.default_rng(1),
                     assigned={}, horizon=4)
        return model

    blind = fit(make_model(cfg, ROBOT, ACTS), train)
    seeing = fit(HeldInputs(make_model(cfg, ROBOT + FEATS, ACTS), ROBOT + FEATS, FEATS),
                 [with_features(e) for e in train])
    e_blind, e_seeing = one_step_error(blind, test, False), one_step_error(seeing, test, True)
    # the blind model can only average the two gains (predicting no motion); the one that sees
    # the terrain predicts the motion of each
    assert e_seeing < 0.2 * e_blind, (e_seeing, e_blind)
    assert "val_h" in seeing.history[-1] and np.isfinite(seeing.history[-1]["val_h"])


def test_aggregate_checks_rank_completions_before_cost():
    cfg = TerrainConfig(terrains=("a", "b", "c"), seeds=(0, 1), paths=("straight",))

    def cell(cpm, done):
        return {"summary": {"cost_per_m": cpm, "completed": done, "cost": cpm}}

    # on a: the image model completes and is close to the per-terrain one; the all-data model
    # is cheaper per metre but does not complete (a robot that stops pays nothing per metre).
    # the spread check is one-sided: on b the image model is worse than the per-terrain one
    # by more than its std (fails), on c better by more than it (passes)
    per_seed = [{"matrix": {
        "per-terrain": {"a": cell(10 + k, 1), "b": cell(10, 1), "c": cell(20 + k, 1)},
        "all data, no images": {"a": cell(5, 0), "b": cell(8, 1), "c": cell(8, 1)},
        "image-conditioned": {"a": cell(11, 1), "b": cell(30, 1), "c": cell(5, 1)},
        "image-conditioned, another terrain's images": {"a": cell(40, 1), "b": cell(40, 1), "c": cell(40, 1)},
    }} for k in (0, 2)]
    agg = aggregate(cfg, per_seed)
    assert agg["checks"]["a"] == {"within_per_terrain_spread": True, "better_than_all_data": True,
                                  "seeds_image_better_than_all_data": 2}
    assert agg["checks"]["b"]["within_per_terrain_spread"] is False
    assert agg["checks"]["b"]["better_than_all_data"] is False
    assert agg["checks"]["c"]["within_per_terrain_spread"] is True  # 5 vs 21 ± 1: better, not "outside"
    assert agg["within_spread_terrains"] == ["a", "c"]
    assert agg["table"]["per-terrain"]["a"]["cost_per_m"]["values"] == [10, 12]
    with pytest.raises(ValueError, match="at least two distinct terrains"):
        TerrainConfig(terrains=("a",))


def test_demo_seed_files_are_reused_claimed_and_never_overwritten(tmp_path, monkeypatch):
    from hilstack.tools import demo_terrain as dt

    cfg = TerrainConfig(terrains=("a", "b"), seeds=(0, 1), paths=("straight",))
    ran = []

    def fake_run_seed(c, seed, encoder):
        ran.append(seed)
        m = {r: {t: {"summary": {"cost_per_m": 1.0 + seed, "completed": 1, "cost": 1.0}, "paths": {}}
                 for t in c.terrains} for r in ("per-terrain", "all data, no images", "image-conditioned",
                                                "image-conditioned, another terrain's images")}
        return {"seed": seed, "matrix": m, "training": {}, "images": {t: np.zeros((1, 8, 8, 3), np.uint8)
                                                                     for t in c.terrains},
                "wall_s": {"data": 0.0, "train": 0.0, "total": 0.0}}

    monkeypatch.setattr(dt, "run_seed", fake_run_seed)
    runs = tmp_path / "runs"
    runs.mkdir()
    (runs / "seed1.claim").write_text("12345\n")  # another process computes seed 1
    with pytest.raises(TimeoutError, match="seed 1 is claimed"):
        dt.run(tmp_path, cfg, wait_s=0.0)
    assert ran == [0] and (runs / "seed0.json").exists() and not (runs / "seed0.claim").exists()
    (runs / "seed1.claim").unlink()  # it died: the claim is removed, the seed is computed here
    rep = dt.run(tmp_path, cfg, wait_s=0.0)
    assert ran == [0, 1]  # seed 0 reused from its file
    assert rep["table"]["per-terrain"]["a"]["cost_per_m"]["values"] == [1.0, 2.0]
    assert (tmp_path / "report.md").exists() and (tmp_path / "camera.png").exists()
    other = TerrainConfig(terrains=("a", "b"), seeds=(0, 1), paths=("left",))
    with pytest.raises(ValueError, match="another configuration"):
        dt.run(tmp_path, other, wait_s=0.0)


def test_whitening_turns_near_collinear_features_into_their_few_unit_variance_directions():
    from hilstack.perception.terrain_features import FeatureWhitening

    rng = np.random.default_rng(0)
    latent = rng.standard_normal((2000, 2)) * [3.0, 0.5]  # two signals of different scale
    mix = rng.standard_normal((2, 16))
    feats = latent @ mix + 1e-4 * rng.standard_normal((2000, 16)) + 7.0  # 16 channels, 2 directions
    w = FeatureWhitening(feats, min_share=0.01)
    assert w.out_dim == 2 and sum(w.shares[:2]) > 0.999
    z = w(feats)
    np.testing.assert_allclose(z.mean(0), 0.0, atol=1e-4)
    np.testing.assert_allclose(np.cov(z.T, bias=True), np.eye(2), atol=1e-3)  # decorrelated, unit variance
    # a linear map of the latent: whitened features of new data carry the same two signals
    new = rng.standard_normal((500, 2)) * [3.0, 0.5]
    zn = w(new @ mix + 7.0)
    coef, *_ = np.linalg.lstsq(np.column_stack([new, np.ones(500)]), zn, rcond=None)
    assert np.abs(np.column_stack([new, np.ones(500)]) @ coef - zn).max() < 1e-3
    with pytest.raises(ValueError, match="min_share"):
        FeatureWhitening(feats, min_share=0.0)
    with pytest.raises(ValueError, match="features must be"):
        FeatureWhitening(feats[:1])


def test_features_at_run_time_are_the_ones_the_model_was_trained_on():
    """The evaluation's per-step stream (current image, averaged with the episode's last k − 1,
    transformed) equals what training computed from the episode's images at once."""
    from hilstack.learning.image_conditioned import FeatureStream, running_mean
    from hilstack.perception.terrain_features import FeatureWhitening, RandomConvEncoder

    rng = np.random.default_rng(1)
    enc = RandomConvEncoder(out_dim=6, seed=0, channels=(4, 8))
    images = rng.integers(0, 255, size=(12, 16, 16, 3), dtype=np.uint8)
    raw = enc.encode(images)
    np.testing.assert_allclose(running_mean(raw, 3)[5], raw[3:6].mean(0), rtol=1e-5)
    np.testing.assert_allclose(running_mean(raw, 3)[1], raw[:2].mean(0), rtol=1e-5)
    w = FeatureWhitening(running_mean(raw, 3), min_share=0.05)
    stream = FeatureStream(enc.encode, w, k=3)
    for _ in range(2):  # a second episode starts over after reset()
        stream.reset()
        got = np.stack([stream(img) for img in images])
        np.testing.assert_allclose(got, w(running_mean(raw, 3)), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="average_frames"):
        TerrainConfig(average_frames=0)
