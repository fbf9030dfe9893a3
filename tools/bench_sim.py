"""VelociRoACH sim speed: how much faster than real time the lockstep backend runs.

The workload is what data collection does: a random-action loop through the driver
contract (``read → write → tick`` at 10 Hz, each tick = 100 firmware ticks + 100 MuJoCo
steps of 1 ms), on one core. The peer is raw ``mujoco.mj_step`` on the same model with a
constant motor voltage (no Python per physics step: one ``mj_step(nstep=100)`` call per
control period): the ceiling the backend's firmware/motor loop is measured against. The
backend (its 1 kHz loop compiled when numba is installed), the same loop in Python and the
peer take turns in blocks of one robot second (as ``hil bench bus`` does), so load from
other work on the machine hits them alike; each part of a period is also timed on CPU time.

Use ``hil bench sim`` or ``python -m hilstack.tools.bench_sim [seconds]``; ``profile=True`` adds
the top cProfile entries (cumulative) of the contract loop.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def _one_core() -> set[int] | None:
    """Pin the process to one core where the OS allows it (the contract loop's claim is
    "one core"); returns the cores it had, for :func:`_restore_cores`."""
    try:
        before = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {min(before)})
        return before
    except (AttributeError, OSError):
        return None


def _restore_cores(cores: set[int] | None) -> None:
    if cores is not None:
        try:
            os.sched_setaffinity(0, cores)
        except OSError:
            pass


def _pct(xs: list[float]) -> dict[str, float]:
    """p50/p99 of per-period times [s], in µs."""
    a = np.asarray(xs) * 1e6
    return {"p50_us": float(np.percentile(a, 50)), "p99_us": float(np.percentile(a, 99))}


def run_bench_sim(seconds_of_robot_time: float = 60.0, terrain: str = "carpet", seed: int = 0,
                  profile: bool = False, block_s: float = 1.0) -> dict:
    """Run the benchmark; returns realtime factors, wall and robot seconds, steps per second.

    Three contestants take turns in blocks of ``block_s`` robot seconds, so a change of load
    on the machine hits each alike: the contract loop as the backend runs it (its 1 kHz loop
    compiled when numba is installed, ``compiled_loop``), the same loop with the 1 kHz loop
    in Python (a second instance given the same commands), and the raw peer (a third
    instance's model and data). ``ratio`` is backend / raw realtime factor over the whole run
    on the wall clock, ``ratio_p50`` the median of the per-block ratios. On a shared machine
    the wall clock counts time the process waits for a core, so ``cpu`` repeats the
    comparison on this thread's CPU time (``time.thread_time``), with each part of a control
    period (read, write, tick, raw) as p50/p99 in µs and ``ratio`` / ``ratio_python_loop``
    over the run."""
    import mujoco

    from hilstack.configs.extras import install_hint
    from hilstack.drivers.velociroach.config import VelociRoachParams
    from hilstack.sim_backends.velociroach.backend import VelociRoachSim

    cores = _one_core()

    def make(compiled: bool = True) -> VelociRoachSim:
        s = VelociRoachSim(VelociRoachParams(sim={"terrain": terrain, "seed": seed}))
        s.compiled_firmware = compiled
        s.configure()
        s.activate()
        return s

    sim, slow, peer = make(), make(compiled=False), make()
    compiled = sim._kernel() is not None
    rng = np.random.default_rng(seed)
    hi = sim.spec.action.high
    period = sim.spec.period_s
    n_ticks = max(1, round(seconds_of_robot_time / period))
    per_block = max(1, round(block_s / period))
    m, d = peer.model, peer.data
    d.ctrl[:] = 2.5
    raw_chunk = max(1, round(period / m.opt.timestep))  # one control period of raw steps per call
    cpu = time.thread_time
    parts: dict[str, list[float]] = {"read": [], "write": [], "tick": [], "tick_python_loop": [],
                                     "read_python_loop": [], "write_python_loop": [], "raw": []}

    def contract(s: VelociRoachSim, actions: list[np.ndarray], tag: str = "") -> None:
        r, w, t = parts["read" + tag], parts["write" + tag], parts["tick" + tag]
        for a in actions:
            t0 = cpu()
            s.read()
            t1 = cpu()
            s.write(a)
            t2 = cpu()
            s.tick()
            t3 = cpu()
            r.append(t1 - t0)
            w.append(t2 - t1)
            t.append(t3 - t2)

    def raw(k: int) -> None:
        # motors at a fixed voltage, no Python per physics step; the same terrain wrap per period
        for _ in range(k):
            t0 = cpu()
            mujoco.mj_step(m, d, nstep=raw_chunk)
            peer._wrap()
            parts["raw"].append(cpu() - t0)

    prof_text = None
    if profile:
        import cProfile
        import io
        import pstats

        pr = cProfile.Profile()
        pr.runcall(contract, sim, [rng.uniform(-hi, hi) for _ in range(per_block)])
        buf = io.StringIO()
        pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(8)
        prof_text = buf.getvalue()
    first = [rng.uniform(-hi, hi)]
    contract(sim, first)  # warm-up (first calls allocate; the compiled loop loads)
    contract(slow, first, "_python_loop")
    raw(1)
    for v in parts.values():
        v.clear()
    t_robot0 = sim.sim_time_s
    wall = raw_wall = 0.0
    ratios = []
    done = 0
    while done < n_ticks:
        k = min(per_block, n_ticks - done)
        actions = [rng.uniform(-hi, hi) for _ in range(k)]
        t0 = time.perf_counter()
        contract(sim, actions)
        t1 = time.perf_counter()
        raw(k)
        t2 = time.perf_counter()
        contract(slow, actions, "_python_loop")
        wall += t1 - t0
        raw_wall += t2 - t1
        ratios.append((t2 - t1) / (t1 - t0))
        done += k
    robot_s = sim.sim_time_s - t_robot0
    steps = round(robot_s / sim.sim.physics_dt_s)
    raw_robot_s = n_ticks * raw_chunk * m.opt.timestep
    for s in (sim, slow, peer):
        s.cleanup()
    raw_cpu = sum(parts["raw"])
    out = {
        "realtime_factor": robot_s / wall,
        "robot_s": robot_s,
        "wall_s": wall,
        "steps_per_s": steps / wall,
        "control_ticks_per_s": n_ticks / wall,
        "peer_raw_realtime_factor": raw_robot_s / raw_wall,
        "peer_raw_steps_per_s": n_ticks * raw_chunk / raw_wall,
        "ratio": (robot_s / wall) / (raw_robot_s / raw_wall),
        "ratio_p50": float(np.median(ratios)),
        "compiled_loop": compiled if compiled else f"no: numba is not installed ({install_hint('numba')})",
        "cpu": {
            "ratio": raw_cpu / sum(sum(parts[k]) for k in ("read", "write", "tick")),
            "ratio_python_loop": raw_cpu / sum(sum(parts[k + "_python_loop"]) for k in ("read", "write", "tick")),
            "per_period": {k: _pct(v) for k, v in parts.items()},
        },
        "blocks": len(ratios),
        "terrain": terrain,
        "physics_dt_s": float(m.opt.timestep),
        "mujoco": mujoco.__version__,
        "loadavg_1min": os.getloadavg()[0],
    }
    _restore_cores(cores)  # the batched rollouts may use both cores
    out["batch"] = run_bench_batch(seed=seed)
    if prof_text is not None:
        out["profile"] = prof_text
    return out


def run_bench_batch(batch: int = 64, steps: int = 100, seed: int = 0) -> dict:
    """Random-data collection on the point mass (the backend whose command goes straight to
    ``data.ctrl``): transitions per second through the contract loop (read, write, tick:
    serial, one rollout after another) vs ``mujoco.rollout`` on the same rate-bounded random
    commands (sim_backends/batch.py), on 1 and 2 threads. Both give the same states
    (tests/test_sim_batch.py). The VelociRoACH does not qualify: its firmware PID runs between
    the 1 ms physics steps (compiled or in Python), which ``mujoco.rollout`` has no place for."""
    from hilstack.sim_backends.batch import rate_bounded_walk
    from hilstack.sim_backends.pointmass import PointMassParams, PointMassSim

    sim = PointMassSim(PointMassParams())
    sim.configure()
    sim.activate()
    sp = sim.spec
    cmds = rate_bounded_walk(sp.action.low, sp.action.high, sp.action_rate_per_s * sp.period_s, batch, steps,
                             np.random.default_rng(seed))
    n_serial = max(1, batch // 8)  # a slice of the batch serially: the rate is per transition
    t0 = time.perf_counter()
    for b in range(n_serial):
        sim.reset()
        for k in range(steps):
            sim.read()
            sim.write(cmds[b, k])
            sim.tick()
    serial = n_serial * steps / (time.perf_counter() - t0)
    sim.reset()
    out = {"robot": "pointmass", "batch": batch, "steps": steps, "serial_samples_per_s": serial}
    for threads in (1, 2):
        t0 = time.perf_counter()
        sim.rollout_batch(cmds, threads=threads)
        rate = batch * steps / (time.perf_counter() - t0)
        out[f"rollout_{threads}thread_samples_per_s"] = rate
        out[f"rollout_{threads}thread_over_serial"] = rate / serial
    sim.cleanup()
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m hilstack.tools.bench_sim", description=__doc__.split("\n")[0])
    ap.add_argument("seconds", nargs="?", type=float, default=60.0, help="robot seconds to simulate (default 60)")
    ap.add_argument("--profile", action="store_true", help="add the top cProfile entries of the contract loop")
    a = ap.parse_args(argv)
    print(json.dumps(run_bench_sim(a.seconds, profile=a.profile), indent=2))


if __name__ == "__main__":
    main()
