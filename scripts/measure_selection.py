"""Before/after measurement of the axis model's effect search (docs/calibration.md, "Search over sets").

Runs the calibration on synthetic cases with two effects (and a clean one) over a few seeds, and on
the three real data sets in ../shared/data/real, and prints one JSON line per run: the effects named
with their evidence level, the verdict, the locked-test multi-step NRMSE before/after, CPU seconds.

    PYTHONPATH=. nice -n 10 python scripts/measure_selection.py --seeds 0,1,2 [--beam-width 3] [--real]
    PYTHONPATH=. nice -n 10 python scripts/measure_selection.py --cases "" --real --sets dfki --real-n-boot 20,25,40
    PYTHONPATH=. nice -n 10 python scripts/measure_selection.py --cases "" --real --sets dfki,dart,emps,emps10k \
        --equation-error-only      # the axis fit before its output-error refinement (the "before" of round 5)
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
import time
import warnings

import torch

CASES = {
    "delay+coulomb": {"delay": {}, "coulomb_friction": {}},
    "backlash": {"backlash": {}},
    "gravity+friction": {"gravity_load": {}, "coulomb_friction": {}},
    "friction+lag": {"coulomb_friction": {}, "actuator_lag": {}},
    "clean": {},
}


def _summary(name, seed, r, cpu):
    decisions = {d["name"]: [d["verdict"], d.get("stability")] for rd in r.get("rounds", [])
                 for d in rd.get("decisions", []) if d.get("stability") is not None}
    return {"case": name, "seed": seed, "n_boot": r["config"].get("n_boot"), "verdict": r["verdict"],
            "decisions": decisions,
            "effects": {e["name"]: e["evidence"]["level"] for e in r["effects"]},
            "findings": {f["name"]: f["level"] for f in r.get("findings", [])},
            "nrmse_before": r["before"]["multi_step_nrmse"]["mean"],
            "nrmse_after": r["after"]["multi_step_nrmse"]["mean"], "cpu_s": round(cpu, 1)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--real", action="store_true", help="also the real data sets (dfki, dart, emps)")
    ap.add_argument("--beam-width", type=int, default=None, help="(after the beam search) its width")
    ap.add_argument("--sets", default="dfki,dart,emps",
                    help="which real data sets (with --real): dfki, dart, emps, emps10k (EMPS's first 10,000 samples)")
    ap.add_argument("--equation-error-only", action="store_true",
                    help="fit the axis model by equation error only (axis.OUTPUT_ERROR_REFINE = False)")
    ap.add_argument("--real-n-boot", default="20", help="bootstrap replicates for the real data sets (a list: each)")
    ap.add_argument("--out", default=None, help="keep each run's report.json under this directory (default: a temp dir)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    from hilstack.calibration import axis, run_calibration
    from hilstack.calibration.selection import SelectionConfig
    from hilstack.calibration.synthetic import SynthConfig, generate

    if a.equation_error_only:
        axis.OUTPUT_ERROR_REFINE = False
    kw = {"n_boot": 25}
    if a.beam_width is not None:
        kw["beam_width"] = a.beam_width
    cfg = SelectionConfig(**kw)
    tmp = a.out or tempfile.mkdtemp()

    def run(name, seed, data, n_boot=None, **extra):
        t0, w0 = time.process_time(), time.perf_counter()
        r = run_calibration(data, out_dir=f"{tmp}/{name}_{seed}_{n_boot}", seed=seed, progress=False, plots=False,
                            config=SelectionConfig(**{**kw, "n_boot": n_boot}) if n_boot else cfg, **extra)
        row = _summary(name, seed, r, time.process_time() - t0)
        row["wall_s"] = round(time.perf_counter() - w0, 1)
        print(json.dumps(row), flush=True)

    for name in [c for c in a.cases.split(",") if c]:
        for seed in [int(s) for s in a.seeds.split(",")]:
            run(name, seed, generate(SynthConfig(effects=CASES[name], seed=seed)))
    if a.real:
        from hilstack.calibration.emps import EMPS_GTAU_N_PER_V, emps_to_csv
        from hilstack.calibration.realdata import dart_episodes, dfki_episodes, find_real

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            dfki = dfki_episodes(find_real("dfki_pendulum"))
            dart = dart_episodes(find_real("dart_rccar"))
        sets = a.sets.split(",")
        for nb in [int(n) for n in a.real_n_boot.split(",")]:
            if "dfki" in sets:
                run("dfki", 0, dfki, n_boot=nb)
            if "dart" in sets:
                run("dart", 0, dart, n_boot=nb)
            if "emps" in sets or "emps10k" in sets:
                csv = emps_to_csv(find_real("emps") / "DATA_EMPS.mat", f"{tmp}/emps.csv")
            if "emps" in sets:
                run("emps", 0, csv, n_boot=nb, column_map="t=time,u=volts,x=position", k_u=EMPS_GTAU_N_PER_V)
            if "emps10k" in sets:
                with open(csv) as f, open(f"{tmp}/emps10k.csv", "w") as g:  # head -10001: header + 10,000 rows
                    g.writelines(itertools.islice(f, 10001))
                run("emps10k", 0, f"{tmp}/emps10k.csv", n_boot=nb, column_map="t=time,u=volts,x=position",
                    k_u=EMPS_GTAU_N_PER_V)


if __name__ == "__main__":
    sys.exit(main())
