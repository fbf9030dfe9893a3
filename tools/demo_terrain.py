"""`hil demo roach --part terrain [--quick|--full] --out DIR`: the image-conditioned roach
model on four terrains beside the per-terrain and the all-data models (thesis ch. 3.3,
Table 3.2; learning/image_conditioned.py, docs/mbrl.md "Image-conditioned dynamics").

Each seed writes ``OUT/runs/seed<n>.json`` when it finishes and is reused by a later run with
the same configuration (an interrupted demo continues). Several processes may share one OUT:
a seed another process has claimed (``seed<n>.claim``) is waited for, not computed twice, so
``for i in 1 2 3; do hil demo roach --part terrain --quick --out OUT & done`` runs the seeds
side by side. ``report.json``, ``report.md``, ``table_3_2_images.png`` (cost per metre, mean
± std over seeds, per terrain and model) and ``camera.png`` (what the robot saw on each
terrain) cover the seeds. A claim older than ``--stale`` is another process that died: delete
the ``.claim`` file to recompute that seed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from hilstack.learning.image_conditioned import ROWS, TerrainConfig, aggregate, run_seed


def config_for(quick: bool, full: bool, seed: int) -> TerrainConfig:
    """The demo's config: ``--quick``/``--full`` presets, else the default ``TerrainConfig``
    (100 rollouts per terrain, half ``--full``'s 200; 60 epochs; the full paths straight, left
    and right), seeds ``seed, seed+1, seed+2``."""
    seeds = (seed, seed + 1, seed + 2)
    if quick:
        return TerrainConfig.from_preset("quick", seeds=seeds)
    if full:
        return TerrainConfig.from_preset("full", seeds=seeds)
    return TerrainConfig(seeds=seeds)


def _conf(cfg: TerrainConfig) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=list))


def _seed_result(cfg: TerrainConfig, seed: int, runs: Path, encoder, wait_s: float) -> dict[str, Any] | None:
    """The seed's result: read from ``runs`` (same config), computed here, or waited for while
    another process holds its claim (None if it does not finish within ``wait_s``)."""
    done, claim = runs / f"seed{seed}.json", runs / f"seed{seed}.claim"
    conf = _conf(cfg)
    deadline = time.monotonic() + wait_s
    while True:
        if done.exists():
            d = json.loads(done.read_text())
            if d.get("config") != conf:
                raise ValueError(f"{done} holds a run of another configuration: use another --out "
                                 "(results are never overwritten)")
            return d
        try:
            fd = os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            if time.monotonic() > deadline:
                return None
            time.sleep(10.0)
            continue
        os.write(fd, f"{os.getpid()}\n".encode())
        os.close(fd)
        try:
            r = run_seed(cfg, seed, encoder)
            images = r.pop("images")
            np.savez_compressed(runs / f"seed{seed}_images.npz", **images)
            tmp = runs / f"seed{seed}.partial.json"
            tmp.write_text(json.dumps({"config": conf, **r}, default=float))
            tmp.replace(done)
        finally:
            claim.unlink(missing_ok=True)


def run(out: Path, cfg: TerrainConfig, wait_s: float = 4 * 3600.0) -> dict[str, Any]:
    """Every seed (computed, reused or waited for), the aggregate, and the report files."""
    import torch

    from hilstack.perception.terrain_features import RandomConvEncoder

    torch.set_num_threads(cfg.threads)
    out = Path(out)
    runs = out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    encoder = RandomConvEncoder(cfg.features, seed=cfg.encoder_seed)
    # first every seed no other process holds, then wait for those another one computes
    got = {s: _seed_result(cfg, s, runs, encoder, 0.0) for s in cfg.seeds}
    per_seed = []
    for s in cfg.seeds:
        r = got[s] or _seed_result(cfg, s, runs, encoder, wait_s)
        if r is None:
            raise TimeoutError(f"seed {s} is claimed by another process that has not finished within "
                               f"{wait_s:.0f} s ({runs / f'seed{s}.claim'}; delete it if that process died)")
        per_seed.append(r)
    report = {"config": _conf(cfg), "rows": list(ROWS), "terrains": list(cfg.terrains), "seeds": list(cfg.seeds),
              "encoder": {"kind": "fixed random conv net + fixed random projection (perception/terrain_features.py)",
                          "features": cfg.features, "seed": cfg.encoder_seed,
                          "whiten_min_share": cfg.whiten_min_share, "average_frames": cfg.average_frames,
                          "model_inputs": {str(r["seed"]): r.get("features", {}).get("model_inputs") for r in per_seed}},
              **aggregate(cfg, per_seed),
              "seed_wall_s": {str(r["seed"]): r["wall_s"] for r in per_seed},
              "wall_s": time.monotonic() - t0}
    (out / "report.json").write_text(json.dumps(report, indent=1, default=float))
    files = write_plots(report, out, runs)
    (out / "report.md").write_text(report_markdown(report, files))
    return report


def write_plots(report: dict[str, Any], out: Path, runs: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    terrains, rows = report["terrains"], report["rows"]
    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(terrains))
    w = 0.8 / len(rows)
    for i, row in enumerate(rows):
        cells = [report["table"][row][t]["cost_per_m"] for t in terrains]
        ax.bar(x + (i - (len(rows) - 1) / 2) * w, [c["mean"] for c in cells], w,
               yerr=[c["std"] for c in cells], capsize=3, label=row)
    ax.set_xticks(x, terrains)
    ax.set_yscale("log")  # a failing controller costs 100x a completing one
    ax.set_ylabel("cost per metre (mean ± std over seeds; lower is better)")
    ax.set_title("Table 3.2, terrains: per-terrain vs all-data vs image-conditioned")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "table_3_2_images.png", dpi=80)
    plt.close(fig)
    files = ["table_3_2_images.png"]
    img = runs / f"seed{report['seeds'][0]}_images.npz"
    if img.exists():
        with np.load(img) as z:
            strips = [np.concatenate(list(z[t][:4]), axis=1) for t in terrains if t in z]
        if strips:
            from PIL import Image

            Image.fromarray(np.concatenate(strips, axis=0)).save(out / "camera.png")
            files.append("camera.png")
    return files


def _cell(c: dict[str, Any]) -> str:
    m, d = c["cost_per_m"], c["completed"]
    return f"{m['mean']:.1f} ± {m['std']:.1f} ({d['mean']:.1f}/{c['paths']})"


def report_markdown(r: dict[str, Any], files: list[str]) -> str:
    c = r["config"]
    lines = [f"# Image-conditioned dynamics on terrains (thesis ch. 3.3, Table 3.2): {len(r['seeds'])} seeds", "",
             f"{c['rollouts_per_terrain']} random rollouts x {c['rollout_steps']} steps per terrain and seed (the "
             f"same data for every model), {c['epochs']} epochs; paths {', '.join(c['paths'])} (scale "
             f"{c['path_scale']}) at speed {c['speed']}; camera {c['camera_px']}x{c['camera_px']}, "
             f"{c['features']} image features (fixed random conv net + random projection)"
             + (f", PCA-whitened to the directions with >= {c['whiten_min_share']:.0%} of their variance "
                f"(model inputs per seed: {r['encoder']['model_inputs']})" if c.get("whiten_min_share") else "")
             + (f", averaged over the last {c['average_frames']} images" if c.get("average_frames", 1) > 1 else "")
             + ".", "",
             "Cost per metre of progress, mean ± std over seeds (paths completed, mean over seeds); lower is "
             "better, and more completions beat a lower cost.", "",
             "| model | " + " | ".join(r["terrains"]) + " |", "|---|" + "---|" * len(r["terrains"])]
    for row in r["rows"]:
        lines.append(f"| {row} | " + " | ".join(_cell(r["table"][row][t]) for t in r["terrains"]) + " |")
    if r.get("prediction_rms_mm"):
        pr = r["prediction_rms_mm"]
        lines += ["", f"Open-loop position error {c['mbrl']['horizon']} steps ahead on {c['heldout_rollouts']} held-out "
                  "random rollouts per terrain (RMS, mm; mean ± std over seeds; the planner's horizon):", "",
                  "| model | " + " | ".join(r["terrains"]) + " |", "|---|" + "---|" * len(r["terrains"])]
        for row in r["rows"]:
            lines.append(f"| {row} | " + " | ".join(f"{pr[row][t]['mean']:.1f} ± {pr[row][t]['std']:.1f}"
                                                    for t in r["terrains"]) + " |")
    ch = r["checks"]
    lines += ["", "Checks (issue 29): the image-conditioned model within the per-terrain model's spread "
              "(as many completions, |mean difference| ≤ the per-terrain std) and better than the all-data "
              "model (completions, then mean cost per metre):", ""]
    for t in r["terrains"]:
        lines.append(f"- {t}: within spread {ch[t]['within_per_terrain_spread']}, better than all data "
                     f"{ch[t]['better_than_all_data']} (per seed: {ch[t]['seeds_image_better_than_all_data']} "
                     f"of {len(r['seeds'])})")
    lines += ["", f"Within spread on {len(r['within_spread_terrains'])} of {len(r['terrains'])} terrains; better "
              f"than all data on {len(r['better_than_all_data_terrains'])}.", "",
              f"Wall time: {r['wall_s']:.0f} s (seeds reused from OUT/runs count as 0; per seed: "
              + ", ".join(f"{s}: {w['total']:.0f} s" for s, w in r["seed_wall_s"].items()) + ").", ""]
    lines += [f"![{f}]({f})" for f in files]
    return "\n".join(lines) + "\n"


def cli_terrain(out: Path, quick: bool = False, full: bool = False, seed: int = 0) -> dict[str, Any]:
    r = run(out, config_for(quick, full, seed))
    for t in r["terrains"]:
        print(f"{t}: " + "; ".join(f"{row} {_cell(r['table'][row][t])}" for row in r["rows"]))
    print(f"image-conditioned within the per-terrain spread on {len(r['within_spread_terrains'])}/"
          f"{len(r['terrains'])} terrains {r['within_spread_terrains']}; better than all data on "
          f"{len(r['better_than_all_data_terrains'])} {r['better_than_all_data_terrains']}")
    print(f"report: {Path(out) / 'report.md'}", file=sys.stderr)
    return r
