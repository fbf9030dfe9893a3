"""`hil export ros2`: a recording (MCAP, JSON messages) as a ROS 2 bag (rosbag2 directory,
MCAP storage, CDR messages) that ROS 2 tools, rosbags and Foxglove read with standard types.

The `rosbags` library (pure Python) writes the bag and serializes CDR; nothing of ROS 2 needs to
be installed. Per robot, from its spec's channel names and units (``hil.Spec``):

| recorded | ROS 2 topic | type |
|---|---|---|
| state: x, y, z [m] and roll/pitch/yaw (or their cos_/sin_ pairs; ZYX Euler, as every backend's ``quat_to_rpy``) | ``/<rig>/<robot>/pose`` | ``geometry_msgs/msg/PoseStamped`` (frame ``world``) |
| state: vx, vy, vz [m/s, world frame: mocap, MuJoCo's free joint] rotated into the body frame by the pose's orientation, and wx, wy, wz [rad/s, body frame: the gyro] | ``/<rig>/<robot>/twist`` | ``geometry_msgs/msg/TwistStamped`` (frame ``<robot>``) |
| state: joint angles [rad] (or cos_/sin_ pairs that are no body angle), their velocities ``<j>_vel`` / ``<j>_vel_<side>`` [rad/s, rev/s → rad/s] | ``/<rig>/<robot>/joint_states`` | ``sensor_msgs/msg/JointState`` |
| state, whole (names, units, values, ok, active, episode) | ``/<rig>/<robot>/state`` | ``hilstack_msgs/msg/RobotState`` |
| command | ``/<rig>/<robot>/cmd`` | ``hilstack_msgs/msg/Command`` (names and action in the spec's units) |
| camera image (JPEG/PNG) | ``/<rig>/<camera>/image/compressed`` (image_transport's name) | ``sensor_msgs/msg/CompressedImage`` |
| camera image (rgb8) | ``/<rig>/<camera>/image`` | ``sensor_msgs/msg/Image`` |
| anything else (plans, e-stops, resets, specs...) | its key with ``/`` | ``hilstack_msgs/msg/Record`` (type + the message as JSON) |

The project's own message definitions (:data:`HIL_MSGS`) are written into the bag, so any reader
decodes them. Header stamps are the messages' own ``stamp_s`` (the publisher's clock); the bag's
receive time is the recording's log time.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: the project's ROS 2 message definitions (.msg syntax), registered with rosbags' typestore
HIL_MSGS: dict[str, str] = {
    "hilstack_msgs/msg/RobotState": (
        "std_msgs/Header header\nstring robot\nfloat64 t_s\nstring[] names\nstring[] units\nfloat64[] state\n"
        "bool ok\nbool active\nstring stopped_reason\nuint32 episode\nuint64 seq\n"
    ),
    "hilstack_msgs/msg/Command": (
        "std_msgs/Header header\nstring robot\nstring[] names\nstring[] units\nfloat64[] action\nstring source\n"
        "uint64 seq\n"
    ),
    "hilstack_msgs/msg/Record": "std_msgs/Header header\nstring type\nstring json\n",
}
WORLD_FRAME = "world"
_BODY_ANGLES = ("roll", "pitch", "yaw")


@dataclass
class ExportResult:
    out: str
    messages: int = 0
    #: ROS 2 topic -> (type, count)
    topics: dict[str, list[Any]] = field(default_factory=dict)
    skipped: int = 0


def _layout(names: list[str], units: list[str]) -> dict[str, Any]:
    """Where pose, twist and joints are in a state vector with these names and units."""
    idx = {n: i for i, n in enumerate(names)}
    angles: dict[str, tuple[str, Any]] = {}  # angle name -> ("rad", i) | ("cs", (i_cos, i_sin))
    for n, i in idx.items():
        if n.startswith("cos_") and f"sin_{n[4:]}" in idx:
            angles[n[4:]] = ("cs", (i, idx[f"sin_{n[4:]}"]))
        elif units[i] == "rad" and not n.startswith(("sin_", "cos_")):
            angles[n] = ("rad", i)
    pose = None
    if all(k in idx for k in ("x", "y")):
        pose = {"pos": [idx.get(k) for k in ("x", "y", "z")], "rpy": [angles.get(a) for a in _BODY_ANGLES]}
    twist = None
    lin, ang = [idx.get(k) for k in ("vx", "vy", "vz")], [idx.get(k) for k in ("wx", "wy", "wz")]
    if any(i is not None for i in lin + ang):
        twist = {"lin": lin, "ang": ang}
    joints = []
    for j, src in angles.items():
        if j in _BODY_ANGLES:
            continue
        head, _, side = j.rpartition("_")
        vel = None
        for cand in (f"{j}_vel", f"vel_{j}", f"{head}_vel_{side}" if head else None):
            if cand in idx and units[idx[cand]] in ("rad/s", "rev/s"):
                vel = (idx[cand], 2 * math.pi if units[idx[cand]] == "rev/s" else 1.0)
                break
        joints.append((j, src, vel))
    return {"pose": pose, "twist": twist, "joints": joints}


def _angle(state: list[float], src: tuple[str, Any] | None) -> float:
    if src is None:
        return 0.0
    kind, i = src
    return float(state[i]) if kind == "rad" else math.atan2(state[i[1]], state[i[0]])


def _v(state: list[float], i: int | None) -> float:
    return 0.0 if i is None else float(state[i])


def _ros_topic(key: str) -> str:
    parts = key.split("/")
    if parts[0] == "hil":
        parts = parts[1:]
    return "/" + "/".join(p.replace("-", "_") for p in parts if p)


def export_ros2(rec: str | Path, out: str | Path, force: bool = False) -> ExportResult:
    """Write recording ``rec`` as a ROS 2 bag directory ``out`` (refuses an existing one unless ``force``)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    from scipy.spatial.transform import Rotation

    from hilstack.bus.recording import iter_messages
    from hilstack.bus.schemas import Command, Image, RobotState, SpecMsg, encode_json, type_name
    from hilstack.tools.common import UserError

    out = Path(out)
    if out.exists():
        if not force:
            raise UserError(f"{out} exists: choose another --out or pass --force to replace it")
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in HIL_MSGS.items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    M = ts.types  # noqa: N806 - the message classes by type name

    def header(stamp_s: float, log_ns: int, frame: str) -> Any:
        ns = int(round(stamp_s * 1e9)) if stamp_s else log_ns
        return M["std_msgs/msg/Header"](stamp=M["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                       frame_id=frame)

    res = ExportResult(out=str(out))
    specs: dict[str, dict[str, Any]] = {}
    layouts: dict[str, dict[str, Any]] = {}
    conns: dict[str, Any] = {}
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:

        def put(topic: str, typ: str, msg: Any, log_ns: int) -> None:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
                res.topics[topic] = [typ, 0]
            w.write(conns[topic], log_ns, ts.serialize_cdr(msg, typ))
            res.topics[topic][1] += 1
            res.messages += 1

        for m in iter_messages(rec):
            msg, key, t = m.msg, m.topic, m.log_time_ns
            base = _ros_topic(key.rsplit("/", 1)[0]) if "/" in key else _ros_topic(key)
            if isinstance(msg, SpecMsg):
                specs[msg.robot] = msg.spec
                st = msg.spec.get("state", {})
                layouts[msg.robot] = _layout(list(st.get("names", [])), list(st.get("units", [])))
            if isinstance(msg, RobotState) and msg.robot in specs:
                st, lay = specs[msg.robot]["state"], layouts[msg.robot]
                s = msg.state
                if len(s) != len(st["names"]):
                    res.skipped += 1
                    continue
                put(f"{base}/state", "hilstack_msgs/msg/RobotState", M["hilstack_msgs/msg/RobotState"](
                    header=header(msg.stamp_s, t, msg.robot), robot=msg.robot, t_s=msg.t_s, names=list(st["names"]),
                    units=list(st["units"]), state=np.asarray(s, dtype=np.float64), ok=msg.ok, active=msg.active,
                    stopped_reason=msg.stopped_reason, episode=max(0, msg.episode), seq=max(0, msg.seq)), t)
                rot = None
                if lay["pose"]:
                    p = lay["pose"]
                    rpy = [_angle(s, a) for a in p["rpy"]]
                    rot = Rotation.from_euler("ZYX", [rpy[2], rpy[1], rpy[0]])
                    q = rot.as_quat()  # x, y, z, w
                    pose = M["geometry_msgs/msg/Pose"](
                        position=M["geometry_msgs/msg/Point"](x=_v(s, p["pos"][0]), y=_v(s, p["pos"][1]),
                                                              z=_v(s, p["pos"][2])),
                        orientation=M["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
                    put(f"{base}/pose", "geometry_msgs/msg/PoseStamped",
                        M["geometry_msgs/msg/PoseStamped"](header=header(msg.stamp_s, t, WORLD_FRAME), pose=pose), t)
                if lay["twist"]:
                    v3 = M["geometry_msgs/msg/Vector3"]
                    lin, ang = ([_v(s, i) for i in lay["twist"][k]] for k in ("lin", "ang"))
                    if rot is not None:  # vx, vy, vz are world-frame (mocap, MuJoCo's free joint): to the body
                        lin = list(rot.inv().apply(lin))
                    put(f"{base}/twist", "geometry_msgs/msg/TwistStamped", M["geometry_msgs/msg/TwistStamped"](
                        header=header(msg.stamp_s, t, msg.robot),
                        twist=M["geometry_msgs/msg/Twist"](linear=v3(x=lin[0], y=lin[1], z=lin[2]),
                                                           angular=v3(x=ang[0], y=ang[1], z=ang[2]))), t)
                if lay["joints"]:
                    js = lay["joints"]
                    vel = [(s[v[0]] * v[1]) if v else math.nan for _, _, v in js]
                    put(f"{base}/joint_states", "sensor_msgs/msg/JointState", M["sensor_msgs/msg/JointState"](
                        header=header(msg.stamp_s, t, msg.robot), name=[j for j, _, _ in js],
                        position=np.array([_angle(s, src) for _, src, _ in js], dtype=np.float64),
                        velocity=np.array(vel if any(v for _, _, v in js) else [], dtype=np.float64),
                        effort=np.array([], dtype=np.float64)), t)
            elif isinstance(msg, Command) and msg.robot in specs:
                a = specs[msg.robot].get("action", {})
                put(f"{base}/cmd", "hilstack_msgs/msg/Command", M["hilstack_msgs/msg/Command"](
                    header=header(msg.stamp_s, t, msg.robot), robot=msg.robot, names=list(a.get("names", [])),
                    units=list(a.get("units", [])), action=np.asarray(msg.action, dtype=np.float64),
                    source=msg.source, seq=max(0, msg.seq)), t)
            elif isinstance(msg, Image):
                if msg.encoding in ("jpeg", "png"):  # image_transport's names: <key>/compressed beside <key>
                    put(f"{_ros_topic(key)}/compressed", "sensor_msgs/msg/CompressedImage",
                        M["sensor_msgs/msg/CompressedImage"](header=header(msg.stamp_s, t, msg.camera),
                                                             format=msg.encoding,
                                                             data=np.frombuffer(msg.data, dtype=np.uint8)), t)
                else:
                    put(_ros_topic(key), "sensor_msgs/msg/Image", M["sensor_msgs/msg/Image"](
                        header=header(msg.stamp_s, t, msg.camera), height=msg.height, width=msg.width,
                        encoding=msg.encoding, is_bigendian=0, step=len(msg.data) // max(1, msg.height),
                        data=np.frombuffer(msg.data, dtype=np.uint8)), t)
            elif not isinstance(msg, RobotState | Command):
                put(_ros_topic(key), "hilstack_msgs/msg/Record", M["hilstack_msgs/msg/Record"](
                    header=header(msg.stamp_s, t, ""), type=type_name(type(msg)), json=encode_json(msg).decode()), t)
            else:
                res.skipped += 1  # a state or command before its robot's spec: no names to export it with
    return res
