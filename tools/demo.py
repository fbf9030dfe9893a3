"""`hil demo`: the MBRL loop on the simulated VelociRoACH, with a report.

Writes ``OUT/report.json``, ``OUT/report.md``, PNG plots, the MCAP recordings of
every phase and a rerun ``OUT/demo.rrd`` of the evaluation.
"""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np

from configs.schema import BusConfig
from learning.mbrl import MbrlConfig, MbrlRun


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def run_demo(out: Path, quick: bool = False, bus: BusConfig | None = None, **overrides: Any) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = MbrlConfig.quick(**overrides) if quick else MbrlConfig(data_sizes=(10, 50, 200, 400),
                                                                 random_rollouts=400, **overrides)
    # a private rendezvous port: a demo never talks to another rig by accident
    bus = bus or BusConfig(endpoint=free_endpoint())
    report = MbrlRun(cfg, out, bus).run()
    report["quick"] = quick
    report["created"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    plots = write_plots(report, out)
    report["plots"] = plots
    from tools.viz import viz_recording

    eval_rec = next((r for r in report["recordings"] if "eval" in r), None)
    if eval_rec:
        viz_recording(eval_rec, out / "demo.rrd", rig=report["rig"])
        report["rerun"] = str(out / "demo.rrd")
    (out / "report.json").write_text(json.dumps(report, indent=1))
    (out / "report.md").write_text(report_markdown(report))
    return report


def write_plots(report: dict[str, Any], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    speeds = [k for k in report if k.endswith("_speed")]
    for label in speeds:
        paths = report[label]["paths"]
        fig, axes = plt.subplots(1, len(paths), figsize=(4 * len(paths), 4))
        for ax, (name, res) in zip(np.atleast_1d(axes), paths.items(), strict=False):
            wp = np.array(res["mpc"]["waypoints"])
            ax.plot(wp[:, 0], wp[:, 1], "k--", lw=1, label="path")
            for who, style in (("mpc", "C0"), ("differential_drive", "C1")):
                xy = np.array(res[who]["xy"])
                ax.plot(xy[:, 0], xy[:, 1], style, label=f"{who} ({res[who]['cost']:.0f})")
            ax.set_title(name)
            ax.set_aspect("equal", adjustable="datalim")
            ax.legend(fontsize=7)
        fig.suptitle(f"{label}: trajectories (cost in legend, lower is better)")
        f = out / f"trajectories_{label}.png"
        fig.tight_layout()
        fig.savefig(f, dpi=80)
        plt.close(fig)
        files.append(f.name)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    x = np.arange(len(speeds))
    ax.bar(x - 0.2, [report[s]["mpc_cost"] for s in speeds], 0.4, label="MPC")
    ax.bar(x + 0.2, [report[s]["differential_drive_cost"] for s in speeds], 0.4, label="differential drive")
    ax.set_xticks(x, speeds)
    ax.set_ylabel("mean path cost (lower is better)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "costs.png", dpi=80)
    plt.close(fig)
    files.append("costs.png")
    if report.get("data_size_curve"):
        d = report["data_size_curve"]
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.plot([r["random_rollouts"] for r in d], [r["mpc_cost"] for r in d], "o-")
        ax.set_xlabel("random rollouts used for training")
        ax.set_ylabel("MPC mean path cost (high speed)")
        fig.tight_layout()
        fig.savefig(out / "data_size.png", dpi=80)
        plt.close(fig)
        files.append("data_size.png")
    return files


def report_markdown(r: dict[str, Any]) -> str:
    cfg = r["config"]
    lines = [
        "# hilstack demo: model-based RL on the simulated VelociRoACH",
        "",
        f"Rig `{r['rig']}`, {'quick' if r.get('quick') else 'full'} run, {r['wall_s']:.0f} s wall clock, "
        f"created {r.get('created', '')}.",
        f"Random data: {cfg['random_rollouts']} rollouts x {cfg['rollout_steps']} steps; model "
        f"{cfg['ensemble']}x MLP {cfg['hidden']}; planner {cfg['planner']} N={cfg['samples']} H={cfg['horizon']}; "
        f"{cfg['iterations']} on-policy iteration(s).",
        "",
        "## Path following: MPC vs differential drive",
        "",
        "Cost per episode (summed over steps): 50·perpendicular distance + 5·heading error − 10·forward progress;"
        " lower is better. Both controllers are scored with the same function on the same paths.",
        "",
        "| speed | MPC cost | differential drive cost | MPC better |",
        "|---|---|---|---|",
    ]
    speeds = [k for k in r if k.endswith("_speed")]
    for s in speeds:
        m, d = r[s]["mpc_cost"], r[s]["differential_drive_cost"]
        lines.append(f"| {s} ({r[s]['speed']:.2f}) | {m:.1f} | {d:.1f} | {'yes' if m < d else 'no'} |")
    lines += ["", "Per path:", "", "| speed | path | MPC | diff. drive | MPC perp. error (m) | plan p50/p99 (ms) |",
              "|---|---|---|---|---|---|"]
    for s in speeds:
        for p, v in r[s]["paths"].items():
            lines.append(
                f"| {s} | {p} | {v['mpc']['cost']:.1f} | {v['differential_drive']['cost']:.1f} | "
                f"{v['mpc']['perp_mean_m']:.3f} | {v['mpc']['plan_ms_p50']:.1f}/{v['mpc']['plan_ms_p99']:.1f} |"
            )
    if r.get("data_size_curve"):
        lines += ["", "## Cost vs amount of random data (thesis Table 3.1 shape)", "",
                  "| random rollouts | MPC cost (high speed) |", "|---|---|"]
        lines += [f"| {d['random_rollouts']} | {d['mpc_cost']:.1f} |" for d in r["data_size_curve"]]
    lines += ["", "## Training", "", "| iteration | episodes | train loss | val 1-step | val H-step |", "|---|---|---|---|---|"]
    for t in r["training"]:
        lines.append(f"| {t['iteration']} | {t['episodes']} | {t.get('train_loss', float('nan')):.4f} | "
                     f"{t.get('val_1step', float('nan')):.4f} | {t.get('val_h', float('nan')):.4f} |")
    lines += ["", "## Files", ""]
    lines += [f"- ![{p}]({p})" for p in r.get("plots", [])]
    lines += [f"- recording: `{p}`" for p in r["recordings"]]
    if r.get("rerun"):
        lines.append(f"- rerun: `rerun {r['rerun']}`")
    lines.append(f"- model checkpoint: `{r['model']}`")
    return "\n".join(lines) + "\n"
