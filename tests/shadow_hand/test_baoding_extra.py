"""Recorded episodes mixed into a Baoding run's training (``--extra-data``, issue 30; docs/baoding.md,
"Does a run whose data hold turns bootstrap?"): they reach every iteration's training split,
ball-swap doubled and repeated, never its validation split; a directory without finished
recordings is refused; a resumed run may add them (and more iterations), nothing else."""

from __future__ import annotations

import json
from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pytest

from hilstack.drivers.shadow_hand.config import ShadowHandParams, shadow_hand_spec
from hilstack.learning.baoding import (
    BaodingConfig,
    BaodingFeatures,
    BaodingRun,
    finished_recordings,
    probe_turn,
)
from hilstack.learning.datasets import Episode
from hilstack.tools.demo_baoding import EpisodeRecording

SPEC = shadow_hand_spec(ShadowHandParams(objects_in_state=True))
NAMES = list(SPEC.state.names)


def record(path, n_steps: int = 6, seed: int = 0) -> None:
    """One episode of the hand's state (balls at rest in the palm) recorded as the demo does."""
    rng = np.random.default_rng(seed)
    rec = EpisodeRecording(path, SPEC)
    for t in range(n_steps):
        s = np.full(len(NAMES), 0.1) + 0.01 * rng.standard_normal(len(NAMES))
        rec(SimpleNamespace(t_s=0.1 * t, state=s, seq=t, ok=True), None if t == 0 else rng.uniform(-1, 1, 20))
    rec.close()


def own_episodes(n: int, start: int = 0) -> list[Episode]:
    f = BaodingFeatures(NAMES, 0.1)
    rng = np.random.default_rng(start)
    return [f.episode(Episode(states=0.1 + 0.01 * rng.standard_normal((9, len(NAMES))), actions=rng.uniform(-1, 1, (8, 20)),
                              times=np.arange(9) * 0.1, name=f"own{start + i}")) for i in range(n)]


class Recorder:
    """A model whose fit records the episode names it was given."""

    def __init__(self):
        self.fits: list[tuple[list[str], list[str]]] = []

    def fit(self, train, epochs, batch_size, val, horizon, progress):
        self.fits.append(([e.name for e in train], [e.name for e in (val or [])]))
        return [{"train_loss": 0.0}]


@pytest.fixture
def demo_dir(tmp_path):
    d = tmp_path / "demos"
    d.mkdir()
    for k in range(3):
        record(d / f"oracle-s10-{k:03d}.mcap", seed=k)
    record(d / "oracle-s10-003.unfinished.mcap", seed=9)  # a partial episode: never read
    return d


def make_run(tmp_path, bus, **kw) -> BaodingRun:
    run = BaodingRun(BaodingConfig.from_preset("tiny", **kw), tmp_path / "run", bus)
    run.state_names = NAMES  # what session() reads from the hand's spec
    return run


def test_extra_episodes_reach_training_and_never_validation(tmp_path, bus, demo_dir):
    run = make_run(tmp_path, bus, extra_recordings=[str(demo_dir)], extra_repeat=3, val_fraction=0.3)
    run.load_extra()
    extra = sorted(e.name for e in run.extra)
    assert len(extra) == 3 and len(set(extra)) == 3  # the unfinished one is left out
    model = Recorder()
    datas = [own_episodes(10), own_episodes(10) + own_episodes(10, start=10)]  # the next iteration: more own data
    for data in datas:
        run.train(model, data, 1)
    for (train, val), data in zip(model.fits, datas, strict=True):
        assert val and all(n.startswith("own") for n in val)
        assert not set(val) & {*extra, *(f"{n}#swapped" for n in extra)}
        for n in extra:  # repeated, and ball-swap doubled as the run's own episodes
            assert train.count(n) == 3 and train.count(f"{n}#swapped") == 3
        own_train = [n for n in train if n.startswith("own") and "#" not in n]
        assert sorted(own_train + val) == sorted(e.name for e in data)
    assert not any(k.startswith("oracle") for k in run.val_assigned)
    # the epochs of a fixed number of steps count the extra points too
    plain = make_run(tmp_path / "p", bus, val_fraction=0.3)
    assert run.extra_points() == 3 * sum(len(e) for e in run.extra)
    with_steps = BaodingConfig.from_preset("tiny", train_steps=50, batch_size=10, val_fraction=0.3,
                                                extra_recordings=[str(demo_dir)], extra_repeat=3)
    run.bcfg, plain.bcfg = with_steps, BaodingConfig.from_preset("tiny", train_steps=50, batch_size=10, val_fraction=0.3)
    raw = [Episode(states=np.zeros((41, 3)), actions=np.zeros((40, 1)), times=np.arange(41) * 0.1, name="x")]
    assert run.epochs_for(raw, 2) < plain.epochs_for(raw, 2)
    assert run.demonstrations()["text"] == f"demonstrations: 3 episodes from {demo_dir}, repeated 3×"


def test_a_directory_without_finished_recordings_is_refused(tmp_path, bus):
    empty = tmp_path / "empty"
    empty.mkdir()
    record(empty / "oracle-s10-000.unfinished.mcap")
    for d in (empty, tmp_path / "missing"):
        with pytest.raises(ValueError, match=f"extra data {d}: ") as e:
            finished_recordings(d)
        assert "\n" not in str(e.value)
    # from the command line: one line, before any rig starts
    from typer.testing import CliRunner

    from hilstack.tools.cli import app

    r = CliRunner().invoke(app, ["demo", "baoding", "--quick", "--extra-data", str(empty), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "no finished recordings" in r.output, r.output
    assert not (tmp_path / "o" / "recordings" / "000-random.mcap").exists()
    r = CliRunner().invoke(app, ["demo", "baoding", "--quick", "--extra-repeat", "2", "--out", str(tmp_path / "o")])
    assert r.exit_code != 0 and "--extra-repeat needs --extra-data" in r.output, r.output
    with pytest.raises(ValueError, match="extra_repeat must be >= 1"):
        BaodingConfig(extra_repeat=0)


def fake_stopped_run(out, config: dict) -> None:
    (out / "checkpoint").mkdir(parents=True)
    (out / "recordings").mkdir(exist_ok=True)
    (out / "recordings" / "000-random.mcap").write_bytes(b"")
    (out / "checkpoint" / "state.json").write_text(json.dumps({"iteration": 3}))
    (out / "report.json").write_text(json.dumps({"config": config}))


def test_resume_may_add_extra_data_and_iterations_nothing_else(tmp_path, bus, demo_dir):
    old = asdict(BaodingConfig.from_preset("tiny"))
    del old["noise_to_signal"], old["extra_recordings"], old["extra_repeat"]  # a run older than these settings
    out = tmp_path / "run"
    fake_stopped_run(out, old)
    run = BaodingRun(BaodingConfig.from_preset("tiny", iterations=5, extra_recordings=[str(demo_dir)], extra_repeat=4),
                     out, bus, resume=True)
    got = run.load_checkpoint()
    assert got["changed"] == {"iterations": [1, 5], "extra_recordings": [[], [str(demo_dir)]], "extra_repeat": [1, 4]}
    for change, name in (({"seed": 1}, "seed"), ({"sigma": 0.5}, "sigma"), ({"noise_to_signal": 0.01}, "noise_to_signal")):
        r = BaodingRun(BaodingConfig.from_preset("tiny", **change), out, bus, resume=True)
        with pytest.raises(ValueError, match=rf"other settings \({name}\)"):
            r.load_checkpoint()
    # a run directory copied elsewhere reads its own recordings, not its original's
    assert run._rebased(["/elsewhere/recordings/000-random.mcap", "/elsewhere/recordings/9-gone.mcap"]) == [
        str(out / "recordings" / "000-random.mcap"), "/elsewhere/recordings/9-gone.mcap"]


def test_report_names_the_demonstrations():
    from hilstack.tools.demo_baoding import report_markdown

    m = {"episodes": 2, "success_90": 0.5, "success_180": 0.0, "mean_rotation_deg": 40.0, "drops": 0, "drop_rate": 0.0,
         "mean_steps": 100, "return": {"mean": -1.0, "std": 0.0}}
    it = {**m, "iteration": 34, "points": 1000, "model": {}, "demonstrations": {"episodes": 72, "repeat": 4, "share": 0.11},
          "own_turn": {"windows": 50, "turn_r2": 0.25}}
    r = {"config": asdict(BaodingConfig.from_preset("tiny")), "planner": {"horizon": 7, "samples": 16, "gamma": 20, "beta": 0.6, "ensemble": 3,
                                              "hidden": [16], "init_mean": "hold", "plan_ms_p50": 1, "plan_ms_p99": 2,
                                              "plans": 3},
         "resets": {"requested": 0, "completed": 0, "failed": 0, "mean_duration_s": 0.0}, "rig": "hand_sim",
         "wall_s": 1.0, "random_policy": m, "hold_policy": m, "iterations": [it], "recordings": [], "model": "m.pt",
         "demonstrations": {"text": "demonstrations: 72 episodes from D, repeated 4×"}}
    md = report_markdown(r)
    assert "Note: demonstrations: 72 episodes from D, repeated 4×" in md and "not the thesis' method" in md
    assert "PDDM iteration 34 (1000 points, +demo 11 %)" in md and "own turn R² 0.25" in md
    del r["demonstrations"], it["demonstrations"]
    assert "demonstrations" not in report_markdown(r) and "+demo" not in report_markdown(r)


def test_own_turn_probe_without_a_window_in_the_palm():
    """An iteration whose episodes all dropped at once has no window to score: no R² (not 1)."""
    f = BaodingFeatures(NAMES, 0.1)
    s = np.zeros((12, len(NAMES)))  # both balls at the origin: not in the palm
    ep = f.episode(Episode(states=s, actions=np.zeros((11, 20)), times=np.arange(12) * 0.1, name="e"))
    from hilstack.learning.baoding import load_baoding_task

    got = probe_turn(_Still(), [ep], load_baoding_task(), 7)
    assert got["windows"] == 0 and np.isnan(got["turn_r2"])
    assert probe_turn(_Still(), [], load_baoding_task(), 7) == {"windows": 0}


class _Still:
    def predict(self, s, a):
        return s[None]


def test_iterations_table_lists_each_runs_iterations_from_the_first_asked(tmp_path):
    from hilstack.tools.demo_baoding import iterations_table, main

    def it(i, s90, demo=None, own=None):
        return {"iteration": i, "points": 100 * i, "success_90": s90, "success_180": 0.0, "mean_rotation_deg": 20.0 + i,
                "drops": 1, "episodes": 30, "mean_steps": 99.0, "weights": {"plans": 5, "ess_mean": 40.0, "ess_frac_mean": 0.06},
                "timing": {"loadavg": ["9.1", "8", "7"]}, "wall_s": {"iteration": 400.0},
                **({"demonstrations": {"share": demo}} if demo else {}), **({"own_turn": own} if own else {})}

    held = {**it(34, 0.1, 0.117, {"windows": 80, "turn_r2": 0.31, "turn_true_std_deg": 14.38}), "held_90": 0.0333}
    for name, rows in (("mix", [it(33, 0.0), held]),
                       ("control", [it(33, 0.0), it(34, 0.0, None, {"windows": 0})])):
        (tmp_path / name).mkdir()
        (tmp_path / name / "report.json").write_text(json.dumps({"iterations": rows}))
    md = iterations_table({"MIX": tmp_path / "mix", "CONTROL": tmp_path / "control"}, first=34)
    lines = md.splitlines()
    assert len(lines) == 4 and "| 33 |" not in md
    assert lines[2] == "| MIX | 34 | 3400 | 12 % | 10 % | 3 % | 0 % | +54.0 | 1/30 | 99 | 0.31 (14.4°, 80) | 40.0 (6 %) | 400 (9.1) |"
    # a report from before held_90: a dash in its column
    assert lines[3].startswith("| CONTROL | 34 | 3400 | – | 0 % | – | 0 % |") and "| – |" in lines[3]
    with pytest.raises(SystemExit, match="no report"):
        main(["table", f"x={tmp_path / 'none'}"])
    with pytest.raises(SystemExit):  # a rise limit only means something when scoring again
        main(["table", f"x={tmp_path / 'mix'}", "--rise-limit", "0.02"])
    # the same runs as one plot of their turns against the points (what --full writes for its seeds)
    main(["plot-seeds", str(tmp_path / "seeds.png"), f"MIX={tmp_path / 'mix'}", f"CONTROL={tmp_path / 'control'}"])
    assert (tmp_path / "seeds.png").stat().st_size > 0
    with pytest.raises(SystemExit):
        main(["plot-seeds", str(tmp_path / "x.png"), str(tmp_path / "mix")])  # no LABEL=


def test_targets_by_the_clock_from_the_command_line(tmp_path, monkeypatch):
    """``--targets clock`` runs the reference code's targets (no lead limit), ``lead`` (the default)
    ours; a bad value, or ``--targets`` on another demo, is refused in one line."""
    from dataclasses import replace

    from typer.testing import CliRunner

    import hilstack.tools.demo_baoding as demo
    from hilstack.learning.baoding import load_baoding_task
    from hilstack.tools.cli import app

    got: list[dict] = []

    def fake_run(out, preset, seed, resume, rig, **overrides):
        got.append(overrides)
        raise ValueError("stopped before the rig")

    monkeypatch.setattr(demo, "run_baoding_demo", fake_run)
    for arg in ("clock", "lead", None):
        r = CliRunner().invoke(app, ["demo", "baoding", "--quick", "--out", str(tmp_path / "o")]
                               + ([] if arg is None else ["--targets", arg]))
        assert r.exit_code == 1 and "stopped before the rig" in r.output, r.output
    task = load_baoding_task()
    assert task.max_lead_rad is not None  # ours by default
    tasks = [replace(task, **demo.make_config("quick", 0, **o).task_overrides) for o in got]
    assert [t.max_lead_rad for t in tasks] == [None, task.max_lead_rad, task.max_lead_rad]
    r = CliRunner().invoke(app, ["demo", "baoding", "--quick", "--targets", "wall", "--out", str(tmp_path / "o")])
    assert r.exit_code != 0 and "--targets must be lead or clock, got 'wall'" in r.output, r.output
    r = CliRunner().invoke(app, ["demo", "roach", "--quick", "--targets", "clock", "--out", str(tmp_path / "r")])
    assert r.exit_code != 0 and "--targets/--hold-pose are for the baoding demo only" in r.output, r.output
    assert not (tmp_path / "r").exists()
