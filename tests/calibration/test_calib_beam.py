"""Issue 28 item 2: the search over sets of effects (a beam) finds two effects that only help together.

A regression model with real least-squares fits stands in for the axis model so the held-out
landscape is known: the target is the difference of two nearly collinear regressors (each alone
explains almost nothing; together they explain it all), and a decoy regressor carries a small part
of the target (the best single candidate, below "moderate"). Greedy stepwise (beam width 1: the
best single candidate with each other one) misses the pair; a beam of width 3 finds it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from hilstack.calibration.data import Recording
from hilstack.calibration.effects import EffectSpec
from hilstack.calibration.model_api import NominalModel
from hilstack.calibration.selection import SelectionConfig, select_effects


def _spec(name: str) -> EffectSpec:
    return EffectSpec(name, "a regressor", "coef", "1", 0.0)


@dataclass
class _Unit:
    F: dict
    y: np.ndarray
    period_s: float = 0.01
    ep: Recording = field(default_factory=lambda: Recording("unit", np.zeros(1), np.zeros(1), np.zeros(1)))


@dataclass
class _Fitted:
    effects: list
    coef: dict

    def primary(self, name):
        return self.coef[name]

    def effect_params(self, name):
        return {name: self.coef[name]}


class _Regression(NominalModel):
    """y ≈ Σ coef·feature over the chosen effects (least squares over the training units)."""

    name = "toy"
    look_alikes: dict = {}
    pair_tests = True

    def __init__(self, names):
        self.catalogue = {n: _spec(n) for n in names}

    def candidate_effects(self, units, accepted=()):
        return [n for n in self.catalogue if n not in accepted], {}

    def norms(self, pool):
        return None

    def fit(self, units, effects, weights=None, **kw):
        effects = list(effects)
        if not effects:
            return _Fitted([], {})
        w = np.ones(len(units)) if weights is None else np.asarray(weights, float)
        X = np.concatenate([np.stack([u.F[e] for e in effects], 1) * np.sqrt(wi) for u, wi in zip(units, w, strict=True)])
        y = np.concatenate([u.y * np.sqrt(wi) for u, wi in zip(units, w, strict=True)])
        beta = np.linalg.lstsq(X, y, rcond=None)[0]
        return _Fitted(effects, dict(zip(effects, beta.tolist(), strict=True)))

    def _loss(self, u, fitted):
        pred = sum((fitted.coef[e] * u.F[e] for e in fitted.effects), np.zeros_like(u.y))
        return float(np.mean((u.y - pred) ** 2))

    def episode_loss(self, u, fitted, horizon, nm):
        return self._loss(u, fitted)

    def oob_loss(self, u, fitted, nm):
        return self._loss(u, fitted)


DECOY = 0.6


def _units(seed, n_units=30, rows=60):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_units):
        z, e1, e2, n = rng.standard_normal((4, rows))
        s = e1 - e2  # the part of the target only the pair explains (its members are nearly collinear)
        # the decoy: a bit of the target on a few units only (a weak, unstable single gain)
        F = {"decoy": (DECOY if k % 3 == 0 else 0.0) * s + rng.standard_normal(rows), "pa": z + 0.1 * e1,
             "pb": z + 0.1 * e2, "noise1": rng.standard_normal(rows), "noise2": rng.standard_normal(rows)}
        out.append(_Unit(F, 10 * (F["pa"] - F["pb"]) + n))
    return out


@pytest.mark.parametrize("width,found", [(1, False), (3, True)])
def test_beam_finds_a_pair_greedy_misses(width, found):
    model = _Regression(["decoy", "noise1", "noise2", "pa", "pb"])
    cfg = SelectionConfig(beam_width=width, n_boot=20, n_boot_gain=1000)
    logs = []
    sel = select_effects(model, _units(0), cfg, seed=0, log=logs.append)
    r1 = {c["name"]: c for c in sel.rounds[0]["candidates"]}
    # neither member of the pair passes alone; the decoy is the best single candidate
    assert r1["pa"]["evidence"]["level"] not in ("strong", "moderate")
    assert r1["pb"]["evidence"]["level"] not in ("strong", "moderate")
    assert sel.rounds[0]["candidates"][0]["name"] == "decoy", sel.rounds[0]["candidates"]
    names = {r.name for r in sel.accepted}
    assert ({"pa", "pb"} <= names) is found, ("\n".join(logs), names)
