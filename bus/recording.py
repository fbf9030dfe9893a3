"""MCAP recording, replay and inspection of everything a rig says.

One file per session; one channel per key expression; one schema per message type
(JSON Schema generated from the msgspec definition, in the subset Foxglove parses),
messages JSON-encoded so any MCAP tool (the ``mcap`` reader, Foxglove, rerun's MCAP
importer) decodes them. Robot poses are also written on Foxglove's well-known
``PoseInFrame``/``FrameTransform`` schemas, and JPEG/PNG camera images as
``CompressedImage`` (derived channels, not replayed). A JPEG/PNG image's bytes are stored
once, in its ``CompressedImage``: its ``hil.Image`` record keeps the metadata with empty
``data``, and :func:`iter_messages` puts the bytes back (:func:`compressed_image_data`).
Chunks are closed, flushed and fsync'ed by time (every ``FLUSH_PERIOD_S``), so a crash
loses at most that much data; :func:`read_messages` reads a truncated file up to the
damage.
"""

from __future__ import annotations

import json
import logging
import math
import os
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import foxglove.messages as fg
import msgspec
import zenoh
from mcap.exceptions import McapError
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.schemas import (
    ALL_TYPES,
    AnyMsg,
    EStop,
    Image,
    MalformedMessage,
    Msg,
    Plan,
    RobotState,
    SpecMsg,
    decode,
    decode_json,
    encode,
    encode_json,
    json_schema,
    type_name,
)
from hilstack.configs.schema import BusConfig

log = logging.getLogger(__name__)

_BY_TAG: dict[str, type[Msg]] = {type_name(t): t for t in ALL_TYPES}

#: parent frame of every robot pose in the Foxglove channels
WORLD_FRAME = "world"


def foxglove_pose_topic(rig: str, robot: str) -> str:
    """Channel of a robot's ``foxglove.PoseInFrame`` (beside ``hil/<rig>/<robot>/state``)."""
    return f"{keys.root(rig)}/foxglove/{robot}/pose"


def foxglove_tf_topic(rig: str) -> str:
    """Channel of the ``foxglove.FrameTransform`` world -> robot of every robot of the rig."""
    return f"{keys.root(rig)}/foxglove/tf"


def planar_pose(names: tuple[str, ...] | list[str], state: list[float]) -> tuple[float, float, float, float] | None:
    """(x, y, z [m], yaw [rad]) from a state vector with channels named ``x``, ``y``
    (optionally ``z``) and ``yaw`` or ``cos_yaw``/``sin_yaw``; None if it has no x/y."""
    idx = {n: i for i, n in enumerate(names)}
    if "x" not in idx or "y" not in idx or max(idx["x"], idx["y"]) >= len(state):
        return None

    def get(n: str, default: float = 0.0) -> float:
        i = idx.get(n)
        return float(state[i]) if i is not None and i < len(state) else default

    if "yaw" in idx:
        yaw = get("yaw")
    elif "cos_yaw" in idx and "sin_yaw" in idx:
        yaw = math.atan2(get("sin_yaw"), get("cos_yaw"))
    else:
        yaw = 0.0
    return get("x"), get("y"), get("z"), yaw


class FoxglovePoses:
    """Robot poses on Foxglove's well-known schemas, so its 3D panel shows the robots.

    Feed every message to :meth:`derive`: it remembers each robot's state names from its
    ``SpecMsg``, and for a ``RobotState`` of a robot whose names include x/y(/yaw) it
    returns a ``foxglove.PoseInFrame`` in ``world`` (on :func:`foxglove_pose_topic`) and a
    ``foxglove.FrameTransform`` world -> <robot> (on :func:`foxglove_tf_topic`), stamped
    with the state's ``stamp_s`` (else ``log_ns``); for a robot with a kinematic chain (an
    arm), its links' FrameTransforms on each state and its 3-D model (:func:`foxglove_model`
    on :func:`foxglove_model_topic`) on each spec. Messages are foxglove-sdk's classes
    (protobuf: ``.encode()``, schema from ``type(m).get_schema()``)."""

    def __init__(self) -> None:
        self._names: dict[str, tuple[str, ...]] = {}
        self._chains: dict[str, list[dict[str, Any]]] = {}

    def derive(self, topic: str, msg: Msg, log_ns: int) -> list[tuple[str, Any, int]]:
        """[(topic, foxglove message, its stamp [ns since the epoch])] derived from ``msg``."""
        if isinstance(msg, SpecMsg):
            try:
                self._names[msg.robot] = tuple(msg.spec["state"]["names"])
                if msg.spec.get("chain"):
                    self._chains[msg.robot] = list(msg.spec["chain"])
            except (KeyError, TypeError, AttributeError):
                return []  # a spec without state names: no pose for this robot
            chain = self._chains.get(msg.robot)
            if not chain:
                return []
            parts = topic.split("/")
            rig = parts[1] if len(parts) > 2 and parts[0] == "hil" else "unknown"
            stamp_ns = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
            try:  # each spec: a viewer that joins late gets the model with the next one
                return [(foxglove_model_topic(rig, msg.robot), foxglove_model(msg.robot, chain, stamp_ns), stamp_ns)]
            except (KeyError, TypeError, ValueError):
                return []
        if not isinstance(msg, RobotState) or msg.robot not in self._names:
            return []
        links = self._links(topic, msg, log_ns)
        pose = planar_pose(self._names[msg.robot], msg.state)
        if pose is None or not all(math.isfinite(v) for v in pose):
            return links
        x, y, z, yaw = pose
        parts = topic.split("/")
        rig = parts[1] if len(parts) > 2 and parts[0] == "hil" else "unknown"
        stamp_ns = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
        ts = fg.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)
        pos = fg.Vector3(x=x, y=y, z=z)
        q = fg.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
        return [
            (foxglove_pose_topic(rig, msg.robot),
             fg.PoseInFrame(timestamp=ts, frame_id=WORLD_FRAME, pose=fg.Pose(position=pos, orientation=q)),
             stamp_ns),
            (foxglove_tf_topic(rig),
             fg.FrameTransform(timestamp=ts, parent_frame_id=WORLD_FRAME, child_frame_id=msg.robot,
                               translation=pos, rotation=q),
             stamp_ns),
            *links,
        ]

    def _links(self, topic: str, msg: RobotState, log_ns: int) -> list[tuple[str, Any, int]]:
        """The FrameTransforms of a robot's kinematic chain (an arm in Foxglove's 3D panel); a
        robot without a planar pose is placed at the world's origin."""
        chain = self._chains.get(msg.robot)
        tfs = None if chain is None else chain_transforms(msg.robot, chain, self._names[msg.robot], msg.state)
        if not tfs:
            return []
        parts = topic.split("/")
        rig = parts[1] if len(parts) > 2 and parts[0] == "hil" else "unknown"
        stamp_ns = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
        ts = fg.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)
        if planar_pose(self._names[msg.robot], msg.state) is None:
            tfs = [(WORLD_FRAME, msg.robot, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), *tfs]
        return [(foxglove_tf_topic(rig),
                 fg.FrameTransform(timestamp=ts, parent_frame_id=a, child_frame_id=b,
                                   translation=fg.Vector3(x=t[0], y=t[1], z=t[2]),
                                   rotation=fg.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])), stamp_ns)
                for a, b, t, q in tfs]


def chain_transforms(robot: str, chain: list[dict[str, Any]], names: list[str] | tuple[str, ...],
                     state: list[float]) -> list[tuple[str, str, tuple[float, float, float],
                                                       tuple[float, float, float, float]]] | None:
    """(parent frame, child frame, translation [m], rotation quaternion x, y, z, w) of each link
    of a spec's kinematic ``chain`` (``RobotSpec.chain``): link ``<robot>/<joint>_link`` sits at
    the joint's offset in its parent link and turns about the joint's axis by the state's
    ``<joint>_pos`` (or ``<joint>``) angle. None if an angle is missing or not finite."""
    idx = {n: i for i, n in enumerate(names)}
    out, parent = [], robot
    for link in chain:
        j = link["joint"]
        i = idx.get(f"{j}_pos", idx.get(j))
        if i is None or i >= len(state) or not math.isfinite(state[i]):
            return None
        ax = link["axis"]
        norm = math.sqrt(sum(a * a for a in ax)) or 1.0
        s, c = math.sin(state[i] / 2), math.cos(state[i] / 2)
        child = f"{robot}/{j}_link"
        out.append((parent, child, tuple(link["xyz"]), (ax[0] / norm * s, ax[1] / norm * s, ax[2] / norm * s, c)))
        parent = child
    return out


#: the links' drawn radius [m]: the WidowX sim's capsules (sim_backends/widowx/model.py)
LINK_RADIUS_M = 0.018
#: the last link has no next link to reach: a stub this long along its joint axis [m]
TOOL_STUB_M = 0.06


def foxglove_model_topic(rig: str, robot: str) -> str:
    """Channel of a robot's 3-D model (``foxglove.SceneUpdate``, entities locked to its link frames)."""
    return f"{keys.root(rig)}/foxglove/{robot}/model"


def chain_segments(robot: str, chain: list[dict[str, Any]]) -> list[tuple[str, tuple[float, float, float],
                                                                           tuple[float, float, float]]]:
    """The robot drawn from its spec's kinematic ``chain`` alone, as capsules (as the sim's MJCF
    draws the WidowX, there to twice each link's centre of mass, which the spec does not
    carry): (frame, start, end) in that frame [m]. The base, in the
    robot's frame, from its origin to the first joint; each link, in its own frame
    (:func:`chain_transforms`), from its origin to the next link's offset; the last link a
    :data:`TOOL_STUB_M` stub along its joint axis."""
    out = []
    parent = robot
    for i, link in enumerate(chain):
        out.append((parent, (0.0, 0.0, 0.0), tuple(float(v) for v in link["xyz"])))
        parent = f"{robot}/{link['joint']}_link"
        if i == len(chain) - 1:
            ax = link["axis"]
            norm = math.sqrt(sum(a * a for a in ax)) or 1.0
            out.append((parent, (0.0, 0.0, 0.0), tuple(TOOL_STUB_M * a / norm for a in ax)))
    return out


def quat_z_to(d: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """The quaternion (x, y, z, w) turning +z onto the direction ``d``."""
    n = math.sqrt(sum(v * v for v in d)) or 1.0
    x, y, z = (v / n for v in d)
    # half-way vector between +z and d (d = -z: a half turn about x)
    hx, hy, hz = x, y, z + 1.0
    hn = math.sqrt(hx * hx + hy * hy + hz * hz)
    if hn < 1e-9:
        return (1.0, 0.0, 0.0, 0.0)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    # q = (z x h, z . h)
    return (-hy, hx, 0.0, hz)


def foxglove_model(robot: str, chain: list[dict[str, Any]], stamp_ns: int) -> Any:
    """A ``foxglove.SceneUpdate``: one entity per segment of :func:`chain_segments`, a cylinder
    with spheres at both ends (Foxglove has no capsule), ``frame_locked`` to its link's frame so
    the 3D panel moves it with the link's FrameTransforms."""
    ts = fg.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)
    color = fg.Color(r=0.15, g=0.15, b=0.15, a=1.0)
    d = 2 * LINK_RADIUS_M
    entities = []
    for i, (frame, a, b) in enumerate(chain_segments(robot, chain)):
        seg = tuple(bb - aa for aa, bb in zip(a, b, strict=True))
        length = math.sqrt(sum(v * v for v in seg))
        mid = fg.Vector3(x=(a[0] + b[0]) / 2, y=(a[1] + b[1]) / 2, z=(a[2] + b[2]) / 2)
        q = quat_z_to(seg)
        ends = [fg.SpherePrimitive(pose=fg.Pose(position=fg.Vector3(x=p[0], y=p[1], z=p[2]),
                                                orientation=fg.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                                   size=fg.Vector3(x=d, y=d, z=d), color=color) for p in (a, b)]
        cyl = fg.CylinderPrimitive(pose=fg.Pose(position=mid, orientation=fg.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])),
                                   size=fg.Vector3(x=d, y=d, z=length), bottom_scale=1.0, top_scale=1.0, color=color)
        entities.append(fg.SceneEntity(timestamp=ts, frame_id=frame, id=f"{robot}/segment{i}",
                                       lifetime=fg.Duration(sec=0, nsec=0), frame_locked=True,
                                       cylinders=[cyl] if length > 0 else [], spheres=ends))
    return fg.SceneUpdate(entities=entities)


def foxglove_image_topic(rig: str, camera: str) -> str:
    """Channel of a camera's ``foxglove.CompressedImage`` (beside ``hil/<rig>/<camera>/image``)."""
    return f"{keys.root(rig)}/foxglove/{camera}/image"


#: hil.Image encodings that are already a file format Foxglove and rerun decode
COMPRESSED_IMAGE_FORMATS = {"jpeg": "jpeg", "png": "png"}


def foxglove_image(topic: str, msg: Msg, log_ns: int) -> tuple[str, Any, int] | None:
    """A ``foxglove.CompressedImage`` (frame ``<camera>``) for a JPEG/PNG ``hil.Image``, else None.
    The bytes are copied as they are: nothing is re-encoded."""
    if not isinstance(msg, Image) or msg.encoding not in COMPRESSED_IMAGE_FORMATS:
        return None
    parts = topic.split("/")
    rig = parts[1] if len(parts) > 2 and parts[0] == "hil" else "unknown"
    stamp_ns = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
    ts = fg.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)
    return (foxglove_image_topic(rig, msg.camera),
            fg.CompressedImage(timestamp=ts, frame_id=msg.camera, data=msg.data,
                               format=COMPRESSED_IMAGE_FORMATS[msg.encoding]),
            stamp_ns)


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    v = shift = 0
    while True:
        b = buf[i]
        i += 1
        v |= (b & 0x7F) << shift
        if b < 0x80:
            return v, i
        shift += 7


def compressed_image_data(payload: bytes) -> bytes:
    """The ``data`` field (number 2, bytes) of a protobuf ``foxglove.CompressedImage``.

    The protobuf wire format read directly (varint keys; wire types 0, 1, 2 and 5), so
    reading a recording needs no protobuf runtime; the foxglove SDK only encodes."""
    i, n = 0, len(payload)
    while i < n:
        key, i = _varint(payload, i)
        field_no, wire = key >> 3, key & 7
        if wire == 0:
            _, i = _varint(payload, i)
        elif wire == 1:
            i += 8
        elif wire == 5:
            i += 4
        elif wire == 2:
            ln, i = _varint(payload, i)
            if field_no == 2:
                return bytes(payload[i:i + ln])
            i += ln
        else:
            raise ValueError(f"CompressedImage: unsupported protobuf wire type {wire}")
    return b""


def state_fields_topic(rig: str, robot: str) -> str:
    """Channel of a robot's named state fields (:class:`StateFields`), beside its poses."""
    return f"{keys.root(rig)}/foxglove/{robot}/fields"


def _num(v: Any) -> float | None:
    return float(v) if math.isfinite(v) else None  # JSON has no NaN: null, a gap in a plot


class StateFields:
    """Each robot's state, action and numeric health counters as *named* JSON fields, on a
    JSON schema made per robot from its spec: Foxglove plots ``state.crank_vel_l`` instead of
    ``.state[19]``. A derived channel (:func:`state_fields_topic`, schema ``hil.StateFields/<robot>``,
    not replayed, not read back by :func:`iter_messages`): the ``hil.RobotState`` channel stays
    the record. The health counters (dropped frames, stale stops, refused commands...) are the
    numeric entries of the robot's first health report."""

    def __init__(self) -> None:
        self._spec: dict[str, tuple[list[str], list[str]]] = {}
        self._health: dict[str, list[str]] = {}

    def derive(self, topic: str, msg: Msg) -> tuple[str, str, dict[str, Any] | None, bytes] | None:
        """(topic, schema name, schema or None if already given for this robot, JSON payload)."""
        if isinstance(msg, SpecMsg):
            try:
                self._spec[msg.robot] = (list(msg.spec["state"]["names"]), list(msg.spec["action"]["names"]))
            except (KeyError, TypeError):
                pass
            return None
        if not isinstance(msg, RobotState) or msg.robot not in self._spec:
            return None
        sn, an = self._spec[msg.robot]
        if len(msg.state) != len(sn):
            return None
        schema = None
        if msg.robot not in self._health:
            self._health[msg.robot] = sorted(k for k, v in msg.health.items()
                                             if isinstance(v, (int, float)) and not isinstance(v, bool))
            num = {"type": "number"}
            schema = {"type": "object", "title": f"hil.StateFields/{msg.robot}", "properties": {
                "robot": {"type": "string"}, "t_s": num, "ok": {"type": "boolean"}, "active": {"type": "boolean"},
                "episode": {"type": "integer"}, "obs_seq": {"type": "integer"},
                "state": {"type": "object", "properties": {n: num for n in sn}},
                "action": {"type": "object", "properties": {n: num for n in an}},
                "health": {"type": "object", "properties": {n: num for n in self._health[msg.robot]}},
            }}
        act = msg.action if len(msg.action) == len(an) else []
        payload = {
            "robot": msg.robot, "t_s": _num(msg.t_s), "ok": msg.ok, "active": msg.active, "episode": msg.episode,
            "obs_seq": msg.obs_seq, "state": {n: _num(v) for n, v in zip(sn, msg.state, strict=True)},
            "action": {n: _num(v) for n, v in zip(an, act, strict=False)},
            "health": {k: _num(msg.health[k]) for k in self._health[msg.robot]
                       if isinstance(msg.health.get(k), (int, float)) and not isinstance(msg.health.get(k), bool)},
        }
        parts = topic.split("/")
        rig = parts[1] if len(parts) > 2 and parts[0] == "hil" else "unknown"
        return state_fields_topic(rig, msg.robot), f"hil.StateFields/{msg.robot}", schema, json.dumps(payload).encode()


def timing_topic(rig: str, robot: str) -> str:
    """Channel of a robot's timing counters (:class:`TimingCounters`), beside its named fields."""
    return f"{keys.root(rig)}/foxglove/{robot}/timing"


class TimingCounters:
    """Each robot's timing as the recorder saw it, one JSON message per state on
    :func:`timing_topic` (schema ``hil.Timing``; derived, not replayed): ``rate_hz``, states per
    second over the last :attr:`WINDOW_S` of the states' stamps; ``period_max_ms``, the longest
    gap between two of them in that window; ``dropped_states``, states missing from the
    recording (gaps in the driver's ``obs_seq``, counted since the recording started; a
    sequence that starts again, a restarted driver, is not a gap); and the driver node's own
    deadline counters from its health (``cycle_late``: periods started late, ``cycle_missed``:
    periods skipped after a stall; bus/cycle.py), absent on lockstep rigs; ``late_plans``, the
    plans of the robot's MPC controller that missed their period (``Plan.late_count`` of its
    latest plan on ``hil/<rig>/mpc/plan``: steps sent from the shifted last plan instead), from
    the first plan recorded on, and ``plan_samples``, the sample count of that latest plan (on a
    wall-clock rig it follows the load). Like the named fields, only for robots whose spec the recording
    holds (every driver node sends one)."""

    WINDOW_S = 1.0
    SCHEMA: dict[str, Any] = {"type": "object", "title": "hil.Timing", "properties": {
        "robot": {"type": "string"}, "rate_hz": {"type": "number"}, "period_max_ms": {"type": "number"},
        "dropped_states": {"type": "integer"}, "cycle_late": {"type": "integer"}, "cycle_missed": {"type": "integer"},
        "late_plans": {"type": "integer"}, "plan_samples": {"type": "integer"}}}

    def __init__(self) -> None:
        self._stamps: dict[str, list[float]] = {}
        self._seq: dict[str, int] = {}
        self._dropped: dict[str, int] = {}
        self._robots: set[str] = set()
        self._late_plans: dict[str, int] = {}
        self._plan_samples: dict[str, int] = {}

    def derive(self, topic: str, msg: Msg, log_ns: int) -> tuple[str, bytes] | None:
        """(topic, JSON payload) for a ``RobotState`` of a robot with a spec, else None."""
        if isinstance(msg, SpecMsg):
            self._robots.add(msg.robot)
        if isinstance(msg, Plan):
            self._late_plans[msg.robot] = msg.late_count
            self._plan_samples[msg.robot] = msg.samples
        if not isinstance(msg, RobotState) or msg.robot not in self._robots:
            return None
        r = msg.robot
        t = msg.stamp_s if msg.stamp_s else log_ns * 1e-9
        st = self._stamps.setdefault(r, [])
        st.append(t)
        while st and st[0] < t - self.WINDOW_S:
            del st[0]
        last = self._seq.get(r)
        if last is not None and msg.obs_seq > last + 1:
            self._dropped[r] = self._dropped.get(r, 0) + msg.obs_seq - last - 1
        self._seq[r] = msg.obs_seq
        span = st[-1] - st[0]
        payload: dict[str, Any] = {
            "robot": r, "rate_hz": (len(st) - 1) / span if span > 0 else None,
            "period_max_ms": max((b - a for a, b in zip(st, st[1:], strict=False)), default=0.0) * 1e3 if len(st) > 1
            else None, "dropped_states": self._dropped.get(r, 0)}
        for k in ("cycle_late", "cycle_missed"):
            v = msg.health.get(k)
            if isinstance(v, int) and not isinstance(v, bool):
                payload[k] = v
        if r in self._late_plans:
            payload["late_plans"] = self._late_plans[r]
            if self._plan_samples.get(r):
                payload["plan_samples"] = self._plan_samples[r]
        parts = topic.split("/")
        rig = parts[1] if len(parts) > 2 and parts[0] == "hil" else "unknown"
        return timing_topic(rig, r), json.dumps(payload).encode()


class _McapFoxglovePoses:
    """Writes :class:`FoxglovePoses` messages to an mcap ``Writer`` (protobuf channels)."""

    def __init__(self, writer: Writer):
        self._w = writer
        self._poses = FoxglovePoses()
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._fields = StateFields()
        self._timing = TimingCounters()
        self._timing_schema: int | None = None

    def _channel(self, topic: str, cls: Any) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sch = cls.get_schema()
            sid = self._schemas.get(sch.name)
            if sid is None:
                sid = self._schemas[sch.name] = self._w.register_schema(sch.name, sch.encoding, bytes(sch.data))
            cid = self._channels[topic] = self._w.register_channel(topic, "protobuf", sid)
        return cid

    def on_message(self, topic: str, msg: Msg, log_ns: int) -> int:
        """Write the Foxglove messages derived from ``msg``; returns how many."""
        out = self._poses.derive(topic, msg, log_ns)
        img = foxglove_image(topic, msg, log_ns)
        if img is not None:
            out.append(img)
        for t, m, stamp_ns in out:
            self._w.add_message(self._channel(t, type(m)), log_time=log_ns, data=m.encode(), publish_time=stamp_ns)
        timing = self._timing.derive(topic, msg, log_ns)
        if timing is not None:
            t, data = timing
            if t not in self._channels:
                if self._timing_schema is None:
                    self._timing_schema = self._w.register_schema(
                        "hil.Timing", "jsonschema", json.dumps(TimingCounters.SCHEMA).encode())
                self._channels[t] = self._w.register_channel(t, "json", self._timing_schema)
            pub = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
            self._w.add_message(self._channels[t], log_time=log_ns, data=data, publish_time=pub)
            out = [*out, timing]  # counted below
        fields = self._fields.derive(topic, msg)
        if fields is not None:
            t, name, schema, data = fields
            if t not in self._channels:
                if schema is None:
                    return len(out)  # a second rig's robot of the same name: its schema is the first one's
                sid = self._w.register_schema(name, "jsonschema", json.dumps(schema).encode())
                self._channels[t] = self._w.register_channel(t, "json", sid)
            pub = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
            self._w.add_message(self._channels[t], log_time=log_ns, data=data, publish_time=pub)
            return len(out) + 1
        return len(out)


#: the 8 bytes every MCAP file starts (and ends) with
MCAP_MAGIC = b"\x89MCAP0\r\n"


class NotARecording(ValueError):
    """The file is not an MCAP recording (empty, another format, cut inside its first bytes)."""


class RecordingExists(FileExistsError):
    """The output file exists and overwriting it was not asked for."""


def check_mcap(path: str | Path) -> None:
    """Raise :class:`NotARecording` (one line naming the file and why) unless ``path``
    starts with the MCAP magic. A file cut after its magic is a (damaged) recording."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as e:
        raise NotARecording(f"{path}: cannot read it ({e.strerror or e})") from None
    if head == MCAP_MAGIC:
        return
    if not head:
        why = "the file is empty"
    elif MCAP_MAGIC.startswith(head):
        why = f"{len(head)} bytes, cut before anything was recorded"
    else:
        why = f"it starts with {head!r}, not the MCAP magic"
    raise NotARecording(f"{path} is not an MCAP recording ({why})")


def open_new(path: str | Path, overwrite: bool = False):  # noqa: ANN201 - a binary file object
    """Open ``path`` for writing, creating its directory. An existing file is never
    replaced unless ``overwrite`` (:class:`RecordingExists` otherwise; the check and the
    creation are one atomic ``open(..., "xb")``)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(21, "is a directory", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        return open(path, "wb" if overwrite else "xb")  # noqa: SIM115 - the caller closes it
    except FileExistsError:
        raise RecordingExists(17, "exists (not overwritten)", str(path)) from None


#: what a cut or corrupted file raises while it is streamed (the mcap package reads
#: lengths and numbers with ``struct``): reading stops there and keeps what came before
_DAMAGE = (McapError, EOFError, ValueError, KeyError, OSError, struct.error)


class RecordingClosed(RuntimeError):
    """A write to a recording that is already closed (the message is not in the file)."""


#: default bound on what a crash can lose: waiting messages are written out (chunk
#: closed, file flushed and fsync'ed) at most this long after the previous flush [s]
FLUSH_PERIOD_S = 0.5


class McapLog:
    """Write typed messages to an MCAP file (thread-compatible: one writer thread).

    Durability is bounded by time, not by size: the mcap ``Writer`` keeps messages in
    an open chunk until ``chunk_size`` bytes; :meth:`flush_if_due` (called by every
    :meth:`write`, and by the recorder's loop when nothing arrives) closes the chunk,
    flushes and fsyncs the file once ``flush_period_s`` passed since the last flush.
    A crash (SIGKILL, power loss) therefore loses at most the messages written during
    the last ``flush_period_s`` plus the caller's polling delay; readers recover
    everything before the damage (:func:`read_messages`).
    """

    def __init__(
        self,
        path: str | Path,
        chunk_size: int = 64 * 1024,
        metadata: dict[str, str] | None = None,
        flush_period_s: float = FLUSH_PERIOD_S,
        foxglove: bool = True,
        overwrite: bool = True,
    ):
        if not flush_period_s > 0:
            raise ValueError(f"flush_period_s must be > 0, got {flush_period_s}")
        self.path = Path(path)
        self.flush_period_s = flush_period_s
        # overwrite=False: an existing file is refused (RecordingExists), never truncated
        self._f = open_new(self.path, overwrite)
        self._w = Writer(self._f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._w.start(profile="", library="hilstack")
        if metadata:
            self._w.add_metadata("hilstack", {k: str(v) for k, v in metadata.items()})
        self._schemas: dict[type[Msg], int] = {}
        self._channels: dict[str, int] = {}
        self._fox = _McapFoxglovePoses(self._w) if foxglove else None
        #: hil messages written (the derived Foxglove messages are not counted)
        self.count = 0
        #: messages written since the last flush (in the open chunk, not on disk yet)
        self.pending = 0
        self._last_flush_s = time.monotonic()
        self._closed = False
        self.flush()  # header and metadata on disk before the first message

    @property
    def closed(self) -> bool:
        return self._closed

    def _channel(self, topic: str, typ: type[Msg]) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schemas.get(typ)
            if sid is None:
                sid = self._w.register_schema(
                    name=type_name(typ), encoding="jsonschema", data=json.dumps(json_schema(typ)).encode()
                )
                self._schemas[typ] = sid
            cid = self._w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            self._channels[topic] = cid
        return cid

    def write(self, topic: str, msg: Msg, log_time_ns: int | None = None) -> None:
        """Append one message (``log_time_ns``: receive time, ns since the epoch; default now).

        Raises :class:`RecordingClosed` after :meth:`close`: nothing is written then."""
        if self._closed:
            raise RecordingClosed(f"{self.path} is closed: {type_name(type(msg))} on {topic} not recorded")
        cid = self._channel(topic, type(msg))
        log_ns = time.time_ns() if log_time_ns is None else log_time_ns
        pub_ns = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
        record = msg
        if self._fox is not None and isinstance(msg, Image) and msg.encoding in COMPRESSED_IMAGE_FORMATS:
            # the bytes go once, into the CompressedImage written right after (iter_messages rejoins them)
            record = msgspec.structs.replace(msg, data=b"")
        self._w.add_message(cid, log_time=log_ns, data=encode_json(record), publish_time=pub_ns, sequence=msg.seq)
        self.count += 1
        self.pending += 1
        if self._fox is not None:
            self.pending += self._fox.on_message(topic, msg, log_ns)
        self.flush_if_due()

    def flush_if_due(self) -> bool:
        """Flush (see :meth:`flush`) if ``flush_period_s`` passed since the last one and
        messages are pending; returns whether it flushed."""
        if self._closed or self.pending == 0 or time.monotonic() - self._last_flush_s < self.flush_period_s:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        """Close the open chunk, write it out and fsync: everything written so far survives a crash."""
        if self._closed:
            raise RecordingClosed(f"{self.path} is closed: nothing to flush")
        self._w.flush()
        # page cache survives a killed process; fsync makes it survive a power cut too
        os.fsync(self._f.fileno())
        self.pending = 0
        self._last_flush_s = time.monotonic()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._w.finish()
            self._f.flush()
            os.fsync(self._f.fileno())
        finally:
            self._f.close()

    def __enter__(self) -> McapLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class RecordedMessage:
    topic: str
    log_time_ns: int
    publish_time_ns: int
    msg: Msg


@dataclass
class ReadResult:
    messages: list[RecordedMessage] = field(default_factory=list)
    truncated: bool = False
    error: str | None = None
    #: messages of hil types that did not decode (skipped, reading went on)
    undecodable: int = 0
    #: first such decode error, "topic: why"
    undecodable_error: str | None = None
    #: channels of other schemas (the Foxglove poses...): topic -> {"schema", "count"}
    foreign: dict[str, dict[str, Any]] = field(default_factory=dict)


def iter_messages(path: str | Path, result: ReadResult | None = None) -> Iterator[RecordedMessage]:
    """Stream our messages in file order; stops quietly at a truncated tail (sets
    ``result.truncated``). A single undecodable message is skipped and counted
    (``result.undecodable``); channels of other schemas are counted in ``result.foreign``."""
    res = result if result is not None else ReadResult()
    check_mcap(path)
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, int]] = {}
    #: JPEG/PNG images written without their bytes, waiting for their CompressedImage (the next
    #: message on the camera's Foxglove channel): that channel's topic -> the message
    held: dict[str, RecordedMessage] = {}
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                kind = type(rec).__name__
                if kind == "Schema":
                    schemas[rec.id] = rec.name
                elif kind == "Channel":
                    channels[rec.id] = (rec.topic, rec.schema_id)
                elif kind == "Message":
                    topic, sid = channels[rec.channel_id]
                    typ = _BY_TAG.get(schemas.get(sid, ""))
                    if typ is None:
                        other = res.foreign.setdefault(topic, {"schema": schemas.get(sid, ""), "count": 0})
                        other["count"] += 1
                        waiting = held.pop(topic, None)
                        if waiting is not None:
                            try:
                                data = compressed_image_data(rec.data)
                            except (ValueError, IndexError):
                                data = b""
                            waiting.msg = msgspec.structs.replace(waiting.msg, data=data)
                            yield waiting
                        continue
                    try:
                        msg = decode_json(rec.data, typ)
                    except MalformedMessage as e:
                        res.undecodable += 1
                        res.undecodable_error = res.undecodable_error or f"{topic}: {e}"
                        continue
                    out = RecordedMessage(topic, rec.log_time, rec.publish_time, msg)
                    if isinstance(msg, Image) and not msg.data and msg.encoding in COMPRESSED_IMAGE_FORMATS:
                        parts = topic.split("/")
                        rig = parts[1] if len(parts) > 2 and parts[0] == "hil" else "unknown"
                        fox = foxglove_image_topic(rig, msg.camera)
                        if fox in held:  # its bytes never came (cannot happen in a file we wrote)
                            yield held.pop(fox)
                        held[fox] = out
                        continue
                    yield out
        except _DAMAGE as e:
            res.truncated = True
            res.error = f"{type(e).__name__}: {e}"
    yield from held.values()  # a file cut between an image and its bytes: the image without them


@dataclass
class RepairResult:
    messages: int
    channels: int
    #: the source had no valid end (crash): everything up to the damage was copied
    truncated: bool
    error: str | None = None


def repair(src: str | Path, dst: str | Path, overwrite: bool = False) -> RepairResult:
    """Copy a recording, crashed or not, into a finished MCAP file (summary, indexes).

    Tools that need the summary (rerun, ``mcap.reader.make_reader``) refuse a file cut
    by a crash. Every schema, channel, message and metadata record up to the damage is
    copied byte for byte (also the Foxglove channels), through the ``mcap`` package: a
    cut keeps every message of the chunks completed before it.

    A source that is not MCAP raises :class:`NotARecording` and nothing is written. The
    copy is written to a temporary file beside ``dst`` and moved to ``dst`` only when it
    is finished; an existing ``dst`` is never replaced unless ``overwrite``
    (:class:`RecordingExists`)."""
    src, dst = Path(src), Path(dst)
    if dst.exists() and src.resolve() == dst.resolve():
        raise ValueError(f"repair: {dst} is the source; write the repaired copy to another file")
    check_mcap(src)
    if dst.is_dir():
        raise IsADirectoryError(21, "is a directory", str(dst))
    if dst.exists() and not overwrite:
        raise RecordingExists(17, "exists (not overwritten)", str(dst))
    dst.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    truncated, error = False, None
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dst.name}.", suffix=".part", dir=dst.parent)
    tmp = Path(tmp_name)
    try:
        with open(src, "rb") as f, os.fdopen(fd, "wb") as out:
            w = Writer(out, compression=CompressionType.ZSTD)
            w.start(profile="", library="hilstack repair")
            try:
                for rec in StreamReader(f, skip_magic=False).records:
                    kind = type(rec).__name__
                    if kind == "Schema" and rec.id not in schema_ids:
                        schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                    elif kind == "Channel" and rec.id not in channel_ids:
                        channel_ids[rec.id] = w.register_channel(
                            rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), rec.metadata
                        )
                    elif kind == "Message" and rec.channel_id in channel_ids:
                        w.add_message(channel_ids[rec.channel_id], rec.log_time, rec.data,
                                      rec.publish_time, rec.sequence)
                        n += 1
                    elif kind == "Metadata":
                        w.add_metadata(rec.name, rec.metadata)
            except _DAMAGE as e:
                truncated, error = True, f"{type(e).__name__}: {e}"
            w.finish()
            out.flush()
            os.fsync(out.fileno())
        if overwrite:
            os.replace(tmp, dst)
        else:
            try:
                os.link(tmp, dst)  # atomic: fails if dst appeared meanwhile
            except FileExistsError:
                raise RecordingExists(17, "exists (not overwritten)", str(dst)) from None
    finally:
        tmp.unlink(missing_ok=True)
    return RepairResult(messages=n, channels=len(channel_ids), truncated=truncated, error=error)


def read_messages(path: str | Path) -> ReadResult:
    res = ReadResult()
    res.messages = list(iter_messages(path, res))
    return res


class Recorder(Node):
    """Records every message under ``hil/<rig>/**`` to one MCAP file; with ``topics``
    (key-expression patterns, as :func:`topic_filter`) only the matching ones, plus the
    robots' specs, without which a recording cannot be read back as robot data.

    Use :meth:`record` (blocks until a signal, ``stop_event`` or ``seconds``) or call
    :meth:`pump` yourself; :meth:`close` writes what is still queued, finishes the file
    and stops listening. ``overwrite=False``: an existing ``path`` is refused
    (:class:`RecordingExists`) before anything is opened. Nothing is written after that (``pump`` then raises
    :class:`RecordingClosed`). A crash loses at most ``flush_period_s`` of messages
    plus one polling period (see :class:`McapLog`).
    """

    def __init__(
        self,
        rig: str,
        path: str | Path,
        bus: BusConfig | None = None,
        flush_period_s: float = FLUSH_PERIOD_S,
        topics: list[str] | None = None,
        overwrite: bool = True,
        **kw: Any,
    ):
        keep = topic_filter(topics)  # a bad pattern fails here, before anything is opened
        for t in topics or []:
            if not zenoh.KeyExpr(t).intersects(zenoh.KeyExpr(keys.all_of(rig))):
                raise ValueError(f"topic pattern {t!r} matches nothing under {keys.all_of(rig)}")
        specs = zenoh.KeyExpr(f"{keys.root(rig)}/*/spec")  # every robot's (bus/keys.py: spec)
        self._keep = keep if topics else None
        self._is_spec = lambda topic: specs.intersects(zenoh.KeyExpr(topic))
        meta = {"rig": rig, "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
        if topics:
            meta["topics"] = " ".join(topics)
        # the file first: a path that cannot be written fails before a session is open
        self.log = McapLog(path, metadata=meta, flush_period_s=flush_period_s, overwrite=overwrite)
        try:
            super().__init__("recorder", rig, bus, **kw)
        except BaseException:
            self.log.close()
            self.log.path.unlink(missing_ok=True)  # our new file, with nothing recorded
            raise
        self._sub = self.subscribe(keys.all_of(rig), AnyMsg, latest=False, capacity=1 << 16)
        self.malformed = 0
        #: messages left out by ``topics``
        self.filtered = 0
        self._lock = threading.Lock()

    def pump(self) -> int:
        """Move everything queued into the file; returns how many were written."""
        n = 0
        with self._lock:
            if self.log.closed:
                raise RecordingClosed(f"recorder of {self.rig} is closed: {self.log.path} is finished")
            for key, payload in self._sub.drain():
                if self._keep is not None and not (self._keep(key) or self._is_spec(key)):
                    self.filtered += 1
                    continue
                try:
                    msg = decode(payload, AnyMsg)
                except MalformedMessage:
                    self.malformed += 1
                    continue
                self.log.write(key, msg)
                n += 1
            # a quiet bus still gets the last messages onto disk in time
            self.log.flush_if_due()
        return n

    def record(self, seconds: float | None = None, poll_s: float = 0.01) -> int:
        """Record until stopped (signal, ``stop_event``) or ``seconds`` pass; always
        finishes the file (:meth:`close`). Returns the number of messages written."""
        t_end = None if seconds is None else time.monotonic() + seconds
        try:
            while not self.stop_event.is_set() and (t_end is None or time.monotonic() < t_end):
                try:
                    self.pump()
                except RecordingClosed:
                    break  # close() from another thread: it wrote the rest
                self.stop_event.wait(poll_s)
        finally:
            self.close()
        return self.log.count

    def close(self) -> None:
        """Stop listening, write what is still queued, finish the file; idempotent."""
        with self._lock:
            if self.log.closed:
                super().close()
                return
        try:
            self.pump()  # what arrived before close() is recorded; what comes later is not
        finally:
            self.log.close()
            super().close()


#: how long a replay waits for its link to a rig that listens at the endpoint before it checks
#: that rig for live driver nodes [s]
LINK_WAIT_S = 5.0

#: Message types :func:`replay` publishes by default: what sensors and driver nodes
#: report. Everything else (e-stop commands and acks, robot commands, reset requests,
#: MPC plans, model updates, pings) can change what a live rig does and needs
#: ``include_commands``. A new sensor message type must be added here to replay by default.
REPLAY_DATA_TYPES: tuple[type[Msg], ...] = (RobotState, SpecMsg, Image)


class ReplayRefused(RuntimeError):
    """Replay would publish onto a rig that has live driver nodes."""


@dataclass
class ReplayStats:
    """What :func:`replay` did: messages published, and what it left out and why."""

    published: int = 0
    #: topic → messages not published because they are commands (``include_commands`` off)
    skipped_commands: dict[str, int] = field(default_factory=dict)
    #: messages left out by the ``topics`` filter
    skipped_by_filter: int = 0
    #: topic → e-stop releases left out: a replay never releases an e-stop, ``include_commands`` or not
    skipped_releases: dict[str, int] = field(default_factory=dict)


def recorded_rig(path: str | Path) -> str | None:
    """The rig a recording was made on (its first message's key ``hil/<rig>/...``), or None."""
    for rm in iter_messages(path):
        parts = rm.topic.split("/")
        return parts[1] if len(parts) > 2 and parts[0] == "hil" else None
    return None


def is_release(topic: str, msg: Msg) -> bool:
    """An e-stop release (on a release key, or an ``EStop`` with ``engaged=False`` anywhere)."""
    if isinstance(msg, EStop) and not msg.engaged:
        return True
    parts = topic.split("/")
    return len(parts) >= 4 and parts[0] == "hil" and parts[2:4] == ["estop", "release"]


def topic_filter(patterns: list[str] | None) -> Callable[[str], bool]:
    """A predicate from Zenoh key-expression patterns (``*`` one segment, ``**`` any).

    None or empty: every topic. A malformed pattern raises ValueError naming it.
    """
    if not patterns:
        return lambda topic: True
    exprs = []
    for p in patterns:
        try:
            exprs.append(zenoh.KeyExpr(p))
        except Exception as e:  # zenoh raises ZError; say which pattern is wrong
            why = str(e).split(" at /", 1)[0]  # drop the Rust source location
            raise ValueError(f"bad topic pattern {p!r}: {why}") from None
    return lambda topic: any(e.intersects(zenoh.KeyExpr(topic)) for e in exprs)


def replay(
    path: str | Path,
    bus: BusConfig | None = None,
    speed: float = 1.0,
    rig: str | None = None,
    session: Any = None,
    topics: list[str] | None = None,
    include_commands: bool = False,
    force: bool = False,
    live_check_s: float = 0.5,
) -> ReplayStats:
    """Publish a recording back onto the bus, timed by log time / ``speed`` (0: as fast as possible).

    By default only sensor and state messages (:data:`REPLAY_DATA_TYPES`) are
    published; ``include_commands`` adds commands, e-stop engages, resets, plans and model
    updates. E-stop releases are never published (:func:`is_release`). ``topics``: Zenoh key-expression patterns matched against the recorded
    topics (``hil/*/pm/state``, ``hil/**/image``). ``rig`` remaps ``hil/<old>/...``
    keys to ``hil/<rig>/...``.

    Before the first message to a rig, its liveliness tokens are checked for
    ``live_check_s``: if a driver node is alive there, :class:`ReplayRefused` is
    raised (nothing is published to it) unless ``force`` (then a warning is logged). Messages are re-sent
    byte-identical to what was recorded (same stamps and sequence numbers).
    """
    from hilstack.bus.node import alive_nodes
    from hilstack.bus.session import open_session, rendezvous_listened, wait_linked

    wanted = topic_filter(topics)
    own = session is None
    # a rig is up at the endpoint: the live-driver check below must see its nodes, so it waits
    # for this session's link to them first (under load the background connect took longer
    # than the check's window, and a replay went ahead onto a live rig)
    rig_up = own and rendezvous_listened(bus)
    s = session if session is not None else open_session(bus)
    if rig_up and not wait_linked(s, bus, LINK_WAIT_S):
        s.close()
        where = bus.router or bus.endpoint if bus is not None else "the default endpoint"
        raise ReplayRefused(f"a rig listens at {where} but this session found no link to it within "
                            f"{LINK_WAIT_S:g} s: cannot check it for live driver nodes, so nothing is replayed")
    pubs: dict[str, Any] = {}
    checked_rigs: set[str] = set()
    stats = ReplayStats()
    t0_log = None
    t0_wall = time.monotonic()
    try:
        for rm in iter_messages(path):
            if not wanted(rm.topic):
                stats.skipped_by_filter += 1
                continue
            if is_release(rm.topic, rm.msg):
                # never: a recorded release would lift the operator's e-stop on the live rig
                stats.skipped_releases[rm.topic] = stats.skipped_releases.get(rm.topic, 0) + 1
                continue
            if not include_commands and not isinstance(rm.msg, REPLAY_DATA_TYPES):
                stats.skipped_commands[rm.topic] = stats.skipped_commands.get(rm.topic, 0) + 1
                continue
            topic = rm.topic
            parts = topic.split("/", 2)
            if rig is not None and len(parts) == 3:
                topic = f"hil/{rig}/{parts[2]}"
                parts = topic.split("/", 2)
            target = parts[1] if len(parts) == 3 else None
            if target is not None and target not in checked_rigs:
                # (also gives a fresh session time to meet its listeners before the first put)
                live = [
                    n for n in alive_nodes(s, target, timeout_s=0.2, window_s=live_check_s)
                    if n.startswith(keys.DRIVER_NODE_PREFIX)
                ]
                if live and not force:
                    raise ReplayRefused(
                        f"rig {target!r} has live driver nodes ({', '.join(live)}): replaying onto it would mix "
                        "recorded and live data; stop them, replay under another --rig, or pass --force"
                    )
                if live:
                    log.warning("forced: replaying onto rig %r with live driver nodes (%s)", target, ", ".join(live))
                checked_rigs.add(target)
            if t0_log is None:
                t0_log = rm.log_time_ns
            if speed > 0:
                due = t0_wall + (rm.log_time_ns - t0_log) / 1e9 / speed
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            p = pubs.get(topic)
            if p is None:
                p = pubs[topic] = s.declare_publisher(topic)
            p.put(encode(rm.msg))
            stats.published += 1
    finally:
        for p in pubs.values():
            p.undeclare()
        if own:
            s.close()
    return stats


def summarize(path: str | Path, gap_factor: float = 3.0) -> dict[str, Any]:
    """Channels, counts, rates, gaps of a recording (works on truncated files)."""
    res = ReadResult()
    per: dict[str, list[int]] = {}
    types: dict[str, str] = {}
    for rm in iter_messages(path, res):
        per.setdefault(rm.topic, []).append(rm.log_time_ns)
        types[rm.topic] = type_name(type(rm.msg))
    chans = {}
    t_all = [t for ts in per.values() for t in ts]
    for topic, ts in sorted(per.items()):
        ts.sort()
        dt = [(b - a) / 1e9 for a, b in zip(ts, ts[1:], strict=False)]
        dur = (ts[-1] - ts[0]) / 1e9 if len(ts) > 1 else 0.0
        med = sorted(dt)[len(dt) // 2] if dt else 0.0
        gaps = [d for d in dt if med > 0 and d > gap_factor * med]
        chans[topic] = {
            "type": types[topic],
            "count": len(ts),
            "rate_hz": (len(ts) - 1) / dur if dur > 0 else 0.0,
            "max_gap_s": max(dt) if dt else 0.0,
            "gaps": len(gaps),
        }
    return {
        "path": str(path),
        "messages": len(t_all),
        "duration_s": (max(t_all) - min(t_all)) / 1e9 if t_all else 0.0,
        "truncated": res.truncated,
        "error": res.error,
        "undecodable": res.undecodable,
        "undecodable_error": res.undecodable_error,
        "channels": chans,
        # derived channels of other schemas (Foxglove poses): not replayed, not in "messages"
        "other_channels": dict(sorted(res.foreign.items())),
    }
