"""A Baoding seed repeats itself on the lockstep hand rig: where episodes end and start is a
property of the states, not of the machine's load (docs/baoding.md, "A seed repeats itself").

Before, the same seeded episodes on two rigs gave different episodes: the supervisor's end of an
episode reached the controller a few states late or early, a hold sent beside a teleport or a
new-episode request stepped the sim a period or not, the verification was sometimes timed from
the state before the teleport, the recording split episodes by the arrival order of messages from
different nodes, and a lockstep sim stepped itself after 5 s without an answer. Two rigs run side
by side here (as two sweep tasks on one machine), so each loads the other."""

from __future__ import annotations

import threading

import numpy as np

from hilstack.configs.schema import BusConfig
from hilstack.learning.baoding import BaodingConfig, BaodingRun, ConstantPolicy, UniformRandomPolicy
from hilstack.learning.recordings import episodes_from_mcap
from tests.helpers import free_port


def _episodes(out, port: int, results: dict, k: int) -> None:
    from hilstack.drivers.shadow_hand.config import hold_pose_action

    run = BaodingRun(BaodingConfig.from_preset("tiny"), out, BusConfig(endpoint=f"tcp/127.0.0.1:{port}"))

    def policy(i: int):  # ended by a drop (random walk, uniform random) or by the step budget (hold)
        return (run.random_walk(i), UniformRandomPolicy(20, seed=i), ConstantPolicy(hold_pose_action()))[i % 3]

    try:
        with run.session():
            path, scores = run.run_episodes(policy, 4, "episodes", "episodes", steps=12)
        results[k] = (episodes_from_mcap(path, "hand"), scores, dict(run.supervisor.stats))
    except BaseException as e:  # the test reports it
        results[k] = e


def test_two_rigs_running_the_same_seeded_episodes_record_the_same_episodes(tmp_path):
    results: dict = {}
    ports = [free_port()]
    while len(ports) < 2:  # each rig its own endpoint
        ports += [p for p in [free_port()] if p not in ports]
    threads = [threading.Thread(target=_episodes, args=(tmp_path / f"run{k}", ports[k], results, k)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    for k in range(2):
        assert not isinstance(results.get(k), BaseException), results.get(k)
    (ea, score_a, stats_a), (eb, score_b, stats_b) = results[0], results[1]
    lens = [len(e) for e in ea]
    assert lens == [len(e) for e in eb], (lens, [len(e) for e in eb])
    assert len(ea) == 4 and max(lens) == 12 and min(lens) < 12  # some ran out their steps, some dropped
    for i, (x, y) in enumerate(zip(ea, eb, strict=True)):
        np.testing.assert_array_equal(x.states, y.states, err_msg=f"episode {i}")
        np.testing.assert_array_equal(x.actions, y.actions, err_msg=f"episode {i}")
    assert score_a == score_b  # the episodes the controller saw, scored
    assert stats_a["failed"] == stats_b["failed"] == 0
