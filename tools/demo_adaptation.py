"""`hil demo adaptation [--quick|--full] --out DIR`: online adaptation on the sim VelociRoACH.

Meta-trains on the training terrains, runs MB, MB+DE, GrBAL, ReBAL and MOLe on each test
perturbation with the same planner and paths, and a switching scenario for MOLe against
k-shot and continued adaptation (learning/adaptation/experiment.py). Writes
``report.json`` (keys of issue 12), ``report.md``, PNG plots and the checkpoints.
Presets: default and ``--full`` (the quick run over 3 seeds), ``--quick``
(seed 0 of it; ≈ 9-15 CPU-min, estimated from the phases measured in docs/adaptation.md) and ``tiny`` (the CLI test). docs/adaptation.md.

``--suite gym``: the thesis' half-cheetah benchmarks instead (``learning/adaptation/gym_suite.py``;
report.json ``benchmarks: {env: {method: {return_mean, return_std, normalized, seeds}}}``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from hilstack.learning.adaptation.experiment import METHODS, SWITCHING_METHODS, AdaptationConfig, run


def config_for(quick: bool, full: bool, tiny: bool = False, seed: int = 0, **overrides: Any) -> AdaptationConfig:
    """The preset's config; ``overrides``: fields to change (experiments from Python, e.g.
    ``run_demo(out, quick=True, overrides={"train_leg_speed_scale": (0.6, 1.4)})``)."""
    if tiny:
        return AdaptationConfig.from_preset("tiny", seeds=(seed,), **overrides)
    if quick:
        return AdaptationConfig.from_preset("quick", seeds=(seed,), **overrides)
    return AdaptationConfig.from_preset("full", seeds=(seed, seed + 1, seed + 2), **overrides)


def _plots(r: dict[str, Any], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    files = []
    perts = list(r["perturbations"])
    methods = [m for m in METHODS if m in r["perturbations"][perts[0]]]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4))
    w = 0.8 / len(methods)
    for i, m in enumerate(methods):
        x = np.arange(len(perts)) + i * w
        axes[0].bar(x, [r["perturbations"][p][m]["progress_m"] for p in perts], w,
                    yerr=[r["perturbations"][p][m]["progress_m_std"] for p in perts], label=m)
        axes[1].bar(x, [r["perturbations"][p][m]["k_step_error"] for p in perts], w, label=m)
    for ax, t in zip(axes, ("progress along the paths, m (higher is better)", "online error on the next K (normalized)"), strict=True):
        ax.set_xticks(np.arange(len(perts)) + 0.4 - w / 2, perts, rotation=20)
        ax.set_title(t)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "perturbations.png", dpi=90)
    plt.close(fig)
    files.append("perturbations.png")

    ba = r["k_step_error_before_after"]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    x = np.arange(len(ba))
    ax.bar(x - 0.2, [v["before"] for v in ba.values()], 0.4, label="before (θ*)")
    ax.bar(x + 0.2, [v["after"] for v in ba.values()], 0.4, label="after (θ' = θ* − ψ⊙∇L)")
    ax.set_xticks(x, list(ba), rotation=20)
    ax.set_title("GrBAL: loss on the next K transitions (cf. thesis Figs 5.4, 5.5)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "k_step_before_after.png", dpi=90)
    plt.close(fig)
    files.append("k_step_before_after.png")

    sw = r["switching"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4))
    for m in SWITCHING_METHODS:
        axes[0].plot(sw[m]["reward_per_segment"], "o-", label=m)
    axes[0].set_xticks(range(len(sw["mole"]["conditions"])), sw["mole"]["conditions"], rotation=20)
    axes[0].set_title("switching: progress per segment (m; cf. thesis Figs 6.6, 6.7)")
    axes[0].legend()
    seed0 = r["per_seed"][0]["switching"]["mole"]
    posts = seed0.get("posterior_per_step", [])
    L = max((len(p) for p in posts), default=0)
    if L:
        P = np.zeros((len(posts), L))
        for t, p in enumerate(posts):
            P[t, :len(p)] = p
        axes[1].imshow(P.T, aspect="auto", interpolation="nearest", origin="lower", cmap="viridis")
        axes[1].set_xlabel("step")
        axes[1].set_ylabel("task")
        axes[1].set_title("MOLe task posterior (first seed)")
    fig.tight_layout()
    fig.savefig(out / "switching.png", dpi=90)
    plt.close(fig)
    files.append("switching.png")
    return files


#: progress along the paths is compared in bins of this size (m): methods that all complete
#: every path differ by centimetres at the goal, and cost per metre decides between them
PROGRESS_BIN_M = 0.05


def _rank(cell: dict[str, Any]) -> tuple[float, float, float]:
    """Sort key, lower is better: completions first (more is better), then progress along
    the paths (more is better, in :data:`PROGRESS_BIN_M` bins), then cost per metre (lower
    is better). Progress before cost: among robots that complete no path, one that never
    moves has cost 0 per metre (it sits on the line) and would otherwise rank first (issue
    24, item 1); with progress first a robot that does not move ranks below every robot
    that moved further along the path."""
    return (-cell["completed"], -float(np.floor(cell["progress_m"] / PROGRESS_BIN_M)), cell["cost_per_m"])


def ranking_line(r: dict[str, Any], other: str, method: str = "grbal") -> str:
    """How often ``method`` ranks above ``other`` (completions, progress, then cost per metre): on the
    means over seeds, and per seed."""
    perts = list(r["perturbations"])
    above = [p for p in perts if _rank(r["perturbations"][p][method]) < _rank(r["perturbations"][p][other])]
    per_seed = [sum(_rank(s["perturbations"][p][method]) < _rank(s["perturbations"][p][other]) for p in perts)
                for s in r.get("per_seed", [])]
    return (f"{method} ranks above {other} on {len(above)} of {len(perts)} ({', '.join(above) or 'none'}) on the "
            f"means; per seed: {per_seed}.")


def report_from_seeds(out: Path) -> dict[str, Any]:
    """The report of the seeds a run has finished so far (``<out>/seed<N>.json``), e.g. of
    a run stopped before its end: ``python -m hilstack.tools.demo_adaptation DIR`` writes
    ``report_seeds.md``."""
    from hilstack.learning.adaptation.experiment import aggregate

    out = Path(out)
    files = sorted(out.glob("seed*.json"))
    if not files:
        raise FileNotFoundError(f"no seed*.json in {out}: no seed has finished")
    per_seed = [json.loads(f.read_text()) for f in files]
    r = {**aggregate(per_seed), "per_seed": per_seed, "seeds": [f.stem[4:] for f in files], "elapsed_s": float("nan"),
         "config": {"paths": sorted({k.split("#")[0] for row in per_seed[0]["perturbations"].values()
                                     for cell in row.values() for k in cell["paths"]})}}
    (out / "report_seeds.md").write_text(report_markdown(r))
    return r


def report_markdown(r: dict[str, Any]) -> str:
    n = r["config"]["paths"]
    first = next(iter(r["perturbations"].values()))
    methods = [m for m in METHODS if m in first]
    runs = first[methods[0]].get("runs", len(n))
    lines = ["# Online adaptation (hil demo adaptation)", "",
             f"seeds {r['seeds']}, paths {n}, {runs} runs (starts) per condition, {r['elapsed_s'] / 60:.1f} min", "",
             "## Perturbations: progress along the paths (m, summed over the runs; the return)", "",
             "| perturbation | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for p, row in r["perturbations"].items():
        lines.append(f"| {p} | " + " | ".join(f"{row[m]['progress_m']:.2f} ± {row[m]['progress_m_std']:.2f}"
                                              for m in methods) + " |")
    lines += ["", "## Perturbations: cost per metre (completed runs) [online error on the next K]", "",
              "| perturbation | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for p, row in r["perturbations"].items():
        cells = [f"{row[m]['cost_per_m']:.1f} ± {row[m]['cost_per_m_std']:.1f} ({row[m]['completed']:.1f}/{runs}) "
                 f"[{row[m]['k_step_error']:.3f} ± {row[m]['k_step_error_std']:.3f}]" for m in methods]
        lines.append(f"| {p} | " + " | ".join(cells) + " |")
    if "grbal" in methods and "mb" in methods:
        lines += ["", ranking_line(r, "mb")]
        lines += [""] + [ranking_line(r, m) for m in ("mb_de", "rebal", "mole", "oracle") if m in methods]
    lines += ["", "## GrBAL: loss on the next K before / after the update", "",
              "| perturbation | before | after | change |", "|---|---|---|---|"]
    for p, v in r["k_step_error_before_after"].items():
        lines.append(f"| {p} | {v['before']:.4f} ± {v.get('before_std', 0):.4f} | {v['after']:.4f} ± "
                     f"{v.get('after_std', 0):.4f} | {100 * (v['after'] / v['before'] - 1):+.1f} % |")
    lines += ["", "## Switching: progress per segment (m)", "", "| method | " +
              " | ".join(r["switching"]["mole"]["conditions"]) + " | tasks created |",
              "|---" * (len(r["switching"]["mole"]["conditions"]) + 2) + "|"]
    for m, v in r["switching"].items():
        lines.append(f"| {m} | " + " | ".join(f"{x:.2f}" for x in v["reward_per_segment"]) +
                     f" | {format(v['tasks_created'], '.3g') if v['tasks_created'] is not None else '-'} |")
    per_seed = r.get("per_seed", [])
    # each seed by its own number (r["seeds"] lists them in run order), not its place in the list
    seeds = r.get("seeds", list(range(len(per_seed))))
    tuned = [(seed, s["training"]["rate_tuning"]) for seed, s in zip(seeds, per_seed, strict=False)
             if s.get("training", {}).get("rate_tuning")]
    if tuned:
        lines += ["", "## Step sizes tuned on held-out rollouts of the training conditions (multiplier: online "
                  "next-K error), per seed", ""]
        for i, tu in tuned:
            lines.append(f"- seed {i}: " + "; ".join(
                f"{m} x{v['rate']:g} (" + ", ".join(f"x{float(g):g}: {e:.4f}" for g, e in v["errors"].items()) + ")"
                for m, v in tu.items()))
        # a step on the grid's edge: its optimum may lie beyond the grid (x0: none is wanted)
        lines += [f"- **warning**, seed {i}: {v['warning']}" for i, tu in tuned
                  for v in tu.values() if v.get("warning")]
    lines += _training_lines(r.get("per_seed", []))
    lines += ["", "Plots: " + ", ".join(f"![]({f})" for f in r.get("plots", []))]
    return "\n".join(lines) + "\n"


def _training_lines(per_seed: list[dict[str, Any]]) -> list[str]:
    """Per seed: how long each training stopped at (early stopping) and the time per phase."""
    seeds = [s for s in per_seed if "timing" in s]
    if not seeds:
        return []
    lines = ["", "## Training (early stopping on held-out rollouts), per seed", "",
             "| seed | MB epochs (best) | MB held-out loss | GrBAL steps kept | GrBAL held-out next-K before/after | "
             "ReBAL steps kept | ReBAL held-out |", "|---|---|---|---|---|---|---|"]
    for i, s in enumerate(seeds):
        tr = s["training"]
        pl, g, rb = tr.get("plain_history", {}), tr["grbal_history"][-1], (tr["rebal_history"] or [{}])[-1]
        lines.append(f"| {i} | {pl.get('epochs_run')} ({pl.get('best_epoch')}) | {pl.get('best_val') or float('nan'):.4f} | "
                     f"{g.get('best_step', g.get('step'))} | {g['before']:.4f} / {g['after']:.4f} | "
                     f"{rb.get('best_step', rb.get('step'))} | {rb.get('val_loss', float('nan')):.4f} |")
    phases = list(seeds[0]["timing"])
    lines += ["", "## Time per phase: wall / CPU (s), per seed", "",
              "| phase | " + " | ".join(str(i) for i in range(len(seeds))) + " |", "|---" * (len(seeds) + 1) + "|"]
    for ph in phases + ["total"]:
        cells = []
        for s in seeds:
            v = s["timing"].get(ph) if ph != "total" else {
                k: sum(x[k] for x in s["timing"].values()) for k in ("wall_s", "cpu_s")}
            cells.append("-" if v is None else f"{v['wall_s']:.0f} / {v['cpu_s']:.0f}")
        lines.append(f"| {ph} | " + " | ".join(cells) + " |")
    return lines


def seed_task(cfg: AdaptationConfig, seed: int, out: str) -> dict[str, Any]:
    """One seed of the experiment as a sweep task (tools/sweep.py): what ``run`` keeps per seed."""
    import torch

    from hilstack.learning.adaptation.experiment import _jsonable, run_seed

    torch.set_num_threads(cfg.threads)
    return _jsonable(run_seed(cfg, seed, Path(out), print))


def run_seeds_on_sweep(cfg: AdaptationConfig, out: Path, log, ray: str, workers: int) -> dict[str, Any]:
    """``run`` with every seed a sweep task (``--ray``): each seed's result in ``out/tasks/`` as it
    finishes, a re-run does only the seeds missing; the same per-seed results and aggregate."""
    from dataclasses import asdict

    from hilstack.learning.adaptation.experiment import _jsonable, aggregate
    from hilstack.tools.sweep import Task, executor_from, run_sweep

    t0 = time.monotonic()
    tasks = [Task(f"seed{s}", seed_task, {"cfg": cfg, "seed": s, "out": str(out)}, threads=cfg.threads)
             for s in cfg.seeds]
    sw = run_sweep(tasks, out, executor=executor_from(ray), workers=workers, log=log)
    if sw["failed"]:
        raise RuntimeError(f"seeds {sorted(sw['failed'])} failed (their log tails above; {out / 'tasks'}); "
                           "the same command again re-runs only those")
    per_seed = [sw["results"][t.key] for t in tasks]
    for s, r in zip(cfg.seeds, per_seed, strict=True):
        (out / f"seed{s}.json").write_text(json.dumps(r))
    return {**aggregate(per_seed), "config": _jsonable(asdict(cfg)), "seeds": list(cfg.seeds),
            "elapsed_s": time.monotonic() - t0, "per_seed": per_seed, "sweep": sw["sweep"]}


def run_demo(out: Path, quick: bool = False, full: bool = False, seed: int = 0, tiny: bool = False,
             overrides: dict[str, Any] | None = None, ray: str | None = None, workers: int = 1) -> dict[str, Any]:
    """``ray``: None (the seeds one after another in this process) or ``local`` / a Ray address:
    every seed a Ray task (:func:`run_seeds_on_sweep`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config_for(quick, full, tiny, seed, **(overrides or {}))
    log_file = (out / "demo.log").open("w")

    def log(msg: str) -> None:
        # CPU seconds beside the wall clock: on a shared machine the wall clock says little
        line = f"[{time.strftime('%H:%M:%S')} cpu {time.process_time():.0f} s] {msg}"
        print(line, flush=True)
        log_file.write(line + "\n")
        log_file.flush()

    try:
        r = run(cfg, out, log) if ray is None else run_seeds_on_sweep(cfg, out, log, ray, workers)
        r["preset"] = "tiny" if tiny else ("quick" if quick else "full")
        r["overrides"] = overrides or {}
        r["cpu_s"] = time.process_time()
        (out / "report.json").write_text(json.dumps(r, indent=1))
        r["plots"] = _plots(r, out)
        (out / "report.json").write_text(json.dumps(r, indent=1))
        (out / "report.md").write_text(report_markdown(r))
        log(f"done in {r['elapsed_s'] / 60:.1f} min: {out / 'report.md'}")
    finally:
        log_file.close()
    return r


def run_gym_demo(out: Path, quick: bool = False, seed: int = 0, tiny: bool = False,
                 overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """`--suite gym`: the half-cheetah benchmarks (learning/adaptation/gym_suite.py)."""
    from hilstack.learning.adaptation import gym_suite

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = gym_suite.config_for(quick, tiny, seed, **(overrides or {}))
    with (out / "demo.log").open("w") as log_file:
        def log(msg: str) -> None:
            line = f"[{time.strftime('%H:%M:%S')} cpu {time.process_time():.0f} s] {msg}"
            print(line, flush=True)
            log_file.write(line + "\n")
            log_file.flush()

        r = gym_suite.run(cfg, out, log, preset="tiny" if tiny else ("quick" if quick else "full"))
        log(f"done in {r['elapsed_s'] / 60:.1f} min: {out / 'report.md'}")
    return r


def cli_adaptation(out: Path, quick: bool = False, full: bool = False, seed: int = 0, suite: str = "roach",
                   ray: str | None = None, workers: int = 1) -> None:
    """Entry of `hil demo adaptation` (tools/cmd_demo.py OTHER_DEMOS); ``suite``: roach | gym."""
    if suite == "gym":
        from hilstack.learning.adaptation.gym_suite import summary_lines

        r = run_gym_demo(out, quick=quick, seed=seed)
        for line in summary_lines(r):
            print(line)
        print(f"report: {Path(out) / 'report.md'}")
        return
    if suite != "roach":
        raise ValueError(f"unknown adaptation suite {suite!r} (roach | gym)")
    r = run_demo(out, quick=quick, full=full, seed=seed, ray=ray, workers=workers)
    for p, row in r["perturbations"].items():
        best = min(row, key=lambda m: _rank(row[m]))
        print(f"{p}: best {best}; progress m " + ", ".join(f"{m} {row[m]['progress_m']:.2f}" for m in row))


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.demo_adaptation",
                                 description="The report tables of the seeds a demo run finished so far "
                                             "(the demo itself: hil demo adaptation).")
    ap.add_argument("out_dir", type=Path, help="the demo's output directory")
    print(report_markdown(report_from_seeds(ap.parse_args(argv).out_dir)))


if __name__ == "__main__":
    main()
