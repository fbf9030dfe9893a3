"""Rerun visualization of a rig: live from the bus, or from an MCAP recording.

Layout (blueprint): a tab per robot by its kind, read from its spec (:func:`robot_kind`: an
arm's 3-D model and joint angles, a mobile robot's path and speeds, a tracker's balls and
confidences), then a 3-D view of the world (robot path, current pose, planned
trajectory), time series of the state and of the commands, and the camera images
when a rig has them (raw RGB, or JPEG/PNG as the camera tracker sends them). Entity paths:
``world/<robot>/{path,pose,plan,balls}`` (``balls``: a camera tracker's ball positions),
``state/<robot>/<channel>``, ``cmd/<robot>/<channel>``, ``camera/<name>``.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from hilstack.bus import keys
from hilstack.bus.recording import LINK_RADIUS_M, chain_segments, chain_transforms, quat_z_to
from hilstack.bus.schemas import (
    AnyMsg,
    Command,
    Image,
    MalformedMessage,
    Msg,
    Plan,
    RobotState,
    SpecMsg,
    TaskPosterior,
    decode,
)
from hilstack.drivers.base import RobotSpec


def robot_kind(spec: RobotSpec) -> str:
    """What a robot is to a viewer, read from its spec alone: ``arm`` (a kinematic chain),
    ``tracker`` (ball positions ``ball<i>_x/y/z``), ``mobile`` (a planar pose ``x``, ``y``),
    ``joints`` (joint angles ``<joint>_pos`` without a chain: the hand, the Sawyer), ``other``."""
    names = set(spec.state.names)
    if spec.chain:
        return "arm"
    if {"ball0_x", "ball0_y", "ball0_z"} <= names:
        return "tracker"
    if {"x", "y"} <= names:
        return "mobile"
    if any(n.endswith("_pos") for n in names):
        return "joints"
    return "other"


#: per kind: the state channels worth a plot of their own (the rest stay in the robot's "all state" view)
def _key_channels(kind: str, spec: RobotSpec) -> list[str]:
    names = list(spec.state.names)
    if kind == "arm":  # the joint angles
        angles = [f"{j}_pos" if f"{j}_pos" in names else j for j, *_ in spec.chain]
        return [n for n in angles if n in names]
    if kind == "joints":
        return [n for n in names if n.endswith("_pos")]
    if kind == "tracker":
        return [n for n in names if n.endswith("_conf")]
    if kind == "mobile":  # speeds and turning rates
        return [n for n in names if n in ("vx", "vy", "v", "speed", "yaw_rate", "wz", "omega", "yaw")]
    return []


def robot_view(robot: str, spec: RobotSpec) -> Any:
    """One robot's tab: its 3-D view (an arm's model, a mobile robot's path in the world, a
    tracker's balls), its key channels (:func:`_key_channels`), all its state and its commands."""
    kind = robot_kind(spec)
    world = rrb.Spatial3DView(origin="world" if kind == "mobile" else f"world/{robot}", name=f"{robot}: 3-D")
    key = _key_channels(kind, spec)
    title = {"arm": "joint angles (rad)", "joints": "joint angles (rad)", "tracker": "confidence",
             "mobile": "speeds"}.get(kind, "")
    series: list[Any] = []
    if key:
        series.append(rrb.TimeSeriesView(origin=f"state/{robot}", contents=[f"state/{robot}/{n}" for n in key],
                                         name=f"{robot}: {title}"))
    series += [rrb.TimeSeriesView(origin=f"state/{robot}", name=f"{robot}: state"),
               rrb.TimeSeriesView(origin=f"cmd/{robot}", name=f"{robot}: commands")]
    return rrb.Horizontal(world, rrb.Vertical(*series), column_shares=[3, 2], name=f"{robot} ({kind})")


def blueprint(has_images: bool = True, specs: dict[str, RobotSpec] | None = None) -> rrb.Blueprint:
    """The layout: a tab per robot of the rig whose spec is known (:func:`robot_view`, by kind),
    then the generic view of every robot (world, state, commands) and the cameras."""
    right = [
        rrb.TimeSeriesView(origin="state", name="state"),
        rrb.TimeSeriesView(origin="cmd", name="commands"),
    ]
    left: list[Any] = [rrb.Spatial3DView(origin="world", name="world")]
    if has_images:
        left.append(rrb.Spatial2DView(origin="camera", name="camera"))
    every = rrb.Horizontal(rrb.Vertical(*left), rrb.Vertical(*right), column_shares=[3, 2], name="all robots")
    tabs = [robot_view(r, sp) for r, sp in (specs or {}).items()]
    return rrb.Blueprint(rrb.Tabs(*tabs, every) if tabs else every, collapse_panels=True)


class RigVisualizer:
    """Turns bus messages into rerun logs on its own recording stream."""

    def __init__(self, rig: str, save: str | Path | None = None, spawn: bool = False, grpc: bool = False):
        self.rig = rig
        self.rec = rr.RecordingStream(f"hilstack-{rig}", recording_id=f"{rig}-{int(time.time())}")
        if save is not None:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(save), default_blueprint=blueprint())
        elif spawn:
            self.rec.spawn(default_blueprint=blueprint())
        elif grpc:
            self.grpc_uri = self.rec.serve_grpc(default_blueprint=blueprint())
        self.rec.send_blueprint(blueprint())
        self.names: dict[str, tuple[str, ...]] = {}
        self.action_names: dict[str, tuple[str, ...]] = {}
        #: each robot's spec, as first seen: the blueprint's tabs (one per robot, by kind)
        self.specs: dict[str, RobotSpec] = {}
        self.chains: dict[str, list[dict]] = {}
        self._path: dict[str, list[list[float]]] = {}
        self.logged = 0

    def _time(self, msg: Msg, t_s: float | None = None) -> None:
        self.rec.set_time("stamp", timestamp=msg.stamp_s or time.time())
        if t_s is not None:
            self.rec.set_time("robot_time", duration=t_s)

    def _xyz(self, robot: str, state: list[float]) -> list[float] | None:
        names = self.names.get(robot)
        if names and "x" in names and "y" in names:
            z = state[names.index("z")] if "z" in names else 0.0
            return [state[names.index("x")], state[names.index("y")], z]
        if not names and len(state) >= 2:  # unknown robot: first two channels as x, y
            return [state[0], state[1], 0.0]
        return None

    def _balls(self, robot: str, state: list[float]) -> list[list[float]] | None:
        """Tracked ball positions (channels ``ball<i>_x/y/z``, the camera tracker's state)."""
        names = self.names.get(robot) or ()
        out = []
        for i in range(8):
            keys_ = (f"ball{i}_x", f"ball{i}_y", f"ball{i}_z")
            if not all(k in names for k in keys_):
                break
            out.append([state[names.index(k)] for k in keys_])
        return out or None

    def _links(self, robot: str, state: list[float]) -> None:
        """An arm's kinematic chain (spec ``chain``): one ``Transform3D`` per link, nested as rerun's
        entity tree (``world/<robot>/links/waist_link/shoulder_link/...``, each relative to its
        parent), with each link drawn as an arrow from its parent's origin to its own."""
        chain = self.chains.get(robot)
        tfs = None if chain is None else chain_transforms(robot, chain, self.names[robot], state)
        if not tfs:
            return
        path = f"world/{robot}/links"
        for _, child, t, q in tfs:
            link = child.rsplit("/", 1)[-1]
            # the segment parent origin -> this link's origin, in the parent's frame
            self.rec.log(f"{path}/to_{link}", rr.Arrows3D(origins=[[0.0, 0.0, 0.0]], vectors=[list(t)]))
            path += "/" + link
            self.rec.log(path, rr.Transform3D(translation=t, quaternion=rr.Quaternion(xyzw=q)))

    def _model(self, robot: str, chain: list[dict]) -> None:
        """The arm's 3-D model (``chain_segments``: a capsule per link), static, each capsule under
        its link's entity so it moves with the link's ``Transform3D`` (:meth:`_links`)."""
        path = f"world/{robot}/links"
        paths = {robot: path}
        for link in chain:
            path += f"/{link['joint']}_link"
            paths[f"{robot}/{link['joint']}_link"] = path
        for frame, a, b in chain_segments(robot, chain):
            seg = [bb - aa for aa, bb in zip(a, b, strict=True)]
            length = float(np.linalg.norm(seg))
            self.rec.log(f"{paths[frame]}/body", rr.Capsules3D(
                lengths=[length], radii=[LINK_RADIUS_M], translations=[list(a)],
                quaternions=[rr.Quaternion(xyzw=quat_z_to(tuple(seg)))], colors=[[40, 40, 40]]), static=True)

    def log(self, topic: str, msg: Msg) -> None:
        if isinstance(msg, SpecMsg):
            spec = RobotSpec.from_dict(msg.spec)
            self.names[msg.robot] = spec.state.names
            self.action_names[msg.robot] = spec.action.names
            if msg.robot not in self.specs:  # a new robot: its tab joins the layout
                self.specs[msg.robot] = spec
                self.rec.send_blueprint(blueprint(specs=self.specs))
            if spec.chain and msg.robot not in self.chains:
                self.chains[msg.robot] = msg.spec["chain"]
                self._model(msg.robot, msg.spec["chain"])
            return
        if isinstance(msg, RobotState):
            self._time(msg, msg.t_s)
            names = self.names.get(msg.robot) or tuple(f"s{i}" for i in range(len(msg.state)))
            for n, v in zip(names, msg.state, strict=False):
                self.rec.log(f"state/{msg.robot}/{n}", rr.Scalars(v))
            balls = self._balls(msg.robot, msg.state)
            if balls is not None:
                self.rec.log(f"world/{msg.robot}/balls", rr.Points3D(balls, radii=0.02,
                                                                     colors=[[220, 50, 50], [50, 80, 220]]))
            self._links(msg.robot, msg.state)
            p = self._xyz(msg.robot, msg.state)
            if p is not None:
                path = self._path.setdefault(msg.robot, [])
                path.append(p)
                if len(path) > 5000:
                    del path[:1000]
                self.rec.log(f"world/{msg.robot}/pose", rr.Points3D([p], radii=0.02))
                self.rec.log(f"world/{msg.robot}/path", rr.LineStrips3D([path]))
        elif isinstance(msg, Command):
            self._time(msg)
            names = self.action_names.get(msg.robot) or tuple(f"a{i}" for i in range(len(msg.action)))
            for n, v in zip(names, msg.action, strict=False):
                self.rec.log(f"cmd/{msg.robot}/{n}", rr.Scalars(v))
        elif isinstance(msg, Plan):
            self._time(msg)
            if msg.states:
                pts = [self._xyz(msg.robot, s) for s in msg.states]
                pts = [p for p in pts if p is not None]
                if pts:
                    self.rec.log(f"world/{msg.robot}/plan", rr.LineStrips3D([pts], colors=[255, 120, 0]))
            self.rec.log(f"cmd/{msg.robot}/plan_cost", rr.Scalars(msg.cost))
        elif isinstance(msg, TaskPosterior):
            self._time(msg)  # MOLe: one line per task
            for i, p in enumerate(msg.posterior):
                self.rec.log(f"model/{msg.method}/posterior/task{i}", rr.Scalars(p))
        elif isinstance(msg, Image):
            self._time(msg, msg.t_s)
            if msg.encoding == "rgb8":
                img = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width, 3)
                self.rec.log(f"camera/{msg.camera}", rr.Image(img))
            elif msg.encoding in ("jpeg", "png"):  # the camera tracker's images: rerun decodes them
                self.rec.log(f"camera/{msg.camera}", rr.EncodedImage(contents=msg.data, media_type=f"image/{msg.encoding}"))
        else:
            return
        self.logged += 1

    def log_many(self, items: Iterable[tuple[str, Msg]]) -> int:
        n = 0
        for topic, msg in items:
            self.log(topic, msg)
            n += 1
        return n

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


#: a live viewer waits at most this long for its link to a listening rig before its clock starts [s]
JOIN_WAIT_S = 5.0


def viz_live(rig: str, bus: Any = None, seconds: float | None = None, **viz_kw: Any) -> RigVisualizer:
    """Subscribe to everything on the rig and log it until stopped or ``seconds`` pass."""
    from hilstack.bus.node import Node

    v = RigVisualizer(rig, **viz_kw)
    node = Node("viz", rig, bus, join_wait_s=JOIN_WAIT_S)
    sub = node.subscribe(keys.all_of(rig), AnyMsg, latest=False, capacity=1 << 14)
    t_end = None if seconds is None else time.monotonic() + seconds
    try:
        while not node.stop_event.is_set() and (t_end is None or time.monotonic() < t_end):
            for key, payload in sub.drain():
                try:
                    v.log(key, decode(payload, AnyMsg))
                except MalformedMessage:
                    continue  # the recorder and the driver nodes count malformed payloads
            node.stop_event.wait(0.02)
    finally:
        node.close()
        v.close()
    return v


def viz_recording(mcap_path: str | Path, save: str | Path, rig: str | None = None) -> int:
    """Convert an MCAP recording into a rerun .rrd with the standard layout."""
    from hilstack.bus.recording import iter_messages

    v = RigVisualizer(rig or Path(mcap_path).stem, save=save)
    n = v.log_many((m.topic, m.msg) for m in iter_messages(mcap_path))
    v.close()
    return n
