"""`hil demo transfer`: SIDM on VelociRoACH expert/novice pairs, GAT vs GARAT on InvertedPendulum
and on the VelociRoACH (source sim → target sim with a missing leg).

Writes ``report.json`` (keys of issue 13) and PNG plots into the output directory.
``part`` (``--part all|sidm|garat``) runs only one half; the other's keys are then absent.
Presets: ``full`` (the issue's sweep), ``quick`` (a reduced sweep meant for ≤ 20 min on two
idle cores) and ``tiny`` (seconds; the CLI test). docs/transfer.md lists what each ran and
how long it took.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

from hilstack.configs.presets import Presets
from hilstack.learning.transfer.grounding import GaratConfig
from hilstack.learning.transfer.pendulum import PendulumConfig
from hilstack.learning.transfer.roach_garat import RoachGaratConfig
from hilstack.learning.transfer.roach_pairs import SidmExperiment
from hilstack.learning.transfer.sidm import SidmConfig, multiplier_text

#: the pendulum settings (GAT's and GARAT's chosen on seed 0, docs/transfer.md); `full` and `quick`
#: run them on fresh seeds only
_PENDULUM = PendulumConfig(agent_timesteps=20000, target_sizes=(500, 3000), source_transitions=5000,
                           validation_transitions=500, gat_fit_steps=4000, gat_val_frac=0.2,
                           # GARAT chosen on seed 0 from tune_pendulum.GARAT_GRID (error at 3000): initial
                           # log σ −2.5 and the π_g kept by its error on a held-out 20 % of the target data
                           garat=GaratConfig(total_timesteps=49152, log_std_init=-2.5, select_frac=0.2))
#: the roach's GAT as tuned on the pendulum; GARAT 48 discriminator updates as on the pendulum (of 256 steps)
_ROACH = RoachGaratConfig(cem_population=8, cem_iterations=6, gat_fit_steps=4000, gat_val_frac=0.2,
                          garat=GaratConfig(total_timesteps=12288, n_steps=256, log_std_init=-2.0))

_PRESETS: dict[str, dict[str, Any]] = {
    "full": {
        # sized for about 45 min on one loaded core (docs/transfer.md "What ran")
        "sidm_exp": SidmExperiment(expert_minutes=20.0, novice_minutes=(1.0, 2.0, 4.0, 8.0, 16.0, 32.0),
                                   validation_minutes=5.0, trials=4, ablation_minutes=(1.0,)),
        "sidm": SidmConfig(latent_dim=128, width=128, enc_layers=0, warm_rounds=10, max_rounds=30,
                           patience_rounds=5),
        "pendulum": _PENDULUM,
        "roach": _ROACH,
        "garat_seeds": (1, 2, 3, 4, 5),  # fresh seeds: seed 0 chose the GAT and GARAT settings
        "roach_seeds": (1, 2, 3, 4, 5),  # as many as the paper's Fig. 3 (the roach part has no tuning seed)
    },
    "quick": {
        # novice 8 min dropped to fit 20 min with both halves (the multiplier was 1.0+ there, docs)
        "sidm_exp": SidmExperiment(expert_minutes=10.0, novice_minutes=(1.0, 2.0, 4.0), validation_minutes=2.0,
                                   trials=3, ablation_minutes=(1.0,)),
        "sidm": SidmConfig(latent_dim=128, width=128, enc_layers=0, warm_rounds=10, max_rounds=30,
                           patience_rounds=5),
        "pendulum": replace(_PENDULUM, target_sizes=(3000,)),  # the done-when size only; `full` has both
        "roach": replace(_ROACH, cem_episodes=1, target_transitions=1000, source_transitions=2000,
                         garat=GaratConfig(total_timesteps=4096, n_steps=256, log_std_init=-2.0)),
        "garat_seeds": (1,),  # a fresh seed (seed 0 chose the settings), whatever --seed says
    },
    "tiny": {
        "sidm_exp": SidmExperiment(expert_minutes=0.1, novice_minutes=(0.05, 0.1), validation_minutes=0.05,
                                   trials=1, episode_s=3.0, drift_steps=5, ablation_minutes=(0.05,)),
        "sidm": SidmConfig(latent_dim=8, width=16, enc_layers=0, pred_iters=10, match_iters=2, warm_rounds=1,
                           max_rounds=2, patience_rounds=2),
        "pendulum": PendulumConfig(agent_timesteps=256, agent_n_steps=256, target_sizes=(200,), source_transitions=200,
                                   validation_transitions=50, gat_fit_steps=50, trace_steps=20,
                                   garat=GaratConfig(total_timesteps=256, n_steps=128, batch_size=64, n_epochs=1,
                                                     disc_steps=2)),
        "roach": RoachGaratConfig(episode_steps=5, cem_population=4, cem_iterations=1, cem_elites=2, cem_episodes=1,
                                  eval_episodes=1,
                                  target_transitions=40, source_transitions=40, gat_fit_steps=50,
                                  garat=GaratConfig(total_timesteps=128, n_steps=64, batch_size=32, n_epochs=1,
                                                    disc_steps=2, log_std_init=-2.0)),
        "garat_seeds": None,
    },
}

#: the SIDM paper's setting (`--part sidm --setting wheeled`, learning/transfer/wheeled_pairs.py): the
#: expert's data and the novice sizes scaled from the paper's ~14 h and 1 min-2 h to two shared cores
#: (docs/transfer.md "SIDM on the wheeled robots"); SIDM as the paper defines it (no warm start), our
#: warm-started SIDM and fine-tuning from the expert's model, beside the novice-only baseline
_WHEELED_MODEL = SidmConfig(latent_dim=128, width=128, enc_layers=0, warm_rounds=10, max_rounds=30,
                            patience_rounds=5)
_PRESETS["full"].update(
    wheeled_exp=SidmExperiment(expert_minutes=10.0, novice_minutes=(0.5, 1.5, 4.5), validation_minutes=1.0,
                               trials=2, paper_sidm=True, finetune=True, drift_steps=0),
    wheeled=_WHEELED_MODEL)
_PRESETS["quick"].update(
    wheeled_exp=SidmExperiment(expert_minutes=5.0, novice_minutes=(0.5, 1.5), validation_minutes=1.0,
                               trials=1, paper_sidm=True, finetune=True, drift_steps=0),
    wheeled=_WHEELED_MODEL)
_PRESETS["tiny"].update(
    wheeled_exp=SidmExperiment(expert_minutes=0.1, novice_minutes=(0.05, 0.1), validation_minutes=0.05, trials=1,
                               episode_s=3.0, paper_sidm=True, finetune=True, drift_steps=0),
    wheeled=SidmConfig(latent_dim=8, width=16, enc_layers=0, pred_iters=10, match_iters=2, warm_rounds=1,
                       max_rounds=2, patience_rounds=2))


@dataclass(frozen=True)
class TransferDemoConfig(Presets):
    """What one transfer demo runs: ``TransferDemoConfig.from_preset("full" | "quick" | "tiny")``.
    ``garat_seeds``/``roach_seeds`` None: the run's ``--seed`` (roach: the GARAT seeds)."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = _PRESETS

    sidm_exp: SidmExperiment
    sidm: SidmConfig
    pendulum: PendulumConfig
    roach: RoachGaratConfig
    garat_seeds: tuple[int, ...] | None = None
    roach_seeds: tuple[int, ...] | None = None
    #: SIDM on the paper's wheeled robots (`setting="wheeled"`): the sweep and the model
    wheeled_exp: SidmExperiment | None = None
    wheeled: SidmConfig | None = None


PARTS = ("all", "sidm", "garat")
SETTINGS = ("roach", "wheeled")


def _sidm_plot(report: dict, out: Path, plt) -> str:
    pairs = report["sidm"]["pairs"]
    fig, axes = plt.subplots(1, len(pairs), figsize=(5 * len(pairs), 4), squeeze=False)
    for ax, (pair, r) in zip(axes[0], pairs.items(), strict=True):
        m = [row["minutes"] for row in r["curve"]]
        labels = {"with_sidm": "SIDM (warm start)", "without_sidm": "novice only",
                  "sidm_paper": "SIDM as in the paper", "finetune": "fine-tuned expert model"}
        for key in report["sidm"].get("variants", ("with_sidm", "without_sidm")):
            label = labels[key]
            ax.plot(m, [row[key] for row in r["curve"]], "o-", label=label)
            ax.fill_between(m, [row[key + "_iqr"][0] for row in r["curve"]],
                            [row[key + "_iqr"][1] for row in r["curve"]], alpha=0.25)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("novice data [min of robot time]")
        ax.set_ylabel("validation MSE (normalised Δs)")
        med = r["data_multiplier"]["median_interpolated"]
        ax.set_title(f"SIDM, {pair} pair\n(warm SIDM: median interpolated multiplier "
                     f"{'n/a' if med is None else f'{med:.2g}x'}, {r['data_multiplier']['beyond_grid']} beyond the grid)",
                     fontsize=8)
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "sidm_validation.png", dpi=100)
    plt.close(fig)
    return "sidm_validation.png"


def _garat_plots(report: dict, out: Path, plt) -> list[str]:
    p = report["garat"]["pendulum"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    n = [row["target_transitions"] for row in p["curve"]]
    for key in ("none", "gat", "garat", "floor"):
        a1.errorbar(n, [row[key] for row in p["curve"]], yerr=[row[key + "_std"] for row in p["curve"]],
                    fmt="o-", capsize=3, label=key)
    a1.set_xscale("log")
    a1.set_xlabel("target transitions")
    a1.set_ylabel("per-step transition error (L2, state units)")
    a1.set_title(f"InvertedPendulum, pole {p['target_pole_mass_kg']:g} kg, seeds {p['seeds']} (mean ± std)")
    a1.legend()
    for key, tr in p["angle_traces_rad"].items():
        a2.plot(range(len(tr)), tr, label=key)
    a2.set_xlabel("step (0.04 s)")
    a2.set_ylabel("pole angle [rad]")
    a2.set_title(f"one policy, same start state (seed {p['seeds'][0]})")
    a2.legend()
    fig.tight_layout()
    fig.savefig(out / "garat_pendulum.png", dpi=100)
    plt.close(fig)

    r = report["garat"]["roach"]
    keys = ("source", "gat", "garat")
    fig, ax = plt.subplots(figsize=(5, 4))
    mean = [r["normalised_return"][k] if r["normalised_return"][k] is not None else float("nan") for k in keys]
    std = [r["normalised_return_std"][k] if r["normalised_return_std"][k] is not None else 0.0 for k in keys]
    ax.bar(keys, mean, yerr=std, capsize=4)
    for i, k in enumerate(keys):
        ax.plot([i] * len(r["per_seed"]), [row["normalised_return"][k] if row["normalised_return"][k] is not None
                                           else float("nan") for row in r["per_seed"]], "k.")
    ax.axhline(1.0, color="g", ls="--", lw=1, label="target-trained = 1")
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_ylabel("normalised target return")
    ax.set_title(f"VelociRoACH, target: {r['target']}, seeds {r['seeds']}", fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "garat_roach.png", dpi=100)
    plt.close(fig)
    return ["garat_pendulum.png", "garat_roach.png"]


def _plots(report: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    if "sidm" in report:
        files.append(_sidm_plot(report, out, plt))
    if "garat" in report:
        files += _garat_plots(report, out, plt)
    return files


def _pendulum_task(cfg: PendulumConfig) -> dict:
    from hilstack.learning.transfer.pendulum import run as run_pendulum

    return run_pendulum(cfg, print)


def _roach_task(cfg: RoachGaratConfig) -> dict:
    from hilstack.learning.transfer.roach_garat import run_seed

    return run_seed(cfg, print)


def _over_seeds(name: str, fn, cfgs: list, log, ray: dict | None, out: Path | None) -> list:
    """``fn(cfg)`` for each seed's config: in this process (``ray`` None, as before), or each a sweep
    task (tools/sweep.py; ``ray``: ``{"ray": "local" | ADDRESS, "workers": N}``) with its result in
    ``out/tasks/<name>-seed<N>.json`` as it finishes and a re-run doing only the seeds missing."""
    if ray is None:
        return [fn(c, log) for c in cfgs]
    from hilstack.tools.sweep import Task, executor_from, run_sweep

    worker = {"pendulum": _pendulum_task, "roach": _roach_task}[name]
    tasks = [Task(f"{name}-seed{c.seed}", worker, {"cfg": c}) for c in cfgs]
    sw = run_sweep(tasks, out, executor=executor_from(ray["ray"]), workers=ray.get("workers", 1), log=log)
    if sw["failed"]:
        raise RuntimeError(f"{name} seeds {sorted(sw['failed'])} failed (their log tails above); the same command "
                           "again re-runs only those")
    return [sw["results"][t.key] for t in tasks]


def _pendulum_over_seeds(cfg: PendulumConfig, seeds: tuple[int, ...], log, ray: dict | None = None,
                         out: Path | None = None) -> dict:
    """The Fig. 1 experiment per seed; the curve carries mean and std over seeds, and
    ``grounding_error`` the mean at the largest target data size."""
    import numpy as np

    from hilstack.learning.transfer.pendulum import run as run_pendulum

    runs = _over_seeds("pendulum", run_pendulum, [replace(cfg, seed=s) for s in seeds], log, ray, out)
    curve = []
    for i, row in enumerate(runs[0]["curve"]):
        agg = {"target_transitions": row["target_transitions"]}
        for k in ("none", "gat", "garat", "floor"):
            v = np.array([r["curve"][i][k] for r in runs])
            agg[k], agg[k + "_std"] = float(v.mean()), float(v.std())
        agg["ordering_holds_on_seeds"] = int(sum(r["curve"][i]["garat"] < r["curve"][i]["gat"] < r["curve"][i]["none"]
                                                 for r in runs))
        agg["garat_below_gat_on_seeds"] = int(sum(r["curve"][i]["garat"] < r["curve"][i]["gat"] for r in runs))
        curve.append(agg)
    last = curve[-1]
    return {"grounding_error": {k: last[k] for k in ("none", "gat", "garat", "floor")},
            "grounding_error_std": {k: last[k + "_std"] for k in ("none", "gat", "garat", "floor")},
            "seeds": list(seeds), "curve": curve, "per_seed": [r["curve"] for r in runs],
            "angle_traces_rad": runs[0]["angle_traces_rad"], "target_pole_mass_kg": runs[0]["target_pole_mass_kg"]}


def _roach_over_seeds(cfg: RoachGaratConfig, seeds: tuple[int, ...], log, ray: dict | None = None,
                      out_dir: Path | None = None) -> dict:
    from hilstack.learning.transfer.roach_garat import run_seed, summarise, target_description

    out = summarise(_over_seeds("roach", run_seed, [replace(cfg, seed=s) for s in seeds], log, ray, out_dir))
    out["missing_leg"] = cfg.missing_leg
    out["leg_speed_scale"] = None if cfg.leg_speed_scale is None else list(cfg.leg_speed_scale)
    out["target"] = target_description(cfg)
    return out


def run_transfer_demo(out: Path, preset: str = "quick", seed: int = 0, log=print, part: str = "all",
                      setting: str = "roach", pairs: tuple[str, ...] | None = None, ray: dict | None = None) -> dict:
    """Run the preset (``part``: all, sidm or garat), write report.json and the plots into ``out``.
    ``ray`` (``{"ray": "local" | ADDRESS, "workers": N}``): GARAT's seeds as Ray tasks (docs/scaling.md).
    ``setting`` "wheeled" (with ``part`` "sidm" only): SIDM on the paper's wheeled robots.
    ``pairs``: only these SIDM pairs (e.g. one per process, to use both cores)."""
    import torch

    from hilstack.learning.transfer.roach_pairs import run_sidm

    p = TransferDemoConfig.from_preset(preset)  # one-line error naming the presets
    if part not in PARTS:
        raise ValueError(f"unknown part {part!r}: choose one of {', '.join(PARTS)}")
    if setting not in SETTINGS or (setting != "roach" and part != "sidm"):
        raise ValueError(f"unknown setting {setting!r} for part {part!r}: 'wheeled' is for part 'sidm' only")
    torch.set_num_threads(1)  # two shared cores: one thread each is faster under load (PLATFORM_NOTES)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sidm_exp, sidm_cfg = (p.sidm_exp, p.sidm) if setting == "roach" else (p.wheeled_exp, p.wheeled)
    sidm_exp, pend = replace(sidm_exp, seed=seed), replace(p.pendulum, seed=seed)
    if pairs is not None:
        unknown = set(pairs) - {k for k, _ in sidm_exp.p_e}
        if unknown:
            raise ValueError(f"unknown SIDM pair(s) {sorted(unknown)}: choose from {[k for k, _ in sidm_exp.p_e]}")
        sidm_exp = replace(sidm_exp, p_e=tuple((k, v) for k, v in sidm_exp.p_e if k in pairs))
    garat_seeds = tuple(p.garat_seeds or (seed,))
    report: dict = {"preset": preset, "seed": seed, "part": part, "setting": setting, "settings": {}, "timing_s": {},
                    "checks": {}}
    t0 = time.monotonic()
    if part in ("all", "sidm"):
        t = time.monotonic()
        if setting == "wheeled":
            from hilstack.learning.transfer import wheeled_pairs

            sidm = run_sidm(sidm_exp, sidm_cfg, log, setting=wheeled_pairs)
        else:
            sidm = run_sidm(sidm_exp, sidm_cfg, log)
        report["sidm"] = sidm
        report["settings"].update(sidm_experiment=asdict(sidm_exp), sidm_model=asdict(sidm_cfg))
        report["timing_s"]["sidm"] = time.monotonic() - t
        # SIDM needs less novice data than the baseline at some size (interpolated or beyond the grid)
        report["checks"]["sidm_multiplier_above_1_on_a_pair"] = any(
            e["where"] == "beyond" or (e["multiplier"] is not None and e["multiplier"] > 1)
            for v in sidm["pairs"].values() for e in v["data_multiplier_per_size"])
    if part in ("all", "garat"):
        t = time.monotonic()
        pendulum = _pendulum_over_seeds(pend, garat_seeds, log, ray, out)
        t1 = time.monotonic()
        roach_seeds = tuple(p.roach_seeds or garat_seeds)
        roach = _roach_over_seeds(p.roach, roach_seeds, log, ray, out)
        report["garat"] = {"pendulum": pendulum, "roach": roach}
        report["settings"].update(pendulum=asdict(pend), roach=asdict(p.roach), garat_seeds=list(garat_seeds),
                                  roach_seeds=list(roach_seeds))
        report["timing_s"].update(garat_pendulum=t1 - t, garat_roach=time.monotonic() - t1)
        ge = pendulum["grounding_error"]
        report["checks"]["garat_below_gat_below_none"] = bool(ge["garat"] < ge["gat"] < ge["none"])
    report["timing_s"]["total"] = time.monotonic() - t0
    report["plots"] = _plots(report, out)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def cli_transfer(out: Path, quick: bool, full: bool, seed: int, part: str = "all", setting: str = "roach",
                 ray: str | None = None, workers: int = 1) -> None:
    """The `hil demo transfer` verb (registered in tools/cmd_demo.py)."""
    import os

    import typer


    preset = os.environ.get("HIL_TRANSFER_PRESET") or ("quick" if quick else "full")
    if out == Path("out/demo"):
        out = Path("out/transfer")
    r = run_transfer_demo(out, preset=preset, seed=seed, log=typer.echo, part=part, setting=setting,
                          ray=None if ray is None else {"ray": ray, "workers": workers})
    for pair, v in r.get("sidm", {}).get("pairs", {}).items():
        for k in r["sidm"]["variants"]:
            if k == "without_sidm":
                continue
            tag = "" if k == "with_sidm" else f"_{k}"
            per = ", ".join(f"{e['minutes']:g} min {multiplier_text(e)}" for e in v["data_multiplier_per_size" + tag])
            typer.echo(f"sidm {pair} {k}: data multiplier per size: {per}")
    if "garat" in r:
        pend, roach = r["garat"]["pendulum"], r["garat"]["roach"]
        ge, sd = pend["grounding_error"], pend["grounding_error_std"]
        typer.echo(f"pendulum grounding error (seeds {pend['seeds']}, mean ± std): "
                   + "  ".join(f"{k} {ge[k]:.4f} ± {sd[k]:.4f}" for k in ("none", "gat", "garat", "floor")))
        for row in pend["curve"]:
            typer.echo(f"pendulum {row['target_transitions']} target transitions: "
                       + "  ".join(f"{k} {row[k]:.4f} ± {row[k + '_std']:.4f}"
                                   for k in ("none", "gat", "garat", "floor"))
                       + f"  (garat < gat on {row['garat_below_gat_on_seeds']} of {len(pend['seeds'])} seeds)")
        nr, ns = roach["normalised_return"], roach["normalised_return_std"]
        typer.echo(f"roach normalised target return (seeds with a gap {roach['seeds_with_gap']} of {roach['seeds']}): "
                   + "  ".join(f"{k} {'n/a' if nr[k] is None else f'{nr[k]:.2f} ± {ns[k]:.2f}'}"
                               for k in ("source", "gat", "garat")))
    for k, ok in r["checks"].items():
        typer.echo(f"{'PASS' if ok else 'FAIL'} {k}")
    typer.echo(f"time {r['timing_s']['total']:.0f} s; report: {out / 'report.json'}")
