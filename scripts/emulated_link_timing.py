"""The emulated WidowX rig's timing: host stamps against the emulator's physics clock
(docs/calibration.md, "Two-stage calibration"). Runs the `hil excite` excitation on the emulated rig
with the emulator's state file on (every 2 ms: wall clock, sim time, servo positions), then prints the
emulator's slip behind the wall clock, the per-period difference between stamped and simulated time,
the read/write timing, and how far each sample's stamp is from the physics time of its data (each
sample matched to the state-file line with the same joint positions). Each of those is given for the
host's stamp (``Observation.t_s``, ``RobotState.t_s``) and for the servos' own clock (the first joint's
Realtime Tick, unwrapped: ``Observation.device_t_s``, ``RobotState.device_t_s``).

    PYTHONPATH=. nice -n 10 python scripts/emulated_link_timing.py 30 0.05 /tmp/timing
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np


def record(dur: float, period: float, out: str) -> None:
    from hilstack.calibration.robot_rig import excitation_targets
    from hilstack.configs.schema import load_robot
    from hilstack.drivers.registry import make_driver
    from hilstack.sim_backends.widowx.backend import MID_POSE_RAD

    cfg = load_robot("widowx", backend="emulated")
    d = make_driver(cfg, backend="emulated", period_s=period, bus_name="timing", telemetry_stale_s=5 * period,
                    emulator={"start_holding": dict(MID_POSE_RAD), "state_file": out + ".state.jsonl",
                              "state_every_s": 0.002})
    mid = np.array(list(MID_POSE_RAD.values()))
    ref = excitation_targets(6, dur, 0)
    rows = []
    with d:
        t_r0 = time.monotonic()
        obs = d.read()
        t_r1 = time.monotonic()
        t0 = obs.t_s
        for _ in range(int(dur / period)):
            q_off, dq = ref(obs.t_s - t0)
            u = dq + 2.0 * (mid + q_off - np.asarray(obs.state[:6]))
            tw0 = time.monotonic()
            d.write(u)
            rows.append([t_r0, t_r1, obs.t_s, tw0, time.monotonic(), *obs.state[:6],
                         np.nan if obs.device_t_s is None else obs.device_t_s])
            d.tick()
            t_r0 = time.monotonic()
            obs = d.read()
            t_r1 = time.monotonic()
    np.save(out + ".host.npy", np.array(rows))


def analyse(out: str, block_samples: int = 40, look_back_s: float = 0.5) -> None:
    h = np.load(out + ".host.npy")
    st = [json.loads(line) for line in open(out + ".state.jsonl")]
    t = np.array([s["t"] for s in st])
    sim = np.array([s["sim_t"] for s in st])
    q = np.array([[s["servos"][str(i)][0] for i in (1, 2, 4, 6, 7, 8)] for s in st])
    lag = (t - t[0]) - (sim - sim[0])
    print(f"emulator behind the wall clock: p50 {np.median(lag) * 1e3:.1f} ms, max {lag.max() * 1e3:.1f} ms; "
          f"time given up over the run {lag[-1] * 1e3:.1f} ms")
    stamps = h[:, 2]
    ds_host, ds_sim = np.diff(stamps), np.diff(np.interp(stamps, t, sim))
    print(f"host periods p50 {np.median(ds_host) * 1e3:.1f} ms p99 {np.percentile(ds_host, 99) * 1e3:.1f} ms; "
          f"|simulated - stamped| per period p50 {np.median(abs(ds_sim - ds_host)) * 1e3:.2f} ms "
          f"p95 {np.percentile(abs(ds_sim - ds_host), 95) * 1e3:.2f} ms")
    print(f"read p50 {np.median(h[:, 1] - h[:, 0]) * 1e3:.2f} ms p95 {np.percentile(h[:, 1] - h[:, 0], 95) * 1e3:.2f} ms; "
          f"stamp to goal written p50 {np.median(h[:, 4] - h[:, 2]) * 1e3:.2f} ms "
          f"p95 {np.percentile(h[:, 4] - h[:, 2], 95) * 1e3:.2f} ms")
    phys = np.full(len(h), np.nan)  # the sim time of each sample's data: the state line with its positions
    for k in range(len(h)):
        # the state lines from look_back_s before the read was sent to just after it returned (under
        # load a reading's data can be older than the read: the emulator answers from its last tick)
        idx = np.flatnonzero((t >= h[k, 0] - look_back_s) & (t <= h[k, 1] + 0.005))
        if idx.size:
            phys[k] = sim[idx[np.argmin(np.abs(q[idx] - h[k, 5:11]).max(1))]]
    age = np.interp(stamps, t, sim) - phys
    print(f"data age at its stamp (sim time) p5/p50/p95 {np.round(np.nanpercentile(age, [5, 50, 95]) * 1e3, 1)} ms")

    def block_drift(clock):
        return [np.nanmax(np.abs((clock[a:a + block_samples] - clock[a]) - (phys[a:a + block_samples] - phys[a])))
                for a in range(0, len(h) - block_samples, block_samples)]

    drift = block_drift(stamps)
    print(f"per {block_samples}-sample block, max |stamped - physics time|: p50 {np.median(drift) * 1e3:.1f} ms, "
          f"max {np.max(drift) * 1e3:.1f} ms")
    if h.shape[1] > 11 and np.isfinite(h[:, 11]).any():
        dev = h[:, 11]
        # the servo clock's origin is the servo's: its error is the spread of (device - physics) time
        off = dev - phys
        err = off - np.nanmedian(off)
        print(f"device clock (Realtime Tick): |device - physics time| about its median offset p50/p95/max "
              f"{np.round(np.nanpercentile(np.abs(err), [50, 95, 100]) * 1e3, 2)} ms; per period "
              f"|d device - d physics| p50 {np.nanmedian(np.abs(np.diff(dev) - np.diff(phys))) * 1e3:.2f} ms "
              f"p95 {np.nanpercentile(np.abs(np.diff(dev) - np.diff(phys)), 95) * 1e3:.2f} ms")
        dd = block_drift(dev)
        print(f"per {block_samples}-sample block, max |device - physics time|: p50 {np.median(dd) * 1e3:.1f} ms, "
              f"max {np.max(dd) * 1e3:.1f} ms")


if __name__ == "__main__":
    if sys.argv[1] == "--analyse":  # an earlier run again: --analyse PERIOD OUT [LOOK_BACK_S]
        period, out = float(sys.argv[2]), sys.argv[3]
        analyse(out, int(round(2.0 / period)), *(float(a) for a in sys.argv[4:5]))
    else:
        dur, period, out = float(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
        record(dur, period, out)
        analyse(out, int(round(2.0 / period)))
