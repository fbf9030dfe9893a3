"""`hil demo mbrl-gym [--quick] [--envs ...] --out DIR`: MB, MF and Mb-Mf on gymnasium's
swimmer, half-cheetah, hopper and ant (thesis ch. 2, Fig. 2.8; learning/mbmf.py).

Each (environment, method, seed) writes ``OUT/runs/<env>_<method>_s<seed>.json`` when it
finishes and is reused by a later run with the same preset (an interrupted demo continues;
several processes may share one OUT, one per environment). ``report.json``, ``report.md``
and ``rewards.png`` (return against environment steps, log axis) cover every environment
with runs in OUT. Presets: default (3 seeds, the four environments, hours on 2 cores: the
budgets in docs/mbrl.md), ``--quick`` (half-cheetah, 1 seed, ≤ 20 min), ``tiny`` (tests).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from hilstack.learning.mbmf import METHODS, TASKS, MbmfConfig, compare, do_nothing_return, run_seed

QUICK_ENVS = ("half_cheetah",)
#: Mb-Mf's sample-efficiency gain over TRPO from scratch in Nagabandi et al., arXiv:1708.02596v1
#: (abstract; their Fig. of return against steps, TRPO for both, 1000-step episodes); the
#: published version and the thesis (ch. 2, Fig. 2.8) summarise it as 3-5x
THESIS_SPEEDUP = {"swimmer": 330.0, "half_cheetah": 4.0, "hopper": 26.0, "ant": 3.0}
LABELS = {"mb": "MB (random-shooting MPC)", "mf": "MF (TRPO from scratch)", "mbmf": "Mb-Mf (DAgger + TRPO)"}


def config_for(quick: bool, tiny: bool = False) -> MbmfConfig:
    return MbmfConfig.tiny() if tiny else (MbmfConfig.quick() if quick else MbmfConfig())


def parse_envs(envs: str | None, quick: bool) -> tuple[str, ...]:
    if not envs:
        return QUICK_ENVS if quick else tuple(TASKS)
    names = tuple(e.strip() for e in envs.split(",") if e.strip())
    bad = [e for e in names if e not in TASKS]
    if bad or not names:
        raise ValueError(f"unknown --envs {', '.join(bad) or repr(envs)}; known: {', '.join(TASKS)}")
    return names


def load_runs(out: Path, cfg: MbmfConfig) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """env → method → the runs (one per seed) in ``out/runs`` written with ``cfg``."""
    from dataclasses import asdict

    from hilstack.learning.mbmf import _jsonable

    conf = _jsonable(asdict(cfg))
    res: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for p in sorted((out / "runs").glob("*.json")):
        if p.name.endswith(".partial.json"):
            continue
        d = json.loads(p.read_text())
        if d.get("config") != conf:
            continue
        res.setdefault(d["env"], {m: [] for m in METHODS})[d["method"]].append(d)
    return res


def build_report(out: Path, cfg: MbmfConfig, preset: str, baselines: dict[str, Any]) -> dict[str, Any]:
    runs = load_runs(out, cfg)
    envs = {e: {**compare(runs[e]), "do_nothing": baselines.get(e)} for e in TASKS if e in runs}
    return {"preset": preset, "config": _config(cfg), "algorithm": "TRPO (sb3_contrib.TRPO)", "envs": envs}


def _config(cfg: MbmfConfig) -> dict[str, Any]:
    from dataclasses import asdict

    from hilstack.learning.mbmf import _jsonable

    return _jsonable(asdict(cfg))


def _fmt(x: float | None, unit: str = "") -> str:
    return "not reached" if x is None else (f"{x / 1000:.1f}k" if unit == "k" else f"{x:.1f}")


def report_markdown(r: dict[str, Any]) -> str:
    lines = [f"# MB, MF and Mb-Mf on gymnasium ({r['preset']})", "",
             f"MF and Mb-Mf's fine-tuning: {r['algorithm']}. Returns: mean ± std over seeds of the evaluation "
             f"return (episodes of {r['config']['episode_len']} steps). docs/mbrl.md explains every column.", "",
             "| env | seeds | paper's speedup | do-nothing | MB last | MF final (budget) | MF converged | Mb-Mf after imitation "
             "(steps) | Mb-Mf final | Mb-Mf steps to MF final | speedup vs MF first reach / budget |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for e, v in r["envs"].items():
        if "mf_final" not in v:
            seeds = ", ".join(f"{m} {len(v['seeds'][m])}" for m in METHODS if m in v["seeds"])
            lines.append(f"| {e} | {seeds} | {THESIS_SPEEDUP[e]:g}× | | | (incomplete) | | | | | |")
            continue
        mb = v["curves"].get("mb") or [{"return_mean": float("nan"), "return_std": float("nan")}]
        dn = v["do_nothing"] or {}
        sp = v["speedup_vs_mf_first_reach"], v["speedup_vs_mf_budget"]
        lines.append(
            f"| {e} | {len(v['seeds']['mf'])} | {THESIS_SPEEDUP[e]:g}× | {dn.get('zero_mean', float('nan')):.1f} | "
            f"{mb[-1]['return_mean']:.1f} ± {mb[-1]['return_std']:.1f} | "
            f"{v['mf_final']:.1f} ± {v['mf_final_std']:.1f} ({v['mf_budget'] / 1000:.0f}k) | "
            f"{'yes' if v['mf_converged'] else 'no'} | {v['mbmf_after_imitation']:.1f} "
            f"({v['mbmf_imitation_steps'] / 1000:.1f}k) | {v['mbmf_final']:.1f} ± {v['mbmf_final_std']:.1f} | "
            f"{_fmt(v['mbmf_steps_to_mf_final'], 'k')} | "
            + (" / ".join("—" if s is None else f"{s:.1f}×" for s in sp)) + " |")
    reached = [e for e, v in r["envs"].items() if v.get("reached_ratio")]
    lines += ["", f"Mb-Mf reached MF's final return with ≥ 3× fewer steps (vs MF's first reach) on "
              f"{len(reached)} of {len(r['envs'])}: {', '.join(reached) or 'none'}.", "",
              "![return against environment steps](rewards.png)", ""]
    return "\n".join(lines)


def plot(r: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    envs = list(r["envs"])
    fig, axes = plt.subplots(1, max(1, len(envs)), figsize=(4.5 * max(1, len(envs)), 3.8), squeeze=False)
    for ax, e in zip(axes[0], envs, strict=False):
        v = r["envs"][e]
        for m in METHODS:
            c = v["curves"].get(m)
            if not c:
                continue
            x = np.maximum([p["steps"] for p in c], 1.0)
            y = np.array([p["return_mean"] for p in c])
            s = np.array([p["return_std"] for p in c])
            ax.plot(x, y, "o-" if m == "mb" else "-", label=LABELS[m], ms=4)
            ax.fill_between(x, y - s, y + s, alpha=0.2)
        if v.get("do_nothing"):
            ax.axhline(v["do_nothing"]["zero_mean"], color="gray", ls=":", label="do-nothing")
        if "mf_final" in v:
            ax.axhline(v["mf_final"], color="k", ls="--", lw=0.8, label="MF final")
        ax.set_xscale("log")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("return")
        ax.set_title(f"{e} (paper: Mb-Mf {THESIS_SPEEDUP[e]:g}x fewer steps)", fontsize=9)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_demo(out: Path, quick: bool = False, seed: int = 0, envs: tuple[str, ...] | None = None,
             tiny: bool = False) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config_for(quick, tiny)
    preset = "tiny" if tiny else ("quick" if quick else "full")
    envs = envs or (QUICK_ENVS if quick or tiny else tuple(TASKS))
    seeds = (seed,) if quick or tiny else (seed, seed + 1, seed + 2)
    t0 = time.monotonic()
    with (out / f"demo_{'_'.join(envs)}.log").open("a") as log_file:
        def log(msg: str) -> None:
            line = f"[{time.strftime('%H:%M:%S')} cpu {time.process_time():.0f} s] {msg}"
            print(line, flush=True)
            log_file.write(line + "\n")
            log_file.flush()

        log(f"mbrl-gym {preset}: envs {', '.join(envs)}, seeds {list(seeds)}")
        for e in envs:
            for s in seeds:
                run_seed(e, cfg, s, out, log)
        baselines = {}
        for e in TASKS:  # one file per environment: processes running other environments share OUT
            p = out / f"do_nothing_{e}.json"
            d = json.loads(p.read_text()) if p.exists() else None
            if e in envs and (d is None or d.get("episode_len") != cfg.episode_len):
                d = {**do_nothing_return(e, cfg.episode_len), "episode_len": cfg.episode_len}
                p.write_text(json.dumps(d, indent=1))
            if d is not None and d.get("episode_len") == cfg.episode_len:
                baselines[e] = d
        r = build_report(out, cfg, preset, baselines)
        r["elapsed_s_this_process"] = round(time.monotonic() - t0, 1)
        (out / "report.json").write_text(json.dumps(r, indent=1))
        plot(r, out / "rewards.png")
        (out / "report.md").write_text(report_markdown(r))
        log(f"done in {(time.monotonic() - t0) / 60:.1f} min: {out / 'report.md'}")
    return r


def cli_mbrl_gym(out: Path, quick: bool = False, full: bool = False, seed: int = 0, envs: str | None = None) -> None:
    """Entry of `hil demo mbrl-gym` (tools/cmd_demo.py OTHER_DEMOS). ``full`` is the default preset."""
    r = run_demo(out, quick=quick, seed=seed, envs=parse_envs(envs, quick))
    for e, v in r["envs"].items():
        if "mf_final" in v:
            print(f"{e}: MF final {v['mf_final']:.1f} at {v['mf_budget'] / 1000:.0f}k steps; Mb-Mf reaches it at "
                  f"{_fmt(v['mbmf_steps_to_mf_final'], 'k')} steps (speedup vs MF first reach "
                  f"{_fmt(v['speedup_vs_mf_first_reach'])}×)")
    print(f"report: {Path(out) / 'report.md'}")
