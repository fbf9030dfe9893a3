"""Run a command; print (and write to OUT.json) its wall time, the CPU seconds of its whole process
tree and the machine's 1-minute load average during it (docs/scaling.md's loaded measurements).

    python scripts/cpu_meter.py OUT.json hil bench calibrate --seeds 2 --ray local --workers 2

The tree is polled every 0.2 s; each descendant (for Ray: its GCS, raylet and workers) counts with
the last user + system time seen, so a process living less than 0.2 s may be missed. psutil (dev extra).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import psutil


def main(out: str, cmd: list[str]) -> dict:
    t0 = time.perf_counter()
    loads = [os.getloadavg()[0]]
    p = subprocess.Popen(cmd)
    root = psutil.Process(p.pid)
    seen: dict[tuple[int, float], float] = {}
    while p.poll() is None:
        try:
            procs = [root, *root.children(recursive=True)]
        except psutil.NoSuchProcess:
            procs = []
        for q in procs:
            try:
                c = q.cpu_times()
                seen[(q.pid, q.create_time())] = c.user + c.system
            except psutil.Error:
                pass
        loads.append(os.getloadavg()[0])
        time.sleep(0.2)
    rec = {"cmd": cmd, "rc": p.returncode, "wall_s": time.perf_counter() - t0, "cpu_s": sum(seen.values()),
           "processes": len(seen), "load_1min": [min(loads), max(loads)]}
    print(json.dumps(rec))
    with open(out, "w") as f:
        json.dump(rec, f)
    return rec


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2:])["rc"])
