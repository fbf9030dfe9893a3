"""ROS 2 messages of the Sawyer, CDR-serialized with rosbags' type system, and the Zenoh
key expressions a ROS 2 ↔ Zenoh bridge uses for them.

Rethink's intera interface: ``sensor_msgs/JointState`` on ``/robot/joint_states``; joint
commands as ``intera_core_msgs/JointCommand`` on ``/robot/limb/right/joint_command``
(mode 2 = velocity). ``JointCommand`` is not a ROS 2 core type, so its definition (from
intera_core_msgs) is registered into the rosbags typestore here.

Keys: zenoh-bridge-ros2dds maps a topic to its name without the leading slash, under the
bridge's namespace if it has one (``namespace/robot/joint_states``). rmw_zenoh uses a
different scheme (domain, type and type hash in the key, plus attachments and
liveliness tokens) that this driver does not speak (docs/arms.md).
"""

from __future__ import annotations

import time
from functools import cache

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

JOINT_STATES_TOPIC = "/robot/joint_states"
JOINT_COMMAND_TOPIC = "/robot/limb/right/joint_command"
JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_COMMAND = "intera_core_msgs/msg/JointCommand"
POSITION_MODE, VELOCITY_MODE = 1, 2

#: intera_core_msgs/msg/JointCommand.msg
JOINT_COMMAND_MSG = """
std_msgs/Header header
int32 mode
string[] names
float64[] position
float64[] velocity
float64[] acceleration
float64[] effort
int32 POSITION_MODE=1
int32 VELOCITY_MODE=2
int32 TORQUE_MODE=3
int32 TRAJECTORY_MODE=4
"""


@cache
def typestore():
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register(get_types_from_msg(JOINT_COMMAND_MSG, JOINT_COMMAND))
    return ts


def bridge_key(topic: str, namespace: str = "") -> str:
    """zenoh-bridge-ros2dds key of a ROS 2 topic: no leading slash, under the namespace."""
    key = topic.lstrip("/")
    ns = namespace.strip("/")
    return f"{ns}/{key}" if ns else key


def _header(ts, stamp_s: float, frame_id: str = ""):
    sec = int(stamp_s)
    return ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int((stamp_s - sec) * 1e9)),
        frame_id=frame_id)


def encode_joint_state(names: list[str] | tuple[str, ...], q, qd, effort, stamp_s: float | None = None) -> bytes:
    ts = typestore()
    msg = ts.types[JOINT_STATE](
        header=_header(ts, time.time() if stamp_s is None else stamp_s), name=list(names),
        position=np.asarray(q, dtype=np.float64), velocity=np.asarray(qd, dtype=np.float64),
        effort=np.asarray(effort, dtype=np.float64))
    return bytes(ts.serialize_cdr(msg, JOINT_STATE))


def decode_joint_state(raw: bytes):
    return typestore().deserialize_cdr(raw, JOINT_STATE)


def encode_joint_command(mode: int, names: list[str] | tuple[str, ...], values, stamp_s: float | None = None) -> bytes:
    ts = typestore()
    v = np.asarray(values, dtype=np.float64)
    empty = np.zeros(0, dtype=np.float64)
    msg = ts.types[JOINT_COMMAND](
        header=_header(ts, time.time() if stamp_s is None else stamp_s), mode=int(mode), names=list(names),
        position=v if mode == POSITION_MODE else empty, velocity=v if mode == VELOCITY_MODE else empty,
        acceleration=empty, effort=empty)
    return bytes(ts.serialize_cdr(msg, JOINT_COMMAND))


def decode_joint_command(raw: bytes):
    return typestore().deserialize_cdr(raw, JOINT_COMMAND)
