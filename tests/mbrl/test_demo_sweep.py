"""`hil demo --full --ray` (tools/demo_sweep.py): the main run and each seed's experiments as
sweep tasks with their own rig processes; serial == Ray for the same seeds; resume."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from hilstack.learning.mbrl import MbrlConfig
from hilstack.tools.demo_sweep import full_tasks, run_full_on_sweep

#: the smallest run with both seeds' Table 3.1 (2 x 30 steps per recording: every recording
#: spans > 50 steps, so it holds a spec message); the other tables' assembly is checked on
#: synthetic task results below (test_assembled_tables_are_the_serial_tables)
TINY = dict(random_rollouts=2, rollout_steps=30, epochs=2, retrain_epochs=1, samples=32, speeds={"high_speed": 1.0},
            paths=("straight",), path_scale=0.2, time_limit_speed_mps=0.4, tune_paths=("right",),
            tune_path_scale=0.2, baseline_candidates=2, seeds=(0, 1), table_sizes=(2,), table_paths=("straight",),
            iterations=0, experiments=("table_3_1",), progress=False)
TABLES = ("table_3_1",)


def test_tasks_cover_every_experiment():
    cfg = MbrlConfig.from_preset("full", seeds=(0, 1), sweep_speeds=(0.4, 1.0))
    keys = [t.key for t in full_tasks(cfg, "unused")]
    assert keys == ["main", "seed0", "seed1", "sweep-dd-0.40", "sweep-dd-1.00", "terrain-seed0", "terrain-seed1",
                    "terrain-dd-carpet", "terrain-dd-styrofoam"]
    # each task works in its own folder, so two on one machine never share a recording
    outs = [t.kwargs["out"] for t in full_tasks(cfg, "unused")]
    assert len(set(outs)) == len(outs)


def test_merged_cells_are_the_cells_over_all_seeds():
    """Cells of one seed each, merged, equal the serial run's cells over the seeds at once."""
    from hilstack.learning.experiments import _cells, _summary
    from hilstack.tools.demo_sweep import merge_cells, merge_summary

    rng = np.random.default_rng(3)
    per_seed = [{p: {"cost": float(rng.normal(50, 20)), "cost_per_m": float(rng.normal(10, 5)), "progress_m": 1.0,
                     "completed": bool(rng.random() < 0.5)} for p in ("straight", "left")} for _ in range(3)]
    assert merge_cells([_cells([r]) for r in per_seed]) == _cells(per_seed)
    assert merge_summary([_summary([r]) for r in per_seed]) == _summary(per_seed)


def _paths(rng, names=("straight", "left")) -> dict:
    """One ``run_paths`` result with random metrics."""
    return {p: {"cost": float(rng.normal(50, 20)), "cost_per_m": float(rng.normal(10, 5)),
                "progress_m": float(rng.uniform(0.5, 2)), "completed": bool(rng.random() < 0.5)} for p in names}


def test_assembled_tables_are_the_serial_tables():
    """The speed sweep and Table 3.2 put together from the tasks' results (``assemble``) equal
    what learning/experiments.py computes from all seeds' path results at once."""
    from hilstack.learning.experiments import _cells, _summary
    from hilstack.tools.demo_sweep import _cell_and_summary, assemble

    cfg = MbrlConfig.from_preset("full", seeds=(0, 1, 2), sweep_speeds=(0.5, 1.0), experiments=("speed_sweep",
                                                                                               "table_3_2"))
    rng = np.random.default_rng(7)
    mpc = {(s, sp): _paths(rng) for s in cfg.seeds for sp in cfg.sweep_speeds}
    dd = {sp: _paths(rng) for sp in cfg.sweep_speeds}
    terr = {(src, t, s): _paths(rng, ("straight",)) for src in (*cfg.terrains, "both") for t in cfg.terrains
            for s in cfg.seeds}
    tdd = {t: _paths(rng, ("straight",)) for t in cfg.terrains}
    t31 = {"speed": 1.0, "paths": ["straight"], "seeds": [0], "rows": {}}
    results = {"main": {"recordings": []}}
    for s in cfg.seeds:
        results[f"seed{s}"] = {"table_3_1": t31, "recordings": [], "sweep_mpc": {
            f"{sp:.2f}": _cell_and_summary([mpc[(s, sp)]]) for sp in cfg.sweep_speeds}}
        results[f"terrain-seed{s}"] = {"recordings": [], "matrix": {
            f"mpc trained on {src}": {t: _cell_and_summary([terr[(src, t, s)]]) for t in cfg.terrains}
            for src in (*cfg.terrains, "both")}}
    for sp in cfg.sweep_speeds:
        results[f"sweep-dd-{sp:.2f}"] = {"params": {"k": sp}, "recordings": [], **_cell_and_summary([dd[sp]])}
    for t in cfg.terrains:
        results[f"terrain-dd-{t}"] = {"params": {"k": t}, "recordings": [], **_cell_and_summary([tdd[t]])}
    rep = assemble(cfg, results)
    for row, sp in zip(rep["speed_sweep"]["rows"], cfg.sweep_speeds, strict=True):
        per = [mpc[(s, sp)] for s in cfg.seeds]
        assert row["speed"] == sp and row["baseline_params"] == {"k": sp}
        assert row["mpc"] == _summary(per) and row["mpc_paths"] == _cells(per)
        assert row["differential_drive"] == _summary([dd[sp]]) and row["differential_drive_paths"] == _cells([dd[sp]])
    m = rep["table_3_2"]["matrix"]
    for src in (*cfg.terrains, "both"):
        for t in cfg.terrains:
            per = [terr[(src, t, s)] for s in cfg.seeds]
            assert m[f"mpc trained on {src}"][t] == {"paths": _cells(per), "summary": _summary(per)}
    assert m["differential drive (tuned per terrain)"]["carpet"]["summary"] == _summary([tdd["carpet"]])
    assert rep["table_3_2"]["seeds"] == [0, 1, 2] and rep["table_3_2"]["baseline_params"]["styrofoam"] == {"k": "styrofoam"}


@pytest.mark.slow
def test_serial_and_ray_give_the_same_tables_and_a_stopped_run_resumes(tmp_path):
    cfg = MbrlConfig.from_preset("full", **TINY)
    serial = run_full_on_sweep(cfg, tmp_path / "serial", None, log=lambda s: None)
    t31 = serial["table_3_1"]
    assert t31["seeds"] == [0, 1] and list(t31["rows"]) == ["2", "2+on-policy"]
    # the cells over seeds are the per-seed tasks' values in seed order, with their mean and sample std
    per_seed = [json.loads((tmp_path / f"serial/tasks/seed{s}.json").read_text())["result"] for s in (0, 1)]
    cell = t31["rows"]["2"]["paths"]["straight"]["cost"]
    assert cell["values"] == [p["table_3_1"]["rows"]["2"]["paths"]["straight"]["cost"]["values"][0] for p in per_seed]
    assert cell["mean"] == pytest.approx(np.mean(cell["values"])) and cell["n"] == 2
    assert cell["values"][0] != cell["values"][1]  # the seed matters, so equal tables below mean something
    assert cell["std"] == pytest.approx(np.std(cell["values"], ddof=1))
    assert t31["rows"]["2"]["paths"]["straight"]["runs"] == 2
    # each seed ran on its own rig: its own driver log and recordings
    for s in (0, 1):
        assert (tmp_path / f"serial/tasks/seed{s}/logs/driver.log").is_file()
        assert str(tmp_path / f"serial/tasks/seed{s}/recordings/312-eval-seed{s}.mcap") in serial["recordings"]

    # a run stopped while both seeds ran (no results, seed 1's files half written), re-run on a
    # local Ray runtime with 2 workers: only the two seeds run, side by side, each on its own rig;
    # the half-written files are kept aside, not overwritten; the tables are the serial run's
    pytest.importorskip("ray", reason="Ray is the cluster extra (pip install hilstack[cluster])")
    shutil.copytree(tmp_path / "serial", tmp_path / "ray")
    for s in (0, 1):
        (tmp_path / f"ray/tasks/seed{s}.json").unlink()
    shutil.rmtree(tmp_path / "ray/tasks/seed0")
    par = run_full_on_sweep(cfg, tmp_path / "ray", "local", workers=2, log=lambda s: None)
    sw = par["sweep"]
    assert sw["executor"] == "ray" and sw["workers"] == 2 and sw["resumed"] == 1 and sw["tasks"] == 3
    assert (tmp_path / "ray/tasks/seed1.interrupted-1/logs/driver.log").is_file()
    assert not (tmp_path / "ray/tasks/seed0.interrupted-1").exists()
    assert {k: par[k] for k in TABLES} == {k: serial[k] for k in TABLES}
    for s in (0, 1):  # the seeds really ran again
        assert json.loads((tmp_path / f"ray/tasks/seed{s}.json").read_text())["host"]
        assert (tmp_path / f"ray/tasks/seed{s}/logs/driver.log").stat().st_mtime > \
            (tmp_path / "serial/tasks/seed1.json").stat().st_mtime


def test_ray_is_refused_where_there_is_nothing_to_split(tmp_path):
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    for args, why in ((["demo", "--ray", "local"], "--ray is for the full run"),
                      (["demo", "baoding", "--ray", "local"], "--ray is for the full run"),
                      (["demo", "meld", "--ray", "local"], "--ray is for the roach and baoding")):
        r = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "o")])
        assert r.exit_code == 2 and why in r.output, (args, r.output)
    assert not (tmp_path / "o").exists()


def test_a_seeds_validation_split_does_not_depend_on_the_seeds_before_it(tmp_path, monkeypatch):
    """The serial --full run trains every seed in one process; a sweep task trains one seed alone.
    Each seed draws its train/validation split from its own generator, so both give one table."""
    import hilstack.learning.mbrl as mbrl
    from hilstack.configs.schema import BusConfig
    from hilstack.learning.mbrl import MbrlRun

    draws = []
    monkeypatch.setattr(mbrl, "fit_episodes", lambda m, e, ep, bs, vf, rng, *a, **k: draws.append(int(rng.integers(1 << 30))))
    cfg = MbrlConfig.from_preset("full", **TINY)
    serial = MbrlRun(cfg, tmp_path / "serial", BusConfig())
    serial.train(None, [], 1)  # the main run's model
    serial.train(None, [], 1, seed=0)
    serial.train(None, [], 1, seed=1)
    alone = MbrlRun(cfg, tmp_path / "alone", BusConfig())
    alone.train(None, [], 1, seed=1)
    assert draws[2] == draws[3] and len(set(draws[:3])) == 3
