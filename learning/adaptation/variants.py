"""GrBAL meta-training variants on a demo run's saved training data (docs/adaptation.md, "Why").

``python -m learning.adaptation.variants --data OUT/data/seed0_training.npz [--seed 0] VARIANT...``

Trains MB exactly as the demo does on that data (same split, same early stopping), then
meta-trains each variant from it and prints, on the held-out segments and on fresh random
rollouts of every test condition (4 per condition, drawn from a fixed generator; cached
under ``--cache``), the next-K loss after GrBAL's step relative to before it (θ*) and
relative to MB's θ. Variants: ``default`` (the demo's), ``theta1e-4`` (θ's meta learning
rate 1e-4 instead of 1e-3), ``psionly`` (θ = MB's, only ψ learned), ``all`` (every parameter
adapted, not just the output layer), ``psi0.1`` (ψ initialized at 0.1).
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

import numpy as np
import torch

from learning.adaptation import grbal
from learning.adaptation.experiment import (
    AdaptationConfig,
    RoachSim,
    _conditions,
    fit_mb,
    load_episodes,
    random_episodes,
)
from learning.adaptation.grbal import segments
from learning.adaptation.model import AdaptiveMLP
from learning.adaptation.training import split_episodes
from sim_backends.velociroach.perturbations import load_presets

VARIANTS = ("default", "theta1e-4", "psionly", "all", "psi0.1")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/adapt_variants"))
    ap.add_argument("variants", nargs="+", choices=VARIANTS)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = AdaptationConfig.quick()
    episodes = load_episodes(a.data)
    p = load_presets(cfg.presets)
    a.cache.mkdir(parents=True, exist_ok=True)
    f = a.cache / f"tests_seed{a.seed}.pkl"
    if f.exists():
        tests = pickle.loads(f.read_bytes())
    else:
        rng = np.random.default_rng(1234)
        envs: dict[str, RoachSim] = {}
        tests = {}
        for name, (terrain, st) in _conditions(p).items():
            if terrain not in envs:
                envs[terrain] = RoachSim(terrain, a.seed)
            tests[name] = random_episodes(envs[terrain], st, 4, cfg.rollout_steps, seed=int(rng.integers(1 << 30)),
                                          name=name)
        for env in envs.values():
            env.close()
        f.write_bytes(pickle.dumps(tests))
    env = RoachSim(p.training_terrains[0], a.seed)
    names = env.state_names
    env.close()
    plain = AdaptiveMLP(names, 2, hidden=cfg.hidden, seed=a.seed)
    t = time.process_time()
    h = fit_mb(cfg, plain, episodes, a.seed)
    print(f"MB: {h['epochs_run']} epochs (best {h['best_epoch']}), held-out {h['best_val']:.4f}, "
          f"cpu {time.process_time() - t:.0f} s", flush=True)
    tr_eps, va_eps = split_episodes(episodes, cfg.val_fraction, a.seed)
    seg, vseg = segments(tr_eps, cfg.M, cfg.K, stride=2), segments(va_eps, cfg.M, cfg.K, stride=4)
    tsegs = {n: segments(e, cfg.M, cfg.K, stride=2) for n, e in tests.items()}
    zero = {k: torch.zeros_like(v) for k, v in plain.params().items()}
    for v in a.variants:
        m = AdaptiveMLP.from_checkpoint(plain.to_checkpoint())
        sub = None if v == "all" else list(m.params())[-2:]
        lr = {"theta1e-4": 1e-4, "psionly": 0.0}.get(v, cfg.meta_lr)
        psi_init = 0.1 if v == "psi0.1" else cfg.psi_init
        t = time.process_time()
        psi, hist = grbal.meta_train(m, seg, steps=cfg.meta_steps, meta_batch=cfg.meta_batch, lr=lr, psi_init=psi_init,
                                     psi_lr=cfg.psi_lr, seed=a.seed, adapt_params=sub, val=vseg,
                                     eval_every=cfg.meta_eval_every, patience=cfg.meta_patience)
        ev = grbal.evaluate(m, m.params(), psi, vseg, names=sub)
        mb = grbal.evaluate(plain, plain.params(), zero, vseg)["before"]
        row = [f"held-out {ev['before']:.4f} -> {ev['after']:.4f} (MB {mb:.4f})"]
        for n, s in tsegs.items():
            e = grbal.evaluate(m, m.params(), psi, s, names=sub)
            b = grbal.evaluate(plain, plain.params(), zero, s)["before"]
            row.append(f"{n} {100 * (e['after'] / e['before'] - 1):+.1f}% (vs MB {100 * (e['after'] / b - 1):+.1f}%)")
        print(f"{v}: {hist[-1].get('best_step')} steps kept, cpu {time.process_time() - t:.0f} s | " + " | ".join(row),
              flush=True)


if __name__ == "__main__":
    main()
