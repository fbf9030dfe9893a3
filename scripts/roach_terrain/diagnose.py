"""Why the image-conditioned roach model helps on one terrain only (issue 29): measurements.

usage: PYTHONPATH=<checkout> python scripts/roach_terrain/diagnose.py OUT [SEED] [ROLLOUTS]

Collects the terrain demo's random data (``random_episodes``: the quick preset's 40 rollouts x
50 steps per terrain, camera on; cached in OUT/data_seed<S>.npz) and prints

1. the image features in the model's input scale (each channel z-scored over all terrains, as
   ``EnsembleDynamics`` normalizes its inputs): the share of each feature's variance that lies
   between terrains (η²), how many principal directions carry it, nearest-centroid accuracy per
   frame and per episode mean (centroids from the other half of the episodes), and how much of
   the within-terrain variation the robot's tilt explains (R² of a linear fit on roll, pitch);
2. the terrains' dynamics in the data: speed per unit mean command and yaw rate per unit
   command difference (least squares on the transitions with |mean command| > 0.3), and the
   residual of the pooled fit against the per-terrain fits;
3. with ``--models``: the per-terrain, all-data and image-conditioned models (the demo's
   ``_fit``), each model's open-loop error ``H`` steps ahead on held-out rollouts split into
   along-track (speed) and cross-track (steering) components, per terrain.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from hilstack.learning.datasets import Episode
from hilstack.learning.dynamics import h_step_windows
from hilstack.learning.image_conditioned import (
    TerrainConfig,
    TerrainSim,
    _fit,
    random_episodes,
    with_features,
)
from hilstack.perception.terrain_features import RandomConvEncoder


def collect(cfg: TerrainConfig, seed: int, enc, path: Path, n: int, heldout: int):
    if path.exists():
        z = np.load(path, allow_pickle=True)
        return z["data"].item(), z["held"].item()
    env = TerrainSim(cfg, seed)
    data, held = {}, {}
    try:
        for i, t in enumerate(cfg.terrains):
            data[t] = random_episodes(env, t, enc, cfg, seed=1000 * seed + i, n=n, keep_images=0)[0]
            held[t] = random_episodes(env, t, enc, cfg, seed=1000 * seed + 500 + i, n=heldout)[0]
            print(f"collected {t}", flush=True)
    finally:
        env.close()
    pack = {t: [(e.states, e.actions, e.meta["features"]) for e in v] for t, v in data.items()}
    packh = {t: [(e.states, e.actions, e.meta["features"]) for e in v] for t, v in held.items()}
    np.savez(path, data=np.array(pack, dtype=object), held=np.array(packh, dtype=object))
    return pack, packh


def episodes(packed, terrain):
    return [Episode(s, a, name=f"{terrain}#{i}", meta={"terrain": terrain, "features": f})
            for i, (s, a, f) in enumerate(packed)]


def features_report(data, names):
    terr = list(data)
    F = {t: np.stack([f for _, _, f in data[t]]) for t in terr}  # [E, T+1, F]
    S = {t: np.stack([s for s, _, _ in data[t]]) for t in terr}
    allf = np.concatenate([F[t].reshape(-1, F[t].shape[-1]) for t in terr])
    mu, sd = allf.mean(0), allf.std(0) + 1e-9
    Z = {t: (F[t] - mu) / sd for t in terr}
    allz = (allf - mu) / sd
    tot = allz.var(0)
    within = np.mean([Z[t].reshape(-1, allz.shape[1]).var(0) for t in terr], axis=0)
    eta2 = 1 - within / tot
    print(f"features: {allz.shape[1]}; between-terrain share of variance (eta^2) per feature, z-scored: "
          f"median {np.median(eta2):.2f}, min {eta2.min():.2f}, max {eta2.max():.2f}")
    ev = np.linalg.svd(allz - allz.mean(0), compute_uv=False) ** 2
    ev = ev / ev.sum()
    print("  principal directions' share of variance: " + " ".join(f"{v:.3f}" for v in ev[:6]))
    # nearest centroid, centroids from the even episodes, tested on the odd ones
    cent = {t: Z[t][0::2].reshape(-1, allz.shape[1]).mean(0) for t in terr}

    def classify(x):
        d = np.stack([((x - cent[t]) ** 2).sum(-1) for t in terr])
        return d.argmin(0)

    for t_i, t in enumerate(terr):
        frames = Z[t][1::2].reshape(-1, allz.shape[1])
        per_frame = (classify(frames) == t_i).mean()
        per_ep = (classify(Z[t][1::2].mean(1)) == t_i).mean()
        # within-terrain variation explained by tilt (roll, pitch, their squares)
        s = S[t].reshape(-1, S[t].shape[-1])
        roll = np.arctan2(s[:, names.index("sin_roll")], s[:, names.index("cos_roll")])
        pitch = np.arctan2(s[:, names.index("sin_pitch")], s[:, names.index("cos_pitch")])
        X = np.column_stack([np.ones_like(roll), roll, pitch, roll**2, pitch**2, np.abs(roll), np.abs(pitch)])
        y = Z[t].reshape(-1, allz.shape[1])
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        r2 = 1 - ((y - X @ coef) ** 2).sum(0) / ((y - y.mean(0)) ** 2).sum(0)
        spread = np.sqrt(((y - y.mean(0)) ** 2).sum(-1).mean())
        gap = min(np.sqrt(((cent[t] - cent[u]) ** 2).sum()) for u in terr if u != t)
        print(f"  {t:10s} nearest-centroid accuracy per frame {per_frame:.2f}, per episode mean {per_ep:.2f}; "
              f"within-terrain RMS spread {spread:.2f} vs distance to the nearest other centroid {gap:.2f}; "
              f"tilt explains R^2 median {np.median(r2):.2f} of the within-terrain variation")


def dynamics_report(data, names, period_s=0.1):
    ivx, ivy, iwz = names.index("vx"), names.index("vy"), names.index("wz")
    icy, isy = names.index("cos_yaw"), names.index("sin_yaw")
    fits, pooled = {}, []
    for t, eps in data.items():
        rows = []
        for s, a, _ in eps:
            v = s[1:, ivx] * s[1:, icy] + s[1:, ivy] * s[1:, isy]  # forward speed after the step
            rows.append(np.column_stack([a.mean(1), a[:, 1] - a[:, 0], v, s[1:, iwz]]))
        r = np.concatenate(rows)
        r = r[np.abs(r[:, 0]) > 0.3]
        pooled.append(r)
        gv = np.linalg.lstsq(r[:, :1], r[:, 2], rcond=None)[0][0]
        X = np.column_stack([r[:, 1], r[:, 0] * r[:, 1]])
        gw = np.linalg.lstsq(X, r[:, 3], rcond=None)[0]
        fits[t] = (gv, gw, r)
        print(f"  {t:10s} speed {gv:.2f} m/s per unit mean command; yaw rate {np.degrees(gw[0]):.0f} deg/s per unit "
              f"command difference (+{np.degrees(gw[1]):.0f} x mean); {len(r)} transitions")
    P = np.concatenate(pooled)
    gvp = np.linalg.lstsq(P[:, :1], P[:, 2], rcond=None)[0][0]
    gwp = np.linalg.lstsq(np.column_stack([P[:, 1], P[:, 0] * P[:, 1]]), P[:, 3], rcond=None)[0]
    for t, (gv, gw, r) in fits.items():
        ev_own = np.sqrt(np.mean((r[:, 2] - gv * r[:, 0]) ** 2))
        ev_pool = np.sqrt(np.mean((r[:, 2] - gvp * r[:, 0]) ** 2))
        X = np.column_stack([r[:, 1], r[:, 0] * r[:, 1]])
        ew_own = np.degrees(np.sqrt(np.mean((r[:, 3] - X @ gw) ** 2)))
        ew_pool = np.degrees(np.sqrt(np.mean((r[:, 3] - X @ gwp) ** 2)))
        print(f"  {t:10s} residual speed {ev_own:.3f} (own fit) vs {ev_pool:.3f} m/s (pooled); "
              f"yaw rate {ew_own:.0f} vs {ew_pool:.0f} deg/s")


def split_error(model, eps, horizon, names):
    """RMS open-loop position error ``horizon`` steps ahead, split into the component along the
    robot's heading at the window's start and across it (m)."""
    start, actions, truth = h_step_windows(eps, horizon, max_starts=None)
    with torch.inference_mode():
        x = torch.as_tensor(start)
        for h in range(horizon):
            x = model.predict(x, torch.as_tensor(actions[:, h])).mean(0)
    d = x.numpy()[:, :2] - truth[:, -1, :2]
    c, s = start[:, names.index("cos_yaw")], start[:, names.index("sin_yaw")]
    along = d[:, 0] * c + d[:, 1] * s
    across = -d[:, 0] * s + d[:, 1] * c
    return 1e3 * np.sqrt((along**2).mean()), 1e3 * np.sqrt((across**2).mean())


def models_report(cfg, data, held, names, feat_names, acts, seed):
    eps = {t: episodes(data[t], t) for t in data}
    heps = {t: episodes(held[t], t) for t in held}
    every = [e for t in eps for e in eps[t]]
    models = {("per-terrain", t): _fit(cfg, seed, eps[t], names, acts)[0] for t in eps}
    models["all"] = _fit(cfg, seed, every, names, acts)[0]
    models["image"] = _fit(cfg, seed, [with_features(e) for e in every], names + feat_names, acts, held=feat_names)[0]
    H = cfg.mbrl.horizon
    print(f"  {H}-step position error on held-out rollouts, RMS mm, along-track / cross-track:")
    for t in heps:
        pt = split_error(models[("per-terrain", t)], heps[t], H, names)
        al = split_error(models["all"], heps[t], H, names)
        im = split_error(models["image"], [with_features(e) for e in heps[t]], H, names + feat_names)
        print(f"  {t:10s} per-terrain {pt[0]:.0f}/{pt[1]:.0f}; all data {al[0]:.0f}/{al[1]:.0f}; "
              f"image-conditioned {im[0]:.0f}/{im[1]:.0f}")
    print("  cross-terrain (per-terrain model of row, held-out rollouts of column), along/across mm:")
    for t in eps:
        print(f"  {t:10s} " + "; ".join(
            "{}/{}".format(*(f"{v:.0f}" for v in split_error(models[('per-terrain', t)], heps[u], H, names)))
            for u in heps))


def main():
    out = Path(sys.argv[1])
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    n = int(sys.argv[3]) if len(sys.argv) > 3 else 40
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    cfg = TerrainConfig.from_preset("quick", progress=False)
    enc = RandomConvEncoder(cfg.features, seed=cfg.encoder_seed)
    data, held = collect(cfg, seed, enc, out / f"data_seed{seed}_n{n}.npz", n, cfg.heldout_rollouts)
    from hilstack.drivers.registry import make_backend

    spec = make_backend(cfg.robot, "sim").spec
    names, acts = list(spec.state.names), list(spec.action.names)
    print(f"seed {seed}, {n} rollouts per terrain")
    features_report(data, names)
    print("dynamics (random data):")
    dynamics_report(data, names)
    if "--models" in sys.argv:
        torch.manual_seed(seed)
        models_report(cfg, data, held, names, enc.names, acts, seed)


if __name__ == "__main__":
    main()
