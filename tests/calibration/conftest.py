"""Shared helpers for the calibration tests: cheap statistical settings, cached runs."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest

from hilstack.calibration import run_calibration
from hilstack.calibration.selection import SelectionConfig
from hilstack.calibration.synthetic import SynthConfig, generate

#: Fewer bootstrap replicates than the default: the tests check behaviour, not tight intervals.
FAST = SelectionConfig(n_boot=25)


@functools.cache
def synth_report(effects: tuple[str, ...], seed: int = 1, excitation: str = "steps", tmp_root: str = "") -> dict:
    eps = generate(SynthConfig(n_episodes=16, seed=seed, effects={e: {} for e in effects}, excitation=excitation))
    out = Path(tmp_root) / ("_".join(effects) or "none") / f"seed{seed}_{excitation}"
    return run_calibration(eps, out_dir=out, seed=seed, progress=False, plots=False, config=FAST)


@pytest.fixture(scope="session")
def report_for(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("calib"))

    def get(*effects: str, seed: int = 1, excitation: str = "steps") -> dict:
        return synth_report(tuple(effects), seed, excitation, root)

    return get


@pytest.fixture(scope="session")
def emps_dir() -> Path:
    """The public EMPS data through the project's own data path ($HIL_DATA, the cache, ../shared).

    Offline: a fresh clone with none of them skips the EMPS tests with the places it looked
    (collection never depends on the data being there).
    """
    from hilstack.calibration.emps import DataNotFound, fetch_emps

    try:
        return fetch_emps(offline=True)
    except DataNotFound as e:
        pytest.skip(str(e))
