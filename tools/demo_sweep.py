"""`hil demo --full --ray`: the MBRL demo's main run and the thesis' experiments as sweep tasks.

The serial `hil demo --full` runs everything in one rig session, one seed after another
(:func:`hilstack.learning.experiments.run_experiments`). Here every piece that does not need
another piece's result is a task of :func:`hilstack.tools.sweep.run_sweep`, and every task
starts its own rig processes (``hil up``) on its own bus endpoint, so tasks run side by side
on one machine or on the nodes of a Ray cluster:

* ``main``: the main comparison (random data, model, on-policy iteration, the baseline tuned
  at each of ``speeds``, MPC vs the tuned baseline), :class:`hilstack.learning.mbrl.MbrlRun`
  without experiments (its model at ``OUT/tasks/main/model.pt``);
* ``seed<k>``: Table 3.1 for seed k, then that seed's model (the on-policy one) on every path
  at every speed of the speed sweep (the MPC half of Fig. 3.8);
* ``sweep-dd-<speed>``: the differential drive tuned at one sweep speed and run on every path
  (the baseline half of Fig. 3.8; seed-independent, as in the serial run);
* ``terrain-seed<k>``: Table 3.2 for seed k: random data on both terrains, the three models,
  each evaluated on both terrains;
* ``terrain-dd-<terrain>``: the differential drive tuned on one terrain and run there.

Each task's working files are under ``OUT/tasks/<key>/`` (recordings, the driver's log);
its result (cells of per-seed values) under ``OUT/tasks/<key>.json``; the report merges the
cells over seeds into the serial run's tables (mean ± std of the same per-seed values). A
stopped run re-run with the same ``--out`` does only the missing tasks (tools/sweep.py).

Per-seed numbers equal those of the same tasks run serially (``run_full_on_sweep(...,
ray=None)``, a test compares them), not those of the serial `hil demo --full`: there the
seeds share one session, and the train/validation split of a seed's episodes draws from
a generator the earlier seeds advanced (``MbrlRun.split_rng``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from hilstack.learning.mbrl import MbrlConfig


# ------------------------------------------------------------------------- merging per-seed cells
def _cat(cells: list[dict[str, Any]]) -> dict[str, Any]:
    """``mean_std`` over the concatenated per-seed ``values`` (the serial run's cell)."""
    from hilstack.learning.experiments import mean_std

    return mean_std([v for c in cells for v in c["values"]])


def merge_cells(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-path cells (``experiments._cells`` of one seed each) → the cells over all seeds."""
    return {p: {"cost": _cat([c[p]["cost"] for c in parts]), "cost_per_m": _cat([c[p]["cost_per_m"] for c in parts]),
                "completed": sum(c[p]["completed"] for c in parts), "runs": sum(c[p]["runs"] for c in parts)}
            for p in parts[0]}


def merge_summary(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Summaries (``experiments._summary`` of one seed each) → the summary over all seeds."""
    return {"cost_per_m": _cat([s["cost_per_m"] for s in parts]), "completed": _cat([s["completed"] for s in parts]),
            "paths": parts[0]["paths"]}


def _cell_and_summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    from hilstack.learning.experiments import _cells, _summary

    return {"paths": _cells(results), "summary": _summary(results)}


# ------------------------------------------------------------------------------- the tasks
@contextlib.contextmanager
def _session(cfg: MbrlConfig, out: Path, rig: str | None = None) -> Iterator[Any]:
    """An :class:`MbrlRun` on ``rig`` (default the config's) with its own rig processes on a
    free endpoint of this host, its files under ``out``."""
    import torch

    from hilstack.configs.schema import load_rig
    from hilstack.learning.mbrl import MbrlRun
    from hilstack.tools.common import provision_credentials, with_endpoint
    from hilstack.tools.demo import free_endpoint

    torch.manual_seed(cfg.seed)  # a Ray worker's torch generator carries the previous task's state
    if rig is not None:
        cfg = dataclasses.replace(cfg, rig=rig)
    rig_cfg = load_rig(cfg.rig)
    bus = with_endpoint(rig_cfg.bus, free_endpoint())
    provision_credentials(rig_cfg.name, bus, rig_cfg)
    run = MbrlRun(cfg, out, bus)
    with run.session():
        yield run


def _workdir(out: str) -> Path:
    """The task's working folder, empty: what an interrupted earlier attempt left there is
    moved aside to ``<folder>.interrupted-<n>``, never overwritten."""
    p = Path(out)
    if p.exists() and any(p.iterdir()):
        n = 1
        while p.with_name(f"{p.name}.interrupted-{n}").exists():
            n += 1
        p.rename(p.with_name(f"{p.name}.interrupted-{n}"))
    p.mkdir(parents=True, exist_ok=True)
    return p


def _config(cfg: dict[str, Any]) -> MbrlConfig:
    return MbrlConfig(**cfg)


def _high(cfg: MbrlConfig) -> float:
    return cfg.speeds.get("high_speed", max(cfg.speeds.values()))


def task_main(cfg: dict[str, Any], out: str) -> dict[str, Any]:
    """The main comparison: the serial demo's report without the experiments."""
    import torch

    from hilstack.configs.schema import load_rig
    from hilstack.learning.mbrl import MbrlRun
    from hilstack.tools.common import provision_credentials, with_endpoint
    from hilstack.tools.demo import free_endpoint

    c = dataclasses.replace(_config(cfg), experiments=())
    torch.manual_seed(c.seed)
    rig_cfg = load_rig(c.rig)
    bus = with_endpoint(rig_cfg.bus, free_endpoint())
    provision_credentials(rig_cfg.name, bus, rig_cfg)
    return MbrlRun(c, _workdir(out), bus).run()


def task_seed(cfg: dict[str, Any], out: str, seed: int) -> dict[str, Any]:
    """Table 3.1 for ``seed`` and its on-policy model on every path at every sweep speed."""
    from hilstack.learning.experiments import _recorded, table_3_1

    c = _config(cfg)
    with _session(c, _workdir(out)) as run:
        table, models = table_3_1(run, [seed], c.table_sizes, c.table_paths, _high(c))
        sweep = {}
        for speed in c.sweep_speeds:
            with _recorded(run, f"330-sweep-{speed:.2f}-seed{seed}"):
                sweep[f"{speed:.2f}"] = _cell_and_summary([run.run_paths(run.mpc_for(models[seed]), speed)])
    return {"table_3_1": table, "sweep_mpc": sweep, "recordings": run.recordings}


def task_sweep_baseline(cfg: dict[str, Any], out: str, speed: float) -> dict[str, Any]:
    """The differential drive tuned at ``speed`` (tuning paths) and run on every path."""
    from hilstack.learning.experiments import _recorded

    c = _config(cfg)
    with _session(c, _workdir(out)) as run, _recorded(run, f"330-sweep-{speed:.2f}-baseline"):
        params = run.tune_baseline(speed)["best_params"]
        res = _cell_and_summary([run.run_paths(run.baseline_for(params), speed)])
    return {"params": params, **res, "recordings": run.recordings}


def _terrain_rigs(cfg: MbrlConfig, out: Path) -> dict[str, str]:
    """The terrain rig files (``experiments.terrain_rig``), written under ``out`` (each task its own)."""
    from hilstack.configs.schema import load_rig
    from hilstack.learning.experiments import terrain_rig

    base = SimpleNamespace(rig=load_rig(cfg.rig), cfg=cfg)  # what terrain_rig reads of a run
    return {t: str(terrain_rig(base, t, out / "rigs")) for t in cfg.terrains}


def task_terrain_seed(cfg: dict[str, Any], out: str, seed: int) -> dict[str, Any]:
    """Table 3.2 for ``seed``: data on each terrain, models on A, on B and on both, each
    evaluated on both terrains (straight line at the high speed, as the serial run)."""
    from hilstack.learning.experiments import _recorded, fit_model, random_episodes

    c = _config(cfg)
    a, b = c.terrains
    out_p = _workdir(out)
    rigs = _terrain_rigs(c, out_p)
    data: dict[str, list] = {}
    recordings: list[str] = []
    for t in c.terrains:
        with _session(c, out_p / f"terrain_{t}", rigs[t]) as run:
            data[t] = random_episodes(run, c.terrain_rollouts, f"320-random-{t}-seed{seed}", seed)
            recordings += run.recordings
    models = {}
    matrix: dict[str, dict[str, Any]] = {}
    for t in c.terrains:  # a folder of its own: the second session's driver log beside the first's
        with _session(c, out_p / f"terrain_{t}_eval", rigs[t]) as run:
            if not models:  # the session gives the state and action names
                models = {a: fit_model(run, data[a], seed), b: fit_model(run, data[b], seed),
                          "both": fit_model(run, data[a] + data[b], seed)}
            with _recorded(run, f"322-eval-{t}-seed{seed}"):
                for src in (a, b, "both"):
                    res = run.run_paths(run.mpc_for(models[src]), _high(c), paths=("straight",))
                    matrix.setdefault(f"mpc trained on {src}", {})[t] = _cell_and_summary([res])
            recordings += run.recordings
    return {"matrix": matrix, "recordings": recordings}


def task_terrain_baseline(cfg: dict[str, Any], out: str, terrain: str) -> dict[str, Any]:
    """The differential drive tuned on ``terrain`` and run there (straight line, high speed)."""
    from hilstack.learning.experiments import _recorded

    c = _config(cfg)
    out_p = _workdir(out)
    rig = _terrain_rigs(c, out_p)[terrain]
    with _session(c, out_p / f"terrain_{terrain}", rig) as run:
        with _recorded(run, f"321-tune-baseline-{terrain}"):
            params = run.tune_baseline(_high(c))["best_params"]
        with _recorded(run, f"322-eval-{terrain}-baseline"):
            res = _cell_and_summary([run.run_paths(run.baseline_for(params), _high(c), paths=("straight",))])
    return {"params": params, **res, "recordings": run.recordings}


def full_tasks(cfg: MbrlConfig, out: Path, threads: int = 1) -> list:
    """The sweep's tasks for ``cfg`` (its ``experiments``, ``seeds``, ``sweep_speeds``, ``terrains``)."""
    from hilstack.tools.sweep import Task

    d = dataclasses.asdict(cfg)
    tdir = Path(out) / "tasks"

    def task(key: str, fn, **kw) -> Task:
        return Task(key, fn, {"cfg": d, "out": str(tdir / key), **kw}, threads=threads)

    tasks = [task("main", task_main)]
    if {"table_3_1", "speed_sweep"} & set(cfg.experiments):
        tasks += [task(f"seed{s}", task_seed, seed=s) for s in cfg.seeds]
    if "speed_sweep" in cfg.experiments:
        tasks += [task(f"sweep-dd-{sp:.2f}", task_sweep_baseline, speed=sp) for sp in cfg.sweep_speeds]
    if "table_3_2" in cfg.experiments:
        tasks += [task(f"terrain-seed{s}", task_terrain_seed, seed=s) for s in cfg.seeds]
        tasks += [task(f"terrain-dd-{t}", task_terrain_baseline, terrain=t) for t in cfg.terrains]
    return tasks


# --------------------------------------------------------------------------- the report
def assemble(cfg: MbrlConfig, results: dict[str, Any]) -> dict[str, Any]:
    """The serial run's report from the tasks' results: the main report, then Table 3.1, the
    speed sweep and Table 3.2 with every cell over the seeds in ``cfg.seeds`` order."""
    report = dict(results["main"])
    recordings = list(report.get("recordings", []))
    seeds = list(cfg.seeds)
    if {"table_3_1", "speed_sweep"} & set(cfg.experiments):
        per = [results[f"seed{s}"] for s in seeds]
        t = [p["table_3_1"] for p in per]
        report["table_3_1"] = {"speed": t[0]["speed"], "paths": t[0]["paths"], "seeds": seeds,
                               "rows": {row: {"paths": merge_cells([x["rows"][row]["paths"] for x in t]),
                                              "summary": merge_summary([x["rows"][row]["summary"] for x in t])}
                                        for row in t[0]["rows"]}}
        for p in per:
            recordings += p["recordings"]
    if "speed_sweep" in cfg.experiments:
        rows = []
        for sp in cfg.sweep_speeds:
            k = f"{sp:.2f}"
            mpc = [results[f"seed{s}"]["sweep_mpc"][k] for s in seeds]
            dd = results[f"sweep-dd-{k}"]
            rows.append({"speed": sp, "mpc": merge_summary([m["summary"] for m in mpc]),
                         "differential_drive": dd["summary"], "mpc_paths": merge_cells([m["paths"] for m in mpc]),
                         "differential_drive_paths": dd["paths"], "baseline_params": dd["params"]})
            recordings += dd["recordings"]
        report["speed_sweep"] = {"seeds": seeds, "rows": rows}
    if "table_3_2" in cfg.experiments:
        a, b = cfg.terrains
        per = [results[f"terrain-seed{s}"] for s in seeds]
        matrix: dict[str, dict[str, Any]] = {}
        for src in (a, b, "both"):
            row = f"mpc trained on {src}"
            matrix[row] = {t: {"paths": merge_cells([p["matrix"][row][t]["paths"] for p in per]),
                               "summary": merge_summary([p["matrix"][row][t]["summary"] for p in per])}
                           for t in cfg.terrains}
        dd = {t: results[f"terrain-dd-{t}"] for t in cfg.terrains}
        matrix["differential drive (tuned per terrain)"] = {t: {"paths": dd[t]["paths"], "summary": dd[t]["summary"]}
                                                            for t in cfg.terrains}
        report["table_3_2"] = {"terrains": list(cfg.terrains), "speed": _high(cfg), "paths": ["straight"],
                               "seeds": seeds, "rollouts_per_terrain": cfg.terrain_rollouts,
                               "baseline_params": {t: dd[t]["params"] for t in cfg.terrains}, "matrix": matrix}
        for p in [*per, *dd.values()]:
            recordings += p["recordings"]
    report["recordings"] = recordings
    return report


def run_full_on_sweep(cfg: MbrlConfig, out: Path, ray: str | None, workers: int = 1,
                      log=print, threads: int = 1) -> dict[str, Any]:
    """``cfg``'s main run and experiments as sweep tasks (``ray``: None for serial in this
    process, ``local`` or a cluster's address); the report of the serial run's shape, with
    ``sweep`` (executor, workers, wall time) and ``wall_s`` of the whole sweep."""
    from hilstack.tools.sweep import executor_from, run_sweep

    t0 = time.monotonic()
    tasks = full_tasks(cfg, out, threads)
    sw = run_sweep(tasks, out, executor=executor_from(ray), workers=workers, log=log)
    if sw["failed"]:
        from hilstack.tools.common import UserError

        raise UserError(f"tasks {sorted(sw['failed'])} failed (their log tails above; {Path(out) / 'tasks'}); "
                           "the same command again re-runs only those")
    report = assemble(cfg, sw["results"])
    report["sweep"] = sw["sweep"]
    report["config"] = report.get("config") | {"experiments": list(cfg.experiments)}
    report["wall_s"] = time.monotonic() - t0
    return report


#: ``--small``: the full run's every experiment at a size that takes minutes, for measuring the
#: executors against each other (docs/scaling.md); not the thesis' numbers
SMALL: dict[str, Any] = dict(random_rollouts=20, epochs=20, retrain_epochs=5, baseline_candidates=2,
                             paths=("straight", "left"), seeds=(0, 1), table_sizes=(10, 20),
                             sweep_speeds=(0.5, 1.0), terrain_rollouts=10)


def main(argv: list[str] | None = None) -> None:
    import argparse
    import json

    from hilstack.tools.demo import write_report

    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.demo_sweep",
                                 description="hil demo --full as sweep tasks, serial without --ray; --small: "
                                             "every experiment at a size of minutes (the executors' comparison "
                                             "in docs/scaling.md)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--small", action="store_true")
    ap.add_argument("--ray", default=None, help="local | a Ray cluster's address (default: serial, in-process)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    cfg = MbrlConfig.from_preset("full", seed=a.seed, progress=False, **(SMALL if a.small else {}))
    report = write_report(run_full_on_sweep(cfg, a.out, a.ray, a.workers), a.out, quick=False, full=True)
    print(json.dumps({"wall_s": report["wall_s"], "sweep": report["sweep"]}))


if __name__ == "__main__":
    main()
