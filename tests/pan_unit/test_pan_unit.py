"""The pan unit (docs/adding_a_robot.md): its config's bounds and the servo following a target
on both simulated backends. The contract itself runs over it in tests/test_contract.py."""

from __future__ import annotations

import numpy as np
import pytest

from hilstack.configs.schema import ConfigError
from hilstack.drivers.registry import make_driver


@pytest.mark.parametrize("backend", ["sim", "emulated"])
def test_the_head_turns_to_the_target_at_the_rate_limit_and_holds(backend):
    d = make_driver("pan_unit", backend)
    rate = float(d.spec.action_rate_per_s[0])
    with d:
        t0, q = d.read().t_s, []
        for _ in range(40):  # 0.8 s: 0.5 rad at 2 rad/s takes 0.25 s
            d.write(np.array([0.5]))
            d.tick()
            o = d.read()
            q.append((o.t_s - t0, o.state[0]))
        q = np.array(q)
        assert abs(q[-1, 1] - 0.5) < 0.03, q[-1]
        # never faster than the rate limit allows (plus the servo's overshoot of one period)
        assert np.all(q[:, 1] <= rate * (q[:, 0] + 2 * d.spec.period_s) + 0.02), q
        d.stop()
        assert d.stop_confirmed()


def test_a_stale_deadline_past_the_error_deadline_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="telemetry_stale_s"):
        make_driver("pan_unit", "sim", telemetry_stale_s=0.6, link_timeout_periods=25)
