"""Seed checks behind the sizes of the slow calibration tests (run by hand, not collected by pytest).

Each command re-runs a test's computation at the test's size over several seeds and prints, per
seed, whether every assertion of the test holds and the margins:

    python -m tests.calibration.seed_checks vr-payload 12 2.0 3 4 5 6 7   # test_calib_velociroach (payload)
    python -m tests.calibration.seed_checks vr-null 12 2.0 11 12 13 14 15 # test_calib_velociroach (none)
    python -m tests.calibration.seed_checks emps 25 0 1 2 3 4             # test_calib_emps (n_boot, seeds)

Arguments: episodes, episode length [s], data seeds (vr-*); bootstrap replicates, calibration seeds (emps).
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PAYLOAD_KG = 0.04


def vr_payload(n_eps: int, dur: float, seeds: list[int]) -> None:
    from hilstack.calibration import run_calibration
    from hilstack.calibration.selection import SelectionConfig
    from hilstack.calibration.synthetic_velociroach import RoachSynthConfig, generate
    from hilstack.calibration.velociroach import channels_from_states, load_sim_params, replay
    from hilstack.drivers.velociroach.config import VelociRoachParams
    from hilstack.sim_backends.velociroach.backend import VelociRoachSim

    p = PAYLOAD_KG
    for seed in seeds:
        t0 = time.time()
        out = Path(tempfile.mkdtemp())
        eps = generate(RoachSynthConfig(n_episodes=n_eps, duration_s=dur, seed=seed, hidden={"payload_kg": p}))
        rep = run_calibration(eps, model="velociroach", out_dir=out, seed=seed - 3, progress=False,
                              config=SelectionConfig(n_boot=25), plots=False)
        names = [e["name"] for e in rep["effects"]]
        e = rep["effects"][0] if rep["effects"] else {"params": {"payload_kg": -1.0}, "interval": [0.0, 0.0],
                                                       "p_value": 1.0, "heldout_gain": 0.0}
        lo, hi = e["interval"]
        b, a = rep["before"]["multi_step_nrmse"]["mean"], rep["after"]["multi_step_nrmse"]["mean"]
        ok = [rep["verdict"] == "found", names == ["payload_mass"],
              abs(e["params"]["payload_kg"] - p) <= 0.3 * p, lo > 0 and lo <= p * 1.15 and hi >= p * 0.85,
              e["p_value"] < 0.05 and e["heldout_gain"] > 0.2, a < 0.7 * b, rep["unexplained_structure"] is False,
              rep["sim_rollouts"] < 1000]
        ratio = float("nan")
        if (out / "sim_params.yaml").exists() and rep["effects"]:
            nominal = VelociRoachSim(VelociRoachParams())
            nominal.configure()
            fresh = generate(RoachSynthConfig(n_episodes=3, seed=77, hidden={"payload_kg": p}))

            def err(sim, fresh=fresh) -> float:
                tot = 0.0
                for ep in fresh:
                    obs = channels_from_states(ep.states, ep.state_names)
                    pred = replay(sim, ep.actions[:-1], (obs[0, 0], obs[0, 1], obs[0, 2]), 0.1)
                    tot += float(np.mean((pred[:, :2] - obs[:, :2]) ** 2))
                return tot

            ratio = err(load_sim_params(out / "sim_params.yaml")) / err(nominal)
        ok.append(ratio < 0.5)
        print(f"seed={seed} n_eps={n_eps} dur={dur} all_ok={all(ok)} checks={ok} names={names} "
              f"payload={e['params']['payload_kg']:.4f} interval=({lo:.4f},{hi:.4f}) p={e['p_value']:.4g} "
              f"gain={e['heldout_gain']:.3f} after/before={a / b:.3f} rollouts={rep['sim_rollouts']} "
              f"loop_ratio={ratio:.3f} t={time.time() - t0:.0f}s", flush=True)


def vr_null(n_eps: int, dur: float, seeds: list[int]) -> None:
    from typer.testing import CliRunner

    from hilstack.calibration.synthetic_velociroach import RoachSynthConfig, generate, write_mcap
    from hilstack.tools.cli import app

    for seed in seeds:
        t0 = time.time()
        tmp = Path(tempfile.mkdtemp())
        rec = write_mcap(generate(RoachSynthConfig(n_episodes=n_eps, duration_s=dur, seed=seed)), tmp / "rec.mcap")
        res = CliRunner().invoke(app, ["calibrate", "--data", str(rec), "--model", "velociroach", "--out",
                                       str(tmp / "o"), "--json", "--quiet"])
        ok = [res.exit_code == 0]
        summary = json.loads(res.output.strip().splitlines()[-1]) if res.exit_code == 0 else {}
        ok.append(summary.get("verdict") == "none" and summary.get("effects") == [])
        best = {"name": None, "heldout_gain": float("nan")}
        if res.exit_code == 0:
            rep = json.loads((tmp / "o" / "report.json").read_text())
            b, a = rep["before"]["multi_step_nrmse"]["mean"], rep["after"]["multi_step_nrmse"]["mean"]
            ok += [abs(a - b) <= 1e-6 * b, (tmp / "o" / "sim_params.yaml").exists(),
                   all(v["value"] is None or v["value"] > 0 for v in rep["detection_limit"]["per_effect"].values())]
            best = max((c for r in rep["rounds"] for c in r["candidates"]), key=lambda c: c.get("heldout_gain", -9))
        print(f"seed={seed} n_eps={n_eps} dur={dur} all_ok={all(ok)} checks={ok} verdict={summary.get('verdict')} "
              f"best_candidate={best.get('name')} gain={best.get('heldout_gain')} p={best.get('p_value')} "
              f"t={time.time() - t0:.0f}s", flush=True)


def emps(n_boot: int, seeds: list[int]) -> None:
    from hilstack.calibration import run_calibration
    from hilstack.calibration.emps import EMPS_GTAU_N_PER_V, EMPS_REFERENCE, emps_to_csv
    from hilstack.calibration.selection import SelectionConfig
    from tests.calibration.test_calib_emps import EMPS_DIR

    for seed in seeds:
        t0 = time.time()
        tmp = Path(tempfile.mkdtemp())
        csv = emps_to_csv(EMPS_DIR / "DATA_EMPS.mat", tmp / "emps.csv")
        r = run_calibration(csv, column_map="t=time,u=volts,x=position", out_dir=tmp / "out", seed=seed,
                            progress=False, k_u=EMPS_GTAU_N_PER_V, plots=False, config=SelectionConfig(n_boot=n_boot))
        names = [e["name"] for e in r["effects"]]
        phys = r["physical_params"]["after"]
        b, a = r["before"]["multi_step_nrmse"]["mean"], r["after"]["multi_step_nrmse"]["mean"]
        ok = [r["verdict"] == "found" and "coulomb_friction" in names and "force_offset" in names,
              r["confirmation"]["confirmed"] is True, r["data"]["segmented"] is True, a <= 0.5 * b,
              abs(phys["J"] / EMPS_REFERENCE["M_kg"] - 1) <= 0.1, abs(phys["Fc"] / EMPS_REFERENCE["Fc_N"] - 1) <= 0.2,
              abs(phys["b"] / EMPS_REFERENCE["Fv_Nspm"] - 1) <= 0.2]
        print(f"n_boot={n_boot} seed={seed} all_ok={all(ok)} checks={ok} names={names} after/before={a / b:.3f} "
              f"J={phys['J']:.1f} Fc={phys['Fc']:.2f} b={phys['b']:.1f} t={time.time() - t0:.0f}s", flush=True)


def main(argv: list[str]) -> None:
    if len(argv) < 3 or argv[0] not in ("vr-payload", "vr-null", "emps"):
        raise SystemExit(__doc__)
    if argv[0] == "emps":
        emps(int(argv[1]), [int(s) for s in argv[2:]])
    else:
        (vr_payload if argv[0] == "vr-payload" else vr_null)(int(argv[1]), float(argv[2]), [int(s) for s in argv[3:]])


if __name__ == "__main__":
    main(sys.argv[1:])
