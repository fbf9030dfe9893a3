"""Image-feature variants of the terrain experiment on one seed's data (issue 29 diagnosis).

usage: PYTHONPATH=<checkout> python scripts/roach_terrain/variants.py OUT SEED [VARIANT ...] [--tip W]

The demo's data (diagnose.py's cache OUT/data_seed<S>_n40.npz, made when missing), the demo's
per-terrain and all-data models, and the image-conditioned model with its features as
* ``raw``: the encoder's 16 features of the current image (the demo before this change);
* ``pca``: the same, projected on the training features' principal directions that carry
  ≥ 1 % of their variance and whitened (the network's first layer sees a few unit-variance
  inputs instead of 16 near-collinear copies; ``perception.terrain_features.FeatureWhitening``);
* ``avg<k>``: the raw features averaged over the episode's last k images;
* ``pcaavg<k>``: both.
Each model drives the paths straight, left, right on every terrain; prints cost per metre
(completions) and writes OUT/variants_seed<S>.json.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from diagnose import collect, episodes  # noqa: E402

from hilstack.control.costs import summarize_paths  # noqa: E402
from hilstack.control.paths import make_path  # noqa: E402
from hilstack.learning.datasets import Episode  # noqa: E402
from hilstack.learning.image_conditioned import (  # noqa: E402
    FeatureStream,
    TerrainConfig,
    TerrainSim,
    _fit,
    _mpc,
    drive_path,
    running_mean,
    with_features,
)
from hilstack.perception.terrain_features import FeatureWhitening, RandomConvEncoder  # noqa: E402


def main():
    out, seed = Path(sys.argv[1]), int(sys.argv[2])
    args = sys.argv[3:]
    tip = None
    if "--tip" in args:
        i = args.index("--tip")
        tip = float(args[i + 1])
        del args[i:i + 2]
    variants = args or ["raw", "pca", "avg10", "pcaavg10"]
    torch.set_num_threads(1)
    cfg = TerrainConfig.from_preset("quick", progress=False, paths=("straight", "left", "right"))
    if tip is not None:
        cfg = dataclasses.replace(cfg, mbrl=dataclasses.replace(cfg.mbrl, tip_weight=tip))
    enc = RandomConvEncoder(cfg.features, seed=cfg.encoder_seed)
    data, _ = collect(cfg, seed, enc, out / f"data_seed{seed}_n40.npz", 40, cfg.heldout_rollouts)
    eps = {t: episodes(data[t], t) for t in data}
    every = [e for t in eps for e in eps[t]]
    torch.manual_seed(seed)
    env = TerrainSim(cfg, seed)
    names, acts = env.state_names, list(env.action_space.names)
    rows = {}
    for t in cfg.terrains:
        rows[("per-terrain", t)] = (_fit(cfg, seed, eps[t], names, acts)[0], names, None)
    rows["all"] = (_fit(cfg, seed, every, names, acts)[0], names, None)
    for v in variants:
        k = int(v.split("avg")[1]) if "avg" in v else 1
        pca = FeatureWhitening(np.concatenate([running_mean(e.meta["features"], k) for e in every])) if v.startswith("pca") else None
        tr = (lambda f: f) if pca is None else pca

        def feat_eps(es, k=k, tr=tr):
            return [Episode(e.states, e.actions, name=e.name, meta={"features": tr(running_mean(e.meta["features"], k))})
                    for e in es]
        fe = feat_eps(every)
        fn = [f"img_{i}" for i in range(fe[0].meta["features"].shape[1])]
        model = _fit(cfg, seed, [with_features(e) for e in fe], names + fn, acts, held=fn)[0]

        def make_feats(k=k, tr=tr):
            return FeatureStream(enc.encode, tr, k)
        rows[v] = (model, names + fn, make_feats)
        print(f"seed {seed} {v}: {len(fn)} features", flush=True)
    res = {}
    t0 = time.monotonic()
    try:
        for t in cfg.terrains:
            for key, (model, snames, mk) in rows.items():
                if isinstance(key, tuple) and key[1] != t:
                    continue
                row = key[0] if isinstance(key, tuple) else key
                make = _mpc(model, cfg, env, snames)
                r = {p: drive_path(env, t, make(make_path(p, scale=cfg.path_scale)), p, cfg, mk() if mk else None)
                     for p in cfg.paths}
                s = summarize_paths(r)
                res.setdefault(row, {})[t] = {"summary": s, "paths": {p: {k2: v2 for k2, v2 in x.items() if k2 != "xy"}
                                                                      for p, x in r.items()}}
                print(f"seed {seed} {t} {row}: {s['cost_per_m']:.1f}/m ({s['completed']}/{len(cfg.paths)}) "
                      + " ".join(f"{p}={x['cost_per_m']:.0f}" for p, x in r.items()), flush=True)
    finally:
        env.close()
    (out / f"variants_seed{seed}{'' if tip is None else f'_tip{tip:g}'}.json").write_text(
        json.dumps(res, default=float))
    print(f"seed {seed}: evaluation {time.monotonic() - t0:.0f} s")


if __name__ == "__main__":
    main()
