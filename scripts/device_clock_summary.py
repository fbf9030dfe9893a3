"""How a rig recording's readings fare on the host's clock and on the device's (docs/calibration.md,
"The emulated hand on its own clock").

    PYTHONPATH=. python scripts/device_clock_summary.py REC.mcap [configs/robots/shadow_hand.yaml]

Prints one JSON line: readings, not-ok and late readings (``RobotState.health["late"]``), readings
that repeat the previous device stamp, the host's and the device's periods (p50/p90/p99/max),
the episodes each clock gives (learning/recordings.py), and, with a robot config, the 2-s blocks
calibration cuts from the device-clock episodes (calibration/mjcf_robot.make_blocks: no block
spans a step longer than STALL_PERIODS median periods).
"""

from __future__ import annotations

import json
import sys

import numpy as np


def main() -> None:
    from hilstack.bus.recording import iter_messages
    from hilstack.bus.schemas import RobotState
    from hilstack.learning.recordings import episodes_from_mcap

    path = sys.argv[1]
    states = sorted((m.msg for m in iter_messages(path) if isinstance(m.msg, RobotState) and m.msg.state),
                    key=lambda m: m.seq)
    host = np.array([m.t_s for m in states])
    dev = np.array([m.device_t_s for m in states])
    ok = np.array([m.ok for m in states])
    late = np.array([bool(m.health.get("late")) for m in states])
    repeat = np.concatenate([[False], np.diff(dev) <= 0])

    def pct(x: np.ndarray) -> list[float]:
        return [round(float(v), 4) for v in np.percentile(x, [50, 90, 99, 100])] if x.size else []

    dstep = np.diff(dev[~repeat])
    out = {"readings": len(states), "not_ok": int((~ok).sum()), "late": int(late.sum()),
           "not_ok_not_late": int((~ok & ~late).sum()), "repeated_device_stamp": int(repeat.sum()),
           "host_period_p50_p90_p99_max": pct(np.diff(host)),
           "device_step_p50_p90_p99_max": pct(dstep),
           "host_span_s": round(float(host[-1] - host[0]), 3), "device_span_s": round(float(dev[-1] - dev[0]), 3)}
    for clock in ("host", "device"):
        eps = episodes_from_mcap(path, normalize=False, clock=clock)
        out[f"{clock}_episodes"] = len(eps)
        out[f"{clock}_episode_samples"] = sorted((len(e.times) for e in eps), reverse=True)[:12]
    if len(sys.argv) > 2:
        from hilstack.calibration.data import load_episodes
        from hilstack.calibration.mjcf_robot import STALL_PERIODS, bench_of, make_blocks

        bench = bench_of(sys.argv[2])
        eps = load_episodes(path, warn=lambda m: None)
        period = float(np.median(np.concatenate([np.diff(e.t_s) for e in eps])))
        out["stall_steps"] = int(sum((np.diff(e.t_s) > STALL_PERIODS * period).sum() for e in eps))
        out["median_period_s"] = round(period, 4)
        try:
            b = make_blocks(eps, bench, float(bench.spec.option.timestep))
            out["blocks"] = {"all": len(b.spans), "train": len(b.train), "test": len(b.test)}
        except Exception as e:  # too short: say so
            out["blocks"] = str(e)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
