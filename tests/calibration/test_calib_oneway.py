"""A gravity (sine-of-position) load is offered only for a position that swings both ways: on a
distance travelled one way (a vehicle's odometry) it has no physical meaning (issue 28 item 3)."""

from __future__ import annotations

from hilstack.calibration import axis
from hilstack.calibration.models import TWO_WAY_MIN_FRACTION, AxisModel, two_way_fraction
from hilstack.calibration.synthetic import SynthConfig, generate


def _candidates(cfg: SynthConfig):
    preps = axis.prepare(generate(cfg))
    names, skipped = AxisModel().candidate_effects(preps)
    return preps, names, skipped


def test_forward_only_vehicle_is_not_offered_a_gravity_sine():
    # the gauntlet's servo_vehicle: forward-only speed commands, 1 cm odometry
    preps, names, skipped = _candidates(SynthConfig(n_episodes=6, duration_s=6.0, seed=0, a=4.0, c_per_s=4.0,
                                                    u_max=2.0, excitation="drive", x_quant=0.01))
    assert two_way_fraction(preps) < TWO_WAY_MIN_FRACTION
    assert "gravity_load" not in names
    assert "one-way travel" in skipped["gravity_load"]
    assert "delay" in names  # the rest of the catalogue is still offered


def test_swinging_axis_keeps_the_gravity_candidate():
    preps, names, skipped = _candidates(SynthConfig(n_episodes=6, seed=1, effects={"gravity_load": {}}))
    assert two_way_fraction(preps) > 0.5
    assert "gravity_load" in names and "gravity_load" not in skipped
