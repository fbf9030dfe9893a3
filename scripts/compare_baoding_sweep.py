"""`hil demo baoding --full`'s seeds serially and as Ray tasks (2 local workers) on the tiny preset,
then a Ray run stopped after its first finished seed and run again (docs/scaling.md).

    PYTHONPATH=. .venv/bin/python scripts/compare_baoding_sweep.py OUT_DIR [SEEDS]   # SEEDS: 0,1

Prints, per step, the wall time and the CPU seconds of this process and its children, then
EQUAL or DIFF for the summaries (every field but the file paths and the sweep record) of the serial
run against a second serial run (the control) and against Ray, with the per-seed final metrics;
for the resume, which seeds ran again.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import resource
import shutil
import sys
import time
from pathlib import Path

from hilstack.tools.demo_baoding import run_full

PRESET, RIG = "tiny", "hand_sim"


def _cpu_s() -> float:
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _comparable(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("runs", "sweep")}


def _run(out: Path, seeds: tuple[int, ...], ray: str | None) -> dict:
    return run_full(out, seeds=seeds, preset=PRESET, rig=RIG, ray=ray, workers=2)


def _stopped_run(out: Path, seeds: tuple[int, ...]) -> None:
    """A Ray sweep in its own process, killed (SIGKILL) as soon as its first seed's result is written,
    with every process it started (its local Ray runtime, the seeds' rigs), each by its pid: never
    `ray stop`, which would end every Ray runtime on the host."""
    import psutil

    p = mp.get_context("spawn").Process(target=_run, args=(out, seeds, "local"))
    p.start()
    tasks = out / "tasks"
    while p.is_alive() and not (tasks.is_dir() and any(tasks.glob("seed*.json"))):
        time.sleep(0.2)
    try:
        family = psutil.Process(p.pid).children(recursive=True)
    except psutil.NoSuchProcess:
        family = []
    p.kill()
    p.join()
    for q in family:
        try:
            q.kill()
        except psutil.NoSuchProcess:
            pass


def main(out: Path, seeds: tuple[int, ...]) -> None:
    if out.exists():
        shutil.rmtree(out)
    res: dict[str, dict] = {}
    for name, ray in (("serial", None), ("serial_again", None), ("ray", "local")):
        t0, c0, load0 = time.perf_counter(), _cpu_s(), os.getloadavg()[0]
        res[name] = _run(out / name, seeds, ray)
        print(f"{name}: wall {time.perf_counter() - t0:.1f} s, cpu {_cpu_s() - c0:.1f} s (this process and "
              f"waited-for children), load {load0:.0f}->{os.getloadavg()[0]:.0f}", flush=True)
    a, a2, b = (_comparable(res[k]) for k in ("serial", "serial_again", "ray"))
    # the control: the same seeds serially twice (a run that differs from itself cannot equal Ray's)
    print("serial vs serial again:", "EQUAL" if a == a2 else "DIFF", "| serial vs ray:", "EQUAL" if a == b else "DIFF")
    for k in ("final_mean_rotation_deg", "final_success_90", "final_mean_return", "final_drop_rate"):
        print(f"  {k}: serial {a[k]['per_seed']} again {a2[k]['per_seed']} ray {b[k]['per_seed']}")
    # the interruption: the first finished seed is kept, the re-run does only the rest
    stopped = out / "stopped"
    _stopped_run(stopped, seeds)
    kept = sorted(p.stem for p in (stopped / "tasks").glob("seed*.json") if not p.stem.endswith(".failed"))
    print("stopped run kept:", kept)
    again = _run(stopped, seeds, "local")
    sw = json.loads((stopped / "sweep.json").read_text())
    print(f"re-run: resumed {sw['resumed']} of {sw['tasks']} tasks, ran {sw['tasks'] - sw['resumed']};",
          "summary vs serial:", "EQUAL" if _comparable(again) == a else "DIFF")


if __name__ == "__main__":
    main(Path(sys.argv[1]), tuple(int(s) for s in (sys.argv[2] if len(sys.argv) > 2 else "0,1").split(",")))
