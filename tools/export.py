"""`hil export ros2`: a recording (MCAP, JSON messages) as a ROS 2 bag (rosbag2 directory,
MCAP storage, CDR messages) that ROS 2 tools, rosbags and Foxglove read with standard types.

The `rosbags` library (pure Python) writes the bag and serializes CDR; nothing of ROS 2 needs to
be installed. Per robot, from its spec's channel names and units (``hil.Spec``):

| recorded | ROS 2 topic | type |
|---|---|---|
| state: x, y, z [m] and roll/pitch/yaw (or their cos_/sin_ pairs; ZYX Euler, as every backend's ``quat_to_rpy``) | ``/<rig>/<robot>/pose`` | ``geometry_msgs/msg/PoseStamped`` (frame ``world``) |
| state: vx, vy, vz [m/s, world frame: mocap, MuJoCo's free joint] rotated into the body frame by the pose's orientation, and wx, wy, wz [rad/s, body frame: the gyro] | ``/<rig>/<robot>/twist`` | ``geometry_msgs/msg/TwistStamped`` (frame ``<robot>``) |
| state: joint angles ``<j>`` or ``<j>_pos`` [rad] (or cos_/sin_ pairs that are no body angle), their velocities ``<j>_vel`` / ``<head>_vel_<side>`` [rad/s, rev/s → rad/s] | ``/<rig>/<robot>/joint_states`` | ``sensor_msgs/msg/JointState`` |
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

import json
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
    for name, src in angles.items():
        if name in _BODY_ANGLES:
            continue
        j = name[:-4] if name.endswith("_pos") else name  # the arms' <joint>_pos beside <joint>_vel
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


# --------------------------------------------------------------------------- LeRobot
#: the LeRobotDataset format version written (lerobot's CODEBASE_VERSION since lerobot 0.4)
LEROBOT_VERSION = "v3.0"
_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
_EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
_INDEX_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}


def _recordings(src: Path) -> list[Path]:
    from hilstack.tools.common import UserError

    if src.is_dir():
        files = sorted(src.glob("*.mcap"))
        if not files:
            raise UserError(f"{src}: no .mcap recordings in this directory")
        return files
    if not src.is_file():
        raise UserError(f"{src}: no such recording or directory")
    return [src]


def export_lerobot(src: str | Path, out: str | Path, robot: str | None = None, task: str = "",
                   force: bool = False) -> dict[str, Any]:
    """Write recordings (a file or a directory of .mcap) as a LeRobotDataset v3.0 directory: one
    LeRobot episode per recorded episode (``RobotState.episode``) of ``robot`` (default: the only
    robot with a spec). Frames are the robot's states; ``action`` is the action the driver applied
    with that state (``RobotState.action``); ``timestamp`` is the robot's clock ``t_s`` from the
    episode's first state; fps is 1 / the spec's ``period_s``. No videos: the exported features are
    state and action (images are not exported yet)."""
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    from hilstack.bus.recording import iter_messages
    from hilstack.bus.schemas import RobotState, SpecMsg
    from hilstack.tools.common import UserError

    out = Path(out)
    if out.exists():
        if not force:
            raise UserError(f"{out} exists: choose another --out or pass --force to replace it")
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    spec: dict[str, Any] | None = None
    episodes: list[list[RobotState]] = []
    for path in _recordings(Path(src)):
        specs: dict[str, dict[str, Any]] = {}
        current: dict[tuple[str, int], list[RobotState]] = {}
        for m in iter_messages(path):
            if isinstance(m.msg, SpecMsg):
                specs[m.msg.robot] = m.msg.spec
            elif isinstance(m.msg, RobotState) and m.msg.active:
                current.setdefault((m.msg.robot, m.msg.episode), []).append(m.msg)
        if robot is None and len(specs) > 1:
            raise UserError(f"{path}: robots {sorted(specs)}: choose one with --robot")
        name = robot or next(iter(specs), None)
        if name not in specs:
            raise UserError(f"{path}: no spec of robot {name!r} in this recording")
        if spec is not None and spec["state"]["names"] != specs[name]["state"]["names"]:
            raise UserError(f"{path}: robot {name!r} has other state channels than the first recording")
        spec = specs[name]
        episodes += [eps for (r, _), eps in current.items() if r == name and len(eps) > 0]
    if spec is None or not episodes:
        raise UserError(f"{src}: no active states of the robot to export")
    fps = 1.0 / float(spec["period_s"])
    if abs(fps - round(fps)) > 1e-6:
        raise UserError(f"period_s {spec['period_s']} is not 1/integer fps, which LeRobot needs")
    fps_i = int(round(fps))
    sn, an = list(spec["state"]["names"]), list(spec["action"]["names"])
    features = {
        "observation.state": {"dtype": "float32", "shape": [len(sn)], "names": sn},
        "action": {"dtype": "float32", "shape": [len(an)], "names": an},
        **_INDEX_FEATURES,
    }
    rows: dict[str, list[Any]] = {k: [] for k in features}
    ep_rows: list[dict[str, Any]] = []
    index = 0
    for e, eps in enumerate(episodes):
        t0 = eps[0].t_s
        start = index
        for f, st in enumerate(eps):
            act = st.action if len(st.action) == len(an) else [math.nan] * len(an)
            rows["observation.state"].append(np.asarray(st.state, dtype=np.float32))
            rows["action"].append(np.asarray(act, dtype=np.float32))
            rows["timestamp"].append(np.float32(st.t_s - t0))
            rows["frame_index"].append(f)
            rows["episode_index"].append(e)
            rows["index"].append(index)
            rows["task_index"].append(0)
            index += 1
        ep_rows.append({"episode_index": e, "tasks": [task or spec.get("name", "")], "length": len(eps),
                        "data/chunk_index": 0, "data/file_index": 0, "dataset_from_index": start,
                        "dataset_to_index": index, "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
    (out / "meta").mkdir(parents=True)
    cols = {}
    for k, ft in features.items():
        if ft["shape"] == [1]:
            cols[k] = pa.array(rows[k], type=pa.float32() if ft["dtype"] == "float32" else pa.int64())
        else:
            cols[k] = pa.FixedSizeListArray.from_arrays(pa.array(np.concatenate(rows[k]), type=pa.float32()),
                                                        ft["shape"][0])
    data_path = out / _DATA_PATH.format(chunk_index=0, file_index=0)
    data_path.parent.mkdir(parents=True)
    pq.write_table(pa.table(cols), data_path)
    ep_path = out / _EPISODES_PATH.format(chunk_index=0, file_index=0)
    ep_path.parent.mkdir(parents=True)
    pd.DataFrame(ep_rows).to_parquet(ep_path)
    task_name = task or spec.get("name", "")
    pd.DataFrame({"task_index": [0]}, index=pd.Index([task_name], name="task")).to_parquet(out / "meta" / "tasks.parquet")
    stats = {}
    for k in ("observation.state", "action"):
        a = np.stack(rows[k]).astype(np.float64)
        stats[k] = {"min": np.nanmin(a, 0).tolist(), "max": np.nanmax(a, 0).tolist(),
                    "mean": np.nanmean(a, 0).tolist(), "std": np.nanstd(a, 0).tolist(), "count": [len(a)]}
    (out / "meta" / "stats.json").write_text(json.dumps(stats, indent=2))
    info = {
        "codebase_version": LEROBOT_VERSION, "robot_type": spec.get("name"), "total_episodes": len(episodes),
        "total_frames": index, "total_tasks": 1, "chunks_size": 1000, "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200, "fps": fps_i, "splits": {"train": f"0:{len(episodes)}"},
        "data_path": _DATA_PATH, "video_path": None, "features": features,
    }
    (out / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    return {"out": str(out), "episodes": len(episodes), "frames": index, "fps": fps_i, "robot_type": spec.get("name")}


def check_lerobot(root: str | Path) -> dict[str, Any]:
    """What lerobot's own ``LeRobotDataset(repo_id, root=root)`` checks when it loads a local
    dataset, ported from lerobot 0.4.4 (``datasets/lerobot_dataset.py``: ``load_metadata``,
    ``load_hf_dataset``, ``_check_cached_episodes_sufficient``, ``__getitem__``; ``datasets/utils.py``:
    ``load_info``, ``check_version_compatibility``, ``_validate_feature_names``,
    ``get_hf_features_from_features``, ``load_nested_dataset``). lerobot itself is not a dependency:
    it pins torch < 2.11 and rerun-sdk < 0.27, older than this project's. Raises ValueError naming
    the first problem; returns {"episodes", "frames", "fps", "features"}."""
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    root = Path(root)
    info = json.loads((root / "meta" / "info.json").read_text())  # load_info
    for key in ("codebase_version", "fps", "features", "data_path", "total_episodes", "total_frames"):
        if key not in info:
            raise ValueError(f"meta/info.json: no {key!r}")
    major = int(str(info["codebase_version"]).lstrip("v").split(".")[0])
    if major < 3:  # check_version_compatibility: BackwardCompatibilityError
        raise ValueError(f"codebase_version {info['codebase_version']}: lerobot 0.4 reads v3.x")
    feats = info["features"]
    bad = [k for k in feats if "/" in k]  # _validate_feature_names
    if bad:
        raise ValueError(f"feature names should not contain '/': {bad}")
    tasks = pd.read_parquet(root / "meta" / "tasks.parquet")  # load_tasks
    ep_files = sorted((root / "meta" / "episodes").glob("*/*.parquet"))  # load_episodes -> load_nested_dataset
    if not ep_files:
        raise ValueError("meta/episodes: no parquet file")
    eps = pd.concat([pd.read_parquet(p) for p in ep_files], ignore_index=True)
    for col in ("episode_index", "tasks", "length", "dataset_from_index", "dataset_to_index",
                "data/chunk_index", "data/file_index"):
        if col not in eps.columns:
            raise ValueError(f"meta/episodes: no column {col!r}")
    data_files = sorted((root / "data").glob("*/*.parquet"))  # load_hf_dataset -> load_nested_dataset
    if not data_files:
        raise ValueError(f"Provided directory does not contain any parquet file: {root / 'data'}")
    table = pa.concat_tables([pq.read_table(p) for p in data_files])
    want = {"float32": pa.float32(), "float64": pa.float64(), "int64": pa.int64(), "bool": pa.bool_()}
    for k, ft in feats.items():  # get_hf_features_from_features: Value for shape (1,), Sequence for 1-D
        if ft["dtype"] in ("video", "image"):
            continue
        if k not in table.column_names:
            raise ValueError(f"feature {k!r} missing from the data files")
        typ, shape = table.schema.field(k).type, tuple(ft["shape"])
        if shape == (1,):
            ok = typ == want.get(ft["dtype"])
        elif len(shape) == 1:
            ok = (pa.types.is_fixed_size_list(typ) and typ.list_size == shape[0] or pa.types.is_list(typ)) and \
                typ.value_type == want.get(ft["dtype"])
            if ok and pa.types.is_list(typ):
                ok = all(len(v) == shape[0] for v in table.column(k).to_pylist())
        else:
            ok = False  # this exporter writes no 2-D+ features
        if not ok:
            raise ValueError(f"feature {k!r}: data type {typ} does not match {ft['dtype']} {list(shape)}")
    n = table.num_rows
    ep_idx = set(table.column("episode_index").to_pylist())
    if not set(range(info["total_episodes"])) <= ep_idx:  # _check_cached_episodes_sufficient
        raise ValueError(f"episodes {sorted(set(range(info['total_episodes'])) - ep_idx)} have no frames")
    if n != info["total_frames"] or int(eps["length"].sum()) != n:
        raise ValueError(f"total_frames {info['total_frames']}, episode lengths {int(eps['length'].sum())}, rows {n}")
    idx = table.column("index").to_numpy()
    if not np.array_equal(idx, np.arange(n)):
        raise ValueError("index is not 0..total_frames-1 in order")
    for _, e in eps.iterrows():  # the ranges lerobot's delta_timestamps queries index by
        sel = table.column("episode_index").to_numpy() == e["episode_index"]
        rows = np.flatnonzero(sel)
        if rows.size != e["length"] or rows[0] != e["dataset_from_index"] or rows[-1] + 1 != e["dataset_to_index"]:
            raise ValueError(f"episode {e['episode_index']}: rows {rows[0]}..{rows[-1]} vs metadata "
                             f"{e['dataset_from_index']}..{e['dataset_to_index']}")
    t_idx = set(table.column("task_index").to_pylist())
    if not t_idx <= set(tasks["task_index"].tolist()):  # __getitem__: self.meta.tasks.iloc[task_idx].name
        raise ValueError(f"task_index {sorted(t_idx)} not all in meta/tasks.parquet")
    # not a load-time check of lerobot 0.4 (v2's check_timestamps_sync was): frames 1/fps apart within its
    # default tolerance_s, what delta_timestamps and video decoding assume; a real rig's jitter shows here
    ts, ep = table.column("timestamp").to_numpy(), table.column("episode_index").to_numpy()
    same = ep[1:] == ep[:-1]
    gaps = np.diff(ts)[same]
    in_sync = bool(np.all(np.abs(gaps - 1.0 / info["fps"]) <= 1e-4)) if gaps.size else True
    return {"episodes": int(info["total_episodes"]), "frames": n, "fps": info["fps"], "features": sorted(feats),
            "timestamps_in_sync": in_sync}
