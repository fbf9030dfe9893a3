"""`hil demo baoding`: PDDM on the simulated Shadow Hand's Baoding balls, every node on the bus.

Writes ``OUT/report.json``, ``OUT/report.md``, ``OUT/turns.png``, the MCAP recordings of
every phase and a rerun ``OUT/demo.rrd`` of the last PDDM iteration (docs/baoding.md).
``--quick``: the scaled-down preset (``BaodingConfig.from_preset("quick")``, ≤10 min on
2 cores); default: the thesis' settings, one seed; ``--full``: the thesis' settings over
seeds 0, 1, 2 (``OUT/seed_<k>/``) with mean ± std across seeds in ``OUT/report.json``.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from hilstack.configs.schema import BusConfig
from hilstack.learning.baoding import BaodingConfig, BaodingRun, probe_model
from hilstack.tools.demo import free_endpoint

FULL_SEEDS = (0, 1, 2)


#: ``hil demo baoding --targets``: how the targets' phase moves (docs/baoding.md, "Targets that
#: do not drag the pair backwards"): "lead" = ours, at most ``max_lead_rad`` ahead of the pair;
#: "clock" = the reference code's, by the step counter alone
TARGETS: dict[str, dict[str, Any]] = {"lead": {}, "clock": {"task_overrides": {"max_lead_rad": None}}}


#: ``hil demo baoding --hold-pose``: the hand's hold pose (drivers/shadow_hand/config.py:
#: ``HOLD_POSES``), its sim rig and the task geometry read for it (docs/baoding.md, "Where the
#: balls sit"). Without the flag a run holds its preset's pose (BaodingConfig: the thesis preset
#: the reference's ``pddm``, quick and tiny our ``cupped``), or, given ``--rig``, that rig's. The
#: sim rigs teleport the balls back: on the reset-arm rig (hand_sim_arm) a ball that comes to
#: rest on the hand's edge is neither in the palm nor at the pick-up spot, and the arm's
#: procedure cannot recover it (docs/baoding.md), so a thesis-scale run would stop at the first such drop
HOLD_POSE_RUNS: dict[str, dict[str, str]] = {"cupped": {"rig": "hand_sim", "task": "baoding"},
                                             "pddm": {"rig": "hand_sim_pddm_pose", "task": "baoding_pddm_pose"}}


def pose_rig_task(preset: str, rig: str | None = None, hold_pose: str | None = None) -> tuple[str, str]:
    """The rig and task of a run: ``hold_pose`` (a key of :data:`HOLD_POSE_RUNS`) gives the task
    and, unless ``rig``, the rig; ``rig`` alone: the task of the pose its hand holds; neither:
    the preset's. ValueError on an unknown pose."""
    if hold_pose is not None:
        if hold_pose not in HOLD_POSE_RUNS:
            raise ValueError(f"--hold-pose must be {' or '.join(HOLD_POSE_RUNS)}, got {hold_pose!r}")
        return rig or HOLD_POSE_RUNS[hold_pose]["rig"], HOLD_POSE_RUNS[hold_pose]["task"]
    cfg = make_config(preset, 0)
    if rig is None:
        return cfg.rig, cfg.task
    from hilstack.learning.baoding import rig_hold_pose

    pose = rig_hold_pose(rig, cfg.robot)
    return rig, HOLD_POSE_RUNS[pose]["task"] if pose in HOLD_POSE_RUNS else cfg.task


def make_config(preset: str, seed: int, **overrides: Any) -> BaodingConfig:
    if preset == "quick":
        return BaodingConfig.from_preset("quick", seed=seed, **overrides)
    if preset == "tiny":
        return BaodingConfig.from_preset("tiny", seed=seed, **overrides)
    if preset == "thesis":
        return BaodingConfig(seed=seed, **overrides)
    raise ValueError(f"unknown preset {preset!r}: quick | thesis | tiny")


def run_baoding_demo(out: Path, preset: str = "quick", seed: int = 0, bus: BusConfig | None = None,
                     resume: bool = False, **overrides: Any) -> dict[str, Any]:
    """One run of PDDM on Baoding; writes the report to ``out`` and returns it. ``resume``:
    continue the stopped run in ``out`` after its last finished iteration (same preset and seed)."""
    from hilstack.learning.baoding import baoding_rig_problem

    cfg = make_config(preset, seed, **overrides)
    problem = baoding_rig_problem(cfg.rig, cfg.robot, cfg.task)
    if problem:  # before anything starts or is written
        raise ValueError(problem)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # a private rendezvous port: a demo never talks to another rig by accident; the rig's bus
    # settings otherwise (an emulated hand's access control, its credentials made when missing)
    if bus is None:
        from hilstack.configs.schema import load_rig
        from hilstack.tools.common import provision_credentials, with_endpoint

        rig_cfg = load_rig(cfg.rig)
        bus = with_endpoint(rig_cfg.bus, free_endpoint())
        provision_credentials(rig_cfg.name, bus, rig_cfg)
    report = BaodingRun(cfg, out, bus, resume=resume).run()
    default = make_config(preset, seed)
    pose = next((k for k, v in HOLD_POSE_RUNS.items() if v["task"] == cfg.task), None)
    rig_arg = ("" if cfg.task == default.task or pose is None else f" --hold-pose {pose}") + (
        "" if cfg.rig == (HOLD_POSE_RUNS[pose]["rig"] if pose and cfg.task != default.task else default.rig)
        else f" --rig {cfg.rig}")
    extra_arg = "".join(f" --extra-data {d}" for d in cfg.extra_recordings) + (
        f" --extra-repeat {cfg.extra_repeat}" if cfg.extra_recordings else "") + (
        f" --iterations {cfg.iterations}" if cfg.iterations != default.iterations else "") + "".join(
        f" --targets {k}" for k, v in TARGETS.items() if v and v.get("task_overrides") == cfg.task_overrides)
    report["command"] = (f"hil demo baoding{' --quick' if preset == 'quick' else ''}{rig_arg} --seed {seed} --out {out}"
                         f"{extra_arg}{' --resume' if resume else ''}")
    report["created"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    report["plots"] = [write_plot(report, out)]
    last = next((r for r in reversed(report["recordings"]) if r.endswith("-mpc.mcap")), None)
    if last:
        from hilstack.tools.viz import viz_recording

        viz_recording(last, out / "demo.rrd", rig=report["rig"])
        report["rerun"] = str(out / "demo.rrd")
    (out / "report.json").write_text(json.dumps(report, indent=1))
    (out / "report.md").write_text(report_markdown(report))
    return report


def seed_run(out: Path, preset: str, seed: int, rig: str, overrides: dict[str, Any],
             resume: bool = False) -> dict[str, Any]:
    """One seed of the full run in ``out``; ``resume``: a finished seed's report is read back,
    a stopped one continues after its last finished iteration, a missing one starts."""
    out = Path(out)
    if resume and (out / "report.json").exists():
        r = json.loads((out / "report.json").read_text())
        if not r.get("partial"):
            return r
        return run_baoding_demo(out, preset=preset, seed=seed, rig=rig, resume=True, **overrides)
    return run_baoding_demo(out, preset=preset, seed=seed, rig=rig, **overrides)


def seed_task(out: str, preset: str, seed: int, rig: str, overrides: dict[str, Any],
              resume: bool = False) -> dict[str, Any]:
    """One seed of the full run as a sweep task (tools/sweep.py): its report (``run_baoding_demo``
    makes the seed's own bus endpoint and rig processes)."""
    return seed_run(Path(out), preset, seed, rig, overrides, resume)


def seeds_on_sweep(out: Path, seeds: tuple[int, ...], preset: str, rig: str, overrides: dict[str, Any],
                   executor: str | None, workers: int = 1,
                   resume: bool = False) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Every seed a sweep task (``executor``: None serial, ``local``, an address): the seeds'
    reports in ``seeds`` order and the sweep's record. A re-run of a stopped sweep (``out`` holds its
    ``tasks/``) continues each stopped seed after its last finished iteration (``resume``), as
    ``--resume`` would: the seed's directory holds its checkpoint, which a fresh start refuses to overwrite."""
    from hilstack.tools.common import UserError
    from hilstack.tools.sweep import Task, run_sweep

    resume = resume or (Path(out) / "tasks").is_dir()
    tasks = [Task(f"seed{s}", seed_task, {"out": str(out / f"seed_{s}"), "preset": preset, "seed": s, "rig": rig,
                                           "overrides": overrides, "resume": resume}) for s in seeds]
    sw = run_sweep(tasks, out, executor=executor, workers=workers)
    if sw["failed"]:
        raise UserError(f"seeds {sorted(sw['failed'])} failed (their log tails above; {out / 'tasks'}); "
                        "the same command again re-runs only those")
    return [sw["results"][t.key] for t in tasks], sw["sweep"]


def run_full(out: Path, seeds: tuple[int, ...] = FULL_SEEDS, preset: str = "thesis", rig: str | None = None,
             ray: str | None = None, workers: int = 1, resume: bool = False, **overrides: Any) -> dict[str, Any]:
    """The thesis' settings over ``seeds``: per-seed reports in ``out/seed_<k>`` and the
    final iteration's metrics as mean ± std across seeds, on the preset's rig unless ``rig``.
    ``ray`` (``local`` or a Ray cluster's address): every seed a sweep task, results in
    ``out/tasks/`` as each finishes, a re-run does only the seeds missing (docs/scaling.md).
    Each seed's run is already independent (its own rig, endpoint and seeded generators), so
    the numbers are the serial run's. ``resume``: seeds already finished are read back, a
    stopped one continues after its last finished iteration, the rest start."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rig = rig or overrides.pop("rig", None) or make_config(preset, 0, **overrides).rig
    sweep = None
    if ray is None:
        runs = [seed_run(out / f"seed_{s}", preset, s, rig, overrides, resume) for s in seeds]
    else:
        from hilstack.tools.sweep import executor_from

        runs, sweep = seeds_on_sweep(out, seeds, preset, rig, overrides, executor_from(ray), workers, resume)

    def across(key: str, pick) -> dict[str, float]:
        v = np.array([pick(r) for r in runs], dtype=np.float64)
        return {"mean": float(v.mean()), "std": float(v.std()), "per_seed": v.tolist()}

    summary = {
        "seeds": list(seeds),
        "final_mean_rotation_deg": across("rot", lambda r: r["iterations"][-1]["mean_rotation_deg"]),
        "final_mean_steps": across("st", lambda r: r["iterations"][-1]["mean_steps"]),
        "hold_success_90": across("h90", lambda r: r["hold_policy"]["success_90"]),
        "hold_mean_rotation_deg": across("hrot", lambda r: r["hold_policy"]["mean_rotation_deg"]),
        "final_mean_return": across("r", lambda r: r["iterations"][-1]["mean_return"]),
        "final_drop_rate": across("d", lambda r: r["iterations"][-1]["drop_rate"]),
        "final_success_90": across("s90", lambda r: r["iterations"][-1]["success_90"]),
        "final_success_180": across("s180", lambda r: r["iterations"][-1]["success_180"]),
        "random_mean_return": across("rr", lambda r: r["random_policy"]["mean_return"]),
        "runs": [str(out / f"seed_{s}" / "report.json") for s in seeds],
    }
    if all("held_90" in r["iterations"][-1] for r in runs):  # reports from before it have none
        summary["final_held_90"] = across("h90", lambda r: r["iterations"][-1]["held_90"])
    if sweep is not None:
        summary["sweep"] = sweep
    summary["plot"] = Path(write_seeds_plot({f"seed {s}": r for s, r in zip(seeds, runs, strict=True)},
                                            out / "turns.png")).name  # beside this report
    (out / "report.json").write_text(json.dumps(summary, indent=1))
    return summary


#: the thesis' claim for the simulated hand (ch. 4, Fig. 4.9): Baoding solved with ~100,000
#: data points (2.7 h of data). Its curve is not reproduced here: a marker at that budget.
THESIS_SOLVED_POINTS = 100_000


def write_seeds_plot(runs: dict[str, dict[str, Any]], png: Path) -> str:
    """success_90 (and held_90 where reported) of several seeds' runs (label → report) against
    the data points trained on: each seed thin, the mean over the seeds at each iteration bold
    (at the seeds' mean points; ± std shaded), hold still and the thesis' ~100k-points marker.
    Returns the file written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not runs:
        raise ValueError("write_seeds_plot: no runs")
    fig, ax = plt.subplots(figsize=(7, 4))
    for i, (label, r) in enumerate(runs.items()):
        its = r["iterations"]
        ax.plot([it["points"] for it in its], [100 * it["success_90"] for it in its], "-", lw=0.8, alpha=0.6,
                color=f"C{i}", label=f"{label}: success_90")
    n = min(len(r["iterations"]) for r in runs.values())  # the iterations every seed has
    for key, style, what in (("success_90", "o-", "turned ≥ 90° before a drop"),
                             ("held_90", "s--", "turned ≥ 90° and kept the pair")):
        rows = [[it.get(key) for it in r["iterations"][:n]] for r in runs.values()]
        if n == 0 or any(v is None for row in rows for v in row):
            continue  # reports from before held_90 have none
        y = 100 * np.array(rows, dtype=float)
        x = np.array([[it["points"] for it in r["iterations"][:n]] for r in runs.values()], dtype=float).mean(0)
        ax.plot(x, y.mean(0), style, color="k", lw=1.8, ms=3, label=f"mean of {len(runs)}: {what}")
        ax.fill_between(x, y.mean(0) - y.std(0), y.mean(0) + y.std(0), color="k", alpha=0.12)
    hold = [r["hold_policy"]["success_90"] for r in runs.values() if "hold_policy" in r]
    if hold:
        ax.axhline(100 * float(np.mean(hold)), color="C2", ls="--", label="hold still: success_90")
    ax.axvline(THESIS_SOLVED_POINTS, color="k", ls=":", label="thesis Fig. 4.9: solved at ~100k points")
    ax.axhline(50, color="0.6", lw=0.6)
    ax.set_xlabel("training points (transitions)")
    ax.set_ylabel("episodes (%)")
    ax.set_ylim(-5, 105)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("Baoding: turns per PDDM iteration, by seed")
    fig.tight_layout()
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=80)
    plt.close(fig)
    return str(png)


def write_plot(r: dict[str, Any], out: Path) -> str:
    """success_90 / success_180 of every iteration against the data points trained on, beside
    hold-still and random, and the thesis' "solved at ~100k points" marker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = r["iterations"]
    x = [it["points"] for it in its]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    ax.plot(x, [100 * it["success_90"] for it in its], "o-", label="PDDM: pair turned ≥ 90° before a drop")
    ax.plot(x, [100 * it["success_180"] for it in its], "s-", label="PDDM: ≥ 180°")
    for key, label, color in (("hold_policy", "hold still", "C2"), ("random_policy", "random", "C3")):
        ax.axhline(100 * r[key]["success_90"], color=color, ls="--", label=f"{label}: ≥ 90°")
    ax.axvline(THESIS_SOLVED_POINTS, color="k", ls=":", label="thesis Fig. 4.9: solved at ~100k points")
    ax.set_xscale("log")
    ax.set_xlabel("training points (transitions)")
    ax.set_ylabel("episodes (%)")
    ax.set_ylim(-5, 105)
    ax.legend(fontsize=7)
    ax2.plot(x, [it["mean_rotation_deg"] for it in its], "o-", label="PDDM")
    for key, label, color in (("hold_policy", "hold still", "C2"), ("random_policy", "random", "C3")):
        ax2.axhline(r[key]["mean_rotation_deg"], color=color, ls="--", label=label)
    ax2.set_xlabel("training points (transitions)")
    ax2.set_ylabel("mean rotation in the targets' direction (°)")
    ax2.legend(fontsize=7)
    fig.suptitle(f"Baoding, {r['config']['preset']} preset, seed {r['config']['seed']}")
    fig.tight_layout()
    fig.savefig(out / "turns.png", dpi=80)
    plt.close(fig)
    return "turns.png"


def report_markdown(r: dict[str, Any]) -> str:
    c, p, rs = r["config"], r["planner"], r["resets"]

    def row(label: str, m: dict[str, Any], extra: str = "") -> str:
        held = f"{100 * m['held_90']:.0f} %" if "held_90" in m else "–"
        return (f"| {label} | {m['episodes']} | {100 * m['success_90']:.0f} % | {held} | {100 * m['success_180']:.0f} % | "
                f"{m['mean_rotation_deg']:.0f} | {m['drops']} ({100 * m['drop_rate']:.0f} %) | {m['mean_steps']:.0f} | "
                f"{m['return']['mean']:.1f} ± {m['return']['std']:.1f} | {extra} |")

    def weights(it: dict[str, Any]) -> str:
        w = it.get("weights", {})
        if not w.get("plans"):
            return ""
        return f"; ESS {w['ess_mean']:.1f} ({100 * w['ess_frac_mean']:.0f} % of K), shift {w['mean_shift_rms']:.3f}"

    lines = [
        "# hilstack demo: PDDM on the Shadow Hand's Baoding balls",
        "",
        f"Rig `{r['rig']}`, {c['preset']} preset, seed {c['seed']}, {r['wall_s']:.0f} s wall clock, created "
        f"{r.get('created', '')}. Reproduce: `{r.get('command', '')}`.",
        *[f"Note: {n}." for n in c.get("notes", [])],
        *([f"Note: {r['demonstrations']['text']} into every iteration's training split from the iteration "
           f"marked `+demo` on (not the thesis' method: recorded episodes the run did not collect)."]
          if r.get("demonstrations") else []),
        "",
        f"Planner: PDDM H={p['horizon']} K={p['samples']} γ={p['gamma']:g} β={p['beta']:g}, ensemble of "
        f"{p['ensemble']} × MLP {list(p['hidden'])}, first mean `{p['init_mean']}`; plan time p50 "
        f"{p['plan_ms_p50'] or 0:.0f} ms, p99 {p['plan_ms_p99'] or 0:.0f} ms over {p['plans']} plans.",
        f"Resets (reset supervisor): {rs['requested']} requested, {rs['completed']} completed, {rs['failed']} failed, "
        f"mean {rs['mean_duration_s']:.2f} s.",
        "",
        "The headline is turns: success at 90°/180° = episodes whose pair turned that far along the targets' "
        "rotation before any drop; mean rotation in the targets' direction (°); drops; steps held (until a "
        "drop or the end). Ranked by turns: " + " > ".join(r.get("ranking_by_turns", [])) + ". "
        "Return per episode: Σ_t −5·Σ_i d(ball_i, target_i) − 500·1(drop) − 10·1(wrist); it rewards holding "
        "still (docs/baoding.md). Drops foreseen: validation windows (H steps, logged actions) with a true drop "
        "whose model prediction drops too. ESS: effective sample size of PDDM's weights per plan; shift: the "
        "RMS change of the planned mean per plan (planner units).",
        "",
        "| policy | episodes | 90° | 90° held (no drop) | 180° | mean rotation (°) | drops | steps held | return (mean ± std) | model val 1-step / H-step; drops foreseen; weights |",
        "|---|---|---|---|---|---|---|---|---|---|",
        row("random (uniform actions)", r["random_policy"]),
        row("hold (keep the start pose)", r["hold_policy"]),
    ]
    for it in r["iterations"]:
        m = it.get("model", {})
        demo = f", +demo {100 * it['demonstrations']['share']:.0f} %" if it.get("demonstrations") else ""
        own = it.get("own_turn", {})
        own_r2 = f"; own turn R² {own['turn_r2']:.2f}" if own.get("windows") else ""
        lines.append(row(f"PDDM iteration {it['iteration']} ({it['points']} points{demo})", it,
                         f"{m.get('val_1step', float('nan')):.3f} / {m.get('val_h', float('nan')):.3f}; "
                         f"{100 * m.get('drop_recall', float('nan')):.0f} % of {m.get('windows_with_drop', 0)}"
                         + weights(it) + own_r2))
    lines += ["", "## Files", "", *[f"- ![{f}]({f})" for f in r.get("plots", [])],
              *[f"- recording: `{f}`" for f in r["recordings"]]]
    if r.get("rerun"):
        lines.append(f"- rerun: `rerun {r['rerun']}`")
    lines.append(f"- model checkpoint: `{r['model']}`")
    return "\n".join(lines) + "\n"


def cli_baoding(out: Path, quick: bool, full: bool, seed: int, ray: str | None = None, workers: int = 1,
                resume: bool = False, rig: str | None = None, extra_data: list[Path] | None = None,
                extra_repeat: int = 1, iterations: int | None = None, targets: str | None = None,
                hold_pose: str | None = None) -> None:
    """The `hil demo baoding` verb (registered in tools/cmd_demo.py); ``ray``: ``--full`` only;
    ``rig``: the rig config (default the preset's: :func:`pose_rig_task`), refused at once when it cannot run
    Baoding (:func:`~hilstack.learning.baoding.baoding_rig_problem`); ``targets``: a key of
    :data:`TARGETS`; ``hold_pose``: a key of :data:`HOLD_POSE_RUNS` (its rig unless ``rig``, and
    its task geometry; without it the rig's pose, or the preset's)."""
    import typer

    from hilstack.learning.baoding import baoding_rig_problem
    from hilstack.learning.mbrl import RigError
    from hilstack.tools.common import UserError

    if quick and full:
        raise typer.BadParameter("choose --quick or --full, not both")
    if ray is not None and not full:
        raise typer.BadParameter("--ray is for the full run (--full): the other runs are one seed")
    extra = {"extra_recordings": [str(d) for d in extra_data], "extra_repeat": extra_repeat} if extra_data else {}
    if extra and full:
        raise typer.BadParameter("--extra-data is for one seed's run, not --full")
    if extra_repeat != 1 and not extra:
        raise typer.BadParameter("--extra-repeat needs --extra-data")
    if targets is not None:
        if targets not in TARGETS:
            raise typer.BadParameter(f"--targets must be {' or '.join(TARGETS)}, got {targets!r}")
        extra.update(TARGETS[targets])
    if iterations is not None:
        if full:
            raise typer.BadParameter("--iterations is for one seed's run, not --full")
        if iterations < 1:
            raise typer.BadParameter(f"--iterations must be >= 1, got {iterations}")
        extra["iterations"] = iterations
    try:
        rig, extra["task"] = pose_rig_task("quick" if quick else "thesis", rig, hold_pose)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    problem = baoding_rig_problem(rig, task=extra["task"])
    if problem:
        raise UserError(f"hil demo baoding --rig {rig}: {problem}")
    if out == Path("out/demo"):
        out = Path("out/baoding")
    try:
        if full:
            s = run_full(out, rig=rig, ray=ray, workers=workers, resume=resume, **extra)  # --targets, --hold-pose
            typer.echo(f"final PDDM success_90 {100 * s['final_success_90']['mean']:.0f} ± "
                       f"{100 * s['final_success_90']['std']:.0f} % (held to the end "
                       f"{100 * s.get('final_held_90', {}).get('mean', float('nan')):.0f} %), "
                       f"success_180 {100 * s['final_success_180']['mean']:.0f} %, "
                       f"rotation {s['final_mean_rotation_deg']['mean']:.0f}°, drop rate "
                       f"{s['final_drop_rate']['mean']:.2f} over seeds {s['seeds']}")
            typer.echo(f"report: {out / 'report.json'}")
            return
        r = run_baoding_demo(out, preset="quick" if quick else "thesis", seed=seed, resume=resume, rig=rig, **extra)
    except (RigError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    last = r["iterations"][-1]
    for label, m in (("random policy", r["random_policy"]), ("hold still", r["hold_policy"]),
                     (f"PDDM (iteration {last['iteration']})", last)):
        typer.echo(f"{label}: 90° {100 * m['success_90']:.0f} % ({100 * m['held_90']:.0f} % held), "
                   f"180° {100 * m['success_180']:.0f} %, rotation "
                   f"{m['mean_rotation_deg']:.0f}°, drops {m['drops']}/{m['episodes']}, steps held "
                   f"{m['mean_steps']:.0f}, return {m['return']['mean']:.1f}")
    typer.echo(f"ranked by turns: {' > '.join(r['ranking_by_turns'])}")
    typer.echo(f"resets: {r['resets']}; report: {out / 'report.md'}")


def compare_choices(run_dir: Path, out: Path | None = None, widths: tuple[int, ...] = (250, 500),
                    betas: tuple[float, ...] = (0.7, 0.6), episodes: int = 3, samples: int = 200,
                    epochs: int = 30, seed: int = 0) -> dict[str, Any]:
    """The small measured comparison behind the quick preset's 2x250 and β (docs/baoding.md).

    On the recordings of a finished run (``run_dir/recordings``): one fixed validation split;
    an ensemble of 3 for each hidden width, trained the same (``epochs``, Adam 1e-3, batch 500),
    compared on one-step and H-step validation error and on the time of one Baoding-scale plan
    (K=700, H=7); then PDDM closed loop with each (width, β) for ``episodes`` episodes on the
    MuJoCo hand in-process (the same sim the rig runs, without the bus: the planner is what is
    compared), K=``samples``. Writes ``out`` (default ``run_dir/compare.json``).
    """
    import torch

    from hilstack.control.costs import BaodingCost, baoding_episode_metrics
    from hilstack.control.planners import BAODING_PDDM
    from hilstack.control.policies import MpcPolicy
    from hilstack.drivers.shadow_hand.config import ShadowHandParams
    from hilstack.learning.baoding import (
        BaodingFeatures,
        BaodingPolicy,
        hold_action_map,
        load_baoding_task,
        summarize,
    )
    from hilstack.learning.datasets import split_episodes
    from hilstack.learning.dynamics import EnsembleDynamics
    from hilstack.learning.recordings import episodes_from_mcap
    from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim

    run_dir = Path(run_dir)
    eps = [e for f in sorted((run_dir / "recordings").glob("*.mcap")) if "eval" not in f.name
           for e in episodes_from_mcap(f, "hand")]
    raw_names = list(eps[0].meta["state_names"])
    feats, amap = BaodingFeatures(raw_names, 0.1), hold_action_map()  # the model's state and actions (BaodingRun's)
    eps = [feats.episode(e, amap) for e in eps]
    train, val = split_episodes(eps, 0.1, np.random.default_rng([seed, 1]), {})
    names = feats.names
    task = load_baoding_task()
    sim = ShadowHandSim(ShadowHandParams(objects_in_state=True))
    sim.configure()
    sim.activate()
    out_d: dict[str, Any] = {"points": int(sum(len(e) for e in train)), "val_points": int(sum(len(e) for e in val)),
                             "epochs": epochs, "episodes_per_setting": episodes, "samples": samples, "models": {},
                             "closed_loop": {}}
    for w in widths:
        torch.manual_seed(seed)
        m = EnsembleDynamics(len(names), 20, ensemble=3, hidden=(w, w), state_names=names, seed=seed)
        t0 = time.perf_counter()
        hist = m.fit(train, epochs=epochs, batch_size=500, val=val, horizon=7, progress=False)
        fit_s = time.perf_counter() - t0
        planner = BAODING_PDDM.planner()  # K=700, H=7: the thesis' plan size
        cost = BaodingCost(task, names, 0.1)
        cost.observe(None)
        s0 = eps[0].states[0]
        planner(m.predict, cost, s0)  # warm up
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            planner(m.predict, cost, s0)
            ts.append(time.perf_counter() - t0)
        out_d["models"][f"2x{w}"] = {"val_1step": hist[-1]["val_1step"], "val_h": hist[-1]["val_h"],
                                    "horizon": hist[-1]["horizon"], "fit_s": fit_s,
                                    "plan_ms_p50_K700": float(np.median(ts) * 1e3)}
        for b in betas:
            scores = []
            for e in range(episodes):
                sim.reset()
                pc = replace(BAODING_PDDM, samples=samples, beta=b, hidden=(w, w))
                pol = BaodingPolicy(MpcPolicy(m, pc.planner(seed=1000 + e, init_mean=np.zeros(20)),
                                              BaodingCost(task, names, 0.1)), BaodingFeatures(raw_names, 0.1), amap)
                pol.reset()
                o = sim.read()
                states, times = [o.state], [o.t_s]
                for _ in range(100):
                    sim.write(pol(o.state))
                    sim.tick()
                    o = sim.read()
                    states.append(o.state)
                    times.append(o.t_s)
                    if task.dropped(o.state[-6:].reshape(2, 3)):
                        break
                st = np.array(states)
                scores.append(baoding_episode_metrics(task, st[:, -6:].reshape(-1, 2, 3), times,
                                                      wrist_rad=st[:, raw_names.index("WRJ0_pos")]))
            out_d["closed_loop"][f"2x{w} beta {b:g}"] = summarize(scores)
    path = Path(out) if out else run_dir / "compare.json"
    path.write_text(json.dumps(out_d, indent=1))
    return out_d


#: the reference code's sampler (google-research/pddm): the default's, not the quick preset's
REF_SAMPLER: dict[str, Any] = {"sigma": 0.9, "filter": "actions", "beta": 0.6, "low_noise_fraction": 0.1, "gamma": 20.0}
#: the quick preset with all of issue 30 and the reference sampler ("ref"), and with one
#: setting of it put back as it was before issue 30; "gamma_100" is the quick preset as it now
#: is (docs/baoding.md, "Our numbers (quick run)")
OLD_SAMPLER: dict[str, Any] = {"sigma": 0.05, "filter": "noise", "beta": 0.7, "low_noise_fraction": 0.0, "gamma": 20.0}
ABLATIONS: dict[str, dict[str, Any]] = {
    "ref": dict(REF_SAMPLER),
    "clock_targets": {**REF_SAMPLER, "task_overrides": {"max_lead_rad": None}},
    # the quick preset of before this round (γ 20), a bolder sampler, and sharper weights (=
    # the quick preset now); docs/baoding.md, "Our numbers (quick run)"
    "old_sampler": dict(OLD_SAMPLER),
    "sigma_02": {**OLD_SAMPLER, "sigma": 0.2},
    "gamma_100": {**OLD_SAMPLER, "gamma": 100.0},
    "paper_filter": {**REF_SAMPLER, "filter": "noise", "beta": 0.7},
    "range_units": {**REF_SAMPLER, "action_units": "range"},
    "joint_vel": {**REF_SAMPLER, "joint_velocities": True},
    "no_low_noise": {**REF_SAMPLER, "low_noise_fraction": 0.0},
    "reward_3d_nowrist": {**REF_SAMPLER, "task_overrides": {"distance": "3d", "wrist_limit_rad": None}},
    "old_targets": {**REF_SAMPLER, "task_overrides": {"radius_m": 0.025, "radius_v_m": None,
                                                      "rate_rad_s": float(np.pi / 5)}},
    # the reference's training noise (noiseToSignal 0.01), here on each channel's std, and 10x it;
    # the quick preset otherwise (docs/baoding.md, "Training noise")
    "noise_001": {"noise_to_signal": 0.01},
    "noise_01": {"noise_to_signal": 0.1},
}


def ablate(out: Path, names: tuple[str, ...] = tuple(ABLATIONS), seed: int = 0, preset: str = "quick") -> list[dict]:
    """The ablations of :data:`ABLATIONS`, one run each (``out/<name>/``), one JSON line per run
    appended to ``out/results.jsonl``: the final iteration's and the pooled (all iterations')
    success_90 / success_180 / mean rotation / drop rate / steps held, hold's and random's, the
    per-iteration ESS and mean shift, the plan time and the load average."""
    out = Path(out)
    rows = []
    for n in names:
        t0 = time.time()
        r = run_baoding_demo(out / n, preset=preset, seed=seed, progress=False, **ABLATIONS[n])
        its = r["iterations"]
        keys = ("success_90", "success_180", "mean_rotation_deg", "drop_rate", "mean_steps")
        row = {"run": n, "overrides": ABLATIONS[n], "wall_s": time.time() - t0,
               "final": {k: its[-1][k] for k in keys},
               "pooled": {k: float(np.mean([it[k] for it in its])) for k in keys},
               "hold": {k: r["hold_policy"][k] for k in keys}, "random": {k: r["random_policy"][k] for k in keys},
               "ess_mean": [it["weights"].get("ess_mean") for it in its],
               "shift": [it["weights"].get("mean_shift_rms") for it in its],
               "plan_ms_p50": r["planner"]["plan_ms_p50"], "load": open("/proc/loadavg").read().split()[:3]}
        with open(out / "results.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")
        rows.append(row)
    return rows


def thesis_scale_cost(calls: int = 15, sizes: tuple[int, ...] = (700, 400, 200),
                      train_points: int = 4000) -> dict[str, Any]:
    """The levers of the thesis-scale run, measured on this machine (docs/baoding.md): the plan
    time of :data:`~hilstack.control.planners.BAODING_PDDM` (through a random-init ensemble of
    its size, on the 36-D model state) for each K in ``sizes``, fp32 and bf16, 1 and 2 torch
    threads; one training step of that ensemble (batch 500 per member); one lockstep period
    of the MuJoCo hand in-process. bf16 only runs natively where :func:`cpu_bf16_support` finds
    it (AMX, AVX512-BF16); elsewhere it is skipped. The load average is recorded."""
    import torch

    from hilstack.control.costs import BaodingCost
    from hilstack.control.planners import BAODING_PDDM
    from hilstack.drivers.shadow_hand.config import ShadowHandParams, shadow_hand_spec
    from hilstack.learning.baoding import BaodingFeatures, load_baoding_task
    from hilstack.learning.datasets import Episode
    from hilstack.learning.dynamics import EnsembleDynamics, cpu_bf16_support
    from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim

    threads0 = torch.get_num_threads()
    out: dict[str, Any] = {"cpu_bf16": cpu_bf16_support(), "loadavg_start": open("/proc/loadavg").read().split()[:3]}
    names = list(shadow_hand_spec(ShadowHandParams(objects_in_state=True)).state.names)
    f, task = BaodingFeatures(names, 0.1), load_baoding_task()
    rng = np.random.default_rng(0)
    eps = [Episode(states=rng.normal(size=(101, f.dim)), actions=rng.uniform(-1, 1, (100, 20)), name=f"e{i}")
           for i in range(max(1, train_points // 100))]
    m = EnsembleDynamics(f.dim, 20, ensemble=BAODING_PDDM.ensemble, hidden=BAODING_PDDM.hidden,
                         state_names=f.names, seed=0)
    t0 = time.perf_counter()
    m.fit(eps, epochs=2, batch_size=500, progress=False)
    out["train_ms_per_step"] = 1e3 * (time.perf_counter() - t0) / (2 * int(np.ceil(len(eps) * 100 / 500)))
    x0 = np.zeros(f.dim)
    x0[24:27] = x0[30:33] = task.center_m
    dtypes = ("fp32", "bf16") if out["cpu_bf16"] else ("fp32",)
    out["plan_ms"] = {}
    for k in sizes:
        for dt in dtypes:
            for th in (1, 2):
                torch.set_num_threads(th)
                m.set_inference_dtype(dt)
                pl = replace(BAODING_PDDM, samples=k).planner(seed=0, init_mean=np.zeros(20))
                cost = BaodingCost(task, f.names, 0.1)
                cost.observe(None)
                for _ in range(3):
                    pl(m.predict, cost, x0)
                ts = []
                for _ in range(calls):
                    t0 = time.perf_counter()
                    pl(m.predict, cost, x0)
                    ts.append(time.perf_counter() - t0)
                out["plan_ms"][f"K{k}_{dt}_{th}thread"] = {"p50": 1e3 * float(np.median(ts)),
                                                           "p99": 1e3 * float(np.percentile(ts, 99))}
    torch.set_num_threads(threads0)
    sim = ShadowHandSim(ShadowHandParams(objects_in_state=True))
    sim.configure()
    sim.activate()
    held = sim.held_command
    t0 = time.perf_counter()
    for _ in range(100):
        sim.write(held)
        sim.tick()
        sim.read()
    out["sim_ms_per_period"] = 1e3 * (time.perf_counter() - t0) / 100
    sim.cleanup()
    out["loadavg_end"] = open("/proc/loadavg").read().split()[:3]
    return out


#: the two presets' samplers (issue 30, the diagnosis of docs/baoding.md): the thesis-scale
#: default's (the reference code's: K 700, sigma 0.9, the action filter, beta 0.6, gamma 20, 10 %
#: low noise) and the quick preset's (K 200, sigma 0.05, the noise filter, beta 0.7, gamma 100)
SAMPLERS: dict[str, dict[str, Any]] = {
    "thesis": {"samples": 700, "sigma": 0.9, "filter": "actions", "beta": 0.6, "gamma": 20.0,
               "low_noise_fraction": 0.1},
    "quick": {"samples": 200, "sigma": 0.05, "filter": "noise", "beta": 0.7, "gamma": 100.0,
              "low_noise_fraction": 0.0},
}
#: the thesis-scale sampler with its candidates projected into the hand's rate limit (``rate_aware``)
SAMPLERS["thesis_rate"] = {**SAMPLERS["thesis"], "rate_aware": True}


def run_episodes(run_dir: Path, stems: list[str] | None = None) -> dict[str, list]:
    """The raw episodes of a run's recordings (``run_dir/recordings``), by recording stem
    (``000-random``, ``012-mpc``...); eval and set-aside recordings are left out."""
    from hilstack.learning.baoding import is_unfinished
    from hilstack.learning.recordings import episodes_from_mcap

    out: dict[str, list] = {}
    for f in sorted((Path(run_dir) / "recordings").glob("*.mcap")):
        if "eval" in f.name or is_unfinished(f) or (stems is not None and f.stem not in stems):
            continue
        out[f.stem] = episodes_from_mcap(f, "hand")
    return out


def _hand_for_closed_loop(sim, sampler: dict):
    """The in-process hand (``sim``, or a new active sim hand with the balls in its state), the
    task, its action map, the state names, the wrist's index, the sampler settings without
    ``rate_aware`` and, with it, the rate-aware reachable set (else None)."""
    from hilstack.drivers.registry import make_backend
    from hilstack.learning.baoding import hold_action_map, load_baoding_task

    if sim is None:
        sim = make_backend("shadow_hand", "sim", objects_in_state=True)
        sim.configure()
        sim.activate()
    task, amap = load_baoding_task(), hold_action_map()
    raw = list(sim.spec.state.names)
    sampler = dict(sampler)
    reach = amap.reachable(sim.spec.action_rate_per_s * sim.spec.period_s) if sampler.pop("rate_aware", False) else None
    return sim, task, amap, raw, raw.index("WRJ0_pos"), sampler, reach


def _episode(sim, pol, task, steps: int, wrist: int, plan_s: list, before_plan=None, cut: list | None = None,
             on_state=None) -> dict:
    """One in-process episode of ``pol`` on ``sim`` (a hand driver), until ``steps`` or a drop:
    its turn metrics. Appends each plan's time to ``plan_s`` and, with ``cut``, what the
    driver's rate limit took off each command; ``before_plan`` runs before each plan;
    ``on_state(obs, applied)`` gets every reading, with the command the hand applied during
    the period that ended with it (None for the first)."""
    from hilstack.control.costs import baoding_episode_metrics

    pol.reset()
    o = sim.read()
    if on_state is not None:
        on_state(o, None)
    states = [o.state]
    for _ in range(steps):
        if before_plan is not None:
            before_plan()
        t0 = time.perf_counter()
        act = pol(o.state)
        plan_s.append(time.perf_counter() - t0)
        applied = sim.write(act)
        if cut is not None:
            cut.append(np.abs(applied - act))  # what the driver's rate limit took off
        sim.tick()
        o = sim.read()
        if on_state is not None:
            on_state(o, applied)
        states.append(o.state)
        if task.dropped(o.state[-6:].reshape(2, 3)):
            break
    st = np.array(states)
    return baoding_episode_metrics(task, st[:, -6:].reshape(-1, 2, 3), None, wrist_rad=st[:, wrist], period_s=0.1)


def closed_loop(model, sampler: dict[str, Any], episodes: int, seed: int = 0, steps: int = 100,
                sim=None) -> dict[str, Any]:
    """PDDM through ``model`` on the MuJoCo hand in-process (the sim the rig runs, without the
    bus: the planner and the model are what is compared), ``episodes`` episodes of at most
    ``steps`` from the reset (hold pose, balls at rest), the planner's sampler from
    ``sampler`` (:data:`SAMPLERS`' keys over :data:`~hilstack.control.planners.BAODING_PDDM`),
    episode ``e`` planned with seed ``(seed, e)``; scored with the task's metrics
    (:func:`~hilstack.learning.baoding.summarize`), with the plan time p50."""
    from hilstack.control.costs import BaodingCost
    from hilstack.control.planners import BAODING_PDDM
    from hilstack.control.policies import MpcPolicy
    from hilstack.learning.baoding import (
        BaodingFeatures,
        BaodingPolicy,
        summarize,
    )

    own = sim is None
    sim, task, amap, raw, wrist, sampler, reach = _hand_for_closed_loop(sim, sampler)
    pc = replace(BAODING_PDDM, **sampler)
    scores, plan_s, cut = [], [], []
    try:
        for e in range(episodes):
            sim.reset()
            feats = BaodingFeatures(raw, 0.1)
            planner = pc.planner(seed=int(np.random.SeedSequence([seed, e]).generate_state(1)[0]),
                                 init_mean=np.zeros(pc.action_dim), reachable=reach)
            pol = BaodingPolicy(MpcPolicy(model, planner, BaodingCost(task, feats.names, 0.1)), feats, amap)
            scores.append(_episode(sim, pol, task, steps, wrist, plan_s, cut=cut))
    finally:
        if own:
            sim.cleanup()
    cut_a = np.array(cut)
    return {**summarize(scores), "rotation_per_episode_deg": [float(m["rotation_deg"]) for m in scores],
            "plan_ms_p50": 1e3 * float(np.median(plan_s)), "sampler": dict(sampler), "rate_aware": reach is not None,
            # the share of commanded joint steps the driver's rate limit cut, and by how much (driver units)
            "rate_cut_share": float((cut_a > 1e-6).mean()), "rate_cut_mean": float(cut_a.mean())}


class SimOracle:
    """A perfect model for the planner: the MuJoCo hand itself. Each plan's first call
    (:meth:`begin` before it) copies the hand's true state (MuJoCo's data and the firmware's
    loops) into one copy per candidate; each call then steps every copy one control period
    with its candidate's action (planner units, mapped to the driver's) and returns the
    copies' model states (:class:`~hilstack.learning.baoding.BaodingFeatures`); each copy's
    command goes through the driver's rate limit (``action_rate_per_s``, one write per period,
    from the command the hand holds), as the hand's own writes do. What PDDM
    scores with it is what the hand would do: an upper bound on what a learned model buys."""

    def __init__(self, sim, features, amap, period_s: float = 0.1):
        self.sim, self.features, self.amap, self.period_s = sim, features, amap, float(period_s)
        self.copies: list = []
        self.fresh = True

    def begin(self) -> None:
        self.fresh = True

    def _raw(self) -> np.ndarray:
        q, qd, _ = self.sim.joint_state()
        return np.concatenate([q, qd, self.sim.balls_m().reshape(-1)])

    def predict(self, state, action):
        import copy

        import mujoco
        import torch

        sim = self.sim
        a = np.asarray(action, dtype=np.float64)
        n = a.shape[0]
        if self.fresh:
            while len(self.copies) < n:
                self.copies.append([mujoco.MjData(sim.model), None, None, None])
            raw0 = self._raw()
            for c in self.copies[:n]:
                mujoco.mj_copyData(c[0], sim.model, sim.data)
                c[1], c[2] = copy.deepcopy(sim.firmware), raw0
                c[3] = None if sim._held is None else np.array(sim._held)
            self.fresh = False
        rate = sim.spec.action_rate_per_s
        step = None if rate is None else np.where(np.isfinite(rate), rate * sim.spec.period_s, np.inf)
        real = sim.data, sim.firmware, sim._badqacc_seen, sim._diverged_pending
        out = np.empty((n, self.features.dim))
        try:
            for k, c in enumerate(self.copies[:n]):
                sim.data, sim.firmware = c[0], c[1]
                cmd = self.amap.to_driver(a[k])
                if c[3] is not None and rate is not None:  # the driver's rate limit, one write per period
                    cmd = np.clip(cmd, c[3] - step, c[3] + step)
                cmd = np.clip(cmd, sim.spec.action.low, sim.spec.action.high)
                sim._write(cmd)
                c[3] = cmd
                sim._advance_locked(self.period_s)
                raw = self._raw()
                out[k] = self.features.transform(np.stack([c[2], raw]))[1]
                c[2] = raw
        finally:
            sim.data, sim.firmware, sim._badqacc_seen, sim._diverged_pending = real
        return torch.from_numpy(out).float()


def _oracle_policy(sim, raw, amap, task, pc, reach, seed: int, episode: int):
    """PDDM planning through the hand itself (:class:`SimOracle`) for one episode: the policy and
    its oracle (whose ``begin`` must run before each plan)."""
    from hilstack.control.costs import BaodingCost
    from hilstack.control.policies import MpcPolicy
    from hilstack.learning.baoding import BaodingFeatures, BaodingPolicy

    feats = BaodingFeatures(raw, 0.1)
    oracle = SimOracle(sim, BaodingFeatures(raw, 0.1), amap)
    planner = pc.planner(seed=int(np.random.SeedSequence([seed, episode]).generate_state(1)[0]),
                         init_mean=np.zeros(pc.action_dim), reachable=reach)
    return BaodingPolicy(MpcPolicy(oracle, planner, BaodingCost(task, feats.names, 0.1)), feats, amap), oracle


def oracle_closed_loop(sampler: dict[str, Any], episodes: int, samples: int, seed: int = 0,
                       steps: int = 40) -> dict[str, Any]:
    """PDDM planning through the hand itself (:class:`SimOracle`) with ``sampler`` at
    ``samples`` candidates, in-process, ``episodes`` episodes of ``steps``: can the task's
    cost and this sampler turn the pair at all when the model is perfect?"""
    from hilstack.control.planners import BAODING_PDDM
    from hilstack.learning.baoding import (
        summarize,
    )

    sim, task, amap, raw, wrist, sampler, reach = _hand_for_closed_loop(None, sampler)
    pc = replace(BAODING_PDDM, **{**sampler, "samples": samples})
    scores, plan_s = [], []
    try:
        for e in range(episodes):
            sim.reset()
            pol, oracle = _oracle_policy(sim, raw, amap, task, pc, reach, seed, e)
            scores.append(_episode(sim, pol, task, steps, wrist, plan_s, before_plan=oracle.begin))
    finally:
        sim.cleanup()
    return {**summarize(scores), "rotation_per_episode_deg": [float(m["rotation_deg"]) for m in scores],
            "max_rotation_per_episode_deg": [float(m["max_rotation_deg"]) for m in scores],
            "plan_ms_p50": 1e3 * float(np.median(plan_s)), "sampler": dict(sampler), "samples": samples,
            "steps": steps}


class EpisodeRecording:
    """One in-process episode as the demo records it (``OUT/recordings/<stem>.mcap``): the
    hand's spec, then one ``RobotState`` per reading with the command applied during the
    period that ended with it (driver units), so :func:`run_episodes`,
    :func:`~hilstack.learning.recordings.episodes_from_mcap` and :func:`probe_model` read
    it like a rig's recording. An existing file is refused, never overwritten."""

    def __init__(self, path: Path, spec, robot: str = "hand"):
        from hilstack.bus import keys
        from hilstack.bus.recording import McapLog
        from hilstack.bus.schemas import SpecMsg

        self.robot, self.n = robot, 0
        self.topic = keys.state("oracle", robot)
        self.log = McapLog(path, overwrite=False, foxglove=False)
        self.log.write(keys.spec("oracle", robot), SpecMsg(robot=robot, spec=spec.to_dict()), log_time_ns=0)

    def __call__(self, obs, applied) -> None:
        from hilstack.bus.schemas import RobotState

        self.n += 1
        self.log.write(self.topic, RobotState(
            robot=self.robot, t_s=float(obs.t_s), state=[float(x) for x in obs.state], obs_seq=int(obs.seq),
            ok=bool(obs.ok), active=True, action=[] if applied is None else [float(x) for x in applied],
            seq=self.n), log_time_ns=self.n)

    def close(self) -> None:
        self.log.close()


def _unfinished(path: Path) -> Path:
    """Where an episode's recording is written until the episode has ended (the loaders skip it)."""
    return path.with_name(path.stem + ".unfinished.mcap")


def oracle_record(out: Path, sampler: str = "thesis", episodes: int = 8, samples: int = 32, seed: int = 0,
                  steps: int = 40) -> list[dict[str, Any]]:
    """Record PDDM episodes planned through the hand itself (:class:`SimOracle`, sampler
    ``SAMPLERS[sampler]`` at ``samples`` candidates), in-process, ``episodes`` episodes of at most
    ``steps`` from the reset, episode ``e`` planned with seed ``(seed, e)`` (as
    :func:`oracle_closed_loop`): data that hold turns, to train a model on (docs/baoding.md,
    "Training on the oracle's turns"). Each episode is one recording,
    ``out/recordings/oracle-s<seed>-<e>.mcap`` (:class:`EpisodeRecording`, written as
    ``...-<e>.unfinished.mcap`` and given its name when the episode has ended, so a run stopped
    or killed mid-episode keeps the finished ones and the loaders skip the partial one), and one
    JSON line in ``out/oracle_episodes.jsonl`` with its turn figures, plan time and the load average."""
    from hilstack.control.planners import BAODING_PDDM

    out = Path(out)
    (out / "recordings").mkdir(parents=True, exist_ok=True)
    paths = [out / "recordings" / f"oracle-s{seed}-{e:03d}.mcap" for e in range(episodes)]
    there = [str(q) for p in paths for q in (p, _unfinished(p)) if q.exists()]
    if there:  # before anything runs: recorded data are never overwritten
        raise FileExistsError(f"oracle recordings already there: {there[0]} (and {len(there) - 1} more); "
                              "use another --seed or OUT")
    sim, task, amap, raw, wrist, sampler_d, reach = _hand_for_closed_loop(None, SAMPLERS[sampler])
    pc = replace(BAODING_PDDM, **{**sampler_d, "samples": samples})
    rows = []
    try:
        for e, path in enumerate(paths):
            sim.reset()
            pol, oracle = _oracle_policy(sim, raw, amap, task, pc, reach, seed, e)
            rec = EpisodeRecording(_unfinished(path), sim.spec)
            plan_s: list[float] = []
            t0 = time.perf_counter()
            try:
                m = _episode(sim, pol, task, steps, wrist, plan_s, before_plan=oracle.begin, on_state=rec)
            finally:
                rec.close()
            _unfinished(path).rename(path)  # only an episode that ended gets the name the loaders read
            row = {"recording": str(path), "seed": seed, "episode": e, "sampler": sampler, "samples": samples,
                   "steps": steps, "states": rec.n, "rotation_deg": float(m["rotation_deg"]),
                   "max_rotation_deg": float(m["max_rotation_deg"]), "dropped": bool(m["dropped"]),
                   "plan_ms_p50": 1e3 * float(np.median(plan_s)), "wall_s": time.perf_counter() - t0,
                   "loadavg": open("/proc/loadavg").read().split()[:3]}
            with open(out / "oracle_episodes.jsonl", "a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
            rows.append(row)
    finally:
        sim.cleanup()
    return rows


def run_split(run_dir: Path, iteration: int):
    """A stopped thesis-scale run's data as its checkpoint after ``iteration`` saw them:
    (features, action map, task, the held-out on-policy model episodes of iteration
    ``iteration`` (``<iteration>-mpc``: recorded after that model was trained, never trained on),
    the training model episodes (the run's split, without that iteration's recordings, doubled
    with the balls swapped as the run trains))."""
    from hilstack.learning.baoding import BaodingFeatures, hold_action_map, load_baoding_task

    run_dir = Path(run_dir)
    report = run_dir / "report.json"
    task_name = json.loads(report.read_text()).get("config", {}).get("task", "baoding") if report.exists() else "baoding"
    if task_name != "baoding":  # the probes and closed loops here build the default (cupped) hand
        raise ValueError(f"{run_dir} ran task {task_name}: diagnose and oracle-train model the default hold pose's "
                         "hand (task baoding) only")
    state = json.loads((run_dir / "checkpoint" / "state.json").read_text())
    if state["iteration"] != iteration:
        raise ValueError(f"{run_dir}: its checkpoint is after iteration {state['iteration']}, not {iteration}")
    stems = [Path(r).stem for r in state["data_recordings"]]
    held = f"{iteration:03d}-mpc"
    data = run_episodes(run_dir, stems)
    raw = list(next(iter(data.values()))[0].meta["state_names"])
    feats, amap, task = BaodingFeatures(raw, 0.1), hold_action_map(), load_baoding_task()
    heldout = [feats.episode(e, amap) for e in data.pop(held)]
    train = [feats.episode(e, amap) for k, v in data.items() if k != f"{iteration:03d}-random" for e in v
             if not state["val_assigned"].get(e.name)]
    return feats, amap, task, heldout, train + [feats.swap_balls(e) for e in train]


def run_checkpoint_model(run_dir: Path):
    """The model a stopped run's checkpoint holds, with its Adam state and bootstrap generator
    (so more training continues the run's own)."""
    import torch

    from hilstack.learning.dynamics import EnsembleDynamics

    run_dir = Path(run_dir)
    m = EnsembleDynamics.load(run_dir / "checkpoint" / "model.pt")
    ts = torch.load(run_dir / "checkpoint" / "train_state.pt", weights_only=True)
    m._optimizer = torch.optim.Adam(m.parameters(), lr=m.config["lr"], weight_decay=m.config["weight_decay"])
    m._optimizer.load_state_dict(ts["optimizer"])
    m._gen.set_state(ts["generator"])
    return m


def eval_model(run_dir: Path, out: Path, name: str, episodes: int = 20, settings: dict[str, Any] | None = None,
               inference_dtype: str = "auto") -> dict[str, Any]:
    """PDDM with a run's last checkpointed model (``run_dir/checkpoint/model.pt``), no training,
    for ``episodes`` episodes on the run's rig with its preset's settings changed by
    ``settings`` (``BaodingConfig`` fields; ``task.FIELD`` for the task's, e.g.
    ``task.max_lead_rad``): does a planner or cost setting alone change the turns or the drops?
    Recorded to ``out/name/recordings``; one JSON line in ``out/eval.jsonl`` (the settings,
    the turn figures, wall time, load). The run's rig and task unless ``settings`` names them."""
    from dataclasses import fields

    from hilstack.configs.schema import load_rig
    from hilstack.learning.baoding import load_baoding_task, summarize
    from hilstack.learning.dynamics import EnsembleDynamics
    from hilstack.tools.common import provision_credentials, with_endpoint

    cfg_run = json.loads(_report_path(run_dir).read_text()).get("config", {})
    ckpt = Path(run_dir) / "checkpoint" / "model.pt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"no model {ckpt} (a run's checkpoint)")
    over, task_over = {}, {}
    for k, v in (settings or {}).items():
        (task_over if k.startswith("task.") else over)[k.removeprefix("task.")] = v
    known = {f.name for f in fields(BaodingConfig)}
    task_known = {f.name for f in fields(load_baoding_task())}
    bad = [k for k in over if k not in known] + [f"task.{k}" for k in task_over if k not in task_known]
    if bad:
        raise ValueError(f"eval: unknown setting {bad[0]!r} (BaodingConfig fields, or task.FIELD of "
                         f"{', '.join(sorted(task_known))})")
    over = {"rig": cfg_run.get("rig"), "task": cfg_run.get("task"), **over}
    if task_over:
        over["task_overrides"] = {**over.get("task_overrides", {}), **task_over}
    cfg = make_config(cfg_run.get("preset", "thesis"), int(cfg_run.get("seed", 0)), **over)
    d = Path(out) / name
    if d.exists():
        raise FileExistsError(f"{d} exists: choose another name (recordings are never overwritten)")
    rig = load_rig(cfg.rig)
    bus = with_endpoint(rig.bus, free_endpoint())
    provision_credentials(rig.name, bus, rig)
    run = BaodingRun(cfg, d, bus)
    model = EnsembleDynamics.load(ckpt)
    t0 = time.perf_counter()
    with run.torch_threads():  # before the precision's timing: the run's thread count
        dtype = model.set_inference_dtype(inference_dtype)
        with run.session():
            _, scores = run.run_episodes(lambda i: run.pddm_policy(model, run._seed(77, i), run.pddm_samples()),
                                         episodes, "eval-pddm", f"eval {name}")
    s = summarize(scores)
    row = {"what": "eval", "run": str(run_dir), "name": name, "settings": settings or {},
           "inference_dtype": str(dtype).removeprefix("torch."), "wall_s": time.perf_counter() - t0,
           **{k: s[k] for k in ("episodes", "success_90", "held_90", "success_180", "mean_rotation_deg", "drops",
                                "mean_steps")}}
    _jsonl_log(Path(out) / "eval.jsonl")(row)
    return row


def _jsonl_log(path: Path):
    def log(row: dict[str, Any]) -> None:
        row["loadavg"] = open("/proc/loadavg").read().split()[:3]
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)

    return log


def oracle_split(oracle_dir: Path, feats, amap, heldout_seeds: tuple[int, ...]) -> tuple[list, list]:
    """The oracle's recorded episodes (:func:`oracle_record`) as model episodes: (training ones,
    doubled with the balls swapped; held-out ones, those recorded with a seed in ``heldout_seeds``)."""
    data = run_episodes(Path(oracle_dir))
    train, held = [], []
    for stem, eps in sorted(data.items()):
        seed = int(stem.split("-")[1][1:])  # oracle-s<seed>-<episode>
        (held if seed in heldout_seeds else train).extend(feats.episode(e, amap) for e in eps)
    return train + [feats.swap_balls(e) for e in train], held


#: the models :func:`train_on_oracle` makes and probes
ORACLE_MODELS = ("run", "control", "run+oracle", "oracle_only")


def _probe_all(models: dict, probes: dict, task, log) -> list[dict[str, Any]]:
    """:func:`probe_model` of every model on every probe set, each row logged and returned."""
    rows = []
    for name, m in models.items():
        m.set_inference_dtype("auto")
        for pname, eps in probes.items():
            row = {"what": "probe", "model": name, "heldout": pname, **probe_model(m, eps, task)}
            log(row)
            rows.append(row)
    return rows


def train_on_oracle(run_dir: Path, oracle_dir: Path, out: Path, iteration: int, heldout_seeds: tuple[int, ...],
                    steps: int = 400, oracle_repeat: int = 20, seed: int = 0,
                    models_wanted: tuple[str, ...] = ORACLE_MODELS) -> dict[str, Any]:
    """Can the model learn the turn from our features when the data hold turns (docs/baoding.md,
    "Training on the oracle's turns")? From a stopped thesis-scale run's checkpoint after
    ``iteration`` and the oracle's recordings in ``oracle_dir`` (:func:`oracle_record`), models of
    the run's size: ``run`` (the checkpoint's), ``run+<steps>`` (``steps`` more gradient steps,
    rounded up to whole epochs, on the run's training episodes: the same effort, no turns added;
    read from ``out/model_run+<steps>.pt`` when there),
    ``run+<steps>+oracle`` (the same number of epochs on the run's episodes plus the oracle's
    training episodes repeated ``oracle_repeat`` times) and ``oracle_only`` (a fresh model of the
    run's configuration, about ``steps`` steps on the oracle's training episodes alone). Each is
    probed (:func:`probe_model`) on the held-out oracle episodes (seeds ``heldout_seeds``), on
    the run's held-out on-policy episodes (``<iteration>-mpc``) and on the oracle's training
    episodes (the fit), one JSON line each in ``out/results.jsonl``; the models are saved as
    ``out/model_<name>.pt`` for :func:`closed_loop` (``closed-loop`` on the command line).
    ``models_wanted``: a subset of :data:`ORACLE_MODELS` (``control`` = ``run+<steps>``), so that
    separate processes can train them side by side."""
    unknown = sorted(set(models_wanted) - set(ORACLE_MODELS))
    if unknown:
        raise ValueError(f"unknown model(s) {unknown}; known: {', '.join(ORACLE_MODELS)}")
    import torch

    from hilstack.learning.dynamics import EnsembleDynamics

    if not any((Path(oracle_dir) / "recordings").glob("oracle-s*.mcap")):  # before the run's data load
        raise FileNotFoundError(f"{oracle_dir}: no oracle recordings (recordings/oracle-s*.mcap; oracle-record makes them)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log = _jsonl_log(out / "results.jsonl")
    feats, amap, task, run_held, run_train = run_split(run_dir, iteration)
    o_train, o_held = oracle_split(oracle_dir, feats, amap, heldout_seeds)
    if not o_train or not o_held:
        raise ValueError(f"{oracle_dir}: {len(o_train) // 2} training and {len(o_held)} held-out oracle episodes "
                         f"(held-out seeds {list(heldout_seeds)}); need both")
    n_run = sum(len(e) for e in run_train)
    epochs = max(1, int(np.ceil(steps * 500 / n_run)))
    log({"what": "data", "run_train_points": n_run, "run_heldout_episodes": len(run_held),
         "oracle_train_episodes": len(o_train) // 2, "oracle_train_points": sum(len(e) for e in o_train),
         "oracle_heldout_episodes": len(o_held), "oracle_repeat": oracle_repeat, "epochs": epochs})
    models: dict[str, Any] = {"run": run_checkpoint_model(run_dir)}
    config = models["run"].config
    if "run" not in models_wanted:
        del models["run"]

    def fit(name: str, m, eps: list, ep: int) -> None:
        t0 = time.perf_counter()
        hist = m.fit(eps, epochs=ep, batch_size=500, progress=False)
        n = sum(len(e) for e in eps)
        log({"what": "training", "model": name, "epochs": ep, "points": n, "steps": ep * int(np.ceil(n / 500)),
             "train_loss_first": hist[0]["train_loss"], "train_loss_last": hist[-1]["train_loss"],
             "wall_s": time.perf_counter() - t0})
        m.save(out / f"model_{name}.pt")
        models[name] = m

    control = out / f"model_run+{steps}.pt"
    if "control" not in models_wanted:
        pass
    elif control.is_file():  # trained already (here, or by `diagnose --extra-steps <steps>` into this OUT: the same fit)
        models[f"run+{steps}"] = EnsembleDynamics.load(control)
        log({"what": "training", "model": f"run+{steps}", "loaded": str(control)})
    else:
        fit(f"run+{steps}", run_checkpoint_model(run_dir), run_train, epochs)
    if "run+oracle" in models_wanted:
        fit(f"run+{steps}+oracle", run_checkpoint_model(run_dir), run_train + o_train * oracle_repeat, epochs)
    if "oracle_only" in models_wanted:
        torch.manual_seed(seed)
        fresh = EnsembleDynamics(feats.dim, 20, ensemble=config["ensemble"], hidden=tuple(config["hidden"]),
                                 state_names=feats.names, seed=seed, lr=config["lr"])
        n_o = sum(len(e) for e in o_train)
        fit("oracle_only", fresh, o_train, max(1, int(np.ceil(steps / np.ceil(n_o / 500)))))
    probes = {"oracle_heldout": o_held, f"run:{iteration:03d}-mpc": run_held,
              "oracle_train": o_train[:len(o_train) // 2]}
    rows = _probe_all(models, probes, task, log)
    return {"rows": rows}


def diagnose(run_dir: Path, out: Path, iteration: int, extra_steps: int = 1000, quick_run: Path | None = None,
             episodes: int = 6, seeds: tuple[int, ...] = (0, 1), samplers: tuple[str, ...] = ("thesis", "quick"),
             steps: int = 100, closed_loop_models: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Why the thesis-scale run turns the pair no further than the quick one (docs/baoding.md,
    "Why success_90 stays at 0"). On a stopped thesis-scale run's checkpoint after
    ``iteration`` (``run_dir/checkpoint``): the model the run planned with, and the same model
    trained about ``extra_steps`` more gradient steps (rounded up to whole epochs) on the same training episodes (the run's
    split, the balls-swapped doubling, its Adam state): does the fixed 200 steps per
    iteration underfit? With ``quick_run``: that run's final model too. Each is probed
    (:func:`probe_model`) on the held-out on-policy episodes of iteration ``iteration``
    (``<iteration>-mpc``: recorded after that model was trained, never trained on), and run
    closed loop (:func:`closed_loop`) with each sampler of :data:`SAMPLERS`, ``episodes``
    episodes per seed in ``seeds`` (only the models named in ``closed_loop_models``, when
    given: ``run``, ``run+<extra_steps>``, ``quick_final``). Appends one JSON line per result
    to ``out/results.jsonl``."""
    from hilstack.learning.dynamics import EnsembleDynamics

    run_dir, out = Path(run_dir), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    feats, amap, task, heldout, train = run_split(run_dir, iteration)
    log = _jsonl_log(out / "results.jsonl")

    def checkpoint_model() -> EnsembleDynamics:
        return run_checkpoint_model(run_dir)

    models: dict[str, Any] = {"run": checkpoint_model()}
    if extra_steps:
        m = checkpoint_model()
        n = sum(len(e) for e in train)
        epochs = max(1, int(np.ceil(extra_steps * 500 / n)))
        t0 = time.perf_counter()
        hist = m.fit(train, epochs=epochs, batch_size=500, progress=False)
        log({"what": "extra training", "model": f"run+{extra_steps}", "epochs": epochs, "train_points": n,
             "train_loss_first": hist[0]["train_loss"], "train_loss_last": hist[-1]["train_loss"],
             "wall_s": time.perf_counter() - t0})
        m.save(out / f"model_run+{extra_steps}.pt")
        models[f"run+{extra_steps}"] = m
    if quick_run is not None:
        models["quick_final"] = EnsembleDynamics.load(Path(quick_run) / "model.pt")
    probes = {f"{run_dir.name}:{iteration:03d}-mpc": heldout}
    if quick_run is not None:  # its last PDDM rollouts: recorded after its final model was trained
        qlast = sorted(f.stem for f in (Path(quick_run) / "recordings").glob("*-mpc.mcap"))[-1]
        probes[f"{Path(quick_run).name}:{qlast}"] = [feats.episode(e, amap)
                                                     for e in run_episodes(Path(quick_run), [qlast])[qlast]]
    rows = _probe_all(models, probes, task, log)
    sim = None
    from hilstack.drivers.registry import make_backend

    sim = make_backend("shadow_hand", "sim", objects_in_state=True)
    sim.configure()
    sim.activate()
    try:
        for name, m in models.items():
            if closed_loop_models is not None and name not in closed_loop_models:
                continue
            for sname in samplers:
                for sd in seeds:
                    t0 = time.perf_counter()
                    r = closed_loop(m, SAMPLERS[sname], episodes, seed=sd, steps=steps, sim=sim)
                    row = {"what": "closed loop", "model": name, "sampler": sname, "seed": sd, "wall_s":
                           time.perf_counter() - t0, **{k: r[k] for k in ("episodes", "success_90", "success_180",
                                                                           "mean_rotation_deg", "drops", "mean_steps",
                                                                           "plan_ms_p50", "rotation_per_episode_deg",
                                                                           "rate_cut_share", "rate_cut_mean")}}
                    log(row)
                    rows.append(row)
    finally:
        sim.cleanup()
    return {"rows": rows}


def _pairs(ap, items: list[str], what: str) -> list[tuple[str, str]]:
    """``A=B`` arguments split at the first ``=``; a usage error naming the first without one."""
    bad = [x for x in items if "=" not in x]
    if bad:
        ap.error(f"{what}, got {bad[0]!r}")
    return [tuple(x.split("=", 1)) for x in items]


def torch_threads(n: int) -> None:
    import torch

    torch.set_num_threads(n)


def main(argv: list[str] | None = None) -> None:
    """``python -m hilstack.tools.demo_baoding compare RUN_DIR | cost | plot RUN_DIR | ablate OUT [NAME...] [--seed S]
    | diagnose RUN_DIR OUT --iteration N | oracle OUT | oracle-record OUT | oracle-train RUN_DIR ORACLE_DIR OUT
    --iteration N --heldout-seeds S... | closed-loop MODEL... --out OUT | table LABEL=RUN_DIR... [--from N]
    | plot-seeds PNG LABEL=RUN_DIR... | eval RUN_DIR OUT NAME [KEY=VALUE...]``."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.demo_baoding",
                                 description="Baoding demo studies (the demo itself: hil demo baoding).")
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("compare", help="compare the sampler choices of a finished run")
    c.add_argument("run_dir", type=Path)
    sub.add_parser("cost", help="what the thesis-scale run would cost here")
    pl = sub.add_parser("plot", help="turns.png of a run's report.json, a stopped (partial) one too")
    pl.add_argument("run_dir", type=Path)
    ab = sub.add_parser("ablate", help="run the ablations (all when no NAME is given)")
    ab.add_argument("out", type=Path)
    ab.add_argument("names", nargs="*", metavar="NAME", help="ablation names")
    ab.add_argument("--seed", type=int, default=0)
    dg = sub.add_parser("diagnose", help="a stopped thesis-scale run's model: held-out probe and closed loop")
    dg.add_argument("run_dir", type=Path)
    dg.add_argument("out", type=Path)
    dg.add_argument("--iteration", type=int, required=True, help="the checkpoint's iteration")
    dg.add_argument("--extra-steps", type=int, default=1000)
    dg.add_argument("--quick-run", type=Path, default=None, help="a finished quick run: its final model too")
    dg.add_argument("--episodes", type=int, default=6, help="closed-loop episodes per seed and setting")
    dg.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    dg.add_argument("--samplers", nargs="+", default=list(SAMPLERS), choices=list(SAMPLERS))
    dg.add_argument("--steps", type=int, default=100)
    dg.add_argument("--closed-loop-models", nargs="+", default=None, help="run, run+N, quick_final (default all)")
    orc = sub.add_parser("oracle", help="PDDM planning through the hand itself (a perfect model)")
    orc.add_argument("out", type=Path)
    orc.add_argument("--samplers", nargs="+", default=list(SAMPLERS), choices=list(SAMPLERS))
    orc.add_argument("--samples", type=int, default=48)
    orc.add_argument("--episodes", type=int, default=2)
    orc.add_argument("--steps", type=int, default=40)
    orc.add_argument("--seed", type=int, default=0)
    orr = sub.add_parser("oracle-record", help="record PDDM episodes planned through the hand itself")
    orr.add_argument("out", type=Path)
    orr.add_argument("--sampler", default="thesis", choices=list(SAMPLERS))
    orr.add_argument("--samples", type=int, default=32)
    orr.add_argument("--episodes", type=int, default=8)
    orr.add_argument("--steps", type=int, default=40)
    orr.add_argument("--seed", type=int, default=0)
    ot = sub.add_parser("oracle-train", help="train the run's model on the oracle's episodes and probe it")
    ot.add_argument("run_dir", type=Path)
    ot.add_argument("oracle_dir", type=Path, help="an oracle-record OUT")
    ot.add_argument("out", type=Path)
    ot.add_argument("--iteration", type=int, required=True, help="the run checkpoint's iteration")
    ot.add_argument("--heldout-seeds", type=int, nargs="+", required=True, help="oracle seeds held out")
    ot.add_argument("--steps", type=int, default=400)
    ot.add_argument("--oracle-repeat", type=int, default=20)
    ot.add_argument("--models", nargs="+", default=list(ORACLE_MODELS), choices=list(ORACLE_MODELS))
    ev = sub.add_parser("eval", help="PDDM with a run's last model, no training, its settings changed "
                        "(KEY=VALUE: a BaodingConfig field, task.FIELD for the task's; values as JSON)")
    ev.add_argument("run_dir", type=Path)
    ev.add_argument("out", type=Path)
    ev.add_argument("name")
    ev.add_argument("settings", nargs="*", metavar="KEY=VALUE")
    ev.add_argument("--episodes", type=int, default=20)
    ev.add_argument("--inference-dtype", default="auto", choices=("fp32", "bf16", "auto"))
    ps = sub.add_parser("plot-seeds", help="success_90 / held_90 of several seeds' runs against the points, "
                        "their mean bold, beside the thesis' ~100k marker (--full writes it too)")
    ps.add_argument("png", type=Path)
    ps.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    ps.add_argument("--rescore", action="store_true", help="the turn figures from the recordings (table --rescore)")
    ps.add_argument("--task", default=None, help="with --rescore: the task config to score with (default the run's)")
    tb = sub.add_parser("table", help="a markdown table of runs' iterations (their report.json)")
    tb.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    tb.add_argument("--from", dest="first", type=int, default=1, help="the first iteration listed")
    tb.add_argument("--rescore", action="store_true", help="score the turns again from the recordings (held_90, "
                    "every early end a drop): figures for runs whose report predates today's scoring")
    tb.add_argument("--task", default=None, help="with --rescore: the task config to score with (default the run's)")
    tb.add_argument("--rise-limit", type=float, default=None, metavar="M",
                    help="with --rescore: a turn counts only while both balls are within M metres above where "
                         "they started (the palm's normal; a ball lifted or thrown turns the pair too)")
    cl = sub.add_parser("closed-loop", help="PDDM through saved models on the MuJoCo hand in-process")
    cl.add_argument("models", type=Path, nargs="+", help="model .pt files (EnsembleDynamics.save)")
    cl.add_argument("--out", type=Path, required=True)
    cl.add_argument("--sampler", default="thesis", choices=list(SAMPLERS))
    cl.add_argument("--episodes", type=int, default=5, help="episodes per seed")
    cl.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    cl.add_argument("--steps", type=int, default=100)
    a = ap.parse_args(argv)
    try:
        _run_cmd(ap, a)
    except (FileExistsError, FileNotFoundError, ValueError) as e:  # bad input: one line, no traceback
        raise SystemExit(f"error: {e}") from None


def rescore_iterations(run_dir: Path, task: str | None = None, first: int = 1,
                       rise_limit_m: float | None = None) -> dict[int, dict[str, Any]]:
    """The turn figures of a run's PDDM iterations from ``first`` on, scored again from its
    recordings (``NNN-mpc.mcap``) with today's scoring (:func:`summarize`: ``held_90``, drops):
    iteration → summary. Reports written by older code lack ``held_90`` and counted only the
    task's own drop rule; here an episode shorter than the run's ``episode_steps`` counts as
    dropped, as the rig's drop detector is the only thing that ends a PDDM episode early
    (:meth:`BaodingRun.score`). ``task``: the task config to score with (default the run's;
    runs that edited a task in place need the name of today's equivalent). The period is the
    recorded states' median spacing. ``rise_limit_m``: turns count only while both balls are
    within that height above where they started (:func:`baoding_episode_metrics`)."""
    from hilstack.control.costs import baoding_episode_metrics
    from hilstack.learning.baoding import BALL_NAMES, load_baoding_task, summarize

    report = json.loads(_report_path(run_dir).read_text())
    cfg = report.get("config", {})
    name = task or cfg.get("task")
    if not name:
        raise ValueError(f"{run_dir}: its report names no task; give one (--task)")
    tk, steps = load_baoding_task(name), int(cfg.get("episode_steps", 100))
    wanted = [it["iteration"] for it in report["iterations"] if it["iteration"] >= first]
    eps = run_episodes(Path(run_dir), [f"{i:03d}-mpc" for i in wanted])
    out = {}
    for i in wanted:
        scores = []
        for e in eps.get(f"{i:03d}-mpc", []):
            names, st = e.meta["state_names"], np.asarray(e.states)
            period = float(np.round(np.median(np.diff(e.times)), 3)) if len(e.times) > 1 else 0.1
            m = baoding_episode_metrics(tk, st[:, [names.index(n) for n in BALL_NAMES]].reshape(-1, 2, 3), None,
                                        wrist_rad=st[:, names.index("WRJ0_pos")], period_s=period,
                                        rise_limit_m=rise_limit_m)
            if len(st) < steps + 1:
                m["dropped"] = 1.0
            scores.append(m)
        if not scores:
            raise ValueError(f"{run_dir}: no recorded episodes for iteration {i} (recordings/{i:03d}-mpc.mcap)")
        out[i] = summarize(scores)
    return out


def _report_path(run_dir: Path) -> Path:
    p = Path(run_dir) / "report.json"
    if not p.is_file():
        raise FileNotFoundError(f"no report {p}")
    return p


def iterations_table(runs: dict[str, Path], first: int = 1, rescore: bool = False, task: str | None = None,
                     rise_limit_m: float | None = None) -> str:
    """A markdown table of the iterations from ``first`` on of each run (label → run directory;
    its ``report.json``, a stopped run's partial one too): the turn figures, the model's turn R²
    on the iteration's own PDDM episodes (``own_turn``), ESS, the demonstrations' share of the
    training split and where the time went. ``rescore``: the turn figures (success, held_90,
    rotation, drops, steps held) from the recordings (:func:`rescore_iterations`, with ``task``
    and ``rise_limit_m``) instead of the report."""
    lines = ["| run | iteration | points | demo share | success_90 | held_90 | success_180 | mean rotation (°) | drops | "
             "steps held | own turn R² (true 7-step turn std, windows) | ESS (% of K) | wall s (load) |", "|---" * 13 + "|"]
    for label, d in runs.items():
        again = rescore_iterations(d, task, first, rise_limit_m) if rescore else {}
        for it in json.loads(_report_path(d).read_text())["iterations"]:
            if it["iteration"] < first:
                continue
            it = {**it, **again.get(it["iteration"], {})}
            own, w, dm = it.get("own_turn", {}), it.get("weights", {}), it.get("demonstrations")
            r2 = (f"{own['turn_r2']:.2f} ({own.get('turn_true_std_deg', float('nan')):.1f}°, {own['windows']})"
                  if own.get("windows") else "–")
            ess = f"{w['ess_mean']:.1f} ({100 * w['ess_frac_mean']:.0f} %)" if w.get("plans") else "–"
            load = (it.get("timing") or {}).get("loadavg") or ["?"]
            share = f"{100 * dm['share']:.0f} %" if dm else "–"
            held = f"{100 * it['held_90']:.0f} %" if "held_90" in it else "–"  # runs before it was reported
            lines.append(f"| {label} | {it['iteration']} | {it['points']} | {share} | {100 * it['success_90']:.0f} % | {held} | "
                         f"{100 * it['success_180']:.0f} % | {it['mean_rotation_deg']:+.1f} | {it['drops']}/{it['episodes']} | "
                         f"{it['mean_steps']:.0f} | {r2} | {ess} | {it['wall_s']['iteration']:.0f} ({load[0]}) |")
    return "\n".join(lines) + "\n"


def closed_loop_models(paths: list[Path], out: Path, sampler: str = "thesis", episodes: int = 5,
                       seeds: tuple[int, ...] = (0, 1), steps: int = 100) -> list[dict[str, Any]]:
    """:func:`closed_loop` for each saved model (``EnsembleDynamics.save``) and seed, one JSON line
    each in ``out/closed_loop.jsonl`` (the model's file, the turn figures, wall time, load)."""
    from hilstack.learning.dynamics import EnsembleDynamics

    missing = [str(p) for p in paths if not Path(p).is_file()]
    if missing:
        raise FileNotFoundError(f"no model file {missing[0]}")
    Path(out).mkdir(parents=True, exist_ok=True)
    log = _jsonl_log(Path(out) / "closed_loop.jsonl")
    rows = []
    for p in paths:
        m = EnsembleDynamics.load(p)
        m.set_inference_dtype("auto")
        for sd in seeds:
            t0 = time.perf_counter()
            r = closed_loop(m, SAMPLERS[sampler], episodes, seed=sd, steps=steps)
            row = {"what": "closed loop", "model": str(p), "sampler": sampler, "seed": sd,
                   "wall_s": time.perf_counter() - t0,
                   **{k: r[k] for k in ("episodes", "success_90", "success_180", "mean_rotation_deg", "drops",
                                        "mean_steps", "plan_ms_p50", "rotation_per_episode_deg")}}
            log(row)
            rows.append(row)
    return rows


def _run_cmd(ap, a) -> None:
    if a.cmd == "cost":
        print(json.dumps(thesis_scale_cost(), indent=1))
    elif a.cmd == "diagnose":
        torch_threads(1)
        diagnose(a.run_dir, a.out, a.iteration, a.extra_steps, a.quick_run, a.episodes, tuple(a.seeds),
                 tuple(a.samplers), a.steps, None if a.closed_loop_models is None else tuple(a.closed_loop_models))
    elif a.cmd == "oracle":
        torch_threads(1)
        a.out.mkdir(parents=True, exist_ok=True)
        for sname in a.samplers:
            t0 = time.perf_counter()
            r = oracle_closed_loop(SAMPLERS[sname], a.episodes, a.samples, a.seed, a.steps)
            row = {"sampler_name": sname, "wall_s": time.perf_counter() - t0, **r}
            with open(a.out / "oracle.jsonl", "a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    elif a.cmd == "oracle-train":
        torch_threads(1)
        train_on_oracle(a.run_dir, a.oracle_dir, a.out, a.iteration, tuple(a.heldout_seeds), a.steps,
                        a.oracle_repeat, models_wanted=tuple(a.models))
    elif a.cmd == "closed-loop":
        torch_threads(1)
        closed_loop_models(a.models, a.out, a.sampler, a.episodes, tuple(a.seeds), a.steps)
    elif a.cmd == "oracle-record":
        torch_threads(1)
        oracle_record(a.out, a.sampler, a.episodes, a.samples, a.seed, a.steps)
    elif a.cmd == "table":
        runs = _pairs(ap, a.runs, "a run is LABEL=RUN_DIR")
        if a.rise_limit is not None and not a.rescore:
            ap.error("--rise-limit is for --rescore")
        print(iterations_table({k: Path(v) for k, v in runs}, a.first, a.rescore, a.task, a.rise_limit), end="")
    elif a.cmd == "plot":
        print(write_plot(json.loads((a.run_dir / "report.json").read_text()), a.run_dir))
    elif a.cmd == "eval":
        settings = {}
        for k, v in _pairs(ap, a.settings, "a setting is KEY=VALUE"):
            try:
                settings[k] = json.loads(v)
            except json.JSONDecodeError:
                settings[k] = v  # a name (a rig, a task)
        eval_model(a.run_dir, a.out, a.name, a.episodes, settings, a.inference_dtype)
    elif a.cmd == "plot-seeds":
        runs = {}
        for label, d in _pairs(ap, a.runs, "a run is LABEL=RUN_DIR"):
            rep = json.loads(_report_path(Path(d)).read_text())
            if a.rescore:  # the turn figures again from the recordings (old reports: no held_90)
                again = rescore_iterations(Path(d), a.task)
                rep["iterations"] = [{**it, **again.get(it["iteration"], {})} for it in rep["iterations"]]
            runs[label] = rep
        print(write_seeds_plot(runs, a.png))
    elif a.cmd == "ablate":
        unknown = [n for n in a.names if n not in ABLATIONS]
        if unknown:
            ap.error(f"unknown ablation(s) {unknown}; known: {', '.join(ABLATIONS)}")
        print(json.dumps(ablate(a.out, tuple(a.names) or tuple(ABLATIONS), seed=a.seed), indent=1))
    else:
        print(json.dumps(compare_choices(a.run_dir), indent=1))


if __name__ == "__main__":
    main()
