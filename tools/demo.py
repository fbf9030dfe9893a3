"""`hil demo`: the MBRL loop on the simulated VelociRoACH, with a report.

Writes ``OUT/report.json``, ``OUT/report.md``, PNG plots, the MCAP recordings of
every phase and a rerun ``OUT/demo.rrd`` of the evaluation.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from hilstack.bus.ports import free_endpoint  # noqa: F401  (the demos' rig endpoints)
from hilstack.configs.schema import BusConfig
from hilstack.learning.mbrl import MbrlConfig, MbrlRun

#: `--quick` on a wall-clock rig (emulated, real): fewer differential-drive candidates. The
#: baseline's random search is the longest phase there (candidates x 3 tuning paths x 2
#: speeds episodes, each with a reset of a few seconds; docs/reset.md has the timings);
#: the lockstep sim's quick run is unchanged.
QUICK_WALL_CLOCK: dict[str, Any] = {"baseline_candidates": 6}


def quick_wall_clock(rig: str) -> dict[str, Any]:
    """The ``--quick`` overrides for ``rig``: :data:`QUICK_WALL_CLOCK` unless it runs in lockstep."""
    from hilstack.configs.schema import load_rig

    return {} if load_rig(rig).pace == "lockstep" else dict(QUICK_WALL_CLOCK)


def run_demo(out: Path, quick: bool = False, bus: BusConfig | None = None, full: bool = False,
             ray: str | None = None, workers: int = 1, **overrides: Any) -> dict[str, Any]:
    """Run the MBRL loop (``quick``: the README's few-minute run; ``full``: also the thesis'
    experiments over seeds, :mod:`hilstack.learning.experiments`) and write the report to ``out``.
    ``ray`` (``full`` only): ``local`` or a Ray cluster's address: the main run and every seed's
    experiments as sweep tasks, each with its own rig processes (:mod:`hilstack.tools.demo_sweep`)."""
    if quick and full:
        raise ValueError("choose --quick or --full, not both")
    if ray is not None and not full:
        raise ValueError("--ray is for the full run (--full): the other runs are one task")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if quick:
        cfg = MbrlConfig.from_preset("quick", **{**quick_wall_clock(overrides.get("rig", MbrlConfig.rig)), **overrides})
    elif full:
        cfg = MbrlConfig.from_preset("full", **overrides)
    else:
        cfg = MbrlConfig(**{"random_rollouts": 400, **overrides})
    # a private rendezvous port: a demo never talks to another rig by accident; the rig's
    # bus settings otherwise (its access control: a real rig's driver admits only its credentials)
    from hilstack.configs.schema import load_rig
    from hilstack.tools.common import provision_credentials, with_endpoint

    rig_cfg = load_rig(cfg.rig)
    if ray is not None:  # every task makes its own endpoint and credentials
        from hilstack.tools.demo_sweep import run_full_on_sweep

        report = run_full_on_sweep(cfg, out, ray, workers)
        return write_report(report, out, quick=quick, full=full)
    if bus is None:
        bus = with_endpoint(rig_cfg.bus, free_endpoint())
    # an emulated rig's credentials, made here when missing: every node of the demo needs them
    provision_credentials(rig_cfg.name, bus, rig_cfg)
    report = MbrlRun(cfg, out, bus).run()
    return write_report(report, out, quick=quick, full=full)


def write_report(report: dict[str, Any], out: Path, quick: bool, full: bool) -> dict[str, Any]:
    """``report.json``, ``report.md``, the plots and the rerun file of the evaluation."""
    report["quick"] = quick
    report["full"] = full
    report["created"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    plots = write_plots(report, out)
    report["plots"] = plots
    from hilstack.tools.viz import viz_recording

    eval_rec = next((r for r in report["recordings"] if "eval" in r), None)
    if eval_rec:
        viz_recording(eval_rec, out / "demo.rrd", rig=report["rig"])
        report["rerun"] = str(out / "demo.rrd")
    (out / "report.json").write_text(json.dumps(report, indent=1))
    (out / "report.md").write_text(report_markdown(report))
    return report


def _save(plt, fig, path: Path) -> str:
    """Write ``fig`` to ``path`` (PNG) and close it; returns the file's name."""
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path.name


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
                done = "done" if res[who]["completed"] else f"stopped at {res[who]['progress_m']:.1f} m"
                ax.plot(xy[:, 0], xy[:, 1], style, label=f"{who} ({res[who]['cost_per_m']:.0f}/m, {done})")
            ax.set_title(name)
            ax.set_aspect("equal", adjustable="datalim")
            ax.legend(fontsize=7)
        fig.suptitle(f"{label}: trajectories (cost per metre in legend, lower is better)")
        files.append(_save(plt, fig, out / f"trajectories_{label}.png"))
    fig, ax = plt.subplots(figsize=(5, 3.5))
    x = np.arange(len(speeds))
    ax.bar(x - 0.2, [report[s]["mpc_cost_per_m"] for s in speeds], 0.4, label="MPC")
    ax.bar(x + 0.2, [report[s]["differential_drive_cost_per_m"] for s in speeds], 0.4, label="tuned differential drive")
    ax.set_xticks(x, [f"{s}\n(done {report[s]['mpc_completed']} vs {report[s]['differential_drive_completed']})"
                      for s in speeds])
    ax.set_ylabel("cost per metre of progress (lower is better)")
    ax.legend()
    files.append(_save(plt, fig, out / "costs.png"))
    files += experiment_plots(report, out, plt)
    return files


def _ms(cell: dict[str, Any]) -> str:
    return f"{cell['mean']:.1f} ± {cell['std']:.1f}"


def experiment_plots(report: dict[str, Any], out: Path, plt) -> list[str]:
    """Error-bar plots (mean ± std over seeds) of the full run's experiments."""
    files = []
    t31 = report.get("table_3_1")
    if t31:
        fig, ax = plt.subplots(figsize=(6, 3.8))
        rows = list(t31["rows"])
        x = np.arange(len(rows))
        for i, p in enumerate(t31["paths"]):
            m = [t31["rows"][r]["paths"][p]["cost_per_m"] for r in rows]
            ax.errorbar(x + 0.1 * (i - 1), [c["mean"] for c in m], yerr=[c["std"] for c in m], fmt="o-", capsize=3, label=p)
        ax.set_xticks(x, rows)
        ax.set_xlabel("random rollouts used for training")
        ax.set_ylabel("MPC cost per metre (mean ± std)")
        ax.set_title(f"Table 3.1: {len(t31['seeds'])} seeds, speed {t31['speed']}")
        ax.legend()
        files.append(_save(plt, fig, out / "table_3_1.png"))
    sw = report.get("speed_sweep")
    if sw:
        fig, ax = plt.subplots(figsize=(5.5, 3.8))
        sp = [r["speed"] for r in sw["rows"]]
        for who, label in (("mpc", "MPC"), ("differential_drive", "tuned differential drive")):
            c = [r[who]["cost_per_m"] for r in sw["rows"]]
            ax.errorbar(sp, [v["mean"] for v in c], yerr=[v["std"] for v in c], fmt="o-", capsize=3, label=label)
        ax.set_xlabel("commanded speed (normalized leg command bound)")
        ax.set_ylabel("cost per metre, all paths (mean ± std)")
        ax.set_title("Fig. 3.8: MPC vs tuned differential drive")
        ax.legend()
        files.append(_save(plt, fig, out / "speed_sweep.png"))
    t32 = report.get("table_3_2")
    if t32:
        fig, ax = plt.subplots(figsize=(6, 3.8))
        rows = list(t32["matrix"])
        x = np.arange(len(rows))
        for i, t in enumerate(t32["terrains"]):
            c = [t32["matrix"][r][t]["summary"]["cost_per_m"] for r in rows]
            ax.bar(x + 0.4 * i - 0.2, [v["mean"] for v in c], 0.4, yerr=[v["std"] for v in c], capsize=3,
                   label=f"evaluated on {t}")
        ax.set_xticks(x, [r.replace(" (tuned per terrain)", "") for r in rows], fontsize=7)
        ax.set_ylabel("straight-line cost per metre (mean ± std)")
        ax.set_title("Table 3.2: terrains")
        ax.legend(fontsize=7)
        files.append(_save(plt, fig, out / "table_3_2.png"))
    return files


def experiments_markdown(r: dict[str, Any]) -> list[str]:
    """Tables of the full run: mean ± std over seeds, completions as done/runs."""
    lines: list[str] = []
    t31 = r.get("table_3_1")
    if t31:
        lines += ["", f"## Table 3.1: MPC cost vs random data ({len(t31['seeds'])} seeds, speed {t31['speed']})", "",
                  "Cost (summed) and cost per metre, mean ± std over seeds; completed runs of all runs.", "",
                  "| rollouts | " + " | ".join(t31["paths"]) + " |", "|---|" + "---|" * len(t31["paths"])]
        for row, v in t31["rows"].items():
            cells = [f"{_ms(v['paths'][p]['cost'])} ({_ms(v['paths'][p]['cost_per_m'])}/m), "
                     f"{v['paths'][p]['completed']}/{v['paths'][p]['runs']}" for p in t31["paths"]]
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    sw = r.get("speed_sweep")
    if sw:
        n_paths = sw["rows"][0]["mpc"]["paths"] if sw["rows"] else 0
        lines += ["", f"## Fig. 3.8: MPC vs tuned differential drive over speeds ({len(sw['seeds'])} seeds)", "",
                  "Cost per metre over all paths and paths completed (of "
                  f"{n_paths}), mean ± std over seeds. The lockstep sim is deterministic for a fixed controller, "
                  "so the baseline runs once per speed (std 0).", "",
                  "| speed | MPC cost/m | MPC completed | diff. drive cost/m | diff. drive completed |",
                  "|---|---|---|---|---|"]
        for row in sw["rows"]:
            m, d = row["mpc"], row["differential_drive"]
            lines.append(f"| {row['speed']:.2f} | {_ms(m['cost_per_m'])} | {_ms(m['completed'])} | "
                         f"{_ms(d['cost_per_m'])} | {_ms(d['completed'])} |")
    t32 = r.get("table_3_2")
    if t32:
        lines += ["", f"## Table 3.2: terrains ({len(t32['seeds'])} seeds, {t32['rollouts_per_terrain']} random "
                  f"rollouts per terrain, {', '.join(t32['paths'])} at speed {t32['speed']})", "",
                  "| controller | " + " | ".join(f"on {t}: cost/m, completed" for t in t32["terrains"]) + " |",
                  "|---|" + "---|" * len(t32["terrains"])]
        for row, per in t32["matrix"].items():
            cells = []
            for t in t32["terrains"]:
                p = per[t]["paths"]
                done = sum(c["completed"] for c in p.values())
                runs = sum(c["runs"] for c in p.values())
                cells.append(f"{_ms(per[t]['summary']['cost_per_m'])}, {done}/{runs}")
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return lines


def resets_markdown(rs: dict[str, Any]) -> list[str]:
    """The reset supervisor's counts (docs/reset.md): resets, their duration, what the
    steps did and which detectors ended episodes."""
    ends = ", ".join(f"{k} {v}" for k, v in rs.get("episode_ends", {}).items()) or "none"
    return ["", "## Automatic resets", "",
            f"{rs['completed']} of {rs['requested']} requested resets completed, {rs['failed']} failed; "
            f"{rs['mean_duration_s']:.1f} s mean, {rs.get('max_duration_s', 0.0):.1f} s longest (wall clock). "
            f"Self-righted {rs.get('self_righted', 0)}; lab-fixture recoveries (operator interventions on a real "
            f"rig) {rs.get('fixture_recoveries', 0)}. Episodes ended by detectors: {ends}."]


def report_markdown(r: dict[str, Any]) -> str:
    cfg = r["config"]
    lines = [
        "# hilstack demo: model-based RL on the simulated VelociRoACH",
        "",
        f"Rig `{r['rig']}`, {'quick' if r.get('quick') else 'full' if r.get('full') else 'default'} run, {r['wall_s']:.0f} s wall clock, "
        f"created {r.get('created', '')}." + (
            f" Run as {r['sweep']['tasks']} sweep tasks ({r['sweep']['executor']}"
            f"{', Ray ' + r['sweep']['ray_version'] if r['sweep'].get('ray_version') else ''}, "
            f"{r['sweep']['workers']} workers, {r['sweep']['resumed']} from an earlier run; docs/scaling.md)."
            if r.get("sweep") else ""),
        f"Random data: {cfg['random_rollouts']} rollouts x {cfg['rollout_steps']} steps; model "
        f"{cfg['ensemble']}x MLP {cfg['hidden']}; planner {cfg['planner']} N={cfg['samples']} H={cfg['horizon']}; "
        f"{cfg['iterations']} on-policy iteration(s).",
        "",
        "## Path following: MPC vs tuned differential drive",
        "",
        "Cost (summed over steps): 50·perpendicular distance + 5·heading error − 10·forward progress;"
        " lower is better. An episode ends at the path's end or at the time limit (path length at "
        f"{cfg['time_limit_speed_mps']} m/s). Controllers are ranked by paths completed, then cost per metre of"
        " progress: a controller that stops never beats one that finishes. Both are scored with the same"
        " function on the same paths.",
        "",
        "| speed | MPC completed | diff. drive completed | MPC cost/m | diff. drive cost/m | MPC better |",
        "|---|---|---|---|---|---|",
    ]
    speeds = [k for k in r if k.endswith("_speed")]
    for s in speeds:
        v = r[s]
        n = len(v["paths"])
        lines.append(f"| {s} ({v['speed']:.2f}) | {v['mpc_completed']}/{n} | {v['differential_drive_completed']}/{n} | "
                     f"{v['mpc_cost_per_m']:.1f} | {v['differential_drive_cost_per_m']:.1f} | "
                     f"{'yes' if v['mpc_better'] else 'no'} |")
    lines += ["", "Per path (cost, progress, time; ✓ = completed):", "",
              "| speed | path | MPC | diff. drive | MPC plan p50/p99 (ms) |", "|---|---|---|---|---|"]

    def cell(m: dict[str, Any]) -> str:
        return (f"{'✓' if m['completed'] else '✗'} {m['cost']:.1f} ({m['cost_per_m']:.1f}/m), "
                f"{m['progress_m']:.2f} m in {m['time_s']:.1f} s")

    for s in speeds:
        for p, v in r[s]["paths"].items():
            lines.append(f"| {s} | {p} | {cell(v['mpc'])} | {cell(v['differential_drive'])} | "
                         f"{v['mpc']['plan_ms_p50']:.1f}/{v['mpc']['plan_ms_p99']:.1f} |")
    if r.get("baseline_tuning"):
        bt = r["baseline_tuning"]
        lines += ["", "## Baseline tuning", "", f"{bt['method']}. {bt['candidates']} candidates per speed on "
                  f"{', '.join(bt['tuning_paths'])} (not the evaluation paths).", "",
                  "| speed | default: completed, cost/m | tuned: completed, cost/m | tuned gains |", "|---|---|---|---|"]
        for s, t in bt["per_speed"].items():
            gains = ", ".join(f"{k} {v:.2f}" for k, v in t["best_params"].items())
            lines.append(f"| {s} | {t['default']['completed']}, {t['default']['cost_per_m']:.1f} | "
                         f"{t['best']['completed']}, {t['best']['cost_per_m']:.1f} | {gains} |")
    if r.get("resets"):
        lines += resets_markdown(r["resets"])
    lines += experiments_markdown(r)
    if r.get("random_data"):
        c = r["random_data"]
        lines += ["", "## Random data coverage", "",
                  f"Ground speed p50/p90/p99 {c['speed_p50_mps']:.2f}/{c['speed_p90_mps']:.2f}/{c['speed_p99_mps']:.2f}"
                  f" m/s; {100 * c['fraction_ge_0.5_mps']:.1f} % of steps at ≥ 0.5 m/s, "
                  f"{100 * c['fraction_ge_0.9_mps']:.1f} % at ≥ 0.9 m/s."]
    lines += ["", "## Training", "",
              f"Validation episodes are drawn once and stay validation data. H = {cfg['horizon']}-step open-loop "
              "errors (thesis Eqn 2.2, normalized per channel) in the world frame and in the body frame of each "
              "window's start; the position error after H steps in m².", "",
              "| iteration | episodes | train loss | val 1-step | val H-step world | val H-step body | xy after H (m²) |",
              "|---|---|---|---|---|---|---|"]
    nan = float("nan")
    for t in r["training"]:
        lines.append(f"| {t['iteration']} | {t['episodes']} | {t.get('train_loss', nan):.4f} | "
                     f"{t.get('val_1step', nan):.4f} | {t.get('val_h', nan):.4f} | {t.get('val_h_body', nan):.4f} | "
                     f"{t.get('val_h_xy_mse_m2', nan):.5f} |")
    lines += ["", "## Files", ""]
    lines += [f"- ![{p}]({p})" for p in r.get("plots", [])]
    lines += [f"- recording: `{p}`" for p in r["recordings"]]
    if r.get("rerun"):
        lines.append(f"- rerun: `rerun {r['rerun']}`")
    lines.append(f"- model checkpoint: `{r['model']}`")
    return "\n".join(lines) + "\n"
