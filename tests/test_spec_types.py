"""The typed vocabulary on both sides of the bus: RobotSpec round trip, the action space's
normalize/denormalize/max step, and the str-valued enums of the wire."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.bus.schemas import ResetEvent, ResetPhase, RobotState, SpecMsg, StoppedReason, decode, encode
from hilstack.drivers.base import RobotSpec, Space


def _spec(**kw) -> RobotSpec:
    return RobotSpec(
        "bot",
        Space.build([("x", "m", -np.inf, np.inf), ("v", "m/s", -3.0, 3.0)]),
        Space.build([("left", "rev/s", -15.0, 15.0), ("grip", "rad", 0.0, 2.0)]),
        period_s=0.05,
        **{"action_rate_per_s": [60.0, np.inf], "safe_action": [0.0, 1.0], **kw},
    )

def test_spec_round_trips_through_the_bus_message():
    spec = _spec()
    wire = decode(encode(SpecMsg(robot="bot", spec=spec.to_dict())), SpecMsg)
    back = RobotSpec.from_dict(wire.spec)
    assert back.name == "bot" and back.period_s == 0.05
    assert back.state.names == spec.state.names and back.action.units == spec.action.units
    np.testing.assert_array_equal(back.state.low, spec.state.low)  # ±inf survive
    np.testing.assert_array_equal(back.action.high, spec.action.high)
    np.testing.assert_array_equal(back.action_rate_per_s, spec.action_rate_per_s)
    np.testing.assert_array_equal(back.safe_action, spec.safe_action)
    held = RobotSpec.from_dict(_spec(safe_action=None, action_rate_per_s=None).to_dict())
    assert held.safe_action is None and held.action_rate_per_s is None
    assert held.max_step_normalized() is None

@pytest.mark.parametrize("mutate, what", [
    (lambda d: d.pop("period_s"), "missing 'period_s'"),
    (lambda d: d["action"].update(low=[0.0]), "space sizes disagree"),
    (lambda d: d.update(period_s=-1.0), "period_s must be a positive"),
    (lambda d: d.update(safe_action=[0.0]), "safe_action has 1 entries"),
])
def test_a_malformed_spec_is_one_line_naming_what_is_wrong(mutate, what):
    d = _spec().to_dict()
    mutate(d)
    with pytest.raises(ValueError, match=what) as e:
        RobotSpec.from_dict(d)
    assert "bot" in str(e.value) and "\n" not in str(e.value)

def test_action_space_normalize_denormalize_and_max_step():
    a = _spec().action
    np.testing.assert_allclose(a.normalize([-15.0, 0.0]), [-1.0, -1.0])
    np.testing.assert_allclose(a.normalize([7.5, 1.5]), [0.5, 0.5])
    np.testing.assert_allclose(a.denormalize([0.5, -1.0]), [7.5, 0.0])
    np.testing.assert_allclose(a.denormalize([5.0, -5.0]), [15.0, 0.0])  # clipped to the range
    x = np.array([3.0, 0.25])
    np.testing.assert_allclose(a.denormalize(a.normalize(x)), x)
    # 60 rev/s² over 0.05 s is 3 rev/s, a tenth of the 30 rev/s range (±15): 0.2 normalized
    np.testing.assert_allclose(_spec().max_step_normalized(), [0.2, np.inf])
    with pytest.raises(ValueError, match=r"\['x'\] are unbounded"):
        _spec().state.normalize([0.0, 0.0])

def test_enums_are_the_wire_strings():
    """str-valued: a state or reset answer encodes the same bytes as before, and decodes back
    to a value the enum recognises (recordings stay readable both ways)."""
    assert [r.value for r in StoppedReason] == ["", "waiting", "stale", "estop", "bad_command", "unhealthy"]
    m = decode(encode(RobotState(robot="r", t_s=0.0, state=[0.0], stopped_reason=StoppedReason.STALE)), RobotState)
    assert m.stopped_reason == "stale" and StoppedReason(m.stopped_reason) is StoppedReason.STALE
    assert encode(RobotState(robot="r", t_s=0.0, state=[0.0], stopped_reason=StoppedReason.ESTOP, stamp_s=1.0)) == \
        encode(RobotState(robot="r", t_s=0.0, state=[0.0], stopped_reason="estop", stamp_s=1.0))
    e = decode(encode(ResetEvent(robot="r", phase=ResetPhase.UNSUPPORTED)), ResetEvent)
    assert ResetPhase(e.phase) is ResetPhase.UNSUPPORTED

def test_the_bridge_sets_only_stopped_reasons_of_the_vocabulary():
    """Every ``stopped_reason`` a driver node assigns is a member (no free strings left)."""
    import ast
    import inspect

    from hilstack.drivers import bridge

    tree = ast.parse(inspect.getsource(bridge))
    assigned = [n.value for n in ast.walk(tree) if isinstance(n, ast.Assign)
                and any(isinstance(t, ast.Attribute) and t.attr == "stopped_reason" for t in n.targets)]
    assert assigned
    for v in assigned:
        assert isinstance(v, ast.Attribute) and isinstance(v.value, ast.Name) and v.value.id == "StoppedReason", \
            ast.unparse(v)
