"""Sawyer emulator: a process playing the robot side of ROS 2 over Zenoh on MuJoCo.

It listens on a Zenoh endpoint, publishes ``sensor_msgs/JointState`` (CDR) at 100 Hz on
the joint-states key and applies ``intera_core_msgs/JointCommand`` from the command key,
with the vendor controller of :mod:`.controller` (velocity/position mode, 0.2 s command
timeout), in real time. The keys are those of zenoh-bridge-ros2dds, so the driver under
test is configured exactly as for a real robot behind a bridge.

    python -m hilstack.sim_backends.sawyer.emulator --listen tcp/127.0.0.1:7461

Prints one JSON line ``{"listen": ..., "pid": ...}`` when ready; logs go to stderr.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import signal
import sys
import time

import zenoh

from hilstack.bus.cycle import Rate
from hilstack.bus.lifetime import exit_with_parent
from hilstack.drivers.sawyer import ros
from hilstack.sim_backends.sawyer.controller import SawyerArm
from hilstack.sim_backends.sawyer.model import JOINTS

STATE_PERIOD_S = 0.01


def log(msg: str) -> None:
    print(f"[sawyer-emulator {os.getpid()}] {msg}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hilstack.sim_backends.sawyer.emulator")
    ap.add_argument("--listen", required=True, help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7461")
    ap.add_argument("--config", default="{}", help="JSON: namespace, joint_states_topic, joint_command_topic")
    args = ap.parse_args(argv)
    cfg = json.loads(args.config)
    ns = cfg.get("namespace", "")
    arm = SawyerArm()
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([args.listen]))
    session = zenoh.open(c)
    inbox: collections.deque[bytes] = collections.deque(maxlen=64)
    # Zenoh's thread only queues the bytes
    sub = session.declare_subscriber(ros.bridge_key(cfg.get("joint_command_topic", ros.JOINT_COMMAND_TOPIC), ns),
                                     lambda s: inbox.append(s.payload.to_bytes()))
    pub = session.declare_publisher(ros.bridge_key(cfg.get("joint_states_topic", ros.JOINT_STATES_TOPIC), ns))
    running = [True]

    def _stop(signum, frame):  # noqa: ARG001
        running[0] = False

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    exit_with_parent(lambda: (log("parent process is gone: exiting"), _stop(None, None)))
    print(json.dumps({"listen": args.listen, "pid": os.getpid()}), flush=True)
    dt = arm.model.opt.timestep
    t0 = time.monotonic()
    states = Rate(STATE_PERIOD_S, t0)  # a late state skips the boundaries it passed (bus/cycle.py)
    bad = 0
    try:
        while running[0]:
            now = time.monotonic()
            while inbox:
                try:
                    m = ros.decode_joint_command(inbox.popleft())
                    v = m.velocity if m.mode == ros.VELOCITY_MODE else m.position
                    arm.command(int(m.mode), list(m.names), v, now - t0)
                except Exception as e:  # never trust the wire
                    bad += 1
                    log(f"bad JointCommand: {type(e).__name__}: {e}")
            while arm.time_s < now - t0:
                arm.step(now - t0)
            if states.due(now):
                pub.put(ros.encode_joint_state(JOINTS, arm.q(), arm.qd(), arm.effort()))
            time.sleep(max(0.0, min(states.next_s, t0 + arm.time_s + dt) - time.monotonic()))
    finally:
        log(f"summary {json.dumps({'sim_time_s': round(arm.time_s, 3), 'timeouts': arm.timeouts, 'rejected': arm.rejected, 'bad': bad, **states.counts('state')})}")
        sub.undeclare()
        pub.undeclare()
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
