"""Live view of a rig in Foxglove: every bus message over Foxglove's WebSocket protocol.

``hil foxglove --rig RIG`` starts foxglove-sdk's WebSocket server (``foxglove.start_server``)
and forwards every message under ``hil/<rig>/**`` on a channel named by its key, JSON with
the same Foxglove-parsable JSON Schema as in recordings (``hilstack.bus.schemas.json_schema``), plus
the robots' poses as ``foxglove.PoseInFrame`` / ``FrameTransform`` and the cameras' JPEG/PNG
frames as ``foxglove.CompressedImage`` (the same derived channels as in recordings,
:class:`hilstack.bus.recording.FoxglovePoses`, :func:`hilstack.bus.recording.foxglove_image`). In Foxglove:
Open connection → Foxglove WebSocket → ``ws://HOST:PORT``; the 3D panel shows the robots in
frame ``world``, an Image panel the cameras.

The node only listens; it never publishes on the bus. Decoding happens in the node's own
loop, not in Zenoh's callbacks.
"""

from __future__ import annotations

import json
import time
from typing import Any

import foxglove
import foxglove.messages as fg
from foxglove.channels import CompressedImageChannel, FrameTransformChannel, PoseInFrameChannel

from hilstack.bus import keys
from hilstack.bus.node import Node
from hilstack.bus.recording import FoxglovePoses, foxglove_image
from hilstack.bus.schemas import AnyMsg, MalformedMessage, Msg, decode, encode_json, json_schema, type_name
from hilstack.configs.schema import BusConfig

#: the Foxglove messages derived from bus messages, and their typed channels
_DERIVED_CHANNELS: dict[type, Any] = {fg.PoseInFrame: PoseInFrameChannel, fg.FrameTransform: FrameTransformChannel,
                                      fg.CompressedImage: CompressedImageChannel}


class FoxgloveLive(Node):
    """Serves rig ``rig`` to Foxglove clients on ``ws://host:port`` (``port=0``: any free port)."""

    def __init__(self, rig: str, bus: BusConfig | None = None, host: str = "127.0.0.1", port: int = 8765,
                 **kw: Any):
        super().__init__("foxglove", rig, bus, **kw)
        # a context of our own: channels and server are not shared with other users of the SDK
        self._ctx = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=f"hilstack {rig}", host=host, port=port, context=self._ctx)
        except Exception as e:
            super().close()
            raise RuntimeError(f"cannot serve Foxglove on {host}:{port}: {e}") from None
        self.host = host
        self._sub = self.subscribe(keys.all_of(rig), AnyMsg, latest=False, capacity=1 << 14)
        self._channels: dict[str, Any] = {}
        self._poses = FoxglovePoses()
        self.forwarded = 0
        self.malformed = 0

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
        return n

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
        super().close()
