"""`hil demo transfer`: SIDM on VelociRoACH expert/novice pairs, GAT vs GARAT on InvertedPendulum.

Writes ``report.json`` (keys of issue 13) and PNG plots into the output directory.
Presets: ``full`` (the issue's sweep), ``quick`` (a reduced sweep meant for ≤ 20 min on two
idle cores) and ``tiny`` (seconds; the CLI test). docs/transfer.md lists what each ran and
how long it took.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path

from learning.transfer.grounding import GaratConfig
from learning.transfer.pendulum import PendulumConfig
from learning.transfer.roach_pairs import SidmExperiment
from learning.transfer.sidm import SidmConfig

PRESETS: dict[str, dict] = {
    "full": {
        # sized for about 45 min on one loaded core (docs/transfer.md "What ran")
        "sidm_exp": SidmExperiment(expert_minutes=20.0, novice_minutes=(1.0, 2.0, 4.0, 8.0, 16.0, 32.0),
                                   validation_minutes=5.0, trials=4, ablation_minutes=(1.0,)),
        "sidm": SidmConfig(latent_dim=128, width=128, enc_layers=0, warm_rounds=10, max_rounds=30,
                           patience_rounds=5),
        "pendulum": PendulumConfig(),
    },
    "quick": {
        "sidm_exp": SidmExperiment(expert_minutes=10.0, novice_minutes=(1.0, 2.0, 4.0, 8.0), validation_minutes=2.0,
                                   trials=3, ablation_minutes=(1.0,)),
        "sidm": SidmConfig(latent_dim=128, width=128, enc_layers=0, warm_rounds=10, max_rounds=30,
                           patience_rounds=5),
        "pendulum": PendulumConfig(agent_timesteps=20000, target_sizes=(500, 3000), source_transitions=5000,
                                   validation_transitions=500, gat_fit_steps=1500,
                                   garat=GaratConfig(total_timesteps=49152)),
    },
    "tiny": {
        "sidm_exp": SidmExperiment(expert_minutes=0.1, novice_minutes=(0.05, 0.1), validation_minutes=0.05,
                                   trials=1, episode_s=3.0, drift_steps=5, ablation_minutes=(0.05,)),
        "sidm": SidmConfig(latent_dim=8, width=16, enc_layers=0, pred_iters=10, match_iters=2, warm_rounds=1,
                           max_rounds=2, patience_rounds=2),
        "pendulum": PendulumConfig(agent_timesteps=256, target_sizes=(200,), source_transitions=200,
                                   validation_transitions=50, gat_fit_steps=50, trace_steps=20,
                                   garat=GaratConfig(total_timesteps=256, n_steps=128, batch_size=64, n_epochs=1,
                                                     disc_steps=2)),
    },
}

ROACH_GARAT_STATUS = ("not run: the VelociRoACH GARAT part (normalised target return for source-only, GAT "
                      "and GARAT) is not built yet (docs/transfer.md)")


def _sidm_plot(report: dict, out: Path, plt) -> str:
    pairs = report["sidm"]["pairs"]
    fig, axes = plt.subplots(1, len(pairs), figsize=(5 * len(pairs), 4), squeeze=False)
    for ax, (pair, r) in zip(axes[0], pairs.items(), strict=True):
        m = [row["minutes"] for row in r["curve"]]
        for key, label in (("with_sidm", "with SIDM"), ("without_sidm", "novice only")):
            ax.plot(m, [row[key] for row in r["curve"]], "o-", label=label)
            ax.fill_between(m, [row[key + "_iqr"][0] for row in r["curve"]],
                            [row[key + "_iqr"][1] for row in r["curve"]], alpha=0.25)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("novice data [min of robot time]")
        ax.set_ylabel("validation MSE (normalised Δs)")
        ax.set_title(f"SIDM, {pair} pair (multiplier {r['data_multiplier'] or float('nan'):.2g}x)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "sidm_validation.png", dpi=100)
    plt.close(fig)
    return "sidm_validation.png"


def _plots(report: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    if report["sidm"] is not None:
        files.append(_sidm_plot(report, out, plt))
    if report["garat"] is None:
        return files
    p = report["garat"]["pendulum"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    n = [row["target_transitions"] for row in p["curve"]]
    for key in ("none", "gat", "garat"):
        a1.plot(n, [row[key] for row in p["curve"]], "o-", label=key)
    a1.set_xscale("log")
    a1.set_xlabel("target transitions")
    a1.set_ylabel("per-step transition error (L2, state units)")
    a1.set_title(f"InvertedPendulum, target pole {p['target_pole_mass_kg']:g} kg")
    a1.legend()
    for key, tr in p["angle_traces_rad"].items():
        a2.plot(range(len(tr)), tr, label=key)
    a2.set_xlabel("step (0.04 s)")
    a2.set_ylabel("pole angle [rad]")
    a2.set_title("one policy, same start state")
    a2.legend()
    fig.tight_layout()
    fig.savefig(out / "garat_pendulum.png", dpi=100)
    plt.close(fig)
    files.append("garat_pendulum.png")
    return files


#: the parts of the demo; ``HIL_TRANSFER_PARTS=sidm`` (or ``garat``) runs only one of them
PARTS = ("sidm", "garat")


def parse_parts(text: str | None) -> tuple[str, ...]:
    """``"sidm,garat"`` → ("sidm", "garat"); None or empty → all parts. Unknown names are an error."""
    if not text:
        return PARTS
    parts = tuple(p.strip() for p in text.split(",") if p.strip())
    bad = [p for p in parts if p not in PARTS]
    if bad or not parts:
        raise ValueError(f"HIL_TRANSFER_PARTS: unknown part(s) {bad or text!r}: choose from {', '.join(PARTS)}")
    return parts


def run_transfer_demo(out: Path, preset: str = "quick", seed: int = 0, log=print,
                      parts: tuple[str, ...] = PARTS) -> dict:
    """Run the preset's ``parts``, write report.json and the plots into ``out``; return the report.
    A part that did not run is ``None`` in the report (with ``skipped``) and has no plot or check."""
    import torch

    from learning.transfer.pendulum import run as run_pendulum
    from learning.transfer.roach_pairs import run_sidm

    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}: choose one of {', '.join(PRESETS)}")
    torch.set_num_threads(1)  # two shared cores: one thread each is faster under load (PLATFORM_NOTES)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    p = PRESETS[preset]
    sidm_exp, pend = replace(p["sidm_exp"], seed=seed), replace(p["pendulum"], seed=seed)
    parts = parse_parts(",".join(parts))
    t0 = time.monotonic()
    sidm = run_sidm(sidm_exp, p["sidm"], log) if "sidm" in parts else None
    t1 = time.monotonic()
    pendulum = run_pendulum(pend, log) if "garat" in parts else None
    t2 = time.monotonic()
    report = {
        "preset": preset,
        "seed": seed,
        "parts": list(parts),
        "skipped": [q for q in PARTS if q not in parts],
        "sidm": sidm,
        "garat": None if pendulum is None else {
            "pendulum": pendulum,
            "roach": {"normalised_return": {"source": None, "gat": None, "garat": None},
                      "status": ROACH_GARAT_STATUS},
        },
        "settings": {"sidm_experiment": asdict(sidm_exp), "sidm_model": asdict(p["sidm"]),
                     "pendulum": asdict(pend)},
        "timing_s": {"sidm": t1 - t0, "garat_pendulum": t2 - t1, "total": t2 - t0},
    }
    report["checks"] = {}
    if sidm is not None:
        mults = {k: v["data_multiplier"] for k, v in sidm["pairs"].items()}
        report["checks"]["sidm_multiplier_above_1_on_a_pair"] = any(m is not None and m > 1 for m in mults.values())
    if pendulum is not None:
        ge = pendulum["grounding_error"]
        report["checks"]["garat_below_gat_below_none"] = bool(ge["garat"] < ge["gat"] < ge["none"])
    report["plots"] = _plots(report, out)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    return report


def cli_transfer(out: Path, quick: bool, full: bool, seed: int) -> None:
    """The `hil demo transfer` verb (registered in tools/cmd_demo.py)."""
    import os

    import typer

    from tools.common import UserError

    preset = os.environ.get("HIL_TRANSFER_PRESET") or ("quick" if quick else "full")
    if out == Path("out/demo"):
        out = Path("out/transfer")
    try:
        parts = parse_parts(os.environ.get("HIL_TRANSFER_PARTS"))
    except ValueError as e:
        raise UserError(str(e)) from None
    r = run_transfer_demo(out, preset=preset, seed=seed, log=typer.echo, parts=parts)
    if r["sidm"] is not None:
        for pair, v in r["sidm"]["pairs"].items():
            m = v["data_multiplier"]
            typer.echo(f"sidm {pair}: data multiplier {'n/a' if m is None else f'{m:.2f}x'}")
    if r["garat"] is not None:
        ge = r["garat"]["pendulum"]["grounding_error"]
        typer.echo(f"pendulum grounding error: none {ge['none']:.4f}  gat {ge['gat']:.4f}  garat {ge['garat']:.4f}")
    if r["skipped"]:
        typer.echo(f"skipped (HIL_TRANSFER_PARTS): {', '.join(r['skipped'])}")
    for k, ok in r["checks"].items():
        typer.echo(f"{'PASS' if ok else 'FAIL'} {k}")
    typer.echo(f"time {r['timing_s']['total']:.0f} s; report: {out / 'report.json'}")
