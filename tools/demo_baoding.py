"""`hil demo baoding`: PDDM on the simulated Shadow Hand's Baoding balls, every node on the bus.

Writes ``OUT/report.json``, ``OUT/report.md``, ``OUT/returns.png``, the MCAP recordings of
every phase and a rerun ``OUT/demo.rrd`` of the last PDDM iteration (docs/baoding.md).
``--quick``: the scaled-down preset (:meth:`hilstack.learning.baoding.BaodingConfig.quick`, ≤10 min on
2 cores); default: the thesis' settings, one seed; ``--full``: the thesis' settings over
seeds 0, 1, 2 (``OUT/seed_<k>/``) with mean ± std across seeds in ``OUT/report.json``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from hilstack.configs.schema import BusConfig
from hilstack.learning.baoding import BaodingConfig, BaodingRun
from hilstack.tools.demo import free_endpoint

FULL_SEEDS = (0, 1, 2)
#: the full run's rig. The teleport rig: on the reset-arm rig (hand_sim_arm) a ball that comes to
#: rest on the hand's edge is neither in the palm nor at the pick-up spot, and the arm's
#: procedure cannot recover it (docs/baoding.md), so a 9-h run would stop at the first such drop
FULL_RIG = "hand_sim"


def make_config(preset: str, seed: int, **overrides: Any) -> BaodingConfig:
    if preset == "quick":
        return BaodingConfig.quick(seed=seed, **overrides)
    if preset == "tiny":
        return BaodingConfig.tiny(seed=seed, **overrides)
    if preset == "thesis":
        return BaodingConfig(seed=seed, **overrides)
    raise ValueError(f"unknown preset {preset!r}: quick | thesis | tiny")


def run_baoding_demo(out: Path, preset: str = "quick", seed: int = 0, bus: BusConfig | None = None,
                     **overrides: Any) -> dict[str, Any]:
    """One run of PDDM on Baoding; writes the report to ``out`` and returns it."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = make_config(preset, seed, **overrides)
    # a private rendezvous port: a demo never talks to another rig by accident; the rig's bus
    # settings otherwise (an emulated hand's access control, its credentials made when missing)
    if bus is None:
        from hilstack.configs.schema import load_rig
        from hilstack.tools.common import provision_credentials, with_endpoint

        rig_cfg = load_rig(cfg.rig)
        bus = with_endpoint(rig_cfg.bus, free_endpoint())
        provision_credentials(rig_cfg.name, bus, rig_cfg)
    report = BaodingRun(cfg, out, bus).run()
    report["command"] = f"hil demo baoding{' --quick' if preset == 'quick' else ''} --seed {seed} --out {out}"
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


def run_full(out: Path, seeds: tuple[int, ...] = FULL_SEEDS, preset: str = "thesis", rig: str = FULL_RIG,
             **overrides: Any) -> dict[str, Any]:
    """The thesis' settings over ``seeds``: per-seed reports in ``out/seed_<k>`` and the
    final iteration's metrics as mean ± std across seeds, on :data:`FULL_RIG` by default."""
    out = Path(out)
    runs = [run_baoding_demo(out / f"seed_{s}", preset=preset, seed=s, rig=rig, **overrides) for s in seeds]

    def across(key: str, pick) -> dict[str, float]:
        v = np.array([pick(r) for r in runs], dtype=np.float64)
        return {"mean": float(v.mean()), "std": float(v.std()), "per_seed": v.tolist()}

    summary = {
        "seeds": list(seeds),
        "final_mean_return": across("r", lambda r: r["iterations"][-1]["mean_return"]),
        "final_drop_rate": across("d", lambda r: r["iterations"][-1]["drop_rate"]),
        "final_success_90": across("s90", lambda r: r["iterations"][-1]["success_90"]),
        "final_success_180": across("s180", lambda r: r["iterations"][-1]["success_180"]),
        "random_mean_return": across("rr", lambda r: r["random_policy"]["mean_return"]),
        "runs": [str(out / f"seed_{s}" / "report.json") for s in seeds],
    }
    (out / "report.json").write_text(json.dumps(summary, indent=1))
    return summary


def write_plot(r: dict[str, Any], out: Path) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = r["iterations"]
    x = [it["points"] for it in its]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    ax.errorbar(x, [it["return"]["mean"] for it in its], yerr=[it["return"]["std"] for it in its], fmt="o-",
                capsize=3, label="PDDM (mean ± std over rollouts)")
    rp = r["random_policy"]["return"]
    ax.axhline(rp["mean"], color="C1", ls="--", label=f"random policy ({rp['mean']:.0f} ± {rp['std']:.0f})")
    ax.set_xlabel("training points (transitions)")
    ax.set_ylabel("episode return (−5·Σ‖ball − target‖ − 500·drop)")
    ax.set_title(f"Baoding, {r['config']['preset']} preset, seed {r['config']['seed']}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "returns.png", dpi=80)
    plt.close(fig)
    return "returns.png"


def report_markdown(r: dict[str, Any]) -> str:
    c, p, rs = r["config"], r["planner"], r["resets"]

    def row(label: str, m: dict[str, Any], extra: str = "") -> str:
        return (f"| {label} | {m['episodes']} | {m['return']['mean']:.1f} ± {m['return']['std']:.1f} | "
                f"{m['drops']} ({100 * m['drop_rate']:.0f} %) | {m['mean_rotation_deg']:.0f} | "
                f"{100 * m['success_90']:.0f} % | {100 * m['success_180']:.0f} % | {extra} |")

    lines = [
        "# hilstack demo: PDDM on the Shadow Hand's Baoding balls",
        "",
        f"Rig `{r['rig']}`, {c['preset']} preset, seed {c['seed']}, {r['wall_s']:.0f} s wall clock, created "
        f"{r.get('created', '')}. Reproduce: `{r.get('command', '')}`.",
        *[f"Note: {n}." for n in c.get("notes", [])],
        "",
        f"Planner: PDDM H={p['horizon']} K={p['samples']} γ={p['gamma']:g} β={p['beta']:g}, ensemble of "
        f"{p['ensemble']} × MLP {list(p['hidden'])}, first mean `{p['init_mean']}`; plan time p50 "
        f"{p['plan_ms_p50'] or 0:.0f} ms, p99 {p['plan_ms_p99'] or 0:.0f} ms over {p['plans']} plans.",
        f"Resets (reset supervisor): {rs['requested']} requested, {rs['completed']} completed, {rs['failed']} failed, "
        f"mean {rs['mean_duration_s']:.2f} s.",
        "",
        "Return per episode: Σ_t −5·Σ_i‖ball_i − target_i‖ − 500·1(drop); an episode ends at 10 s or on a drop. "
        "Success at 90°/180°: the pair turned that far along the targets' rotation before any drop. "
        "Drops foreseen: validation windows (H steps, logged actions) with a true drop whose model "
        "prediction drops too. An episode that drops later scores lower than one that drops at once "
        "(docs/baoding.md): read drops beside the return.",
        "",
        "| policy | episodes | return (mean ± std) | drops | mean rotation (°) | 90° | 180° | model val 1-step / H-step; drops foreseen |",
        "|---|---|---|---|---|---|---|---|",
        row("random (uniform actions)", r["random_policy"]),
        row("hold (keep the start pose)", r["hold_policy"]),
    ]
    for it in r["iterations"]:
        m = it.get("model", {})
        lines.append(row(f"PDDM iteration {it['iteration']} ({it['points']} points)", it,
                         f"{m.get('val_1step', float('nan')):.3f} / {m.get('val_h', float('nan')):.3f}; "
                         f"{100 * m.get('drop_recall', float('nan')):.0f} % of {m.get('windows_with_drop', 0)}"))
    lines += ["", "## Files", "", *[f"- ![{f}]({f})" for f in r.get("plots", [])],
              *[f"- recording: `{f}`" for f in r["recordings"]]]
    if r.get("rerun"):
        lines.append(f"- rerun: `rerun {r['rerun']}`")
    lines.append(f"- model checkpoint: `{r['model']}`")
    return "\n".join(lines) + "\n"


def cli_baoding(out: Path, quick: bool, full: bool, seed: int) -> None:
    """The `hil demo baoding` verb (registered in tools/cmd_demo.py)."""
    import typer

    from hilstack.learning.mbrl import RigError

    if quick and full:
        raise typer.BadParameter("choose --quick or --full, not both")
    if out == Path("out/demo"):
        out = Path("out/baoding")
    try:
        if full:
            s = run_full(out)
            typer.echo(f"final PDDM return {s['final_mean_return']['mean']:.1f} ± {s['final_mean_return']['std']:.1f} "
                       f"over seeds {s['seeds']}; random {s['random_mean_return']['mean']:.1f}")
            typer.echo(f"report: {out / 'report.json'}")
            return
        r = run_baoding_demo(out, preset="quick" if quick else "thesis", seed=seed)
    except (RigError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    rp, last = r["random_policy"], r["iterations"][-1]
    typer.echo(f"random policy: return {rp['return']['mean']:.1f} ± {rp['return']['std']:.1f}, drops {rp['drops']}/"
               f"{rp['episodes']}")
    typer.echo(f"PDDM (iteration {last['iteration']}): return {last['return']['mean']:.1f} ± {last['return']['std']:.1f}, "
               f"drops {last['drops']}/{last['episodes']}, 90° {100 * last['success_90']:.0f} %, "
               f"180° {100 * last['success_180']:.0f} %")
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
    from hilstack.control.planners import BAODING_PDDM, PddmConfig
    from hilstack.control.policies import MpcPolicy
    from hilstack.drivers.shadow_hand.config import ShadowHandParams, hold_pose_action
    from hilstack.learning.baoding import load_baoding_task, summarize
    from hilstack.learning.dynamics import EnsembleDynamics
    from hilstack.learning.mbrl import split_episodes
    from hilstack.learning.recordings import episodes_from_mcap
    from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim

    run_dir = Path(run_dir)
    eps = [e for f in sorted((run_dir / "recordings").glob("*.mcap")) if "eval" not in f.name
           for e in episodes_from_mcap(f, "hand")]
    train, val = split_episodes(eps, 0.1, np.random.default_rng([seed, 1]), {})
    names = list(eps[0].meta["state_names"])
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
                pc = PddmConfig(horizon=7, samples=samples, gamma=20.0, beta=b, ensemble=3, hidden=(w, w),
                                state_dim=len(names), action_dim=20)
                pol = MpcPolicy(m, pc.planner(seed=1000 + e, init_mean=hold_pose_action()), BaodingCost(task, names, 0.1))
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
                scores.append(baoding_episode_metrics(task, np.array(states)[:, -6:].reshape(-1, 2, 3), times))
            out_d["closed_loop"][f"2x{w} beta {b:g}"] = summarize(scores)
    path = Path(out) if out else run_dir / "compare.json"
    path.write_text(json.dumps(out_d, indent=1))
    return out_d


if __name__ == "__main__":  # python -m hilstack.tools.demo_baoding compare RUN_DIR
    import sys

    if len(sys.argv) != 3 or sys.argv[1] != "compare":
        raise SystemExit("usage: python -m hilstack.tools.demo_baoding compare RUN_DIR")
    print(json.dumps(compare_choices(Path(sys.argv[2])), indent=1))
