"""Does a Baoding seed repeat itself on the lockstep hand rig? The tiny preset N times with one
seed; per run, each recording's episode lengths, the final metrics and the driver's lockstep
timeouts; then ALL EQUAL or DIFFER (docs/baoding.md, "A seed repeats itself").

    PYTHONPATH=. .venv/bin/python scripts/baoding_repeat.py OUT_DIR [N=3] [SEED=0]
"""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path

from hilstack.learning.recordings import episodes_from_mcap
from hilstack.tools.demo_baoding import run_baoding_demo


def main(out: Path, n: int, seed: int) -> None:
    res = []
    for k in range(n):
        o = out / f"run{k}"
        t0 = time.time()
        rep = run_baoding_demo(o, preset="tiny", seed=seed, rig="hand_sim")
        lens = {Path(r).stem: [len(e) for e in episodes_from_mcap(r, "hand")] for r in rep["recordings"]}
        drv = (o / "logs/driver.log").read_text(errors="replace") if (o / "logs/driver.log").exists() else ""
        timeouts = re.findall(r"lockstep_timeouts=\d+", drv)
        final = {k2: rep["iterations"][-1][k2] for k2 in ("mean_rotation_deg", "mean_steps", "drops", "mean_return")}
        print(f"run{k}: {time.time() - t0:.1f} s, load {os.getloadavg()[0]:.1f}, episode lengths {lens}, "
              f"final {final}, {timeouts[-1:] or 'no stats'}", flush=True)
        res.append((lens, final, rep.get("random_policy"), rep.get("hold_policy")))
    print("ALL EQUAL" if all(r == res[0] for r in res) else "DIFFER")


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 3, int(sys.argv[3]) if len(sys.argv) > 3 else 0)
