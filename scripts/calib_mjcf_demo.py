"""The WidowX MJCF calibration, end to end (docs/calibration.md, "The robots' own MuJoCo models").

For each effect the bench's servos can carry (and none): record an excitation of the bench with
the effect (seed S, --train-s of sim time), run `hil calibrate --model configs/robots/widowx.yaml`
on it, record a NEW excitation (seed S+100, other sines), and score the nominal MJCF and the
calibrated one on every block of the new recording (open-loop, 2 s). Prints one JSON line per run.

    nice -n 10 python scripts/calib_mjcf_demo.py --seeds 0 1 --train-s 100 --new-s 60
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

EFFECTS = {
    "none": {},
    "friction": {"joint_friction_nm": 0.3},
    "damping": {"joint_damping_nm_s": 0.5},
    "delay": {"input_delay_s": 0.03},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--effects", nargs="+", default=list(EFFECTS), choices=list(EFFECTS))
    ap.add_argument("--train-s", type=float, default=100.0)
    ap.add_argument("--new-s", type=float, default=60.0)
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[1] / "configs/robots/widowx.yaml"))
    args = ap.parse_args()

    import torch  # noqa: F401 - nothing here uses it; keep the thread count of any import low
    torch.set_num_threads(1)
    from hilstack.calibration.data import load_episodes
    from hilstack.calibration.mjcf_robot import Bench, evaluate, run_mjcf_calibration
    from hilstack.calibration.robot_rig import record_excitation
    from hilstack.drivers.registry import make_driver

    for name in args.effects:
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as td:
                td = Path(td)
                t0 = time.perf_counter()
                record_excitation(td / "train.mcap", duration_s=args.train_s, seed=seed, effects=EFFECTS[name])
                record_excitation(td / "new.mcap", duration_s=args.new_s, seed=seed + 100, effects=EFFECTS[name])
                t_rec = time.perf_counter() - t0
                rep = run_mjcf_calibration(td / "train.mcap", args.config, td / "out", seed=seed, progress=False)
                new = load_episodes(td / "new.mcap")
                nominal = make_driver("widowx", backend="sim")
                calibrated = make_driver("widowx", backend="sim", sim={"mjcf": rep["calibrated_mjcf"]})
                before = evaluate(Bench.from_layout(nominal.calibration_bench(nominal.params)), new)
                after = evaluate(Bench.from_layout(calibrated.calibration_bench(calibrated.params)), new)
                print(json.dumps({"effect": name, "emulator": EFFECTS[name], "seed": seed, "named": rep["effects"],
                                  "values": {k: [round(x, 4) for x in v] for k, v in rep["values"].items()},
                                  "ci95": {k: [round(x, 4) for x in v] for k, v in rep["intervals_95"].items()},
                                  "unidentifiable": rep["unidentifiable"],
                                  "heldout_before": round(rep["before_multi_step_nrmse"], 5),
                                  "heldout_after": round(rep["after_multi_step_nrmse"], 5),
                                  "heldout_ratio": round(rep["ratio"], 3),
                                  "new_before": round(before, 5), "new_after": round(after, 5),
                                  "new_ratio": round(after / before, 3), "samples": rep["samples"],
                                  "calibrate_wall_s": rep["wall_s"], "calibrate_cpu_s": rep["cpu_s"],
                                  "record_wall_s": round(t_rec, 1)}), flush=True)


if __name__ == "__main__":
    main()
