"""Pieces of the MBRL loop that need no rig: the validation split and the baseline search."""

from __future__ import annotations

import numpy as np
import pytest

from learning.datasets import Episode
from learning.mbrl import BASELINE_SEARCH, baseline_candidates, default_baseline_params, split_episodes


def eps(names):
    return [Episode(np.zeros((3, 2)), np.zeros((2, 1)), name=n) for n in names]


def test_validation_split_is_fixed_for_good_as_the_data_grows():
    rng, assigned = np.random.default_rng(0), {}
    first = eps([f"random:{i}" for i in range(70)])
    tr0, va0 = split_episodes(first, 0.1, rng, assigned)
    assert len(va0) == 7 and len(tr0) == 63
    grown = first + eps([f"mpc1:{i}" for i in range(10)])
    tr1, va1 = split_episodes(grown, 0.1, rng, assigned)
    tr0n, va0n = {e.name for e in tr0}, {e.name for e in va0}
    # no training episode of iteration 0 is validation data later, and the reverse
    assert not tr0n & {e.name for e in va1}
    assert va0n <= {e.name for e in va1} and not va0n & {e.name for e in tr1}
    # the new episodes are split too
    assert sum(e.name.startswith("mpc1") for e in va1) == 1
    assert len(tr1) + len(va1) == 80


def test_validation_split_needs_unique_names():
    with pytest.raises(ValueError, match="unique"):
        split_episodes(eps(["a", "a", "b"]), 0.5, np.random.default_rng(0), {})


def test_baseline_candidates_start_at_the_default_and_cover_the_ranges():
    c = baseline_candidates(20, 0.5, seed=0)
    assert len(c) == 20 and c[0] == default_baseline_params(0.5)
    for k, (lo, hi, scaled) in BASELINE_SEARCH.items():
        v = np.array([p[k] for p in c[1:]]) / (0.5 if scaled else 1.0)
        assert v.min() >= lo and v.max() <= hi
        # Latin hypercube: one candidate in each of the 19 equal bins of every gain's range
        bins = np.floor((v - lo) / (hi - lo) * 19).astype(int)
        assert sorted(bins.tolist()) == list(range(19))
    assert baseline_candidates(20, 0.5, seed=0) == c
    with pytest.raises(ValueError):
        baseline_candidates(0, 0.5)
