"""GrBAL meta-training variants on a demo run's saved training data (docs/adaptation.md, "Why").

``python -m hilstack.learning.adaptation.variants --data OUT/data/seed0_training.npz [--seed 0] VARIANT...``

Trains MB exactly as the demo does on that data (same split, same early stopping), then
meta-trains each variant from it and prints, on the held-out segments and on fresh random
rollouts of every test condition (12 per condition: 4 from generator 1234 and 8 from
generator 4321; cached under ``--cache``), the next-K loss before (θ*) and after GrBAL's
step, the change, and the change relative to MB's θ. Variants (θ's meta learning rate /
inner-gradient cap as a quantile of the training windows' norms at the warm start):
``default`` (the demo's presets: 1e-4 / 0.5), ``uncapped`` (the demo before: 1e-3 / none),
``theta1e-4`` (1e-4 / none), ``cap1e-3`` (1e-3 / 0.5), ``cap95`` (3e-4 / 0.95),
``psionly`` (θ = MB's, only ψ learned; no cap), ``all`` (every parameter adapted, not just
the output layer; 1e-3 / none), ``psi0.1`` (ψ initialized at 0.1; 1e-3 / none).
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

import numpy as np
import torch

from hilstack.learning.adaptation import grbal
from hilstack.learning.adaptation.experiment import (
    AdaptationConfig,
    RoachSim,
    _conditions,
    fit_mb,
    load_episodes,
    random_episodes,
)
from hilstack.learning.adaptation.grbal import segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.datasets import split_episodes
from hilstack.tasks.perturbations import load_presets

# variant -> (θ's meta learning rate, cap quantile or None)
VARIANTS = {"default": (1e-4, 0.5), "uncapped": (1e-3, None), "theta1e-4": (1e-4, None), "cap1e-3": (1e-3, 0.5),
            "cap95": (3e-4, 0.95), "psionly": (0.0, None), "all": (1e-3, None), "psi0.1": (1e-3, None)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m hilstack.learning.adaptation.variants", description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/adapt_variants"))
    ap.add_argument("variants", nargs="+", choices=list(VARIANTS))
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = AdaptationConfig.from_preset("quick")
    episodes = load_episodes(a.data)
    p = load_presets(cfg.presets)
    a.cache.mkdir(parents=True, exist_ok=True)
    tests: dict[str, list] = {}
    for gen_seed, n in ((1234, 4), (4321, 8)):
        f = a.cache / f"tests_seed{a.seed}_{gen_seed}x{n}.pkl"
        if f.exists():
            part = pickle.loads(f.read_bytes())
        else:
            rng = np.random.default_rng(gen_seed)
            envs: dict[str, RoachSim] = {}
            part = {}
            for name, (terrain, st) in _conditions(p).items():
                if terrain not in envs:
                    envs[terrain] = RoachSim(terrain, a.seed)
                part[name] = random_episodes(envs[terrain], st, n, cfg.rollout_steps,
                                             seed=int(rng.integers(1 << 30)), name=name)
            for env in envs.values():
                env.close()
            f.write_bytes(pickle.dumps(part))
        for name, eps in part.items():
            tests[name] = tests.get(name, []) + eps
    env = RoachSim(p.training_terrains[0], a.seed)
    names = env.state_names
    env.close()
    plain = AdaptiveMLP(names, 2, hidden=cfg.hidden, seed=a.seed)
    t = time.process_time()
    tr_eps, va_eps = split_episodes(episodes, cfg.val_fraction, a.seed)
    h = fit_mb(cfg, plain, tr_eps, va_eps, a.seed)
    print(f"MB: {h['epochs_run']} epochs (best {h['best_epoch']}), held-out {h['best_val']:.4f}, "
          f"cpu {time.process_time() - t:.0f} s", flush=True)
    seg, vseg = segments(tr_eps, cfg.M, cfg.K, stride=2), segments(va_eps, cfg.M, cfg.K, stride=4)
    tsegs = {n: segments(e, cfg.M, cfg.K, stride=2) for n, e in tests.items()}
    zero = {k: torch.zeros_like(v) for k, v in plain.params().items()}
    last = list(plain.params())[-2:]
    norms = grbal.gradient_norms(plain, plain.params(), seg, last)
    print(f"inner-gradient norms of the training windows (output layer, MB's θ): median {np.median(norms):.4f}, "
          f"95 % {np.quantile(norms, 0.95):.4f}; of the test windows (median / 90 %): " + ", ".join(
              f"{n} {np.median(x):.2f}/{np.quantile(x, 0.9):.2f}"
              for n, x in ((n, grbal.gradient_norms(plain, plain.params(), s, last)) for n, s in tsegs.items())),
          flush=True)
    for v in a.variants:
        m = AdaptiveMLP.from_checkpoint(plain.to_checkpoint())
        sub = None if v == "all" else last
        lr, q = VARIANTS[v]
        clip = None if q is None else float(np.quantile(norms, q))
        psi_init = 0.1 if v == "psi0.1" else cfg.psi_init
        t = time.process_time()
        psi, hist = grbal.meta_train(m, seg, steps=cfg.meta_steps, meta_batch=cfg.meta_batch, lr=lr, psi_init=psi_init,
                                     psi_lr=cfg.psi_lr, seed=a.seed, adapt_params=sub, val=vseg,
                                     eval_every=cfg.meta_eval_every, patience=cfg.meta_patience, clip=clip)
        ev = grbal.evaluate(m, m.params(), psi, vseg, names=sub, clip=clip)
        mb = grbal.evaluate(plain, plain.params(), zero, vseg)["before"]
        row = [f"held-out {ev['before']:.4f} -> {ev['after']:.4f} (MB {mb:.4f})"]
        for n, s in tsegs.items():
            e = grbal.evaluate(m, m.params(), psi, s, names=sub, clip=clip, max_tasks=len(s))
            b = grbal.evaluate(plain, plain.params(), zero, s, max_tasks=len(s))["before"]
            row.append(f"{n} {e['before']:.3f} -> {e['after']:.3f} {100 * (e['after'] / e['before'] - 1):+.1f}% "
                       f"(vs MB {b:.3f}: {100 * (e['after'] / b - 1):+.1f}%)")
        psi_m = [round(float(psi[k].mean()), 4) for k in last]
        print(f"{v} (lr {lr:g}, cap {clip if clip is None else round(clip, 4)}): {hist[-1].get('best_step')} steps kept, "
              f"ψ mean {psi_m}, cpu {time.process_time() - t:.0f} s | " + " | ".join(row), flush=True)


if __name__ == "__main__":
    main()
