"""MCAP recording, replay and inspection of everything a rig says.

One file per session; one channel per key expression; one schema per message type
(JSON Schema generated from the msgspec definition), messages JSON-encoded so any
MCAP tool (the ``mcap`` reader, Foxglove, rerun's MCAP importer) decodes them.
Chunks are small and the file is flushed after each one, so a crash loses at most
the last chunk; :func:`read_messages` reads a truncated file up to the damage.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
import zenoh
from mcap.exceptions import McapError
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from bus import keys
from bus.node import Node
from bus.schemas import (
    ALL_TYPES,
    AnyMsg,
    Image,
    MalformedMessage,
    Msg,
    RobotState,
    SpecMsg,
    decode,
    encode,
    json_schema,
    type_name,
)
from configs.schema import BusConfig

log = logging.getLogger(__name__)

_BY_TAG: dict[str, type[Msg]] = {type_name(t): t for t in ALL_TYPES}
_json_enc = msgspec.json.Encoder()


class _FlushingFile:
    """File wrapper that flushes after every write of a chunk-sized block."""

    def __init__(self, f: IO[bytes], flush_over: int):
        self._f = f
        self._flush_over = flush_over

    def write(self, b: bytes) -> int:
        n = self._f.write(b)
        if len(b) >= self._flush_over:
            self._f.flush()
        return n

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        self._f.flush()


class McapLog:
    """Write typed messages to an MCAP file (thread-compatible: one writer thread)."""

    def __init__(self, path: str | Path, chunk_size: int = 64 * 1024, metadata: dict[str, str] | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._w = Writer(
            _FlushingFile(self._f, flush_over=min(chunk_size // 2, 4096)),
            chunk_size=chunk_size,
            compression=CompressionType.ZSTD,
        )
        self._w.start(profile="", library="hilstack")
        if metadata:
            self._w.add_metadata("hilstack", {k: str(v) for k, v in metadata.items()})
        self._schemas: dict[type[Msg], int] = {}
        self._channels: dict[str, int] = {}
        self.count = 0
        self._closed = False

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
        cid = self._channel(topic, type(msg))
        log_ns = time.time_ns() if log_time_ns is None else log_time_ns
        pub_ns = int(msg.stamp_s * 1e9) if msg.stamp_s else log_ns
        self._w.add_message(cid, log_time=log_ns, data=_json_enc.encode(msg), publish_time=pub_ns, sequence=msg.seq)
        self.count += 1

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._w.finish()
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


def iter_messages(path: str | Path, result: ReadResult | None = None) -> Iterator[RecordedMessage]:
    """Stream messages in file order; stops quietly at a truncated tail (sets ``result.truncated``)."""
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, int]] = {}
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
                        continue
                    yield RecordedMessage(
                        topic, rec.log_time, rec.publish_time, msgspec.json.decode(rec.data, type=typ)
                    )
        except (McapError, EOFError, ValueError, KeyError, OSError) as e:
            if result is not None:
                result.truncated = True
                result.error = f"{type(e).__name__}: {e}"


def read_messages(path: str | Path) -> ReadResult:
    res = ReadResult()
    res.messages = list(iter_messages(path, res))
    return res


class Recorder(Node):
    """Records every message under ``hil/<rig>/**`` to one MCAP file."""

    def __init__(self, rig: str, path: str | Path, bus: BusConfig | None = None, **kw: Any):
        super().__init__("recorder", rig, bus, **kw)
        self.log = McapLog(path, metadata={"rig": rig, "started": time.strftime("%Y-%m-%dT%H:%M:%S")})
        self._sub = self.subscribe(keys.all_of(rig), AnyMsg, latest=False, capacity=1 << 16)
        self.malformed = 0
        self._lock = threading.Lock()

    def pump(self) -> int:
        """Move everything queued into the file; returns how many were written."""
        n = 0
        with self._lock:
            for key, payload in self._sub.drain():
                try:
                    msg = decode(payload, AnyMsg)
                except MalformedMessage:
                    self.malformed += 1
                    continue
                self.log.write(key, msg)
                n += 1
        return n

    def record(self, seconds: float | None = None, poll_s: float = 0.01) -> int:
        """Record until stopped (signal) or ``seconds`` pass; always closes the file."""
        t_end = None if seconds is None else time.monotonic() + seconds
        try:
            while not self.stop_event.is_set() and (t_end is None or time.monotonic() < t_end):
                self.pump()
                self.stop_event.wait(poll_s)
            self.pump()
        finally:
            self.log.close()
        return self.log.count

    def close(self) -> None:
        try:
            self.pump()
        finally:
            self.log.close()
            super().close()


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
    published; ``include_commands`` adds commands, e-stops, resets, plans and model
    updates. ``topics``: Zenoh key-expression patterns matched against the recorded
    topics (``hil/*/pm/state``, ``hil/**/image``). ``rig`` remaps ``hil/<old>/...``
    keys to ``hil/<rig>/...``.

    Before the first message to a rig, its liveliness tokens are checked for
    ``live_check_s``: if a driver node is alive there, :class:`ReplayRefused` is
    raised (nothing is published to it) unless ``force`` (then a warning is logged). Messages are re-sent
    byte-identical to what was recorded (same stamps and sequence numbers).
    """
    from bus.node import alive_nodes
    from bus.session import open_session

    wanted = topic_filter(topics)
    own = session is None
    s = session if session is not None else open_session(bus)
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
        "channels": chans,
    }
