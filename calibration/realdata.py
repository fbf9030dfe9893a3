"""Real recordings from other labs, used in place (read only, never copied into the project).

``shared/data/real/`` beside the repository holds, each in its folder with its source and
licence: ``emps`` (ball-screw axis, :mod:`hilstack.calibration.emps`), ``dfki_pendulum`` (DFKI
torque-limited simple pendulum) and ``dart_rccar`` (DART 1:10 RC car). :func:`find_real` finds a
folder through the project's data path (``$HIL_DATA/<name>``, ``$HIL_DATA/real/<name>``, the
cache, ``shared/data/real/<name>`` beside the repository or one of its parents) and raises
:class:`~hilstack.calibration.emps.DataNotFound` naming the places it looked. The loaders turn
each source's files into single-axis :class:`~hilstack.calibration.data.Recording` s for the
``axis`` model:

* DFKI pendulum: ``u`` = the measured output-shaft torque [N·m] (what the motor applied,
  feedback and saturation included), ``x`` = angle [rad] (0 hanging down), ``v`` = the measured
  velocity [rad/s]. The hand-moved gravity-compensation run is left out by default: the
  hand's torque is an input that was not recorded.
* DART car: ``u`` = throttle (−1…1), ``v`` = the wheel-encoder speed [m/s], ``x`` = the
  distance travelled (trapezoid integral of the speed) [m]; the throttle-step runs (10_ and 19_).
"""

from __future__ import annotations

import os
from pathlib import Path

from hilstack.calibration.data import Recording, _make_episode
from hilstack.calibration.emps import DataNotFound

#: The real data sets and the file each must hold to count as found.
REAL_SETS = {
    "emps": "DATA_EMPS.mat",
    "dfki_pendulum": "results/control_method_pd/system_identification/data_measured.csv",
    "dart_rccar": "System_identification/Data/19_step_input_data",
}


def real_search_dirs(name: str) -> list[Path]:
    dirs = []
    if os.environ.get("HIL_DATA"):
        dirs += [Path(os.environ["HIL_DATA"]) / name, Path(os.environ["HIL_DATA"]) / "real" / name]
    root = os.environ.get("HILSTACK_CACHE")
    base = Path(root) / "data" if root else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / \
        "hilstack" / "data"
    dirs.append(base / name)
    repo = Path(__file__).resolve().parents[1]
    dirs += [p / "shared" / "data" / "real" / name for p in repo.parents]
    return dirs


def find_real(name: str) -> Path:
    """The folder of real data set ``name`` (see :data:`REAL_SETS`), or DataNotFound with the places looked."""
    if name not in REAL_SETS:
        raise KeyError(f"unknown real data set {name!r}; known: {sorted(REAL_SETS)}")
    dirs = real_search_dirs(name)
    for d in dirs:
        if (d / REAL_SETS[name]).exists():
            return d
    raise DataNotFound(f"real data set {name!r} not found (looked in {', '.join(str(d) for d in dirs)}); "
                       f"point $HIL_DATA at a folder holding {name}/")


def _warn(msg: str) -> None:
    import warnings

    warnings.warn(msg, stacklevel=3)


#: DFKI runs left out by default, and why.
DFKI_EXCLUDED = {"control_method_gravity_compensation": "moved by hand: the hand's torque was not recorded"}


def dfki_episodes(root: Path, include_hand: bool = False, warn=None) -> list[Recording]:
    """Every measured DFKI run (``data_measured*.csv``) as an episode: u = torque, x = angle, v = velocity."""
    import pandas as pd

    warn = warn or _warn
    out = []
    for f in sorted((root / "results").rglob("data_measured*.csv")):
        run = f.parent.relative_to(root / "results").as_posix()
        if not include_hand and run.split("/")[0] in DFKI_EXCLUDED:
            continue
        df = pd.read_csv(f)
        arrays = {"t": df["time"].to_numpy(float), "u": df["torque"].to_numpy(float),
                  "x": df["position"].to_numpy(float), "v": df["velocity"].to_numpy(float)}
        out.extend(_make_episode(f"dfki:{run}/{f.name}", arrays, f, warn))
    return out


#: DART throttle-step folders (the steering runs hold the throttle constant).
DART_STEP_FOLDERS = ("10_step_input_data_rubbery_floor", "19_step_input_data")


def dart_episodes(root: Path, folders: tuple[str, ...] = DART_STEP_FOLDERS, warn=None) -> list[Recording]:
    """DART throttle-step runs: u = throttle, v = encoder speed, x = distance (integral of the speed)."""
    import pandas as pd
    from scipy.integrate import cumulative_trapezoid

    warn = warn or _warn
    out = []
    for folder in folders:
        for f in sorted((root / "System_identification" / "Data" / folder).glob("*.csv")):
            df = pd.read_csv(f)
            t = df["elapsed time sensors"].to_numpy(float)
            v = df["vel encoder"].to_numpy(float)
            x = cumulative_trapezoid(v, t, initial=0.0)
            arrays = {"t": t, "u": df["throttle"].to_numpy(float), "x": x, "v": v}
            out.extend(_make_episode(f"dart:{folder}/{f.name}", arrays, f, warn))
    return out


__all__ = ["DFKI_EXCLUDED", "REAL_SETS", "dart_episodes", "dfki_episodes", "find_real", "real_search_dirs"]
