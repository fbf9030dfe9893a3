"""EMPS: a real electro-mechanical positioning system (prismatic ball-screw axis).

Data set of the 2019 Workshop on Nonlinear System Identification Benchmarks (A. Janot,
M. Gautier, M. Brunot, "Data set and reference models of EMPS", 2019). The axis is driven
by a DC motor in closed-loop position control; ``vir`` is the controller output voltage
and the drive force is ``gtau · vir`` with gtau = 35.15 N/V (benchmark documentation).
Published reference model: M·q̈ + Fv·q̇ + Fc·sign(q̇) + offset = gtau·vir with M = 95.1 kg,
Fv = 203.5 N s/m, Fc = 20.4 N, offset = −3.16 N.

The converter writes ``time, volts, position`` (+ ``reference`` for information), so the
generic CSV path of ``hil calibrate`` applies:

    hil data emps --csv emps.csv       # finds or downloads the files (checksummed), converts
    hil calibrate --data emps.csv --map t=time,u=volts,x=position --ku 35.15 --out out/emps

Getting the files (:func:`fetch_emps`): the first directory holding both files with the
right SHA-256 wins: ``$HIL_DATA/emps`` (or ``$HIL_DATA/real/emps``), the download cache,
``shared/data/real/emps`` beside the repository (or beside one of its parent folders);
otherwise pooch downloads them from the public repository they were published in into
the cache (``$HILSTACK_CACHE/data/emps``, default ``~/.cache/hilstack/data/emps``) and
checks their SHA-256. Data files are never committed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: Force per volt of the EMPS drive [N/V] (benchmark documentation).
EMPS_GTAU_N_PER_V = 35.15
#: Published reference values (Janot et al. 2019), in N, kg, N s/m.
EMPS_REFERENCE = {"M_kg": 95.1, "Fv_Nspm": 203.5, "Fc_N": 20.4, "offset_N": -3.16}


#: Where the files were published: forgi86/sysid-neural-continuous (Apache-2.0),
#: examples/EMPS/data/, at the commit the checksums below were taken from.
EMPS_BASE_URL = "https://raw.githubusercontent.com/forgi86/sysid-neural-continuous/956aa7e/examples/EMPS/data/"
#: SHA-256 of each file (of the copies in shared/data/real/emps, from that commit).
EMPS_SHA256 = {
    "DATA_EMPS.mat": "6cf6814ae14618795da0101aae2bb97ff0c6351b0501b5492751b02b07facf7e",
    "DATA_EMPS_PULSES.mat": "0eab75bb1f6b16228ee78791343a88bf9bfd9a51036ac9807d7b5fc11c0e1704",
}


class DataError(RuntimeError):
    """The data could not be obtained (download failed, checksum mismatch)."""


class DataNotFound(DataError):
    """Offline and no local copy: the user must point ``$HIL_DATA`` at one."""


def emps_cache_dir() -> Path:
    root = os.environ.get("HILSTACK_CACHE")
    if root:
        return Path(root) / "data" / "emps"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "hilstack" / "data" / "emps"


def emps_search_dirs() -> list[Path]:
    """Local copies, in the order they are tried (the cache comes after ``$HIL_DATA``)."""
    dirs = []
    if os.environ.get("HIL_DATA"):
        dirs += [Path(os.environ["HIL_DATA"]) / "emps", Path(os.environ["HIL_DATA"]) / "real" / "emps"]
    dirs.append(emps_cache_dir())
    repo = Path(__file__).resolve().parents[1]
    dirs += [p / "shared" / "data" / "real" / "emps" for p in repo.parents]
    return dirs


def _sha256_ok(path: Path) -> bool:
    import pooch

    return path.is_file() and pooch.file_hash(str(path), alg="sha256") == EMPS_SHA256[path.name]


def fetch_emps(*, base_url: str | None = None, offline: bool = False,
               search_dirs: list[Path] | None = None, cache_dir: Path | None = None) -> Path:
    """The directory holding ``DATA_EMPS.mat`` and ``DATA_EMPS_PULSES.mat`` (checked).

    Looks in ``search_dirs`` (default :func:`emps_search_dirs`); then, unless ``offline``,
    downloads from ``base_url`` (default :data:`EMPS_BASE_URL`) into ``cache_dir`` with
    pooch, which checks the SHA-256 and keeps nothing that fails it.
    Raises :class:`DataNotFound` (offline, no copy) or :class:`DataError`.
    """
    dirs = emps_search_dirs() if search_dirs is None else search_dirs
    bad: list[str] = []
    for d in dirs:
        files = [d / name for name in EMPS_SHA256]
        if all(_sha256_ok(f) for f in files):
            return d
        bad += [f"{f} (checksum mismatch)" for f in files if f.is_file() and not _sha256_ok(f)]
    if offline:
        tried = ", ".join(str(d) for d in dirs) or "nowhere"
        extra = f"; rejected {', '.join(bad)}" if bad else ""
        raise DataNotFound(f"EMPS data not found offline (looked in {tried}{extra}); "
                           "put DATA_EMPS.mat and DATA_EMPS_PULSES.mat in $HIL_DATA/emps")
    return _download(base_url or EMPS_BASE_URL, cache_dir or emps_cache_dir())


def _download(base_url: str, cache: Path) -> Path:
    import pooch
    import requests

    cache.mkdir(parents=True, exist_ok=True)
    for name, sha in EMPS_SHA256.items():
        url = base_url.rstrip("/") + "/" + name
        try:
            pooch.retrieve(url, known_hash=f"sha256:{sha}", fname=name, path=cache, progressbar=False)
        except ValueError as e:  # pooch: hash mismatch; it has deleted the download
            raise DataError(f"{name} from {url} failed its checksum, not kept ({str(e).splitlines()[0]})") from None
        except (requests.RequestException, OSError) as e:
            raise DataError(f"cannot download {url}: {type(e).__name__}: {e}; offline? "
                            "put the files in $HIL_DATA/emps") from None
    return cache


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
    """``python -m hilstack.calibration.emps DATA_EMPS.mat emps.csv``."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m hilstack.calibration.emps",
                                 description="Convert the EMPS benchmark's DATA_EMPS.mat to a calibration CSV.")
    ap.add_argument("mat", help="DATA_EMPS.mat")
    ap.add_argument("csv", help="the CSV to write")
    a = ap.parse_args(argv)
    print(emps_to_csv(a.mat, a.csv))


if __name__ == "__main__":
    main()
