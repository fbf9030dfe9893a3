"""`hil calibrate --model <robot config>` with a smaller search (docs/calibration.md, "Results on the
emulated rigs"): the candidates, the fit blocks and the rounds given, for a slow machine.

    nice -n 10 python scripts/calib_mjcf_run.py REC.mcap configs/robots/shadow_hand.yaml OUT \\
        --candidates joint_frictionloss joint_damping input_delay --fit-blocks 4 --rounds 2

Prints the report's summary as one JSON line (and writes OUT/calibrated.xml, report.json, report.md).
"""

from __future__ import annotations

import argparse
import json


def main() -> None:
    from hilstack.calibration.mjcf_robot import CANDIDATES, run_mjcf_calibration

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("model")
    ap.add_argument("out")
    ap.add_argument("--candidates", nargs="+", default=list(CANDIDATES))
    ap.add_argument("--fit-blocks", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--current", action="store_true", help="fit and score the motor current too (WidowX)")
    ap.add_argument("--base", default=None, help="a previous calibration (directory or calibrated.xml) as the nominal")
    a = ap.parse_args()
    rep = run_mjcf_calibration(a.data, a.model, a.out, seed=a.seed, force=a.force, candidates=tuple(a.candidates),
                               max_rounds=a.rounds, max_fit_blocks=a.fit_blocks, base=a.base,
                               current=a.current)
    print(json.dumps({k: rep[k] for k in ("effects", "values", "intervals_95", "unidentifiable", "pruned",
                                          "before_multi_step_nrmse", "after_multi_step_nrmse", "ratio", "samples",
                                          "wall_s", "cpu_s", "outputs")} |
                     {k: rep[k] for k in ("before_position_nrmse", "after_position_nrmse") if k in rep}), flush=True)


if __name__ == "__main__":
    main()
