"""GrBAL's inner-gradient cap and θ's meta learning rate chosen on training conditions only.

``python -m hilstack.learning.adaptation.tune_grbal --data OUT/data/seed<N>_training.npz --seed N [--out F.json]``

Issue 24: the cap quantile (``grbal_clip_quantile``) and θ's meta learning rate
(``grbal_meta_lr``) were chosen in an earlier session on open-loop losses with the test
perturbations in view. Here they are chosen with :func:`~hilstack.learning.adaptation.experiment.tune_rates`'
criterion and data: the online next-K error when GrBAL is replayed over held-out rollouts of
the *training* conditions (the demo's split, its first ``tune_rollouts``). MB is trained
exactly as the demo trains it on that data; GrBAL is meta-trained from it once per grid point
(:data:`CLIP_QUANTILES` x :data:`META_LRS`), and each grid point's error is GrBAL's at its
own best step-size multiplier (``rate_grid``, as the demo tunes it afterwards) with the error
at x1 beside it. The data must hold training conditions only (:func:`check_training_only`):
an episode of a test condition or of the held-out terrain is an error, so the choice cannot
see one. docs/adaptation.md, "GrBAL's cap and θ's rate on training conditions".
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hilstack.learning.adaptation.experiment import (
    AdaptationConfig,
    Trained,
    fit_mb,
    load_episodes,
    meta_train_grbal,
    rate_edge,
    tune_rates,
)
from hilstack.learning.adaptation.grbal import segments
from hilstack.learning.adaptation.model import AdaptiveMLP
from hilstack.learning.datasets import Episode, Transitions, split_episodes
from hilstack.tasks.perturbations import PerturbationPresets, PerturbationSettings, load_presets

#: the grid (issue 24, the fifth session's "What remains"): cap quantiles (None: no cap) and θ's
#: meta learning rates; the presets' values (0.5, 1e-4) are on it
CLIP_QUANTILES: tuple[float | None, ...] = (0.25, 0.5, 0.75, None)
META_LRS: tuple[float, ...] = (1e-4, 3e-4, 1e-3)
_TOL = 1e-9


def training_condition_error(ep: Episode, p: PerturbationPresets) -> str | None:
    """Why ``ep`` is not a rollout of a training condition (None when it is): its terrain (the
    condition's ``terrain``, else the name's ``<terrain>-c<i>`` prefix the demo gives) must be a
    training terrain, and its perturbation inside the presets' training range (no disabled
    leg or one of the training legs, payload, slope and heading offset within their ranges,
    no mocap offset). The test conditions all lie outside it (configs/perturbations)."""
    cond = dict(ep.meta.get("condition") or {})
    cond.pop("leg_speed_scale", None)  # the training data's drive-side factor; no test changes it
    terrain = cond.pop("terrain", None) or (ep.name.split("-c")[0] if "-c" in ep.name else None)
    if terrain not in p.training_terrains:
        return f"terrain {terrain!r} is not a training terrain {list(p.training_terrains)}"
    try:
        s = PerturbationSettings.model_validate(cond)
    except ValueError as e:
        return f"condition {cond} does not parse: {str(e).splitlines()[0]}"
    r = p.training
    if len(s.missing_leg) > 1 or any(leg not in r.missing_leg for leg in s.missing_leg):
        return f"missing_leg {s.missing_leg} is not one of the training legs {list(r.missing_leg)}"
    for f in ("payload_kg", "slope_deg", "heading_offset_deg"):
        lo, hi = getattr(r, f)
        v = getattr(s, f)
        if not lo - _TOL <= v <= hi + _TOL:
            return f"{f} {v} is outside the training range [{lo}, {hi}]"
    if any(abs(x) > _TOL for x in s.mocap_offset_m):
        return f"mocap_offset_m {list(s.mocap_offset_m)} (the training range has none)"
    return None


def check_training_only(episodes: Sequence[Episode], p: PerturbationPresets) -> None:
    """Raise a one-line ValueError naming the first episode that is not a training condition."""
    for ep in episodes:
        why = training_condition_error(ep, p)
        if why is not None:
            raise ValueError(f"tune_grbal: episode {ep.name!r} is not a training condition ({why}): "
                             "the choice must never see a test condition")


def grid_points(quantiles: Sequence[float | None], meta_lrs: Sequence[float],
                current: dict[str, Any]) -> list[tuple[float | None, float]]:
    """Every (quantile, rate) pair, nearest the presets' point first (in grid steps; the same
    set whatever the order): a run stopped early has compared the current values with their
    neighbours on both axes."""
    qi = {q: i for i, q in enumerate(quantiles)}
    li = {lr: i for i, lr in enumerate(meta_lrs)}
    q0, l0 = qi.get(current["clip_quantile"]), li.get(current["meta_lr"])
    pts = [(q, lr) for q in quantiles for lr in meta_lrs]
    if q0 is None or l0 is None:
        return pts
    return sorted(pts, key=lambda p: abs(qi[p[0]] - q0) + abs(li[p[1]] - l0))


def train_plain(cfg: AdaptationConfig, episodes: list[Episode], state_names: list[str], seed: int):
    """MB exactly as ``experiment.train`` trains it: (model, train rollouts, held-out rollouts, history)."""
    torch.manual_seed(seed)
    plain = AdaptiveMLP(state_names, 2, hidden=cfg.hidden, seed=seed)
    tr_eps, va_eps = split_episodes(episodes, cfg.val_fraction, seed)
    h = fit_mb(cfg, plain, tr_eps, va_eps, seed)
    return plain, tr_eps, va_eps, h


def tune_grbal(cfg: AdaptationConfig, episodes: list[Episode], state_names: list[str], seed: int,
               presets: PerturbationPresets, quantiles: Sequence[float | None] = CLIP_QUANTILES,
               meta_lrs: Sequence[float] = META_LRS, log: Callable[[str], None] = print,
               on_point: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """The grid's online errors and the choice (lowest error) on ``episodes``, training conditions only.

    Returns ``{"grid": [{clip_quantile, meta_lr, clip, errors: {rate: error}, rate, error,
    error_x1, steps_kept, cpu_s}], "choice": {clip_quantile, meta_lr}, "edge": {clip_quantile,
    meta_lr}, "warnings": [...], "current": the presets' point, "spread": (max − min) / min of
    the errors, "plain_history"}``. ``error`` is GrBAL's online error at its best multiplier of
    ``cfg.rate_grid`` (x1 when None). A choice on a grid's edge is flagged as ``tune_rates``
    flags a step size: the lowest cap quantile or either end of the learning rates (the optimum
    may lie beyond); "no cap" is the cap's upper end, beyond which there is nothing.
    ``on_point(partial result)`` after each grid point (the CLI writes it to disk)."""
    check_training_only(episodes, presets)
    quantiles, meta_lrs = tuple(quantiles), tuple(float(x) for x in meta_lrs)
    if not quantiles or not meta_lrs or len(set(quantiles)) != len(quantiles) or len(set(meta_lrs)) != len(meta_lrs):
        raise ValueError(f"tune_grbal: the grid must be non-empty and distinct, got {quantiles} x {meta_lrs}")
    plain, tr_eps, va_eps, h_plain = train_plain(cfg, episodes, state_names, seed)
    held = va_eps[:cfg.tune_rollouts]
    if not held:
        raise ValueError("tune_grbal needs held-out training rollouts: val_fraction is 0 or too small")
    seg = segments(tr_eps, cfg.M, cfg.K, stride=2)
    vseg = segments(va_eps, cfg.M, cfg.K, stride=4)
    s, _, n = Transitions.from_episodes(episodes).arrays()
    scale = np.maximum((n - s).std(0), 1e-6)
    current = {"clip_quantile": cfg.grbal_clip_quantile,
               "meta_lr": cfg.meta_lr if cfg.grbal_meta_lr is None else cfg.grbal_meta_lr}
    grid = []
    for q, lr in grid_points(quantiles, meta_lrs, current):
        c0 = time.process_time()
        meta, psi, clip, adapt_params, hist = meta_train_grbal(cfg, plain, seg, vseg, seed, clip_quantile=q,
                                                               theta_lr=lr)
        tr = Trained(plain, meta, psi, None, None, scale, adapt_params=adapt_params, clip=clip)
        rates = tune_rates(cfg, tr, held, methods=("grbal",))["grbal"]
        errs = rates["errors"]
        x1 = errs[1.0] if 1.0 in errs else None
        row = {"clip_quantile": q, "meta_lr": lr, "clip": clip, "errors": errs, "rate": rates["rate"],
               "error": float(errs[rates["rate"]]), "error_x1": x1,
               "steps_kept": hist[-1].get("best_step", hist[-1]["step"]), "cpu_s": time.process_time() - c0}
        grid.append(row)
        if on_point is not None:
            on_point({"grid": grid, "current": current, "partial": True})
        log(f"seed {seed} cap quantile {q} θ lr {lr:g}: cap {clip if clip is None else round(clip, 4)}, "
            f"{row['steps_kept']} steps kept, online error {row['error']:.5f} at x{row['rate']:g} "
            + "/".join(f"{e:.5f}" for e in errs.values()) + f" ({row['cpu_s']:.0f} s cpu)")
    best = min(grid, key=lambda r: r["error"] if np.isfinite(r["error"]) else np.inf)
    qs = [1.0 if q is None else q for q in quantiles]  # no cap sorts as the top quantile
    q_edge = rate_edge(tuple(qs), 1.0 if best["clip_quantile"] is None else best["clip_quantile"])
    lr_edge = rate_edge(meta_lrs, best["meta_lr"])
    warnings = []
    if q_edge == "lower":
        warnings.append(f"cap quantile {best['clip_quantile']} is the grid's lower edge: a lower cap may be better")
    elif q_edge == "upper" and best["clip_quantile"] is not None:
        warnings.append(f"cap quantile {best['clip_quantile']} is the grid's upper edge: no cap may be better")
    elif q_edge == "upper":
        warnings.append("no cap chosen, the grid's upper edge: the training conditions ask for no cap")
    if lr_edge is not None:
        beyond = "below" if lr_edge == "lower" else "above"
        warnings.append(f"θ's meta learning rate {best['meta_lr']:g} is the grid's {lr_edge} edge: its best may "
                        f"lie {beyond} the grid")
    for w in warnings:
        log(f"WARNING tune_grbal, seed {seed}: {w}")
    errs = [r["error"] for r in grid if np.isfinite(r["error"])]
    return {"grid": grid, "choice": {"clip_quantile": best["clip_quantile"], "meta_lr": best["meta_lr"]},
            "edge": {"clip_quantile": q_edge, "meta_lr": lr_edge}, "warnings": warnings, "current": current,
            "spread": (max(errs) - min(errs)) / min(errs) if errs else float("nan"),
            "plain_history": {k: h_plain[k] for k in ("best_epoch", "best_val", "epochs_run")},
            "held_out_rollouts": [e.name for e in held]}


def summarize(results: Sequence[dict[str, Any]]) -> str:
    """A markdown table of several seeds' :func:`tune_grbal` results (the grid points every seed
    has), mean ± sample std of the error, and the adoption rule: the lowest mean replaces the
    presets' point only if it is below it on every seed (else the criterion is flat for this
    grid and the presets stay)."""
    seeds = [r.get("seed", i) for i, r in enumerate(results)]
    rows = [{(g["clip_quantile"], g["meta_lr"]): g for g in r["grid"]} for r in results]
    common = [k for k in rows[0] if all(k in rw for rw in rows)]
    if not common:
        raise ValueError("summarize: no grid point is in every seed's result")
    cur = results[0]["current"]
    cur_key = (cur["clip_quantile"], cur["meta_lr"])
    mean = {k: float(np.mean([rw[k]["error"] for rw in rows])) for k in common}
    lines = ["| cap quantile | θ lr | " + " | ".join(f"seed {s}: error (x rate)" for s in seeds)
             + " | mean ± std |", "|---|---|" + "---|" * (len(seeds) + 1)]
    for k in sorted(common, key=mean.get):
        errs = [rw[k]["error"] for rw in rows]
        sd = float(np.std(errs, ddof=1)) if len(errs) > 1 else 0.0
        cells = " | ".join(f"{rw[k]['error']:.4f} (x{rw[k]['rate']:g})" for rw in rows)
        star = " (presets)" if k == cur_key else ""
        lines.append(f"| {k[0]}{star} | {k[1]:g} | {cells} | {mean[k]:.4f} ± {sd:.4f} |")
    best = min(common, key=mean.get)
    if cur_key not in common:
        verdict = "the presets' point is not in every seed's grid: no comparison"
    elif best == cur_key:
        verdict = "the presets' point has the lowest mean: keep it"
    elif all(rw[best]["error"] < rw[cur_key]["error"] for rw in rows):
        verdict = f"adopt cap quantile {best[0]}, θ lr {best[1]:g}: below the presets' point on every seed"
    else:
        verdict = (f"flat: the lowest mean (cap quantile {best[0]}, θ lr {best[1]:g}) is not below the presets' "
                   "point on every seed; keep the presets")
    spread = (max(mean.values()) - min(mean.values())) / min(mean.values())
    return "\n".join(lines + ["", f"{len(common)} grid points in every seed; spread of the means "
                               f"{100 * spread:.2f} %; {verdict}"])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m hilstack.learning.adaptation.tune_grbal",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--summarize", type=Path, nargs="+", metavar="JSON",
                    help="print the table of these --out files (one per seed) and the adoption rule, then exit")
    ap.add_argument("--data", type=Path, help="a demo run's OUT/data/seed<N>_training.npz")
    ap.add_argument("--seed", type=int, help="the seed the data was gathered with (the demo's split)")
    ap.add_argument("--preset", default="quick", help="the demo's preset whose sizes to use (quick | full | tiny)")
    ap.add_argument("--out", type=Path, help="write the result as JSON here (never over an existing file)")
    a = ap.parse_args(argv)
    if a.summarize:
        print(summarize([json.loads(f.read_text()) for f in a.summarize]))
        return
    if a.data is None or a.seed is None:
        raise SystemExit("tune_grbal: --data and --seed are required (or --summarize)")
    if a.out is not None and a.out.exists():
        raise SystemExit(f"tune_grbal: {a.out} exists; pick another --out")
    torch.set_num_threads(1)
    cfg = AdaptationConfig.from_preset(a.preset)
    p = load_presets(cfg.presets)
    episodes = load_episodes(a.data)
    from hilstack.learning.adaptation.experiment import RoachSim

    env = RoachSim(p.training_terrains[0], a.seed)
    names = env.state_names
    env.close()
    t0, c0 = time.monotonic(), time.process_time()
    def partial(r: dict[str, Any]) -> None:  # every grid point on disk as it ends: a run stopped early keeps them
        if a.out is not None:
            a.out.parent.mkdir(parents=True, exist_ok=True)
            a.out.write_text(json.dumps({**r, "seed": a.seed, "data": str(a.data)}, default=_json, indent=1))

    r = tune_grbal(cfg, episodes, names, a.seed, p, on_point=partial)
    r.update(seed=a.seed, data=str(a.data), wall_s=time.monotonic() - t0, cpu_s=time.process_time() - c0)
    print(f"choice: cap quantile {r['choice']['clip_quantile']}, θ lr {r['choice']['meta_lr']:g} "
          f"(current {r['current']}); spread of the grid's errors {100 * r['spread']:.2f} %; "
          f"{r['wall_s']:.0f} s wall, {r['cpu_s']:.0f} s cpu")
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(r, default=_json, indent=1))


def _json(x: Any) -> Any:
    return None if x is None else float(x)


if __name__ == "__main__":
    main()
