"""VelociRoACH sim speed: how much faster than real time the lockstep backend runs.

The workload is what data collection does: a random-action loop through the driver
contract (``read → write → tick`` at 10 Hz, each tick = 100 firmware ticks + 100 MuJoCo
steps of 1 ms), on one core. The peer is raw ``mujoco.mj_step`` on the same model with a
constant motor voltage (no Python per physics step: one ``mj_step(nstep=100)`` call per
control period): the ceiling the backend's Python firmware/motor loop is measured against.
The two take turns in blocks of one robot second (as ``hil bench bus`` does), so load from
other work on the machine hits both alike.

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


def run_bench_sim(seconds_of_robot_time: float = 60.0, terrain: str = "carpet", seed: int = 0,
                  profile: bool = False, block_s: float = 1.0) -> dict:
    """Run the benchmark; returns realtime factors, wall and robot seconds, steps per second.

    The contract loop and the raw peer (a second backend instance's model and data, so
    neither disturbs the other's state) take turns in blocks of ``block_s`` robot seconds, so
    a change of load on the machine hits each alike; ``ratio`` is backend / raw realtime
    factor over the whole run, ``ratio_p50`` the median of the per-block ratios."""
    import mujoco

    from hilstack.drivers.velociroach.config import VelociRoachParams
    from hilstack.sim_backends.velociroach.backend import VelociRoachSim

    cores = _one_core()

    def make() -> VelociRoachSim:
        s = VelociRoachSim(VelociRoachParams(sim={"terrain": terrain, "seed": seed}))
        s.configure()
        s.activate()
        return s

    sim, peer = make(), make()
    rng = np.random.default_rng(seed)
    hi = sim.spec.action.high
    period = sim.spec.period_s
    n_ticks = max(1, round(seconds_of_robot_time / period))
    per_block = max(1, round(block_s / period))
    m, d = peer.model, peer.data
    d.ctrl[:] = 2.5
    raw_chunk = max(1, round(period / m.opt.timestep))  # one control period of raw steps per call

    def contract(k: int) -> None:
        for _ in range(k):
            sim.read()
            sim.write(rng.uniform(-hi, hi))
            sim.tick()

    def raw(k: int) -> None:
        # motors at a fixed voltage, no Python per physics step; the same terrain wrap per period
        for _ in range(k):
            mujoco.mj_step(m, d, nstep=raw_chunk)
            peer._wrap()

    prof_text = None
    if profile:
        import cProfile
        import io
        import pstats

        pr = cProfile.Profile()
        pr.runcall(contract, per_block)
        buf = io.StringIO()
        pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(8)
        prof_text = buf.getvalue()
    contract(1)  # warm-up (first calls allocate)
    raw(1)
    t_robot0 = sim.sim_time_s
    wall = raw_wall = 0.0
    ratios = []
    done = 0
    while done < n_ticks:
        k = min(per_block, n_ticks - done)
        t0 = time.perf_counter()
        contract(k)
        t1 = time.perf_counter()
        raw(k)
        t2 = time.perf_counter()
        wall += t1 - t0
        raw_wall += t2 - t1
        ratios.append((t2 - t1) / (t1 - t0))
        done += k
    robot_s = sim.sim_time_s - t_robot0
    steps = round(robot_s / sim.sim.physics_dt_s)
    raw_robot_s = n_ticks * raw_chunk * m.opt.timestep
    sim.cleanup()
    peer.cleanup()
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
    (tests/test_sim_batch.py). The VelociRoACH does not qualify: its firmware PID runs in
    Python every 1 ms tick."""
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
