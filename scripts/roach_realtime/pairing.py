"""Which recorded command explains the crank velocity at the next state?

learning/recordings.py pairs (s_t, s_{t+1}.action, s_{t+1}); on a correct recording the
crank velocity at t+1 matches s_{t+1}.action (the command held during that period).

usage: pairing.py RECORDING.mcap
"""

import sys

import numpy as np

from hilstack.bus.recording import iter_messages
from hilstack.bus.schemas import RobotState
from hilstack.drivers.velociroach.config import STATE_NAMES

path = sys.argv[1]
by_ep: dict[int, list[RobotState]] = {}
for rm in iter_messages(path):
    m = rm.msg
    if isinstance(m, RobotState) and m.state and m.action and m.ok:
        by_ep.setdefault(m.episode, []).append(m)
il = STATE_NAMES.index("crank_vel_l")
err_next, err_before, dts = [], [], []
for ms in by_ep.values():
    ms.sort(key=lambda m: m.seq)
    for a, b in zip(ms[:-1], ms[1:], strict=True):
        if b.seq != a.seq + 1:
            continue
        v = np.array(b.state[il:il + 2])
        err_next.append(np.abs(v - np.array(b.action)).mean())
        err_before.append(np.abs(v - np.array(a.action)).mean())
        dts.append(b.t_s - a.t_s)
print(path)
print(f"transitions {len(err_next)}; state period p50 {np.median(dts) * 1e3:.1f} ms p99 {np.percentile(dts, 99) * 1e3:.1f} ms")
print(f"|crank_vel[t+1] - action(states[t+1])| mean {np.mean(err_next):.2f} rev/s (recordings.py pairing)")
print(f"|crank_vel[t+1] - action(states[t])|   mean {np.mean(err_before):.2f} rev/s")
