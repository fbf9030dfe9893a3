"""Body-frame dynamics: exact frame algebra and invariance of predictions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hilstack.learning.datasets import Episode
from hilstack.learning.dynamics import EnsembleDynamics, h_step_error, h_step_windows
from hilstack.learning.frames import BodyFrameDynamics, PlanarFrame, load_dynamics

NAMES = ["x", "y", "vx", "vy", "cos_yaw", "sin_yaw", "w"]


def _unicycle(s, a, dt=0.1):
    """A toy planar robot: a = (forward speed, yaw rate)."""
    x, y, _, _, c, sn, _ = s
    yaw = np.arctan2(sn, c) + a[1] * dt
    vx, vy = a[0] * np.cos(yaw), a[0] * np.sin(yaw)
    return np.array([x + vx * dt, y + vy * dt, vx, vy, np.cos(yaw), np.sin(yaw), a[1]])


def _episodes(n, T, rng):
    eps = []
    for _ in range(n):
        yaw = rng.uniform(-np.pi, np.pi)
        s = [np.array([*rng.uniform(-2, 2, 2), 0, 0, np.cos(yaw), np.sin(yaw), 0])]
        a = rng.uniform(-1, 1, (T, 2))
        for t in range(T):
            s.append(_unicycle(s[-1], a[t]))
        eps.append(Episode(np.array(s), a))
    return eps


def test_frame_round_trip_and_identity():
    f = PlanarFrame(NAMES)
    rng = np.random.default_rng(0)
    s = rng.normal(size=(6, 7))
    ref = rng.normal(size=(6, 7))
    for arr in (s, ref):
        yaw = rng.uniform(-3, 3, 6)
        arr[:, 4], arr[:, 5] = np.cos(yaw), np.sin(yaw)
    np.testing.assert_allclose(f.to_world(f.to_body(s, ref), ref), s, atol=1e-12)
    b = f.to_body(s, s)
    np.testing.assert_allclose(b[:, [0, 1, 4, 5]], np.tile([0, 0, 1, 0], (6, 1)), atol=1e-12)


def test_body_frame_model_is_translation_and_rotation_invariant(tmp_path):
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = BodyFrameDynamics(EnsembleDynamics(7, 2, hidden=(64, 64), seed=0), NAMES)
    model.fit(_episodes(30, 20, rng), val=_episodes(4, 20, rng), epochs=30, progress=False, horizon=4)
    s = np.array([0.3, -0.2, 0.0, 0.0, 1.0, 0.0, 0.0])
    a = torch.tensor([[0.8, 0.5]], dtype=torch.float32)
    with torch.inference_mode():
        p0 = model.predict(torch.tensor(s[None], dtype=torch.float32), a)[0, 0].numpy()
        yaw = 1.1
        s2 = s.copy()
        s2[:2] = [5.0, 7.0]
        s2[4:6] = [np.cos(yaw), np.sin(yaw)]
        p2 = model.predict(torch.tensor(s2[None], dtype=torch.float32), a)[0, 0].numpy()
    f = PlanarFrame(NAMES)
    np.testing.assert_allclose(f.to_body(p2, s2), f.to_body(p0, s), atol=1e-4)
    # and it learned the dynamics: one step matches the toy robot
    np.testing.assert_allclose(p0[:2], _unicycle(s, a[0].numpy())[:2], atol=0.02)
    assert model.history[-1]["val_h_xy_mse_m2"] < 0.01
    model.save(tmp_path / "m.pt")
    back = load_dynamics(tmp_path / "m.pt")
    assert isinstance(back, BodyFrameDynamics)
    with torch.inference_mode():
        np.testing.assert_allclose(
            back.predict(torch.tensor(s2[None], dtype=torch.float32), a)[0, 0].numpy(), p2, atol=1e-5
        )


def test_body_frame_validation_reports_the_real_h_step_error():
    """val_h is the H-step open-loop error, not the one-step loss the wrapped model sees."""
    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    train, val = _episodes(20, 20, rng), _episodes(4, 20, rng)
    model = BodyFrameDynamics(EnsembleDynamics(7, 2, hidden=(32, 32), seed=0), NAMES)
    last = model.fit(train, val=val, epochs=5, progress=False, horizon=4)[-1]
    assert last["horizon"] == 4
    errs = {h: model.validation_errors(train, val, h) for h in (1, 4)}
    assert errs[4]["val_h"] == pytest.approx(last["val_h"])
    # open-loop errors grow with the horizon, in both frames
    assert errs[4]["val_h"] > errs[1]["val_h"] and errs[4]["val_h_body"] > errs[1]["val_h_body"]
    assert errs[4]["val_h_xy_mse_m2"] > errs[1]["val_h_xy_mse_m2"]
    # position error has the same size in both frames (a rotation), the heading error too:
    # raw body-frame error of x, y, cos, sin equals the world-frame one
    windows = h_step_windows(val, 4)
    _, raw_world = h_step_error(model, *windows, state_std=torch.ones(7))
    _, raw_body = h_step_error(model, *windows, state_std=torch.ones(7), frame=model.frame.to_body)
    assert raw_body == pytest.approx(raw_world, rel=1e-4)


def _lagged_episodes(n, T, rng):
    """A planar robot whose heading follows the yaw rate *in the state* (w), itself the last
    command: the position two steps on depends on w, the next step's does not."""
    eps = []
    for _ in range(n):
        yaw = rng.uniform(-np.pi, np.pi)
        s = [np.array([0.0, 0.0, 0.0, 0.0, np.cos(yaw), np.sin(yaw), 0.0])]
        a = rng.uniform(-1, 1, (T, 2))
        for t in range(T):
            x, y, _, _, c, sn, w = s[-1]
            yaw = np.arctan2(sn, c) + 3.0 * w * 0.1
            vx, vy = a[t, 0] * np.cos(yaw), a[t, 0] * np.sin(yaw)
            s.append(np.array([x + vx * 0.1, y + vy * 0.1, vx, vy, np.cos(yaw), np.sin(yaw), a[t, 1]]))
        eps.append(Episode(np.array(s), a))
    return eps


def test_open_loop_loss_trains_what_only_later_steps_reveal():
    """fit_open_loop's loss runs through the rollout: with w weighted 0 in the loss, one-step
    training never learns w's next value, but the H-step loss does, because w steers the
    heading and so the position of the steps after it (train_horizon, issue 29)."""
    rng = np.random.default_rng(3)
    eps, val = _lagged_episodes(30, 20, rng), _lagged_episodes(6, 20, rng)
    w0 = [1, 1, 1, 1, 1, 1, 0]
    errs = {}
    for h in (1, 3):
        torch.manual_seed(0)
        m = BodyFrameDynamics(EnsembleDynamics(7, 2, hidden=(32, 32), loss_weights=w0, seed=0), NAMES,
                              train_horizon=h)
        hist = m.fit(eps, epochs=20, batch_size=64, progress=False)
        assert ("train_h_loss" in hist[-1]) == (h > 1)
        s = np.concatenate([e.states[:-1] for e in val])
        a = np.concatenate([e.actions for e in val])
        with torch.inference_mode():
            p = m.predict(torch.tensor(s, dtype=torch.float32), torch.tensor(a, dtype=torch.float32))[0].numpy()
        errs[h] = np.sqrt(((p[:, 6] - a[:, 1]) ** 2).mean())  # next w is the command: std 0.58
    assert errs[3] < 0.2 and errs[1] > 0.5, errs  # measured 0.09 and 0.71
    with pytest.raises(ValueError, match="train_horizon"):
        BodyFrameDynamics(EnsembleDynamics(7, 2), NAMES, train_horizon=0)
