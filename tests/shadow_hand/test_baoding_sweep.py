"""`hil demo baoding --full --ray`: every seed a sweep task; the summary is the serial run's."""

from __future__ import annotations

from pathlib import Path

import hilstack.tools.demo_baoding as demo


def _fake_run(calls: list):
    """A seeded stand-in for one seed's run (a real one takes minutes): the report fields the summary reads."""
    def run(out: Path, preset: str, seed: int, rig: str, **overrides) -> dict:
        calls.append(seed)
        m = {"mean_rotation_deg": 10.0 * seed + 3, "mean_steps": 50 + seed, "success_90": seed / 4,
             "mean_return": -seed, "drop_rate": 0.1 * seed, "success_180": seed / 8, "points": 1000 + seed}
        return {"iterations": [m], "hold_policy": {**m, "success_90": 0.0}, "random_policy": {"mean_return": -9.0},
                "preset": preset, "rig": rig, "overrides": overrides}
    return run


def test_seeds_as_sweep_tasks_give_the_serial_summary_and_resume(tmp_path, monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(demo, "run_baoding_demo", _fake_run(calls))
    serial = demo.run_full(tmp_path / "serial", seeds=(0, 1, 2), preset="tiny", rig="hand_sim", epochs=1)
    assert serial["plot"] == "turns.png" and (tmp_path / "serial" / "turns.png").stat().st_size > 0  # the seeds' curve
    runs, sweep = demo.seeds_on_sweep(tmp_path / "sweep", (0, 1, 2), "tiny", "hand_sim", {"epochs": 1}, None)
    assert calls == [0, 1, 2, 0, 1, 2] and sweep["tasks"] == 3
    assert runs[2]["overrides"] == {"epochs": 1} and runs[1]["rig"] == "hand_sim"
    # the summary of the sweep's reports is the serial one
    monkeypatch.setattr(demo, "seeds_on_sweep", lambda *a, **k: (runs, sweep))
    par = demo.run_full(tmp_path / "sweep", seeds=(0, 1, 2), preset="tiny", rig="hand_sim", ray="local", epochs=1)
    assert par.pop("sweep") == sweep and par["final_success_90"]["per_seed"] == [0.0, 0.25, 0.5]
    assert {k: v for k, v in par.items() if k != "runs"} == {k: v for k, v in serial.items() if k != "runs"}
    # resume: only the seed without a result runs again
    (tmp_path / "sweep/tasks/seed1.json").unlink()
    monkeypatch.undo()
    monkeypatch.setattr(demo, "run_baoding_demo", _fake_run(calls))
    again, sw2 = demo.seeds_on_sweep(tmp_path / "sweep", (0, 1, 2), "tiny", "hand_sim", {"epochs": 1}, None)
    assert calls[6:] == [1] and sw2["resumed"] == 2 and again == runs


def test_a_stopped_seed_continues_when_the_sweep_runs_again(tmp_path, monkeypatch):
    """A seed killed mid-run leaves its checkpoint (a partial report.json), which a fresh start
    refuses to overwrite (as run_baoding_demo does): the sweep's re-run resumes it instead."""
    starts: list[tuple[int, bool]] = []

    def run(out: Path, preset: str, seed: int, rig: str, resume: bool = False, **overrides) -> dict:
        if (out / "report.json").exists() and not resume:
            raise ValueError(f"{out} already holds a run (report.json): resume it (--resume)")
        starts.append((seed, resume))
        return {"seed": seed, "resumed": resume}

    monkeypatch.setattr(demo, "run_baoding_demo", run)
    out = tmp_path / "sweep"
    demo.seeds_on_sweep(out, (0, 1), "tiny", "hand_sim", {}, None)
    (out / "tasks/seed1.json").unlink()  # seed 1 was stopped half-way: no result, its checkpoint left
    (out / "seed_1").mkdir(parents=True, exist_ok=True)
    (out / "seed_1/report.json").write_text('{"partial": true}')
    runs, sw = demo.seeds_on_sweep(out, (0, 1), "tiny", "hand_sim", {}, None)
    assert starts == [(0, False), (1, False), (1, True)] and sw["resumed"] == 1 and runs[1] == {"seed": 1, "resumed": True}
