"""Table 3.1 of the serial `MbrlRun.run()` (what `hil demo --full` runs) against the serial sweep
(`tools/demo_sweep.py`, what `--ray` distributes), on a tiny preset (that of tests/mbrl/test_demo_sweep.py).

    .venv/bin/python scripts/compare_full_vs_sweep.py OUT_DIR   # prints EQUAL or DIFF, then both cells
"""

import json
import sys
from pathlib import Path

from hilstack.configs.schema import BusConfig
from hilstack.learning.mbrl import MbrlConfig, MbrlRun
from hilstack.tools.bench_bus import free_port
from hilstack.tools.demo_sweep import run_full_on_sweep

TINY = dict(random_rollouts=2, rollout_steps=30, epochs=2, retrain_epochs=1, samples=32, speeds={"high_speed": 1.0},
            paths=("straight",), path_scale=0.2, time_limit_speed_mps=0.4, tune_paths=("right",),
            tune_path_scale=0.2, baseline_candidates=2, seeds=(0, 1), table_sizes=(2,), table_paths=("straight",),
            iterations=0, experiments=("table_3_1",), progress=False)


def main(out: Path) -> None:
    cfg = MbrlConfig.from_preset("full", **TINY)
    old = MbrlRun(cfg, out / "old", BusConfig(endpoint=f"tcp/127.0.0.1:{free_port()}")).run()
    new = run_full_on_sweep(cfg, out / "new", None, log=lambda s: None)
    a, b = old["table_3_1"], new["table_3_1"]
    print("EQUAL" if a == b else "DIFF")
    print(json.dumps(a["rows"]["2"]["paths"]["straight"]["cost"]), json.dumps(b["rows"]["2"]["paths"]["straight"]["cost"]))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
