"""Live view of a rig in Foxglove: every bus message over Foxglove's WebSocket protocol.

``hil foxglove --rig RIG`` starts foxglove-sdk's WebSocket server (``foxglove.start_server``)
and forwards every message under ``hil/<rig>/**`` on a channel named by its key, JSON with
the same Foxglove-parsable JSON Schema as in recordings (``hilstack.bus.schemas.json_schema``), plus
the robots' poses as ``foxglove.PoseInFrame`` / ``FrameTransform`` and the cameras' JPEG/PNG
frames as ``foxglove.CompressedImage`` (the same derived channels as in recordings,
:class:`hilstack.bus.recording.FoxglovePoses`, :func:`hilstack.bus.recording.foxglove_image`). In Foxglove:
Open connection → Foxglove WebSocket → ``ws://HOST:PORT``; the 3D panel shows the robots in
frame ``world``, an Image panel the cameras.

Client publish (Foxglove's ``clientPublish`` capability, JSON): a client (Foxglove's Publish or
Teleop panel, an e-stop button) may advertise

* ``hil/<rig>/<robot>/cmd``: a teleop command, ``{"action": [...]}`` in the robot's action units,
  or a ``geometry_msgs/Twist`` (``{"linear": {"x": v}, "angular": {"z": w}}``, Foxglove's Teleop
  panel) for a differential robot: ``v``, ``w`` in [-1, 1] are the forward speed and the turn as
  fractions of the range, mapped by ``hil teleop``'s drive map (:class:`hilstack.tools.teleop.TeleopMapper`);
  published as a :class:`~hilstack.bus.schemas.Command` (``source: foxglove``) answering the
  robot's newest state, so the driver node applies the contract's limits as to any controller;
* ``hil/<rig>/estop``: an e-stop engage (``{}`` or ``{"engaged": true, "reason": ...}``), sent as
  ``hil estop`` does. A release is refused: it is an operator's deliberate act in their own name
  (``hil estop --release``, ``hil console``).

Everything is published in this node's bus user's name, so the rig's access control applies: a
user outside ``bus.access.command`` gets its commands refused here (and by the rig's router
anyway). A refusal is counted (``refused``), logged and shown to the clients as a status message.
Decoding happens in the node's own loop (``pump``), not in Zenoh's or the server's callbacks.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from typing import Any

import foxglove
import foxglove.messages as fg
from foxglove.channels import (
    CompressedImageChannel,
    FrameTransformChannel,
    PoseInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.websocket import Capability, Client, ClientChannel, ServerListener, StatusLevel

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.recording import FoxglovePoses, foxglove_image
from hilstack.bus.schemas import (
    AnyMsg,
    Command,
    MalformedMessage,
    Msg,
    RobotState,
    SpecMsg,
    decode,
    encode_json,
    json_schema,
    type_name,
)
from hilstack.configs.schema import BusConfig

#: the Foxglove messages derived from bus messages, and their typed channels
_DERIVED_CHANNELS: dict[type, Any] = {fg.PoseInFrame: PoseInFrameChannel, fg.FrameTransform: FrameTransformChannel,
                                      fg.CompressedImage: CompressedImageChannel, fg.SceneUpdate: SceneUpdateChannel}


log = logging.getLogger(__name__)


def command_refusal(rig: str, bus: BusConfig | None) -> str | None:
    """Why this process's bus user may not command ``rig``'s robots (None: it may)."""
    acc = None if bus is None else bus.access
    if acc is None:
        return None
    from hilstack.bus.access import user_of

    user = user_of(acc)
    return None if user in acc.command else (f"user {user!r} may not command rig {rig} "
                                             f"(bus.access.command: {acc.command})")


class _ClientPublish(ServerListener):
    """The server's callbacks (its own thread): client channels, and their messages queued for ``pump``."""

    def __init__(self) -> None:
        self.channels: dict[tuple[int, int], str] = {}
        self.inbox: deque[tuple[str, bytes]] = deque(maxlen=1024)
        self.lock = threading.Lock()

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        with self.lock:
            self.channels[(client.id, channel.id)] = channel.topic

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        with self.lock:
            self.channels.pop((client.id, client_channel_id), None)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        with self.lock:
            topic = self.channels.get((client.id, client_channel_id))
        if topic is not None:
            self.inbox.append((topic, bytes(data)))


class FoxgloveLive(Node):
    """Serves rig ``rig`` to Foxglove clients on ``ws://host:port`` (``port=0``: any free port)."""

    def __init__(self, rig: str, bus: BusConfig | None = None, host: str = "127.0.0.1", port: int = 8765,
                 **kw: Any):
        super().__init__("foxglove", rig, bus, **kw)
        # a context of our own: channels and server are not shared with other users of the SDK
        self._ctx = foxglove.Context()
        self._listener = _ClientPublish()
        try:
            self.server = foxglove.start_server(name=f"hilstack {rig}", host=host, port=port, context=self._ctx,
                                                capabilities=[Capability.ClientPublish], supported_encodings=["json"],
                                                server_listener=self._listener)
        except Exception as e:
            super().close()
            raise RuntimeError(f"cannot serve Foxglove on {host}:{port}: {e}") from None
        self.host = host
        self._sub = self.subscribe(keys.all_of(rig), AnyMsg, latest=False, capacity=1 << 14)
        self._channels: dict[str, Any] = {}
        self._poses = FoxglovePoses()
        self.forwarded = 0
        self.malformed = 0
        #: client publish: commands and e-stop engages taken, and refusals (one line each)
        self.client_commands = 0
        self.client_estops = 0
        self.refused: list[str] = []
        self._bus = bus
        self._cmd_pubs: dict[str, Any] = {}
        self._state_seq: dict[str, int] = {}
        self._held: dict[str, list[float]] = {}
        self._specs: dict[str, dict[str, Any]] = {}
        self._estop_threads: list[threading.Thread] = []

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def _channel(self, topic: str, msg: Msg) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            typ = type(msg)
            schema = foxglove.Schema(name=type_name(typ), encoding="jsonschema",
                                     data=json.dumps(json_schema(typ)).encode())
            ch = self._channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="json",
                                                          context=self._ctx)
        return ch

    def _derived_channel(self, topic: str, m: Any) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            ch = self._channels[topic] = _DERIVED_CHANNELS[type(m)](topic, context=self._ctx)
        return ch

    def pump(self) -> int:
        """Forward everything queued; returns how many bus messages were forwarded."""
        n = 0
        for key, payload in self._sub.drain():
            try:
                msg = decode(payload, AnyMsg)
            except MalformedMessage:
                self.malformed += 1
                continue
            if isinstance(msg, RobotState):
                self._state_seq[msg.robot] = msg.seq
                self._held[msg.robot] = list(msg.action)
            elif isinstance(msg, SpecMsg):
                self._specs[msg.robot] = msg.spec
            now_ns = time.time_ns()
            self._channel(key, msg).log(encode_json(msg), log_time=now_ns)
            derived = self._poses.derive(key, msg, now_ns)
            img = foxglove_image(key, msg, now_ns)
            if img is not None:
                derived.append(img)
            for topic, m, _stamp_ns in derived:
                self._derived_channel(topic, m).log(m, log_time=now_ns)
            n += 1
        self.forwarded += n
        while self._listener.inbox:
            topic, data = self._listener.inbox.popleft()
            why = self._client_message(topic, data)
            if why is not None:
                line = f"refused a client message on {topic}: {why}"
                self.refused.append(line)
                log.warning(line)
                self.server.publish_status(line, StatusLevel.Warning)
        return n

    def _cmd_pub(self, robot: str) -> Any:
        pub = self._cmd_pubs.get(robot)
        if pub is None:
            pub = self._cmd_pubs[robot] = self.publisher(keys.cmd(self.rig, robot), Command)
        return pub

    def _client_message(self, topic: str, data: bytes) -> str | None:
        """Take one client message (a command or an e-stop engage); why not, or None."""
        try:
            body = json.loads(data)
        except ValueError as e:
            return f"not JSON ({e})"
        if not isinstance(body, dict):
            return "expected a JSON object"
        if topic == keys.estop(self.rig):
            if body.get("engaged", True) is not True:
                return "a release is not taken from Foxglove: hil estop RIG --release or hil console, in your name"
            from hilstack.bus.estop import command_estop

            reason = str(body.get("reason") or "foxglove")[:200]
            t = threading.Thread(target=command_estop, args=(self,), kwargs={"engaged": True, "reason": reason},
                                 name="foxglove-estop", daemon=True)
            t.start()
            self._estop_threads.append(t)
            self.client_estops += 1
            return None
        parts = topic.split("/")
        if len(parts) != 4 or parts[:2] != ["hil", self.rig] or parts[3] != "cmd":
            return f"not a topic a client may publish on (hil/{self.rig}/<robot>/cmd, hil/{self.rig}/estop)"
        robot = parts[2]
        from hilstack.bus.keys import _NAME

        if not _NAME.match(robot):
            return f"bad robot name {robot!r}"
        if (why := command_refusal(self.rig, self._bus)) is not None:
            return why
        if "action" in body:
            act = body["action"]
            if not (isinstance(act, list) and act and all(isinstance(v, (int, float)) and math.isfinite(v)
                                                          for v in act)):
                return "action: expected a list of finite numbers"
            action = [float(v) for v in act]
        elif "linear" in body or "angular" in body:
            spec = self._specs.get(robot)
            if spec is None:
                return f"no spec of robot {robot!r} heard yet (is its driver node up?)"
            from hilstack.tools.teleop import TeleopMapper

            m = TeleopMapper(spec)
            if m.mode != "drive":
                return f"a Twist drives a differential robot; {robot} takes an action list"
            try:
                v = float((body.get("linear") or {}).get("x", 0.0))
                w = float((body.get("angular") or {}).get("z", 0.0))
            except (TypeError, ValueError, AttributeError):
                return "Twist: linear.x and angular.z must be numbers"
            if not (math.isfinite(v) and math.isfinite(w)):
                return "Twist: linear.x and angular.z must be finite"
            m.speed, m.turn = max(-1.0, min(1.0, v)), max(-1.0, min(1.0, w))
            action = [float(a) for a in m.action(self._held.get(robot, []))]
        else:
            return 'expected {"action": [...]} or a Twist {"linear": {"x": ...}, "angular": {"z": ...}}'
        self._cmd_pub(robot).put(Command(robot=robot, action=action, state_seq=self._state_seq.get(robot, 0), source="foxglove"))
        self.client_commands += 1
        return None

    def serve(self, seconds: float | None = None, poll_s: float = 0.01) -> int:
        """Forward until stopped (signal, ``stop_event``) or ``seconds`` pass; always closes."""
        t_end = None if seconds is None else time.monotonic() + seconds
        try:
            while not self.stop_event.is_set() and (t_end is None or time.monotonic() < t_end):
                self.pump()
                self.stop_event.wait(poll_s)
        finally:
            self.close()
        return self.forwarded

    def close(self) -> None:
        if not self._closed:
            self.server.stop()
            for t in self._estop_threads:
                t.join(timeout=3.0)
        super().close()
