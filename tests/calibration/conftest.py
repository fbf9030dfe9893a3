"""Shared helpers for the calibration tests: cheap statistical settings, cached runs."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest

from calibration import run_calibration
from calibration.selection import SelectionConfig
from calibration.synthetic import SynthConfig, generate

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
