"""EMPS: a real electro-mechanical positioning system (prismatic ball-screw axis).

Data set of the 2019 Workshop on Nonlinear System Identification Benchmarks (A. Janot,
M. Gautier, M. Brunot, "Data set and reference models of EMPS", 2019). The axis is driven
by a DC motor in closed-loop position control; ``vir`` is the controller output voltage
and the drive force is ``gtau · vir`` with gtau = 35.15 N/V (benchmark documentation).
Published reference model: M·q̈ + Fv·q̇ + Fc·sign(q̇) + offset = gtau·vir with M = 95.1 kg,
Fv = 203.5 N s/m, Fc = 20.4 N, offset = −3.16 N.

The converter writes ``time, volts, position`` (+ ``reference`` for information), so the
generic CSV path of ``hil calibrate`` applies:

    hil calibrate --data emps.csv --map t=time,u=volts,x=position --ku 35.15 --out out/emps
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Force per volt of the EMPS drive [N/V] (benchmark documentation).
EMPS_GTAU_N_PER_V = 35.15
#: Published reference values (Janot et al. 2019), in N, kg, N s/m.
EMPS_REFERENCE = {"M_kg": 95.1, "Fv_Nspm": 203.5, "Fc_N": 20.4, "offset_N": -3.16}


def read_emps(mat_path: str | Path) -> dict[str, np.ndarray | float]:
    """Read an EMPS .mat file: t [s], qm [m], qg [m], vir [V], gtau [N/V]."""
    from scipy.io import loadmat

    d = loadmat(str(mat_path))
    out: dict[str, np.ndarray | float] = {k: np.asarray(d[k], float).ravel() for k in ("t", "qm", "qg", "vir")}
    out["gtau"] = float(np.asarray(d["gtau"]).ravel()[0])
    return out


def emps_to_csv(mat_path: str | Path, out_path: str | Path) -> Path:
    """Convert an EMPS .mat file to CSV with columns time [s], volts [V], position [m], reference [m].

    ``volts`` is the controller output voltage ``vir`` (force = gtau·vir), ``position`` the
    measured motor-side position ``qm``, ``reference`` the position set-point ``qg``.
    """
    import pandas as pd

    d = read_emps(mat_path)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"time": d["t"], "volts": d["vir"], "position": d["qm"], "reference": d["qg"]}).to_csv(
        out_path, index=False
    )
    return out_path


def main(argv: list[str] | None = None) -> None:
    """``python -m calibration.emps DATA_EMPS.mat emps.csv``."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        raise SystemExit("usage: python -m calibration.emps DATA_EMPS.mat out.csv")
    print(emps_to_csv(args[0], args[1]))


if __name__ == "__main__":
    main()
