"""Train the keypoint CNN on rendered images with domain randomisation; write the weights.

    MUJOCO_GL=egl python -m hilstack.tools.train_keypoints --out perception/weights/keypoint_net.pt

(what made the shipped weights; see docs/camera.md for the numbers). No data is
downloaded: every image is rendered from the MuJoCo hand scene with the stereo pair
(:class:`hilstack.sim_backends.shadow_hand.cameras.HandCameraScene`).

Domain randomisation per rendered sample: finger poses about the hold pose (occlusions),
ball positions over and beside the palm (6 % out of view, 10 % hidden under the hand), light and headlight
intensity, ball and hand colours, camera pose jitter (a few mm and ~1°); per training
image: Gaussian pixel noise and brightness/contrast. Labels: each ball's pixel (the
projection of its centre with the jittered camera) and its visible fraction (segmentation
render: visible ball pixels over the area of the whole ball's disc).
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from hilstack.perception.geometry import apply, cv_from_mujoco_cam, intrinsics_from_fovy, invert, project
from hilstack.perception.keypoint_net import KeypointNet, save_keypoint_net
from hilstack.perception.tracker import BALL_RADIUS_M


@dataclass
class Dataset:
    images: np.ndarray  # (N, H, W, 3) uint8
    uv: np.ndarray  # (N, 2, 2) px
    vis: np.ndarray  # (N, 2) in [0, 1]


def _small_rotation(rng: np.random.Generator, sigma_rad: float) -> np.ndarray:
    v = rng.normal(0.0, sigma_rad, 3)
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, v / (np.linalg.norm(v) + 1e-12), float(np.linalg.norm(v)))
    return q


def render_dataset(n_pairs: int, seed: int = 0, scene=None, randomize: bool = True, log=None) -> Dataset:
    """``2·n_pairs`` labelled images (left and right views of ``n_pairs`` random scenes)."""
    from hilstack.sim_backends.shadow_hand.cameras import (
        LEFT_CAMERA,
        PALM_CENTER_IN_HAND_M,
        RIGHT_CAMERA,
        HandCameraScene,
    )

    own = scene is None
    sc = scene or HandCameraScene()
    m, d = sc.model, sc.data
    rng = np.random.default_rng(seed)
    cams = [m.camera(LEFT_CAMERA).id, m.camera(RIGHT_CAMERA).id]
    base_pos = m.cam_pos[cams].copy()
    base_quat = m.cam_quat[cams].copy()
    ball_geoms = [m.geom(f"ball{i}").id for i in range(2)]
    hand_geoms = [g for g in range(m.ngeom) if m.geom(g).name.startswith("robot0:") or m.geom_bodyid[g] > 0
                  and g not in ball_geoms]
    base_rgba = m.geom_rgba.copy()
    base_light = m.light_diffuse.copy()
    base_head = (m.vis.headlight.diffuse.copy(), m.vis.headlight.ambient.copy())
    K = intrinsics_from_fovy(sc.mount.fovy_deg, sc.mount.width_px, sc.mount.height_px)
    r = sc.renderer._r.renderer
    H, W = sc.mount.height_px, sc.mount.width_px
    imgs = np.zeros((2 * n_pairs, H, W, 3), np.uint8)
    uvs = np.zeros((2 * n_pairs, 2, 2))
    vis = np.zeros((2 * n_pairs, 2))
    c = np.asarray(PALM_CENTER_IN_HAND_M)
    try:
        for k in range(n_pairs):
            if log and k % 50 == 0:
                log(f"rendering pair {k}/{n_pairs}")
            q = sc.hold_q.copy()
            balls = np.stack([c, c])
            if randomize:
                q[2:] += rng.normal(0.0, 0.25, q.size - 2)
                q[:2] += rng.normal(0.0, 0.05, 2)
                for i in range(2):
                    rad, th = 0.045 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
                    balls[i] = c + [rad * np.cos(th), rng.uniform(-0.015, 0.006), rad * np.sin(th)]
                    u = rng.uniform()
                    if u < 0.06:  # out of view
                        balls[i] = c + [rng.choice([-1, 1]) * rng.uniform(0.2, 0.4), 0.0, rng.uniform(-0.1, 0.1)]
                    elif u < 0.16:  # under the palm or the fingers: hidden
                        balls[i] = c + [rng.uniform(-0.04, 0.04), rng.uniform(0.03, 0.07), rng.uniform(-0.05, 0.05)]
                for j, cam in enumerate(cams):
                    m.cam_pos[cam] = base_pos[j] + rng.normal(0.0, 0.003, 3)
                    mujoco.mju_mulQuat(m.cam_quat[cam], base_quat[j], _small_rotation(rng, np.radians(1.0)))
                m.light_diffuse[:] = base_light * rng.uniform(0.4, 1.3)
                m.vis.headlight.diffuse[:] = base_head[0] * rng.uniform(0.3, 1.6)
                m.vis.headlight.ambient[:] = base_head[1] * rng.uniform(0.3, 3.0)
                m.geom_rgba[hand_geoms, :3] = np.clip(base_rgba[hand_geoms, :3] * rng.uniform(0.6, 1.1), 0, 1)
                m.geom_rgba[ball_geoms[0], :3] = (rng.uniform(0.55, 1.0), rng.uniform(0.0, 0.3), rng.uniform(0.0, 0.3))
                m.geom_rgba[ball_geoms[1], :3] = (rng.uniform(0.0, 0.3), rng.uniform(0.1, 0.45),
                                                  rng.uniform(0.55, 1.0))
            sc.set_hand(q)
            sc.set_balls(balls)  # runs mj_forward: the jittered cameras are in data now
            world_balls = apply(sc.world_from_hand, balls)
            for j, cam in enumerate(cams):
                i_img = 2 * k + j
                cv_from_world = invert(cv_from_mujoco_cam(d.cam_xpos[cam], d.cam_xmat[cam]))
                uvs[i_img] = project(K, cv_from_world, world_balls)
                z = apply(cv_from_world, world_balls)[:, 2]
                r.update_scene(d, camera=cam)
                imgs[i_img] = r.render()
                r.enable_segmentation_rendering()
                r.update_scene(d, camera=cam)
                seg = r.render()[..., 0]
                r.disable_segmentation_rendering()
                for b in range(2):
                    full = np.pi * (K[0, 0] * BALL_RADIUS_M / z[b]) ** 2
                    vis[i_img, b] = min(1.0, float((seg == ball_geoms[b]).sum()) / full) if z[b] > 0 else 0.0
    finally:
        m.cam_pos[cams], m.cam_quat[cams] = base_pos, base_quat
        m.geom_rgba[:] = base_rgba
        m.light_diffuse[:] = base_light
        m.vis.headlight.diffuse[:], m.vis.headlight.ambient[:] = base_head
        if own:
            sc.close()
    return Dataset(imgs, uvs, vis)


def augment(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Brightness/contrast and Gaussian pixel noise on a (B, 3, h, w) batch in [0, 1]."""
    B = x.shape[0]
    gain = 0.75 + 0.5 * torch.rand(B, 1, 1, 1, generator=gen)
    bias = 0.1 * (torch.rand(B, 1, 1, 1, generator=gen) - 0.5)
    sigma = 0.025 * torch.rand(B, 1, 1, 1, generator=gen)
    return (x * gain + bias + sigma * torch.randn(x.shape, generator=gen)).clamp(0.0, 1.0)


def train(data: Dataset, epochs: int = 30, batch: int = 32, lr: float = 3e-3, seed: int = 0,
          width: int = 12, log=print) -> KeypointNet:
    """Spatial-softmax keypoint regression (Huber on pixels, where the ball is visible) plus
    the visibility head (binary cross-entropy on the visible fraction)."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    net = KeypointNet(width=width)
    x_all = KeypointNet.preprocess(data.images)
    uv_all = torch.from_numpy(data.uv).float()
    vis_all = torch.from_numpy(data.vis).float()
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    steps = epochs * ((len(x_all) + batch - 1) // batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
    for ep in range(epochs):
        perm = torch.randperm(len(x_all), generator=gen)
        tot = 0.0
        for s in range(0, len(perm), batch):
            idx = perm[s:s + batch]
            uv, vl = net(augment(x_all[idx], gen))
            w = (vis_all[idx] > 0.3).float()
            kp = (torch.nn.functional.huber_loss(uv, uv_all[idx], reduction="none", delta=2.0).sum(-1) * w).sum()
            kp = kp / w.sum().clamp(min=1.0)
            loss = kp + 5.0 * torch.nn.functional.binary_cross_entropy_with_logits(vl, vis_all[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            tot += float(loss.detach()) * len(idx)
        if log:
            log(f"epoch {ep + 1}/{epochs}: loss {tot / len(perm):.3f}", flush=True)
    net.eval()
    return net


def evaluate(net: KeypointNet, data: Dataset) -> dict[str, float]:
    """Pixel error where the ball is at least half visible, and visibility accuracy."""
    with torch.inference_mode():
        uv, vis = net.predict(data.images)
    m = data.vis > 0.5
    err = np.linalg.norm(uv - data.uv, axis=-1)[m]
    return {"pixel_error_mean": float(err.mean()), "pixel_error_p95": float(np.percentile(err, 95)),
            "visibility_accuracy": float(((vis > 0.5) == (data.vis > 0.5)).mean())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.train_keypoints", description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="perception/weights/keypoint_net.pt")
    ap.add_argument("--pairs", type=int, default=300, help="rendered stereo pairs (2 images each)")
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", default=None, help="an .npz of the rendered data: written once, reused after")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    t0 = time.monotonic()
    if a.cache and os.path.exists(a.cache):
        z = np.load(a.cache)
        data = Dataset(z["images"], z["uv"], z["vis"])
        held = Dataset(z["h_images"], z["h_uv"], z["h_vis"])
    else:
        data = render_dataset(a.pairs, seed=a.seed, log=lambda m: print(m, flush=True))
        held = render_dataset(30, seed=a.seed + 1000)
        if a.cache:
            np.savez(a.cache, images=data.images, uv=data.uv, vis=data.vis, h_images=held.images, h_uv=held.uv,
                     h_vis=held.vis)
    t1 = time.monotonic()
    print(f"rendered {len(data.images)} + {len(held.images)} images in {t1 - t0:.0f} s")
    net = train(data, epochs=a.epochs, seed=a.seed)
    ev = evaluate(net, held)
    print(f"trained in {time.monotonic() - t1:.0f} s; held out: {ev}")
    meta = {"pairs": a.pairs, "epochs": a.epochs, "seed": a.seed, "held_out": ev,
            "command": f"python -m hilstack.tools.train_keypoints --pairs {a.pairs} --epochs {a.epochs} --seed {a.seed}"}
    p = save_keypoint_net(net, a.out, meta)
    print(f"wrote {p} ({os.path.getsize(p) / 1024:.0f} KiB)")


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    main()
