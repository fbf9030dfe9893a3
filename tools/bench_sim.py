"""VelociRoACH sim speed: how much faster than real time the lockstep backend runs.

The workload is what data collection does: a random-action loop through the driver
contract (``read → write → tick`` at 10 Hz, each tick = 100 firmware ticks + 100 MuJoCo
steps of 1 ms), on one core. The peer is raw ``mujoco.mj_step`` on the same model with a
constant motor voltage (no Python in the loop): the ceiling the backend's Python
firmware/motor loop is measured against.

Use ``hil bench sim`` or ``python -m hilstack.tools.bench_sim [seconds]``; ``profile=True`` adds
the top cProfile entries (cumulative) of the contract loop.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np


def _one_core() -> None:
    # the benchmark claims "one core": pin the process where the OS allows it
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass


def run_bench_sim(seconds_of_robot_time: float = 60.0, terrain: str = "carpet", seed: int = 0,
                  profile: bool = False) -> dict:
    """Run the benchmark; returns realtime factors, wall and robot seconds, steps per second."""
    import mujoco

    from hilstack.drivers.velociroach.config import VelociRoachParams
    from hilstack.sim_backends.velociroach.backend import VelociRoachSim

    _one_core()
    sim = VelociRoachSim(VelociRoachParams(sim={"terrain": terrain, "seed": seed}))
    sim.configure()
    sim.activate()
    rng = np.random.default_rng(seed)
    hi = sim.spec.action.high
    n_ticks = max(1, round(seconds_of_robot_time / sim.spec.period_s))

    def loop() -> None:
        for _ in range(n_ticks):
            sim.read()
            sim.write(rng.uniform(-hi, hi))
            sim.tick()

    t_robot0 = sim.sim_time_s
    prof_text = None
    t0 = time.perf_counter()
    if profile:
        import cProfile
        import io
        import pstats

        pr = cProfile.Profile()
        pr.runcall(loop)
        wall = time.perf_counter() - t0
        buf = io.StringIO()
        pstats.Stats(pr, stream=buf).sort_stats("tottime").print_stats(8)
        prof_text = buf.getvalue()
    else:
        loop()
        wall = time.perf_counter() - t0
    robot_s = sim.sim_time_s - t_robot0
    steps = round(robot_s / sim.sim.physics_dt_s)

    # peer: raw mj_step on the same model, motors at a fixed voltage, no Python per step
    m, d = sim.model, sim.data
    sim.reset()
    d.ctrl[:] = 2.5
    n_raw = steps
    t0 = time.perf_counter()
    for k in range(0, n_raw, 100):  # 0.1 s chunks: keeps the robot on the (periodic) terrain
        mujoco.mj_step(m, d, nstep=min(100, n_raw - k))
        sim._wrap()
    raw_wall = time.perf_counter() - t0
    raw_robot_s = n_raw * m.opt.timestep
    sim.cleanup()
    out = {
        "realtime_factor": robot_s / wall,
        "robot_s": robot_s,
        "wall_s": wall,
        "steps_per_s": steps / wall,
        "control_ticks_per_s": n_ticks / wall,
        "peer_raw_realtime_factor": raw_robot_s / raw_wall,
        "peer_raw_steps_per_s": n_raw / raw_wall,
        "terrain": terrain,
        "physics_dt_s": float(m.opt.timestep),
        "mujoco": mujoco.__version__,
    }
    if prof_text is not None:
        out["profile"] = prof_text
    return out


if __name__ == "__main__":
    secs = float(sys.argv[1]) if len(sys.argv) > 1 else 60.0
    print(json.dumps(run_bench_sim(secs), indent=2))
