"""The sweep executor (tools/sweep.py): serial == Ray for the same seeds, resume, failures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hilstack.tools.sweep import Task, run_sweep


def tiny_fit(seed: int, calls_dir: str, threads_seen: bool = True) -> dict:
    """A seeded least-squares fit by gradient descent in torch; leaves a mark per call."""
    import os

    import torch

    Path(calls_dir, f"{seed}-{os.getpid()}-{len(os.listdir(calls_dir))}").touch()
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(64, 3, generator=g)
    y = x @ torch.tensor([1.0, -2.0, 0.5]) + 0.1 * torch.randn(64, generator=g)
    w = torch.zeros(3, requires_grad=True)
    opt = torch.optim.SGD([w], lr=0.1)
    for _ in range(50):
        opt.zero_grad()
        loss = ((x @ w - y) ** 2).mean()
        loss.backward()
        opt.step()
    print(f"seed {seed}: loss {loss.item():.4f}")
    return {"seed": seed, "w": w.detach().tolist(), "loss": loss.item(), "threads": torch.get_num_threads()}


def broken(seed: int) -> dict:
    print(f"about to fail on seed {seed}")
    raise ValueError(f"bad seed {seed}")


def _tasks(calls: Path, threads: int = 1) -> list[Task]:
    return [Task(f"fit-seed{s}", tiny_fit, {"seed": s, "calls_dir": str(calls)}, threads=threads) for s in (0, 1)]


def test_serial_resume_and_failure(tmp_path):
    calls = tmp_path / "calls"
    calls.mkdir()
    lines: list[str] = []
    r = run_sweep(_tasks(calls), tmp_path / "out", log=lines.append)
    assert set(r["results"]) == {"fit-seed0", "fit-seed1"} and r["sweep"]["executor"] == "serial"
    assert r["results"]["fit-seed0"]["w"] != r["results"]["fit-seed1"]["w"]
    assert abs(r["results"]["fit-seed0"]["w"][1] + 2.0) < 0.1  # the fit worked
    assert any("2/2 done" in ln for ln in lines)
    # resume: one result lost; the re-run does only that one and gives the same result
    kept = (tmp_path / "out/tasks/fit-seed0.json").read_text()
    (tmp_path / "out/tasks/fit-seed1.json").unlink()
    r2 = run_sweep(_tasks(calls), tmp_path / "out", log=lines.append)
    assert len(list(calls.iterdir())) == 3
    assert r2["sweep"]["resumed"] == 1 and (tmp_path / "out/tasks/fit-seed0.json").read_text() == kept
    rec = json.loads((tmp_path / "out/sweep.json").read_text())  # the first run's record is kept beside
    assert [e["resumed"] for e in rec["earlier_runs"]] == [0] and rec["earlier_runs"][0]["wall_s"] > 0
    assert r2["results"] == r["results"]
    # a failing task: reported with its log tail, the others still run, re-run next time
    bad = [Task("bad-seed3", broken, {"seed": 3}), *_tasks(calls)]
    lines.clear()
    r3 = run_sweep(bad, tmp_path / "out", log=lines.append)
    assert set(r3["failed"]) == {"bad-seed3"} and r3["sweep"]["failed"] == 1
    text = "\n".join(lines)
    assert "about to fail on seed 3" in text and "bad seed 3" in text
    rec = json.loads((tmp_path / "out/tasks/bad-seed3.failed.json").read_text())
    assert rec["log_tail"] == ["about to fail on seed 3"]
    assert len(list(calls.iterdir())) == 3  # the finished tasks did not run again


def test_bad_tasks_are_named():
    with pytest.raises(ValueError, match="task key"):
        Task("a/b", tiny_fit)
    with pytest.raises(ValueError, match="duplicate task keys"):
        run_sweep([Task("a", tiny_fit), Task("a", tiny_fit)], "unused")


@pytest.fixture
def local_ray():
    """One local Ray runtime (2 CPUs) for the test: starting one takes seconds, so both sweeps share it
    (run_sweep joins a runtime already started in its process and leaves it running)."""
    ray = pytest.importorskip("ray", reason="Ray is the cluster extra (pip install hilstack[cluster])")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


def test_ray_gives_the_serial_results_and_resumes(tmp_path, local_ray):
    calls = tmp_path / "calls"
    calls.mkdir()
    serial = run_sweep(_tasks(calls, threads=2), tmp_path / "serial", log=lambda s: None)
    lines: list[str] = []
    par = run_sweep(_tasks(calls, threads=2), tmp_path / "ray", executor="local", workers=2, log=lines.append)
    assert par["results"] == serial["results"]
    assert all(v["threads"] == 2 for v in par["results"].values())  # pinned inside the task
    sw = json.loads((tmp_path / "ray/sweep.json").read_text())
    assert sw["executor"] == "ray" and sw["workers"] == 2 and sw["ray_version"] and sw["wall_s"] > 0
    assert len(list(calls.iterdir())) == 4
    # resume on Ray: only the missing task runs
    (tmp_path / "ray/tasks/fit-seed0.json").unlink()
    again = run_sweep(_tasks(calls, threads=2), tmp_path / "ray", executor="local", workers=2, log=lines.append)
    assert again["sweep"]["resumed"] == 1 and again["results"] == serial["results"]
    assert len(list(calls.iterdir())) == 5
