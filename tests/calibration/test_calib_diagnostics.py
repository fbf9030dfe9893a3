"""Issue 28, item 3: the residual diagnostics a physicist looks at propose the right candidates."""

from __future__ import annotations

import pytest

from hilstack.calibration import axis
from hilstack.calibration.diagnostics import plot_diagnostics, residual_diagnostics
from hilstack.calibration.synthetic import SynthConfig, generate


def _proposed(effects, seed=1):
    eps = generate(SynthConfig(n_episodes=8, duration_s=3.0, seed=seed, effects={e: {} for e in effects}))
    preps = axis.prepare(eps)
    params = axis.fit_axis(preps, [])
    d = residual_diagnostics(preps, params)
    return d, {q["name"] for q in d["proposed"]}, preps, params


@pytest.mark.parametrize("effect,proposal", [
    ("coulomb_friction", "coulomb_friction"),  # a step of the residual at v = 0
    ("gravity_load", "gravity_load"),  # a sin(x) component
    ("delay", "delay or actuator_lag"),  # correlation with the command change
])
def test_diagnostic_proposes_the_hidden_effect(effect, proposal):
    _, names, _, _ = _proposed([effect])
    assert proposal in names, names


def test_clean_data_proposes_nothing_and_the_plot_is_written(tmp_path):
    d, names, preps, params = _proposed([])
    assert names == set(), d["proposed"]
    for key in ("velocity", "position", "command_history", "reversals"):
        assert key in d
    plot_diagnostics(tmp_path / "r.png", d, preps, params)
    assert (tmp_path / "r.png").stat().st_size > 1000
