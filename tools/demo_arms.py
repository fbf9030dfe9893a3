"""`hil demo arms`: reach with a learned model + MPC vs tuned IK and random, on both arms.

Writes ``OUT/<arm>/report.json`` (and ``report.md``) per arm and ``OUT/report.md`` over
both; docs/arms.md explains the task and the numbers.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from hilstack.bus.ports import free_endpoint
from hilstack.configs.schema import BusConfig

ARM_ORDER = ("widowx", "sawyer")


def reproduce_command(out: Path, quick: bool, full: bool, seed: int) -> str:
    flags = " --quick" if quick else " --full" if full else ""
    return f"hil demo arms{flags} --seed {seed} --out {out}"


def _ms(c: dict[str, float], scale: float = 100.0) -> str:
    return f"{scale * c['mean']:.1f} ± {scale * c['std']:.1f}"


def arm_markdown(r: dict[str, Any]) -> str:
    cfg = r["config"]
    scaled = r["task"]["random_scaled"] if cfg["random_scaled"] is None else cfg["random_scaled"]
    lines = [f"# Reach on the {r['arm']} (rig `{r['rig']}`)", "",
             f"Reproduce: `{r['command']}`. {r['wall_s']:.0f} s wall clock, {r['created']}.", "",
             f"Policy at {r['policy_hz']:.2f} Hz, {cfg['episode_steps']}-step episodes; success = end effector within "
             f"{100 * r['success_m']:.0f} cm of the goal at the end. Reward −(d² + log(d + 1e-5)) (MELD, thesis ch. 7).",
             f"MPC: CEM N={cfg['samples']} H={cfg['horizon']} on a {cfg['ensemble']}× MLP {cfg['hidden']} trained on "
             f"{cfg['random_episodes']} random episodes per seed ({'scaled' if scaled else 'uniform'} actions); "
             f"seeds {cfg['seeds']}.", "",
             "| controller | success | final distance (cm, mean ± std) | episodes |", "|---|---|---|---|"]
    labels = {"mpc": "learned model + CEM MPC", "ik": "damped least-squares IK (tuned)", "random": "random"}
    for c, s in r["summary"].items():
        lines.append(f"| {labels[c]} | {100 * s['success_rate']:.0f} % | {_ms(s['final_distance_m'])} | {s['episodes']} |")
    for run in r["seeds"]:
        t = run["ik_tuning"]
        lines += ["", f"Seed {run['seed']}: {run['random_transitions']} random transitions; IK search: "
                  f"{len(t['candidates'])} gain sets × goals = {t['episodes']} episodes (default "
                  f"{t['default']['params']}: {t['default']['successes']} successes, mean {100 * t['default']['mean_final_m']:.1f} cm; "
                  f"best {json.dumps({k: round(v, 4) for k, v in t['best_params'].items()})}: {t['best']['successes']} "
                  f"successes, mean {100 * t['best']['mean_final_m']:.1f} cm)."]
    return "\n".join(lines) + "\n"


def run_arms(out: Path, quick: bool = False, full: bool = False, seed: int = 0,
             arms: tuple[str, ...] = ARM_ORDER, bus: BusConfig | None = None, **overrides: Any) -> dict[str, Any]:
    from hilstack.learning.reach import ReachConfig, run_arm

    out = Path(out)
    cmd = reproduce_command(out, quick, full, seed)
    reports = {}
    for arm in arms:
        kw = {"arm": arm, **overrides}
        kw.setdefault("seeds", (seed, seed + 1, seed + 2) if full else (seed,))
        cfg = ReachConfig.from_preset("quick", **kw) if quick else ReachConfig.from_preset("full", **kw) if full else ReachConfig(**kw)
        t0 = time.monotonic()
        r = run_arm(cfg, out / arm, bus or BusConfig(endpoint=free_endpoint()))
        r.update(command=cmd, wall_s=time.monotonic() - t0, created=time.strftime("%Y-%m-%d %H:%M:%S"),
                 quick=quick, full=full)
        (out / arm).mkdir(parents=True, exist_ok=True)
        (out / arm / "report.json").write_text(json.dumps(r, indent=1))
        (out / arm / "report.md").write_text(arm_markdown(r))
        reports[arm] = r
    (out / "report.md").write_text("\n".join(arm_markdown(reports[a]) for a in arms))
    return reports


def cli_arms(out: Path, quick: bool = False, full: bool = False, seed: int = 0) -> None:
    """`hil demo arms` (tools/cmd_demo.py's OTHER_DEMOS)."""
    import typer

    from hilstack.learning.mbrl import RigError

    try:
        reports = run_arms(out, quick=quick, full=full, seed=seed)
    except (RigError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    for arm, r in reports.items():
        s = r["summary"]
        typer.echo(f"{arm}: success mpc {100 * s['mpc']['success_rate']:.0f} % ik {100 * s['ik']['success_rate']:.0f} % "
                   f"random {100 * s['random']['success_rate']:.0f} %; final distance cm mpc "
                   f"{_ms(s['mpc']['final_distance_m'])} ik {_ms(s['ik']['final_distance_m'])} random "
                   f"{_ms(s['random']['final_distance_m'])}")
    typer.echo(f"report: {out / 'report.md'}")
