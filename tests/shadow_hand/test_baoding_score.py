"""An episode the rig's drop detector ended is scored as dropped (learning/baoding.py:
``BaodingRun.score``), also where the task's own drop rule (a depth along the palm normal) has
not fired: a ball on the sloping fingertips, below the rig's world height, was scored as held and
the drop rate looked better than it was (the clock-target run of docs/baoding.md)."""

from __future__ import annotations

import numpy as np

from hilstack.bus.schemas import RobotState
from hilstack.control.reset.detectors import DropDetector
from hilstack.drivers.shadow_hand.config import ShadowHandParams, shadow_hand_spec
from hilstack.learning.baoding import BaodingConfig, BaodingRun

NAMES = list(shadow_hand_spec(ShadowHandParams(objects_in_state=True)).state.names)
#: the last state of an episode the rig ended (clock targets, iteration 3): ball 0 on the
#: fingertips 2.2 cm from the palm centre, world z 0.0738 m, under the rig's 0.075 m
ON_THE_FINGERTIPS = [[0.9744, 0.8626, 0.0738], [0.9976, 0.8906, 0.0904]]


def states_ending_at(balls_end) -> np.ndarray:
    run_task_rest = np.array([[0.985, 0.8847, 0.115], [1.009, 0.8847, 0.115]])
    st = np.zeros((6, len(NAMES)))
    for k in range(6):
        b = run_task_rest if k < 5 else np.asarray(balls_end)
        st[k, [NAMES.index(f"ball{i}_{c}") for i in range(2) for c in "xyz"]] = b.reshape(-1)
    return st


def test_an_episode_the_rig_ended_on_a_drop_is_scored_dropped(tmp_path, bus):
    run = BaodingRun(BaodingConfig.from_preset("tiny"), tmp_path / "run", bus)
    run.state_names = NAMES
    st = states_ending_at(ON_THE_FINGERTIPS)
    assert not run.task.dropped(np.asarray(ON_THE_FINGERTIPS))  # the task's rule alone misses it
    t = np.arange(6) * 0.1
    # the reason as the rig's own drop detector words it (learning/mbrl.py prefixes "supervisor: ")
    det = DropDetector(["ball0_z", "ball1_z"], min_height_m=0.075)
    det.bind(NAMES)
    why = det(RobotState(robot="hand", t_s=0.5, state=st[-1].tolist()))
    assert why, "the rig's detector fires on the last state"
    assert run.score(st, t, f"supervisor: {why}")["dropped"] == 1.0
    assert run.score(st, t, "supervisor: timeout: 10.0 s")["dropped"] == 0.0
    assert run.score(st, t, "")["dropped"] == 0.0
    fallen = states_ending_at([[0.98, 0.88, 0.0], [1.0, 0.88, 0.115]])
    assert run.score(fallen, t, "")["dropped"] == 1.0  # the task's rule still counts on its own
