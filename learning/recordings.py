"""Episodes from MCAP recordings of a rig.

A driver node publishes one ``RobotState`` per control period carrying the measured
state, the action held during the period that ended with it, and an ``episode``
counter incremented by each reset. So transition t of an episode is
``(states[t], states[t+1].action, states[t+1])``. Actions are returned normalized to
[-1, 1] of the robot's spec (recorded on ``.../spec``) unless ``normalize=False``.

The driver node bumps ``episode`` only when a reset is done, so the reset's own motion
(self-right kicks, the drive back, a lab fixture putting the robot on its legs, a
teleport) is recorded under the episode that ended. The reset supervisor's recorded
``ResetTransition`` messages say when: every state between leaving ``running`` and coming
back to it is left out, and the episode's transitions end where the episode did. A
recording whose first transition does not leave ``running`` started during a reset (the
previous file holds the episode's end): the states before it are left out too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hilstack.bus.recording import iter_messages
from hilstack.bus.schemas import ResetTransition, RobotState, SpecMsg
from hilstack.drivers.base import RobotSpec
from hilstack.learning.datasets import Episode


def episodes_from_mcap(
    path: str | Path,
    robot: str | None = None,
    normalize: bool = True,
    min_steps: int = 2,
    episodes: set[int] | None = None,
    clock: str = "host",
) -> list[Episode]:
    """Split a recording into episodes of one robot (the only one, or ``robot``).

    ``clock``: the episode's ``times``. "host": ``RobotState.t_s``, the host's stamp when the reading
    returned. "device": ``RobotState.device_t_s`` (the device's own clock when the data were sampled:
    a Dynamixel's Realtime Tick) for every episode whose states all carry one, else the host's;
    ``meta["clock"]`` says which, and ``meta["host_times"]`` keeps the host stamps. A state whose
    time does not advance on that clock (the same reading stamped twice) is dropped. On the
    device clock a reading that was not ok only because it reached the host late (its recorder
    set ``RobotState.health["late"]``) does not end the episode; any other not-ok reading does.
    """
    if clock not in ("host", "device"):
        raise ValueError(f"clock must be 'host' or 'device', got {clock!r}")
    states: dict[tuple[str, int], list[RobotState]] = {}
    specs: dict[str, dict] = {}
    #: per robot, once it has a reset transition in this file: inside a reset now
    resetting: dict[str, bool] = {}
    in_reset: set[int] = set()  # ids of the states recorded during a reset
    #: per robot: ids of the states recorded before its first reset transition
    before_first: dict[str, list[int]] = {}
    # transitions that name the robot's newest state (ResetTransition.state_seq) split by the
    # states' own sequence numbers, whatever order the messages arrived in: the last state of
    # each ended episode; for a file that opens inside a reset, the first state after it (the
    # resume's state; None while the file has none)
    end_seq: dict[tuple[str, int], int] = {}
    opened_until: dict[str, int | None] = {}
    by_seq: set[str] = set()
    for rm in iter_messages(path):
        m = rm.msg
        if isinstance(m, SpecMsg):
            if m.robot not in specs:  # repeated at 1 Hz: the first one, typed
                specs[m.robot] = RobotSpec.from_dict(m.spec)
        elif isinstance(m, RobotState) and m.state:
            states.setdefault((m.robot, m.episode), []).append(m)
            if resetting.get(m.robot):
                in_reset.add(id(m))
            if m.robot not in resetting:
                before_first.setdefault(m.robot, []).append(id(m))
        elif isinstance(m, ResetTransition):
            if m.state_seq >= 0:
                if m.robot not in by_seq and m.source != "running":
                    opened_until[m.robot] = None
                by_seq.add(m.robot)
                if m.source == "running" and m.dest != "running":
                    end_seq.setdefault((m.robot, m.episode), m.state_seq)
                elif m.dest == "running" and m.robot in opened_until and opened_until[m.robot] is None:
                    opened_until[m.robot] = m.state_seq
            if m.robot not in resetting and m.source != "running":
                # the recording started during a reset (the previous file holds the end of the
                # episode that opened it): what came before is the reset's, not an episode's
                in_reset.update(before_first.get(m.robot, []))
            if m.source == "running" and m.dest != "running":
                resetting[m.robot] = True  # the episode ended (or the rig stopped)
            elif m.dest == "running":
                resetting[m.robot] = False
            else:  # a step inside a reset; the first one seen says the file started in one
                resetting[m.robot] = resetting.get(m.robot, True)
    robots = sorted({r for r, _ in states})
    if robot is None:
        if len(robots) != 1:
            raise ValueError(f"{path}: recording has robots {robots}; say which one")
        robot = robots[0]
    if robot not in robots:
        raise ValueError(f"{path}: no states of robot {robot!r}; robots are {robots}")
    spec = specs.get(robot)
    if normalize and spec is None:
        raise ValueError(f"{path}: no spec message for {robot!r}, cannot normalize actions")
    out = []
    for (r, ep), msgs in sorted(states.items()):
        if r != robot or (episodes is not None and ep not in episodes):
            continue
        msgs.sort(key=lambda m: m.seq)
        if r in by_seq:
            last = end_seq.get((r, ep))
            opened = r in opened_until
            until = opened_until.get(r)
            for m in msgs:
                if (last is not None and m.seq > last) or (opened and (until is None or m.seq < until)):
                    in_reset.add(id(m))
                else:
                    in_reset.discard(id(m))
        on_device = clock == "device" and all(m.device_t_s >= 0 for m in msgs)

        def t_of(m: RobotState, on_device: bool = on_device) -> float:
            return m.device_t_s if on_device else m.t_s

        # consecutive duplicates (a state re-published without a step) carry no transition
        uniq = [msgs[0]]
        for m in msgs[1:]:
            if t_of(m) > t_of(uniq[-1]):
                uniq.append(m)
        # a reading flagged not ok (link trouble, sim blow-up) ends a segment: transitions
        # into or out of it are not trustworthy; so does a reset (its motion is not the
        # episode's, and a fixture or teleport moves the robot without a cause in the action).
        # On the device clock a reading its recorder marked late (``health["late"]``: not ok
        # only because it reached the host late, on a device whose stamp covers the whole
        # reading; calibration/robot_rig.py) keeps its segment: its device stamp says when it
        # was sampled, so the transitions into and out of it are timed (a gap in that clock is
        # for the user to judge: calibration's blocks never span one, calibration/mjcf_robot.py)
        def usable(m: RobotState, on_device: bool = on_device) -> bool:
            return m.ok or (on_device and bool(m.health.get("late")) and bool(np.all(np.isfinite(m.state))))

        segments: list[list[RobotState]] = [[]]
        for m in uniq:
            if usable(m) and id(m) not in in_reset:
                segments[-1].append(m)
            elif segments[-1]:
                segments.append([])
        for k, seg in enumerate(s for s in segments if len(s) >= min_steps + 1):
            if any(len(m.action) == 0 for m in seg[1:]):
                continue
            st = np.array([m.state for m in seg])
            act = np.array([m.action for m in seg[1:]])
            if normalize:
                act = spec.action.normalize(act)
            out.append(
                Episode(
                    states=st,
                    actions=act,
                    times=np.array([t_of(m) for m in seg]),
                    name=f"{Path(path).stem}:{robot}:{ep}" + (f".{k}" if k else ""),
                    meta={
                        "robot": robot,
                        "episode": ep,
                        "state_names": None if spec is None else list(spec.state.names),
                        "action_names": None if spec is None else list(spec.action.names),
                        "actions_normalized": normalize,
                        "clock": "device" if on_device else "host",
                        **({"host_times": np.array([m.t_s for m in seg])} if on_device else {}),
                    },
                )
            )
    return out
