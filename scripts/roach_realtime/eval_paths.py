"""MPC (a saved model) and the untuned differential drive on paths of a rig, through the
demo's own MbrlRun.run_paths (planner fitted to the period on wall-clock rigs).

usage: eval_paths.py RIG MODEL.pt SPEED PATH[,PATH...] [mpc,dd] [OUT_DIR]
"""

import json
import sys
import time
from pathlib import Path

import torch

from hilstack.configs.schema import BusConfig
from hilstack.learning.frames import load_dynamics
from hilstack.learning.mbrl import MbrlConfig, MbrlRun
from tests.helpers import free_port

torch.set_num_threads(1)
rig, model_path, speed, paths = sys.argv[1], sys.argv[2], float(sys.argv[3]), tuple(sys.argv[4].split(","))
which = sys.argv[5].split(",") if len(sys.argv) > 5 else ["mpc", "dd"]
out = Path(sys.argv[6]) if len(sys.argv) > 6 else Path("/tmp/roach_realtime_eval")
run = MbrlRun(MbrlConfig.from_preset("quick", rig=rig, progress=False), out, BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}"))
model = load_dynamics(model_path)
t0 = time.monotonic()
res = {}
with run.session():
    for w in which:
        r = run.run_paths(run.mpc_for(model) if w == "mpc" else run.baseline_for(None), speed, paths=paths)
        res[w] = r
        for p, m in r.items():
            print(f"{w:4s} {p:9s} speed {speed} completed {m['completed']!s:5s} progress {m['progress_m']:.2f} m "
                  f"time {m['time_s']:.1f}/{m['time_limit_s']:.1f} s cost/m {m['cost_per_m']:.1f} end {m.get('end')!r} "
                  f"late {m.get('late_plans')} plan p50/p99 {m['plan_ms_p50']:.0f}/{m['plan_ms_p99']:.0f} ms "
                  f"steps {m['steps']}", flush=True)
print(f"wall {time.monotonic() - t0:.0f} s planner_fit {getattr(run, 'planner_fit', None)} "
      f"delay {getattr(run, 'command_delay', None)}")
(out / "eval.json").write_text(json.dumps(
    {w: {p: {k: v for k, v in m.items() if k not in ("xy", "waypoints")} for p, m in r.items()} for w, r in res.items()},
    indent=1, default=str))
