"""Run a sweep's tasks (seed x condition x method) serially in-process or as Ray Core tasks.

A :class:`Task` names a module-level function, its keyword arguments and the resources it
declares (``num_cpus``; ``threads``, pinned inside the task with ``torch.set_num_threads`` and the
BLAS thread variables). :func:`run_sweep` runs the tasks that have no result yet and writes
each result as it finishes to ``OUT/tasks/<key>.json`` (written by the driver, so on a cluster
the results land on the machine that started the sweep); a stopped sweep re-run does only
what is missing. A failed task leaves ``OUT/tasks/<key>.failed.json`` with its log tail and is
run again next time.

Executors: ``None`` (the default): serial, in this process, nothing else changes; ``"local"``:
a local Ray runtime with ``workers`` CPUs; any other string: the address of a running Ray
cluster (``ray start --head`` printed it; docs/scaling.md). Ray is the ``cluster`` extra.
The sweep's record (``OUT/sweep.json``) names the executor, Ray's version, the workers and the
wall time.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import sys
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

LOG_TAIL_LINES = 20
_KEY = re.compile(r"^[A-Za-z0-9_.=-]+$")


@dataclass(frozen=True)
class Task:
    """One unit of a sweep: ``fn(**kwargs)`` returning a JSON-serializable result."""

    key: str
    fn: Callable[..., Any]
    kwargs: dict[str, Any] = field(default_factory=dict)
    num_cpus: float = 1.0
    threads: int = 1

    def __post_init__(self) -> None:
        if not _KEY.match(self.key):
            raise ValueError(f"task key {self.key!r}: use letters, digits and _ . = - only (it names a file)")
        if not self.num_cpus > 0 or self.threads < 1:
            raise ValueError(f"task {self.key}: num_cpus must be > 0 and threads >= 1")


_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


@contextlib.contextmanager
def _pinned_threads(threads: int):
    """``threads`` for torch and BLAS inside the block; the process's own settings after it."""
    before = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update({v: str(threads) for v in _THREAD_VARS})
    try:
        import torch
    except ImportError:  # a task without torch needs no pinning beyond the variables
        torch = None
    torch_before = torch.get_num_threads() if torch else None
    if torch:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        for v, val in before.items():
            if val is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = val
        if torch:
            torch.set_num_threads(torch_before)


class _Tee(io.TextIOBase):
    """Keeps what a task prints (for its log tail) and passes it on when ``echo``."""

    def __init__(self, echo: io.TextIOBase | None) -> None:
        self.buf = io.StringIO()
        self.echo = echo

    def write(self, s: str) -> int:
        self.buf.write(s)
        if self.echo is not None:
            self.echo.write(s)
        return len(s)

    def tail(self, n: int = LOG_TAIL_LINES) -> list[str]:
        return self.buf.getvalue().splitlines()[-n:]


def execute(fn: Callable[..., Any], kwargs: dict[str, Any], threads: int, echo: bool = False) -> dict[str, Any]:
    """Run one task where it is (in this process or a Ray worker): its outcome, never an exception."""
    tee = _Tee(sys.stdout if echo else None)
    t0 = time.perf_counter()
    try:
        with _pinned_threads(threads), contextlib.redirect_stdout(tee), contextlib.redirect_stderr(tee):
            result = fn(**kwargs)
        json.dumps(result, default=str)  # a result that cannot be written is the task's failure, said here
        return {"ok": True, "result": result, "elapsed_s": time.perf_counter() - t0, "host": os.uname().nodename}
    except Exception:  # noqa: BLE001 - any task failure is reported, the sweep goes on
        return {"ok": False, "error": traceback.format_exc(),
                "log_tail": tee.tail(), "elapsed_s": time.perf_counter() - t0, "host": os.uname().nodename}


def require_ray():
    try:
        import ray
    except ImportError:
        from hilstack.tools.common import UserError

        raise UserError("--ray needs Ray: install hilstack[cluster]") from None
    return ray


def _write(path: Path, obj: Any) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=str))
    tmp.replace(path)  # atomic: a stopped sweep never leaves half a result


class _Progress:
    def __init__(self, total: int, skipped: int, workers: int, log: Callable[[str], Any]) -> None:
        self.total, self.skipped, self.workers, self.log = total, skipped, workers, log
        self.done = self.failed = 0
        self.t0 = time.perf_counter()

    def line(self, pending: int, last: str) -> str:
        """``pending``: submitted and not finished; at most ``workers`` of them run, the rest wait."""
        running = min(pending, self.workers)
        finished = self.done + self.failed
        left = self.total - self.skipped - finished
        elapsed = time.perf_counter() - self.t0
        eta = f"{elapsed / finished * left:.0f} s" if finished else "?"
        return (f"sweep: {self.skipped + self.done}/{self.total} done ({self.skipped} from before), "
                f"{running} running, {pending - running} queued, {self.failed} failed, ETA {eta} [{last}]")


def run_sweep(tasks: Iterable[Task], out: str | Path, executor: str | None = None, workers: int | None = None,
              log: Callable[[str], Any] = print,
              on_result: Callable[[str, Any], Any] | None = None) -> dict[str, Any]:
    """Run the ``tasks`` missing under ``out`` (``on_result(key, result)`` as each succeeds); returns ``{"results": {key: result}, "failed": {key:
    outcome}, "sweep": record}`` with the results of every task done so far (earlier runs included)."""
    tasks = list(tasks)
    keys = [t.key for t in tasks]
    if len(set(keys)) != len(keys):
        raise ValueError(f"duplicate task keys: {sorted({k for k in keys if keys.count(k) > 1})}")
    out = Path(out)
    tdir = out / "tasks"
    tdir.mkdir(parents=True, exist_ok=True)
    todo = [t for t in tasks if not (tdir / f"{t.key}.json").exists()]
    record: dict[str, Any] = {"executor": "serial" if executor is None else "ray", "tasks": len(tasks),
                              "resumed": len(tasks) - len(todo)}
    failed: dict[str, Any] = {}
    t0 = time.perf_counter()

    def finish(task: Task, outcome: dict[str, Any], prog: _Progress, pending: int) -> None:
        stale = tdir / f"{task.key}.failed.json"
        if outcome["ok"]:
            _write(tdir / f"{task.key}.json", {"key": task.key, "kwargs": task.kwargs, **outcome})
            stale.unlink(missing_ok=True)
            prog.done += 1
            if on_result is not None:
                on_result(task.key, json.loads(json.dumps(outcome["result"], default=str)))
        else:
            _write(stale, {"key": task.key, "kwargs": task.kwargs, **outcome})
            failed[task.key] = outcome
            prog.failed += 1
            log(f"task {task.key} failed on {outcome['host']}:\n" + "\n".join(
                f"  | {ln}" for ln in outcome["log_tail"] + outcome["error"].rstrip().splitlines()[-3:]))
        log(prog.line(pending, task.key))

    if executor is None:
        record["workers"] = 1
        prog = _Progress(len(tasks), record["resumed"], 1, log)
        for i, task in enumerate(todo):
            finish(task, execute(task.fn, task.kwargs, task.threads, echo=True), prog, len(todo) - i - 1)
    else:
        ray = require_ray()
        started_here = not ray.is_initialized()
        if started_here:
            if executor == "local":
                ray.init(num_cpus=workers or os.cpu_count(), include_dashboard=False, log_to_driver=False,
                         configure_logging=False)
            else:
                ray.init(address=executor, log_to_driver=False, configure_logging=False)
        try:
            record.update(ray_version=ray.__version__, address=executor,
                          workers=int(ray.cluster_resources().get("CPU", 0)),
                          nodes=len([n for n in ray.nodes() if n.get("Alive")]))
            prog = _Progress(len(tasks), record["resumed"], max(1, record["workers"]), log)
            remote = ray.remote(execute)
            pending = {remote.options(num_cpus=t.num_cpus).remote(t.fn, t.kwargs, t.threads): t for t in todo}
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                task = pending.pop(ready[0])
                finish(task, ray.get(ready[0]), prog, len(pending))
        finally:
            if started_here:
                ray.shutdown()
    record["wall_s"] = time.perf_counter() - t0
    record["failed"] = len(failed)
    rec_path = out / "sweep.json"
    if rec_path.exists():  # a resumed sweep: the earlier runs' records (their wall times) are kept
        try:
            before = json.loads(rec_path.read_text())
        except (OSError, ValueError):
            before = {}
        record["earlier_runs"] = [*before.pop("earlier_runs", []), before] if before else []
    _write(rec_path, record)
    results = {}
    for k in keys:
        p = tdir / f"{k}.json"
        if p.exists():
            results[k] = json.loads(p.read_text())["result"]
    return {"results": results, "failed": failed, "sweep": record}


def executor_from(ray: str | None) -> str | None:
    """The executor for a command's ``--ray`` value (None: serial; ``local``: a local runtime; else an address)."""
    if ray is not None and not ray.strip():
        from hilstack.tools.common import UserError

        raise UserError("--ray: give 'local' or a Ray cluster's address (host:6379)")
    return ray
