"""Why does one GrBAL step from θ* help so little? Meta-training variants on the same data.

``python -m hilstack.learning.adaptation.diagnose [--seed 0] [--steps 300] [--cache DIR]``: random data
as the quick preset gathers it (cached as .npz), the plain model, then meta-training variants
(which parameters are adapted, ψ's initial value and learning rate), each scored by GrBAL's
loss on the next K before / after its step on random rollouts under every test condition
(the demo's ``k_step_error_before_after``). docs/adaptation.md records the numbers.

``--closed-loop CKPT_DIR NAME...``: on the demo's paths under the named conditions, MB, GrBAL's
θ* without its step, and GrBAL, from a demo run's seed checkpoints (the same seed's data gives
the error scale; it reproduces the demo's MB and GrBAL numbers exactly).
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

import numpy as np
import torch

from hilstack.learning.adaptation import grbal
from hilstack.learning.adaptation.experiment import AdaptationConfig, RoachSim, _conditions, random_episodes
from hilstack.learning.adaptation.grbal import segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.adaptation.training import fit_plain
from hilstack.tasks.perturbations import PerturbationSettings, load_presets


def data(cfg: AdaptationConfig, seed: int, cache: Path):
    f = cache / f"diag_data_{cfg.presets}_seed{seed}_{cfg.conditions_per_terrain}x{cfg.rollouts_per_condition}x{cfg.before_after_rollouts}.pkl"
    if f.is_file():
        return pickle.loads(f.read_bytes())
    p = load_presets(cfg.presets)
    rng = np.random.default_rng(seed)
    envs: dict[str, RoachSim] = {}

    def env(t):
        if t not in envs:
            envs[t] = RoachSim(t, seed)
        return envs[t]
    train = []
    for terrain in p.training_terrains:
        for c in range(cfg.conditions_per_terrain):
            st = PerturbationSettings() if c == 0 else p.training.sample(rng)
            train += random_episodes(env(terrain), st, cfg.rollouts_per_condition, cfg.rollout_steps,
                                     seed=int(rng.integers(1 << 30)), name=f"{terrain}-c{c}")
    tests = {name: random_episodes(env(t), st, cfg.before_after_rollouts, cfg.rollout_steps,
                                   seed=int(rng.integers(1 << 30)), name=name)
             for name, (t, st) in _conditions(p).items()}
    names = env(p.training_terrains[0]).state_names
    for e in envs.values():
        e.close()
    out = (train, tests, names)
    cache.mkdir(parents=True, exist_ok=True)
    f.write_bytes(pickle.dumps(out))
    return out


def closed_loop(ckpt_dir: str, names: list[str], seed: int, cache: Path) -> None:
    from hilstack.learning.adaptation import load_adapter
    from hilstack.learning.adaptation.baselines import MbAdapter
    from hilstack.learning.adaptation.experiment import Trained, run_paths
    from hilstack.learning.datasets import Transitions

    cfg = AdaptationConfig.from_preset("full")
    train, _, _ = data(AdaptationConfig.from_preset("quick"), seed, cache)
    plain = load_adapter(Path(ckpt_dir) / f"seed{seed}_mb_de.pt").model
    g = load_adapter(Path(ckpt_dir) / f"seed{seed}_grbal.pt")
    s, _, n = Transitions.from_episodes(train).arrays()

    class T(Trained):
        def adapter(self, method, cfg):
            return MbAdapter(self.meta, window=cfg.M) if method == "theta_star" else super().adapter(method, cfg)

    tr = T(plain, g.model, g.psi, plain, None, np.maximum((n - s).std(0), 1e-6), adapt_params=g.adapt_params)
    conds = _conditions(load_presets(cfg.presets))
    for name in names:
        terrain, st = conds[name]
        env = RoachSim(terrain, seed)
        for method in ("mb", "theta_star", "grbal"):
            r = run_paths(cfg, env, st, tr, method)
            print(f"{name} {method}: completed {r['completed']} cost_per_m {r['cost_per_m']:.1f} "
                  f"k_step_error {r['k_step_error']:.3f}", flush=True)
        env.close()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m hilstack.learning.adaptation.diagnose", description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--cache", default="/tmp/adapt_diag")
    ap.add_argument("--presets", default="velociroach")
    ap.add_argument("--M", type=int, default=16)
    ap.add_argument("--conditions", type=int, default=6, help="per training terrain (quick: 6)")
    ap.add_argument("--rollouts", type=int, default=4, help="per condition (quick: 4)")
    ap.add_argument("--test-rollouts", type=int, default=3, help="per test condition (quick: 3)")
    ap.add_argument("--variants", default="all,all_psi_lr,last,last_psi_lr,last_psi1")
    ap.add_argument("--closed-loop", nargs="+", metavar=("CKPT_DIR", "NAME"))
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.closed_loop:
        return closed_loop(a.closed_loop[0], a.closed_loop[1:], a.seed, Path(a.cache))
    cfg = AdaptationConfig.from_preset("quick", presets=a.presets, M=a.M, conditions_per_terrain=a.conditions,
                                 rollouts_per_condition=a.rollouts, before_after_rollouts=a.test_rollouts)
    train, tests, names = data(cfg, a.seed, Path(a.cache))
    plain = AdaptiveMLP(names, 2, hidden=cfg.hidden, seed=a.seed)
    t0 = time.process_time()
    h = fit_plain(plain, train, epochs=cfg.plain_epochs, seed=a.seed)
    print(f"{len(train)} training rollouts; plain: loss {h[-1]:.4f} ({time.process_time() - t0:.0f} s cpu)", flush=True)
    seg = segments(train, cfg.M, cfg.K, stride=2)
    tsegs = {n: segments(e, cfg.M, cfg.K, stride=2) for n, e in tests.items()}
    last = [k for k in plain.params()][-2:]
    variants = {  # name: (adapt_params, psi_init, psi_lr)
        "all": (None, 0.01, None), "all_psi_lr": (None, 0.01, 1e-2),
        "last": (last, 0.01, None), "last_psi_lr": (last, 0.01, 1e-2), "last_psi1": (last, 1.0, 1e-2),
        "last_psi03": (last, 0.3, 1e-2),
        # θ stays the plain model's (lr 0): only the step size is meta-learned
        "all_psi_only": (None, 0.01, 1e-2), "last_psi_only": (last, 0.01, 1e-2),
    }
    for v in a.variants.split(","):
        names_, init, plr = variants[v]
        m = AdaptiveMLP.from_checkpoint(plain.to_checkpoint())
        t0 = time.process_time()
        psi, hist = grbal.meta_train(m, seg, steps=a.steps, meta_batch=cfg.meta_batch,
                                     lr=0.0 if v.endswith("psi_only") else cfg.meta_lr,
                                     psi_init=init, psi_lr=plr, seed=a.seed, adapt_params=names_)
        cells = []
        for n, ts in tsegs.items():
            e = grbal.evaluate(m, m.params(), psi, ts, names=names_)
            cells.append(f"{n} {e['before']:.3f}->{e['after']:.3f} ({100 * (e['after'] / e['before'] - 1):+.0f}%)")
        pm = {k: round(float(t.mean()), 4) for k, t in psi.items() if k in (names_ or psi)}
        print(f"{v}: train {hist[-1]['before']:.4f}->{hist[-1]['after']:.4f} psi {pm if names_ else ''} "
              f"({time.process_time() - t0:.0f} s cpu)\n   " + "; ".join(cells), flush=True)


if __name__ == "__main__":
    main()
