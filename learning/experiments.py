"""The thesis' VelociRoACH experiments with statistics over seeds (`hil demo --full`).

Nagabandi's thesis, ch. 3, on the simulated rig, each repeated for every seed in
``MbrlConfig.seeds`` (a seed sets the random data, the model's initialization and its
training order) and reported as mean ± std (sample std, ``ddof=1``) over seeds:

* **Table 3.1** (:func:`table_3_1`): MPC on straight/left/right at the high speed after
  training on the first 50, 200 and 400 random rollouts × 50 steps, and after one
  on-policy iteration on top of the largest.
* **Fig. 3.8** (:func:`speed_sweep`): MPC vs the tuned differential drive over the
  commanded speeds ``sweep_speeds``, all evaluation paths; the baseline is tuned at each
  speed (:meth:`hilstack.learning.mbrl.MbrlRun.tune_baseline`).
* **Table 3.2** (:func:`table_3_2`): two terrain presets of the sim (``carpet`` and
  ``styrofoam``, docs/velociroach.md). Models trained on A, on B and on both, plus the
  baseline tuned on each terrain: the straight-line cost matrix.

Every cell keeps the per-seed values next to the mean and std, so a reader can check the
spread. Completion counts are summed over seeds (``completed`` of ``runs``).
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hilstack.control.costs import summarize_paths
from hilstack.learning.datasets import Episode
from hilstack.learning.mbrl import EXPERIMENTS, MbrlRun, _log, make_model, recording
from hilstack.learning.recordings import episodes_from_mcap

__all__ = ["mean_std", "table_3_1", "speed_sweep", "table_3_2", "run_experiments", "EXPERIMENTS"]

def mean_std(values) -> dict[str, Any]:
    """``{mean, std, n, values}`` (sample std; 0 for a single value)."""
    v = [float(x) for x in values]
    return {"mean": float(np.mean(v)) if v else float("nan"),
            "std": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0, "n": len(v), "values": v}


def _cells(per_seed: list[dict[str, dict]]) -> dict[str, dict[str, Any]]:
    """Per path, over seeds: cost and cost per metre (mean ± std), completions."""
    out = {}
    for path in per_seed[0]:
        ms = [r[path] for r in per_seed]
        out[path] = {"cost": mean_std(m["cost"] for m in ms), "cost_per_m": mean_std(m["cost_per_m"] for m in ms),
                     "completed": int(sum(bool(m["completed"]) for m in ms)), "runs": len(ms)}
    return out


def _summary(per_seed: list[dict[str, dict]]) -> dict[str, Any]:
    sums = [summarize_paths(r) for r in per_seed]
    return {"cost_per_m": mean_std(s["cost_per_m"] for s in sums), "completed": mean_std(s["completed"] for s in sums),
            "paths": len(per_seed[0])}


def fit_model(run: MbrlRun, episodes: list[Episode], seed: int, epochs: int | None = None):
    """A fresh model (initialized from ``seed``) trained on ``episodes``."""
    cfg = dataclasses.replace(run.cfg, seed=seed)
    model = make_model(cfg, run.state_names, run.action_names)
    run.train(model, episodes, epochs or run.cfg.epochs, seed=seed)
    return model


@contextlib.contextmanager
def _recorded(run: MbrlRun, name: str) -> Iterator[None]:
    """Record everything the rig says meanwhile to ``run.rec_dir/name.mcap``."""
    path = run.rec_dir / f"{name}.mcap"
    with recording(run.rig.name, path, run.bus):
        yield
    run.recordings.append(str(path))


def random_episodes(run: MbrlRun, n: int, name: str, seed: int) -> list[Episode]:
    path = run.collect_random(n, name, seed=seed)
    return episodes_from_mcap(path, run.cfg.robot)


def table_3_1(run: MbrlRun, seeds, sizes, paths, speed: float) -> tuple[dict[str, Any], dict[int, Any]]:
    """Rows ``"<n>"`` and ``"<max>+on-policy"``: per path cost, cost per metre and
    completions over seeds. Returns the table and, per seed, the on-policy model."""
    cfg = run.cfg
    rows: dict[str, list] = {}
    models = {}
    for seed in seeds:
        eps = random_episodes(run, max(sizes), f"310-random-seed{seed}", seed)
        model = None
        with _recorded(run, f"312-eval-seed{seed}"):
            for n in sizes:
                model = fit_model(run, eps[:n], seed)
                rows.setdefault(str(n), []).append(run.run_paths(run.mpc_for(model), speed, paths=paths))
                _log(cfg, f"table 3.1 seed {seed}: {n} rollouts {summarize_paths(rows[str(n)][-1])}")
        # one on-policy iteration on the largest model: MPC rollouts on the evaluation
        # paths at every speed, aggregated, warm-start retrain
        onp = run.rec_dir / f"311-onpolicy-seed{seed}.mcap"
        with recording(run.rig.name, onp, run.bus):
            for sp in cfg.speeds.values():
                run.run_paths(run.mpc_for(model), sp)
        run.recordings.append(str(onp))
        run.train(model, eps + episodes_from_mcap(onp, cfg.robot), cfg.retrain_epochs)
        key = f"{max(sizes)}+on-policy"
        with _recorded(run, f"313-eval-onpolicy-seed{seed}"):
            rows.setdefault(key, []).append(run.run_paths(run.mpc_for(model), speed, paths=paths))
        models[seed] = model
    table = {"speed": speed, "paths": list(paths), "seeds": list(seeds),
             "rows": {k: {"paths": _cells(v), "summary": _summary(v)} for k, v in rows.items()}}
    return table, models


def speed_sweep(run: MbrlRun, models: dict[int, Any], speeds) -> dict[str, Any]:
    """MPC (each seed's model) vs the differential drive tuned at each speed, all paths."""
    rows = []
    for speed in speeds:
        with _recorded(run, f"330-sweep-{speed:.2f}"):
            rows.append(_sweep_row(run, models, speed))
    return {"seeds": list(models), "rows": rows}


def _sweep_row(run: MbrlRun, models: dict[int, Any], speed: float) -> dict[str, Any]:
    tuning = run.tune_baseline(speed)
    mpc = [run.run_paths(run.mpc_for(m), speed) for m in models.values()]
    # the lockstep sim is deterministic for a fixed controller: one baseline run per speed
    dd = [run.run_paths(run.baseline_for(tuning["best_params"]), speed)]
    row = {"speed": speed, "mpc": _summary(mpc), "differential_drive": _summary(dd),
           "mpc_paths": _cells(mpc), "differential_drive_paths": _cells(dd),
           "baseline_params": tuning["best_params"]}
    _log(run.cfg, f"speed sweep {speed:.2f}: mpc {row['mpc']['cost_per_m']['mean']:.1f}/m "
                  f"dd {row['differential_drive']['cost_per_m']['mean']:.1f}/m")
    return row


def terrain_rig(run: MbrlRun, terrain: str, out: Path) -> Path:
    """A copy of the run's rig file with ``params.sim.terrain`` set, written under ``out``."""
    src = run.rig.source
    if src is None:
        raise ValueError(f"rig {run.rig.name!r} has no source file to derive a {terrain} rig from")
    doc = yaml.safe_load(Path(src).read_text())
    doc["name"] = f"{doc['name']}_{terrain}"
    entry = doc["robots"][run.cfg.robot]
    # a relative robot config resolves against the original rig's folder
    cfg_ref = Path(str(entry["config"]))
    if not cfg_ref.is_absolute() and cfg_ref.suffix:
        entry["config"] = str((Path(src).parent / cfg_ref).resolve())
    params = entry.setdefault("params", {}) or {}
    params.setdefault("sim", {})["terrain"] = terrain
    entry["params"] = params
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{doc['name']}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def table_3_2(run: MbrlRun, seeds, terrains: tuple[str, str], rollouts: int, speed: float,
              paths=("straight",)) -> dict[str, Any]:
    """Models trained on terrain A, on B and on both (per seed, ``rollouts`` random
    rollouts per terrain), and the baseline tuned on each terrain, evaluated on each."""
    cfg = run.cfg
    a, b = terrains
    runs = {}
    for t in terrains:
        sub_cfg = dataclasses.replace(cfg, rig=str(terrain_rig(run, t, run.out / "rigs")))
        runs[t] = MbrlRun(sub_cfg, run.out / f"terrain_{t}", run.bus)
    data: dict[str, dict[int, list[Episode]]] = {t: {} for t in terrains}
    baseline: dict[str, dict] = {}
    for t in terrains:
        r = runs[t]
        with r.session():
            for seed in seeds:
                data[t][seed] = random_episodes(r, rollouts, f"320-random-{t}-seed{seed}", seed)
            with _recorded(r, f"321-tune-baseline-{t}"):
                baseline[t] = r.tune_baseline(speed)["best_params"]
    trained = {}
    with runs[b].session():  # any rig gives the state and action names
        r = runs[b]
        for seed in seeds:
            trained[(a, seed)] = fit_model(r, data[a][seed], seed)
            trained[(b, seed)] = fit_model(r, data[b][seed], seed)
            trained[("both", seed)] = fit_model(r, data[a][seed] + data[b][seed], seed)
    matrix: dict[str, dict[str, Any]] = {}
    for t in terrains:
        r = runs[t]
        with r.session(), _recorded(r, f"322-eval-{t}"):
            for src in (a, b, "both"):
                res = [r.run_paths(r.mpc_for(trained[(src, seed)]), speed, paths=paths) for seed in seeds]
                matrix.setdefault(f"mpc trained on {src}", {})[t] = {"paths": _cells(res), "summary": _summary(res)}
            res = [r.run_paths(r.baseline_for(baseline[t]), speed, paths=paths)]
            matrix.setdefault("differential drive (tuned per terrain)", {})[t] = {
                "paths": _cells(res), "summary": _summary(res)}
        run.recordings += r.recordings
    return {"terrains": list(terrains), "speed": speed, "paths": list(paths), "seeds": list(seeds),
            "rollouts_per_terrain": rollouts, "baseline_params": baseline, "matrix": matrix}


def run_experiments(run: MbrlRun) -> dict[str, Any]:
    """The experiments in ``run.cfg.experiments``, on ``run``'s rig (open session)."""
    cfg = run.cfg  # experiment names were checked by MbrlConfig
    high = cfg.speeds.get("high_speed", max(cfg.speeds.values()))
    out: dict[str, Any] = {}
    models: dict[int, Any] = {}
    if "table_3_1" in cfg.experiments or "speed_sweep" in cfg.experiments:
        out["table_3_1"], models = table_3_1(run, cfg.seeds, cfg.table_sizes, cfg.table_paths, high)
    if "speed_sweep" in cfg.experiments:
        out["speed_sweep"] = speed_sweep(run, models, cfg.sweep_speeds)
    return out
