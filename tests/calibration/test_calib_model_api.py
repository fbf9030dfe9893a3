"""The typed accessors of calibration: the network inside a dynamics checkpoint."""

from __future__ import annotations

import pytest


def test_ensemble_of_unwraps_a_body_frame_model_and_refuses_anything_else():
    from hilstack.learning.dynamics import EnsembleDynamics
    from hilstack.learning.frames import BodyFrameDynamics, ensemble_of

    names = ["x", "y", "vx", "vy", "cos_yaw", "sin_yaw"]
    net = EnsembleDynamics(len(names), 2, 1, [8], state_names=names)
    assert ensemble_of(net) is net
    assert ensemble_of(BodyFrameDynamics(net, names)) is net
    with pytest.raises(TypeError, match="^expected an EnsembleDynamics or a BodyFrameDynamics, got dict$"):
        ensemble_of({})
